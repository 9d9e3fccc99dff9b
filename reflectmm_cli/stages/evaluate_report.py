"""Stage ``evaluate-report``: the closing report of a run — errors of every stage against ground truth
(library: :func:`reflectmm_cli.evaluation.report.build_report`, which computes and writes the text from what this
stage reads: each role's artifacts and the truth, read as the report goes)."""

from __future__ import annotations

from dataclasses import replace
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND, flatten
from reflectmm_cli.progress import progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.workspace import files_in

VERB = "evaluate-report"

PARAMS = ()

#: The report's inputs on the command line: whatever each stage wrote in the workspace (an empty folder, or none,
#: leaves the role out).
_FOUND = Default("all", optional=True)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('geometry', 'geometry', upstream='fit-geometry', many=True, default=_FOUND),
    Input('detected', 'geometry', upstream='fit-geometry', many=True,
          help="fits from a detector's landmarks, set against the reference role's (else the geometry role's)"),
    Input('reference', 'geometry', upstream='fit-geometry', many=True,
          help="fits of the detected role's identities with landmarks on every view"),
    Input('maps', 'reflectance-maps', upstream='fit-reflectance', many=True, default=_FOUND),
    Input('observations', 'uv-observations', upstream='unwrap-uv', many=True, default=_FOUND,
          help="the observations the reflectance fits took: the views and flashes of each are listed"),
    Input('model', 'reflectance-model', upstream='build-pca', many=True, default=_FOUND),
    Input('truth', 'ground-truth NPZ files or their folder', upstream='synth-multipie', many=True,
          default=Default('truth', optional=True, listed=True)),
    Input('representation', 'evaluation', upstream='evaluate-representation', many=True, default=_FOUND),
    Input('reconstruction', 'evaluation', upstream='evaluate-reconstruction', many=True, default=_FOUND),
    Input('albedo', 'evaluation', upstream='evaluate-albedo', many=True, default=_FOUND),
    Input('relighting', 'evaluation', upstream='evaluate-relighting', many=True, default=_FOUND),
    Input('finetune', 'reflectance-model', upstream='finetune', many=True, default=_FOUND),
    Input('expressive', 'evaluation', upstream='evaluate-expressive', many=True, default=_FOUND),
    Input('viewer', 'viewer page', upstream='view', many=True, default=replace(_FOUND, suffix='.html')),
)


class Artifacts(Sequence):
    """One role's artifacts for :func:`~reflectmm_cli.evaluation.report.build_report`: ``(path, Artifact)`` pairs
    read one at a time as the report iterates them (so memory, progress lines and the first error come in the
    order they did when the report read the files itself).  ``skip``: an unreadable file is left out instead of
    raising.  ``len()`` (and truth) count the paths given."""

    def __init__(self, paths: list[Path], kind: str, skip: bool = False, members: Sequence[str] | None = None):
        self.paths, self.kind, self.skip, self.members = [Path(p) for p in paths], kind, skip, members

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i):
        return (self.paths[i], read_artifact(self.paths[i], self.kind, members=self.members))

    def __iter__(self) -> Iterator[tuple[Path, Any]]:
        for p in self.paths:
            try:
                art = read_artifact(p, self.kind, members=self.members)
            except ReflectmmError:
                if self.skip:
                    continue
                raise
            yield p, art


class TruthByIdentity(Mapping):
    """Ground truth by identity (file stem) from synth-truth files or folders of them; a lookup reads the file's
    arrays (nothing is kept)."""

    def __init__(self, paths: list[Path]):
        self.files: dict[str, Path] = {}
        for t in map(Path, paths):
            for q in (files_in(t) if t.is_dir() else [t]):
                self.files[q.stem] = q

    def __getitem__(self, identity: str):
        return read_artifact(self.files[identity]).arrays

    def __iter__(self):
        return iter(self.files)

    def __len__(self) -> int:
        return len(self.files)


def _report_outputs(ctx: StageContext) -> list[Path]:
    """[evaluation artifact (primary, carries the cache key), markdown report]."""
    if ctx.output is not None and Path(ctx.output).suffix.lower() != ".npz":
        md = Path(ctx.output)
        return [md.with_suffix(".npz"), md]
    npz = ctx.output_path()
    return [npz, npz.with_suffix(".md")]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.report import build_report

    out_npz, out_md = _report_outputs(ctx)
    def given(role: str, kind: str, skip: bool = True, members: Sequence[str] | None = None) -> Artifacts:
        return Artifacts(ctx.input_list(role, required=False), kind, skip, members)

    text, doc = build_report(ctx.workspace, out_md,
                             geometry=given("geometry", "geometry", skip=False),
                             maps=given("maps", "reflectance-maps", skip=False),
                             observations=given("observations", "uv-observations",
                                                members=("view_names", "flash_ids")),
                             models=given("model", "reflectance-model"),
                             truth=TruthByIdentity(ctx.input_list("truth", required=False)),
                             representation=given("representation", EVAL_KIND),
                             reconstruction=given("reconstruction", EVAL_KIND),
                             albedo=given("albedo", EVAL_KIND),
                             relighting=given("relighting", EVAL_KIND),
                             finetune=ctx.input_list("finetune", required=False),
                             expressive=given("expressive", EVAL_KIND),
                             viewer=ctx.input_list("viewer", required=False),
                             detected=given("detected", "geometry", skip=False),
                             reference=given("reference", "geometry", skip=False),
                             progress=lambda it, **k: progress(it, **k))
    flat = flatten("", doc, {})
    names = sorted(flat)
    write_artifact(out_npz, EVAL_KIND, {"names": np.array(names, dtype=str),
                                        "values": np.array([flat[n] for n in names], np.float64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out_npz.parent), producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta={"evaluation": "report", "report": doc})
    atomic_write_text(out_md, text)
    return [out_md, out_npz]


# version 4: + the finetuning gains of Table 2 and the expressive-power section; 5: + the viewer's link;
# 6: + the detector's chain; 7: + its reference fits; 8: + Table 2's ceiling (the oracle's gain), the gap to it
# closed in PSNR and the encoders' unequal budgets; 9: the ceiling with its interval; 10: Table 2's gain with its
# interval in "Paper vs reflectmm"; 11: the views and flashes each reflectance fit took
STAGE = Stage(VERB, version=11, run=run, per_identity=False, outputs=_report_outputs, params=PARAMS,
              help="closing report of a run: errors of every stage against ground truth", inputs=INPUTS)

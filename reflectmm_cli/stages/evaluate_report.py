"""Stage ``evaluate-report``: the closing report of a run — errors of every stage against ground truth
(library: :func:`reflectmm_cli.evaluation.report.build_report`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, write_artifact
from reflectmm_cli.evaluation.documents import EVAL_KIND, flatten
from reflectmm_cli.progress import progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "evaluate-report"

PARAMS = ()

#: The report's inputs on the command line: whatever each stage wrote in the workspace (an empty folder, or none,
#: leaves the role out).
_FOUND = Default("all", optional=True)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('geometry', 'geometry', upstream='fit-geometry', many=True, default=_FOUND),
    Input('maps', 'reflectance-maps', upstream='fit-reflectance', many=True, default=_FOUND),
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
    text, doc = build_report(ctx.workspace, out_md,
                             geometry=ctx.input_list("geometry", required=False),
                             maps=ctx.input_list("maps", required=False),
                             models=ctx.input_list("model", required=False),
                             truth=ctx.input_list("truth", required=False),
                             representation=ctx.input_list("representation", required=False),
                             reconstruction=ctx.input_list("reconstruction", required=False),
                             albedo=ctx.input_list("albedo", required=False),
                             relighting=ctx.input_list("relighting", required=False),
                             finetune=ctx.input_list("finetune", required=False),
                             expressive=ctx.input_list("expressive", required=False),
                             viewer=ctx.input_list("viewer", required=False),
                             progress=lambda it, **k: progress(it, **k))
    flat = flatten("", doc, {})
    names = sorted(flat)
    write_artifact(out_npz, EVAL_KIND, {"names": np.array(names, dtype=str),
                                        "values": np.array([flat[n] for n in names], np.float64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out_npz.parent), producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta={"evaluation": "report", "report": doc})
    atomic_write_text(out_md, text)
    return [out_md, out_npz]


# version 4: + the finetuning gains of Table 2 and the expressive-power section; 5: + the viewer's link
STAGE = Stage(VERB, version=5, run=run, per_identity=False, outputs=_report_outputs, params=PARAMS,
              help="closing report of a run: errors of every stage against ground truth", inputs=INPUTS)

"""Stage ``build-baseline``: the paper's baseline reflectance models rebuilt from ground truth — BFM09's role
(``diffuse-only``) and AlbedoMM's role (``albedomm``), models (a) and (b) of Tables 2 and 3
(library: :mod:`reflectmm_cli.evaluation.baselines`; docs/evaluation.md).

Inputs: ``truth`` (synth-truth ``<id>.npz`` files, or the folder holding them — the "scanned" identities),
``face_model`` (for the per-vertex model that finetune / reconstruct / evaluate read). Output: a
``reflectance-model`` artifact ``<ws>/build-baseline/<kind>.npz`` (or ``--output``) and its component preview.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "build-baseline"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('truth', 'ground-truth NPZ files or their folder', upstream='synth-multipie', many=True, help='identities to build the baseline from',
          default=Default('truth')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', missing='build-baseline: no --face-model given and none found in {workspace}')),
)


def _check_ids(ids) -> None:
    if ids and len(set(ids)) != len(ids):
        raise ValueError("an identity is listed twice")


PARAMS = (
    Param("kind", "str", "diffuse-only", choices=("diffuse-only", "albedomm"),
          help="diffuse-only = BFM09's role (Lambertian PCA); albedomm = AlbedoMM's role (diffuse + specular "
               "albedo PCA, one Blinn-Phong lobe)."),
    Param("components", "int", 80, range=(1, None), help="PCA components (capped by N − 1 with a message)."),
    Param("exponent", "float", 20.0, range=(0.0, 10000.0), low_open=True,
          help="Global Blinn-Phong exponent of the albedomm baseline (ignored for diffuse-only)."),
    Param("ids", "strs", None, check=_check_ids,
          help="Use only these truth identities (default: every file given); keep the held-out identities "
               "of Table 3 / relighting out."),
    Param("preview", "bool", True, option="--no-preview", help="Skip the component preview PNG."),
)


def _out(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.output_path(name=ctx.params["kind"])


def _outputs(ctx: StageContext) -> list[Path]:
    out = _out(ctx)
    return [out] + ([out.with_name(out.stem + "_components.png")] if ctx.params["preview"] else [])


def truth_files(paths: list[Path], ids: list[str] | None) -> list[Path]:
    """The synth-truth files of ``paths`` (files, or folders of ``<id>.npz``), restricted to ``ids`` (in that
    order; a missing one is an error)."""
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        files += sorted(q for q in p.glob("*.npz") if not q.name.startswith(".")) if p.is_dir() else [p]
    if ids:
        by = {f.stem: f for f in files}
        missing = [i for i in ids if i not in by]
        if missing:
            raise ReflectmmError(f"build-baseline: no truth file for identity '{missing[0]}' "
                                 f"(have {', '.join(sorted(by)) or 'none'})")
        files = [by[i] for i in ids]
    return files


def load_truths(paths: list[Path]) -> tuple[list[dict[str, np.ndarray]], list[str]]:
    """Read ``synth-truth`` artifacts → (list of {albedo, spec_albedo, uv_mask, …} dicts, identity ids), each
    checked by :func:`reflectmm_cli.evaluation.baselines.truth_maps` (the stage reads, the library builds)."""
    from reflectmm_cli.evaluation.baselines import truth_maps

    out, ids = [], []
    for p in paths:
        art = read_artifact(p, "synth-truth")
        arrs = {k: np.asarray(art.arrays[k]) for k in ("albedo", "spec_albedo", "uv_mask", "vertex_albedo",
                                                       "vertex_spec_albedo") if k in art.arrays}
        truth_maps(arrs, str(p))
        out.append(arrs)
        ids.append(str(art.meta.get("identity", Path(p).stem)))
    return out, ids


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.baselines import build_baseline, write_baseline_model
    from reflectmm_cli.geometry.face_model import load_face_model

    p = ctx.params
    files = truth_files(ctx.input_list("truth"), p.get("ids"))
    if len(files) < 2:
        raise ReflectmmError(f"build-baseline: a PCA needs at least 2 truth identities, got {len(files)}")
    truths, ids = load_truths(files)
    fm_path = ctx.input("face_model")
    fm = load_face_model(fm_path)
    comps = int(p["components"])
    if comps > len(files) - 1:
        log.info(f"build-baseline: {comps} components requested, {len(files)} identities: using {len(files) - 1}")
        comps = len(files) - 1
    model = build_baseline(p["kind"], truths, components=comps, ids=ids, vertex_uv=fm.uv,
                           exponent=float(p["exponent"]), log=log.info)
    out = _out(ctx)
    written = []
    if p["preview"]:
        from reflectmm_cli.model.preview import component_grid

        written.append(write_png(out.with_name(out.stem + "_components.png"), component_grid(model, 3, 2.0)))
    write_baseline_model(model, out, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                         producer=ctx.producer(), cache_key=ctx.cache_key,
                         face_model={"path": Path(fm_path).name, "n_vertices": int(fm.uv.shape[0])})
    log.info(f"build-baseline: {p['kind']} from {len(files)} truth identities, {model.n_components} components")
    return [out] + written


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="baseline reflectance model from ground truth (BFM09's or AlbedoMM's role)", inputs=INPUTS)

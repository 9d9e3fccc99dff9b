"""Stage ``build-pca``: N identities' reflectance maps → the initial reflectance model (docs/design.md §1 step 5).

Reads ``reflectance-maps`` artifacts → :func:`reflectmm_cli.model.build.build_reflectance_model` (PCA with
specular transfer, per-vertex model on the face model) → ``reflectance-model`` artifact + PNG previews beside it.
"""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.artifacts import write_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.model import MODEL_KIND, model_arrays
from reflectmm_cli.model.build import build_reflectance_model
from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "build-pca"

PARAMS = (
    Param("components", "int", 80, range=(1, None), help="PCA components (capped by N − 1 with a message)."),
    Param("samples", "int", 30, range=(0, 1000), option="", help="Random samples rendered in the preview."),
    Param("seed", "int", 0, option="", range=SEED_RANGE, help="Seed of the preview samples."),
    Param("spread", "float", 2.0, range=(0.0, None), option="", unit="σ",
          help="± spread of the component preview."),
    Param("preview", "bool", True, option="--no-preview", help="Skip the PNG previews."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('maps', 'reflectance-maps', upstream='fit-reflectance', many=True, default=Default(checked=False)),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', optional=True)),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    outs = [out]
    if ctx.params["preview"]:
        outs.append(out.with_name(out.stem + "_components.png"))
        if ctx.inputs.get("face_model"):
            outs.append(out.with_name(out.stem + "_samples.png"))
    return outs


def run(ctx: StageContext) -> list[Path]:
    p = ctx.params
    maps = ctx.input_list("maps")
    if len(maps) < 2:
        raise ReflectmmError(f"build-pca: a PCA needs at least 2 reflectance-maps files, got {len(maps)}")
    fm_paths = ctx.input_list("face_model", required=False)
    fm_path = fm_paths[0] if fm_paths else None
    refl_model, fm = build_reflectance_model(maps, p["components"], fm_path)
    out = ctx.output_path()
    resolved = {"components": p["components"]}
    extra = {"n_identities": len(maps), "n_components": refl_model.n_components, "stats": refl_model.stats,
             "ids": refl_model.ids,
             "method": "PCA of the centred diffuse albedo (N x N Gram eigendecomposition + one Lowdin "
                       "re-orthonormalisation); specular bases = the same combination of training samples "
                       "(AlbedoMM); beta in units of sigma (ddof=1)",
             "face_model": None if fm_path is None else {"path": Path(fm_path).name,
                                                         "n_vertices": int(fm.uv.shape[0])}}
    written = [out]
    renderer = None
    if p["preview"]:
        from reflectmm_cli.model.preview import component_grid, render_samples

        written.append(write_png(out.with_name(out.stem + "_components.png"),
                                 component_grid(refl_model, 3, p["spread"])))
        if fm is not None:
            img, renderer = render_samples(refl_model, fm.mean_shape, fm.triangles, n=p["samples"], seed=p["seed"],
                                           uv=fm.uv)
            log.info(f"build-pca: samples rendered with {renderer}")
            written.append(write_png(out.with_name(out.stem + "_samples.png"), img))
        else:
            log.warning("build-pca: no face model given: no per-vertex model and no rendered samples "
                        "(give --face-model)")
    extra["preview_renderer"] = renderer
    # the artifact last: it is the primary output whose cache key says the whole set is up to date
    write_artifact(out, MODEL_KIND, model_arrays(refl_model), params=resolved, inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta=extra)
    ev = refl_model.explained_variance_ratio
    log.info(f"build-pca: {len(maps)} identities -> {refl_model.n_components} components; first 3 explain "
             f"{100 * float(ev[:3].sum()):.1f}% of the diffuse variance")
    return written


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="PCA reflectance model (diffuse albedo + transferred lobe weights)", inputs=INPUTS)

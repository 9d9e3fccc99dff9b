"""Stage ``build-light-pca``: HDR environment maps → PCA lighting model (docs/design.md §1 step 6).

Reads the maps → :func:`reflectmm_cli.model.light.build_light_model` → the ``light-model`` artifact and a PNG
preview next to it.
"""

from __future__ import annotations

import os
from pathlib import Path

from reflectmm_cli.artifacts import write_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.model.light import (
    LIGHT_MODEL_KIND,
    build_light_model,
    find_envmaps,
    light_model_arrays,
    light_model_preview,
)
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages.base import Input, Stage, StageContext

VERB = "build-light-pca"

PARAMS = (
    Param("order", "int", 8, range=(0, 32), help="SH order L."),
    Param("rotations", "int", 1, range=(1, 4096),
          help="Copies of each map rotated about the vertical axis by 360°/N (1 = no augmentation)."),
    Param("tilt", "float", 0.0, range=(0.0, 90.0), unit="degrees",
          help="Also tilt every rotated copy by ±DEG about the horizontal x axis (0 = off)."),
    Param("components", "int", 80, range=(0, None), help="PCA components (capped by the data, with a message)."),
    Param("quadrature", "str", "fejer", choices=("fejer", "area"),
          help="Projection weights: Fejér (exact for band-limited maps) or pixel solid angles."),
    Param("preview", "int", 4, range=(0, 64), option="", help="Components shown in the PNG preview."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('envmaps', 'EXR/HDR maps or folders', upstream='synth-envmaps', many=True),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".png")]


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    return {"envmaps": find_envmaps(ctx.input_list("envmaps"))}


def run(ctx: StageContext) -> list[Path]:
    p = ctx.params
    files = find_envmaps(ctx.input_list("envmaps"))
    if not files:
        raise ReflectmmError("build-light-pca: no environment maps (.exr/.hdr) found in "
                             + ", ".join(str(x) for x in ctx.input_list("envmaps")))
    model, skipped = build_light_model(
        files, order=p["order"], rotations=p["rotations"], tilt=p["tilt"],
        components=p["components"], quadrature=p["quadrature"], log=log.warning,
        progress=lambda it: progress(it, desc="env maps", unit="map"))
    out = ctx.output_path()
    used = [Path(n) for n in model.map_names]
    # names relative to the artifact (like its input records), so a moved workspace gives the same bytes
    model.map_names = [os.path.relpath(n, out.parent) for n in model.map_names]
    skipped = [(os.path.relpath(n, out.parent), r) for n, r in skipped]
    resolved = {k: p[k] for k in ("order", "rotations", "tilt", "components", "quadrature")}
    write_artifact(out, LIGHT_MODEL_KIND, light_model_arrays(model), params=resolved,
                   inputs=ctx.input_refs(out.parent, files={"envmaps": used}), producer=ctx.producer(),
                   cache_key=ctx.cache_key,
                   extra_meta={"n_maps": len(used), "n_samples": int(model.dc.shape[0]),
                               "n_components": model.n_components,
                               "skipped": [{"file": n, "reason": r} for n, r in skipped],
                               "frame": "+y up, camera looks down -z; SH polar axis +z (docs/shading.md)",
                               "normalisation": "each channel divided by its own 0-th SH coefficient (dc)"})
    preview = write_png(out.with_suffix(".png"), light_model_preview(model, p["preview"]))
    ratio = float(model.explained_variance_ratio.sum()) if model.n_components else 0.0
    log.info(f"build-light-pca: {len(used)} maps ({len(skipped)} skipped) x {model.dc.shape[0] // max(len(used), 1)}"
             f" rotations -> {model.n_components} components explaining {100 * ratio:.2f}% of the variance")
    return [out, preview]



STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, input_files=_input_files,
              params=PARAMS, help="PCA lighting model (SH of HDR environment maps)", inputs=INPUTS)

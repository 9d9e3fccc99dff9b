"""``reflectmm build-light-pca``: PCA lighting model from HDR environment maps (DESIGN.md §1 step 6).

Thin layer over :func:`reflectmm_cli.shading.build_light_model`: parse options → library → write the
``light-model`` artifact and a PNG preview next to it.
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from reflectmm_cli.artifacts import write_artifact, write_png
from reflectmm_cli.commands._common import emit, json_option, output_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log, progress
from reflectmm_cli.model.light import (
    LIGHT_MODEL_KIND,
    build_light_model,
    find_envmaps,
    light_model_arrays,
    light_model_preview,
)
from reflectmm_cli.stages import StageContext, register_stage

DEFAULTS = {"order": 8, "rotations": 1, "tilt": 0.0, "components": 80, "quadrature": "fejer", "preview": 4}


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".png")]


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    return {"envmaps": find_envmaps(ctx.input_list("envmaps"))}


@register_stage("build-light-pca", version=1, per_identity=False, outputs=_outputs, input_files=_input_files,
                cache_params=tuple(DEFAULTS), help="PCA lighting model (SH of HDR environment maps)")
def run_build_light_pca(ctx: StageContext) -> list[Path]:
    p = {**DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    files = find_envmaps(ctx.input_list("envmaps"))
    if not files:
        raise ReflectmmError("build-light-pca: no environment maps (.exr/.hdr) found in "
                             + ", ".join(str(x) for x in ctx.input_list("envmaps")))
    model, skipped = build_light_model(
        files, order=int(p["order"]), rotations=int(p["rotations"]), tilt=float(p["tilt"]),
        components=int(p["components"]), quadrature=str(p["quadrature"]), log=log.warning,
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
    preview = write_png(out.with_suffix(".png"), light_model_preview(model, int(p["preview"])))
    ratio = float(model.explained_variance_ratio.sum()) if model.n_components else 0.0
    log.info(f"build-light-pca: {len(used)} maps ({len(skipped)} skipped) x {model.dc.shape[0] // max(len(used), 1)}"
             f" rotations -> {model.n_components} components explaining {100 * ratio:.2f}% of the variance")
    return [out, preview]


@click.command("build-light-pca")
@click.argument("maps", nargs=-1, type=click.Path(path_type=Path))
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(path_type=Path),
              help="An HDR environment map (.exr/.hdr, equirectangular) or a folder of them; repeatable.")
@click.option("--order", type=click.IntRange(0, 32), default=8, show_default=True, help="SH order L.")
@click.option("--rotations", type=click.IntRange(1, 4096), default=1, show_default=True,
              help="Copies of each map rotated about the vertical axis by 360°/N (1 = no augmentation).")
@click.option("--tilt", type=click.FloatRange(0, 90), default=0.0, show_default=True,
              help="Also tilt every rotated copy by ±DEG about the horizontal x axis (0 = off).")
@click.option("--components", type=click.IntRange(0, None), default=80, show_default=True,
              help="PCA components (capped by the data, with a message).")
@click.option("--quadrature", type=click.Choice(["fejer", "area"]), default="fejer", show_default=True,
              help="Projection weights: Fejér (exact for band-limited maps) or pixel solid angles.")
@workspace_option
@output_option
@json_option
def build_light_pca_cmd(maps, inputs, order, rotations, tilt, components, quadrature, workspace, output, as_json):
    """Build a PCA lighting model from HDR environment maps (MAPS and/or --input, files or folders).

    Writes a `light-model` artifact (<workspace>/build-light-pca/build-light-pca.npz or --output) and a PNG
    preview beside it. Unreadable or non-finite maps are skipped and reported on stderr.
    """
    paths = list(inputs) + list(maps)
    if not paths:
        raise click.UsageError("give at least one environment map or folder (MAPS or --input)")
    params = {"order": order, "rotations": rotations, "tilt": tilt, "components": components,
              "quadrature": quadrature}
    out = run_stage_cli("build-light-pca", workspace=workspace, params=params, inputs={"envmaps": paths},
                        output=output)
    emit(out, as_json)


COMMANDS = [build_light_pca_cmd]

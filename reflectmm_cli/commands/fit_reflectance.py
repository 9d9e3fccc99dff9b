"""``reflectmm fit-reflectance``: per-identity diffuse albedo and lobe-weight maps (DESIGN.md §3).

Thin layer over :func:`reflectmm_cli.reflectance.fit_maps`: read a ``uv-observations`` artifact, fit, write
the ``reflectance-maps`` artifact, an EXR with named channels and PNG previews next to it.
"""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.artifacts import make_meta, read_artifact, write_artifact, write_exr, write_png
from reflectmm_cli.commands._common import (device_option, emit, json_option, output_option, run_stage_cli,
                                            workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages import StageContext, register_stage

DEFAULTS = {"solver": "fast", "exponents": [1.0, 8.0, 64.0], "symmetry": 1.0, "symmetry_mode": "adaptive",
            "loss": "l1", "prior": 1e-4, "prior_tail": 100.0,
            "steps": 1000, "flash_intensity": None, "seed": 0, "cond_min": 1e-4}
PREVIEWS = ("albedo", "weights", "residual", "flagged")


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".exr")] + [out.with_name(f"{out.stem}_{k}.png") for k in PREVIEWS]


def _input_path(ctx: StageContext) -> Path:
    if ctx.inputs.get("observations"):
        return ctx.input("observations")
    if ctx.identity is None:
        raise ReflectmmError("fit-reflectance: give --id or --input")
    return ctx.workspace / "unwrap-uv" / f"{ctx.identity}.npz"


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    return {"observations": [_input_path(ctx)]}


def resolve_params(params: dict) -> dict:
    """Defaults + given params, validated and normalised (what goes into meta and the cache key)."""
    p = {**DEFAULTS, **{k: v for k, v in params.items() if v is not None}}
    exps = p["exponents"]
    if isinstance(exps, str):
        try:
            exps = [float(e) for e in exps.replace(" ", "").split(",") if e]
        except ValueError:
            raise ReflectmmError(f"--exponents: not a comma-separated list of numbers: {exps!r}") from None
    p["exponents"] = [float(e) for e in exps]
    fi = p.get("flash_intensity")
    if isinstance(fi, str):
        try:
            fi = [float(e) for e in fi.replace(" ", "").split(",") if e]
        except ValueError:
            raise ReflectmmError(f"--flash-intensity: not a number or comma-separated list: {fi!r}") from None
    if isinstance(fi, (int, float)):
        fi = [float(fi)]
    p["flash_intensity"] = None if fi is None else [float(v) for v in fi]
    return p


def _channel_name(p: float) -> str:
    return f"weight.p{p:g}".replace(".", "_").replace("weight_p", "weight.p")


# version 2: mirror pooling only where a texel's own data are ill-posed by default (symmetry_mode)
# version 3: tail prior on lobe weights seen only in their lobe's tail (prior_tail)
# version 4: adaptive mirror pooling by default (issue 13)
@register_stage("fit-reflectance", version=4, per_identity=True, outputs=_outputs, input_files=_input_files,
                help="fit diffuse albedo and lobe-weight maps to one identity's UV observations")
def run_fit_reflectance(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.reflectance import fit_maps
    from reflectmm_cli.reflectance.previews import (albedo_preview, flagged_preview, residual_preview,
                                                    weights_preview)

    p = resolve_params(ctx.params)
    src = _input_path(ctx)
    if not src.exists():
        raise ReflectmmError("uv-observations input not found (run unwrap-uv first or give --input)", src)
    obs = read_artifact(src, "uv-observations")
    maps = fit_maps(obs.arrays, exponents=p["exponents"], solver=p["solver"], symmetry=float(p["symmetry"]),
                    symmetry_mode=str(p["symmetry_mode"]), loss=p["loss"], prior=float(p["prior"]),
                    prior_tail=float(p["prior_tail"]),
                    flash_intensity=p["flash_intensity"],
                    steps=int(p["steps"]), device=ctx.device, seed=int(p["seed"]), cond_min=float(p["cond_min"]),
                    progress=progress, path=src)
    stats = {k: v for k, v in maps.stats.items() if k != "time_s"}  # no timings in artifacts (byte-identical reruns)
    out = ctx.output_path()
    resolved = {k: p[k] for k in sorted(DEFAULTS)}
    inputs = ctx.input_refs(out.parent, files={"observations": [src]})
    extra = {"stats": stats,
             "scale": "radiance = C·E·cos/π + Σ W·E·f·cos_h^p with E = flash_intensity/d²; scaling "
                      "flash_intensity by k scales C and W by 1/k (global scale ambiguity)",
             "flash_intensity_used": (p["flash_intensity"] if p["flash_intensity"] is not None
                                      else [float(v) for v in obs["flash_intensity"]])}
    write_artifact(out, "reflectance-maps", maps.arrays(), params=resolved, inputs=inputs, producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta=extra)
    meta = make_meta("reflectance-maps", params=resolved, inputs=inputs, producer=ctx.producer(),
                     cache_key=ctx.cache_key, extra=extra)
    channels = {f"albedo.{c}": maps.albedo[i] for i, c in enumerate("RGB")}
    for k, e in enumerate(maps.exponents):
        channels[_channel_name(float(e))] = maps.weights[k]
    exr = write_exr(out.with_suffix(".exr"), channels, meta)
    pngs = [
        write_png(out.with_name(f"{out.stem}_albedo.png"), albedo_preview(maps.albedo, maps.mask)),
        write_png(out.with_name(f"{out.stem}_weights.png"), weights_preview(maps.weights, maps.mask)),
        write_png(out.with_name(f"{out.stem}_residual.png"), residual_preview(maps.residual, maps.mask)),
        write_png(out.with_name(f"{out.stem}_flagged.png"),
                  flagged_preview(maps.mask, maps.flagged, maps.observability)),
    ]
    s = maps.stats
    log.info(f"fit-reflectance {ctx.identity or out.stem}: {p['solver']} solver, {s['n_texels']} texels, "
             f"{s['n_flagged']} flagged, {s['n_observable']} fully observable, median RMS residual "
             f"{s['residual_rms_median']:.3g}, {s['time_s']:.2f} s")
    return [out, exr] + pngs


@click.command("fit-reflectance")
@click.option("--id", "identity", default=None, help="Identity (reads <workspace>/unwrap-uv/<id>.npz).")
@click.option("--input", "-i", "input_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="uv-observations artifact (overrides the workspace convention).")
@click.option("--solver", type=click.Choice(["fast", "adam"]), default="fast", show_default=True,
              help="fast: exact batched IRLS/NNLS per texel; adam: the paper's Adam reference.")
@click.option("--exponents", default="1,8,64", show_default=True, help="Lobe exponents, comma separated.")
@click.option("--symmetry", type=click.FloatRange(0.0, 1.0), default=1.0, show_default=True,
              help="Mirror pooling weight (fast) / random flips on (adam, when > 0).")
@click.option("--symmetry-mode", type=click.Choice(["adaptive", "ill-posed", "all"]), default="adaptive", show_default=True,
              help="Fast solver: adaptive = pool ill-posed texels with their mirror and well-posed ones only as far "
                   "as the measured local asymmetry allows; ill-posed = only where a texel's own data are ill-posed "
                   "(few observations or conditioning < --cond-min); all = every texel (the paper's random flip).")
@click.option("--loss", type=click.Choice(["l1", "l2"]), default="l1", show_default=True,
              help="cos-weighted L1 (the paper's, IRLS) or cos-weighted least squares (fast solver).")
@click.option("--prior", type=click.FloatRange(0.0, None), default=1e-4, show_default=True,
              help="Tikhonov strength towards the neighbourhood prior, × trace of each texel's data term.")
@click.option("--prior-tail", type=click.FloatRange(0.0, None), default=100.0, show_default=True,
              help="Extra prior on a lobe weight whose lobe is seen only in its tail: × prior × "
                   "(1 − observability/0.5)² (0 = off).")
@click.option("--steps", type=click.IntRange(1, None), default=1000, show_default=True, help="Adam steps.")
@click.option("--flash-intensity", default=None,
              help="Flash radiant intensity (one value or one per flash, comma separated); default: the "
                   "observations' values. Sets the global scale of C and W.")
@click.option("--cond-min", type=click.FloatRange(0.0, 1.0), default=1e-4, show_default=True,
              help="Flag texels whose pooled conditioning is below this.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of Adam's random flips.")
@device_option
@workspace_option
@output_option
@json_option
def fit_reflectance_cmd(identity, input_path, solver, exponents, symmetry, symmetry_mode, loss, prior, prior_tail,
                        steps, flash_intensity, cond_min, seed, device, workspace, output, as_json):
    """Fit diffuse albedo C and lobe weights W for one identity.

    Writes <workspace>/fit-reflectance/<id>.npz (reflectance-maps), <id>.exr (channels albedo.R/G/B,
    weight.p<exponent>) and PNG previews <id>_albedo/_weights/_residual/_flagged.png.
    """
    if identity is None and input_path is None:
        raise click.UsageError("give --id or --input")
    params = resolve_params({"solver": solver, "exponents": exponents, "symmetry": symmetry,
                             "symmetry_mode": symmetry_mode, "loss": loss, "prior": prior,
                             "prior_tail": prior_tail, "steps": steps,
                             "flash_intensity": flash_intensity, "seed": seed, "cond_min": cond_min})
    inputs = {"observations": [input_path]} if input_path is not None else None
    if inputs is None and identity is not None:
        from reflectmm_cli.stages import default_workspace

        ws = (workspace or default_workspace()).resolve()
        src = ws / "unwrap-uv" / f"{identity}.npz"
        if not src.exists():
            raise ReflectmmError("uv-observations not found (run unwrap-uv first or give --input)", src)
        inputs = {"observations": [src]}
    if identity is None:
        identity = Path(input_path).stem
    paths = run_stage_cli("fit-reflectance", workspace=workspace, identity=identity, params=params, inputs=inputs,
                          output=output, device=device)
    emit(paths, as_json)


COMMANDS = [fit_reflectance_cmd]

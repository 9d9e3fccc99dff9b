"""Stage ``fit-reflectance``: one identity's UV observations → diffuse albedo and lobe-weight maps (docs/design.md §3).

Reads a ``uv-observations`` artifact, calls :func:`reflectmm_cli.reflectance.fit_maps`, writes the
``reflectance-maps`` artifact, an EXR with named channels and PNG previews next to it.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from reflectmm_cli.artifacts import (artifact_identity, check_identity, make_meta, read_artifact, write_artifact,
                                     write_exr, write_png)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.progress import log, progress
from reflectmm_cli.reflectance.fit import FitMapsConfig
from reflectmm_cli.shading.brdf import check_exponents
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.workspace import stage_output

VERB = "fit-reflectance"

#: FitMapsConfig's defaults by flat name (the nested config's settings are flat parameters and options here)
_CFG = SimpleNamespace(**FitMapsConfig().flat())

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('observations', 'uv-observations', upstream='unwrap-uv',
          default=Default(missing='{path}: uv-observations not found (run unwrap-uv first or give --input)')),
)


def _cfg(name: str, kind: str, **kw: Any) -> Param:
    """A Param for a FitMapsConfig setting (by its flat name), its default declared once, there."""
    return Param.of_field(_CFG, name, kind, **kw)


#: Lobe exponents: positive, at most MAX_EXPONENT, no two collinear lobes (shading.brdf.check_exponents).
EXPONENTS = _cfg("exponents", "floats", check=check_exponents,
                  help="Lobe exponents, comma separated (distinct, each in (0, 10000]).")

#: The solver's parameters, shared with evaluate-representation (which refits every representation).
SOLVER_PARAMS = (
    _cfg("solver", "str", choices=("fast", "adam"),
          help="fast: exact batched IRLS/NNLS per texel; adam: the paper's Adam reference."),
    _cfg("symmetry", "float", range=(0.0, 1.0),
          help="Mirror pooling weight (fast) / random flips on (adam, when > 0)."),
    _cfg("symmetry_mode", "str", choices=("adaptive", "ill-posed", "all"),
          help="Fast solver: adaptive = pool ill-posed texels with their mirror and well-posed ones only as far "
               "as the measured local asymmetry allows; ill-posed = only where a texel's own data are ill-posed "
               "(few observations or conditioning < --cond-min); all = every texel (the paper's random flip)."),
    _cfg("loss", "str", choices=("l1", "l2"),
          help="cos-weighted L1 (the paper's, IRLS) or cos-weighted least squares (fast solver)."),
    _cfg("prior", "float", range=(0.0, None),
          help="Tikhonov strength towards the neighbourhood prior, × trace of each texel's data term."),
    _cfg("prior_tail", "float", range=(0.0, None),
          help="Extra prior on a lobe weight whose lobe is seen only in its tail: × prior × "
               "(1 − observability/0.5)² (0 = off)."),
)

#: A sane flash radiant intensity, in linear pixel units × mm² (E = I / d², d in mm): the synthetic rig's is 4.5e6,
#: 1 is the choice for real data of unknown intensity. Far outside, E·C overflows or underflows in the design matrix
#: and every texel came out "ill-conditioned", blaming the exponents.
FLASH_INTENSITY_RANGE = (1e-12, 1e12)

PARAMS = (EXPONENTS,) + SOLVER_PARAMS + (
    _cfg("steps", "int", range=(1, 10 ** 7), help="Adam steps."),
    Param("flash_intensity", "floats", None, range=FLASH_INTENSITY_RANGE,
          help="Flash radiant intensity in linear pixel units x mm² (E = I/d²; one value or one per flash, comma "
               "separated); default: the observations' values. Sets the global scale of C and W."),
    _cfg("cond_min", "float", range=(0.0, 1.0), help="Flag texels whose pooled conditioning is below this."),
    _cfg("seed", "int", range=SEED_RANGE, help="Seed of Adam's random flips."),
    _cfg("refine_normals", "int", range=(0, 100),
          help="Photometric normal refinement: alternations of Gauss–Newton steps of each texel's normal and the "
               "reflectance solve (fast solver; 0 = off)."),
    _cfg("normal_sigma", "float", range=(0.0, 90.0), low_open=True, unit="degrees",
          help="σ of the refined normal's Gaussian prior towards the geometric normal."),
)

#: the params that are FitMapsConfig settings (flash_intensity is an input of the fit, not a setting)
_SETTINGS = tuple(q.name for q in PARAMS if q.name in FitMapsConfig.flat_names())

PREVIEWS = ("albedo", "weights", "residual", "flagged")


def _previews(params) -> tuple[str, ...]:
    return PREVIEWS + (("normal_correction",) if params.get("refine_normals") else ())


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".exr")] + [out.with_name(f"{out.stem}_{k}.png") for k in _previews(ctx.params)]


def input_path(ctx: StageContext) -> Path:
    """The uv-observations input: the given one, else ``<ws>/unwrap-uv/<id>.npz``."""
    if ctx.inputs.get("observations"):
        return ctx.input("observations")
    if ctx.identity is None:
        raise ReflectmmError("fit-reflectance: give --id or --input")
    return stage_output(ctx.workspace, "unwrap-uv", ctx.identity)


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    return {"observations": [input_path(ctx)]}


def _channel_name(p: float) -> str:
    return f"weight.p{p:g}".replace(".", "_").replace("weight_p", "weight.p")


#: Settings of the fast solver that the paper's Adam does not use (it fits its own L1 loss, prior and flips).
FAST_ONLY = ("loss", "symmetry_mode", "prior", "prior_tail", "prior_tail_obs")


def check_solver_settings(p: dict) -> None:
    """Refuse fast-solver settings given with ``solver = "adam"``: they would be recorded in the artifact and its
    cache key as used, while the maps are the same to the bit."""
    if p.get("solver") != "adam":
        return
    default = FitMapsConfig().flat()
    given = [k for k in FAST_ONLY if k in p and p[k] is not None and p[k] != default[k]]
    if given:
        raise ReflectmmError(f"{', '.join(f'--{k.replace(chr(95), chr(45))} {p[k]}' for k in given)}: setting(s) of "
                             "the fast solver, which --solver adam does not use; leave them out")


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.reflectance import fit_maps
    from reflectmm_cli.reflectance.previews import (albedo_preview, flagged_preview, normal_correction_preview,
                                                    residual_preview, weights_preview)

    p = ctx.params
    src = input_path(ctx)
    if not src.exists():
        raise ReflectmmError("uv-observations input not found (run unwrap-uv first or give --input)", src)
    obs = check_identity(read_artifact(src, "uv-observations"), ctx.identity)
    observed = np.asarray(obs.arrays.get("observed", np.zeros(0, bool)), bool)
    if observed.size and not observed.any():  # the library would flag every texel; a verb writes no such maps
        raise ReflectmmError(f"uv-observations has no observed texel ({observed.shape[0]} pairs, none observed): "
                             "nothing to fit; check unwrap-uv's --views and --flashes and the geometry", src)
    fi = p.get("flash_intensity")
    check_solver_settings(p)
    cfg = FitMapsConfig.from_flat(**{k: p[k] for k in _SETTINGS}, device=ctx.device)
    maps = fit_maps(obs.arrays, cfg, flash_intensity=fi, progress=progress, path=src)
    if maps.stats["n_texels"] and maps.stats["n_flagged"] >= maps.stats["n_texels"]:
        raise ReflectmmError(f"no texel could be fitted: all {maps.stats['n_texels']} are ill-conditioned for the "
                             f"lobes of exponents {', '.join(f'{e:g}' for e in maps.exponents)} (too many or too close "
                             "for the view-flash pairs observed); nothing written", src)
    stats = {k: v for k, v in maps.stats.items() if k != "time_s"}  # no timings in artifacts (byte-identical reruns)
    out = ctx.output_path()
    resolved = {q.name: p.get(q.name) for q in sorted(PARAMS, key=lambda q: q.name)}
    inputs = ctx.input_refs(out.parent, files={"observations": [src]})
    extra = {"stats": stats,
             "scale": "radiance = C·E·cos/π + Σ W·E·f·cos_h^p with E = flash_intensity/d²; scaling "
                      "flash_intensity by k scales C and W by 1/k (global scale ambiguity)",
             "flash_intensity_used": (fi if fi is not None else [float(v) for v in obs["flash_intensity"]])}
    ident = ctx.identity if ctx.identity is not None else artifact_identity(obs)
    if ident is not None:  # so that a consumer can refuse another identity's maps (evaluate truth)
        extra["identity"] = str(ident)
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
    if maps.normal_correction is not None:
        pngs.append(write_png(out.with_name(f"{out.stem}_normal_correction.png"),
                              normal_correction_preview(maps.normal_correction, maps.mask)))
    s = maps.stats
    log.info(f"fit-reflectance {ctx.identity or out.stem}: {p['solver']} solver, {s['n_texels']} texels, "
             f"{s['n_flagged']} flagged, {s['n_observable']} fully observable, median RMS residual "
             f"{s['residual_rms_median']:.3g}, {s['time_s']:.2f} s")
    return [out, exr] + pngs


# version 2: mirror pooling only where a texel's own data are ill-posed by default (symmetry_mode)
# version 3: tail prior on lobe weights seen only in their lobe's tail (prior_tail)
# version 4: adaptive mirror pooling by default (issue 13)
STAGE = Stage(VERB, version=4, run=run, per_identity=True, outputs=_outputs, input_files=_input_files,
              params=PARAMS, help="fit diffuse albedo and lobe-weight maps to one identity's UV observations", inputs=INPUTS)

"""Stage ``evaluate-representation``: the paper's Table 1 — global exponents vs multi-lobe, re-rendered against
held-out flash images (library: :mod:`reflectmm_cli.evaluation.representation`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, read_artifact, write_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.params import Param, named_twice, parse_list
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.stages.fit_reflectance import SOLVER_PARAMS, check_solver_settings

VERB = "evaluate-representation"

#: The command's image-space inputs: with --ids (and --space other than uv), each identity's capture and geometry and
#: the workspace's face model are passed when every one of them exists, else none of them (a given --face-model
#: included); the stage then re-renders in image space when they are given (--space auto), as in a recipe that
#: names them.
_IMAGE_SPACE = Default(optional=True, group="image", unless=("space", "uv"))

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('observations', 'uv-observations', upstream='unwrap-uv', many=True, default=Default(checked=False)),
    Input('capture', 'capture', upstream='preprocess-multipie', many=True, default=_IMAGE_SPACE),
    Input('geometry', 'geometry', upstream='fit-geometry', many=True, default=_IMAGE_SPACE),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=replace(_IMAGE_SPACE, rule='face-model')),
    Input('lpips_weights', 'LPIPS weights (safetensors)'),
)


def _check_sets(text: str) -> None:
    """Every ';'-separated set is a valid exponent list (a single exponent = a global exponent)."""
    from reflectmm_cli.evaluation.representation import parse_exponent_sets

    try:
        parse_exponent_sets(text)
    except ReflectmmError as exc:
        raise ValueError(str(exc).split(": ", 1)[-1]) from None


def _check_holdout(text: str) -> None:
    """A comma list of flash ids, each named once (``05,05`` was taken as "held-out flashes 05, 05"). The param
    stays a string (its recorded value and the cache keys of earlier runs are unchanged)."""
    twice = named_twice(parse_list(text, "holdout"))
    if twice:
        raise ValueError(f"{', '.join(twice)} named more than once")


#: Params written to the artifact's meta (all but execution details).
REP_PARAMS = ("exponents_sets", "holdout", "baselines", "solver", "symmetry", "symmetry_mode", "loss", "prior",
              "prior_tail", "lpips_net", "space", "max_identities")

PARAMS = (
    Param("exponents_sets", "str", "8;16;32;64;1,8,64", check=_check_sets,
          help="Representations separated by ';' (a single exponent = global exponent, K = 1; 0 or 'diffuse' = "
               "diffuse only)."),
    Param("holdout", "str", "05,09", check=_check_holdout, help="Flash ids held out for re-rendering (all views)."),
    Param("baselines", "bool", True, option="--no-baselines",
          help="Skip 'diffuse only' and 'spec albedo + shininess 20'."),
) + SOLVER_PARAMS + (
    Param("lpips_net", "str", "alex", choices=("alex", "vgg"), help="LPIPS backbone."),
    Param("space", "str", "auto", choices=("auto", "image", "uv"),
          help="Re-render in image space against the captured OLAT images (needs <ws>/preprocess-multipie/<id>.npz, "
               "<ws>/fit-geometry/<id>.npz and a face model) or in UV space; auto = image when available."),
    Param("max_identities", "int", 0, range=(0, None),
          help="Evaluate only the first N identities whose observations hold the held-out flashes (0 = all); ~45 s "
               "per identity at UV 256 on 2 cores."),
)


def _by_identity(paths: list[Path], kind: str) -> dict[str, Path]:
    from reflectmm_cli.artifacts import read_meta

    out = {}
    for p in paths:
        meta = read_meta(p)
        out[str(meta.get("identity") or Path(p).stem)] = Path(p)
    return out


def _image_space_renderers(ctx: StageContext, ids: list[str], space: str):
    """Per identity an ImageSpaceRenderer when captures, geometries and a face model are given (space image/auto);
    None for UV space."""
    caps = ctx.input_list("capture", required=False)
    geos = ctx.input_list("geometry", required=False)
    fms = ctx.input_list("face_model", required=False)
    if space == "uv":
        return None
    have = bool(caps and geos and fms)
    if have:
        cap_by, geo_by = _by_identity(caps, "capture"), _by_identity(geos, "geometry")
        missing = [i for i in ids if i not in cap_by or i not in geo_by]
        have = not missing
    if not have:
        if space == "image":
            raise ReflectmmError("evaluate representation --space image needs a capture, a geometry and a face model "
                                 "for every identity (inputs capture, geometry, face_model)"
                                 + (f"; missing for {', '.join(missing)}" if caps and geos and fms else ""))
        log.info("evaluate representation: no captures/geometry/face model for every identity: UV-space "
                 "re-rendering")
        return None
    from reflectmm_cli.evaluation.image_space import ImageSpaceRenderer
    from reflectmm_cli.geometry.face_model import load_face_model

    try:
        from reflectmm_cli.geometry import has_embree
        if not has_embree():
            raise ImportError
    except ImportError:
        if space == "image":
            raise ReflectmmError("evaluate representation --space image needs Embree (embreex)") from None
        log.warning("evaluate representation: Embree unavailable: UV-space re-rendering")
        return None
    fm = load_face_model(fms[0])
    return [ImageSpaceRenderer(read_artifact(cap_by[i], "capture").arrays, read_artifact(geo_by[i], "geometry").arrays,
                               fm.triangles, fm.uv, name=i) for i in ids]


def _rep_outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


def _identities_with_holdout(files: list[Path], holdout: list[str], max_identities: int
                             ) -> tuple[list[dict], list[str], list[str]]:
    """The observations (in input order) whose flashes include every held-out one and at least one more, up to
    ``max_identities`` (0 = all).  An identity without them (its observations kept only the flashes that landmarks
    placed, say) is skipped with a warning; none left is a one-line error naming the held-out flashes."""
    from reflectmm_cli.evaluation.representation import holdout_problem

    obs, ids, skipped = [], [], []
    for f in files:
        if max_identities > 0 and len(obs) >= max_identities:
            break
        art = read_artifact(f, "uv-observations")
        ident = str(art.meta.get("identity") or Path(f).stem)
        if ident in ids or ident in skipped:
            raise ReflectmmError(f"evaluate representation: identity {ident} is given twice: each counts once", f)
        why = holdout_problem(art.arrays["flash_ids"], holdout)
        if why is not None:
            skipped.append(ident)
            log.warning(f"evaluate representation: identity {ident} skipped: {why}")
            continue
        obs.append(art.arrays)
        ids.append(ident)
    if not obs:
        raise ReflectmmError(f"evaluate representation: no identity's observations hold the held-out flashes "
                             f"{', '.join(holdout)} and another to fit (skipped: {', '.join(skipped)})")
    if max_identities > 0 and len(files) > len(obs):
        log.info(f"evaluate representation: using {len(obs)} of {len(files)} identities (max_identities "
                 f"{max_identities})")
    return obs, ids, skipped


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.metrics import load_lpips
    from reflectmm_cli.evaluation.representation import (comparison_figure, compare_representations,
                                                         default_representations, margin_of_multilobe,
                                                         comparison_table)

    p = ctx.params
    check_solver_settings(p)
    files = ctx.input_list("observations")
    lp_files = ctx.input_list("lpips_weights", required=False)
    lp = load_lpips(lp_files[0] if lp_files else None, str(p["lpips_net"]))
    reps = default_representations(str(p["exponents_sets"]), bool(p["baselines"]))
    holdout = parse_list(p["holdout"], "holdout")
    obs, ids, skipped = _identities_with_holdout(files, holdout, int(p["max_identities"]))
    kw = {k: p[k] for k in ("solver", "symmetry", "symmetry_mode", "loss", "prior", "prior_tail")}
    space = p["space"]
    isr = _image_space_renderers(ctx, ids, space)
    res = compare_representations(obs, ids, reps, holdout, lp, fit_kwargs=kw,
                                  progress=lambda it, **k: progress(it, unit="id", **k), image_space=isr)
    out = ctx.output_path()
    table = comparison_table(res)
    margin = margin_of_multilobe(res)
    arrays = {"representations": np.array([r.name for r in reps], dtype=str), "ids": np.array(ids, dtype=str),
              "psnr": res.psnr, "ssim": res.ssim, "psnr_pairs": res.psnr_pairs, "ssim_pairs": res.ssim_pairs,
              "train_psnr": res.train_psnr, "fit_seconds": res.fit_seconds,
              "outside_domain": np.asarray(res.outside_domain, np.float64),
              "pairs_per_identity": np.asarray(res.pairs_per_identity, np.int64),
              "holdout_flashes": np.array(holdout, dtype=str), "skipped_ids": np.array(skipped, dtype=str)}
    if res.lpips is not None:
        arrays["lpips"] = res.lpips
    exps = {r.name: list(r.exponents) for r in reps}
    write_artifact(out, EVAL_KIND, arrays, params={k: p[k] for k in REP_PARAMS},
                   inputs=ctx.input_refs(out.parent), producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "representation", "space": res.space, "exponents": exps,
                               "protocol": "held-out flashes (all views); same training pairs for every "
                                           "representation; metrics on clip(x,0,1)^(1/1.2), peak 1",
                               "lpips": "on" if lp is not None else "off (no weights given)",
                               "figure": {"identity": res.figure.get("identity"), "view": res.figure.get("view"),
                                          "flash": res.figure.get("flash")},
                               "margin": margin, "table": table})
    head = ("# Representation comparison\n\nFigure: `" + out.with_suffix(".png").name + "` — identity "
            f"{res.figure.get('identity')}, view {res.figure.get('view')}, flash {res.figure.get('flash')}: "
            "truth | " + " | ".join(r.name for r in reps) + " (top), absolute error of the display encoding ×20, black → red → yellow → white (bottom).\n\n")
    md = head + table
    if margin:
        md += (f"\n{margin['multilobe']} vs the best global exponent ({margin['best_global']}): "
               f"{margin['psnr_margin_db']:+.2f} dB PSNR, {margin['ssim_margin']:+.4f} SSIM; beats every global "
               f"exponent: PSNR {'yes' if margin['beats_every_global_psnr'] else 'NO'}, SSIM "
               f"{'yes' if margin['beats_every_global_ssim'] else 'NO'}.\n")
    atomic_write_text(out.with_suffix(".md"), md)
    write_png(out.with_suffix(".png"), comparison_figure(res, labels=[r.name for r in reps]))
    log.info(table)
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


# version 2: image-space region inside the maps' domain; symmetry_mode. version 3: prior_tail version 4: adaptive
# version 6: the diffuse-only baseline fills the texels without data from their neighbours (as fit-reflectance)
STAGE = Stage(VERB, version=8, run=run, per_identity=False, outputs=_rep_outputs, params=PARAMS,
              help="the paper's Table 1: global exponents vs multi-lobe on held-out flashes", inputs=INPUTS)

"""``reflectmm calibrate-rig``: one rig for all identities of a capture (aggregate stage, docs/capture.md).

Thin layer over :func:`reflectmm_cli.fitting.calibrate.calibrate_from_captures`: the landmarks of every
identity's ``capture`` artifact (preprocess-multipie) + a face model + a nominal rig table → the ``rig`` artifact
(``<ws>/calibrate-rig/calibrate-rig.npz``) and beside it ``rig.toml``, the calibrated table that
``fit-geometry --rig`` reads.
"""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, json_option, output_option, parse_ids, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages import StageContext, default_workspace, register_stage

VERB = "calibrate-rig"
DEFAULTS = {"focal": None, "focal_mode": "auto", "loss": "cauchy", "loss_scale_px": 3.0, "landmark_sigma_px": 1.0,
            "outlier_px": 6.0, "max_iters": 60, "views": None, "distance_sigma_rel": 0.1}


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name("rig.toml")]


def _config(p: dict):
    from reflectmm_cli.fitting.calibrate import CalibrationConfig

    mode = p["focal_mode"]
    if mode == "auto":  # a focal the user knows is kept; otherwise one shared focal is estimated
        mode = "fixed" if p["focal"] is not None else "shared"
    return CalibrationConfig(focal=mode, focal_px=None if p["focal"] is None else float(p["focal"]), loss=p["loss"],
                             loss_scale_px=float(p["loss_scale_px"]), landmark_sigma_px=float(p["landmark_sigma_px"]),
                             outlier_px=float(p["outlier_px"]), max_iters=int(p["max_iters"]),
                             distance_sigma_rel=float(p["distance_sigma_rel"]))


@register_stage(VERB, version=1, per_identity=False, outputs=_outputs,
                help="landmarks of every identity + face model + nominal rig -> one calibrated rig (rig artifact + "
                     "rig.toml)")
def run_calibrate_rig(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.fitting.calibrate import calibrate_from_captures, write_rig_calibration

    p = {**DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    caps = ctx.input_list("capture")
    fm = ctx.input("face_model")
    rigs = ctx.input_list("rig", required=False)
    views = None if not p["views"] else [str(v) for v in p["views"]]
    cal = calibrate_from_captures(caps, fm, rigs[0] if rigs else None, _config(p), views=views, progress_fn=progress)
    out = ctx.output_path()
    written = write_rig_calibration(cal, out, toml_path=out.with_name("rig.toml"), params=ctx.resolved_params(),
                                    inputs=ctx.input_refs(out.parent), producer=ctx.producer(),
                                    cache_key=ctx.cache_key)
    for a in cal.assumptions:
        log.info("calibrate-rig: assumed: %s", a)
    if cal.report["outliers"]:
        log.warning("calibrate-rig: %d landmark(s) further than %.1f px from the fit (outliers; first: %s)",
                    cal.report["outliers"], float(p["outlier_px"]), ", ".join(cal.report["outliers_first"][:5]))
    return written


@click.command(VERB)
@click.option("--ids", default=None, help="Identities (001,002 or 001-128): reads <ws>/preprocess-multipie/<id>.npz.")
@click.option("--capture", "-i", "captures", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="A capture artifact (repeatable; instead of or in addition to --ids).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model (default: face_model.npz of the first capture's dataset folder, else "
                   "<ws>/face_model.npz).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="nominal rig table TOML: camera angles, a rough distance and the focal (default: rig.toml of the "
                   "dataset folder, else the packaged Multi-PIE table; its image size must match the images).")
@click.option("--focal", type=click.FloatRange(min=1e-3), default=None,
              help="focal length in px of the images, if known (then kept fixed unless --focal-mode says otherwise).")
@click.option("--focal-mode", type=click.Choice(["auto", "fixed", "shared", "per-camera"]), default="auto",
              show_default=True, help="auto: fixed if --focal is given, else one shared focal estimated.")
@click.option("--loss", type=click.Choice(["cauchy", "huber", "l2"]), default="cauchy", show_default=True,
              help="robust loss of the landmark distances.")
@click.option("--loss-scale", type=click.FloatRange(min=1e-3), default=3.0, show_default=True,
              help="scale of the robust loss in px.")
@click.option("--outlier-px", type=click.FloatRange(min=1e-3), default=6.0, show_default=True,
              help="landmarks further than this from the fit are reported as outliers.")
@click.option("--distance-sigma", type=click.FloatRange(min=0), default=0.1, show_default=True,
              help="relative uncertainty of the nominal table's distances: its size is fused with the faces' mean "
                   "size by these weights (0 = the faces only; 0.01 for a measured rig).")
@click.option("--views", default=None, help="cameras to calibrate, comma separated (default: every capture view).")
@workspace_option
@output_option
@json_option
def calibrate_rig_cmd(ids, captures, face_model, rig, focal, focal_mode, loss, loss_scale, outlier_px, distance_sigma,
                      views, workspace, output, as_json):
    """Estimate one rig (camera poses, focal, flash positions) from the landmarks of all identities.

    Writes the `rig` artifact (<ws>/calibrate-rig/calibrate-rig.npz) and rig.toml beside it; pass that to
    `fit-geometry --rig` (with a tight --rig-sigma, e.g. 3 mm).
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.commands.fit_geometry import default_face_model_for, default_rig_for

    ws = (workspace or default_workspace()).resolve()
    paths = [ws / "preprocess-multipie" / f"{i}.npz" for i in parse_ids(ids)] + list(captures)
    if not paths:
        raise click.UsageError("give --ids or --capture files")
    missing = [p for p in paths if not Path(p).is_file()]
    if missing:
        raise ReflectmmError("capture artifact not found (run preprocess-multipie first)", missing[0])
    first = read_artifact(paths[0], "capture")
    face_model = face_model or default_face_model_for(first, ws)
    if face_model is None:
        raise ReflectmmError("no face model: pass --face-model", paths[0])
    rig = rig or default_rig_for(first)
    inputs = {"capture": paths, "face_model": [face_model]}
    if rig is not None:
        inputs["rig"] = [rig]
    params = {"focal": focal, "focal_mode": focal_mode, "loss": loss, "loss_scale_px": loss_scale,
              "outlier_px": outlier_px, "distance_sigma_rel": distance_sigma, "views": [v.strip() for v in views.split(",") if v.strip()] if views else None}
    out = run_stage_cli(VERB, workspace=ws, params={k: v for k, v in params.items() if v is not None}, inputs=inputs,
                        output=output)
    emit(out, as_json)


COMMANDS = [calibrate_rig_cmd]

"""Stage ``calibrate-rig``: the landmarks of every identity + face model + nominal rig → one calibrated rig.

Library: :func:`reflectmm_cli.geometry_fit.calibrate.calibrate_from_captures` (docs/capture.md).  Inputs:
``capture`` (the preprocess-multipie artifacts of all identities), ``face_model``, optional ``rig`` (the nominal
table; default the packaged Multi-PIE table, whose image size must then match the images).  Outputs: the ``rig``
artifact (``<ws>/calibrate-rig/calibrate-rig.npz``) and beside it ``rig.toml``, the calibrated table that
``fit-geometry --rig`` reads (recipes: ``@calibrate-rig.outputs.rig``).  The fit's parameters are fields of
:class:`~reflectmm_cli.geometry_fit.calibrate.CalibrationConfig` (their defaults are its defaults).  With
``geometry`` (one preliminary fit-geometry output per capture, on this calibration's rig, same order) the cameras
no identity annotates are then registered jointly by the flash images
(:func:`reflectmm_cli.geometry_fit.joint.register_calibration`; options ``joint_*``, recorded only when given).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit.calibrate import FOCAL_MODES, LOSSES, CalibrationConfig
from reflectmm_cli.geometry_fit.joint import JointOptions, check_pairs, register_calibration
from reflectmm_cli.params import Param
from reflectmm_cli.progress import progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.stages.fit_geometry import LANDMARK_WEIGHTS

log = logging.getLogger("reflectmm")

VERB = "calibrate-rig"

_CFG = CalibrationConfig()
_JOINT = JointOptions()

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('capture', 'capture', upstream='preprocess-multipie', many=True, default=Default(
        check_given=True, missing='{path}: capture artifact not found (run preprocess-multipie first)')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', capture='capture', missing='{capture}: no face model: pass --face-model')),
    Input('rig', 'rig TOML', upstream='synth-multipie', help='the nominal table to start from',
          default=Default('rig', capture='capture', optional=True)),
    Input('geometry', 'geometry', upstream='fit-geometry', many=True,
          help='preliminary fits on this calibration\'s rig, one per capture in the same order: the cameras no '
               'identity annotates are then registered jointly by the flash images (docs/capture.md)'),
)


def _cfg(name: str, kind: str, **kw: Any) -> Param:
    """A Param for a CalibrationConfig field, its default declared once, there."""
    return Param.of_field(_CFG, name, kind, **kw)


PARAMS = (
    Param("focal", "float", _CFG.focal_px, range=(1e-3, None), unit="px",
          help="focal length of the images, if known (then kept fixed unless --focal-mode says otherwise)."),
    Param("focal_mode", "str", "auto", choices=("auto",) + FOCAL_MODES,
          help="auto: fixed if --focal is given, else one shared focal estimated."),
    _cfg("loss", "str", choices=LOSSES, help="robust loss of the landmark distances."),
    _cfg("loss_scale_px", "float", range=(0.0, None), low_open=True, option="--loss-scale", unit="px",
         help="scale of the robust loss."),
    _cfg("landmark_sigma_px", "float", range=(0.0, None), low_open=True, option="--landmark-sigma", unit="px",
         help="assumed landmark noise: balances landmarks against the shape/expression prior."),
    _cfg("outlier_px", "float", range=(0.0, None), low_open=True, unit="px",
         help="landmarks further than this from the fit are reported as outliers."),
    LANDMARK_WEIGHTS,
    _cfg("max_iters", "int", range=(1, 100000), option="", help="Levenberg-Marquardt iterations."),
    _cfg("distance_sigma_rel", "float", range=(0.0, None), option="--distance-sigma",
         help="relative uncertainty of the nominal table's distances: its size is fused with the faces' mean "
              "size by these weights (0 = the faces only; 0.01 for a measured rig)."),
    Param("views", "strs", None, help="cameras to calibrate, comma separated (default: every capture view)."),
    # not recorded unless given (rigs calibrated before it keep their bytes)
    Param("carry", "str", None, choices=("centres", "poses"),
          help="a camera no identity annotates keeps the nominal table's pose, moved by the similarity of the "
               "annotated cameras' centres or of their poses (centres and orientations: better with a guessed table, "
               "worse with an exact one; docs/capture.md) [default: centres]."),
    Param("carry_scale", "str", None, choices=("fit", "distances"),
          help="the carrying similarity's scale: fitted to the annotated cameras (fit) or the ratio of their "
               "distances from the head to the table's (distances) [default: fit]."),
    # the joint registration's options: not recorded unless given (rigs calibrated before them keep their bytes)
    Param("joint_sigma", "float", None, range=(0.0, None), low_open=True, unit="mm",
          help="with --geometry: prior σ of an unannotated camera's centre around its nominal place "
               f"(fit-geometry's --unmarked-sigma) [default: {_JOINT.center_sigma_mm:g}]."),
    Param("joint_rot_sigma", "float", None, range=(0.0, None), low_open=True, unit="deg",
          help=f"with --geometry: prior σ of its aim (fit-geometry's --unmarked-rot-sigma) "
               f"[default: {_JOINT.rot_sigma_deg:g}]."),
    Param("joint_blur", "floats", None, range=(0.0, None), unit="px",
          help="with --geometry: one registration round per Gaussian blur of the flash images "
               f"[default: {','.join(f'{b:g}' for b in _JOINT.blur_px)}]."),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name("rig.toml")]


def config_from_params(p: dict) -> CalibrationConfig:
    """The CalibrationConfig of resolved stage params (``focal_mode`` auto: fixed with a focal, else shared)."""
    mode = p["focal_mode"]
    if mode == "auto":  # a focal the user knows is kept; otherwise one shared focal is estimated
        mode = "fixed" if p.get("focal") is not None else "shared"
    return CalibrationConfig(focal=mode, focal_px=p.get("focal"), loss=p["loss"], loss_scale_px=p["loss_scale_px"],
                             landmark_sigma_px=p["landmark_sigma_px"], outlier_px=p["outlier_px"],
                             max_iters=p["max_iters"], distance_sigma_rel=p["distance_sigma_rel"],
                             group_weights=dict(p["landmark_weights"]) or None, carry=p.get("carry") or "centres",
                             carry_scale=p.get("carry_scale") or "fit")


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.geometry_fit.calibrate import calibrate_from_captures, write_rig_calibration

    p = ctx.params
    caps = ctx.input_list("capture")
    fm = ctx.input("face_model")
    rigs = ctx.input_list("rig", required=False)
    geos = ctx.input_list("geometry", required=False)
    if geos:
        check_pairs(caps, geos)
    cal = calibrate_from_captures(caps, fm, rigs[0] if rigs else None, config_from_params(p), views=p.get("views"),
                                  progress_fn=progress)
    if geos:  # the cameras no identity annotates: one pose each, by the flash images of every identity
        from reflectmm_cli.geometry import load_face_model
        from reflectmm_cli.geometry_fit.model import ShapeModel

        opts = JointOptions(center_sigma_mm=p.get("joint_sigma") or _JOINT.center_sigma_mm,
                            rot_sigma_deg=p.get("joint_rot_sigma") or _JOINT.rot_sigma_deg,
                            blur_px=tuple(float(b) for b in (p.get("joint_blur") or _JOINT.blur_px)))
        register_calibration(cal, ShapeModel.from_face_model(load_face_model(fm)), caps, geos, opts)
    _check_fit(cal.report, p["outlier_px"], fm)
    out = ctx.output_path()
    written = write_rig_calibration(cal, out, toml_path=out.with_name("rig.toml"), params=ctx.resolved_params(),
                                    inputs=ctx.input_refs(out.parent), producer=ctx.producer(),
                                    cache_key=ctx.cache_key)
    for a in cal.assumptions:
        log.info("calibrate-rig: assumed: %s", a)
    if cal.report["outliers"]:
        many = cal.report["outlier_fraction"] > WARN_OUTLIER_FRACTION
        log.warning("calibrate-rig: %d landmark(s) further than %.1f px from the fit (outliers%s; first: %s)%s",
                    cal.report["outliers"], p["outlier_px"],
                    f", {cal.report['outlier_fraction']:.0%} of those used" if many else "",
                    ", ".join(cal.report["outliers_first"][:5]), f": {_MISFIT_HINT}" if many else "")
    return written


#: More landmarks than this fraction further than ``outlier_px`` from the calibration: warned about with the likely
#: causes; more than :data:`MAX_OUTLIER_FRACTION`: refused, nothing written.  On the demo's dlib points (8
#: identities, 1938–2584 landmarks used) the model's own landmark vertices with the default weights (jaw 0.5)
#: leave 90 % outliers and faces 1.25x too large, with the jaw at weight 0 19 %, the embedded model with the jaw
#: 13 %, and the embedded model without it (the recipe) 0.1 % (docs/capture.md, "Landmarks from a detector").
WARN_OUTLIER_FRACTION = 0.1
MAX_OUTLIER_FRACTION = 0.5

_MISFIT_HINT = ("the landmarks read the face otherwise than the face model's landmark vertices (a detector's points "
                "need a face model embedded for that detector and --landmark-weights jaw=0: docs/capture.md, "
                "\"Landmarks from a detector\"), or the focal or the image size is wrong")


def _check_fit(report: dict, outlier_px: float, face_model: Path) -> None:
    """Refuse a calibration that most landmarks do not fit (:data:`MAX_OUTLIER_FRACTION`): one line, no rig."""
    frac = float(report.get("outlier_fraction") or 0.0)
    if frac > MAX_OUTLIER_FRACTION:
        raise ReflectmmError(
            f"calibrate-rig: {report['outliers']} of {report['landmarks_used']} landmarks ({frac:.0%}) are further "
            f"than {outlier_px:g} px from the calibration (median landmark RMS "
            f"{float(report['landmark_rmse_px_median']):.1f} px): {_MISFIT_HINT}; no rig written", face_model)


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="landmarks of every identity + face model + nominal rig -> one calibrated rig (rig artifact + "
                   "rig.toml)", inputs=INPUTS)

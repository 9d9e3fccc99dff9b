"""Stage ``fit-geometry``: capture + face model + rig → fitted shape, expression and cameras (``geometry``).

Library: :func:`reflectmm_cli.geometry_fit.identity.fit_identity` (docs/fit-geometry.md).  The fit's
parameters are the fields of :class:`~reflectmm_cli.geometry_fit.FitConfig` (their defaults are its defaults).
"""

from __future__ import annotations

import logging
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from reflectmm_cli.artifacts import check_identity, path_for_meta, read_artifact, write_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit import FitConfig
from reflectmm_cli.geometry_fit.identity import fit_identity, geometry_from_truth
from reflectmm_cli.geometry_fit.landmarks import GROUPS, format_group_weights, landmark_weights, parse_group_weights
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

log = logging.getLogger("reflectmm")

VERB = "fit-geometry"

_CFG = FitConfig()

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('capture', 'capture', upstream='preprocess-multipie', default=Default(
        check_given=True, missing='{path}: capture artifact not found (run preprocess-multipie first or pass --capture)')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', capture='capture', needs=('capture',), missing=(
              '{capture}: no face model: pass --face-model (a face-model artifact or a BFM .mat); none found '
              "beside the capture's dataset or at <workspace>/face_model.npz"))),
    Input('rig', 'rig TOML', upstream='calibrate-rig', default=Default('fit-rig', capture='capture', optional=True)),
    Input('landmarks', 'landmark files or folder', many=True),
    Input('truth', 'ground-truth NPZ', upstream='synth-multipie', help="only for the report's errors",
          default=Default('truth', capture='capture', optional=True)),
)


def _cfg(name: str, kind: str, **kw: Any) -> Param:
    """A Param for a FitConfig field, its default declared once, there."""
    return Param.of_field(_CFG, name, kind, **kw)


#: Per-group landmark weights (also calibrate-rig's).
LANDMARK_WEIGHTS = Param(
    "landmark_weights", "custom", {}, convert=parse_group_weights, multiple=True, metavar="GROUP=W",
    help=f"Weight of a landmark group ({', '.join(GROUPS)}; repeatable or comma separated); 0 leaves it out. "
         "jaw=0 for a detector's landmarks, whose jaw follows the silhouette.")

PARAMS = (
    Param("focal", "float", None, range=(1e-3, None), unit="px", help="focal length (default: rig)."),
    _cfg("landmark_iters", "int", range=(0, 100000), option="",
         help="L-BFGS iterations of the landmark stage (--iters sets it and photo_iters = iters // 10)."),
    _cfg("photo_rounds", "int", range=(0, 10),
         help="photometric rounds with refreshed visibility (0 = landmarks only)."),
    _cfg("photo_iters", "int", range=(0, 100000), option="", help="L-BFGS iterations per photometric round."),
    _cfg("landmark_sigma_px", "float", range=(1e-3, None), option="--landmark-sigma", unit="px",
         help="assumed landmark noise: balances landmarks against the priors."),
    LANDMARK_WEIGHTS,
    _cfg("jaw_contour", "bool",
         help="slide the cheek points 0-4 and 12-16 to each view's outline of the fitted face (landmark marching), "
              "for a detector's landmarks, whose jaw follows the silhouette; the chin (5-11) is left out. Not yet "
              "better than --landmark-weights jaw=0 with dlib (docs/fit-geometry.md)."),
    _cfg("contour_rounds", "int", range=(1, 20), option="",
         help="landmark fits with the jaw slid to the outline of the fit before (with --jaw-contour)."),
    _cfg("contour_gate_px", "float", range=(0.0, None), option="--contour-gate", unit="px",
         help="with --jaw-contour: a cheek point further than this across the outline after a slide is left out "
              "until the next slide (0 = keep every point)."),
    _cfg("contour_behind_mm", "float", range=(0.0, None), option="", unit="mm",
         help="how far behind the model's jaw ends (landmarks 0 and 16) the contour lines reach (with "
              "--jaw-contour)."),
    _cfg("huber_px", "float", range=(0.0, None), low_open=True, option="", unit="px",
         help="Huber threshold of the landmark residual."),
    _cfg("w_landmark", "float", range=(0.0, None), option="", help="weight of the landmark term."),
    _cfg("w_photo", "float", range=(0.0, None), help="weight of the photometric term."),
    _cfg("w_shape", "float", range=(0.0, None), option="", help="weight of the shape prior."),
    _cfg("w_exp", "float", range=(0.0, None), option="", help="weight of the expression prior."),
    _cfg("rig_sigma_mm", "float", range=(0.0, None), option="--rig-sigma", unit="mm",
         help="soft rig constraint σ (0 = free pose per view)."),
    _cfg("rig_rot_sigma_deg", "float", range=(0.0, None), option="--rig-rot-sigma", unit="deg",
         help="soft rig constraint on the camera orientations (0 = free aim per view; for a calibrated rig)."),
    _cfg("unmarked_sigma_mm", "float", range=(0.0, None), option="--unmarked-sigma", unit="mm",
         help="soft rig constraint σ of a view without landmarks (0 = --rig-sigma); wider when the rig's camera "
              "is only a nominal table's (calibrate-rig reports which)."),
    _cfg("unmarked_rot_sigma_deg", "float", range=(0.0, None), low_open=True, option="--unmarked-rot-sigma",
         unit="deg", help="prior on the aim of a view without landmarks: the rig's, moved by the head rotation."),
    _cfg("register_blur_px", "floats", range=(0.0, None), option="--register-blur", unit="px", allow_empty=True,
         help="views without landmarks: one round per blur registering their poses by the flash images, the face "
              "and the other views held (empty = off)."),
    _cfg("register_iters", "int", range=(0, 100000), option="", help="L-BFGS iterations per registration round."),
    _cfg("w_room", "float", range=(0.0, None), option="--w-room",
         help="views that their flash images registered are then refined with the room-light images' agreement "
              "across views beside the flash term, at this weight (0 = off; docs/fit-geometry.md)."),
    _cfg("register_room_blur_px", "floats", range=(0.0, None), option="--register-room-blur", unit="px",
         help="with --w-room: one refinement round per blur."),
    _cfg("joint_rounds", "int", range=(0, 20),
         help="after the registration: rounds of the flash term in which the registered views without landmarks "
              "follow the head at their registered places and their images shape the face beside the others' "
              "(0 = off; for a rig whose cameras the registration confirms: docs/fit-geometry.md, Views without "
              "landmarks)."),
    _cfg("joint_blur_px", "float", range=(0.0, None), option="--joint-blur", unit="px",
         help="Gaussian blur of the images in the joint rounds."),
    _cfg("joint_gate_mm", "float", range=(0.0, None), option="--joint-gate", unit="mm",
         help="a registered view without landmarks enters the joint rounds only within this distance of the rig."),
    _cfg("joint_register", "bool",
         help="register the views without landmarks again after each joint round (about 2 s more per round and "
              "identity)."),
    _cfg("joint_unmarked_weight", "float", range=(0.0, 1.0), option="--joint-unmarked-weight",
         help="weight of the images of the views without landmarks in the joint rounds, relative to the others' "
              "(their flashes count in full)."),
    _cfg("joint_max_landmark_rise", "float", range=(1.0, None), option="",
         help="the joint rounds are undone when they raise the median landmark RMS of the views with landmarks by "
              "more than this factor."),
    _cfg("uncertainty", "str", choices=("none", "unmarked", "all"),
         help="report the pose uncertainty of the views without landmarks (unmarked), of every view, or none "
              "(12 gradient evaluations per view)."),
    _cfg("head_sigma_mm", "float", range=(0.0, None), option="", unit="mm",
         help="prior on where the head sits in the rig frame (0 = off)."),
    _cfg("fit_expression", "bool", option="", help="fit expression coefficients."),
    _cfg("photo_vertices", "int", range=(1, 1000000), option="", help="skin vertices in the photometric term."),
    _cfg("photo_min_cos", "float", range=(-1.0, 1.0), option="", help="n·v threshold of the photometric term."),
    _cfg("photo_blur_px", "floats", range=(0.0, None), option="", unit="px",
         help="Gaussian blur of the images per photometric round."),
    _cfg("flash_rounds", "int", range=(0, 10),
         help="rounds of the flash term after the photometric rounds: each flash image as a point light at its "
              "flash, cast shadows and highlights left out, the albedo per vertex (0 = off; docs/fit-geometry.md)."),
    _cfg("flash_iters", "int", range=(0, 100000),
         help="L-BFGS iterations per flash round (the default stops short of convergence; more cost time and "
              "bring the faces closer: docs/fit-geometry.md, Schedule)."),
    _cfg("w_flash", "float", range=(0.0, None), help="weight of the flash term."),
    _cfg("flash_highlight_deg", "float", range=(0.0, 90.0), option="--flash-highlight", unit="deg",
         help="flash samples whose normal is within this angle of the half vector are left out (highlights)."),
    _cfg("flash_min_cos", "float", range=(0.0, 1.0), option="", help="n·l threshold of the flash term."),
    _cfg("flash_gains", "bool", option="", help="fit one relative intensity per flash."),
    _cfg("albedo", "str", choices=("auto", "texture", "per-vertex", "constant"),
         help="albedo of the photometric term (auto: the model's mean texture if it has one, else a per-vertex "
              "estimate; constant = one skin colour)."),
    _cfg("dtype", "str", choices=("float64", "float32"), help="precision of the optimisation (float32 for GPUs)."),
    _cfg("threads", "int", range=(1, 256), option="", invalidates_cache=False,
         help="torch intra-op threads during the fit."),
    Param("flash_intensity", "float", None, range=(0.0, None), low_open=True,
          help="radiant intensity of every flash (default: the rig table's values). On real data use 1: "
               "intensity and reflectance share one global scale."),
    Param("from_truth", "bool", False, option="",
          help="write the ground-truth geometry of the truth input instead of fitting."),
    Param("no_overlay", "bool", False, help="do not write the per-view overlay PNGs."),
)

_CONFIG_FIELDS = {f.name for f in fields(FitConfig)}


def _str_list(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    paths = [out]
    caps = ctx.inputs.get("capture") or []
    if ctx.params["from_truth"] or ctx.params["no_overlay"] or len(caps) != 1 or not Path(caps[0]).is_file():
        return paths
    try:  # read only the view names (the planner calls this; the OLAT stack can be large)
        with np.load(caps[0], allow_pickle=False) as npz:
            names = _str_list(npz["view_names"])
    except (OSError, KeyError, ValueError):
        return paths
    return paths + [ctx.output_path(f"{ctx.identity}_overlay_{n}", ".png") for n in names]


def config_from_params(params: dict) -> FitConfig:
    """The FitConfig of resolved stage params."""
    kw = {k: v for k, v in params.items() if k in _CONFIG_FIELDS and v is not None}
    if params.get("landmark_weights"):
        kw["group_weights"] = dict(params["landmark_weights"])
    for k in kw:  # the per-round blurs: tuples in the config, lists in params
        if isinstance(getattr(_CFG, k), tuple):
            kw[k] = tuple(float(x) for x in kw[k])
    return FitConfig(**kw)


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.geometry_fit.report import overlay

    identity = ctx.identity
    if not identity:
        raise ReflectmmError("fit-geometry runs per identity: give --id")
    out = ctx.output_path()
    t0 = time.perf_counter()
    capture_path = ctx.input("capture")
    truth_list = ctx.input_list("truth", required=False)
    truth_path = truth_list[0] if truth_list else None
    if ctx.params["from_truth"]:
        capture = check_identity(read_artifact(capture_path, "capture", members=(  # not the image stacks
            "view_names", "flash_ids", "image_size", "landmarks")), identity) if capture_path.is_file() else None
        kw: dict[str, Any] = {}
        if capture is not None:
            kw = {"view_names": _str_list(capture["view_names"]), "flash_ids": _str_list(capture["flash_ids"]),
                  "image_size": tuple(int(x) for x in np.asarray(capture["image_size"]).reshape(-1)[:2]),
                  "landmarks": np.asarray(capture["landmarks"], np.float64) if "landmarks" in capture.arrays
                  else None}
        fm_list = ctx.input_list("face_model", required=False)
        if fm_list:
            from reflectmm_cli.geometry import load_face_model

            kw["landmark_ids"] = load_face_model(fm_list[0]).landmarks
        rig_in = ctx.input_list("rig", required=False)
        arrays, report = geometry_from_truth(truth_path, rig_path=rig_in[0] if rig_in else None, **kw)
        report["truth_file"] = path_for_meta(truth_path, out)
        report["identity"] = str(identity)  # as a fitted geometry records it (later stages match by identity)
        write_artifact(out, "geometry", arrays, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                       producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
        log.info("fit-geometry %s: ground-truth geometry from %s (%d views)", identity, truth_path, report["views"])
        return [out]
    fm_path = ctx.input("face_model")
    rig_list = ctx.input_list("rig", required=False)
    lm_list = ctx.input_list("landmarks", required=False)
    cfg = config_from_params(ctx.params)
    if rig_list:
        check_rig_landmarks(identity, rig_list[0], fm_path, cfg)
    arrays, report, ex = fit_identity(capture_path, fm_path, identity, rig_path=rig_list[0] if rig_list else None,
                                      landmarks_dir=lm_list[0] if lm_list else None, focal=ctx.params.get("focal"),
                                      config=cfg, truth_path=truth_path, device=ctx.device,
                                      flash_intensity=ctx.params.get("flash_intensity"))
    if "truth_file" in report:
        report["truth_file"] = path_for_meta(truth_path, out)
    write_artifact(out, "geometry", arrays, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
    written = [out]
    if not ctx.params["no_overlay"]:
        model = ex["model"]
        scale = max(1, int(np.ceil(360 / max(ex["room"].shape[1], 1))))
        for v, name in enumerate(arrays["view_names"]):
            img = overlay(ex["room"][v], arrays["vertices"].astype(np.float64), model.triangles, arrays["K"][v],
                          arrays["R"][v], arrays["t"][v], arrays["landmarks_given"][v], arrays["landmarks_fit"][v],
                          origin=ex["origin"][v], scale=scale)
            written.append(write_png(ctx.output_path(f"{identity}_overlay_{name}", ".png"), img))
    pr = arrays["photo_residual"]
    photo = (f"photometric RMS {float(np.nanmedian(pr)):.4f}" if np.isfinite(pr).any()
             else "no room-light photometric rounds")
    lm_rms = arrays["landmark_rmse_px"]
    n_lm = int(np.isfinite(lm_rms).sum())
    msg = (f"fit-geometry {identity}: landmark RMS {np.nanmedian(lm_rms):.2f} px (median of "
           f"{n_lm} views with landmarks), {photo}")
    if "err_vertex_rmse_mm" in arrays:
        msg += (f"; vs truth: landmarks {np.median(arrays['err_landmark_px']):.2f} px, vertices "
                f"{float(arrays['err_vertex_rmse_mm']):.2f} mm RMS ({100 * float(arrays['err_vertex_rmse_iod']):.1f}% "
                f"of the inter-ocular distance), camera centres {np.median(arrays['err_cam_center_mm']):.1f} mm")
    log.info("%s; %.1f s", msg, time.perf_counter() - t0)
    _log_placement(identity, report["placement"])
    return written


def _same_file(a: Path, b: Path) -> bool:
    """The same file, or two files with the same bytes (a copied face model)."""
    import filecmp

    try:
        return a.resolve() == b.resolve() or filecmp.cmp(a, b, shallow=False)
    except OSError:
        return False


def check_rig_landmarks(identity: str, rig: Path, face_model: Path, cfg: FitConfig) -> bool:
    """Warn (one stderr line) when the rig is a calibration's whose landmark definition — face model, landmark
    weights — is not the fit's.  The calibration placed the cameras from landmarks on its model's vertices with its
    weights; a fit with other ones (a detector's jaw points on the model's fixed jaw vertices) turns and moves the
    head in the rig, 17–26 mm of vertex error on the demo's identity 003 against 1.0 mm (docs/fit-geometry.md,
    "A calibrated rig's landmark definition").  Returns True when they agree or the rig has no calibration."""
    from reflectmm_cli.artifacts import sha256_file
    from reflectmm_cli.workspace import rig_calibration

    try:
        cal = rig_calibration(rig)
    except ReflectmmError as e:
        log.warning("fit-geometry %s: cannot check the fit's landmark definition against the rig's calibration: %s",
                    identity, e)
        return False
    if cal is None:
        return True
    differ = []
    if not np.array_equal(landmark_weights(cfg.group_weights), landmark_weights(cal.landmark_weights)):
        ours, theirs = (format_group_weights(w) for w in (cfg.group_weights, cal.landmark_weights))
        differ.append(f"landmark weights {ours or 'the defaults'} where it used {theirs or 'the defaults'}"
                      + (f" (--landmark-weights {theirs})" if theirs else ""))
    if cal.face_model_sha256:  # the bytes it was calibrated with, wherever the fit's copy lives
        if sha256_file(face_model) != cal.face_model_sha256:
            differ.append(f"face model {face_model} where it used another"
                          + (f" ({cal.face_model_problem})" if cal.face_model_problem
                             else f", {cal.face_model} (--face-model)"))
    elif cal.face_model is not None and not _same_file(Path(face_model), cal.face_model):
        differ.append(f"face model {face_model} where it used {cal.face_model} (--face-model)")
    if differ:
        log.warning("fit-geometry %s: the rig %s was calibrated with another landmark definition: this fit has %s; "
                    "its face would sit in another frame than the rig's cameras", identity, rig, "; ".join(differ))
    return not differ


def _log_placement(identity: str, placement: list[dict]) -> None:
    """One stderr line per view that landmarks did not place: its evidence, residuals, uncertainty, rig shift."""
    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)

    for p in placement:
        if p["evidence"].startswith("landmarks"):
            continue
        log.info("fit-geometry %s: view %s placed by %s: photometric RMS %s, flash RMS %s, centre ±%s mm, aim ±%s°, "
                 "%s mm from the rig%s", identity, p["view"], p["evidence"], f(p["photo_residual"], ".4f"),
                 f(p["flash_residual"], ".4f"), f(p["center_sigma_mm"], ".1f"), f(p["rotation_sigma_deg"], ".2f"),
                 f(p["rig_shift_mm"], ".1f"), "; its images shaped the face" if p.get("shaped_face") else "")


STAGE = Stage(VERB, version=1, run=run, per_identity=True, outputs=_outputs, params=PARAMS,
              help="capture + face model + rig -> fitted shape/expression and cameras (geometry)", inputs=INPUTS)

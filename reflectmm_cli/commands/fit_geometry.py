"""``reflectmm fit-geometry``: capture + face model + rig → fitted shape, expression and cameras (``geometry``).

Library entry points: :func:`fit_identity` (a full fit from artifacts), :func:`geometry_from_truth`
(ground-truth geometry of a synthetic identity in the same format); the maths is in
:mod:`reflectmm_cli.fitting` (docs/fit-geometry.md).
"""

from __future__ import annotations

import logging
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

import click
import numpy as np

from reflectmm_cli.artifacts import Artifact, read_artifact, write_artifact, write_png
from reflectmm_cli.commands._common import (
    device_option,
    emit,
    json_option,
    output_option,
    run_stage_cli,
    workspace_option,
)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import StageContext, default_workspace, register_stage

log = logging.getLogger("reflectmm")

VERB = "fit-geometry"
GEOMETRY_KEYS = ("shape_coeffs", "exp_coeffs", "vertices", "view_names", "K", "R", "t", "image_size",
                 "cam_centers", "flash_ids", "flash_pos", "flash_intensity", "landmark_rmse_px", "photo_residual")


# --------------------------------------------------------------------------- inputs

def capture_root(capture: Artifact) -> Path | None:
    """The dataset folder a capture artifact was made from (its meta input of role ``root``), if it exists."""
    for ref in capture.meta.get("inputs", []):
        if ref.get("role") == "root" and capture.path is not None:
            p = (Path(capture.path).parent / ref.get("path", "")).resolve()
            if p.is_dir():
                return p
    return None


def _str_list(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


def _expected_landmark_file(capture: Artifact, identity: str, view: str) -> str:
    sess = str(capture.arrays.get("session", np.array("NN")))
    rec = str(capture.arrays.get("recording", np.array("RR")))
    return f"{identity}_{sess}_{rec}_{view.replace('_', '')}_00_lm.pts"


def gather_landmarks(capture: Artifact, identity: str, view_names: list[str], landmarks_dir: Path | None
                     ) -> tuple[np.ndarray, list[str]]:
    """(V, 68, 2) full-frame landmarks per view (``--landmarks DIR`` files first, else the capture's), and where
    each came from; a clear error naming the expected file for a view without any."""
    from reflectmm_cli.fitting.landmarks import find_landmark_file, read_landmarks

    V = len(view_names)
    out = np.full((V, 68, 2), np.nan)
    src = ["" for _ in range(V)]
    cap_lm = capture.arrays.get("landmarks")
    if cap_lm is not None:
        cap_lm = np.asarray(cap_lm, dtype=np.float64)
        if cap_lm.ndim != 3 or cap_lm.shape[0] != V or cap_lm.shape[2] != 2:
            raise ReflectmmError(f"capture landmarks have shape {cap_lm.shape}, expected ({V}, 68, 2)", capture.path)
        if cap_lm.shape[1] != 68:
            raise ReflectmmError(f"capture landmarks: expected 68 landmarks per view, found {cap_lm.shape[1]}",
                                 capture.path)
    for v, name in enumerate(view_names):
        if landmarks_dir is not None:
            f = find_landmark_file(landmarks_dir, name)
            if f is not None:
                out[v] = read_landmarks(f)
                src[v] = str(f)
                continue
        if cap_lm is not None and np.isfinite(cap_lm[v]).all(-1).sum() >= 6:
            out[v] = cap_lm[v]
            src[v] = "capture"
            continue
        where = f"in {landmarks_dir} or " if landmarks_dir is not None else ""
        raise ReflectmmError(
            f"no landmarks for view {name} of identity {identity}: expected "
            f"{_expected_landmark_file(capture, identity, name)} (or {name}.pts/.txt/.npy) {where}beside the "
            "images when running preprocess-multipie; pass --landmarks DIR", capture.path)
    return out, src


def view_cameras(rig, view_names: list[str], image_size: tuple[int, int], focal: float | None,
                 rig_path: Path | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """K, R, t and positions of the rig cameras of the views (--focal applied).

    A rig camera whose image size differs from the capture frame is refused unless ``focal`` is given: its focal
    length in pixels belongs to its own image size, and rescaling it to another frame would be a guess (a wrong
    focal biases distance, face size and flash irradiance; docs/fit-geometry.md)."""
    from reflectmm_cli.rig import RigCamera

    missing = [n for n in view_names if n not in rig.camera_names]
    if missing:
        raise ReflectmmError(f"view(s) {', '.join(missing)} of the capture are not cameras of the rig "
                             f"(rig cameras: {', '.join(rig.camera_names)})", rig_path or rig.source)
    W, H = image_size
    Ks, Rs, ts, pos = [], [], [], []
    for n in view_names:
        c = rig.camera(n)
        if (c.width, c.height) != (W, H):
            if focal is None:
                raise ReflectmmError(
                    f"rig camera {n} is {c.width}x{c.height} (focal {c.focal_px:g} px) but the capture frame is "
                    f"{W}x{H}: pass --focal PX for these images or a rig table of this size (calibrate-rig writes "
                    "one)", rig_path or rig.source)
            log.warning("fit-geometry: rig camera %s is %dx%d, the capture frame %dx%d: using --focal %g px and the "
                        "image centre", n, c.width, c.height, W, H, focal)
            c = RigCamera(c.name, c.position, c.look_at, c.up, float(focal), W, H)
        K = c.K.copy()
        if focal is not None:
            K[0, 0] = K[1, 1] = float(focal)
        Ks.append(K)
        Rs.append(c.R)
        ts.append(c.t)
        pos.append(c.center)
    return np.array(Ks), np.array(Rs), np.array(ts), np.array(pos)


def default_rig_for(capture: Artifact) -> Path | None:
    root = capture_root(capture)
    if root is not None and (root / "rig.toml").is_file():
        return root / "rig.toml"
    return None


def default_face_model_for(capture: Artifact, workspace: Path) -> Path | None:
    root = capture_root(capture)
    for p in ([root / "face_model.npz"] if root else []) + [workspace / "face_model.npz"]:
        if p.is_file():
            return p
    return None


def default_truth_for(capture: Artifact, identity: str) -> Path | None:
    root = capture_root(capture)
    if root is not None and (root / "truth" / f"{identity}.npz").is_file():
        return root / "truth" / f"{identity}.npz"
    return None


# --------------------------------------------------------------------------- library

def _truth_views(truth: Artifact, view_names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    names = _str_list(truth["camera_names"])
    missing = [n for n in view_names if n not in names]
    if missing:
        raise ReflectmmError(f"ground truth has no camera(s) {', '.join(missing)}", truth.path)
    idx = [names.index(n) for n in view_names]
    return (np.asarray(truth["K"], np.float64)[idx], np.asarray(truth["R"], np.float64)[idx],
            np.asarray(truth["t"], np.float64)[idx])


def _check_truth_size(truth: Artifact, image_size) -> None:
    tw, th = (int(x) for x in np.asarray(truth["image_size"]).reshape(-1)[:2])
    if (tw, th) != tuple(int(x) for x in image_size):
        raise ReflectmmError(f"ground truth was rendered at {tw}x{th} but the capture frame is "
                             f"{image_size[0]}x{image_size[1]}", truth.path)


def fit_identity(capture_path: Path, face_model_path: Path, identity: str, *, rig_path: Path | None = None,
                 landmarks_dir: Path | None = None, focal: float | None = None, config=None,
                 truth_path: Path | None = None, device: str = "cpu", flash_intensity: float | None = None
                 ) -> tuple[dict[str, np.ndarray], dict, Any]:
    """Fit one identity. Returns (geometry arrays, report dict, extras for the overlays)."""
    from reflectmm_cli.fitting import FitConfig, ShapeModel, ViewSet, fit_geometry, flash_positions, initial_poses
    from reflectmm_cli.fitting.report import truth_errors
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.rig import load_rig

    cfg = config or FitConfig()
    capture = read_artifact(capture_path, "capture")
    fm = load_face_model(face_model_path)
    model = ShapeModel.from_face_model(fm)
    rig = load_rig(rig_path)
    view_names = _str_list(capture["view_names"])
    flash_ids = _str_list(capture["flash_ids"])
    W, H = (int(x) for x in np.asarray(capture["image_size"]).reshape(-1)[:2])
    room = np.asarray(capture["room"], dtype=np.float32)
    if room.ndim != 4 or room.shape[0] != len(view_names) or room.shape[3] != 3:
        raise ReflectmmError(f"capture 'room' has shape {room.shape}, expected ({len(view_names)}, H, W, 3)",
                             capture_path)
    origin = np.asarray(capture.arrays.get("crop_origin", np.zeros((len(view_names), 2))), dtype=np.float64)
    lm, lm_src = gather_landmarks(capture, identity, view_names, landmarks_dir)
    K, R_rig, t_rig, rig_pos = view_cameras(rig, view_names, (W, H), focal, rig_path)
    R0, t0, init_rms = initial_poses(model.mean[model.landmarks], lm, K, R_rig, t_rig)
    log.info("fit-geometry %s: %d views, %d vertices, initial landmark RMS %s px", identity, len(view_names),
             model.n_vertices, " ".join(f"{e:.1f}" for e in init_rms))
    views = ViewSet(names=view_names, K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H), images=room,
                    rig_centers=rig_pos, image_origin=origin)
    fit = fit_geometry(model, views, cfg, device=device)
    fpos, fint, fsrc, rig_res = flash_positions(rig, flash_ids, view_names, fit.R, fit.t)
    if flash_intensity is not None:
        fint = np.full(len(flash_ids), float(flash_intensity))
    arrays: dict[str, np.ndarray] = {
        "shape_coeffs": fit.shape_coeffs, "exp_coeffs": fit.exp_coeffs,
        "vertices": fit.vertices.astype(np.float32), "view_names": np.array(view_names, dtype=str),
        "K": fit.K, "R": fit.R, "t": fit.t, "image_size": np.array([W, H], dtype=np.int32),
        "cam_centers": fit.cam_centers, "flash_ids": np.array(flash_ids, dtype=str), "flash_pos": fpos,
        "flash_intensity": fint, "landmark_rmse_px": fit.landmark_rmse_px, "photo_residual": fit.photo_residual,
        # extras (not in the minimal contract)
        "landmarks_given": lm, "landmarks_fit": fit.landmark_px, "landmark_rmse_init_px": init_rms,
        "visible_count": fit.visible_count, "rig_residual_mm": rig_res,
        "flash_from_view": np.array([s == "view" for s in fsrc]),
    }
    if fit.sh is not None:
        arrays["sh_room"] = fit.sh
    report: dict[str, Any] = {
        "identity": identity, "views": len(view_names),
        "landmark_rmse_px": [round(float(x), 4) for x in fit.landmark_rmse_px],
        "photo_residual": [None if not np.isfinite(x) else round(float(x), 6) for x in fit.photo_residual],
        "landmark_sources": lm_src, "history": fit.history, "config": cfg.as_dict(),
        "rig_residual_mm": [round(float(x), 3) for x in rig_res],
        "flash_intensity_note": ("radiant intensity " + ("set by --flash-intensity" if flash_intensity is not None
                                                         else "from the rig table")
                                 + " (linear pixel units x mm^2); on real data one global scale ambiguity with the "
                                   "reflectance (docs/pipeline.md)"),
    }
    if truth_path is not None:
        truth = read_artifact(truth_path, "synth-truth")
        tK, tR, tt_ = _truth_views(truth, view_names)
        _check_truth_size(truth, (W, H))
        errs = truth_errors(fit.vertices, fit.K, fit.R, fit.t, np.asarray(truth["vertices"], np.float64), tK, tR,
                            tt_, model.landmarks)
        arrays.update(errs)
        report["truth"] = {k: (np.round(v, 4).tolist() if np.ndim(v) else round(float(v), 5))
                           for k, v in errs.items()}
        report["truth_file"] = str(truth_path)
    extras = {"model": model, "fm": fm, "room": room, "origin": origin, "fit": fit}
    return arrays, report, extras


def geometry_from_truth(truth_path: Path, *, view_names: list[str] | None = None, flash_ids: list[str] | None = None,
                        image_size: tuple[int, int] | None = None, landmarks: np.ndarray | None = None,
                        landmark_ids: np.ndarray | None = None, rig_path: Path | None = None
                        ) -> tuple[dict[str, np.ndarray], dict]:
    """The ground-truth geometry of a synthetic identity as ``geometry`` arrays (same keys as a fit).

    Views / flashes default to the ones rendered (truth meta); ``image_size`` (the capture frame) must equal the
    rendered size; ``landmarks`` (V, 68, 2) gives ``landmark_rmse_px`` of the
    true geometry against them (NaN otherwise).  ``truth_path`` may also be a registered scan (``.ply``/``.obj``
    …, the face model's topology, mm) with the cameras and flashes of the rig table ``rig_path``
    (:mod:`reflectmm_cli.evaluation.external`).
    """
    from reflectmm_cli.evaluation.external import MESH_SUFFIXES, geometry_truth_arrays

    if Path(truth_path).suffix.lower() in MESH_SUFFIXES:
        if rig_path is None:
            raise ReflectmmError("a mesh as ground truth needs its cameras: pass --rig CAMERAS.toml", truth_path)
        from reflectmm_cli.rig import load_rig

        t_arrays, t_meta = geometry_truth_arrays(truth_path, load_rig(rig_path))
        truth = Artifact("synth-truth", t_arrays, t_meta, Path(truth_path))
    else:
        truth = read_artifact(truth_path, "synth-truth")
    names = view_names or [str(x) for x in truth.meta.get("views", _str_list(truth["camera_names"]))]
    fl_all = _str_list(truth["flash_ids"])
    fls = flash_ids or [str(x) for x in truth.meta.get("flashes", fl_all)]
    K, R, t = _truth_views(truth, names)
    W, H = (int(x) for x in np.asarray(truth["image_size"]).reshape(-1)[:2])
    if image_size is not None:
        _check_truth_size(truth, image_size)
    missing = [f for f in fls if f not in fl_all]
    if missing:
        raise ReflectmmError(f"ground truth has no flash(es) {', '.join(missing)}", truth_path)
    fi = [fl_all.index(f) for f in fls]
    verts = np.asarray(truth["vertices"], np.float64)
    V = len(names)
    rmse = np.full(V, np.nan)
    lm_fit = np.full((V, 68, 2), np.nan)
    from reflectmm_cli.fitting.camera_math import camera_centers, project

    lm_ids = None if landmark_ids is None else np.asarray(landmark_ids, dtype=np.int64)
    if landmarks is not None and lm_ids is None:
        # the landmark vertex ids are not stored in the truth; recover them from the recorded 2-D landmarks
        lm_ids = _truth_landmark_ids(truth)
    if lm_ids is not None:
        for v in range(V):
            lm_fit[v] = project(verts[lm_ids], K[v], R[v], t[v])[0]
            if landmarks is not None:
                e = np.linalg.norm(lm_fit[v] - landmarks[v], axis=-1)
                ok = np.isfinite(e)
                rmse[v] = float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else np.nan
    arrays = {
        "shape_coeffs": np.asarray(truth["shape_coeffs"], np.float64),
        "exp_coeffs": np.asarray(truth["exp_coeffs"], np.float64), "vertices": verts.astype(np.float32),
        "view_names": np.array(names, dtype=str), "K": K, "R": R, "t": t,
        "image_size": np.array([W, H], dtype=np.int32), "cam_centers": camera_centers(R, t),
        "flash_ids": np.array(fls, dtype=str), "flash_pos": np.asarray(truth["flash_pos"], np.float64)[fi],
        "flash_intensity": np.asarray(truth["flash_intensity"], np.float64)[fi],
        "landmark_rmse_px": rmse, "photo_residual": np.full(V, np.nan),
    }
    return arrays, {"source": "ground truth", "truth_file": str(truth_path), "views": V}


def _truth_landmark_ids(truth: Artifact) -> np.ndarray | None:
    """Landmark vertex ids of a synth-truth artifact: for each landmark, the vertex whose projection in the first
    recorded view is nearest to the recorded (noise-free when landmark_noise = 0) 2-D landmark."""
    if "landmarks_2d" not in truth.arrays or "landmark_views" not in truth.arrays:
        return None
    from reflectmm_cli.fitting.camera_math import project

    names = _str_list(truth["camera_names"])
    lv = _str_list(truth["landmark_views"])
    verts = np.asarray(truth["vertices"], np.float64)
    score = np.zeros((68, len(verts)))
    for k, name in enumerate(lv):
        i = names.index(name)
        uv, _ = project(verts, np.asarray(truth["K"])[i], np.asarray(truth["R"])[i], np.asarray(truth["t"])[i])
        lm = np.asarray(truth["landmarks_2d"], np.float64)[k]
        score += ((uv[None] - lm[:, None]) ** 2).sum(-1)
    return np.argmin(score, axis=1)


# --------------------------------------------------------------------------- stage

def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    paths = [out]
    caps = ctx.inputs.get("capture") or []
    if ctx.param("from_truth") or ctx.param("no_overlay") or len(caps) != 1 or not Path(caps[0]).is_file():
        return paths
    try:  # read only the view names (the planner calls this; the OLAT stack can be large)
        with np.load(caps[0], allow_pickle=False) as npz:
            names = _str_list(npz["view_names"])
    except (OSError, KeyError, ValueError):
        return paths
    return paths + [ctx.output_path(f"{ctx.identity}_overlay_{n}", ".png") for n in names]


def _config_from_params(params: dict) -> Any:
    from reflectmm_cli.fitting import FitConfig

    names = {f.name for f in fields(FitConfig)}
    kw = {k: v for k, v in params.items() if k in names and v is not None}
    if "photo_blur_px" in kw:
        kw["photo_blur_px"] = tuple(float(x) for x in kw["photo_blur_px"])
    try:
        return FitConfig(**kw)
    except TypeError as exc:  # pragma: no cover - guarded by the names filter
        raise ReflectmmError(f"fit-geometry: bad parameters ({exc})") from None


@register_stage(VERB, version=1, per_identity=True, outputs=_outputs,
                help="capture + face model + rig -> fitted shape/expression and cameras (geometry)")
def run_fit_geometry(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.fitting.report import overlay

    identity = ctx.identity
    if not identity:
        raise ReflectmmError("fit-geometry runs per identity: give --id")
    out = ctx.output_path()
    t0 = time.perf_counter()
    capture_path = ctx.input("capture")
    truth_list = ctx.input_list("truth", required=False)
    truth_path = truth_list[0] if truth_list else None
    if ctx.param("from_truth"):
        capture = read_artifact(capture_path, "capture") if capture_path.is_file() else None
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
        write_artifact(out, "geometry", arrays, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                       producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
        log.info("fit-geometry %s: ground-truth geometry from %s (%d views)", identity, truth_path, report["views"])
        return [out]
    fm_path = ctx.input("face_model")
    rig_list = ctx.input_list("rig", required=False)
    lm_list = ctx.input_list("landmarks", required=False)
    cfg = _config_from_params(ctx.params)
    arrays, report, ex = fit_identity(capture_path, fm_path, identity, rig_path=rig_list[0] if rig_list else None,
                                      landmarks_dir=lm_list[0] if lm_list else None, focal=ctx.param("focal"),
                                      config=cfg, truth_path=truth_path, device=ctx.device,
                                      flash_intensity=ctx.param("flash_intensity"))
    write_artifact(out, "geometry", arrays, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
    written = [out]
    if not ctx.param("no_overlay"):
        model = ex["model"]
        scale = max(1, int(np.ceil(360 / max(ex["room"].shape[1], 1))))
        for v, name in enumerate(arrays["view_names"]):
            img = overlay(ex["room"][v], arrays["vertices"].astype(np.float64), model.triangles, arrays["K"][v],
                          arrays["R"][v], arrays["t"][v], arrays["landmarks_given"][v], arrays["landmarks_fit"][v],
                          origin=ex["origin"][v], scale=scale)
            written.append(write_png(ctx.output_path(f"{identity}_overlay_{name}", ".png"), img))
    pr = arrays["photo_residual"]
    photo = float(np.nanmedian(pr)) if np.isfinite(pr).any() else float("nan")
    msg = (f"fit-geometry {identity}: landmark RMS {np.median(arrays['landmark_rmse_px']):.2f} px (median of "
           f"{len(arrays['view_names'])} views), photometric RMS {photo:.4f}")
    if "err_vertex_rmse_mm" in arrays:
        msg += (f"; vs truth: landmarks {np.median(arrays['err_landmark_px']):.2f} px, vertices "
                f"{float(arrays['err_vertex_rmse_mm']):.2f} mm RMS ({100 * float(arrays['err_vertex_rmse_iod']):.1f}% "
                f"of the inter-ocular distance), camera centres {np.median(arrays['err_cam_center_mm']):.1f} mm")
    log.info("%s; %.1f s", msg, time.perf_counter() - t0)
    return written


@click.command(VERB)
@click.option("--id", "identity", required=True, help="Identity (e.g. 042).")
@click.option("--capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="capture artifact (default <ws>/preprocess-multipie/<id>.npz).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model: face-model artifact or BFM09/Deep3DFaceRecon .mat (default: face_model.npz of the "
                   "capture's dataset folder, else <ws>/face_model.npz).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="rig table TOML (default: rig.toml of the capture's dataset folder, else the packaged "
                   "Multi-PIE rig).")
@click.option("--landmarks", "landmarks_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="folder with landmark files <view>.{pts,txt,npy} or *_<CCC>_00_lm.{pts,txt,npy} "
                   "(full-frame pixels; default: the landmarks stored in the capture).")
@click.option("--focal", type=click.FloatRange(min=1e-3), default=None, help="focal length in px (default: rig).")
@click.option("--iters", type=click.IntRange(0, None), default=None,
              help="L-BFGS iterations of the landmark stage (default 400; the photometric rounds scale with it).")
@click.option("--photo-rounds", type=click.IntRange(0, 10), default=None,
              help="photometric rounds with refreshed visibility (default 2; 0 = landmarks only).")
@click.option("--w-photo", type=click.FloatRange(min=0), default=None, help="weight of the photometric term.")
@click.option("--rig-sigma", type=click.FloatRange(min=0), default=None,
              help="soft rig constraint σ in mm (default 10; 0 = free pose per view).")
@click.option("--landmark-sigma", type=click.FloatRange(min=1e-3), default=None,
              help="assumed landmark noise in px (default 1): balances landmarks against the priors.")
@click.option("--truth", "truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="synth-truth artifact to report errors against (default: <dataset>/truth/<id>.npz if present).")
@click.option("--from-truth", "from_truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the ground-truth geometry of this synth-truth artifact (or of a registered scan .ply/.obj "
                   "with --rig CAMERAS.toml) instead of fitting.")
@click.option("--flash-intensity", type=click.FloatRange(min=0, min_open=True), default=None,
              help="radiant intensity of every flash (default: the rig table's values). On real data use 1: "
                   "intensity and reflectance share one global scale.")
@click.option("--albedo", type=click.Choice(["auto", "texture", "per-vertex", "constant"]), default=None,
              help="albedo of the photometric term (default auto: the model's mean texture if it has one, else a "
                   "per-vertex estimate; constant = one skin colour).")
@click.option("--dtype", type=click.Choice(["float64", "float32"]), default=None,
              help="precision of the optimisation (default float64; float32 for GPUs).")
@click.option("--no-overlay", is_flag=True, help="do not write the per-view overlay PNGs.")
@device_option
@workspace_option
@output_option
@json_option
def fit_geometry_cmd(identity, capture, face_model, rig, landmarks_dir, focal, iters, photo_rounds, w_photo,
                     rig_sigma, landmark_sigma, truth, from_truth, flash_intensity, albedo, dtype, no_overlay,
                     device, workspace, output, as_json):
    """Fit one identity's shape, expression and per-view cameras to its landmarks and room-light images.

    Writes the `geometry` artifact (<ws>/fit-geometry/<id>.npz) and one overlay PNG per view.
    """
    ws = (workspace or default_workspace()).resolve()
    capture = capture or ws / "preprocess-multipie" / f"{identity}.npz"
    params: dict[str, Any] = {}
    inputs: dict[str, list[Path]] = {}
    if from_truth is not None:
        inputs["truth"] = [from_truth]
        if Path(capture).exists():
            inputs["capture"] = [capture]
            face_model = face_model or default_face_model_for(read_artifact(capture, "capture"), ws)
        if face_model is not None:
            inputs["face_model"] = [face_model]
        if rig is not None:
            inputs["rig"] = [rig]
        params["from_truth"] = True
        paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=params, inputs=inputs, output=output,
                              device=device)
        emit(paths, as_json)
        return
    if not Path(capture).exists():
        raise ReflectmmError("capture artifact not found (run preprocess-multipie first or pass --capture)", capture)
    cap = read_artifact(capture, "capture")
    if face_model is None:
        face_model = default_face_model_for(cap, ws)
        if face_model is None:
            raise ReflectmmError("no face model: pass --face-model (a face-model artifact or a BFM .mat); none found "
                                 "beside the capture's dataset or at <workspace>/face_model.npz", capture)
    rig = rig or default_rig_for(cap)
    truth = truth or default_truth_for(cap, identity)
    inputs = {"capture": [capture], "face_model": [face_model]}
    if rig is not None:
        inputs["rig"] = [rig]
    if truth is not None:
        inputs["truth"] = [truth]
    if landmarks_dir is not None:
        inputs["landmarks"] = [landmarks_dir]
    for key, val in (("focal", focal), ("photo_rounds", photo_rounds), ("w_photo", w_photo),
                     ("rig_sigma_mm", rig_sigma), ("landmark_sigma_px", landmark_sigma),
                     ("flash_intensity", flash_intensity), ("albedo", albedo), ("dtype", dtype)):
        if val is not None:
            params[key] = val
    if iters is not None:
        params["landmark_iters"] = iters
        params["photo_iters"] = max(1, iters // 10) if iters else 0
    if no_overlay:
        params["no_overlay"] = True
    paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=params, inputs=inputs, output=output,
                          device=device)
    emit(paths, as_json)


COMMANDS = [fit_geometry_cmd]

"""Fit one identity's geometry from artifacts: the library entry of ``fit-geometry`` (docs/fit-geometry.md).

:func:`fit_identity` reads a capture, a face model and a rig, fits (:func:`.fit.fit_geometry`) and returns the
``geometry`` arrays and a report; :func:`geometry_from_truth` gives the ground-truth geometry of a synthetic
identity in the same format.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from reflectmm_cli.artifacts import Artifact, check_identity, read_artifact
from reflectmm_cli.capture.images import check_finite_images
from reflectmm_cli.errors import ReflectmmError

log = logging.getLogger("reflectmm")

__all__ = ["GEOMETRY_KEYS", "fit_identity", "geometry_from_truth", "gather_landmarks", "view_cameras",
           "placement_report"]

GEOMETRY_KEYS = ("shape_coeffs", "exp_coeffs", "vertices", "view_names", "K", "R", "t", "image_size",
                 "cam_centers", "flash_ids", "flash_pos", "flash_intensity", "landmark_rmse_px", "photo_residual")


# --------------------------------------------------------------------------- inputs

def _str_list(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


def _expected_landmark_file(capture: Artifact, identity: str, view: str) -> str:
    sess = str(capture.arrays.get("session", np.array("NN")))
    rec = str(capture.arrays.get("recording", np.array("RR")))
    return f"{identity}_{sess}_{rec}_{view.replace('_', '')}_00_lm.pts"


def gather_landmarks(capture: Artifact, identity: str, view_names: list[str], landmarks_dir: Path | None
                     ) -> tuple[np.ndarray, list[str]]:
    """(V, 68, 2) full-frame landmarks per view (``--landmarks DIR`` files first, else the capture's; NaN for a
    view without any, which the fit places by the rig and the images), and where each came from (``""`` for none);
    a clear error naming the expected file when no view of the identity has landmarks."""
    from reflectmm_cli.geometry_fit.landmarks import find_landmark_file
    from reflectmm_cli.landmarks import check_in_frame, check_view_landmarks, read_landmarks

    V = len(view_names)
    size = tuple(int(x) for x in np.asarray(capture["image_size"]).reshape(-1)[:2])
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
                out[v] = check_in_frame(read_landmarks(f), *size, f)
                src[v] = str(f)
                continue
        if cap_lm is not None and check_view_landmarks(cap_lm[v], name, *size, capture.path):
            out[v] = cap_lm[v]
            src[v] = "capture"
    if not any(src):
        name = view_names[0]
        where = f"in {landmarks_dir} or " if landmarks_dir is not None else ""
        raise ReflectmmError(
            f"no landmarks for any view of identity {identity} (at least one is needed): expected e.g. "
            f"{_expected_landmark_file(capture, identity, name)} (or {name}.pts/.txt/.npy) {where}beside the "
            "images when running preprocess-multipie (detect-landmarks writes them); pass --landmarks DIR",
            capture.path)
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


def _flash_inputs(capture: Artifact, capture_path: Path, rig, view_names: list[str], flash_ids: list[str],
                  hw: tuple[int, int], flash_intensity: float | None) -> dict[str, np.ndarray]:
    """The flash images of a capture and where each flash sits, for the fit's flash term (``ViewSet`` fields)."""
    from reflectmm_cli.geometry_fit.init import flash_mounts

    if "olat" not in capture.arrays:
        raise ReflectmmError("the flash term needs the capture's flash images ('olat'), which it does not have",
                             capture_path)
    olat = np.asarray(capture["olat"])
    V, F = len(view_names), len(flash_ids)
    if olat.shape != (V, F, *hw, 3):
        raise ReflectmmError(f"capture 'olat' has shape {olat.shape}, expected {(V, F, *hw, 3)}", capture_path)
    check_finite_images(olat, "olat", view_names, capture_path, flash_ids)
    fview, fpos, fint = flash_mounts(rig, flash_ids, view_names)
    fpos[fview >= 0] = np.nan  # these move with their fitted view
    if flash_intensity is not None:
        fint = np.full(F, float(flash_intensity))
    sat = capture.arrays.get("saturated")
    sat = None if sat is None else np.asarray(sat, dtype=bool)
    if sat is not None and sat.shape != olat.shape[:4]:
        raise ReflectmmError(f"capture 'saturated' has shape {sat.shape}, expected {olat.shape[:4]}", capture_path)
    return {"flash_images": olat, "flash_view": fview, "flash_rig_pos": fpos, "flash_intensity": fint,
            "flash_saturated": sat}


# --------------------------------------------------------------------------- library

def _num(x, nd: int = 3):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def placement_report(view_names: list[str], fit) -> list[dict]:
    """Per view: the evidence that placed it, its residuals, its pose uncertainty and its shift from the rig
    (:mod:`.placement`); JSON-ready."""
    out = []
    for v, name in enumerate(view_names):
        def arr(a, nd=4):
            return None if a is None else _num(a[v], nd)
        out.append({"view": name, "evidence": fit.evidence[v], "landmark_rmse_px": arr(fit.landmark_rmse_px, 3),
                    "photo_residual": arr(fit.photo_residual, 5), "flash_residual": arr(fit.flash_residual, 5),
                    "center_sigma_mm": arr(fit.center_sigma_mm, 2),
                    "rotation_sigma_deg": arr(fit.rotation_sigma_deg, 3),
                    "rig_shift_mm": arr(fit.rig_shift_mm, 2),
                    "registered_by_flash": None if fit.evidence[v].startswith("landmarks") or fit.registered is None
                    else bool(fit.registered[v]),
                    "refined_by_room": None if fit.evidence[v].startswith("landmarks") or fit.room_refined is None
                    else bool(fit.room_refined[v]),
                    "shaped_face": None if fit.evidence[v].startswith("landmarks") or fit.joined is None
                    else bool(fit.joined[v])})
    return out


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
    from reflectmm_cli.geometry_fit import FitConfig, ShapeModel, ViewSet, fit_geometry, flash_positions, initial_poses
    from reflectmm_cli.geometry_fit.init import place_by_rig
    from reflectmm_cli.geometry_fit.report import truth_errors
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.geometry_fit.embedding import correct_by_face_model
    from reflectmm_cli.rig import load_rig

    cfg = config or FitConfig()
    capture = check_identity(read_artifact(capture_path, "capture"), identity)
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
    check_finite_images(room, "room", view_names, capture_path)
    origin = np.asarray(capture.arrays.get("crop_origin", np.zeros((len(view_names), 2))), dtype=np.float64)
    lm, lm_src = gather_landmarks(capture, identity, view_names, landmarks_dir)
    lm, bias_note = correct_by_face_model(lm, view_names, fm.info, face_model_path)
    if bias_note:
        log.info("fit-geometry %s: %s", identity, bias_note)
    K, R_rig, t_rig, rig_pos = view_cameras(rig, view_names, (W, H), focal, rig_path)
    R0, t0, init_rms = initial_poses(model.mean[model.landmarks], lm, K, R_rig, t_rig)
    marked = np.array([bool(s) for s in lm_src])
    if not marked.all():
        R0, t0, _, _ = place_by_rig(R0, t0, marked, R_rig, t_rig)
        init_rms[~marked] = np.nan
        unmarked = ", ".join(n for n, m in zip(view_names, marked) if not m)
        if (cfg.flash_rounds <= 0 or cfg.w_flash <= 0) and "olat" in capture.arrays:
            log.warning("fit-geometry %s: no landmarks for view(s) %s and no flash rounds: those views stay where the "
                        "rig puts them under the head; --flash-rounds 3 registers them by their flash images "
                        "(docs/fit-geometry.md, \"Views without landmarks\")", identity, unmarked)
        else:
            log.info("fit-geometry %s: no landmarks for view(s) %s: placed by the rig and the other views, refined "
                     "by the image terms", identity, unmarked)
    log.info("fit-geometry %s: %d views, %d vertices, initial landmark RMS %s px", identity, len(view_names),
             model.n_vertices, " ".join(f"{e:.1f}" for e in init_rms))
    flash_kw = _flash_inputs(capture, capture_path, rig, view_names, flash_ids, room.shape[1:3], flash_intensity) \
        if cfg.flash_rounds > 0 and cfg.w_flash > 0 else {}
    views = ViewSet(names=view_names, K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H), images=room,
                    rig_centers=rig_pos, image_origin=origin, rig_R=R_rig, **flash_kw)
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
        "view_evidence": np.array(fit.evidence, dtype=str), "rig_shift_mm": fit.rig_shift_mm,
    }
    if fit.center_sigma_mm is not None:
        arrays["center_sigma_mm"] = fit.center_sigma_mm
        arrays["rotation_sigma_deg"] = fit.rotation_sigma_deg
    if fit.sh is not None:
        arrays["sh_room"] = fit.sh
    if fit.flash_residual is not None:
        arrays["flash_residual"] = fit.flash_residual
        arrays["flash_gain"] = fit.flash_gain
    report: dict[str, Any] = {
        "identity": identity, "views": len(view_names),
        "landmark_rmse_px": [round(float(x), 4) for x in fit.landmark_rmse_px],
        "photo_residual": [None if not np.isfinite(x) else round(float(x), 6) for x in fit.photo_residual],
        "landmark_sources": lm_src, "landmark_view_bias": bias_note, "history": fit.history, "config": cfg.as_dict(),
        "placement": placement_report(view_names, fit),
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
    from reflectmm_cli.geometry.camera import camera_centers, project

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
    from reflectmm_cli.geometry.camera import project

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

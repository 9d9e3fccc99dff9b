"""Pose initialisation (rig nominal pose refined by PnP) and the rig → model-space transform for flashes."""

from __future__ import annotations

import logging

import numpy as np

from reflectmm_cli.geometry import align
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.geometry.rotations import nearest_rotation

log = logging.getLogger("reflectmm")


def pnp_pose(object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray, R0: np.ndarray, t0: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, float]:
    """Refine a pose (R0, t0) with ``cv2.solvePnP`` (iterative LM from the initial guess) on the finite
    correspondences; keep the better of the initial and refined pose by reprojection RMS.

    Returns (R, t, rms_px).
    """
    import cv2

    ok = np.isfinite(image_points).all(-1) & np.isfinite(object_points).all(-1)
    obj = np.ascontiguousarray(object_points[ok], dtype=np.float64)
    img = np.ascontiguousarray(image_points[ok], dtype=np.float64)

    def rms(R, t):
        if len(obj) == 0:
            return np.nan
        uv, z = project(obj, K, R, t)
        if np.any(z <= 0):
            return np.inf
        return float(np.sqrt(((uv - img) ** 2).sum(-1).mean()))

    best = (R0, t0, rms(R0, t0))
    if len(obj) < 6:
        return best
    rvec0, _ = cv2.Rodrigues(np.asarray(R0, dtype=np.float64))
    tvec0 = np.asarray(t0, dtype=np.float64).reshape(3, 1).copy()
    try:
        found, rvec, tvec = cv2.solvePnP(obj, img, np.asarray(K, dtype=np.float64), None, rvec0.copy(), tvec0,
                                         useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error as exc:  # pragma: no cover - degenerate input
        log.debug("solvePnP failed: %s", exc)
        return best
    if found:
        R = cv2.Rodrigues(rvec)[0]
        t = tvec.reshape(3)
        e = rms(R, t)
        if e < best[2]:
            best = (R, t, e)
    return best


def initial_poses(landmarks3d: np.ndarray, landmarks2d: np.ndarray, K: np.ndarray, R_rig: np.ndarray,
                  t_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-view initial (R, t) from the rig's nominal pose refined by PnP on the mean-shape landmarks.

    landmarks3d (68, 3) model space; landmarks2d (V, 68, 2); K, R_rig (V, 3, 3); t_rig (V, 3).
    Returns R (V, 3, 3), t (V, 3), rms (V,) px of the initial pose.
    """
    V = len(K)
    R = np.zeros((V, 3, 3))
    t = np.zeros((V, 3))
    err = np.zeros(V)
    for v in range(V):
        R[v], t[v], err[v] = pnp_pose(landmarks3d, landmarks2d[v], K[v], R_rig[v], t_rig[v])
    return R, t, err


def place_by_rig(R: np.ndarray, t: np.ndarray, placed: np.ndarray, R_rig: np.ndarray, t_rig: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Poses of the views without landmarks from the rig and the views with them.

    R (V, 3, 3), t (V, 3): model → camera poses, valid where ``placed`` (V,) bool; R_rig, t_rig: the rig's
    world → camera poses.  The head pose (rig → model, ``x_model = Rh x_rig + th``) is estimated from the placed
    views — its rotation the rotation nearest the mean of ``R_vᵀ R_rig,v``, its translation the mean of
    ``c_v − Rh c_rig,v`` over their centres — and every other view is the rig's camera moved by it:
    ``R_v = R_rig,v Rhᵀ``, centre ``Rh c_rig,v + th``.

    Returns (R (V, 3, 3), t (V, 3) with the unplaced views filled in, Rh (3, 3), th (3,)).
    """
    placed = np.asarray(placed, dtype=bool)
    if not placed.any():
        raise ValueError("place_by_rig needs at least one placed view")
    R, t = np.array(R, dtype=np.float64), np.array(t, dtype=np.float64)
    Rh = nearest_rotation(np.einsum("vji,vjk->vik", R[placed], R_rig[placed]).mean(0))
    c_rig = camera_centers(R_rig, t_rig)
    th = (camera_centers(R[placed], t[placed]) - c_rig[placed] @ Rh.T).mean(0)
    for v in np.nonzero(~placed)[0]:
        R[v] = R_rig[v] @ Rh.T
        t[v] = -R[v] @ (Rh @ c_rig[v] + th)
    return R, t, Rh, th


def rigid_align(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid transform (Kabsch, no scale) with ``dst ≈ src @ Rᵀ + t``
    (:func:`reflectmm_cli.geometry.align.rigid_align`, plus the residuals).

    Returns (R (3, 3), t (3,), residual (n,) distances after alignment).  Needs ≥ 3 non-collinear points.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    R, t, _ = align.rigid_align(src, dst)
    res = np.linalg.norm(src @ R.T + t - dst, axis=-1)
    return R, t, res


def flash_mounts(rig, flash_ids: list[str], view_names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each flash sits: (index of the fitted view whose camera carries it, −1 if none (F,); its rig-frame
    position (F, 3) — the carrying camera's for an attached flash, the table's for a free-standing one; its
    radiant intensity (F,))."""
    view = np.full(len(flash_ids), -1, dtype=np.int64)
    pos = np.zeros((len(flash_ids), 3))
    inten = np.zeros(len(flash_ids))
    for i, fid in enumerate(flash_ids):
        fl = rig.flash(fid)
        inten[i] = fl.intensity
        pos[i] = rig.camera(fl.camera).position if fl.camera is not None else fl.position
        if fl.camera is not None and fl.camera in view_names:
            view[i] = view_names.index(fl.camera)
    return view, pos, inten


def flash_positions(rig, flash_ids: list[str], view_names: list[str], R: np.ndarray, t: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """Flash positions in the fitted model space.

    A flash attached to a fitted view sits at that view's fitted centre ``−Rᵀt``.  Every other flash (the
    raised cameras' flashes 14/18 when 08_1/19_1 are not fitted views, stand-alone flashes 15–17) is mapped
    from the rig frame with the rigid transform that best aligns the rig camera positions of the fitted views
    to their fitted centres (needs ≥ 3 views, else the rig frame is used as model space).

    Returns (flash_pos (F, 3), flash_intensity (F,), source per flash ("view" / "rig"), rig→model residual (V,)).
    """
    centers = camera_centers(R, t)
    rig_pos = np.array([rig.camera(n).position for n in view_names], dtype=np.float64)
    if len(view_names) >= 3:
        Ra, ta, res = rigid_align(rig_pos, centers)
    else:
        Ra, ta, res = np.eye(3), np.zeros(3), np.linalg.norm(rig_pos - centers, axis=-1)
    view, pos, inten = flash_mounts(rig, flash_ids, view_names)
    for i, v in enumerate(view):
        pos[i] = centers[v] if v >= 0 else Ra @ pos[i] + ta
    source = ["view" if v >= 0 else "rig" for v in view]
    return pos, inten, source, res

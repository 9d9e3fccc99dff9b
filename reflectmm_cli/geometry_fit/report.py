"""Errors of a fitted geometry against ground truth (synthetic data) and overlay images."""

from __future__ import annotations

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.landmarks import inter_ocular


def inter_ocular_mm(vertices: np.ndarray, landmarks: np.ndarray) -> float:
    """Distance between the eye centres of a mesh's landmark vertices (:func:`reflectmm_cli.landmarks.inter_ocular`),
    mm."""
    return float(inter_ocular(np.asarray(vertices, dtype=np.float64)[np.asarray(landmarks)]))


def truth_errors(vertices: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, truth_vertices: np.ndarray,
                 truth_K: np.ndarray, truth_R: np.ndarray, truth_t: np.ndarray, landmark_ids: np.ndarray
                 ) -> dict[str, np.ndarray]:
    """Errors of a fit against ground truth, all in model space without any alignment (we fit in model space).

    Returns arrays: ``err_landmark_px (V,)`` RMS distance between the fitted and the true projections of the 68
    landmark vertices; ``err_vertex_px (V,)`` the same over every vertex in front of the camera;
    ``err_vertex_rmse_mm ()`` and ``err_vertex_max_mm ()`` 3-D vertex error; ``err_vertex_rmse_iod ()`` the RMSE
    as a fraction of the true inter-ocular distance; ``err_cam_center_mm (V,)``; ``truth_iod_mm ()``.
    """
    V = len(K)
    v_fit = np.asarray(vertices, dtype=np.float64)
    v_true = np.asarray(truth_vertices, dtype=np.float64)
    d3 = np.linalg.norm(v_fit - v_true, axis=-1)
    iod = inter_ocular_mm(v_true, landmark_ids)
    lm_err = np.zeros(V)
    vx_err = np.zeros(V)
    for v in range(V):
        uf, zf = project(v_fit, K[v], R[v], t[v])
        ut, zt = project(v_true, truth_K[v], truth_R[v], truth_t[v])
        e = np.linalg.norm(uf - ut, axis=-1)
        lm_err[v] = np.sqrt(np.mean(e[landmark_ids] ** 2))
        front = (zf > 0) & (zt > 0)
        vx_err[v] = np.sqrt(np.mean(e[front] ** 2)) if front.any() else np.nan
    cc = np.linalg.norm(camera_centers(R, t) - camera_centers(truth_R, truth_t), axis=-1)
    rmse = float(np.sqrt(np.mean(d3 ** 2)))
    return {"err_landmark_px": lm_err, "err_vertex_px": vx_err, "err_vertex_rmse_mm": np.float64(rmse),
            "err_vertex_max_mm": np.float64(d3.max()), "err_vertex_rmse_iod": np.float64(rmse / iod),
            "err_cam_center_mm": cc, "truth_iod_mm": np.float64(iod)}


def display_image(linear: np.ndarray) -> np.ndarray:
    """Linear image → uint8 for display (99.5th percentile to 1, gamma 1/2.2)."""
    x = np.nan_to_num(np.asarray(linear, dtype=np.float32))
    hi = float(np.percentile(x, 99.5)) if x.size else 1.0
    return encode_display(x / max(hi, 1e-6), "gamma", nan_to_num=False, uint8=True)


def overlay(image: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, K: np.ndarray, R: np.ndarray,
            t: np.ndarray, landmarks_given: np.ndarray, landmarks_fit: np.ndarray, origin=(0.0, 0.0),
            scale: int = 1, alpha: float = 0.45) -> np.ndarray:
    """RGB uint8 overlay of a fitted mesh on one view.

    The mesh is ray traced (Embree) in the pixel frame of ``image`` and shown as a shaded surface (cool tint,
    shading ``0.25 + 0.75 n·v``) blended with weight ``alpha``, plus its silhouette (white); given landmarks are
    green dots, fitted landmark projections red crosses, joined by yellow lines.  ``K`` is full-frame;
    ``origin`` (x0, y0) is the full-frame pixel of the image's top-left pixel; ``scale`` upsamples the result.
    """
    import cv2

    from reflectmm_cli.geometry import Camera, RayScene, rasterize

    img = display_image(image) if image.dtype != np.uint8 else image.copy()
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    H, W = img.shape[:2]
    off = np.asarray(origin, dtype=np.float64)
    S = int(scale)
    # camera of the upsampled crop: pixel p_full -> (p_full - off + 0.5) * S - 0.5
    Kc = np.asarray(K, dtype=np.float64).copy()
    Kc[:2, :2] *= S
    Kc[0, 2] = (Kc[0, 2] - off[0] + 0.5) * S - 0.5
    Kc[1, 2] = (Kc[1, 2] - off[1] + 0.5) * S - 0.5
    if S != 1:
        img = cv2.resize(img, (W * S, H * S), interpolation=cv2.INTER_NEAREST)
    ras = rasterize(RayScene(vertices, triangles), Camera(Kc, R, t, W * S, H * S, "overlay"))
    m = ras.mask
    if m.any():
        c = camera_centers(R, t)
        v = c[None] - ras.position[m].astype(np.float64)
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        ndv = np.clip((ras.normal[m] * v).sum(-1), 0.0, 1.0)
        shade = (0.25 + 0.75 * ndv)[:, None] * np.array([150.0, 200.0, 255.0])
        out = img.astype(np.float32)
        out[m] = (1 - alpha) * out[m] + alpha * shade
        img = np.clip(out + 0.5, 0, 255).astype(np.uint8)
        edge = m ^ cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        img[edge] = (255, 255, 255)
    lg = (np.asarray(landmarks_given, dtype=np.float64) - off + 0.5) * S - 0.5
    lf = (np.asarray(landmarks_fit, dtype=np.float64) - off + 0.5) * S - 0.5
    r = max(2, S + 1)
    for a, b in zip(lg, lf):
        if not np.all(np.isfinite(b)):
            continue
        bb = tuple(int(round(x)) for x in b)
        if np.all(np.isfinite(a)):
            aa = tuple(int(round(x)) for x in a)
            cv2.line(img, aa, bb, (255, 255, 0), 1, cv2.LINE_AA)
            cv2.circle(img, aa, r, (0, 255, 0), -1, cv2.LINE_AA)
        cv2.drawMarker(img, bb, (255, 0, 0), cv2.MARKER_TILTED_CROSS, 2 * r + 1, 1, cv2.LINE_AA)
    return img

"""What placed each view of a fit, and how well: evidence labels, pose uncertainty and the shift from the rig.

A view with landmarks is placed by them; a view without any is placed by the rig (its camera moved by the head
pose the other views fix) and refined by the image terms it enters (room-light photo-consistency, its flashes).
The uncertainty is a Laplace approximation: the curvature of the last stage's objective in a centre shift δc (mm)
that keeps the camera aimed at the model origin and a turn ω (in units of 1 / distance rad, ≈ 1 mm at the face)
of each view, the others held (σ conditional on them), taken by central differences of
the autograd gradient (steps of a few pixels, so that the piecewise-bilinear image sampling averages out).  The
objective is scaled to a negative log-likelihood by the landmark weight sum (exact for the landmark term and
the priors, which are divided by it; the image terms' noise scale is nominal): compare the views of one fit rather
than reading the numbers as calibrated errors.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from reflectmm_cli.geometry.camera import camera_centers

__all__ = ["pose_curvature", "data_cut_psd", "pose_sigmas", "view_evidence", "rig_shift"]


def _fd_curvature(prob, loss, views, steps: np.ndarray) -> np.ndarray:
    """(V, 6, 6) central-difference curvature of ``loss()`` in ``prob.probe`` per view in ``views`` (NaN others)."""
    V = prob.V
    H = np.full((V, 6, 6), np.nan)
    for v in views:
        for j in range(6):
            g = []
            for sgn in (1.0, -1.0):
                p = torch.zeros(V, 6, dtype=prob.dtype, device=prob.device)
                p[v, j] = sgn * steps[j]
                p.requires_grad_(True)
                prob.probe = p
                try:
                    (gr,) = torch.autograd.grad(loss(), p)
                finally:
                    prob.probe = None
                g.append(gr[v].detach().cpu().numpy().astype(np.float64))
            H[v, :, j] = (g[0] - g[1]) / (2 * steps[j])
        H[v] = 0.5 * (H[v] + H[v].T)
    return H


def pose_curvature(prob, views, h_rot: float = 2.0, h_mm: float = 2.0) -> np.ndarray:
    """(V, 6, 6) curvature of ``prob.last_loss`` × ``prob.wsum`` in (ω, δc mm) of each view in ``views``, the
    other views held (NaN for the views not asked for).  One view at a time: the flash term couples the views
    (a camera's flash lights every view), so moving all views at once would mix their blocks.

    The priors' curvature is taken alone and the rest (landmarks, image terms) is cut to its positive
    semi-definite part: where the image terms curve down (they are not convex far from a pixel-sharp optimum)
    they inform nothing, and the priors still bound the pose.

    ``prob`` is a fit problem (``fit._FitProblem``): its ``poses()`` applies ``prob.probe`` (V, 6), and its
    ``held_out_of()`` takes the unknowns out of autograd while the differences are taken."""
    steps = np.array([h_rot] * 3 + [h_mm] * 3)
    if prob.last_loss is None:
        return np.full((prob.V, 6, 6), np.nan)
    with prob.held_out_of():  # only the probe moves: every unknown is a constant of these differences
        total = _fd_curvature(prob, prob.last_loss, views, steps)
        prior = _fd_curvature(prob, lambda: prob.prior(*prob.poses()), views, steps)
    H = np.full_like(total, np.nan)
    for v in views:
        H[v] = data_cut_psd(total[v], prior[v])
    return H * prob.wsum


def data_cut_psd(total: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(n, n) curvature ``total`` with its data part (``total − prior``) cut to its positive semi-definite part
    (negative eigenvalues set to 0), plus the ``prior`` curvature: what the Laplace approximations of a pose
    use where the image terms curve down."""
    w, U = np.linalg.eigh(total - prior)
    return (U * np.clip(w, 0.0, None)) @ U.T + prior


def pose_sigmas(H: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-σ of each camera centre (mm, RMS over the axes × √3, i.e. the norm of the σ vector) and orientation
    (degrees, the largest axis) from (V, 6, 6) curvatures and the camera distances (V,) mm; ∞ where the
    curvature is not positive definite."""
    V = len(H)
    c_sig, r_sig = np.full(V, np.inf), np.full(V, np.inf)
    for v in range(V):
        if not np.isfinite(H[v]).all():
            c_sig[v] = r_sig[v] = np.nan
            continue
        w, U = np.linalg.eigh(H[v])
        if w.min() <= 1e-12 * max(abs(w).max(), 1e-300):
            continue
        cov = (U / w) @ U.T
        c_sig[v] = math.sqrt(max(np.trace(cov[3:, 3:]), 0.0))
        r_sig[v] = math.degrees(math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)) / dist[v])
    return c_sig, r_sig


def view_evidence(marked: np.ndarray, photo_visible: np.ndarray | None, flash_residual: np.ndarray | None,
                  room: np.ndarray | None = None) -> list[str]:
    """(V,) labels: ``landmarks`` or ``rig``, then ``+photo`` for a view with room-light samples, ``+flash``
    for one with flash samples (a finite flash residual) and ``+room`` for one that the room-light
    photo-consistency refined (``room`` (V,) bool)."""
    out = []
    for v, m in enumerate(np.asarray(marked, dtype=bool)):
        parts = ["landmarks" if m else "rig"]
        if photo_visible is not None and photo_visible[v] > 0:
            parts.append("photo")
        if flash_residual is not None and np.isfinite(flash_residual[v]):
            parts.append("flash")
        if room is not None and room[v]:
            parts.append("room")
        out.append("+".join(parts))
    return out


def rig_shift(prob) -> np.ndarray:
    """(V,) distance (mm) of each fitted camera centre from its rig centre under the fitted head pose (NaN without
    the rig constraint): how far the evidence moved the view from where the rig puts it."""
    if not prob.use_rig:
        return np.full(prob.V, np.nan)
    with torch.no_grad():
        R, t = prob.poses()
        Rh, th = prob.head()
        d = camera_centers(R, t) - (prob.rig_t @ Rh.T + th)
    return np.linalg.norm(d.cpu().numpy().astype(np.float64), axis=-1)

"""Rotation and pinhole-projection maths used by the geometry fit (numpy and torch).

Frames (docs/pipeline.md): ``x_cam = R @ x_model + t``; ``u = fx·X/Z + cx``, ``v = fy·Y/Z + cy``;
camera centre in model space ``c = −Rᵀ t``.  Rotations are parameterised by axis-angle vectors
(Rodrigues); the fit optimises a left-multiplied update ``R = exp([δ]×) @ R0`` so that poses near a
rotation by π (every camera looking down −z of its own frame) are never at the axis-angle singularity.
"""

from __future__ import annotations

import numpy as np
import torch


def skew(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) → (..., 3, 3) cross-product matrices ``[w]×`` with ``[w]× v = w × v``."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([
        torch.stack([z, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], z, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], z], -1),
    ], -2)


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: (..., 3) axis-angle (radians, |w| = angle) → (..., 3, 3) rotation matrices.

    ``R = I + sin θ/θ [w]× + (1 − cos θ)/θ² [w]×²``; for θ < 1e-4 the Taylor series is used so the value and
    the gradient are exact at and near zero (the fit starts every update at exactly zero).
    """
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, (1.0 - torch.cos(theta)) / theta2_safe)
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices → (..., 3) axis-angle vectors (numpy, robust near 0 and π)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def camera_centers(R, t):
    """Camera centres in model space ``c = −Rᵀ t`` for (..., 3, 3) R and (..., 3) t (numpy or torch)."""
    if isinstance(R, torch.Tensor):
        return -(R.transpose(-1, -2) @ t[..., None])[..., 0]
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", R, t)


def project(points, K, R, t):
    """Project (..., N, 3) model-space points with (..., 3, 3) K, R and (..., 3) t.

    Returns ((..., N, 2) pixels, (..., N) depth).

    Works on numpy arrays or torch tensors (differentiable).  Depth is the camera-frame Z (> 0 in front).
    """
    if isinstance(points, torch.Tensor):
        Xc = points @ R.transpose(-1, -2) + t[..., None, :]
        Z = Xc[..., 2]
        uv = torch.stack([K[..., 0, 0, None] * Xc[..., 0] / Z + K[..., 0, 1, None] * Xc[..., 1] / Z
                          + K[..., 0, 2, None],
                          K[..., 1, 1, None] * Xc[..., 1] / Z + K[..., 1, 2, None]], -1)
        return uv, Z
    points = np.asarray(points, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    Xc = points @ np.swapaxes(R, -1, -2) + t[..., None, :]
    Z = Xc[..., 2]
    uv = np.stack([K[..., 0, 0, None] * Xc[..., 0] / Z + K[..., 0, 1, None] * Xc[..., 1] / Z + K[..., 0, 2, None],
                   K[..., 1, 1, None] * Xc[..., 1] / Z + K[..., 1, 2, None]], -1)
    return uv, Z


def intrinsics(focal: float, width: int, height: int, cx: float | None = None, cy: float | None = None
               ) -> np.ndarray:
    """3×3 pinhole K with square pixels; principal point at the image centre ((W−1)/2, (H−1)/2) by default
    (pixel centres at integer coordinates, docs/pipeline.md)."""
    cx = (width - 1) / 2.0 if cx is None else cx
    cy = (height - 1) / 2.0 if cy is None else cy
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber penalty of residual magnitudes ``x`` ≥ 0: ½x² for x ≤ δ, δ(x − ½δ) beyond (C¹)."""
    return torch.where(x <= delta, 0.5 * x * x, delta * (x - 0.5 * delta))

"""Rotations, numpy and torch: the one home of every rotation conversion of the toolkit.

Conventions (those of :mod:`reflectmm_cli.geometry.camera`): right-handed frames, rotation matrices act on column
vectors (``x' = R @ x``), angles in radians unless a name says degrees.  Axis-angle vectors ``w`` have the unit
axis times the angle (``|w| = θ``), so ``axis_angle_to_matrix(w) = exp([w]×)`` (Rodrigues).

Each function takes numpy arrays (array-likes) or torch tensors where its docstring says so: numpy in → numpy
out (float64), torch in → torch out (the input's dtype and device, differentiable unless said otherwise).
Shapes are ``(..., 3)`` for vectors and ``(..., 3, 3)`` for matrices, batched over the leading dimensions; a
wrong trailing shape raises ValueError naming the function.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["skew", "axis_angle_to_matrix", "rodrigues", "matrix_to_axis_angle", "rotation_x", "rotation_y",
           "rotation_z", "euler_yxz_to_matrix", "look_at_rotation", "nearest_rotation", "rotation_angle"]


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def _check_trailing(fn: str, x, shape: tuple[int, ...]) -> None:
    if x.ndim < len(shape) or tuple(x.shape[x.ndim - len(shape):]) != shape:
        want = "(..., " + ", ".join(str(s) for s in shape) + ")"
        raise ValueError(f"{fn}: expected shape {want}, got {tuple(x.shape)}")


def skew(w):
    """Cross-product matrices: (..., 3) → (..., 3, 3) ``[w]×`` with ``[w]× v = w × v``.

    numpy → float64 numpy; torch → torch (dtype and device of ``w``, differentiable).
    """
    if _is_torch(w):
        import torch

        _check_trailing("skew", w, (3,))
        z = torch.zeros_like(w[..., 0])
        return torch.stack([
            torch.stack([z, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], z, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], z], -1),
        ], -2)
    w = np.asarray(w)
    _check_trailing("skew", w, (3,))
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def axis_angle_to_matrix(w):
    """Rodrigues: (..., 3) axis-angle vectors (radians, ``|w| = θ``) → (..., 3, 3) rotation matrices.

    ``R = I + sin θ/θ [w]× + (1 − cos θ)/θ² [w]×²``, with the Taylor series of both factors near θ = 0 so the
    value is exact at and near zero.  torch (differentiable): the series below θ² = 1e-8 to order θ⁴, so the
    gradient is exact at exactly zero too (the geometry fit starts every update there).  numpy (float64): the
    series below θ² = 1e-16 to order θ².
    """
    if _is_torch(w):
        import torch

        _check_trailing("axis_angle_to_matrix", w, (3,))
        theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
        small = theta2 < 1e-8
        theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
        theta = torch.sqrt(theta2_safe)
        a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(theta) / theta)
        b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, (1.0 - torch.cos(theta)) / theta2_safe)
        K = skew(w)
        eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(K.shape)
        return eye + a * K + b * (K @ K)
    w = np.asarray(w, np.float64)
    _check_trailing("axis_angle_to_matrix", w, (3,))
    th2 = (w * w).sum(-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-16
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    Kx = skew(w)
    return np.eye(3) + a * Kx + b * (Kx @ Kx)


#: The numpy name the rig calibration has always used for :func:`axis_angle_to_matrix`.
rodrigues = axis_angle_to_matrix


def matrix_to_axis_angle(R):
    """(..., 3, 3) rotation matrices → (..., 3) axis-angle vectors, robust near 0 and π (scipy).

    numpy → float64 numpy; torch → torch of the input's dtype and device (not differentiable: computed by
    scipy on a float64 copy).  At θ = π the sign of ``w`` is scipy's choice (both signs are the same rotation).
    """
    from scipy.spatial.transform import Rotation

    if _is_torch(R):
        import torch

        _check_trailing("matrix_to_axis_angle", R, (3, 3))
        out = matrix_to_axis_angle(R.detach().cpu().double().numpy())
        return torch.as_tensor(out, dtype=R.dtype, device=R.device)
    R = np.asarray(R, dtype=np.float64)
    _check_trailing("matrix_to_axis_angle", R, (3, 3))
    flat = R.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(R.shape[:-2] + (3,))


def rotation_x(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about +x (right-handed; +y goes towards +z)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about +y (right-handed; +z goes towards +x)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_z(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about +z (right-handed; +x goes towards +y)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_yxz_to_matrix(y: float, x: float, z: float) -> np.ndarray:
    """(3, 3) ``Rz(z) · Rx(x) · Ry(y)`` (radians): first about y, then x, then z, all about the fixed axes
    (scipy's extrinsic ``"yxz"``; e.g. a head's yaw, pitch, roll)."""
    return rotation_z(z) @ rotation_x(x) @ rotation_y(y)


def look_at_rotation(position: Sequence[float], target: Sequence[float], up: Sequence[float]) -> np.ndarray:
    """(3, 3) world-to-camera rotation R (rows = camera x, y, z axes in world coordinates), numpy.

    Camera +z points from ``position`` to ``target``; camera +y is image-down, i.e. opposite to ``up``
    projected onto the image plane; camera +x = y × z (image right).  Raises ValueError when degenerate.
    """
    c = np.asarray(position, np.float64)
    z = np.asarray(target, np.float64) - c
    nz = np.linalg.norm(z)
    if nz <= 0:
        raise ValueError("look_at equals position")
    z = z / nz
    u = np.asarray(up, np.float64)
    y = -(u - np.dot(u, z) * z)
    ny = np.linalg.norm(y)
    if ny <= 1e-9 * max(np.linalg.norm(u), 1e-300):
        raise ValueError("up is parallel to the viewing direction")
    y = y / ny
    x = np.cross(y, z)
    return np.stack([x, y, z])


def nearest_rotation(M) -> np.ndarray:
    """(3, 3) rotation nearest to a (3, 3) matrix in the Frobenius norm (e.g. the mean of rotations), numpy:
    ``U diag(1, 1, sign det(U Vᵀ)) Vᵀ`` from the SVD ``M = U S Vᵀ``."""
    M = np.asarray(M, np.float64)
    _check_trailing("nearest_rotation", M, (3, 3))
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def rotation_angle(Ra, Rb) -> np.ndarray:
    """Angle (radians, in [0, π]) of the relative rotation between (..., 3, 3) ``Ra`` and ``Rb``, numpy:
    ``arccos((tr(Raᵀ Rb) − 1) / 2)`` (the argument clipped to [−1, 1])."""
    Ra, Rb = np.asarray(Ra, np.float64), np.asarray(Rb, np.float64)
    _check_trailing("rotation_angle", Ra, (3, 3))
    _check_trailing("rotation_angle", Rb, (3, 3))
    c = (np.einsum("...ij,...ij->...", Ra, Rb) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))

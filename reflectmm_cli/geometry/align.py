"""Rigid and similarity alignment of corresponding point sets: the one home of Kabsch / Umeyama in the toolkit."""
from __future__ import annotations

import numpy as np

__all__ = ["rigid_align"]


def rigid_align(src, dst, weights=None, scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares transform with ``dst ≈ s · src @ Rᵀ + t`` (Kabsch; Umeyama with ``scale=True``), numpy.

    Minimises ``Σ_i w_i ‖s R src_i + t − dst_i‖²`` over proper rotations R (det = +1: a reflection is never
    returned, the smallest singular direction is flipped instead), translations t and, with ``scale=True``, a
    scale s > 0 (else s = 1).

    Args:
        src, dst: (N, D) corresponding points, D = 2 or 3 (float64 internally).  Needs N ≥ D points not all on
            one line (D = 3) for a unique R; degenerate sets are not refused.
        weights: optional (N,) non-negative weights (not all zero); None = all equal (the plain centroid and
            cross-covariance, bit for bit the unweighted formula).
        scale: also estimate the similarity's scale s.
    Returns:
        (R (D, D), t (D,), s float).
    Raises:
        ValueError on mismatched or non-(N, D) shapes, or weights of the wrong shape or summing to ≤ 0.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape != dst.shape or src.shape[1] not in (2, 3):
        raise ValueError(f"rigid_align: src and dst must both be (N, 2) or (N, 3), got {src.shape} and {dst.shape}")
    if weights is None:
        ms, md = src.mean(0), dst.mean(0)
        H = (src - ms).T @ (dst - md)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != src.shape[:1] or not np.all(w >= 0) or not w.sum() > 0:
            raise ValueError(f"rigid_align: weights must be ({src.shape[0]},), ≥ 0 and not all zero")
        w = w / w.sum()
        ms, md = w @ src, w @ dst
        H = (w[:, None] * (src - ms)).T @ (dst - md)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    diag = np.ones(src.shape[1])
    diag[-1] = d
    R = Vt.T @ np.diag(diag) @ U.T
    if not scale:
        return R, md - R @ ms, 1.0
    xs = src - ms  # Umeyama: s = tr(S D) / Σ w_i ‖src_i − src̄‖² (the same normalisation as H)
    s = float((S * diag).sum() / ((xs * xs).sum() if weights is None else (w[:, None] * xs * xs).sum()))
    return R, md - s * (R @ ms), s

"""UV-space rasterisation of a mesh: per texel the covering triangle and barycentric weights.

Texel ``(row, col)`` of an ``S×S`` map samples ``u = (col + 0.5)/S``, ``v = (row + 0.5)/S`` (docs/pipeline.md;
row 0 = v near 0 = top of the face).  A texel belongs to the triangle whose UV image contains its centre
(edges included); where UV triangles overlap (they should not), one of them wins, deterministically.
"""

from __future__ import annotations

import numpy as np

from reflectmm_cli.errors import ReflectmmError

#: Barycentric tolerance that closes hairline cracks between adjacent triangles.
EDGE_TOL = 1e-7
_BLOCK = 1 << 21  # candidate texels per vectorised block


def uv_rasterize(uv: np.ndarray, triangles: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise triangles in UV space.

    Args:
        uv: (N, 2) texture coordinates in [0, 1].
        triangles: (T, 3) vertex indices.
        size: S, the map is S×S.
    Returns:
        ``tri (S, S)`` int32 triangle index (−1 = empty) and ``bary (S, S, 3)`` float32 barycentric weights of
        the triangle's three vertices (0 where empty).
    """
    uv = np.asarray(uv, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    S = int(size)
    if S < 1:
        raise ReflectmmError(f"UV size must be >= 1, got {size}")
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ReflectmmError(f"uv must be (N, 2), got {uv.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ReflectmmError(f"triangles must be (T, 3), got {tri.shape}")
    P = uv * S - 0.5  # continuous texel coordinates (col, row) of each vertex
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    lo = np.ceil(np.minimum(np.minimum(a, b), c) - 1e-9).astype(np.int64)
    hi = np.floor(np.maximum(np.maximum(a, b), c) + 1e-9).astype(np.int64)
    lo = np.clip(lo, 0, S - 1)
    hi = np.clip(hi, -1, S - 1)
    ext = hi - lo + 1
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    ok = (ext[:, 0] > 0) & (ext[:, 1] > 0) & (np.abs(area) > 1e-14)
    out_tri = np.full(S * S, -1, dtype=np.int64)
    out_bary = np.zeros((S * S, 3), dtype=np.float64)
    idx_all = np.flatnonzero(ok)
    if idx_all.size == 0:
        return out_tri.reshape(S, S).astype(np.int32), out_bary.reshape(S, S, 3).astype(np.float32)
    side = np.maximum(ext[idx_all, 0], ext[idx_all, 1])
    bucket = np.ceil(np.log2(np.maximum(side, 1))).astype(np.int64)
    for bk in np.unique(bucket):
        ids = idx_all[bucket == bk]
        bw = int(ext[ids, 0].max())
        bh = int(ext[ids, 1].max())
        per = max(1, _BLOCK // (bw * bh))
        gx, gy = np.meshgrid(np.arange(bw), np.arange(bh))
        gx, gy = gx.reshape(-1), gy.reshape(-1)
        for s0 in range(0, ids.size, per):
            t = np.sort(ids[s0:s0 + per])
            px = lo[t, 0][:, None] + gx[None, :]
            py = lo[t, 1][:, None] + gy[None, :]
            inb = (px <= hi[t, 0][:, None]) & (py <= hi[t, 1][:, None])
            ax, ay = a[t, 0][:, None], a[t, 1][:, None]
            bx, by = b[t, 0][:, None], b[t, 1][:, None]
            cx, cy = c[t, 0][:, None], c[t, 1][:, None]
            ar = area[t][:, None]
            w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / ar
            w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / ar
            w2 = 1.0 - w0 - w1
            inside = inb & (w0 >= -EDGE_TOL) & (w1 >= -EDGE_TOL) & (w2 >= -EDGE_TOL)
            ti, gi = np.nonzero(inside)
            flat = py[ti, gi] * S + px[ti, gi]
            out_tri[flat] = t[ti]
            out_bary[flat] = np.stack([w0[ti, gi], w1[ti, gi], w2[ti, gi]], 1)
    return out_tri.reshape(S, S).astype(np.int32), np.clip(out_bary, 0.0, 1.0).reshape(S, S, 3).astype(np.float32)


def interpolate(values: np.ndarray, triangles: np.ndarray, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values (N, C)`` into a UV map ``(S, S, C)`` (0 where empty)."""
    values = np.asarray(values, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    S = tri.shape[0]
    out = np.zeros((S, S, values.shape[1]), dtype=np.float64)
    m = tri >= 0
    corners = triangles[tri[m]]  # (M, 3)
    w = bary[m].astype(np.float64)
    out[m] = np.einsum("mk,mkc->mc", w, values[corners])
    return out

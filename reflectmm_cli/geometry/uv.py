"""UV-space rasterisation and map sampling (texel conventions of docs/pipeline.md).

Texel ``(row, col)`` of an S×S map has ``u = (col + 0.5)/S``, ``v = (row + 0.5)/S``; row 0 is the top of the
face (v = 0).  Maps are channel-first ``(C, S, S)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["UVRaster", "rasterize_uv", "uv_positions", "sample_uv_map", "vertex_to_uv_map", "cylindrical_uv",
           "uv_distortion"]


@dataclass
class UVRaster:
    """Which triangle covers each texel, and where.

    Attributes:
        tri_id: (S, S) int32 triangle index or −1.
        bary: (S, S, 3) float32 barycentric weights (0 outside the mask).
        mask: (S, S) bool, ``tri_id >= 0``.
        triangles: (T, 3) int32 the triangles the ids refer to.
    """

    tri_id: np.ndarray
    bary: np.ndarray
    mask: np.ndarray
    triangles: np.ndarray

    def __iter__(self):  # allows ``tri_id, bary, mask = rasterize_uv(...)``
        return iter((self.tri_id, self.bary, self.mask))

    @property
    def size(self) -> int:
        return int(self.mask.shape[0])

    def interpolate(self, values) -> np.ndarray:
        """(S, S, C) per-vertex values (N, C) interpolated over the texels (0 outside the mask)."""
        vals = np.asarray(values)
        v2 = vals.reshape(vals.shape[0], -1).astype(np.float64)
        out = np.zeros(self.mask.shape + (v2.shape[1],), dtype=np.float32)
        tv = self.triangles[self.tri_id[self.mask]]
        out[self.mask] = np.einsum("mk,mkc->mc", self.bary[self.mask].astype(np.float64), v2[tv])
        return out.reshape(self.mask.shape + vals.shape[1:])


def rasterize_uv(model_uv, triangles, size: int) -> UVRaster:
    """Rasterise the UV layout: for each texel centre, the covering triangle and its barycentrics.

    Exact point-in-triangle tests per triangle bounding box (vectorised over triangles of similar size), so
    every texel centre inside a triangle is found; texels on a shared edge go to one of the triangles.
    Triangles with zero UV area cover nothing.
    """
    uv = np.asarray(model_uv, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    S = int(size)
    if S <= 0:
        raise ReflectmmError(f"rasterize_uv: size must be positive, got {size}")
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ReflectmmError(f"rasterize_uv: uv must be (N, 2), got {uv.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ReflectmmError(f"rasterize_uv: triangles must be (T, 3), got {tri.shape}")
    tri_id = np.full((S, S), -1, dtype=np.int32)
    bary = np.zeros((S, S, 3), dtype=np.float32)
    # texel coordinates: x = u·S − 0.5 (column), y = v·S − 0.5 (row)
    P = uv[tri] * S - 0.5  # (T, 3, 2)
    x0, y0 = P[:, 0, 0], P[:, 0, 1]
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    cmin = np.clip(np.ceil(P[:, :, 0].min(1) - 1e-9), 0, S - 1).astype(np.int64)
    cmax = np.clip(np.floor(P[:, :, 0].max(1) + 1e-9), 0, S - 1).astype(np.int64)
    rmin = np.clip(np.ceil(P[:, :, 1].min(1) - 1e-9), 0, S - 1).astype(np.int64)
    rmax = np.clip(np.floor(P[:, :, 1].max(1) + 1e-9), 0, S - 1).astype(np.int64)
    w = np.where(ok, cmax - cmin + 1, 0)
    h = np.where(ok, rmax - rmin + 1, 0)
    ok &= (w > 0) & (h > 0)
    # group triangles by bounding-box size so each group is one vectorised pass
    bw, bh = w[ok], h[ok]
    ids = np.nonzero(ok)[0]
    keys = bw * 100003 + bh
    order = np.argsort(keys, kind="stable")
    ids, keys = ids[order], keys[order]
    starts = np.r_[0, np.nonzero(np.diff(keys))[0] + 1, len(keys)]
    for a, b in zip(starts[:-1], starts[1:]):
        if b <= a:
            continue
        g = ids[a:b]
        gw, gh = int(w[g[0]]), int(h[g[0]])
        dc, dr = np.meshgrid(np.arange(gw), np.arange(gh))
        cols = cmin[g][:, None] + dc.ravel()[None]
        rows = rmin[g][:, None] + dr.ravel()[None]
        px = cols - x0[g][:, None]
        py = rows - y0[g][:, None]
        inv = 1.0 / det[g][:, None]
        l1 = (px * e2[g, 1][:, None] - py * e2[g, 0][:, None]) * inv
        l2 = (e1[g, 0][:, None] * py - e1[g, 1][:, None] * px) * inv
        l0 = 1.0 - l1 - l2
        tol = -1e-9
        inside = (l0 >= tol) & (l1 >= tol) & (l2 >= tol)
        if not inside.any():
            continue
        ti = np.broadcast_to(g[:, None], inside.shape)[inside]
        r, c = rows[inside], cols[inside]
        tri_id[r, c] = ti
        bary[r, c, 0] = l0[inside]
        bary[r, c, 1] = l1[inside]
        bary[r, c, 2] = l2[inside]
    mask = tri_id >= 0
    b = np.clip(bary[mask], 0.0, 1.0)
    bary[mask] = b / b.sum(1, keepdims=True)
    return UVRaster(tri_id, bary, mask, tri.astype(np.int32))


def uv_positions(vertices, normals, uv_raster: UVRaster) -> tuple[np.ndarray, np.ndarray]:
    """(position (S, S, 3), unit normal (S, S, 3)) interpolated over the texels; zeros outside the mask."""
    pos = uv_raster.interpolate(np.asarray(vertices, dtype=np.float64))
    nrm = uv_raster.interpolate(np.asarray(normals, dtype=np.float64)).astype(np.float64)
    ln = np.linalg.norm(nrm, axis=-1, keepdims=True)
    nrm = np.divide(nrm, ln, out=np.zeros_like(nrm), where=ln > 0)
    return pos.astype(np.float32), nrm.astype(np.float32)


def sample_uv_map(uv_map, uv) -> np.ndarray:
    """Bilinear lookup of a (C, S, S) (or (S, S)) map at (N, 2) UV coordinates → (N, C) (or (N,)).

    Texel centres at ``(i + 0.5)/S``; coordinates outside clamp to the border texels.
    """
    m = np.asarray(uv_map)
    squeeze = m.ndim == 2
    if squeeze:
        m = m[None]
    if m.ndim != 3 or m.shape[1] != m.shape[2]:
        raise ReflectmmError(f"sample_uv_map: map must be (C, S, S) or (S, S), got {np.shape(uv_map)}")
    q = np.asarray(uv, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 2:
        raise ReflectmmError(f"sample_uv_map: uv must be (N, 2), got {q.shape}")
    S = m.shape[1]
    x = np.clip(q[:, 0] * S - 0.5, 0, S - 1)
    y = np.clip(q[:, 1] * S - 0.5, 0, S - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), S - 2 if S > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), S - 2 if S > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, S - 1), np.minimum(y0 + 1, S - 1)
    fx, fy = (x - x0)[None], (y - y0)[None]
    out = (m[:, y0, x0] * (1 - fx) * (1 - fy) + m[:, y0, x1] * fx * (1 - fy) + m[:, y1, x0] * (1 - fx) * fy
           + m[:, y1, x1] * fx * fy)
    out = out.T.astype(np.result_type(m.dtype, np.float32))
    return out[:, 0] if squeeze else out


def vertex_to_uv_map(values, uv_raster: UVRaster) -> np.ndarray:
    """Per-vertex values (N, C) or (N,) → (C, S, S) (or (S, S)) map by barycentric interpolation (0 outside)."""
    vals = np.asarray(values)
    img = uv_raster.interpolate(vals.reshape(vals.shape[0], -1))
    out = np.moveaxis(img, -1, 0)
    return out[0] if vals.ndim == 1 else out


def cylindrical_uv(vertices, margin: float = 0.02) -> np.ndarray:
    """A left-right symmetric UV layout for a face mesh without one.

    ``u`` is linear in the azimuth ``atan2(x − x_c, z − z_c)`` about a vertical axis behind the face (x_c = the
    middle of the x range, z_c = the mesh's minimum z minus 10 % of its depth, so the front maps monotonically)
    and symmetric about x = x_c (u ↔ 1 − u); ``v`` is linear in height, v = 0 at the top.  Both are scaled to
    [margin, 1 − margin] with the same scale on both axes (arc length vs height), so texels are roughly square on
    the cylinder.
    """
    v = np.asarray(vertices, dtype=np.float64)
    xc = 0.5 * (v[:, 0].max() + v[:, 0].min())  # symmetry plane (x = 0 for a centred model)
    zc = v[:, 2].min() - 0.1 * np.ptp(v[:, 2])
    radius = np.median(np.hypot(v[:, 0] - xc, v[:, 2] - zc))
    az = np.arctan2(v[:, 0] - xc, v[:, 2] - zc) * radius  # arc length, mm
    ext_u = 2 * np.abs(az).max()
    ymax, ymin = v[:, 1].max(), v[:, 1].min()
    ext = max(ext_u, ymax - ymin, 1e-9)
    s = (1 - 2 * margin) / ext
    u = 0.5 + az * s
    vv = 0.5 - (v[:, 1] - 0.5 * (ymax + ymin)) * s
    return np.stack([u, vv], 1).astype(np.float32)


def uv_distortion(vertices, triangles, uv) -> dict:
    """Area distortion of a UV layout: statistics of the per-triangle ratio (UV area / 3-D area), normalised
    by the global ratio (1 = area-preserving), plus the fraction of flipped / degenerate UV triangles."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    q = np.asarray(uv, dtype=np.float64)
    a3 = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    e1, e2 = q[t[:, 1]] - q[t[:, 0]], q[t[:, 2]] - q[t[:, 0]]
    signed = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    a2 = np.abs(signed)
    good = (a3 > 0) & (a2 > 0)
    if not good.any():
        return {"area_ratio_p5": float("nan"), "area_ratio_median": float("nan"),
                "area_ratio_p95": float("nan"), "flipped_fraction": float("nan"), "degenerate_fraction": 1.0}
    ratio = (a2[good] / a3[good]) / (a2[good].sum() / a3[good].sum())
    # with v pointing down, outward-facing (CCW in 3-D seen from outside) triangles are clockwise in (u, v);
    # the minority orientation counts as flipped
    major = np.sign(np.median(np.sign(signed[good])))
    return {"area_ratio_p5": float(np.percentile(ratio, 5)), "area_ratio_median": float(np.median(ratio)),
            "area_ratio_p95": float(np.percentile(ratio, 95)),
            "flipped_fraction": float(np.mean(np.sign(signed[good]) != major)),
            "degenerate_fraction": float(1 - good.mean())}

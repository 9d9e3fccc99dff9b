"""Ray casting with Embree (through embreex, the backend of ``trimesh.ray.ray_pyembree``).

* :func:`rasterize` — one primary ray per pixel centre: triangle id, barycentrics, depth, position and the
  interpolated vertex normal.
* :func:`visibility` — a point is visible from an eye if the segment from the point (offset along its normal)
  to the eye is unoccluded.
* :func:`shadow_mask` — the same test towards a point light; points facing away from the light
  (n·l ≤ 0) are unlit without casting a ray.

Embree works in float32.  The self-hit offset is ``eps`` (default 1e-4 × the mesh bounding-box diagonal,
≈ 0.03 mm for a face) along the normal *and* along the ray; that suppresses self-intersections without
letting light leak through thin folds thicker than that.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .camera import Camera
from .face_model import vertex_normals

log = logging.getLogger("reflectmm")

__all__ = ["RayScene", "Raster", "rasterize", "visibility", "shadow_mask", "has_embree", "RayStats"]


def has_embree() -> bool:
    try:
        import trimesh.ray

        return bool(trimesh.ray.has_embree)
    except ImportError:  # pragma: no cover
        return False


@dataclass
class RayStats:
    """Counters of the last query on a scene (rays cast, rays skipped, seconds)."""

    cast: int = 0
    skipped: int = 0
    seconds: float = 0.0

    @property
    def rays_per_second(self) -> float:
        return self.cast / self.seconds if self.seconds > 0 else float("nan")


class RayScene:
    """An Embree scene of one triangle mesh.

    Args:
        vertices: (N, 3) positions (mm).
        triangles: (T, 3) 0-based indices.
        normals: optional (N, 3) vertex normals (default: area-weighted, computed once).
    """

    def __init__(self, vertices, triangles, normals=None):
        if not has_embree():
            raise ReflectmmError("Embree ray casting needs the 'embreex' package (pip install embreex)")
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        v = np.ascontiguousarray(vertices, dtype=np.float64)
        t = np.ascontiguousarray(triangles, dtype=np.int32)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ReflectmmError(f"RayScene: vertices must be (N, 3), got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ReflectmmError(f"RayScene: triangles must be (T, 3), got {t.shape}")
        if t.size and (t.min() < 0 or t.max() >= v.shape[0]):
            raise ReflectmmError(f"RayScene: triangle indices out of range [0, {v.shape[0]})")
        if not np.all(np.isfinite(v)):
            raise ReflectmmError("RayScene: vertices contain NaN/inf")
        self.vertices = v
        self.triangles = t
        self.normals = (vertex_normals(v, t) if normals is None else np.asarray(normals, dtype=np.float32))
        self.diag = float(np.linalg.norm(v.max(0) - v.min(0))) if len(v) else 1.0
        self._scene = rtcore_scene.EmbreeScene(robust=True)  # watertight: rays through vertices/edges hit
        TriangleMesh(self._scene, v.astype(np.float32), t)
        self.stats = RayStats()

    def __getstate__(self):
        # the Embree scene is a C object: pickle the mesh and rebuild it (process pools, Dask workers)
        return {"vertices": self.vertices, "triangles": self.triangles, "normals": self.normals}

    def __setstate__(self, state):
        self.__init__(state["vertices"], state["triangles"], state["normals"])

    @property
    def default_eps(self) -> float:
        return 1e-4 * self.diag

    def intersect(self, origins, dirs, tfar=None, *, retry=None) -> dict:
        """First hits of rays: dict with ``tri`` (M,) int32 (−1 miss), ``u``, ``v`` (Embree barycentrics, hit =
        (1−u−v)·v0 + u·v1 + v·v2) and ``t`` (M,) distance along the unit direction.

        Embree (even in its robust mode, which is used) misses about 1 % of rays that pass *exactly* through a
        vertex.  ``retry`` — True for all misses, or a boolean (M,) array selecting which misses — re-casts those
        rays once with the direction tilted by 1e-6 rad (≈ 0.6 µm at 600 mm).
        """
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(dirs, dtype=np.float32)
        tf = None if tfar is None else np.ascontiguousarray(np.broadcast_to(tfar, (len(o),)), dtype=np.float32)
        t0 = time.perf_counter()
        res = self._run(o, d, tf)
        n = len(o)
        if retry is not None and retry is not False:
            miss = res["primID"] < 0
            if retry is not True:
                miss &= np.asarray(retry, dtype=bool)
            idx = np.nonzero(miss)[0]
            if idx.size:
                dd = d[idx].astype(np.float64)
                perp = np.cross(dd, np.where(np.abs(dd[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
                perp /= np.linalg.norm(perp, axis=1, keepdims=True)
                d2 = dd + 1e-6 * perp
                d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
                r2 = self._run(o[idx], d2.astype(np.float32), None if tf is None else tf[idx])
                for k in ("primID", "u", "v", "tfar"):
                    res[k][idx] = r2[k]
                n += idx.size
        self.stats = RayStats(n, 0, time.perf_counter() - t0)
        return {"tri": res["primID"].astype(np.int32), "u": res["u"], "v": res["v"], "t": res["tfar"]}

    def _run(self, o, d, tf):
        if len(o) == 0:
            z = np.zeros(0, dtype=np.float32)
            return {"primID": np.zeros(0, dtype=np.int32), "u": z, "v": z.copy(), "tfar": z.copy()}
        if tf is None:
            return self._scene.run(o, d, output=1)
        return self._scene.run(o, d, dists=tf, output=1)

    def occluded(self, origins, dirs, tfar) -> np.ndarray:
        """(M,) bool: is anything hit along each ray before distance ``tfar``?"""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(dirs, dtype=np.float32)
        if len(o) == 0:
            return np.zeros(0, dtype=bool)
        res = self._scene.run(o, d, dists=np.ascontiguousarray(tfar, dtype=np.float32), query="OCCLUDED")
        return res != -1


@dataclass
class Raster:
    """Per-pixel result of :func:`rasterize` (H×W images; background: tri_id −1, zeros elsewhere).

    Attributes:
        tri_id: (H, W) int32 triangle index or −1.
        bary: (H, W, 3) float32 barycentric weights of the triangle's three vertices.
        depth: (H, W) float32 camera-space Z (mm) of the hit; 0 on background.
        position: (H, W, 3) float32 model-space hit point.
        normal: (H, W, 3) float32 unit interpolated vertex normal (model space).
        mask: (H, W) bool, ``tri_id >= 0``.
    """

    tri_id: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    mask: np.ndarray

    def interpolate(self, values, triangles) -> np.ndarray:
        """(H, W, C) per-vertex ``values`` (N, C) interpolated at the hits (0 on background)."""
        vals = np.asarray(values)
        vals2 = vals.reshape(vals.shape[0], -1)
        out = np.zeros(self.mask.shape + (vals2.shape[1],), dtype=np.float32)
        tri = np.asarray(triangles)[self.tri_id[self.mask]]
        b = self.bary[self.mask]
        out[self.mask] = np.einsum("mk,mkc->mc", b, vals2[tri])
        return out.reshape(self.mask.shape + vals.shape[1:])


def rasterize(scene: RayScene, camera: Camera) -> Raster:
    """Cast one ray per pixel centre of ``camera`` into ``scene``."""
    H, W = camera.height, camera.width
    o, d = camera.rays()
    hit = scene.intersect(o, d)
    tri = hit["tri"].reshape(H, W)
    miss = tri < 0
    if miss.any() and (~miss).any():
        # a miss with a hit 4-neighbour may be a ray exactly through a vertex: retry those only
        near = np.zeros_like(miss)
        near[1:] |= ~miss[:-1]
        near[:-1] |= ~miss[1:]
        near[:, 1:] |= ~miss[:, :-1]
        near[:, :-1] |= ~miss[:, 1:]
        sel = (miss & near).ravel()
        if sel.any():
            idx = np.nonzero(sel)[0]
            h2 = scene.intersect(o[idx], d[idx], retry=True)
            for k in hit:
                hit[k][idx] = h2[k]
            tri = hit["tri"].reshape(H, W)
    mask = tri >= 0
    m = mask.ravel()
    bary = np.zeros((H * W, 3), dtype=np.float32)
    bu, bv = hit["u"][m], hit["v"][m]
    bary[m, 0] = 1.0 - bu - bv
    bary[m, 1] = bu
    bary[m, 2] = bv
    bary[m] = np.clip(bary[m], 0.0, 1.0)
    bary[m] /= bary[m].sum(1, keepdims=True)
    tv = scene.triangles[tri.ravel()[m]]
    pos = np.zeros((H * W, 3), dtype=np.float32)
    pos[m] = np.einsum("mk,mkc->mc", bary[m], scene.vertices[tv])
    nrm = np.zeros((H * W, 3), dtype=np.float32)
    n = np.einsum("mk,mkc->mc", bary[m], scene.normals[tv].astype(np.float64))
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    nrm[m] = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    depth = np.zeros(H * W, dtype=np.float32)
    depth[m] = (pos[m].astype(np.float64) @ camera.R[2] + camera.t[2])
    return Raster(tri, bary.reshape(H, W, 3), depth.reshape(H, W), pos.reshape(H, W, 3), nrm.reshape(H, W, 3),
                  mask)


def _segment_test(scene: RayScene, points, normals, target, eps, what: str):
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if n is not None and n.shape != p.shape:
        raise ReflectmmError(f"{what}: normals {n.shape} do not match points {p.shape}")
    eps = scene.default_eps if eps is None else float(eps)
    tgt = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if tgt.shape[0] not in (1, p.shape[0]):
        raise ReflectmmError(f"{what}: target must be (3,) or ({p.shape[0]}, 3), got {tgt.shape}")
    return p, n, tgt, eps


def _occlusion(scene: RayScene, p, n, tgt, eps, active):
    """True where the segment from p (offset) to tgt hits the mesh; only for ``active`` points."""
    out = np.zeros(p.shape[0], dtype=bool)
    idx = np.nonzero(active)[0]
    if idx.size == 0:
        return out
    pa = p[idx]
    ta = tgt[idx] if tgt.shape[0] > 1 else tgt
    d = ta - pa
    dist = np.linalg.norm(d, axis=1)
    d = d / np.maximum(dist, 1e-30)[:, None]
    o = pa + eps * d
    if n is not None:
        o = o + eps * n[idx]
    tfar = np.maximum(dist - 2 * eps, 0.0)
    out[idx] = scene.occluded(o, d, tfar)
    return out


def visibility(scene: RayScene, points, normals, eye, *, eps: float | None = None) -> np.ndarray:
    """(M,) bool: each point sees ``eye`` (3,) unoccluded and faces it (n·v > 0 when normals are given).

    Without normals only occlusion by *other* surfaces is tested: a point on the far side of an open mesh
    whose ray leaves through nothing counts as visible.  Counters in ``scene.stats``.
    """
    t0 = time.perf_counter()
    p, n, tgt, eps = _segment_test(scene, points, normals, eye, eps, "visibility")
    active = np.ones(p.shape[0], dtype=bool)
    if n is not None:
        active = ((tgt - p) * n).sum(1) > 0
    occ = _occlusion(scene, p, n, tgt, eps, active)
    scene.stats = RayStats(int(active.sum()), int((~active).sum()), time.perf_counter() - t0)
    return active & ~occ


def shadow_mask(scene: RayScene, points, normals, light_pos, *, eps: float | None = None) -> np.ndarray:
    """(M,) bool ``lit``: n·l > 0 and no triangle between the point and the point light ``light_pos``.

    Points with n·l ≤ 0 are unlit without a ray; ``scene.stats.skipped`` counts them (logged at debug level).
    Without normals every point casts a ray and only occlusion is tested (see :func:`visibility`).
    """
    t0 = time.perf_counter()
    p, n, tgt, eps = _segment_test(scene, points, normals, light_pos, eps, "shadow_mask")
    active = np.ones(p.shape[0], dtype=bool) if n is None else ((tgt - p) * n).sum(1) > 0
    occ = _occlusion(scene, p, n, tgt, eps, active)
    scene.stats = RayStats(int(active.sum()), int((~active).sum()), time.perf_counter() - t0)
    log.debug("shadow rays: %d cast, %d skipped (n·l ≤ 0), %.0f rays/s", scene.stats.cast, scene.stats.skipped,
              scene.stats.rays_per_second)
    return active & ~occ

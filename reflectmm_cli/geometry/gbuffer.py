"""Per-pixel G-buffers of fixed geometry, rasterised once with Embree (docs/design.md §7, docs/wild.md).

A G-buffer holds, for every face pixel of an S×S image (the pixels whose centre ray hits the face model):

* ``pix_yx`` (P, 2) int16 — (row, col) of the pixel;
* ``vert_ids`` (P, 3) int32 — the face model's vertex ids of the triangle hit at the pixel centre;
* ``bary`` (P, 3) float32 — the hit's barycentrics (sum 1): per-vertex values interpolate as a rasteriser would;
* ``normal``, ``view``, ``reflect`` (P, 3) — unit shading normal (barycentric interpolation of the vertex
  normals, renormalised), unit direction surface → camera centre, ``r = 2(n·v)n − v``; float16 by default;
* ``visible`` (P,) bool — ``n·v > 0`` (the shading normal faces the camera);
* ``face_mask`` (S, S) bool — the pixels listed above.

Frame of the directions: the **light frame** (the frame of the SH lighting and of shading/envmap.py: +y up,
the camera looks down −z, +x right).  The camera is fixed in it: a direction in OpenCV camera axes ``d_cv`` is
``d_light = diag(1, −1, −1) · d_cv``, so a model-space direction ``d`` is ``diag(1, −1, −1) · R · d``.
Lighting coefficients given in model space convert with :func:`light_from_model_sh`.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .camera import Camera
from .raycast import Raster, RayScene, rasterize

__all__ = ["CV_TO_LIGHT", "GBUFFER_KEYS", "model_to_light", "light_from_model_sh", "gbuffer_from_raster",
           "gbuffer_for_image", "pack_gbuffers", "unpack_gbuffer", "shade_gbuffer", "gbuffer_nbytes"]

#: OpenCV camera axes → light frame (y and z flip).
CV_TO_LIGHT = np.diag([1.0, -1.0, -1.0])

#: The per-pixel arrays of one G-buffer, in the order they are packed.
GBUFFER_KEYS = ("pix_yx", "vert_ids", "bary", "normal", "view", "reflect", "visible")


def model_to_light(R) -> np.ndarray:
    """(3, 3) rotation taking model-space directions to the light frame: ``diag(1, −1, −1) · R``."""
    return CV_TO_LIGHT @ np.asarray(R, dtype=np.float64).reshape(3, 3)


def light_from_model_sh(sh_model, R) -> np.ndarray:
    """SH radiance coefficients (3, (L+1)²) given in model space → the light frame of a camera with rotation R.

    The light frame is the model frame carried by ``M = model_to_light(R)``: ``L_light(d) = L_model(Mᵀ d)``, i.e.
    ``K_light = K_model · sh_rotation(M, L)ᵀ``.
    """
    from reflectmm_cli.shading import sh_order, sh_rotation

    K = np.asarray(sh_model, dtype=np.float64)
    order = sh_order(K.shape[-1])
    return K @ sh_rotation(model_to_light(R), order).T


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def gbuffer_from_raster(raster: Raster, triangles, camera: Camera, *, dtype=np.float16) -> dict[str, np.ndarray]:
    """The G-buffer (see the module docstring) of an existing :func:`rasterize` result.

    ``dtype`` of normal/view/reflect: float16 (the shard format) or float32/float64 (tests, exact shading).
    Directions are computed in float64 from the raster's float32 position/normal, then rounded once.
    """
    m = raster.mask
    rows, cols = np.nonzero(m)
    tri = np.asarray(triangles)[raster.tri_id[m]]
    M = model_to_light(camera.R)
    n_model = raster.normal[m].astype(np.float64)
    v_model = _unit(camera.center[None, :] - raster.position[m].astype(np.float64))
    n = _unit(n_model) @ M.T
    v = v_model @ M.T
    ndv = (n * v).sum(1)
    r = 2.0 * ndv[:, None] * n - v
    r = _unit(r)
    H, W = m.shape
    if max(H, W) > np.iinfo(np.int16).max:
        raise ReflectmmError(f"G-buffer: image {W}x{H} too large for int16 pixel coordinates")
    return {
        "pix_yx": np.stack([rows, cols], 1).astype(np.int16),
        "vert_ids": tri.astype(np.int32),
        "bary": raster.bary[m].astype(np.float32),
        "normal": n.astype(dtype),
        "view": v.astype(dtype),
        "reflect": r.astype(dtype),
        "visible": ndv > 0,
        "face_mask": m.copy(),
    }


def gbuffer_for_image(face_model, shape, expression, R, t, K, size: int | tuple[int, int], *,
                      dtype=np.float16, scene: RayScene | None = None) -> dict[str, np.ndarray]:
    """Rasterise the face model with coefficients (shape, expression) seen by camera (K, R, t) into a G-buffer.

    Args:
        face_model: a :class:`~reflectmm_cli.geometry.FaceModel` (vertices in mm).
        shape: (Ks,) shape coefficients; expression: (Ke,) expression coefficients (or None).
        R: (3, 3) rotation model → OpenCV camera; t: (3,) translation (mm); K: (3, 3) intrinsics (pixels).
        size: S (square) or (W, H) of the image.
        dtype: dtype of normal/view/reflect (float16 in the shard format).
        scene: an existing :class:`RayScene` of exactly these vertices (skips building one).
    Returns:
        dict of the arrays of the module docstring (P = number of face pixels) plus ``face_mask`` (H, W).
    """
    W, H = (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))
    cam = Camera(K, R, t, W, H, "gbuffer")
    if scene is None:
        verts = face_model.vertices(shape, expression).astype(np.float64)
        scene = RayScene(verts, face_model.triangles)
    ras = rasterize(scene, cam)
    return gbuffer_from_raster(ras, face_model.triangles, cam, dtype=dtype)


def pack_gbuffers(gbuffers: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate the per-pixel arrays of N G-buffers: ``pix_offset`` (N+1,) int64 plus :data:`GBUFFER_KEYS`.

    Image i owns rows ``pix_offset[i]:pix_offset[i+1]``.  ``face_mask`` is stacked to (N, H, W) when present.
    """
    counts = [len(g["pix_yx"]) for g in gbuffers]
    out = {"pix_offset": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)}
    for k in GBUFFER_KEYS:
        if gbuffers:
            out[k] = np.concatenate([np.asarray(g[k]) for g in gbuffers], 0)
    if gbuffers and all("face_mask" in g for g in gbuffers):
        out["face_mask"] = np.stack([np.asarray(g["face_mask"], bool) for g in gbuffers])
    return out


def unpack_gbuffer(packed: Mapping[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """The G-buffer of image ``i`` of a packed set (views into the packed arrays where possible)."""
    off = np.asarray(packed["pix_offset"])
    a, b = int(off[i]), int(off[i + 1])
    out = {k: packed[k][a:b] for k in GBUFFER_KEYS}
    if "face_mask" in packed:
        out["face_mask"] = packed["face_mask"][i]
    return out


def shade_gbuffer(gbuffer: Mapping[str, np.ndarray], vertex_albedo, vertex_weights, exponents, sh_light, *,
                  dtype=np.float64):
    """Shade one G-buffer with the project's model: per-vertex albedo (V,3) / lobe weights (V,K) interpolated
    with ``bary`` at ``vert_ids``, then :func:`reflectmm_cli.shading.shade_env` with lighting ``sh_light``
    (3, (L+1)²) in the light frame.  Returns (diffuse (P,3), specular (P,3)) in ``dtype``.
    """
    from reflectmm_cli.shading import shade_env

    ids = np.asarray(gbuffer["vert_ids"])
    b = np.asarray(gbuffer["bary"], dtype=np.float64)
    c = np.einsum("pk,pkc->pc", b, np.asarray(vertex_albedo, np.float64)[ids])
    w = np.einsum("pk,pkc->pc", b, np.asarray(vertex_weights, np.float64)[ids])
    n = np.asarray(gbuffer["normal"], dtype=dtype)
    v = np.asarray(gbuffer["view"], dtype=dtype)
    return shade_env(c.astype(dtype), w.astype(dtype), np.asarray(exponents, np.float64), n, v,
                     np.asarray(sh_light, np.float64))


def gbuffer_nbytes(gbuffer: Mapping[str, np.ndarray]) -> int:
    """Bytes of the per-pixel arrays (what a shard stores per image, without the masks)."""
    return int(sum(np.asarray(gbuffer[k]).nbytes for k in GBUFFER_KEYS))

"""A small physically based renderer on top of :mod:`raycast` and :mod:`reflectmm_cli.shading`.

Radiance per pixel = the shading of docs/design.md §2 at the first hit of the pixel's primary ray:

* point light of radiant intensity ``I`` at ``light_pos``: ``E = I / d²`` and ``shade_directional`` with
  ``l = normalize(light_pos − x)``, ``v = normalize(c − x)`` (c = camera centre); optional cast shadows by a
  shadow ray per lit pixel (pixels with n·l ≤ 0 cost no ray);
* SH environment light: ``shade_env`` (diffuse + specular), no visibility (the SH model has none).

Reflectance is per vertex (albedo (N,3), weights (N,K)) — interpolated with the hit's barycentrics — or UV maps
(albedo (3,S,S), weights (K,S,S)) sampled bilinearly at the interpolated UV of the hit.  Output images are
linear radiance (H, W, 3) float32, 0 on the background.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError

from .camera import Camera
from .raycast import Raster, RayScene, rasterize, shadow_mask
from .uv import sample_uv_map

__all__ = ["RenderResult", "surface_reflectance", "render_point_light", "render_envmap", "to_display"]


@dataclass
class RenderResult:
    """image (H,W,3) linear radiance; mask (H,W) face pixels; lit (H,W) pixels lit by the light (n·l > 0 and
    unshadowed; all of ``mask`` for environment light); raster: the primary-ray raster; rays: shadow-ray
    counts {cast, skipped}."""

    image: np.ndarray
    mask: np.ndarray
    lit: np.ndarray
    raster: Raster
    rays: dict


def _is_map(a: np.ndarray) -> bool:
    return a.ndim == 3 and a.shape[1] == a.shape[2]


def surface_reflectance(raster: Raster, triangles, albedo, weights, uv=None) -> tuple[np.ndarray, np.ndarray]:
    """(albedo (M,3), weights (M,K)) at the M hit pixels of ``raster`` (row-major order of ``raster.mask``).

    ``albedo``/``weights`` are per vertex ((N,3)/(N,K)) or UV maps ((3,S,S)/(K,S,S), then ``uv`` (N,2) is
    required).
    """
    a = np.asarray(albedo, dtype=np.float32)
    w = np.asarray(weights, dtype=np.float32)
    m = raster.mask
    tri = np.asarray(triangles)[raster.tri_id[m]]
    b = raster.bary[m].astype(np.float64)
    if _is_map(a) and a.shape[0] == 3:
        if uv is None:
            raise ReflectmmError("render: UV-map reflectance needs the face model's vertex UVs")
        if not _is_map(w) or w.shape[1:] != a.shape[1:]:
            raise ReflectmmError(f"render: weights map must be (K, {a.shape[1]}, {a.shape[2]}), got {w.shape}")
        puv = np.einsum("mk,mkc->mc", b, np.asarray(uv, dtype=np.float64)[tri])
        return sample_uv_map(a, puv).astype(np.float32), sample_uv_map(w, puv).astype(np.float32)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ReflectmmError(f"render: albedo must be (N, 3) per vertex or (3, S, S) in UV, got {a.shape}")
    if w.ndim != 2 or w.shape[0] != a.shape[0]:
        raise ReflectmmError(f"render: weights must be ({a.shape[0]}, K) per vertex, got {w.shape}")
    return (np.einsum("mk,mkc->mc", b, a[tri].astype(np.float64)).astype(np.float32),
            np.einsum("mk,mkc->mc", b, w[tri].astype(np.float64)).astype(np.float32))


def _rgb(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ReflectmmError(f"render: {name} must be a finite scalar or RGB triple, got {np.shape(x)}")
    return a


def render_point_light(scene: RayScene, camera: Camera, albedo, weights, exponents, light_pos, intensity=1.0, *,
                       uv=None, shadows: bool = False, raster: Raster | None = None) -> RenderResult:
    """Render under one point light of radiant intensity ``intensity`` (scalar or RGB) at ``light_pos`` (mm)."""
    from reflectmm_cli.shading import shade_directional

    r = rasterize(scene, camera) if raster is None else raster
    m = r.mask
    I = _rgb(intensity, "intensity")
    L = np.asarray(light_pos, dtype=np.float64).reshape(3)
    img = np.zeros(m.shape + (3,), dtype=np.float32)
    lit_img = np.zeros(m.shape, dtype=bool)
    rays = {"cast": 0, "skipped": 0}
    if not m.any():
        return RenderResult(img, m, lit_img, r, rays)
    x = r.position[m].astype(np.float64)
    n = r.normal[m].astype(np.float64)
    c, w = surface_reflectance(r, scene.triangles, albedo, weights, uv)
    ld = L - x
    d2 = (ld * ld).sum(1)
    vd = camera.center - x
    lit = (ld * n).sum(1) > 0
    if shadows:
        lit = shadow_mask(scene, x, n, L)
        rays = {"cast": scene.stats.cast, "skipped": scene.stats.skipped}
    E = I[None, :] / np.maximum(d2, 1e-30)[:, None]
    s = shade_directional(c.astype(np.float64), w.astype(np.float64), np.asarray(exponents, dtype=np.float64), n, ld,
                          vd, E)
    s = np.where(lit[:, None], s, 0.0)
    img[m] = s
    lit_img[m] = lit
    return RenderResult(img, m, lit_img, r, rays)


def render_envmap(scene: RayScene, camera: Camera, albedo, weights, exponents, sh_coeffs, *, uv=None,
                  raster: Raster | None = None, band_tol: float = 0.0) -> RenderResult:
    """Render under SH environment lighting ``sh_coeffs`` (3, (L+1)²) (frame: model space, +y up)."""
    from reflectmm_cli.shading import shade_env

    r = rasterize(scene, camera) if raster is None else raster
    m = r.mask
    img = np.zeros(m.shape + (3,), dtype=np.float32)
    K = np.asarray(sh_coeffs, dtype=np.float64)
    if K.ndim != 2 or K.shape[0] != 3:
        raise ReflectmmError(f"render: SH coefficients must be (3, (L+1)²), got {K.shape}")
    if m.any():
        x = r.position[m].astype(np.float64)
        n = r.normal[m].astype(np.float64)
        c, w = surface_reflectance(r, scene.triangles, albedo, weights, uv)
        diff, spec = shade_env(c.astype(np.float64), w.astype(np.float64), np.asarray(exponents, dtype=np.float64),
                               n, camera.center - x, K, band_tol=band_tol)
        img[m] = diff + spec
    return RenderResult(img, m, m.copy(), r, {"cast": 0, "skipped": 0})


def to_display(image: np.ndarray, exposure: float | None = None, transfer: str = "srgb") -> np.ndarray:
    """Linear (H,W,3) → display [0,1]: scale by ``exposure`` (default: the 99.5th percentile of the non-zero
    pixels maps to 0.9), then sRGB (``transfer='srgb'``), a 1/2.2 power (``'gamma'``) or a 1/1.2 power
    (``'gamma1.2'``), clipped; float64.
    :func:`reflectmm_cli.color.encode_display` with ``exposure='auto'`` by default."""
    return encode_display(image, transfer, "auto" if exposure is None else exposure, dtype=np.float64)

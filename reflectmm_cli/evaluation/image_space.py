"""Image-space re-rendering of fitted maps against the captured OLAT images (the paper's protocol).

For one identity: the fitted mesh (``geometry`` artifact: vertices, per-view K, R, t) and the face model's
triangles and vertex UVs are ray cast (Embree, :func:`reflectmm_cli.geometry.rasterize`) into each view's stored
capture window (``capture`` artifact: ``crop_origin`` + OLAT crops); each pixel's reflectance is looked up in the
UV maps at its interpolated UV (:func:`reflectmm_cli.geometry.surface_reflectance`) and shaded with
:func:`reflectmm_cli.shading.shade_directional` under the point flash (E = I/d², position and intensity from the
geometry artifact). The face region of a pair is: rendered face pixels ∧ lit (n·l > 0 and no occluder between the
point and the flash, ray cast) ∧ n·v > 0 ∧ not saturated in the capture.

Rasters and shadow masks do not depend on the reflectance, so they are computed once per view / pair and shared by
every representation.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["ImageSpaceRenderer"]


class ImageSpaceRenderer:
    """Renders maps into one identity's capture windows. ``capture``/``geometry``: artifact arrays."""

    def __init__(self, capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray], triangles: np.ndarray,
                 uv: np.ndarray, name: str = "", domain: np.ndarray | None = None):
        from reflectmm_cli.geometry import RayScene, has_embree

        if not has_embree():
            raise ReflectmmError("image-space evaluation needs Embree ray casting (the 'embreex' package)")
        self.name = name
        self.capture = capture
        self.geometry = geometry
        self.uv = np.asarray(uv, np.float64)
        self.triangles = np.asarray(triangles)
        verts = np.asarray(geometry["vertices"], np.float64)
        if self.uv.shape != (verts.shape[0], 2):
            raise ReflectmmError(f"{name}: face model has {self.uv.shape[0]} vertex UVs but the fitted mesh has "
                                 f"{verts.shape[0]} vertices")
        self.scene = RayScene(verts, self.triangles)
        self.cap_views = [str(x) for x in np.asarray(capture["view_names"])]
        self.cap_flashes = [str(x) for x in np.asarray(capture["flash_ids"])]
        self.geo_views = [str(x) for x in np.asarray(geometry["view_names"])]
        self.geo_flashes = [str(x) for x in np.asarray(geometry["flash_ids"])]
        self._rasters: dict[str, object] = {}
        self._lit: dict[tuple[str, str], np.ndarray] = {}
        self._refl: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}
        self.domain: np.ndarray | None = None
        self._inside: dict[str, np.ndarray] = {}
        if domain is not None:
            self.set_domain(domain)

    def set_domain(self, domain: np.ndarray | None) -> None:
        """Restrict every region to pixels whose bilinear UV footprint lies in the (S,S) bool ``domain``."""
        self.domain = None if domain is None else np.asarray(domain, bool)
        self._inside.clear()
        self._lit.clear()

    def inside(self, view: str) -> np.ndarray:
        """(h,w) bool: face pixels of ``view`` whose bilinear UV lookup uses only texels of the domain."""
        from reflectmm_cli.geometry import surface_reflectance

        cam, r = self.raster(view)
        if self.domain is None:
            return r.mask
        if view not in self._inside:
            d = self.domain.astype(np.float32)
            cov, _ = surface_reflectance(r, self.triangles, np.repeat(d[None], 3, 0), np.zeros((1,) + d.shape),
                                         self.uv)
            full = np.zeros(r.mask.shape, bool)
            full[r.mask] = cov[:, 0] >= 1.0 - 1e-5
            self._inside[view] = full
        return self._inside[view]

    def _index(self, names, name, what):
        try:
            return names.index(name)
        except ValueError:
            raise ReflectmmError(f"{self.name}: {what} '{name}' not found (have {', '.join(names)})") from None

    def raster(self, view: str):
        """The raster of the capture window of ``view`` (cached)."""
        from reflectmm_cli.geometry import Camera, rasterize

        if view not in self._rasters:
            g = self._index(self.geo_views, view, "geometry view")
            c = self._index(self.cap_views, view, "capture view")
            x0, y0 = (int(v) for v in np.asarray(self.capture["crop_origin"])[c])
            h, w = np.asarray(self.capture["olat"]).shape[2:4]
            K = np.array(self.geometry["K"][g], np.float64)
            K[0, 2] -= x0
            K[1, 2] -= y0
            cam = Camera(K, self.geometry["R"][g], self.geometry["t"][g], w, h, view)
            self._rasters[view] = (cam, rasterize(self.scene, cam))
        return self._rasters[view]

    def region(self, view: str, flash: str) -> np.ndarray:
        """(h,w) bool face region of a pair: face ∧ lit (ray-cast shadows) ∧ n·v > 0 ∧ not saturated."""
        from reflectmm_cli.geometry import shadow_mask

        key = (view, flash)
        if key not in self._lit:
            cam, r = self.raster(view)
            f = self._index(self.geo_flashes, flash, "geometry flash")
            L = np.asarray(self.geometry["flash_pos"][f], np.float64)
            m = r.mask
            x = r.position[m].astype(np.float64)
            n = r.normal[m].astype(np.float64)
            lit = shadow_mask(self.scene, x, n, L) & (((cam.center - x) * n).sum(1) > 0)
            full = np.zeros(m.shape, bool)
            full[m] = lit
            full &= self.inside(view)
            c = self._index(self.cap_views, view, "capture view")
            cf = self._index(self.cap_flashes, flash, "capture flash")
            if "saturated" in self.capture:
                full &= ~np.asarray(self.capture["saturated"][c, cf], bool)
            self._lit[key] = full
        return self._lit[key]

    def target(self, view: str, flash: str) -> np.ndarray:
        c = self._index(self.cap_views, view, "capture view")
        f = self._index(self.cap_flashes, flash, "capture flash")
        return np.asarray(self.capture["olat"][c, f], np.float64)

    def render(self, albedo: np.ndarray, weights: np.ndarray | None, exponents, view: str, flash: str,
               key: int | None = None) -> np.ndarray:
        """(h,w,3) linear radiance of the maps in the capture window of (view, flash); 0 outside the region.
        ``key`` caches the per-pixel reflectance lookup of one set of maps per view."""
        from reflectmm_cli.geometry import surface_reflectance
        from reflectmm_cli.shading import shade_directional

        cam, r = self.raster(view)
        reg = self.region(view, flash)
        m = r.mask
        ck = (key, view) if key is not None else None
        if ck is not None and ck in self._refl:
            c, w = self._refl[ck]
        else:
            W = np.zeros((1,) + np.shape(albedo)[1:]) if weights is None or len(exponents) == 0 else weights
            c, w = surface_reflectance(r, self.triangles, albedo, W, self.uv)
            if ck is not None:
                self._refl[ck] = (c, w)
        p = np.asarray(exponents if len(exponents) else [1.0], np.float64)
        f = self._index(self.geo_flashes, flash, "geometry flash")
        L = np.asarray(self.geometry["flash_pos"][f], np.float64)
        I = float(np.asarray(self.geometry["flash_intensity"], np.float64).reshape(-1)[f])
        x = r.position[m].astype(np.float64)
        n = r.normal[m].astype(np.float64)
        ld = L - x
        E = I / np.maximum((ld * ld).sum(1), 1e-30)
        s = shade_directional(c.astype(np.float64), w.astype(np.float64), p, n, ld, cam.center - x,
                              np.repeat(E[:, None], 3, 1))
        out = np.zeros(m.shape + (3,))
        out[m] = s
        out[~reg] = 0.0
        return out

"""PNG previews of a reflectance model: principal components (paper Fig. 1 style) and random samples rendered
under a white frontal point light.

Display conventions: diffuse albedo in sRGB (linear → sRGB transfer, clipped), lobe weights ×3 shown as RGB
(lobe i → channel i for K = 3; for other K the sum Σw ×3 as grey), background grey.

Renders: the face model's mean shape seen by a perspective camera on +z, 600 mm in front of the nose (focal
chosen to frame the face), with a point light of radiant intensity ``I = π · d0²`` at the camera centre (so that
a frontal texel at the head-centre distance d0 receives irradiance π: white albedo shades to 1). With Embree the
geometry renderer is used (UV maps looked up per pixel); otherwise the per-vertex model is shaded with
:func:`reflectmm_cli.shading.shade_directional` and splatted with a z-buffer over dense barycentric samples of
every triangle (every covered pixel receives at least one sample, so there are no holes).
"""
from __future__ import annotations

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError

from .pca import ReflectanceModel, sample_model

__all__ = ["srgb_preview", "weights_to_rgb", "component_grid", "VertexSplat", "render_vertex_colors", "render_samples"]

BG = 0.5


def srgb_preview(x: np.ndarray) -> np.ndarray:
    """Linear (*) → float64 sRGB display values (clipped to [0, 1]; NaN stays NaN)."""
    return encode_display(x, "srgb", nan_to_num=False, dtype=np.float64)


def weights_to_rgb(w: np.ndarray, gain: float = 3.0) -> np.ndarray:
    """(K,S,S) lobe weights → (S,S,3) display image (×gain, clipped)."""
    w = np.asarray(w, np.float64)
    if w.shape[0] == 3:
        img = np.moveaxis(w, 0, -1)
    else:
        img = np.repeat(w.sum(0)[..., None], 3, -1)
    return np.clip(img * gain, 0, 1)


def component_grid(model: ReflectanceModel, n_components: int = 3, spread: float = 2.0, pad: int = 2
                   ) -> np.ndarray:
    """Rows: mean, then component k at −spread·σ and +spread·σ. Columns: albedo (sRGB) −/mean/+ and weights ×3
    −/mean/+. Returns (H,W,3) in [0,1]."""
    m = min(n_components, model.n_components)
    mask = model.mask
    S = model.size

    def tile(img):
        t = np.where(mask[..., None], img, BG)
        return np.pad(t, ((pad, pad), (pad, pad), (0, 0)), constant_values=1.0)

    rows = []
    for k in range(m):
        beta_m = np.zeros(k + 1)
        beta_m[k] = -spread
        beta_p = -beta_m
        am, wm = sample_model(model, beta_m)
        ap, wp = sample_model(model, beta_p)
        a0, w0 = model.albedo_mean, model.weights_mean
        cells = [srgb_preview(np.moveaxis(a, 0, -1)) for a in (am, a0, ap)]
        cells += [weights_to_rgb(w) for w in (wm, w0, wp)]
        rows.append(np.concatenate([tile(c) for c in cells], 1))
    if not rows:
        raise ReflectmmError("component_grid: the model has no component")
    assert rows[0].shape[0] == S + 2 * pad
    return np.concatenate(rows, 0)


def _frontal_camera(vertices: np.ndarray, width: int, distance: float = 600.0):
    lo, hi = vertices.min(0), vertices.max(0)
    centre = 0.5 * (lo + hi)
    extent = max(hi[0] - lo[0], hi[1] - lo[1]) * 1.08
    eye = np.array([centre[0], centre[1], hi[2] + distance])
    f = width * (distance + (hi[2] - centre[2])) / max(extent, 1e-6)
    return eye, centre, f


class VertexSplat:
    """The visibility of a z-buffered splat of a mesh, worked out once and reused for any per-vertex colours.

    Dense barycentric samples of every triangle are projected by a pinhole camera at ``eye`` looking down −z
    (focal ``focal`` px, principal point at the image centre); each pixel keeps its nearest sample (ties: the
    first triangle). Only the colours change between the renders of one figure, so :meth:`render` interpolates
    the kept samples' vertex colours and touches no geometry.

    Args:
        vertices: (N, 3) positions (mm).
        triangles: (F, 3) vertex indices.
        width: image side (px).
        eye, focal: the camera; both None frames the mesh from the front (600 mm in front of its nose).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, width: int = 160, eye: np.ndarray | None = None,
                 focal: float | None = None):
        V = np.asarray(vertices, np.float64)
        T = np.asarray(triangles, np.int64)
        if eye is None or focal is None:
            eye, _, focal = _frontal_camera(V, width)
        c = width / 2.0
        rel = V - eye
        z = -rel[:, 2]
        if np.any(z <= 1e-6):
            raise ReflectmmError("render: vertices behind the preview camera")
        px = np.stack([focal * rel[:, 0] / z + c - 0.5, -focal * rel[:, 1] / z + c - 0.5], -1)
        # subdivision level from the largest projected edge so every covered pixel gets a sample
        e = np.concatenate([np.linalg.norm(px[T[:, a]] - px[T[:, b]], axis=1) for a, b in ((0, 1), (1, 2), (2, 0))])
        n = int(np.clip(np.ceil(np.percentile(e, 99.5) * 1.5), 1, 64))
        ij = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)], np.float64) / n
        bary = np.stack([1 - ij.sum(1), ij[:, 0], ij[:, 1]], -1)  # (B,3)
        B = len(bary)
        zbuf = np.full(width * width, np.inf)
        winner = np.full(width * width, -1, np.int64)  # flat sample index triangle * B + b
        step = max(1, 200000 // B)
        for a in range(0, T.shape[0], step):
            t = T[a:a + step]
            p = np.einsum("bk,tkd->tbd", bary, px[t]).reshape(-1, 2)
            zz = np.einsum("bk,tk->tb", bary, z[t]).reshape(-1)
            sid = a * B + np.arange(zz.size)
            ix = np.rint(p).astype(np.int64)
            ok = (ix[:, 0] >= 0) & (ix[:, 0] < width) & (ix[:, 1] >= 0) & (ix[:, 1] < width)
            lin = ix[ok, 1] * width + ix[ok, 0]
            zz, sid = zz[ok], sid[ok]
            order = np.lexsort((zz, lin))
            lin, zz, sid = lin[order], zz[order], sid[order]
            first = np.ones(lin.size, bool)
            first[1:] = lin[1:] != lin[:-1]
            lin, zz, sid = lin[first], zz[first], sid[first]
            closer = zz < zbuf[lin]
            zbuf[lin[closer]] = zz[closer]
            winner[lin[closer]] = sid[closer]
        self.width = int(width)
        self.pixels = np.flatnonzero(winner >= 0)
        won = winner[self.pixels]
        self.corners = T[won // B]  # (P,3) vertex indices of the kept samples' triangles
        self.bary = bary[won % B]  # (P,3)
        self.n_vertices = V.shape[0]

    def render(self, colors: np.ndarray) -> np.ndarray:
        """(N, C) per-vertex colours → (width, width, C), NaN where nothing is visible."""
        C = np.asarray(colors, np.float64)
        if C.ndim != 2 or C.shape[0] != self.n_vertices:
            raise ReflectmmError(f"render: colours of shape {C.shape}, expected ({self.n_vertices}, C)")
        out = np.full((self.width * self.width, C.shape[1]), np.nan)
        out[self.pixels] = np.einsum("pk,pkd->pd", self.bary, C[self.corners])
        return out.reshape(self.width, self.width, C.shape[1])


def render_vertex_colors(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray, width: int = 160,
                         eye: np.ndarray | None = None, focal: float | None = None, centre=None) -> np.ndarray:
    """Z-buffered splat of per-vertex colours (N,C) over dense barycentric samples of the triangles, seen by a
    pinhole camera at ``eye`` looking down −z. Returns (width, width, C) with NaN where nothing is visible.
    Several colourings of one mesh and camera: build one :class:`VertexSplat` and call its ``render``."""
    return VertexSplat(vertices, triangles, width, eye, focal).render(colors)


def render_samples(model: ReflectanceModel, vertices: np.ndarray, triangles: np.ndarray, n: int = 30,
                   seed: int = 0, width: int = 128, cols: int = 6, spread: float = 1.0, uv: np.ndarray | None = None
                   ) -> tuple[np.ndarray, str]:
    """Grid of ``n`` random samples (β ~ N(0, spread²)) rendered under a white frontal point light (sRGB).

    With Embree available and ``uv`` given, the geometry renderer
    (:func:`reflectmm_cli.geometry.render_point_light`: ray-cast rasterisation, UV-map reflectance looked up per
    pixel) is used; otherwise the per-vertex model is splatted (:func:`render_vertex_colors`). Returns the image
    and the name of the renderer used.
    """
    from reflectmm_cli.geometry.face_model import vertex_normals
    from reflectmm_cli.shading import shade_directional

    V = np.asarray(vertices, np.float64)
    eye, centre, focal = _frontal_camera(V, width)
    d0 = float(np.linalg.norm(eye - centre))
    intensity = np.pi * d0 ** 2  # irradiance π at the head centre: a white Lambertian texel facing the light → 1
    rng = np.random.default_rng(seed)
    betas = [rng.normal(0.0, spread, model.n_components) for _ in range(n)]
    renderer = "splat"
    scene = None
    if uv is not None:
        try:
            from reflectmm_cli.geometry import RayScene, has_embree, look_at, rasterize, render_point_light

            if has_embree():
                scene = RayScene(V, triangles)
                cam = look_at(eye, centre, focal_px=focal, width=width, height=width)
                raster = rasterize(scene, cam)
                renderer = "reflectmm_cli.geometry.render_point_light"
        except ImportError:  # pragma: no cover - geometry is part of the package
            scene = None
    if scene is None and not model.has_vertex_model:
        raise ReflectmmError("render_samples: the model has no per-vertex part and no renderer for UV maps")
    tiles = []
    if scene is None:
        nrm = np.asarray(vertex_normals(V, triangles), np.float64)
        ld = eye - V
        E = intensity / np.sum(ld * ld, -1)
        splat = VertexSplat(V, triangles, width, eye, focal)
    for beta in betas:
        if scene is not None:
            alb, wts = sample_model(model, beta)
            res = render_point_light(scene, cam, np.clip(alb, 0, None), np.clip(wts, 0, None), model.exponents,
                                     eye, intensity, uv=uv, raster=raster)
            img = np.where(res.mask[..., None], srgb_preview(res.image), BG)
        else:
            alb, wts = sample_model(model, beta, space="vertex")
            alb, wts = np.clip(alb, 0, None), np.clip(wts, 0, None)
            s = shade_directional(alb, wts, model.exponents, nrm, ld, ld, np.repeat(E[:, None], 3, -1))
            img = splat.render(s)
            img = np.where(np.isnan(img), BG, srgb_preview(np.nan_to_num(img)))
        tiles.append(np.pad(img, ((1, 1), (1, 1), (0, 0)), constant_values=1.0))
    while len(tiles) % cols:
        tiles.append(np.ones_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + cols], 1) for i in range(0, len(tiles), cols)]
    return np.concatenate(rows, 0), renderer

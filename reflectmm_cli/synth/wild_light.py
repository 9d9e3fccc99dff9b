"""Image-based GGX lighting for ``synth wild``: a map split into directional sources + a smooth residual.

An equirectangular HDR map (the convention of :mod:`reflectmm_cli.shading.envmap`) is split exactly into

* up to ``max_sources`` **directional sources** — the compact, very bright regions (sun, lamps): pixels whose
  radiance exceeds ``threshold`` × the map's median, grouped around the brightest pixel within
  ``source_radius``; each becomes one direction (power-weighted mean) with RGB irradiance ``Σ (L − fill) ΔΩ``;
* the **residual** map: the same map with those pixels replaced by ``fill`` (the median radiance of a ring
  around the source), so residual + sources carry exactly the map's energy.

Shading (docs/wild.md, "what is modelled"):

* sources: Lambert + GGX (:func:`reflectmm_cli.synth.ggx.ggx_directional`) × a shadow ray per pixel and source;
* residual, diffuse: ``c/π · E_SH(n) · AO`` with the order-8 SH irradiance and ray-traced ambient occlusion;
* residual, specular (split sum): ``ρ · E_ggx(α, n·v) · P_α(r) · V_spec`` with ``P_α`` the residual map
  prefiltered with the GGX lobe at normal view (``D(h)·(n·l)``, ``n = v = r``), ``E_ggx`` the GGX directional
  albedo at view angle ``n·v`` (:func:`ggx_view_albedo`) and ``V_spec`` the visible fraction of the lobe.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.synth.ggx import SKIN_F0, schlick_fresnel, smith_g2

__all__ = ["PREFILTER_ALPHAS", "ggx_view_albedo", "sample_ggx_h", "equirect_lookup", "SplitMap", "split_map"]

#: Roughness levels of the prefiltered residual (interpolated in log α; clamped outside).
PREFILTER_ALPHAS = (0.05, 0.08, 0.13, 0.21, 0.34, 0.55, 0.9)


def _hammersley(n: int) -> np.ndarray:
    i = np.arange(n, dtype=np.uint64)
    b = i.copy()
    b = ((b & 0x55555555) << 1) | ((b & 0xAAAAAAAA) >> 1)
    b = ((b & 0x33333333) << 2) | ((b & 0xCCCCCCCC) >> 2)
    b = ((b & 0x0F0F0F0F) << 4) | ((b & 0xF0F0F0F0) >> 4)
    b = ((b & 0x00FF00FF) << 8) | ((b & 0xFF00FF00) >> 8)
    b = ((b & 0x0000FFFF) << 16) | ((b & 0xFFFF0000) >> 16)
    return np.stack([(i.astype(np.float64) + 0.5) / n, b.astype(np.float64) / 2.0 ** 32], 1)


def sample_ggx_h(u: np.ndarray, alpha) -> np.ndarray:
    """Half vectors (…, 3) in the local frame (normal = +z) distributed as ``D(h)(n·h)`` from uniforms u (…, 2)."""
    a2 = np.asarray(alpha, np.float64) ** 2
    u1, u2 = u[..., 0], u[..., 1]
    c2 = (1.0 - u1) / (u1 * (a2 - 1.0) + 1.0)
    c = np.sqrt(np.clip(c2, 0, 1))
    s = np.sqrt(np.clip(1 - c2, 0, 1))
    ph = 2 * math.pi * u2
    return np.stack([s * np.cos(ph), s * np.sin(ph), c], -1)


_DFG_ALPHAS = np.geomspace(0.02, 1.0, 48)
_DFG_MU = np.linspace(0.0, 1.0, 33)[1:]


@lru_cache(maxsize=4)
def _dfg_table(f0: float) -> np.ndarray:
    u = _hammersley(4096)
    tab = np.zeros((len(_DFG_ALPHAS), len(_DFG_MU)))
    for i, a in enumerate(_DFG_ALPHAS):
        h = sample_ggx_h(u, a)                                   # (S, 3)
        for j, mu in enumerate(_DFG_MU):
            v = np.array([math.sqrt(1 - mu * mu), 0.0, mu])
            vh = h @ v
            l = 2 * vh[:, None] * h - v
            nl = l[:, 2]
            g = smith_g2(nl, mu, a)
            # ∫ F D V (n·l) dω_l = E_h[F G2 (v·h) / ((n·v)(n·h))] for h ~ D(h)(n·h)
            val = np.where((nl > 0) & (vh > 0), schlick_fresnel(vh, f0) * g * vh / (mu * h[:, 2]), 0.0)
            tab[i, j] = val.mean()
    return tab


def ggx_view_albedo(alpha, cos_view, f0: float = SKIN_F0) -> np.ndarray:
    """Directional albedo ``∫ F D V (n·l) dω_l`` of the GGX specular term (ρ = 1) at view cosine ``cos_view``.

    Tabulated (48 α × 32 n·v, 4096 Hammersley half-vector samples each; ≈ 1e-3 relative) and bilinearly
    interpolated in (log α, n·v).  At n·v = 1 it is :func:`reflectmm_cli.synth.ggx.ggx_specular_albedo`.
    """
    tab = _dfg_table(float(f0))
    la = np.clip(np.log(np.asarray(alpha, np.float64)), math.log(_DFG_ALPHAS[0]), math.log(_DFG_ALPHAS[-1]))
    mu = np.clip(np.asarray(cos_view, np.float64), _DFG_MU[0], 1.0)
    fa = (la - math.log(_DFG_ALPHAS[0])) / (math.log(_DFG_ALPHAS[-1]) - math.log(_DFG_ALPHAS[0])) \
        * (len(_DFG_ALPHAS) - 1)
    fm = (mu - _DFG_MU[0]) / (_DFG_MU[-1] - _DFG_MU[0]) * (len(_DFG_MU) - 1)
    ia = np.clip(np.floor(fa).astype(int), 0, len(_DFG_ALPHAS) - 2)
    im = np.clip(np.floor(fm).astype(int), 0, len(_DFG_MU) - 2)
    wa, wm = fa - ia, fm - im
    return ((1 - wa) * (1 - wm) * tab[ia, im] + wa * (1 - wm) * tab[ia + 1, im]
            + (1 - wa) * wm * tab[ia, im + 1] + wa * wm * tab[ia + 1, im + 1])


def equirect_lookup(image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an equirect map (H, W, C) at directions (M, 3) (wraps in azimuth, clamps at the poles)."""
    from reflectmm_cli.shading import direction_to_equirect

    H, W = image.shape[:2]
    u, v = direction_to_equirect(d)
    x = u * W - 0.5
    y = np.clip(v * H - 0.5, 0, H - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, H - 2 if H > 1 else 0)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0w, x1w = x0 % W, (x0 + 1) % W
    y1 = np.minimum(y0 + 1, H - 1)
    return ((1 - fx) * (1 - fy) * image[y0, x0w] + fx * (1 - fy) * image[y0, x1w]
            + (1 - fx) * fy * image[y1, x0w] + fx * fy * image[y1, x1w])


def _box_down(img: np.ndarray, width: int) -> np.ndarray:
    H, W, C = img.shape
    f = W // width
    if f <= 1:
        return img.astype(np.float64)
    # area-weighted (solid angle ∝ sin θ) average keeps the energy of each block
    from reflectmm_cli.shading import equirect_weights

    w = equirect_weights(W, H, "area")[:, None, None]
    num = (img * w).reshape(H // f, f, W // f, f, C).sum((1, 3))
    den = np.broadcast_to(w, (H, W, 1)).reshape(H // f, f, W // f, f, 1).sum((1, 3))
    return num / den


def _prefilter(src: np.ndarray, tgt_width: int, alpha: float) -> np.ndarray:
    """Residual map (h, w, 3) convolved with the normalised GGX lobe at normal view (float32 dense sum)."""
    from reflectmm_cli.shading import equirect_directions, equirect_weights

    h, w = src.shape[:2]
    ds = equirect_directions(w, h, np.float32).reshape(-1, 3)
    om = np.repeat(equirect_weights(w, h, "area"), w).astype(np.float32)
    L = np.concatenate([src.reshape(-1, 3), np.ones((h * w, 1))], 1).astype(np.float32)
    dt = equirect_directions(tgt_width, tgt_width // 2, np.float32).reshape(-1, 3)
    a2 = float(alpha) ** 2
    # D(n·h) with (n·h)² = (1 + r·l)/2:  D ∝ 1 / ((1 + r·l)(α² − 1)/2 + 1)²  (the constant cancels)
    c1, c0 = np.float32((a2 - 1) / 2), np.float32((a2 + 1) / 2)
    out = np.empty((len(dt), 3))
    for s in range(0, len(dt), 1024):
        c = dt[s:s + 1024] @ ds.T                                  # r·l
        k = c * c1
        k += c0
        np.square(k, out=k)
        np.divide(np.maximum(c, 0, out=c), k, out=k)
        k *= om
        acc = k @ L
        out[s:s + 1024] = acc[:, :3] / np.maximum(acc[:, 3:], 1e-30)
    return out.reshape(tgt_width // 2, tgt_width, 3)


@dataclass
class SplitMap:
    """A map split into sources and a residual (see the module docstring); all in the map's own frame.

    Attributes: ``image`` (H, W, 3) the full map; ``source_dirs`` (S, 3) unit; ``source_irradiance`` (S, 3);
    ``residual_sh`` (3, 81) order-8 SH of the residual; ``prefiltered`` list of (h, w, 3) per
    :data:`PREFILTER_ALPHAS`; ``sh`` (3, 81) order-8 SH of the full map.
    """

    image: np.ndarray
    source_dirs: np.ndarray
    source_irradiance: np.ndarray
    residual_sh: np.ndarray
    sh: np.ndarray
    prefiltered: list = field(default_factory=list)
    alphas: tuple = PREFILTER_ALPHAS

    def radiance(self, d: np.ndarray) -> np.ndarray:
        return equirect_lookup(self.image, d)

    def specular(self, d: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """Prefiltered residual radiance at directions d (M, 3) for roughness alpha (M,) → (M, 3)."""
        la = np.log(np.clip(alpha, self.alphas[0], self.alphas[-1]))
        lt = np.log(np.asarray(self.alphas))
        i = np.clip(np.searchsorted(lt, la) - 1, 0, len(lt) - 2)
        f = ((la - lt[i]) / (lt[i + 1] - lt[i]))[:, None]
        out = np.zeros((len(d), 3))
        for k in range(len(lt) - 1):
            sel = i == k
            if sel.any():
                a = equirect_lookup(self.prefiltered[k], d[sel])
                b = equirect_lookup(self.prefiltered[k + 1], d[sel])
                out[sel] = (1 - f[sel]) * a + f[sel] * b
        return out


def split_map(image: np.ndarray, *, max_sources: int = 6, threshold: float = 30.0, source_radius_deg: float = 4.0,
              prefilter_width: int = 128, source_width: int = 256, min_fraction: float = 0.004) -> SplitMap:
    """Split an HDR map into directional sources + residual and precompute its lighting (see module docstring).

    ``prefilter_width``/``source_width``: resolution of the prefiltered residual maps and of the residual they
    are filtered from (α ≥ 0.07 filters half that residual; α ≥ 0.2 also lands on half the width).  A source
    must carry at least ``min_fraction`` of the map's total power.  Cost ≈ 1–3 s per 512-wide map, once per map.
    """
    from reflectmm_cli.shading import equirect_directions, equirect_weights, project_envmap

    img = np.asarray(image, np.float64)
    H, W, _ = img.shape
    if W != 2 * H:
        raise ReflectmmError(f"environment map must be 2:1 equirectangular, got {W}x{H}")
    d = equirect_directions(W, H)
    om = np.broadcast_to(equirect_weights(W, H, "area")[:, None], (H, W))
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    med = float(np.median(lum))
    resid = img.copy()
    dirs, irr = [], []
    cos_r = math.cos(math.radians(source_radius_deg))
    cos_ring = math.cos(math.radians(2 * source_radius_deg))
    taken = np.zeros((H, W), bool)
    total = float((lum * om).sum())
    for _ in range(max_sources):
        cand = np.where(taken, -1.0, lum)
        k = int(np.argmax(cand))
        if cand.flat[k] <= threshold * max(med, 1e-12):
            break
        c = d.reshape(-1, 3)[k]
        cosang = d @ c
        region = (cosang >= cos_r) & (lum > threshold * med) & ~taken
        ring = (cosang < cos_r) & (cosang >= cos_ring) & ~taken
        fill = np.median(img[ring], 0) if ring.any() else np.zeros(3)
        excess = np.maximum(img[region] - fill, 0.0)
        wgt = (excess.sum(1) * om[region])
        E = (excess * om[region][:, None]).sum(0)
        dd = (d[region] * wgt[:, None]).sum(0)
        if np.linalg.norm(dd) == 0:
            break
        if float(E @ np.array([0.2126, 0.7152, 0.0722])) < min_fraction * total:
            break
        dirs.append(dd / np.linalg.norm(dd))
        irr.append(E)
        resid[region] = np.minimum(img[region], fill)
        taken |= cosang >= cos_r
    resid = resid.astype(np.float32)
    residual_sh = project_envmap(resid, 8)
    sh = project_envmap(img.astype(np.float32), 8)
    src_hi = _box_down(resid, min(source_width, W))
    src_lo = _box_down(resid, min(source_width // 2, W))
    pre = []
    for a in PREFILTER_ALPHAS:
        if a < 0.07:      # the sharpest level from the finer residual
            pre.append(_prefilter(src_hi, prefilter_width, a))
        elif a < 0.2:
            pre.append(_prefilter(src_lo, prefilter_width, a))
        else:
            pre.append(_prefilter(src_lo, max(prefilter_width // 2, 16), a))
    return SplitMap(img.astype(np.float32), np.array(dirs).reshape(-1, 3), np.array(irr).reshape(-1, 3),
                    residual_sh, sh, pre)

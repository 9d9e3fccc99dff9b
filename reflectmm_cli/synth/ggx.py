"""GGX microfacet specular + Lambertian diffuse: the ground-truth BRDF of the synthetic world.

The synthetic identities are rendered with a *different* BRDF than the project's 3-lobe Blinn-Phong model, so
that fitted representations are compared honestly (docs/design.md §4).  Per texel:

* diffuse: Lambertian ``c/π`` (no (1−F) energy coupling);
* specular: ``ρ · F(v·h) · D(n·h) · G2(l, v) / (4 (n·l)(n·v))`` with

  - ``D`` the GGX / Trowbridge-Reitz NDF ``α² / (π ((n·h)² (α² − 1) + 1)²)`` (``α`` is the GGX width —
    the ``roughness`` map stores ``α`` itself, not its square root),
  - ``G2`` Smith height-correlated masking-shadowing ``1 / (1 + Λ(v) + Λ(l))``,
    ``Λ(x) = (−1 + sqrt(1 + α² tan²θ_x)) / 2``,
  - ``F`` Schlick's approximation with ``f0 = 0.028`` (skin, n ≈ 1.4),
  - ``ρ`` the spatially varying specular intensity (a unitless scale, 1 = a plain dielectric).

Shading of a directional light of irradiance E (the convention of ``shading.shade_directional``: the cosine is
part of the shading, never a division by n·l):
``s = E · (c/π · n·l + ρ F D V · n·l)`` with ``V = G2 / (4 n·l n·v)`` in its stable form
``V = 0.5 / (n·l sqrt((n·v)²(1−α²) + α²) + n·v sqrt((n·l)²(1−α²) + α²))``; ``s = 0`` when n·l ≤ 0 or n·v ≤ 0.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS

__all__ = ["SKIN_F0", "ggx_ndf", "smith_g2", "schlick_fresnel", "ggx_brdf", "ggx_directional", "ggx_two_lobe_directional",
           "ggx_specular_albedo", "fit_lobes_to_ggx", "ggx_lobe_weights"]

#: Fresnel reflectance at normal incidence of skin (n ≈ 1.4): ((n−1)/(n+1))² = 0.0278.
SKIN_F0 = 0.028

_ALPHA_MIN = 1e-3


def _alpha(alpha) -> np.ndarray:
    a = np.asarray(alpha, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ReflectmmError("ggx: roughness (alpha) must be finite")
    if np.any(a <= 0):
        raise ReflectmmError(f"ggx: roughness (alpha) must be > 0, got min {float(a.min())}")
    return np.maximum(a, _ALPHA_MIN)


def _unit(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape[-1:] != (3,):
        raise ReflectmmError(f"ggx: argument '{name}' must have shape (..., 3), got {x.shape}")
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def ggx_ndf(cos_h, alpha) -> np.ndarray:
    """GGX normal distribution D(θ_h), normalised so that ∫ D(h) (n·h) dω_h = 1 over the hemisphere.

    ``cos_h`` (...): n·h (values ≤ 0 give 0); ``alpha`` (...): GGX width α > 0.
    """
    a2 = _alpha(alpha) ** 2
    c = np.asarray(cos_h, dtype=np.float64)
    c2 = np.clip(c, 0.0, 1.0) ** 2
    d = c2 * (a2 - 1.0) + 1.0
    return np.where(c > 0, a2 / (math.pi * d * d), 0.0)


def smith_lambda(cos_t, alpha) -> np.ndarray:
    """Smith Λ for GGX: (−1 + sqrt(1 + α² tan²θ)) / 2 (cos_t in (0, 1])."""
    c2 = np.clip(np.asarray(cos_t, dtype=np.float64), 1e-12, 1.0) ** 2
    return 0.5 * (-1.0 + np.sqrt(1.0 + _alpha(alpha) ** 2 * (1.0 - c2) / c2))


def smith_g2(cos_l, cos_v, alpha) -> np.ndarray:
    """Height-correlated Smith masking-shadowing G2 = 1 / (1 + Λ(l) + Λ(v)); 0 if either cosine ≤ 0."""
    cl, cv = np.asarray(cos_l, np.float64), np.asarray(cos_v, np.float64)
    g = 1.0 / (1.0 + smith_lambda(cl, alpha) + smith_lambda(cv, alpha))
    return np.where((cl > 0) & (cv > 0), g, 0.0)


def schlick_fresnel(cos_d, f0=SKIN_F0) -> np.ndarray:
    """Schlick's Fresnel approximation f0 + (1 − f0)(1 − cos)^5 (cos = v·h = l·h)."""
    c = np.clip(np.asarray(cos_d, dtype=np.float64), 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def _spec_cos_weighted(ndl, ndv, ndh, vdh, alpha, f0):
    """ρ-free specular term times n·l: F D V n·l (stable visibility form); 0 outside n·l>0, n·v>0."""
    a = _alpha(alpha)
    a2 = a * a
    l = np.clip(ndl, 0.0, 1.0)
    v = np.clip(ndv, 0.0, 1.0)
    denom = l * np.sqrt(v * v * (1.0 - a2) + a2) + v * np.sqrt(l * l * (1.0 - a2) + a2)
    vis = 0.5 / np.maximum(denom, 1e-300)
    val = schlick_fresnel(vdh, f0) * ggx_ndf(ndh, a) * vis * l
    return np.where((ndl > 0) & (ndv > 0), val, 0.0)


def ggx_brdf(normal, light_dir, view_dir, alpha, spec_intensity=1.0, albedo=None, f0=SKIN_F0) -> np.ndarray:
    """The BRDF value f(l, v) (1/sr): ρ F D G2 / (4 n·l n·v) [+ c/π if ``albedo`` (…, 3) is given → (…, 3)].

    For tests (reciprocity, energy); rendering uses :func:`ggx_directional`, which never divides by n·l.
    Zero when n·l ≤ 0 or n·v ≤ 0.
    """
    n, l, v = _unit(normal, "normal"), _unit(light_dir, "light_dir"), _unit(view_dir, "view_dir")
    h = _unit(l + v, "half")
    ndl, ndv, ndh, vdh = (n * l).sum(-1), (n * v).sum(-1), (n * h).sum(-1), (v * h).sum(-1)
    ok = (ndl > 0) & (ndv > 0)
    a = _alpha(alpha)
    spec = np.asarray(spec_intensity, np.float64) * schlick_fresnel(vdh, f0) * ggx_ndf(ndh, a) \
        * smith_g2(ndl, ndv, a) / np.where(ok, 4.0 * ndl * ndv, 1.0)
    spec = np.where(ok, spec, 0.0)
    if albedo is None:
        return spec
    return spec[..., None] + np.where(ok[..., None], np.asarray(albedo, np.float64) / math.pi, 0.0)


def ggx_directional(albedo, spec_intensity, roughness, normal, light_dir, view_dir, irradiance, *,
                    f0: float = SKIN_F0, return_parts: bool = False):
    """RGB shading of a directional light with Lambert + GGX (same convention as ``shade_directional``).

    ``s = E · (c/π · max(n·l, 0) + ρ · F D V · n·l)``, 0 where n·l ≤ 0 or n·v ≤ 0 (white specular).

    Args:
        albedo: (..., 3) diffuse colour c (linear).
        spec_intensity: (...) specular intensity ρ ≥ 0.
        roughness: (...) GGX width α > 0.
        normal, light_dir, view_dir: (..., 3), normalised internally; directions point away from the surface.
        irradiance: scalar or (..., 3) RGB irradiance E at normal incidence.
        f0: Fresnel reflectance at normal incidence.
    Returns:
        (..., 3) float64 shading, or ``(total, diffuse, specular)`` with ``return_parts``.
    """
    c = np.asarray(albedo, np.float64)
    if c.shape[-1:] != (3,):
        raise ReflectmmError(f"ggx: argument 'albedo' must have shape (..., 3), got {c.shape}")
    n, l, v = _unit(normal, "normal"), _unit(light_dir, "light_dir"), _unit(view_dir, "view_dir")
    h = _unit(l + v, "half")
    ndl, ndv, ndh, vdh = (n * l).sum(-1), (n * v).sum(-1), (n * h).sum(-1), (v * h).sum(-1)
    ok = (ndl > 0) & (ndv > 0)
    E = np.asarray(irradiance, np.float64)
    if E.ndim > 0 and E.shape[-1] != 3:
        raise ReflectmmError(f"ggx: argument 'irradiance' must be a scalar or (..., 3) RGB, got shape {E.shape}")
    diffuse = E * np.where(ok, ndl, 0.0)[..., None] * c / math.pi
    spec = np.asarray(spec_intensity, np.float64) * _spec_cos_weighted(ndl, ndv, ndh, vdh, roughness, f0)
    specular = E * spec[..., None]
    total = diffuse + specular
    return (total, diffuse, specular) if return_parts else total


def ggx_two_lobe_directional(albedo, spec_intensity, roughness, roughness_broad, lobe_mix, normal, light_dir,
                             view_dir, irradiance, *, f0: float = SKIN_F0, return_parts: bool = False):
    """:func:`ggx_directional` of the two-lobe skin: the specular is ``ρ ((1 − m) GGX(α_sharp) + m GGX(α_broad))``
    (each lobe with its own D, G2 and the shared Fresnel), ``roughness`` = α_sharp, ``roughness_broad`` = α_broad,
    ``lobe_mix`` = m (...)."""
    m = np.asarray(lobe_mix, np.float64)
    rho = np.asarray(spec_intensity, np.float64)
    _, diffuse, s1 = ggx_directional(albedo, rho * (1.0 - m), roughness, normal, light_dir, view_dir, irradiance,
                                     f0=f0, return_parts=True)
    _, _, s2 = ggx_directional(np.zeros_like(np.asarray(albedo, np.float64)), rho * m, roughness_broad, normal,
                               light_dir, view_dir, irradiance, f0=f0, return_parts=True)
    specular = s1 + s2
    total = diffuse + specular
    return (total, diffuse, specular) if return_parts else total


# --------------------------------------------------------------------------- normal-incidence tables

_TABLE_ALPHAS = np.geomspace(0.01, 1.0, 257)


def _normal_view_quadrature(n: int = 4096):
    """Nodes θ_l in (0, π/2) (dense where the lobe peaks) and weights of ∫ ... 2π sinθ dθ (Gauss-Legendre
    in θ_h = θ_l/2 after splitting the range so narrow lobes are resolved)."""
    x, w = np.polynomial.legendre.leggauss(64)
    # panels in θ_h, geometrically refined towards 0
    edges = np.concatenate([[0.0], np.geomspace(1e-4, math.pi / 4, n // 64)])
    th, wt = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        th.append(0.5 * (b - a) * x + 0.5 * (a + b))
        wt.append(0.5 * (b - a) * w)
    th_h = np.concatenate(th)
    w_h = np.concatenate(wt)
    th_l = 2.0 * th_h
    return th_l, 2.0 * w_h * 2.0 * math.pi * np.sin(th_l)  # dθ_l = 2 dθ_h


@lru_cache(maxsize=8)
def _albedo_table(f0: float) -> np.ndarray:
    th_l, w = _normal_view_quadrature()
    cl = np.cos(th_l)
    ch = np.cos(th_l / 2.0)
    vals = _spec_cos_weighted(cl[None, :], np.ones_like(cl)[None, :], ch[None, :], ch[None, :],
                              _TABLE_ALPHAS[:, None], f0)
    return vals @ w


def ggx_specular_albedo(roughness, spec_intensity=1.0, f0: float = SKIN_F0) -> np.ndarray:
    """Directional albedo of the specular term at normal view: ``ρ ∫ F D V (n·l) dω_l`` with v = n.

    This is the shading under uniform unit radiance seen head-on, i.e. the quantity the 3-lobe model calls
    the "specular albedo" Σ w_i, so the two are comparable.  Tabulated over α by adaptive Gauss-Legendre
    quadrature (relative error < 1e-6) and interpolated in log α.
    """
    a = np.clip(_alpha(roughness), _TABLE_ALPHAS[0], _TABLE_ALPHAS[-1])
    tab = _albedo_table(float(f0))
    return np.asarray(spec_intensity, np.float64) * np.interp(np.log(a), np.log(_TABLE_ALPHAS), tab)


@lru_cache(maxsize=8)
def _lobe_fit_table(exponents: tuple[float, ...], f0: float) -> np.ndarray:
    from scipy.optimize import nnls

    from reflectmm_cli.shading import blinn_phong_norm

    th_l, w = _normal_view_quadrature(1024)
    cl, ch = np.cos(th_l), np.cos(th_l / 2.0)
    p = np.asarray(exponents, np.float64)
    basis = blinn_phong_norm(p)[None, :] * ch[:, None] ** p[None, :]       # (Q, K) lobe values at v = n
    sw = np.sqrt(w)[:, None]
    out = np.zeros((len(_TABLE_ALPHAS), len(p)))
    for i, a in enumerate(_TABLE_ALPHAS):
        target = _spec_cos_weighted(cl, np.ones_like(cl), ch, ch, a, f0)
        out[i], _ = nnls(basis * sw, target * sw[:, 0])
    return out


def fit_lobes_to_ggx(roughness, spec_intensity=1.0, exponents=DEFAULT_EXPONENTS, f0: float = SKIN_F0) -> np.ndarray:
    """Best non-negative 3-lobe (K-lobe) approximation of the GGX specular lobe at normal view.

    For each α, NNLS of ``Σ w_i f_i (n·h)^p_i`` against ``F D V (n·l)`` over the light hemisphere at v = n,
    weighted by solid angle; scaled by ρ.  Returns (..., K).  It is a reference for comparing fitted weights,
    not an exact representation (away from normal view the lobes differ).
    """
    a = np.clip(_alpha(roughness), _TABLE_ALPHAS[0], _TABLE_ALPHAS[-1])
    tab = _lobe_fit_table(tuple(float(p) for p in exponents), float(f0))
    la, lt = np.log(a), np.log(_TABLE_ALPHAS)
    w = np.stack([np.interp(la, lt, tab[:, k]) for k in range(tab.shape[1])], -1)
    return np.asarray(spec_intensity, np.float64)[..., None] * w


ggx_lobe_weights = fit_lobes_to_ggx

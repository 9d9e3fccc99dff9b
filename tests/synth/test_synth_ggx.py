"""GGX ground-truth BRDF: checked against quadrature, Monte-Carlo and its own symmetries."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.synth.ggx import (
    fit_lobes_to_ggx, ggx_brdf, ggx_directional, ggx_ndf, ggx_specular_albedo, schlick_fresnel, smith_lambda,
)

alphas = st.floats(0.02, 1.0)


def _unit_vectors(rng, n, upper=True):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    if upper:
        v[:, 2] = np.abs(v[:, 2])
    return v


@given(alphas)
def test_ndf_projected_area_is_one(alpha):
    # ∫ D(h) (n·h) dω_h = 2π ∫_0^{π/2} D(θ) cosθ sinθ dθ = 1 (adaptive scipy quadrature, independent of
    # the module's own tables)
    val, _ = integrate.quad(lambda t: ggx_ndf(math.cos(t), alpha) * math.cos(t) * math.sin(t), 0, math.pi / 2,
                            points=[min(alpha, 1.0) * k for k in (0.1, 0.5, 1.0)], limit=400)
    assert 2 * math.pi * val == pytest.approx(1.0, rel=1e-6)


@settings(max_examples=12)
@given(alphas, st.floats(0.05, 1.0))
def test_smith_g1_weak_white_furnace(alpha, cos_v):
    # ∫ G1(v) max(v·h, 0) D(h) dω_h = n·v  (Heitz 2014, eq. 18) with G1 = 1/(1+Λ(v)); 2-D Gauss-Legendre.
    sin_v = math.sqrt(1 - cos_v * cos_v)
    v = np.array([sin_v, 0.0, cos_v])
    xt, wt = np.polynomial.legendre.leggauss(160)
    # θ_h on [0, π/2] split at a few α-scaled points for peaked D
    edges = np.unique(np.clip([0, 0.2 * alpha, alpha, 3 * alpha, math.pi / 2], 0, math.pi / 2))
    th, wth = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        th.append(0.5 * (b - a) * xt + 0.5 * (a + b))
        wth.append(0.5 * (b - a) * wt)
    th, wth = np.concatenate(th), np.concatenate(wth)
    ph = (np.arange(128) + 0.5) * 2 * math.pi / 128
    T, P = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    vdh = np.maximum(h @ v, 0)
    integrand = vdh * ggx_ndf(np.cos(T), alpha) * np.sin(T)
    total = (integrand * wth[:, None]).sum() * (2 * math.pi / 128)
    g1 = 1.0 / (1.0 + smith_lambda(cos_v, alpha))
    assert g1 * total == pytest.approx(cos_v, rel=2e-3)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("theta_v", [0.0, 0.6, 1.2, 1.5])
def test_white_furnace_directional_albedo_at_most_one(alpha, theta_v):
    # f0 = 1 (perfect mirror facets): the single-scattering albedo is ≤ 1 (energy lost to multiple scattering
    # only), by cosine-weighted Monte-Carlo.
    rng = np.random.default_rng(1)
    N = 400_000
    u1, u2 = rng.random(N), rng.random(N)
    r, ph = np.sqrt(u1), 2 * math.pi * u2
    l = np.stack([r * np.cos(ph), r * np.sin(ph), np.sqrt(1 - u1)], -1)  # pdf cosθ/π
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([math.sin(theta_v), 0.0, math.cos(theta_v)])
    f = ggx_brdf(n, l, v, alpha, f0=1.0)
    est = f.mean() * math.pi
    se = f.std() * math.pi / math.sqrt(N)
    assert est <= 1.0 + 4 * se
    if alpha <= 0.05 and theta_v < 1.3:
        assert est > 0.95  # smooth surface: almost no loss


@pytest.mark.parametrize("alpha", [0.1, 0.25, 0.45, 1.0])
def test_specular_albedo_table_matches_monte_carlo(alpha):
    rng = np.random.default_rng(2)
    N = 1_000_000
    u1, u2 = rng.random(N), rng.random(N)
    r, ph = np.sqrt(u1), 2 * math.pi * u2
    l = np.stack([r * np.cos(ph), r * np.sin(ph), np.sqrt(1 - u1)], -1)
    n = np.array([0.0, 0.0, 1.0])
    f = ggx_brdf(n, l, n, alpha, spec_intensity=1.7)
    est, se = f.mean() * math.pi, f.std() * math.pi / math.sqrt(N)
    assert ggx_specular_albedo(alpha, 1.7) == pytest.approx(est, abs=5 * se + 1e-6)


@given(st.integers(0, 2**31 - 1), alphas)
def test_reciprocity(seed, alpha):
    rng = np.random.default_rng(seed)
    n = np.array([0.0, 0.0, 1.0])
    l, v = _unit_vectors(rng, 50), _unit_vectors(rng, 50)
    c = rng.random((50, 3))
    np.testing.assert_allclose(ggx_brdf(n, l, v, alpha, 1.3, c), ggx_brdf(n, v, l, alpha, 1.3, c), rtol=1e-10)


@given(st.integers(0, 2**31 - 1), alphas)
def test_directional_equals_brdf_times_cosine(seed, alpha):
    rng = np.random.default_rng(seed)
    n = _unit_vectors(rng, 40, upper=False)
    l, v = _unit_vectors(rng, 40, upper=False), _unit_vectors(rng, 40, upper=False)
    c, rho = rng.random((40, 3)), rng.random(40) * 3
    E = rng.random((40, 3)) * 5
    s = ggx_directional(c, rho, alpha, n, l, v, E)
    ndl = np.maximum((n * l).sum(-1), 0)
    expect = E * ggx_brdf(n, l, v, alpha, rho, c) * ndl[:, None]
    np.testing.assert_allclose(s, expect, rtol=1e-9, atol=1e-14)
    back = ((n * l).sum(-1) <= 0) | ((n * v).sum(-1) <= 0)
    assert np.all(s[back] == 0)


def test_grazing_light_is_finite_and_vanishes():
    n = np.array([0.0, 0.0, 1.0])
    for eps in (1e-3, 1e-8, 1e-15, 0.0):
        l = np.array([1.0, 0.0, eps])
        s = ggx_directional([0.5, 0.4, 0.3], 1.0, 0.05, n, l, [0.0, 0.3, 1.0], 10.0)
        assert np.all(np.isfinite(s))
    assert np.all(s == 0)


def test_schlick_limits():
    assert schlick_fresnel(1.0) == pytest.approx(0.028)
    assert schlick_fresnel(0.0) == pytest.approx(1.0)


def test_lobe_fit_is_nonnegative_and_close_in_albedo():
    a = np.linspace(0.2, 0.6, 9)
    w = fit_lobes_to_ggx(a, 2.0)
    assert w.shape == (9, 3) and np.all(w >= 0)
    np.testing.assert_allclose(w.sum(-1), ggx_specular_albedo(a, 2.0), rtol=0.1)


def test_bad_roughness_and_irradiance_are_refused():
    with pytest.raises(ReflectmmError, match="alpha"):
        ggx_ndf(0.5, -0.1)
    n = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(ReflectmmError, match="irradiance"):
        ggx_directional(np.full((4, 3), 0.5), 1.0, 0.3, n, n, n, np.ones(4))

"""Sharp lobes (large exponents) are cheap and exact: closed-form Funk–Hecke coefficients vs quadrature."""
import math

import numpy as np
import pytest
from scipy import integrate, special

from reflectmm_cli.shading import shade_env
from reflectmm_cli.shading.sh import blinn_phong_norm, blinn_phong_sh_coeffs


def _bl_quad(p, l):  # noqa: E741 - independent: adaptive quadrature of the defining integral
    f = float(blinn_phong_norm(p))
    g = lambda t: ((1 + t) / 2) ** (p / 2) * special.eval_legendre(l, t)  # noqa: E731
    v, _ = integrate.quad(g, 0.0, 1.0, points=[1 - 10 / p, 1 - 40 / p], epsabs=1e-15, epsrel=1e-13, limit=400)
    return 2 * math.pi * f * v


@pytest.mark.parametrize("p", [199.0, 200.0, 500.0, 1000.0, 2500.0, 5000.0])
def test_closed_form_matches_quadrature(p):
    B = blinn_phong_sh_coeffs(p, 12)
    ref = np.array([_bl_quad(p, l) for l in range(13)])
    np.testing.assert_allclose(B, ref, rtol=0, atol=1e-12)


def test_sharp_lobe_tends_to_gaussian_asymptote():
    l = np.arange(9)  # noqa: E741
    for p in (1e4, 1e5):
        B = blinn_phong_sh_coeffs(p, 8)
        rel = np.abs(B / np.exp(-2 * l * (l + 1) / p) - 1)
        assert np.all(rel <= 4 * (l * (l + 1)) ** 2 / p ** 2 + 1e-12), rel


def test_huge_exponent_costs_no_big_quadrature(monkeypatch):
    real = np.polynomial.legendre.leggauss

    def guarded(n):
        assert n <= 4096, f"leggauss({n}) for a sharp lobe"
        return real(n)

    monkeypatch.setattr(np.polynomial.legendre, "leggauss", guarded)
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    K = rng.normal(size=(3, 81))
    d, s = shade_env(np.full(3, 0.5), np.array([0.1, 0.2, 0.3]), np.array([1.0, 8.0, 1.23e5]), n, n, K)
    assert np.isfinite(d).all() and np.isfinite(s).all()
    # a 1e5 lobe at normal view reflects the radiance along the normal (B_l → 1 for l ≤ 8)
    from reflectmm_cli.shading.sh import sh_basis

    _, s1 = shade_env(np.zeros(3), np.array([1.0]), np.array([1e7]), n, n, K)
    np.testing.assert_allclose(s1, sh_basis(n, 8) @ K.T, rtol=1e-4, atol=1e-4)

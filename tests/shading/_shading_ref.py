"""Independent reference computations for the shading tests (scipy special functions and quadrature only —
nothing here calls reflectmm_cli.shading)."""
import math

import numpy as np
from scipy import special


def real_sh_ref(l, m, dirs):
    """Real SH with Condon–Shortley phase from scipy's complex Y_l^m: √2 Re/Im for m ≷ 0."""
    d = np.asarray(dirs, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    theta = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
    phi = np.arctan2(d[..., 1], d[..., 0])
    Y = special.sph_harm_y(l, abs(m), theta, phi)
    if m == 0:
        return Y.real
    return math.sqrt(2.0) * (Y.real if m > 0 else Y.imag)


def real_sh_matrix_ref(dirs, order):
    return np.stack([real_sh_ref(l, m, dirs) for l in range(order + 1) for m in range(-l, l + 1)], -1)


def sphere_quadrature(order):
    """Gauss–Legendre in z × uniform φ: exact for polynomials of degree ≤ 2·order+1 on the sphere."""
    nz = order + 2
    nphi = 2 * order + 3
    z, wz = np.polynomial.legendre.leggauss(nz)
    phi = 2 * np.pi * np.arange(nphi) / nphi
    r = np.sqrt(1 - z * z)
    d = np.stack([r[:, None] * np.cos(phi)[None], r[:, None] * np.sin(phi)[None],
                  np.broadcast_to(z[:, None], (nz, nphi))], -1).reshape(-1, 3)
    w = np.broadcast_to((wz * 2 * np.pi / nphi)[:, None], (nz, nphi)).reshape(-1)
    return d, w


def hemisphere_quadrature(axis, nt, nphi, lo=0.0):
    """Directions with t = d·axis ∈ [lo, 1] (Gauss–Legendre in t, uniform φ) and their solid-angle weights."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    x, wx = np.polynomial.legendre.leggauss(nt)
    t = lo + (1 - lo) * (x + 1) / 2
    wt = wx * (1 - lo) / 2
    phi = 2 * np.pi * (np.arange(nphi) + 0.5) / nphi
    s = np.sqrt(np.maximum(0, 1 - t * t))
    d = (t[:, None, None] * a + s[:, None, None] * (np.cos(phi)[None, :, None] * e1
                                                   + np.sin(phi)[None, :, None] * e2)).reshape(-1, 3)
    w = np.broadcast_to((wt * 2 * np.pi / nphi)[:, None], (nt, nphi)).reshape(-1)
    return d, w


def bp_norm_ref(p):
    return (p + 2) / (4 * np.pi * (2 - 2 ** (-p / 2)))


def bp_sh_ref(p, l):
    """B_l by adaptive quadrature (scipy.integrate.quad) of 2π ∫_0^1 f ((1+t)/2)^(p/2) P_l(t) dt."""
    from scipy.integrate import quad

    f = bp_norm_ref(p)
    width = min(1.0, 8.0 / p)
    g = lambda t: ((1 + t) / 2) ** (p / 2) * special.eval_legendre(l, t)  # noqa: E731
    a, _ = quad(g, 0, 1 - width, epsabs=1e-14, epsrel=1e-13, limit=400) if width < 1 else (0.0, 0)
    b, _ = quad(g, max(0.0, 1 - width), 1, epsabs=1e-14, epsrel=1e-13, limit=400)
    return 2 * np.pi * f * (a + b)


def random_lighting(seed, order):
    """(3, (order+1)²) SH light coefficients: normal draws damped by 1 + band, plus 3 on the constant term."""
    rng = np.random.default_rng(seed)
    K = rng.normal(size=(3, (order + 1) ** 2)) / (1 + np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1))
    K[:, 0] += 3.0
    return K

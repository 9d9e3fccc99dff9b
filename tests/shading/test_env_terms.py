"""The diffuse and lobe SH terms of shade_env as pure functions, against independent quadrature; the numpy kernel's
Chebyshev basis against scipy's spherical harmonics; the execution paths against each other."""
import math

import numpy as np
import pytest

from _shading_ref import bp_norm_ref, hemisphere_quadrature, random_lighting as _lighting, real_sh_matrix_ref
from reflectmm_cli.shading import EnvBasis, shade_env
from reflectmm_cli.shading import env as E
from reflectmm_cli.shading.sh import blinn_phong_sh_coeffs

torch = pytest.importorskip("torch")
P = np.array([1.0, 8.0, 64.0])


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("order", [2, 5, 8])
def test_diffuse_term_is_the_clamped_cosine_integral(order):
    # c/π ∫ L(ω) max(0, n·ω) dω by quadrature over the hemisphere of n (L from scipy's SH) against the term, with
    # the basis of n also from scipy: only diffuse_rows/diffuse_term are under test
    K = _lighting(order, order)
    rng = np.random.default_rng(1)
    n = _unit(rng, 5)
    c = rng.random((5, 3))
    ref = np.empty((5, 3))
    for k in range(5):
        d, wq = hemisphere_quadrature(n[k], order + 4, 2 * order + 4)
        L = real_sh_matrix_ref(d, order) @ K.T
        ref[k] = c[k] / math.pi * ((L * (d @ n[k])[:, None]) * wq[:, None]).sum(0)
    Yn = real_sh_matrix_ref(n, order)
    rows = E.diffuse_rows(K, order)
    np.testing.assert_allclose(E.diffuse_term(c, rows, Yn), ref, rtol=1e-11, atol=1e-13)
    # coefficient-major layout and torch give the same numbers
    np.testing.assert_allclose(E.diffuse_term(c.T, rows, Yn.T, coeff_major=True).T, ref, rtol=1e-11, atol=1e-13)
    t = E.diffuse_term(torch.tensor(c), E.diffuse_rows(torch.tensor(K), order), torch.tensor(Yn))
    np.testing.assert_allclose(t.numpy(), ref, rtol=1e-11, atol=1e-13)
    # a band limit drops exactly the higher bands of the lighting
    low = 2
    Kl = K.copy()
    Kl[:, (low + 1) ** 2:] = 0
    np.testing.assert_allclose(E.diffuse_term(c, E.diffuse_rows(K, low), Yn[:, :(low + 1) ** 2]),
                               E.diffuse_term(c, E.diffuse_rows(Kl, order), Yn), rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("order", [3, 6])
def test_lobe_term_is_the_lobe_integral(order):
    # Σ_i w_i ∫_{r·ω>0} L(ω) f_i ((1 + r·ω)/2)^(p_i/2) dω (Funk–Hecke form of the lobe, design.md §2) by
    # quadrature over the hemisphere of r, against the stacked lobe term; lobes with different band limits
    K = _lighting(10 + order, order)
    rng = np.random.default_rng(2)
    r = _unit(rng, 4)
    w = rng.random((4, 3))
    Yr = real_sh_matrix_ref(r, order)
    B = blinn_phong_sh_coeffs(P, order)
    ref = np.zeros((4, 3))
    for k in range(4):
        d, wq = hemisphere_quadrature(r[k], 120, 2 * order + 4)
        L = real_sh_matrix_ref(d, order) @ K.T
        t = d @ r[k]
        for i, p in enumerate(P):
            ref[k] += w[k, i] * ((L * (bp_norm_ref(p) * ((1 + t) / 2) ** (p / 2))[:, None]) * wq[:, None]).sum(0)
    orders = [order] * 3
    rows = E.lobe_rows(K, B, orders, [0, 1, 2])
    np.testing.assert_allclose(E.lobe_term(w, rows, Yr), ref, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(E.lobe_term(w.T, rows, Yr.T, coeff_major=True).T, ref, rtol=1e-9, atol=1e-11)
    t = E.lobe_term(torch.tensor(w), E.lobe_rows(torch.tensor(K), B, orders, [0, 1, 2]), torch.tensor(Yr))
    np.testing.assert_allclose(t.numpy(), ref, rtol=1e-9, atol=1e-11)
    # per-lobe band limits and a subset of lobes: the lobe rows of lobe 1 beyond its band 1 are exact zeros, and
    # the term equals the sum of one-lobe terms
    lim = [order, 1, 2]
    rows = E.lobe_rows(K, B, lim, [1, 2])
    assert rows.shape == (6, 9)
    assert np.all(rows[0:3, 4:] == 0)
    one = [E.lobe_term(w[:, i:i + 1], E.lobe_rows(K, B, lim, [i]), Yr[:, :(lim[i] + 1) ** 2]) for i in (1, 2)]
    np.testing.assert_allclose(E.lobe_term(w[:, 1:], rows, Yr[:, :9]), one[0] + one[1], rtol=1e-13, atol=1e-14)


def test_reflect_and_unit():
    rng = np.random.default_rng(3)
    n, v = E.unit(rng.normal(size=(50, 3)) * 7), E.unit(rng.normal(size=(50, 3)) * 0.1)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, rtol=1e-14)
    r, ndv = E.reflect(n, v)
    np.testing.assert_allclose(ndv, (n * v).sum(1), rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, rtol=1e-13)  # a mirror keeps the length
    np.testing.assert_allclose((r * n).sum(1), ndv, atol=1e-14)  # same angle to n on the other side
    np.testing.assert_allclose(np.cross(r + v, n), 0, atol=1e-14)  # r + v along n
    r0, d0 = E.reflect(n.T, v.T, axis=0)  # coefficient-major layout
    np.testing.assert_allclose(r0.T, r, rtol=1e-15)
    np.testing.assert_allclose(d0, ndv, rtol=1e-15)
    rt, dt_ = E.reflect(torch.tensor(n), torch.tensor(v))
    np.testing.assert_allclose(rt.numpy(), r, rtol=1e-15)
    assert np.all(E.unit(np.zeros((2, 3))) == 0)


@pytest.mark.parametrize("order", [0, 1, 2, 5, 8, 12])
@pytest.mark.parametrize("which", ["all", "diffuse"])
def test_chebyshev_basis_spans_the_sh(order, which):
    # the numpy kernel's basis Φ with its constant matrix M reproduces scipy's real SH: Y = M Φ
    from reflectmm_cli.shading.sh import lambert_sh_coeffs

    A = lambert_sh_coeffs(order)
    bands = tuple(range(order + 1)) if which == "all" else tuple(l for l in range(order + 1) if A[l] != 0)
    plan = E._cheb_plan(order, bands)
    d = np.concatenate([_unit(np.random.default_rng(4), 300), [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]])
    for dt, tol in ((np.float64, 1e-12), (np.float32, 5e-6)):
        x = np.ascontiguousarray(d.T.astype(dt))
        Phi = E._cheb_basis_into(x[0], x[1], x[2], plan, np.empty((plan.n_rows, len(d)), dt),
                                 np.empty((8, len(d)), dt))
        Y = (plan.M @ Phi.astype(np.float64)).T
        ref = real_sh_matrix_ref(d, order)
        lv = np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)
        used = np.isin(lv, bands)
        np.testing.assert_allclose(Y[:, used], ref[:, used], rtol=0, atol=tol * (order + 1))
        assert np.all(Y[:, ~used] == 0)


def _inputs(seed, mostly_front, N=400):
    rng = np.random.default_rng(seed)
    c, w, n, v = rng.random((N, 3)), rng.random((N, 3)), rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    if mostly_front:  # ~90 % facing the viewer: the blocked kernel shades whole blocks and zeroes the rest
        n = v / np.linalg.norm(v, axis=1, keepdims=True) + 0.6 * rng.normal(size=(N, 3))
    w[:, 1] = 0  # an all-zero lobe
    n[:7] = -v[:7]  # some texels facing away
    return c, w, n, v, rng.random(N) < 0.5


@pytest.mark.parametrize("mostly_front", [False, True])
@pytest.mark.parametrize("kw", [{}, {"band_tol": 1e-2}, {"view_correction": True}, {"mask": True}])
def test_execution_paths_agree(kw, mostly_front):
    # the blocked kernel (compiled, or numpy without numba), the numpy kernel, the numpy broadcasting path (per-texel lighting), torch with and without geometry
    # gradients, torch's masked gather and the EnvBasis path (global and per-texel lighting) on the same inputs
    order = 6
    K = _lighting(7, order)
    c, w, n, v, mask = _inputs(8, mostly_front)
    front = (n * v).sum(1) > 0
    assert (front.mean() > 0.8) == mostly_front
    N = len(c)
    kw = dict(kw)
    if kw.pop("mask", False):
        kw["mask"] = mask
    ref = shade_env(c, w, P, n, v, K, chunk=96, **kw)
    T = [torch.tensor(a) for a in (c, w, P, n, v)]
    Kt = torch.tensor(K)
    Kp = np.broadcast_to(K, (N,) + K.shape)
    eb = EnvBasis(n, v, order, dtype=torch.float64)
    ng = T[3].clone().requires_grad_(True)
    got = {
        "numpy per-texel lighting": shade_env(c, w, P, n, v, Kp, **kw),
        "torch, fixed geometry": shade_env(*T, Kt, **kw),
        "torch, geometry with gradient": shade_env(T[0], T[1], T[2], ng, T[4], Kt, **kw),
        "EnvBasis": shade_env(T[0], T[1], P, None, None, Kt, basis=eb, **kw),
        "EnvBasis, per-texel lighting": shade_env(T[0], T[1], P, None, None, torch.tensor(Kp), basis=eb, **kw),
        "numpy one thread, one block": shade_env(c, w, P, n, v, K, chunk=N, threads=1, **kw),
        "numpy kernel (ref: the compiled one when numba is installed)": shade_env(c, w, P, n, v, K, chunk=96,
                                                                                   backend="numpy", **kw),
    }
    for name, (d, s) in got.items():
        d = d.detach().numpy() if torch.is_tensor(d) else d
        s = s.detach().numpy() if torch.is_tensor(s) else s
        np.testing.assert_allclose(d, ref[0], rtol=1e-10, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(s, ref[1], rtol=1e-10, atol=1e-12, err_msg=name)
    assert np.all(ref[1][(n * v).sum(1) <= 0] == 0)
    if "mask" in kw:
        assert np.all(ref[0][~mask] == 0) and np.all(ref[1][~mask] == 0)
    # the specular part really depends on the weights and the view (the comparison above is not between zeros)
    assert np.abs(ref[1]).max() > 0.1 and np.abs(ref[0]).max() > 0.1

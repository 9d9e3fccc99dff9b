"""The compiled (numba) kernel of shade_env against the blocked numpy kernel and against the pure term functions
on scipy's spherical harmonics; the backend choice."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _shading_ref import random_lighting as _lighting, real_sh_matrix_ref
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import env as E
from reflectmm_cli.shading import shade_env
from reflectmm_cli.shading.sh import blinn_phong_sh_coeffs

needs_numba = pytest.mark.skipif(E.compiled_kernel() is None, reason="numba is not installed")

#: max |compiled − numpy| / max |numpy| allowed: the two sum the basis rows in different orders
TOL = {np.float32: 1e-6, np.float64: 1e-12}


def _rel(a, b):
    return float(np.abs(a.astype(np.float64) - b).max() / max(np.abs(b).max(), 1e-30))


def _both(*args, **kw):
    got = shade_env(*args, backend="compiled", **kw)
    ref = shade_env(*args, backend="numpy", **kw)
    for a, b in zip(got, ref):
        assert a.dtype == b.dtype and a.shape == b.shape
    return got, ref


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


@needs_numba
def test_compiled_kernel_is_the_sh_formula():
    # independent reference: the two terms on scipy's SH of n and of r = 2(n·v)n − v, per-lobe band limits from
    # band_tol, the view albedo by specular_view_albedo; the compiled kernel must give the same in float64
    order, N = 7, 300
    rng = np.random.default_rng(3)
    K = _lighting(4, order)
    P = np.array([2.0, 30.0, 400.0])
    c, w = rng.random((N, 3)), rng.random((N, 3))
    n, v = rng.normal(size=(N, 3)) * 3, rng.normal(size=(N, 3)) * 0.5
    for band_tol, vc in ((0.0, False), (1e-3, True)):
        d, s = shade_env(c, w, P, n, v, K, band_tol=band_tol, view_correction=vc, backend="compiled", chunk=128)
        nn, vv = _unit(n), _unit(v)
        ndv = (nn * vv).sum(1)
        r = 2 * ndv[:, None] * nn - vv
        Ld, Ls = E.band_limits(P, order, band_tol)
        Yn, Yr = real_sh_matrix_ref(nn, order), real_sh_matrix_ref(r, order)
        lvl = np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)
        A = np.where(lvl <= Ld, E.lambert_sh_coeffs(order)[lvl] / np.pi, 0.0)
        d_ref = c * (Yn @ (K * A).T)
        B = blinn_phong_sh_coeffs(P, order)
        s_ref = np.zeros((N, 3))
        for i, p in enumerate(P):
            Bi = np.where(lvl <= Ls[i], B[i][lvl], 0.0)
            wi = w[:, i] * (E.specular_view_albedo(p, ndv) if vc else 1.0)
            s_ref += wi[:, None] * (Yr @ (K * Bi).T)
        s_ref[ndv <= 0] = 0
        np.testing.assert_allclose(d, d_ref, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(s, s_ref, rtol=1e-11, atol=1e-12)
        assert np.abs(s_ref).max() > 0.1


_dirs = st.integers(0, 2 ** 32 - 1)


@needs_numba
@settings(max_examples=40, deadline=None)
@given(seed=_dirs, N=st.integers(1, 700), order=st.integers(0, 9),
       exps=st.lists(st.floats(0.5, 2000.0), min_size=1, max_size=4),
       dtype=st.sampled_from([np.float32, np.float64]), vc=st.booleans(), masked=st.booleans(),
       band_tol=st.sampled_from([0.0, 1e-3]), chunk=st.sampled_from([64, 257, 16384]))
def test_property_compiled_matches_numpy_kernel(seed, N, order, exps, dtype, vc, masked, band_tol, chunk):
    rng = np.random.default_rng(seed)
    K = _lighting(seed % 97, order).astype(dtype)
    c = rng.random((N, 3)).astype(dtype)
    w = rng.random((N, len(exps))).astype(dtype)
    w[:, rng.random(len(exps)) < 0.3] = 0  # some all-zero lobes
    n = (rng.normal(size=(N, 3)) * rng.uniform(0.1, 10)).astype(dtype)
    v = (rng.normal(size=(N, 3)) * rng.uniform(0.1, 10)).astype(dtype)
    mask = rng.random(N) < 0.4 if masked else None
    P = np.array(exps, dtype)
    got, ref = _both(c, w, P, n, v, K, mask=mask, band_tol=band_tol, view_correction=vc, chunk=chunk, threads=2)
    for a, b in zip(got, ref):
        assert _rel(a, b) <= TOL[dtype]
    nn, vv = n.astype(np.float64), v.astype(np.float64)
    away = (nn * vv).sum(1) < -1e-3 * np.linalg.norm(nn, axis=1) * np.linalg.norm(vv, axis=1)
    assert np.all(got[1][away] == 0)
    if masked:
        assert np.all(got[0][~mask] == 0) and np.all(got[1][~mask] == 0)


@needs_numba
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_on_benchmark_like_inputs_and_layouts(dtype):
    # broadcast inputs (one view for all texels), a (2, N) texel shape, back-facing halves, sizes that are no
    # multiple of the sub-block, no texel in the mask, no active lobe
    rng = np.random.default_rng(0)
    N = 3001
    K = _lighting(1, 8).astype(dtype)
    n = rng.normal(size=(2, N, 3)).astype(dtype)
    n[:, : N // 2, 2] = -np.abs(n[:, : N // 2, 2])
    v = np.array([0.1, 0.0, 1.0], dtype)
    c, w = rng.random((2, N, 3)).astype(dtype), rng.random((N, 3)).astype(dtype)
    P = np.array([1.0, 8.0, 64.0], dtype)
    for kw in ({}, {"view_correction": True}, {"mask": rng.random((2, N)) < 0.3}):
        got, ref = _both(c, w, P, n, v, K, **kw)
        assert got[0].shape == (2, N, 3)
        assert _rel(got[0], ref[0]) <= TOL[dtype] and _rel(got[1], ref[1]) <= TOL[dtype]
    got, _ = _both(c, w, P, n, v, K, mask=np.zeros((2, N), bool))
    assert not got[0].any() and not got[1].any()
    got, ref = _both(c, np.zeros_like(w), P, n, v, K)
    assert not got[1].any() and _rel(got[0], ref[0]) <= TOL[dtype]


def test_backend_choice(monkeypatch):
    rng = np.random.default_rng(0)
    args = (rng.random((5, 3)), rng.random((5, 1)), [8.0], rng.normal(size=(5, 3)), rng.normal(size=(5, 3)),
            _lighting(0, 2))
    with pytest.raises(ReflectmmError, match="backend must be one of"):
        shade_env(*args, backend="gpu")
    monkeypatch.setattr(E, "compiled_kernel", lambda: None)  # numba absent
    with pytest.raises(ReflectmmError, match="needs numba"):
        shade_env(*args, backend="compiled")
    d, s = shade_env(*args)  # auto falls back to the numpy kernel
    d0, s0 = shade_env(*args, backend="numpy")
    assert np.array_equal(d, d0) and np.array_equal(s, s0)

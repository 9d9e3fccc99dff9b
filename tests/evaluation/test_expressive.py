"""Expressive power (evaluation/expressive.py): the projection against a general-purpose optimiser, exact spans,
the oracle model reproducing its own training identities, the gap-closed ratio."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.optimize import minimize

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.expressive import (gap_closed, oracle_model, oracle_reflectance_model,
                                                projection_coefficients, projection_residuals)


def _part(rng, V=40, C=3, M=4):
    return rng.uniform(0.2, 0.6, (V, C)), rng.normal(0, 0.1, (M, V, C)), rng.uniform(0.5, 2.0, M)


def test_projection_matches_a_general_optimiser():
    rng = np.random.default_rng(0)
    mu, B, sg = _part(rng)
    t = rng.uniform(0.1, 0.7, (2, 40, 3))
    region = rng.random(40) > 0.3
    lam = 0.05
    got = projection_residuals(mu, B, sg, t, region, prior=lam)
    for i in range(2):
        r = region
        tt = (t[i][r] ** 2).sum()

        def f(x):
            pred = x[0] * mu[r] + np.tensordot(x[1:] * sg, B[:, r], 1)
            return ((pred - t[i][r]) ** 2).sum() / tt + lam * (x[1:] ** 2).sum()

        x = minimize(f, np.r_[1.0, np.zeros(4)], method="BFGS", options={"gtol": 1e-12}).x
        pred = x[0] * mu[r] + np.tensordot(x[1:] * sg, B[:, r], 1)
        np.testing.assert_allclose(got[i], np.sqrt(((pred - t[i][r]) ** 2).sum() / tt), rtol=1e-5)
        # the minimiser itself, (s, c)
        np.testing.assert_allclose(projection_coefficients(mu, B, sg, t, region, prior=lam)[i], x, rtol=1e-4,
                                   atol=1e-6)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 16), scale=st.floats(0.2, 5.0))
def test_truth_in_the_span_has_zero_residual(seed, scale):
    rng = np.random.default_rng(seed)
    mu, B, sg = _part(rng)
    beta = rng.normal(0, 1, 4)
    t = scale * (mu + np.tensordot(beta * sg, B, 1))
    assert projection_residuals(mu, B, sg, t[None], prior=0.0)[0] < 1e-8
    np.testing.assert_allclose(projection_coefficients(mu, B, sg, t[None], prior=0.0)[0], np.r_[scale, scale * beta],
                               rtol=1e-6, atol=1e-8)
    # the prior only ever raises the residual
    assert projection_residuals(mu, B, sg, t[None], prior=0.1)[0] >= -1e-12


def test_oracle_reproduces_its_training_identities():
    rng = np.random.default_rng(1)
    N, V, K = 6, 50, 3
    a = rng.uniform(0.2, 0.7, (N, V, 3))
    w = rng.uniform(0.0, 0.2, (N, V, K))
    m = oracle_model(a, w, [1.0, 16.0, 128.0], components=N - 1)
    assert m["vertex_albedo_basis"].shape == (N - 1, V, 3) and m["vertex_weights_basis"].shape == (N - 1, V, K)
    np.testing.assert_allclose(m["vertex_albedo_mean"], a.mean(0), atol=1e-5)
    res = projection_residuals(m["vertex_albedo_mean"], m["vertex_albedo_basis"], m["sigma"], a, prior=0.0)
    assert res.max() < 1e-4
    # fewer components leave a residual, and the lobe weights follow the albedo's combination (transfer)
    m2 = oracle_model(a, w, [1.0, 16.0, 128.0], components=2)
    assert projection_residuals(m2["vertex_albedo_mean"], m2["vertex_albedo_basis"], m2["sigma"], a,
                                prior=0.0).min() > 1e-3


def test_oracle_as_a_whole_model():
    """The oracle as a reflectance model: its per-vertex part is exactly :func:`oracle_model`'s; its UV maps,
    looked up at the vertices as the project's per-vertex sampler does, give that part back (a smooth truth on a
    mesh whose UV layout is its own (x, y)); the PCA's σ and training coefficients reproduce the training
    identities."""
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.model.pca import sample_uv_bilinear

    fm = procedural_face_model(grid=(31, 25), n_shape=2, n_exp=1, seed=0)
    uv = np.asarray(fm.uv, np.float64)
    V, N, K = uv.shape[0], 5, 3
    rng = np.random.default_rng(4)
    # smooth per-vertex truth: low-order polynomials of the UVs with random coefficients per identity
    basis = np.stack([np.ones(V), uv[:, 0], uv[:, 1], uv[:, 0] * uv[:, 1]], 1)
    a = 0.4 + 0.1 * np.einsum("vp,npc->nvc", basis, rng.normal(size=(N, 4, 3)))
    w = 0.1 + 0.02 * np.einsum("vp,npc->nvc", basis, rng.normal(size=(N, 4, K)))
    exps = [1.0, 16.0, 128.0]
    whole = oracle_reflectance_model(a, w, exps, N - 1, uv, fm.triangles, 64, ids=[f"i{i}" for i in range(N)])
    part = oracle_model(a, w, exps, N - 1)
    for k in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis", "sigma"):
        np.testing.assert_array_equal(getattr(whole, k), part[k], err_msg=k)
    assert whole.albedo_mean.shape == (3, 64, 64) and whole.weights_basis.shape == (N - 1, K, 64, 64)
    scale = np.abs(whole.vertex_albedo_mean).max()
    back = sample_uv_bilinear(whole.albedo_mean, uv)
    assert np.abs(back - whole.vertex_albedo_mean).max() < 0.02 * scale
    for k in range(N - 1):
        b = sample_uv_bilinear(whole.weights_basis[k], uv)
        assert np.abs(b - whole.vertex_weights_basis[k]).max() < 0.02 * np.abs(whole.vertex_weights_basis[k]).max()
    # the training coefficients (units of σ) rebuild each identity's albedo from the per-vertex part
    rec = whole.vertex_albedo_mean + np.einsum("nm,m,mvc->nvc", whole.train_coeffs, whole.sigma,
                                               whole.vertex_albedo_basis)
    np.testing.assert_allclose(rec, a, atol=1e-4)
    assert whole.ids == [f"i{i}" for i in range(N)] and whole.stats["baseline"] == "oracle"
    with pytest.raises(ReflectmmError, match="vertex UVs"):
        oracle_reflectance_model(a, w, exps, 2, uv[:-1], fm.triangles, 64)


def test_gap_closed():
    assert gap_closed(0.2, 0.15, 0.1) == pytest.approx(0.5)
    assert gap_closed(0.2, 0.25, 0.1) == pytest.approx(-0.5)
    assert np.isnan(gap_closed(0.1, 0.1, 0.2))


def test_bad_inputs_are_one_line_errors():
    rng = np.random.default_rng(2)
    mu, B, sg = _part(rng)
    with pytest.raises(ReflectmmError, match="truth must be"):
        projection_residuals(mu, B, sg, np.ones((2, 39, 3)))
    t = np.ones((1, 40, 3))
    t[0, 3, 1] = np.nan
    with pytest.raises(ReflectmmError, match="NaN"):
        projection_residuals(mu, B, sg, t)
    with pytest.raises(ReflectmmError, match="zero truth"):
        projection_residuals(mu, B, sg, np.zeros((1, 40, 3)))

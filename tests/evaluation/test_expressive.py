"""Expressive power (evaluation/expressive.py): the projection against a general-purpose optimiser, exact spans,
the oracle model reproducing its own training identities, the gap-closed ratio."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.optimize import minimize

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.expressive import gap_closed, oracle_model, projection_coefficients, projection_residuals


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

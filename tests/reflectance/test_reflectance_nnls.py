"""Batched non-negative QP against scipy's Lawson-Hanson NNLS and the KKT conditions."""
import numpy as np
import pytest
from hypothesis import given, strategies as st
from scipy.optimize import nnls

from reflectmm_cli.reflectance import kkt_violation, nnls_batched


@pytest.mark.parametrize("m", [1, 4, 6, 8])
def test_matches_scipy_nnls(m):
    rng = np.random.default_rng(m)
    N = 300
    A = rng.normal(size=(N, 3 * m + 2, m)) * rng.uniform(0.01, 10, size=(N, 1, m))
    b = rng.normal(size=(N, 3 * m + 2)) * 2
    H = np.einsum("nij,nik->njk", A, A)
    g = np.einsum("nij,ni->nj", A, b)
    x, info = nnls_batched(H, g)
    ref = np.stack([nnls(A[i], b[i], maxiter=1000)[0] for i in range(N)])
    np.testing.assert_allclose(x, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())
    assert info["unconverged"] == 0
    assert np.all(x >= 0)
    assert kkt_violation(H, g, x).max() < 1e-9


@given(seed=st.integers(0, 2 ** 20), m=st.integers(1, 7))
def test_kkt_holds_on_random_problems(seed, m):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(20, m + rng.integers(0, 5), m))
    H = np.einsum("nij,nik->njk", A, A) + 1e-6 * np.eye(m)
    g = rng.normal(size=(20, m)) * 10.0 ** rng.uniform(-3, 3)
    x, info = nnls_batched(H, g)
    assert info["unconverged"] == 0
    assert np.all(np.isfinite(x)) and np.all(x >= 0)
    # g spans 1e-3 … 1e3: the violation is round-off relative to the gradient's scale (1.1e-8 at |g| ~ 1e3 was
    # found by hypothesis; an absolute 1e-8 was too tight)
    assert kkt_violation(H, g, x).max() < 1e-8 * max(1.0, float(np.abs(g).max()))


def test_kkt_violation_detects_wrong_answers():
    H = np.eye(2)[None]
    g = np.array([[1.0, -1.0]])
    assert kkt_violation(H, g, np.array([[1.0, 0.0]]))[0] < 1e-15
    assert kkt_violation(H, g, np.array([[0.5, 0.0]]))[0] > 0.1   # gradient negative on a free variable
    assert kkt_violation(H, g, np.array([[1.0, -1.0]]))[0] > 0.1  # infeasible

"""Mesh harmonics (geometry/harmonics.py): the cotangent Laplacian against closed forms (linear precision on a flat
grid, the total area), the harmonics against a dense generalised eigensolver, their M-orthonormality and the
eigen-equation residual."""
import numpy as np
import pytest
import scipy.linalg

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.harmonics import cotangent_laplacian, mesh_harmonics


def grid(n=9, bend=0.0, seed=0):
    """An n×n grid over [0, 1]², jittered, optionally bent (z = bend·sin), and its triangles."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1.3, n))
    X = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    inner = (X[:, 0] > 0) & (X[:, 0] < 1) & (X[:, 1] > 0) & (X[:, 1] < 1.3)
    X[inner, :2] += rng.uniform(-0.2, 0.2, (inner.sum(), 2)) / n
    X[:, 2] = bend * np.sin(3 * X[:, 0]) * np.cos(2 * X[:, 1])
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    T = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return X, T, inner


def test_cotangent_laplacian_closed_forms():
    X, T, inner = grid()
    L, M = cotangent_laplacian(X, T)
    Ld = L.toarray()
    np.testing.assert_allclose(Ld, Ld.T, atol=1e-12)
    np.testing.assert_allclose(Ld.sum(1), 0, atol=1e-12)
    assert np.linalg.eigvalsh(Ld).min() > -1e-10  # positive semidefinite
    # linear precision: a linear function is harmonic at the interior vertices of a flat mesh
    f = 0.7 * X[:, 0] - 1.9 * X[:, 1] + 0.3
    np.testing.assert_allclose((L @ f)[inner], 0, atol=1e-12)
    # the lumped mass sums to the area (1 × 1.3)
    np.testing.assert_allclose(M.diagonal().sum(), 1.3, rtol=1e-12)
    # the Dirichlet energy of f is |∇f|² × area
    np.testing.assert_allclose(f @ (L @ f), (0.7 ** 2 + 1.9 ** 2) * 1.3, rtol=1e-10)


@pytest.mark.parametrize("bend", [0.0, 0.4])
def test_harmonics_against_a_dense_eigensolver(bend):
    X, T, _ = grid(bend=bend)
    Q = 12
    phi, lam = mesh_harmonics(X, T, Q)
    L, M = cotangent_laplacian(X, T)
    want = scipy.linalg.eigh(L.toarray(), M.toarray(), eigvals_only=True)[:Q]
    np.testing.assert_allclose(lam, np.maximum(want, 0), atol=1e-9 * want[-1])
    np.testing.assert_allclose(phi.T @ (M @ phi), np.eye(Q), atol=1e-10)
    np.testing.assert_allclose(L @ phi, (M @ phi) * lam, atol=1e-8 * lam[-1])
    assert lam[0] == pytest.approx(0, abs=1e-9) and np.ptp(phi[:, 0]) < 1e-8  # the constant comes first
    assert np.all(np.diff(lam) >= -1e-12)


def test_bad_meshes_are_refused():
    X, T, _ = grid(5)
    with pytest.raises(ReflectmmError, match="outside"):
        cotangent_laplacian(X, T + 1)
    with pytest.raises(ReflectmmError, match="count"):
        mesh_harmonics(X, T, len(X))
    with pytest.raises(ReflectmmError, match=r"\(V,3\)"):
        cotangent_laplacian(X[:, :2], T)

"""Spherical harmonics: basis, kernels and rotation against independent computations."""
import math

import numpy as np
import pytest
from scipy import special
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

from _shading_ref import bp_sh_ref, real_sh_matrix_ref, sphere_quadrature
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import (
    blinn_phong_sh_coeffs,
    lambert_sh_coeffs,
    sh_basis,
    sh_index,
    sh_rotation,
)

RNG = np.random.default_rng(1234)


def _dirs(n, extra_poles=True):
    d = RNG.normal(size=(n, 3))
    if extra_poles:
        d = np.concatenate([d, [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [1e-9, 0, 1], [0, -1e-12, -1]]])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_index_layout():
    assert sh_index(0, 0) == 0 and sh_index(1, -1) == 1 and sh_index(1, 1) == 3 and sh_index(2, -2) == 4
    assert sh_basis(np.zeros((5, 3)) + [0, 0, 1.0], 8).shape == (5, 81)


def test_closed_forms_up_to_l3_and_deep3d_signs():
    d = _dirs(200)
    x, y, z = d.T
    pi = math.pi
    ref = [
        np.full_like(x, 0.5 / math.sqrt(pi)),
        -math.sqrt(3 / (4 * pi)) * y, math.sqrt(3 / (4 * pi)) * z, -math.sqrt(3 / (4 * pi)) * x,
        0.5 * math.sqrt(15 / pi) * x * y, -0.5 * math.sqrt(15 / pi) * y * z,
        0.25 * math.sqrt(5 / pi) * (3 * z * z - 1), -0.5 * math.sqrt(15 / pi) * x * z,
        0.25 * math.sqrt(15 / pi) * (x * x - y * y),
        -0.25 * math.sqrt(35 / (2 * pi)) * y * (3 * x * x - y * y), 0.5 * math.sqrt(105 / pi) * x * y * z,
        -0.25 * math.sqrt(21 / (2 * pi)) * y * (5 * z * z - 1), 0.25 * math.sqrt(7 / pi) * z * (5 * z * z - 3),
        -0.25 * math.sqrt(21 / (2 * pi)) * x * (5 * z * z - 1), 0.25 * math.sqrt(105 / pi) * z * (x * x - y * y),
        -0.25 * math.sqrt(35 / (2 * pi)) * x * (x * x - 3 * y * y),
    ]
    Y = sh_basis(d, 3)
    np.testing.assert_allclose(Y, np.stack(ref, -1), atol=1e-13)
    # Deep3DFaceRecon (models/facerecon_model / bfm.py) builds its order-2 basis as
    # [c0, -c1*y, c1*z, -c1*x, c2*x*y, -c2*y*z, 0.5*c2/sqrt(3)*(3z²-1), -c2*x*z, 0.5*c2*(x²-y²)]
    c0, c1, c2 = 1 / math.sqrt(4 * pi), math.sqrt(3) / math.sqrt(4 * pi), 3 * math.sqrt(5) / math.sqrt(12 * pi)
    deep3d = np.stack([np.full_like(x, c0), -c1 * y, c1 * z, -c1 * x, c2 * x * y, -c2 * y * z,
                       0.5 * c2 / math.sqrt(3) * (3 * z * z - 1), -c2 * x * z, 0.5 * c2 * (x * x - y * y)], -1)
    np.testing.assert_allclose(Y[:, :9], deep3d, atol=1e-13)


@pytest.mark.parametrize("order", [8, 16, 24])
def test_against_scipy_complex_sh(order):
    d = _dirs(60)
    np.testing.assert_allclose(sh_basis(d, order), real_sh_matrix_ref(d, order), atol=1e-11)


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 2e-5)])
def test_orthonormal_by_quadrature(dtype, tol):
    order = 16
    d, w = sphere_quadrature(order)
    Y = sh_basis(d.astype(dtype), order).astype(np.float64)
    G = (Y * w[:, None]).T @ Y
    assert np.abs(G - np.eye(G.shape[0])).max() < tol


def test_addition_theorem_and_poles_high_order():
    order = 20
    a, b = _dirs(40), _dirs(40)[::-1]
    Ya, Yb = sh_basis(a, order), sh_basis(b, order)
    cos = np.clip((a * b).sum(1), -1, 1)
    for l in range(order + 1):  # noqa: E741
        s = slice(l * l, (l + 1) ** 2)
        lhs = (Ya[:, s] * Yb[:, s]).sum(1)
        rhs = (2 * l + 1) / (4 * math.pi) * special.eval_legendre(l, cos)
        np.testing.assert_allclose(lhs, rhs, atol=1e-11)
    # exactly at the poles only m = 0 survives, Y_l0(±z) = sqrt((2l+1)/4π) (±1)^l
    Yp = sh_basis(np.array([[0, 0, 1.0], [0, 0, -1.0]]), 32)
    assert np.isfinite(Yp).all()
    for l in range(33):  # noqa: E741
        row = Yp[:, l * l:(l + 1) ** 2]
        np.testing.assert_allclose(row[:, l], [math.sqrt((2 * l + 1) / (4 * math.pi)) * s ** l for s in (1, -1)],
                                   rtol=1e-12)
        if l:
            assert np.abs(np.delete(row, l, axis=1)).max() < 1e-12


def test_torch_matches_numpy_and_normalises():
    torch = pytest.importorskip("torch")
    d = _dirs(30) * RNG.uniform(0.1, 10, size=(36, 1))  # non-unit
    Yn = sh_basis(d, 8)
    Yt = sh_basis(torch.tensor(d), 8)
    np.testing.assert_allclose(Yt.numpy(), Yn, atol=1e-12)
    assert sh_basis(torch.tensor(d, dtype=torch.float32), 8).dtype == torch.float32
    assert sh_basis(d.astype(np.float16), 4).dtype == np.float32


def test_lambert_coeffs_against_integration():
    A = lambert_sh_coeffs(12)
    for l in range(13):  # noqa: E741
        ref = 2 * math.pi * quad(lambda t: t * special.eval_legendre(l, t), 0, 1, epsabs=1e-14)[0]
        assert abs(A[l] - ref) < 1e-12, (l, A[l], ref)
    assert abs(A[0] - math.pi) < 1e-15 and abs(A[1] - 2 * math.pi / 3) < 1e-15 and abs(A[2] - math.pi / 4) < 1e-15


def test_blinn_phong_coeffs_reference_values():
    np.testing.assert_allclose(blinn_phong_sh_coeffs(1, 3), [1, 0.52815, 0.04175, -0.10507], atol=6e-6)
    np.testing.assert_allclose(blinn_phong_sh_coeffs(64, 3), [1, 0.94118, 0.83361, 0.69468], atol=6e-6)


@pytest.mark.parametrize("p", [0.5, 1.0, 3.7, 8.0, 64.0, 250.0, 1000.0])
def test_blinn_phong_coeffs_against_adaptive_quadrature(p):
    B = blinn_phong_sh_coeffs(p, 12)
    ref = np.array([bp_sh_ref(p, l) for l in range(13)])
    np.testing.assert_allclose(B, ref, atol=1e-9)
    assert abs(B[0] - 1) < 1e-10


def test_blinn_phong_coeffs_vector_and_errors():
    B = blinn_phong_sh_coeffs([1, 8, 64], 8)
    assert B.shape == (3, 9)
    np.testing.assert_allclose(B[2], blinn_phong_sh_coeffs(64, 8))
    with pytest.raises(ReflectmmError, match="exponents"):
        blinn_phong_sh_coeffs([1, -2], 4)
    with pytest.raises(ReflectmmError, match="order"):
        sh_basis(np.ones((2, 3)), -1)


def _project(fun, order):
    d, w = sphere_quadrature(order + 2)
    return (real_sh_matrix_ref(d, order) * (fun(d) * w)[:, None]).sum(0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rotation_equals_reprojection(seed):
    order = 8
    R = Rotation.random(random_state=seed).as_matrix()
    c = np.random.default_rng(seed).normal(size=(order + 1) ** 2)
    f = lambda d: real_sh_matrix_ref(d, order) @ c  # noqa: E731
    g = lambda d: f(d @ R)  # g(d) = f(Rᵀ d)  # noqa: E731
    M = sh_rotation(R, order)
    np.testing.assert_allclose(M @ c, _project(g, order), atol=1e-10)
    # orthogonal, block diagonal, composes like the rotations
    np.testing.assert_allclose(M @ M.T, np.eye(M.shape[0]), atol=1e-12)
    R2 = Rotation.random(random_state=seed + 10).as_matrix()
    np.testing.assert_allclose(sh_rotation(R2 @ R, order), sh_rotation(R2, order) @ M, atol=1e-11)
    for l in range(order + 1):  # noqa: E741
        blk = M[l * l:(l + 1) ** 2]
        assert np.abs(np.delete(blk, np.s_[l * l:(l + 1) ** 2], axis=1)).max() == 0


def test_rotation_about_z_closed_form_and_torch():
    torch = pytest.importorskip("torch")
    a = 0.7
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    M = sh_rotation(Rz, 3)
    # rotating about +z by a shifts φ by a: Y_{l,m} ↔ cos/sin(m(φ − a))
    c = np.zeros(16)
    c[sh_index(3, 2)] = 1.0  # ∝ cos 2φ  → cos(2φ − 2a) = cos2a cos2φ + sin2a sin2φ
    out = M @ c
    np.testing.assert_allclose(out[sh_index(3, 2)], math.cos(2 * a), atol=1e-12)
    np.testing.assert_allclose(out[sh_index(3, -2)], math.sin(2 * a), atol=1e-12)
    Mt = sh_rotation(torch.tensor(Rz, requires_grad=True), 3)
    np.testing.assert_allclose(Mt.detach().numpy(), M, atol=1e-12)
    Mt.sum().backward()
    with pytest.raises(ReflectmmError, match="rotation"):
        sh_rotation(np.diag([1.0, 1.0, -1.0]), 2)


def test_deep3d_lighting_conversion():
    # Deep3DFaceRecon's colour, written out from its source (models/bfm.py compute_color), equals our diffuse
    from reflectmm_cli.shading import sh_from_deep3d, shade_env

    rng = np.random.default_rng(0)
    gamma = rng.normal(size=27) * 0.2
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tex = rng.random((50, 3))
    pi = math.pi
    a = [pi, 2 * pi / math.sqrt(3.0), 2 * pi / math.sqrt(8.0)]
    c = [1 / math.sqrt(4 * pi), math.sqrt(3.0) / math.sqrt(4 * pi), 3 * math.sqrt(5.0) / math.sqrt(12 * pi)]
    x, y, z = n.T
    Y = np.stack([a[0] * c[0] * np.ones_like(x), -a[1] * c[1] * y, a[1] * c[1] * z, -a[1] * c[1] * x,
                  a[2] * c[2] * x * y, -a[2] * c[2] * y * z, 0.5 * a[2] * c[2] / math.sqrt(3.0) * (3 * z * z - 1),
                  -a[2] * c[2] * x * z, 0.5 * a[2] * c[2] * (x * x - y * y)], -1)
    g = gamma.reshape(3, 9) + np.array([0.8, 0, 0, 0, 0, 0, 0, 0, 0])
    deep3d = (Y @ g.T) * tex
    diffuse, _ = shade_env(tex, np.zeros(1), [8.0], n, n, sh_from_deep3d(gamma))
    np.testing.assert_allclose(diffuse, deep3d, rtol=1e-12, atol=1e-14)

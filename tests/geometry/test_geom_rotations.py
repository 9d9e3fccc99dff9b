"""geometry/rotations.py against independent computations: scipy's Rotation, the matrix exponential of [w]×,
closed-form axis rotations, and the defining properties (orthonormal, det = +1, round trips)."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from reflectmm_cli.geometry import camera
from reflectmm_cli.geometry.rotations import (
    axis_angle_to_matrix,
    euler_yxz_to_matrix,
    look_at_rotation,
    matrix_to_axis_angle,
    nearest_rotation,
    rodrigues,
    rotation_angle,
    rotation_x,
    rotation_y,
    rotation_z,
    skew,
)

unit = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: np.asarray(v) / np.linalg.norm(v))
angle = st.floats(0.0, math.pi)
# magnitudes from exactly 0 through both small-angle series thresholds (θ² = 1e-16 numpy, 1e-8 torch) to π
tiny = st.one_of(st.just(0.0), st.floats(-12.0, math.log10(math.pi)).map(lambda e: 10.0 ** e))


def _is_rotation(R, atol):
    R = np.asarray(R)
    eye = np.broadcast_to(np.eye(3), R.shape)
    return np.allclose(R @ np.swapaxes(R, -1, -2), eye, atol=atol) and np.allclose(np.linalg.det(R), 1.0, atol=atol)


def test_skew_is_the_cross_product_numpy_and_torch():
    rng = np.random.default_rng(0)
    w, v = rng.normal(size=(2, 5, 4, 3))
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", skew(w), v), np.cross(w, v), atol=1e-14)
    Kt = skew(torch.tensor(w, dtype=torch.float32))
    assert Kt.dtype == torch.float32 and Kt.shape == (5, 4, 3, 3)
    np.testing.assert_allclose(Kt.numpy(), skew(w), atol=1e-6)
    np.testing.assert_array_equal(skew(w), -np.swapaxes(skew(w), -1, -2))


@given(unit, tiny)
def test_axis_angle_is_the_exponential_of_the_skew_matrix(axis, theta):
    w = axis * theta
    ref = expm(skew(w))
    R = axis_angle_to_matrix(w)
    np.testing.assert_allclose(R, ref, atol=1e-14)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    assert _is_rotation(R, 1e-14)
    Rt = axis_angle_to_matrix(torch.tensor(w, dtype=torch.float64))
    np.testing.assert_allclose(Rt.numpy(), R, atol=1e-14)  # numpy and torch: the same rotation


def test_axis_angle_on_a_log_grid_of_angles_numpy_and_torch():
    # every decade from 1e-12 to π, so both sides of each small-angle series threshold are covered
    rng = np.random.default_rng(4)
    theta = np.logspace(-12, np.log10(math.pi), 400)
    axes = rng.normal(size=(400, 3))
    w = axes / np.linalg.norm(axes, axis=1, keepdims=True) * theta[:, None]
    ref = np.stack([expm(K) for K in skew(w)])
    np.testing.assert_allclose(axis_angle_to_matrix(w), ref, rtol=0, atol=5e-15)
    np.testing.assert_allclose(axis_angle_to_matrix(torch.tensor(w)).numpy(), ref, rtol=0, atol=5e-15)
    assert _is_rotation(axis_angle_to_matrix(w), 1e-15)


@given(unit, angle)
def test_matrix_axis_angle_round_trip(axis, theta):
    R = axis_angle_to_matrix(axis * theta)
    w = matrix_to_axis_angle(R)
    assert abs(np.linalg.norm(w) - theta) < 1e-7  # the angle is recovered
    np.testing.assert_allclose(axis_angle_to_matrix(w), R, atol=1e-9)
    if 1e-6 < theta < math.pi - 1e-6:  # away from 0 and π the vector itself is unique
        np.testing.assert_allclose(w, axis * theta, atol=1e-8)
    wt = matrix_to_axis_angle(torch.tensor(R, dtype=torch.float64))
    assert isinstance(wt, torch.Tensor) and wt.dtype == torch.float64
    np.testing.assert_array_equal(wt.numpy(), w)


def test_angle_pi_and_exact_zero():
    for axis in np.eye(3):
        R = axis_angle_to_matrix(axis * math.pi)
        np.testing.assert_allclose(R, 2 * np.outer(axis, axis) - np.eye(3), atol=1e-15)  # π: reflection through axis
        w = matrix_to_axis_angle(R)
        np.testing.assert_allclose(np.abs(w), axis * math.pi, atol=1e-12)
        assert rotation_angle(R, np.eye(3)) == pytest.approx(math.pi)
    np.testing.assert_array_equal(axis_angle_to_matrix(np.zeros(3)), np.eye(3))
    np.testing.assert_array_equal(axis_angle_to_matrix(torch.zeros(3, dtype=torch.float64)).numpy(), np.eye(3))
    np.testing.assert_array_equal(matrix_to_axis_angle(np.eye(3)), np.zeros(3))


def test_torch_gradient_at_zero_is_the_generator_and_batches():
    w = torch.zeros(3, dtype=torch.float64)
    J = torch.autograd.functional.jacobian(axis_angle_to_matrix, w)  # (3, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(J[..., k].numpy(), skew(np.eye(3)[k]), atol=1e-15)
    wb = torch.tensor(np.random.default_rng(1).normal(size=(4, 2, 3)), dtype=torch.float64)
    np.testing.assert_allclose(axis_angle_to_matrix(wb).numpy(), Rotation.from_rotvec(wb.reshape(-1, 3).numpy())
                               .as_matrix().reshape(4, 2, 3, 3), atol=1e-14)


@given(st.floats(-10.0, 10.0))
def test_axis_rotations_are_axis_angle_about_the_axes(a):
    for f, axis in ((rotation_x, 0), (rotation_y, 1), (rotation_z, 2)):
        np.testing.assert_allclose(f(a), axis_angle_to_matrix(np.eye(3)[axis] * a), atol=1e-13)


def test_axis_rotation_directions():
    np.testing.assert_allclose(rotation_y(math.pi / 2) @ [0, 0, 1.0], [1, 0, 0], atol=1e-15)  # +z → +x
    np.testing.assert_allclose(rotation_x(math.pi / 2) @ [0, 1.0, 0], [0, 0, 1], atol=1e-15)  # +y → +z
    np.testing.assert_allclose(rotation_z(math.pi / 2) @ [1.0, 0, 0], [0, 1, 0], atol=1e-15)  # +x → +y


@given(st.floats(-3, 3), st.floats(-1.5, 1.5), st.floats(-3, 3))
def test_euler_yxz_matches_scipy_extrinsic(y, x, z):
    np.testing.assert_allclose(euler_yxz_to_matrix(y, x, z), Rotation.from_euler("yxz", [y, x, z]).as_matrix(),
                               atol=1e-14)


def test_look_at_rotation():
    pos, target = np.array([300.0, 200.0, 1000.0]), np.array([10.0, -5.0, 20.0])
    R = look_at_rotation(pos, target, (0, 1, 0))
    assert _is_rotation(R, 1e-14)
    f = (target - pos) / np.linalg.norm(target - pos)
    np.testing.assert_allclose(R[2], f, atol=1e-15)          # camera +z looks at the target
    assert R[1] @ [0, 1, 0] < 0 and abs(R[0] @ [0, 1, 0]) < 1e-15  # image down is world down, x horizontal
    with pytest.raises(ValueError, match="parallel"):
        look_at_rotation((0, 0, 0), (0, 5, 0), (0, 1, 0))
    assert camera.look_at_rotation is look_at_rotation  # re-exported where cameras live


def test_nearest_rotation_and_rotation_angle():
    rng = np.random.default_rng(2)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-14)
    M = R + rng.normal(size=(3, 3)) * 0.05
    Rn = nearest_rotation(M)
    assert _is_rotation(Rn, 1e-13)
    for _ in range(20):  # no rotation is closer to M
        Q = Rn @ Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix()
        assert np.linalg.norm(M - Rn) <= np.linalg.norm(M - Q)
    Ra = Rotation.from_rotvec(rng.normal(size=(6, 3))).as_matrix()
    Rb = Rotation.from_rotvec(rng.normal(size=(6, 3))).as_matrix()
    ref = (Rotation.from_matrix(Ra).inv() * Rotation.from_matrix(Rb)).magnitude()
    np.testing.assert_allclose(rotation_angle(Ra, Rb), ref, atol=1e-7)


def test_shape_checks_and_old_names():
    for f, bad in ((skew, np.zeros(4)), (axis_angle_to_matrix, np.zeros((2, 2))),
                   (axis_angle_to_matrix, torch.zeros(2)), (matrix_to_axis_angle, np.zeros((3, 4))),
                   (nearest_rotation, np.zeros(3))):
        with pytest.raises(ValueError, match=f.__name__):
            f(bad)
    assert rodrigues is axis_angle_to_matrix
    from reflectmm_cli.geometry_fit.calibrate import rodrigues as calibrate_rodrigues
    from reflectmm_cli.model.light import rotation_y as light_rotation_y

    assert calibrate_rodrigues is axis_angle_to_matrix and light_rotation_y is rotation_y
    assert camera.axis_angle_to_matrix is axis_angle_to_matrix and camera.skew is skew

"""Rotation, projection, camera-centre and alignment maths against closed forms and scipy."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from reflectmm_cli.geometry.camera import (
    axis_angle_to_matrix,
    camera_centers,
    intrinsics,
    matrix_to_axis_angle,
    project,
)
from reflectmm_cli.geometry_fit.fit import huber
from reflectmm_cli.geometry_fit.init import pnp_pose, rigid_align

vec3 = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)


@given(vec3)
def test_axis_angle_matches_scipy(w):
    R = axis_angle_to_matrix(torch.tensor(w, dtype=torch.float64)).numpy()
    assert np.allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)


@given(st.floats(1e-9, 1e-3), vec3)
def test_axis_angle_small_angles(scale, d):
    d = np.asarray(d)
    if np.linalg.norm(d) < 1e-6:
        d = np.array([1.0, 0.0, 0.0])
    w = d / np.linalg.norm(d) * scale
    R = axis_angle_to_matrix(torch.tensor(w, dtype=torch.float64)).numpy()
    assert np.allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-15)


def test_axis_angle_gradient_at_zero_is_the_generator():
    # d/dw_k of exp([w]x) at 0 is the k-th cross-product generator
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    for k in range(3):
        g = torch.autograd.functional.jacobian(lambda x: axis_angle_to_matrix(x), w)[..., k]
        e = np.zeros(3)
        e[k] = 1.0
        G = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
        assert np.allclose(g.numpy(), G, atol=1e-12)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64,
                                                                         requires_grad=True),))


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.5, math.pi - 1e-6, math.pi])
def test_matrix_to_axis_angle_round_trip(angle):
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    R = Rotation.from_rotvec(axis * angle).as_matrix()
    w = matrix_to_axis_angle(R)
    assert np.allclose(Rotation.from_rotvec(w).as_matrix(), R, atol=1e-9)


@given(vec3, vec3)
def test_camera_center_identity(w, t):
    R = Rotation.from_rotvec(w).as_matrix()
    t = np.asarray(t) * 500.0
    c = camera_centers(R, t)
    assert np.allclose(R @ c + t, 0.0, atol=1e-9)  # the centre maps to the camera origin
    ct = camera_centers(torch.tensor(R), torch.tensor(t)).numpy()
    assert np.allclose(ct, c, atol=1e-12)


def test_projection_closed_form():
    K = intrinsics(1000.0, 640, 480)
    assert K[0, 2] == 319.5 and K[1, 2] == 239.5
    # a camera at (0, 0, 1300) looking at the origin (x right, y down, z forward = −z model)
    R = np.diag([1.0, -1.0, -1.0])
    t = -R @ np.array([0.0, 0.0, 1300.0])
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 20.0, 100.0]])
    uv, z = project(pts, K, R, t)
    assert np.allclose(z, [1300.0, 1300.0, 1200.0])
    assert np.allclose(uv[0], [319.5, 239.5])
    assert np.allclose(uv[1], [319.5 + 1000 * 10 / 1300, 239.5])
    assert np.allclose(uv[2], [319.5, 239.5 - 1000 * 20 / 1200])  # +y model is up = −v
    uvt, zt = project(torch.tensor(pts), torch.tensor(K), torch.tensor(R), torch.tensor(t))
    assert np.allclose(uvt.numpy(), uv) and np.allclose(zt.numpy(), z)


def test_huber_is_c1():
    x = torch.tensor([0.0, 1.0, 2.0, 2.0 + 1e-9, 5.0], dtype=torch.float64, requires_grad=True)
    y = huber(x, 2.0)
    assert np.allclose(y.detach().numpy(), [0.0, 0.5, 2.0, 2.0 + 2e-9, 2.0 * (5.0 - 1.0)])
    (g,) = torch.autograd.grad(y.sum(), x)
    assert np.allclose(g.numpy(), [0.0, 1.0, 2.0, 2.0, 2.0])


def test_rigid_align_recovers_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(9, 3)) * 800
    R = Rotation.from_rotvec([0.1, -0.4, 0.2]).as_matrix()
    t = np.array([5.0, -30.0, 12.0])
    Ra, ta, res = rigid_align(src, src @ R.T + t)
    assert np.allclose(Ra, R, atol=1e-10) and np.allclose(ta, t, atol=1e-8) and res.max() < 1e-8


def test_pnp_refines_a_perturbed_pose():
    rng = np.random.default_rng(1)
    obj = rng.normal(size=(68, 3)) * np.array([60, 80, 30])
    K = intrinsics(1000.0, 640, 480)
    R = Rotation.from_rotvec([0.2, 2.9, 0.1]).as_matrix()
    t = np.array([10.0, -5.0, 1300.0])
    img, _ = project(obj, K, R, t)
    R0 = Rotation.from_rotvec([0.25, 2.8, 0.05]).as_matrix()
    Rf, tf, rms = pnp_pose(obj, img, K, R0, t + np.array([20.0, 10.0, 50.0]))
    # OpenCV 5 stops its LM at 1.4e-6 px (4.x went below 1e-6); the pose is exact to 3e-8 either way
    assert rms < 1e-5 and np.allclose(Rf, R, atol=1e-7) and np.allclose(tf, t, atol=1e-4)


def test_flash_positions_follow_the_rig_transform():
    from reflectmm_cli.geometry_fit.init import flash_positions
    from reflectmm_cli.rig import ALL_FLASHES, DEFAULT_VIEWS, load_rig

    rig = load_rig()
    views = list(DEFAULT_VIEWS)
    Ra = Rotation.from_rotvec([0.05, -0.2, 0.03]).as_matrix()
    ta = np.array([12.0, -30.0, 25.0])
    # cameras of a head that sits at x_model = Ra x_rig + ta: R' = R Raᵀ, t' = t − R' ta
    R = np.array([rig.camera(v).R @ Ra.T for v in views])
    t = np.array([rig.camera(v).t - R[i] @ ta for i, v in enumerate(views)])
    pos, inten, src, res = flash_positions(rig, list(ALL_FLASHES), views, R, t)
    expect = np.array([Ra @ rig.flash(f).position + ta for f in ALL_FLASHES])
    assert np.allclose(pos, expect, atol=1e-8) and res.max() < 1e-8
    assert np.allclose(inten, [rig.flash(f).intensity for f in ALL_FLASHES])
    on_views = {f for f in ALL_FLASHES if rig.flash(f).camera in views}
    assert {f for f, s in zip(ALL_FLASHES, src) if s == "view"} == on_views
    assert src[list(ALL_FLASHES).index("16")] == "rig" and src[list(ALL_FLASHES).index("14")] == "rig"

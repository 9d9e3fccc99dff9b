"""Cameras: OpenCV projection against closed forms, rays, presets, torch projection."""
import numpy as np
import pytest
import torch

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry import Camera, deep3d_camera, look_at, orbit_camera, parse_camera_spec
from reflectmm_cli.geometry import project as project_torch


def test_frontal_closed_form():
    cam = look_at((0, 0, 1000), (0, 0, 0), (0, 1, 0), focal_px=1500, width=640, height=480)
    np.testing.assert_allclose(cam.center, [0, 0, 1000], atol=1e-9)
    pts = np.array([[10.0, 20.0, 0.0], [-30.0, 5.0, 100.0], [0, 0, 0]])
    uv, z = cam.project(pts)
    Z = 1000 - pts[:, 2]
    np.testing.assert_allclose(z, Z)
    # +x (subject's left) is image right, +y (up) is image up = smaller row
    np.testing.assert_allclose(uv[:, 0], 319.5 + 1500 * pts[:, 0] / Z)
    np.testing.assert_allclose(uv[:, 1], 239.5 - 1500 * pts[:, 1] / Z)


def test_center_is_minus_Rt_t_and_yaw_direction():
    cam = orbit_camera(yaw_deg=90, distance=800)
    np.testing.assert_allclose(cam.center, [800, 0, 0], atol=1e-9)
    np.testing.assert_allclose(cam.center, -cam.R.T @ cam.t)
    np.testing.assert_allclose(cam.forward, [-1, 0, 0], atol=1e-12)
    up = orbit_camera(pitch_deg=30, distance=1000).center
    assert up[1] > 0
    c = parse_camera_spec("yaw=-45,distance=1200,size=320x240")
    np.testing.assert_allclose(c.center, 1200 * np.array([-np.sqrt(0.5), 0, np.sqrt(0.5)]), atol=1e-9)
    assert (c.width, c.height) == (320, 240)
    with pytest.raises(ReflectmmError, match="cannot parse"):
        parse_camera_spec("yaw:30")
    for bad, what in (("yaw=0,focal=0", "focal"), ("distance=-5", "distance"), ("size=0x48", "width")):
        with pytest.raises(ReflectmmError, match=f"{what} must be finite and > 0"):  # focal 0: a singular K
            parse_camera_spec(bad)


def test_rays_reproject_to_their_pixels():
    cam = orbit_camera(yaw_deg=25, pitch_deg=-10, distance=900, focal_px=1200, width=64, height=48)
    cam.K[0, 1] = 3.0  # skew is honoured
    o, d = cam.rays()
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    pts = o + d * np.linspace(300, 1500, len(d))[:, None]
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv, cam.pixel_grid(), atol=1e-7)
    assert np.all(z > 0)


def test_behind_camera_is_nan():
    cam = look_at((0, 0, 100))
    uv, z = cam.project(np.array([[0.0, 0.0, 200.0]]))
    assert z[0] < 0 and np.all(np.isnan(uv))


def test_deep3d_preset_matches_its_projection():
    cam = deep3d_camera()
    rng = np.random.default_rng(0)
    p_dm = rng.uniform(-1, 1, size=(20, 3))  # Deep3D units (dm)
    zc = 10 - p_dm[:, 2]
    u_ref = 1015 * p_dm[:, 0] / zc + 112
    v_up = 1015 * p_dm[:, 1] / zc + 112  # Deep3D's image v points up
    uv, z = cam.project(p_dm * 100.0)  # our model space is mm
    np.testing.assert_allclose(uv[:, 0], u_ref, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], 224 - v_up, atol=1e-9)
    np.testing.assert_allclose(z, zc * 100)
    np.testing.assert_allclose(cam.center, [0, 0, 1000])


def test_project_torch_matches_and_gradient():
    cam = orbit_camera(yaw_deg=15, distance=1000)
    pts = torch.tensor(np.random.default_rng(1).uniform(-80, 80, (5, 3)), requires_grad=True)
    uv, z = project_torch(pts, cam.K, cam.R, cam.t)
    uv_np, z_np = cam.project(pts.detach().numpy())
    np.testing.assert_allclose(uv.detach().numpy(), uv_np, atol=1e-9)
    np.testing.assert_allclose(z.detach().numpy(), z_np, atol=1e-9)
    uv[2, 0].backward()
    h = 1e-5
    p = pts.detach().numpy().copy()
    p[2, 1] += h
    fd = (cam.project(p)[0][2, 0] - uv_np[2, 0]) / h
    assert abs(pts.grad[2, 1].item() - fd) < 1e-4
    # batched over views
    Ks = np.stack([cam.K, cam.K])
    Rs = np.stack([cam.R, np.eye(3)])
    ts = np.stack([cam.t, [0, 0, 1000.0]])
    uvb, _ = project_torch(pts.detach()[None].expand(2, -1, -1), Ks, Rs, ts)
    np.testing.assert_allclose(uvb[0].numpy(), uv_np, atol=1e-9)


def test_bad_rotation_refused():
    with pytest.raises(ReflectmmError, match="rotation"):
        Camera(np.eye(3), np.diag([1.0, 1.0, -1.0]), np.zeros(3), 10, 10)


def test_deep3d_camera_frames_the_procedural_face():
    from reflectmm_cli.geometry import procedural_face_model

    m = procedural_face_model(n_vertices=3000, n_shape=1, n_exp=1)
    cam = deep3d_camera()
    uv, z = cam.project(m.mean_shape[m.landmarks])
    assert np.all((uv > 0) & (uv < 224)) and np.all(z > 800)
    # the subject's right eye (iBUG 36-41) is on the image left, the forehead up (small rows)
    assert uv[36:42, 0].mean() < 112 < uv[42:48, 0].mean()
    assert uv[19, 1] < uv[8, 1]


def test_with_size_keeps_the_pixel_centre_convention():
    cam = orbit_camera(20, 5, 900, focal_px=1000, width=320, height=240)
    big = cam.with_size(640, 480)
    p = np.random.default_rng(0).uniform(-50, 50, (10, 3))
    uv, _ = cam.project(p)
    uv2, _ = big.project(p)
    np.testing.assert_allclose(uv2, (uv + 0.5) * 2 - 0.5, atol=1e-9)
    np.testing.assert_allclose(big.center, cam.center)

"""The flash (point-light) photometric term of fit-geometry: its formulas, its gradient, and what it buys on the
toy model rendered by an independent ray tracer with cast shadows."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

import toy
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry_fit import FitConfig, ViewSet, fit_geometry, initial_poses
from reflectmm_cli.geometry_fit.photometric import flash_loss, gather_bilinear, point_irradiance, sample_images
from reflectmm_cli.geometry_fit.visibility import vertex_visibility

D = torch.float64
AZ = [-45, -15, 15, 45]
W, H = 320, 240
RAISED = np.array([0.0, 600.0, 1150.0])  # a free-standing flash above the arc (rig frame = model frame here)


def test_point_irradiance_closed_forms():
    p = torch.zeros(3, 3, dtype=D)
    n = torch.tensor([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0]], dtype=D)
    lights = torch.tensor([[0, 0, 2.0], [math.sqrt(3.0), 0, 1.0]], dtype=D)  # on the normal; 60° off it
    E, ld = point_irradiance(p[None], n[None], lights[:, None], torch.tensor([[8.0], [8.0]], dtype=D))
    assert torch.allclose(E[0], torch.tensor([2.0, 2.0, 0.0], dtype=D))  # I/d², I/d², back-facing → 0
    assert torch.allclose(E[1, :2], torch.tensor([8.0 * 0.5 / 4.0] * 2, dtype=D))  # I cos60°/d²
    assert torch.allclose(ld[1, 0], torch.tensor([math.sqrt(3.0) / 2, 0, 0.5], dtype=D))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.floats(1e-3, 1e4))
def test_point_irradiance_is_finite_and_matches_numpy(seed, dist):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(7, 3))
    nrm = rng.normal(size=(7, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    lp = rng.normal(size=(3, 3))
    lp = dist * lp / np.linalg.norm(lp, axis=-1, keepdims=True) + 2 * dist * np.eye(3)
    inten = rng.uniform(0.1, 10, size=3)
    E, _ = point_irradiance(torch.tensor(pts)[None], torch.tensor(nrm)[None], torch.tensor(lp)[:, None],
                            torch.tensor(inten)[:, None])
    ref = np.zeros((3, 7))
    for a in range(3):
        for m in range(7):
            d = lp[a] - pts[m]
            r = math.sqrt(d @ d)
            ref[a, m] = inten[a] * max(float(nrm[m] @ d) / r, 0.0) / (r * r)
    assert np.isfinite(E.numpy()).all()
    assert np.allclose(E.numpy(), ref, rtol=1e-10, atol=0.0)


def test_flash_albedo_is_the_weighted_least_squares_per_vertex():
    # uniform images: each pair observes one colour everywhere, so the albedo of vertex m is the weighted
    # least-squares fit of those colours by its irradiances — compared with numpy's lstsq
    rng = np.random.default_rng(2)
    M, P = 6, 5
    pts = rng.normal(size=(M, 3)) * 10
    nrm = np.tile([0, 0, 1.0], (M, 1)) + rng.normal(size=(M, 3)) * 0.2
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    lights = np.column_stack([rng.uniform(-300, 300, P), rng.uniform(-300, 300, P), np.full(P, 800.0)])
    inten = rng.uniform(5e5, 1e6, P)
    colours = rng.uniform(0.1, 0.9, size=(P, 3))
    images = torch.tensor(np.broadcast_to(colours[:, None, None, :], (P, 8, 8, 3)).copy(), dtype=D)
    weight = (rng.uniform(size=(P, M)) > 0.25).astype(float)
    weight[:, 0] = 1.0
    K = torch.tensor([[[100.0, 0, 3.5], [0, 100.0, 3.5], [0, 0, 1]]], dtype=D)
    R = torch.eye(3, dtype=D)[None]
    t = torch.tensor([[0, 0, 1000.0]], dtype=D)
    _, r, c = flash_loss(torch.tensor(pts), torch.tensor(nrm), torch.arange(M), torch.tensor(weight), K, R, t,
                         images, torch.zeros(P, dtype=torch.long), torch.tensor(lights), torch.tensor(inten), 0.3)
    for m in range(M):
        d = lights - pts[m]
        dist = np.linalg.norm(d, axis=-1)
        E = inten * np.clip((d @ nrm[m]) / dist, 0, None) / dist ** 2
        w = weight[:, m] > 0
        for ch in range(3):
            ref = np.linalg.lstsq(E[w, None], colours[w, ch], rcond=None)[0][0]
            assert c[m, ch].item() == pytest.approx(ref, rel=1e-10)
        assert np.allclose(r[w, m].numpy(), c[m].numpy()[None] * E[w, None] - colours[w])
        assert not r[~w, m].numpy().any()


def _flash_world(gains=(1.0, 1.0, 1.0, 1.0, 1.0), n_shape=6, seed=1):
    m = toy.toy_model(n_shape=n_shape, n_exp=2, texture=True)
    rng = np.random.default_rng(seed)
    zs = rng.normal(size=m.n_shape) * 0.8
    ze = rng.normal(size=m.n_exp) * 0.5
    verts = m.vertices(zs * m.shape_sigma, ze * m.exp_sigma)
    K, R, t = toy.arc_cameras(AZ, focal=1000 * H / 480, width=W, height=H)
    lights = np.vstack([camera_centers(R, t), RAISED])
    inten = 2.6e6 * np.asarray(gains)
    imgs = np.stack([np.stack([toy.render_point(verts, m.triangles, m.mean_tex, lights[f], inten[f], K[v], R[v],
                                                t[v], W, H) for f in range(len(lights))])
                     for v in range(len(AZ))]).astype(np.float32)
    return m, zs, ze, verts, K, R, t, lights, imgs


@pytest.fixture(scope="module")
def world():
    return _flash_world()


def _loss(world, verts=None, t_shift=(0.0, 0.0, 0.0), scale=0.2):
    m, zs, ze, vtrue, K, R, t, lights, imgs = world
    verts = vtrue if verts is None else verts
    V, F = imgs.shape[:2]
    X = torch.tensor(verts, dtype=D)
    nrm = torch.tensor(vertex_normals(verts, m.triangles, dtype=np.float64))
    front = np.nonzero(vertex_normals(vtrue, m.triangles)[:, 2] > 0.7)[0]
    pv = np.repeat(np.arange(V), F)
    pf = np.tile(np.arange(F), V)
    # samples seen by the camera and lit by the flash (ray cast at the truth, cos > 0.3)
    n_true = vertex_normals(vtrue, m.triangles, dtype=np.float64)
    cam = vertex_visibility(vtrue, m.triangles, n_true, camera_centers(R, t), sample=front, cos_cutoff=0.3)
    lit = vertex_visibility(vtrue, m.triangles, n_true, lights, sample=front, cos_cutoff=0.3)
    weight = (cam[pv] & lit[pf]).astype(float)
    images = torch.tensor(imgs[pv, pf], dtype=D)
    loss, r, c = flash_loss(X, nrm, torch.tensor(front), torch.tensor(weight), torch.tensor(K, dtype=D),
                            torch.tensor(R, dtype=D), torch.tensor(t + np.asarray(t_shift), dtype=D), images,
                            torch.tensor(pv), torch.tensor(lights[pf], dtype=D),
                            torch.full((len(pf),), 2.6e6, dtype=D), scale, eps=1e-3)
    return float(loss), r.numpy(), c.numpy(), front


def test_flash_residual_vanishes_at_truth_and_grows_off_shape(world):
    m, zs, ze, verts, *_ = world
    l0, r0, c0, front = _loss(world)
    # at the truth the residual is the interpolation of the ray-traced pixels only, and the albedo is the texture
    assert np.median(np.abs(r0)) < 0.004
    assert np.median(np.abs(c0 * math.pi - m.mean_tex[front])) < 0.01
    bent = m.vertices((zs + np.r_[0.4, np.zeros(m.n_shape - 1)]) * m.shape_sigma, ze * m.exp_sigma)
    assert _loss(world, verts=bent)[0] > 1.5 * l0
    assert _loss(world, t_shift=(2.0, 0.0, 0.0))[0] > 1.5 * l0


def test_flash_gradient_matches_finite_differences(world):
    m, zs, ze, verts, K, R, t, lights, imgs = world
    V, F = imgs.shape[:2]
    pv = torch.tensor(np.repeat(np.arange(V), F))
    pf = np.tile(np.arange(F), V)
    front = torch.tensor(np.nonzero(vertex_normals(verts, m.triangles)[:, 2] > 0.7)[0][::9])
    images = torch.tensor(imgs[pv.numpy(), pf], dtype=D)
    tri = torch.tensor(m.triangles)
    base = torch.tensor(verts, dtype=D)
    dirs = torch.tensor(np.random.default_rng(0).normal(size=(2, len(base), 3)), dtype=D)
    weight = torch.ones(len(pf), len(front), dtype=D)
    Kt, Rt = torch.tensor(K, dtype=D), torch.tensor(R, dtype=D)

    def f(p):
        X = base + p[0] * dirs[0] + p[1] * dirs[1]
        tt = torch.tensor(t, dtype=D) + p[2:5]
        lp = torch.tensor(lights[pf], dtype=D) + p[5:8]
        return flash_loss(X, vertex_normals(X, tri), front, weight, Kt, Rt, tt, images, pv, lp,
                          torch.full((len(pf),), 2.6e6, dtype=D), 0.2, eps=0.02)[0]

    p = torch.tensor([0.1, -0.05, 0.3, -0.2, 0.5, 3.0, -2.0, 1.0], dtype=D, requires_grad=True)
    (g,) = torch.autograd.grad(f(p), p)
    h = 1e-6
    with torch.no_grad():
        fd = torch.stack([(f(p + h * e) - f(p - h * e)) / (2 * h) for e in torch.eye(8, dtype=D)])
    assert torch.allclose(g, fd, rtol=1e-4, atol=1e-8), (g, fd)
    assert g[:5].abs().max() > 1e-4 and g[5:].abs().max() > 0  # geometry and light positions both matter


def test_flash_stage_improves_a_noisy_landmark_fit_and_recovers_flash_gains():
    # 2 px landmark noise; the flashes' true intensities differ by up to 20 % from the table's (all equal): the
    # flash rounds must pull the geometry towards the truth and find the relative intensities.  Measured: vertex
    # RMSE 3.20 mm with landmarks only, 0.58 mm with the flash rounds; gains within 1.5 % of the truth.
    gains = np.array([1.0, 1.2, 0.85, 1.1, 0.95])
    m, zs, ze, verts, K, R, t, lights, imgs = _flash_world(gains=gains)
    rng = np.random.default_rng(4)
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(len(AZ))])
    lm = lm + rng.normal(size=lm.shape) * 2.0
    R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, R, t)
    vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H),
                 rig_centers=camera_centers(R, t), flash_images=imgs, flash_view=np.array([0, 1, 2, 3, -1]),
                 flash_rig_pos=np.vstack([np.full((4, 3), np.nan), RAISED]), flash_intensity=np.full(5, 2.6e6))

    def err(fit):
        return np.sqrt(((fit.vertices - verts) ** 2).sum(-1).mean())

    lm_only = fit_geometry(m, vs, FitConfig(landmark_sigma_px=2.0, photo_rounds=0))
    flash = fit_geometry(m, vs, FitConfig(landmark_sigma_px=2.0, photo_rounds=0, flash_rounds=2, w_flash=100.0))
    assert lm_only.flash_residual is None
    assert np.all(flash.flash_residual < 0.01)
    assert err(flash) < 0.5 * err(lm_only), (err(flash), err(lm_only))
    true_rel = gains / np.exp(np.log(gains).mean())
    assert np.allclose(flash.flash_gain, true_rel, rtol=0.03), (flash.flash_gain, true_rel)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_gather_bilinear_matches_grid_sample(seed):
    rng = np.random.default_rng(seed)
    P, h, w = 3, 7, 9
    imgs = rng.uniform(size=(P, h, w, 3))
    uv = np.column_stack([rng.uniform(-1, w, 20), rng.uniform(-1, h, 20)])
    pair = rng.integers(0, P, 20)
    got = gather_bilinear(torch.tensor(imgs), torch.tensor(pair), torch.tensor(uv)).numpy()
    ref = sample_images(torch.tensor(imgs.transpose(0, 3, 1, 2).copy()),
                        torch.tensor(uv[None].repeat(P, 0))).numpy()[pair, np.arange(20)]
    assert np.allclose(got, ref, atol=1e-12)


def test_wrong_flash_positions_show_in_the_flash_residual():
    # the flash positions are what the user must know (docs/fit-geometry.md): placed 80 mm off, the fit can no
    # longer explain the shading, and the reported residual says so (measured: 0.0011 → 0.0072, while the vertex
    # error goes from 0.13 to 2.4 mm)
    m, zs, ze, verts, K, R, t, lights, imgs = _flash_world()
    rng = np.random.default_rng(4)
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(len(AZ))])
    lm = lm + rng.normal(size=lm.shape) * 1.0
    R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, R, t)

    def fit(offset_mm):
        off = rng.normal(size=(len(lights), 3))
        off *= offset_mm / np.linalg.norm(off, axis=-1, keepdims=True)
        vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H),
                     rig_centers=camera_centers(R, t), flash_images=imgs, flash_view=np.full(len(lights), -1),
                     flash_rig_pos=lights + off, flash_intensity=np.full(len(lights), 2.6e6))
        return fit_geometry(m, vs, FitConfig(photo_rounds=0, flash_rounds=2))

    right, wrong = fit(0.0), fit(80.0)
    assert np.median(wrong.flash_residual) > 3 * np.median(right.flash_residual), (right.flash_residual,
                                                                                      wrong.flash_residual)


def test_vertex_visibility_shares_rays_between_eyes_at_one_place_and_applies_each_cutoff():
    # a bumpy sheet seen from three eyes, two of them at one place (a camera and the flash it carries): one call
    # with per-eye cutoffs equals separate calls, and an independent test (n·dir, then a dense segment check
    # against every triangle) agrees
    g = np.linspace(-1.0, 1.0, 9)
    xx, yy = np.meshgrid(g, g)
    zz = 0.3 * np.sin(3 * xx) * np.cos(2 * yy)
    v = np.c_[xx.ravel(), yy.ravel(), zz.ravel()]
    tri = []
    for i in range(8):
        for j in range(8):
            a = i * 9 + j
            tri += [[a, a + 1, a + 10], [a, a + 10, a + 9]]
    tri = np.array(tri)
    n = vertex_normals(v, tri, dtype=np.float64)
    eyes = np.array([[2.0, 0.0, 1.0], [2.0, 0.0, 1.0], [3.0, 0.5, 0.4]])   # grazing: some vertices occluded
    cut = np.array([0.6, 0.0, 0.1])
    both = vertex_visibility(v, tri, n, eyes, cos_cutoff=cut)
    for k in range(3):
        np.testing.assert_array_equal(both[k], vertex_visibility(v, tri, n, eyes[k:k + 1], cos_cutoff=cut[k])[0])
    assert (both[1] & ~both[0]).any()                     # the same rays, a looser cutoff: more vertices
    facing = ((eyes[2] - v) / np.linalg.norm(eyes[2] - v, axis=1)[:, None] * n).sum(1) > cut[2]
    assert (facing & ~both[2]).sum() >= 5                 # and the occlusion test has work to do
    # independent: facing by the cutoff, unoccluded by a dense Möller–Trumbore test of every triangle
    for k, c in enumerate(eyes):
        for m in range(len(v)):
            d = c - v[m]
            dist = np.linalg.norm(d)
            d /= dist
            if (n[m] @ d) <= cut[k]:
                assert not both[k, m]
                continue
            if (n[m] @ d) <= cut[k] + 0.1:   # grazing: the ray leaves along the vertex's own faces, where the ray
                continue                     # caster's offset start decides; not a test of the sharing
            hit = False
            for t0, t1, t2 in tri:
                if m in (t0, t1, t2):
                    continue
                e1, e2 = v[t1] - v[t0], v[t2] - v[t0]
                pv = np.cross(d, e2)
                det = e1 @ pv
                if abs(det) < 1e-12:
                    continue
                tv = v[m] - v[t0]
                u = (tv @ pv) / det
                qv = np.cross(tv, e1)
                w = (d @ qv) / det
                s = (e2 @ qv) / det
                if u >= 0 and w >= 0 and u + w <= 1 and 1e-6 < s < dist:
                    hit = True
                    break
            assert both[k, m] == (not hit), (k, m)

"""The named stages of fit_geometry (_FitProblem and its steps), each against an independent computation
(issue 20)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import toy
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry_fit import FitConfig, ViewSet, initial_poses
from reflectmm_cli.geometry_fit.fit import (
    _FitProblem, _FlashPairs, _albedo_mode, _flash_weights, _landmark_stage, _photometric_stage, _round_blurs,
    _sub_mesh, _usable_flashes)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit.landmarks import landmark_weights

AZ = [-45, -15, 15, 45]
W, H = 160, 120
RAISED = np.array([0.0, 600.0, 1150.0])


@pytest.fixture(scope="module")
def scene():
    m = toy.toy_model(n_shape=4, n_exp=2, texture=True)
    rng = np.random.default_rng(7)
    zs = rng.normal(size=m.n_shape) * 0.8
    ze = rng.normal(size=m.n_exp) * 0.5
    verts = m.vertices(zs * m.shape_sigma, ze * m.exp_sigma)
    K, R, t = toy.arc_cameras(AZ, focal=1000 * H / 480, width=W, height=H)
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(4)])
    lm = lm + rng.normal(size=lm.shape)
    R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, R, t)
    return m, verts, K, R, t, lm, R0, t0


def _views(scene, **kw):
    m, verts, K, R, t, lm, R0, t0 = scene
    return ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H),
                   rig_centers=camera_centers(R, t), **kw)


def test_landmark_loss_and_prior_match_numpy(scene):
    m, verts, K, R, t, lm, R0, t0 = scene
    cfg = FitConfig(huber_px=1.5, landmark_sigma_px=2.0, w_shape=0.7, w_exp=1.3, rig_sigma_mm=0.0)
    prob = _FitProblem(m, _views(scene), cfg, "cpu")
    with torch.no_grad():
        prob.zs.copy_(torch.linspace(-1, 1, m.n_shape, dtype=torch.float64))
        prob.ze.copy_(torch.tensor([0.3, -0.4], dtype=torch.float64))
        Rt, tt = prob.poses()
        loss = float(prob.landmark_term(Rt, tt))
        prior = float(prob.prior(Rt, tt))
    X = m.vertices(prob.zs.detach().numpy() * m.shape_sigma, prob.ze.detach().numpy() * m.exp_sigma)
    d = np.linalg.norm(np.stack([project(X[m.landmarks], K[v], R0[v], t0[v])[0] for v in range(4)]) - lm, axis=-1)
    hub = np.where(d <= 1.5, 0.5 * d * d, 1.5 * (d - 0.75))
    w = np.broadcast_to(landmark_weights(None), d.shape)
    assert loss == pytest.approx((w * hub).sum() / (w.sum() * 4.0), rel=1e-9)
    z2 = 0.7 * (prob.zs.detach().numpy() ** 2).sum() + 1.3 * (prob.ze.detach().numpy() ** 2).sum()
    assert prior == pytest.approx(0.5 * z2 / w.sum(), rel=1e-12)


def test_rig_prior_is_zero_on_the_aligned_rig(scene):
    # initial poses from the true cameras: the rigid rig → model map aligns the centres exactly
    m, verts, K, R, t, lm, _, _ = scene
    vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R, t0=t, landmarks=lm, image_size=(W, H),
                 rig_centers=camera_centers(R, t), rig_R=R)
    prob = _FitProblem(m, vs, FitConfig(rig_rot_sigma_deg=1.0, head_sigma_mm=0.0), "cpu")
    assert prob.use_rig and prob.use_rot
    with torch.no_grad():
        assert float(prob.prior(*prob.poses())) == pytest.approx(0.0, abs=1e-12)


def test_landmark_stage_lowers_the_loss_and_records_it(scene):
    m, verts, K, R, t, lm, R0, t0 = scene
    vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0 + [8.0, -5.0, 30.0], landmarks=lm,
                 image_size=(W, H), rig_centers=camera_centers(R, t))  # initial poses 30 mm off
    prob = _FitProblem(m, vs, FitConfig(landmark_iters=50), "cpu")

    def total():
        with torch.no_grad():
            R, t = prob.poses()
            return float(prob.landmark_term(R, t) + prob.prior(R, t))

    before = total()
    _landmark_stage(prob)
    assert prob.history[-1]["stage"] == "landmarks"
    assert prob.history[-1]["loss"] == pytest.approx(total(), rel=1e-12)
    assert total() < 0.5 * before


def test_a_poses_only_run_holds_the_face_out_of_autograd_and_moves_as_before(scene):
    # run_lbfgs over the poses alone: the face and the head are constants of that run.  Against the same run with
    # every unknown in autograd and the face's steps masked to zero (what the registration did before), the poses
    # must come out the same to the bit; the face gets no gradient and is an unknown again afterwards.
    m, verts, K, R, t, lm, R0, t0 = scene
    vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0 + [4.0, -3.0, 10.0], landmarks=lm,
                 image_size=(W, H), rig_centers=camera_centers(R, t))

    def loss_of(prob):
        def loss():
            R_, t_ = prob.poses()
            return prob.landmark_term(R_, t_) + prob.prior(R_, t_)
        return loss

    held = _FitProblem(m, vs, FitConfig(), "cpu")
    with torch.no_grad():
        held.zs.copy_(torch.linspace(-0.5, 0.5, m.n_shape, dtype=torch.float64))
    held.run_lbfgs([held.dw, held.dtr], loss_of(held), 25, "poses", tick=False)
    assert all(p.grad is None for p in (held.zs, held.ze, held.dwh, held.dth))
    assert all(p.requires_grad for p in (held.zs, held.ze, held.dwh, held.dth))

    masked = _FitProblem(m, vs, FitConfig(), "cpu")
    with torch.no_grad():
        masked.zs.copy_(torch.linspace(-0.5, 0.5, m.n_shape, dtype=torch.float64))
    from reflectmm_cli.geometry_fit.fit import lbfgs_minimise
    lbfgs_minimise([masked.dw, masked.dtr], loss_of(masked), 25)  # the face's gradients computed, then unused
    assert masked.zs.grad is not None and float(masked.zs.grad.abs().sum()) > 0
    assert torch.equal(held.dw, masked.dw) and torch.equal(held.dtr, masked.dtr)
    assert torch.equal(held.zs, masked.zs)
    assert float(held.dw.detach().abs().sum()) > 0  # the run did move the poses


def test_sub_mesh_normals_are_the_full_mesh_normals(scene):
    m = scene[0]
    prob = _FitProblem(m, _views(scene), FitConfig(photo_vertices=300), "cpu")
    with torch.no_grad():
        prob.zs.fill_(0.5)
    sm = _sub_mesh(prob)
    assert len(sm.sample) <= 300
    with torch.no_grad():
        Xs, nv = sm.surface(prob)
        X = prob.verts().numpy()
    full = vertex_normals(X, m.triangles, dtype=np.float64)
    assert np.allclose(Xs[sm.sample_t].numpy(), X[sm.sample], atol=1e-12)
    assert np.allclose(nv[sm.sample_t].numpy(), full[sm.sample], atol=1e-9)


def test_a_held_face_computes_its_surface_once_and_again_after_a_change(scene):
    # With the face out of autograd (a registration, the pose curvature) the sub-mesh surface is a constant: the
    # same tensors come back while the coefficients are unchanged, and a new surface — equal to the one computed
    # from scratch — after an in-place change of them.  With the face in autograd nothing is kept.
    m = scene[0]
    prob = _FitProblem(m, _views(scene), FitConfig(photo_vertices=300), "cpu")
    sm = _sub_mesh(prob)
    free = sm.surface(prob)
    assert free[0].requires_grad and sm._held is None
    with prob.held_out_of([prob.dw, prob.dtr]):
        X1, n1 = sm.surface(prob)
        X2, n2 = sm.surface(prob)
        assert X1 is X2 and n1 is n2 and not X1.requires_grad
        assert torch.equal(X1, free[0].detach()) and torch.equal(n1, free[1].detach())
        with torch.no_grad():
            prob.zs.add_(0.3)  # an in-place change: a new surface
        X3, n3 = sm.surface(prob)
        assert X3 is not X1 and not torch.equal(X3, X1)
        fresh = sm._surface(prob.zs, prob.ze)
        assert torch.equal(X3, fresh[0]) and torch.equal(n3, fresh[1])
        with torch.no_grad():
            prob.ze.sub_(0.2)
        assert not torch.equal(sm.surface(prob)[0], X3)
    again = sm.surface(prob)  # the face is an unknown again: computed with its graph
    assert again[0].requires_grad and sm._held is None


def test_albedo_mode_and_round_blurs():
    m = toy.toy_model(n_shape=2, n_exp=1, texture=False)
    assert _albedo_mode(m, FitConfig()) == "per-vertex"
    with pytest.raises(ReflectmmError, match="no mean texture"):
        _albedo_mode(m, FitConfig(albedo="texture"))
    assert _round_blurs(FitConfig(photo_blur_px=(2.0, 1.0)), 3)[:4] == [2.0, 1.0, 1.0, 1.0]
    assert _round_blurs(FitConfig(photo_blur_px=()), 2) == [0.0, 0.0]


def test_photometric_stage_fits_lighting_to_a_rendered_face(scene):
    # images rendered at the truth under known SH light: after one round the linear residual is small
    m, verts, K, R, t, lm, R0, t0 = scene
    sh = np.zeros((9, 3))
    sh[0] = [1.2, 1.1, 1.0]
    sh[2] = [0.4, 0.4, 0.35]
    imgs = np.stack([toy.render(verts, m.triangles, m.mean_tex, sh, K[v], R[v], t[v], W, H)
                     for v in range(4)]).astype(np.float32)
    prob = _FitProblem(m, _views(scene, images=imgs), FitConfig(photo_rounds=1, photo_iters=15,
                                                                photo_vertices=500), "cpu")
    _landmark_stage(prob)
    out = _photometric_stage(prob, _sub_mesh(prob))
    assert np.all(out.visible > 50) and np.all(out.residual < 0.05)
    assert out.sh.shape == (4, 9, 3)
    assert prob.history[-1]["stage"] == "photometric round 1"


def test_flash_pairs_gains_and_weights(scene):
    m, verts, K, R, t, lm, R0, t0 = scene
    F = 5
    fimg = np.full((4, F, H, W, 3), 0.5, np.float32)
    vs = _views(scene, flash_images=fimg, flash_view=np.array([0, 1, 2, 3, -1]),
                flash_rig_pos=np.vstack([np.full((4, 3), np.nan), RAISED]), flash_intensity=np.full(F, 2e6))
    cfg = FitConfig(flash_rounds=1, flash_highlight_deg=20.0)
    prob = _FitProblem(m, vs, cfg, "cpu")
    usable = _usable_flashes(prob)
    assert list(usable) == [0, 1, 2, 3, 4]
    fp = _FlashPairs(prob, usable)
    with torch.no_grad():
        fp.log_gain.copy_(torch.tensor([0.1, -0.2, 0.3, 0.0, 0.5], dtype=torch.float64))
    g = fp.gains()
    assert math.exp(np.log(g).mean()) == pytest.approx(1.0, rel=1e-12)
    assert np.allclose(fp.intensities().detach().numpy(), 2e6 * g[fp.pf])
    with torch.no_grad():
        pos = fp.positions(*prob.poses()).numpy()
        Rn, tn = (a.numpy() for a in prob.poses())
    assert np.allclose(pos[:4], camera_centers(Rn, tn), atol=1e-9)
    sm = _sub_mesh(prob)
    weight, uv = _flash_weights(prob, sm, fp, None)
    assert weight.shape == (len(fp.pv), len(sm.sample)) and weight.any()
    # no weighted sample lies in its pair's highlight (normal within 20° of the half vector)
    X = prob.numpy_geometry()[0]
    nrm = vertex_normals(X, m.triangles, dtype=np.float64)[sm.sample]
    cen = camera_centers(Rn, tn)
    for p in range(0, len(fp.pv), 3):
        v, f = fp.pv[p], fp.pf[p]
        for j in np.nonzero(weight[p])[0][::7]:
            x = X[sm.sample[j]]
            hv = (cen[v] - x) / np.linalg.norm(cen[v] - x) + (pos[f] - x) / np.linalg.norm(pos[f] - x)
            assert hv @ nrm[j] / np.linalg.norm(hv) <= math.cos(math.radians(20.0)) + 1e-12
            assert nrm[j] @ (pos[f] - x) / np.linalg.norm(pos[f] - x) > cfg.flash_min_cos
    # a saturated image removes every sample of its pair
    sat = np.zeros((len(fp.pv), H, W), bool)
    sat[0] = True
    w2, _ = _flash_weights(prob, sm, fp, sat)
    assert not w2[0].any() and np.array_equal(w2[1:], weight[1:])

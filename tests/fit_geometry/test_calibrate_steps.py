"""The named steps of calibrate_rig, each against an independent computation (issue 20)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit.calibrate import (
    CalibrationConfig, LMOptions, _gauge_free_cov, _initial_state, _levenberg_marquardt, _place_flashes, _Problem,
    _reframe, _residuals, _rig_target, _scale_anchor, _setup, _uncertainty, expected_face_size, rodrigues,
    simulate_landmarks, table_distance_ratio)
from reflectmm_cli.geometry_fit.model import ShapeModel
from reflectmm_cli.rig import DEFAULT_VIEWS, load_rig

VIEWS = list(DEFAULT_VIEWS)[:5]


@pytest.fixture(scope="module")
def model():
    from reflectmm_cli.geometry.procedural import procedural_face_model

    return ShapeModel.from_face_model(procedural_face_model(2000))


@pytest.fixture(scope="module")
def small(model):
    rig = load_rig()
    sim = simulate_landmarks(model, rig, VIEWS, 3, seed=5, noise_px=0.5)
    return rig, sim["landmarks"]


def _problem(model, rig, lm, **cfg):
    config = CalibrationConfig(max_iters=8, **cfg)
    setup = _setup(model, lm, VIEWS, (640, 480), rig, config, None)
    prob = _Problem(model, setup.lm, setup.R0, setup.c0, setup.f0, setup.pp, config, setup.Ks, setup.Ke)
    return config, setup, prob


def _dense(prob, eq):
    """The full (Pc + N·n_id)² Gauss–Newton matrix assembled from the Schur blocks (cameras first)."""
    Hcc, _, Hic, Hii, _ = eq
    N, n, P = prob.N, prob.n_id, prob.Pc
    H = np.zeros((P + N * n, P + N * n))
    H[:P, :P] = Hcc
    for i in range(N):
        a = P + i * n
        H[a:a + n, a:a + n] = Hii[i]
        H[a:a + n, :P] = Hic[i]
        H[:P, a:a + n] = Hic[i].T
    return H


def test_setup_refuses_bad_shapes_and_unseen_cameras(model, small):
    rig, lm = small
    with pytest.raises(ReflectmmError, match="landmarks must be"):
        _setup(model, lm[:, :3], VIEWS, (640, 480), rig, CalibrationConfig(), None)
    blind = lm.copy()
    blind[:, 2] = np.nan  # one camera no identity annotates: kept (calibrate_rig carries the nominal pose to it)
    assert _setup(model, blind, VIEWS, (640, 480), rig, CalibrationConfig(), None).names == VIEWS
    blind[:, :3] = np.nan  # but only two cameras with landmarks cannot carry the table
    with pytest.raises(ReflectmmError, match=f"{VIEWS[0]}, {VIEWS[1]}, {VIEWS[2]} and only 2 camera"):
        _setup(model, blind, VIEWS, (640, 480), rig, CalibrationConfig(), None)


def test_rig_target_is_the_point_every_axis_passes_through():
    rng = np.random.default_rng(0)
    p = np.array([10.0, -20.0, 5.0])
    c0 = rng.normal(size=(4, 3)) * 500
    R0 = np.zeros((4, 3, 3))
    for k in range(4):  # camera k looks from c0[k] towards p (third row of R = the optical axis)
        z = (p - c0[k]) / np.linalg.norm(p - c0[k])
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R0[k] = np.stack([x, np.cross(z, x), z])
    assert np.allclose(_rig_target(R0, c0), p, atol=1e-9)
    assert np.array_equal(_rig_target(R0[:1], c0[:1]), np.zeros(3))


def test_lm_step_matches_the_dense_damped_solve(model, small):
    rig, lm = small
    _, setup, prob = _problem(model, rig, lm, focal="per-camera")
    st = _initial_state(prob, setup.R0, setup.c0)
    eq = prob.normal_equations(st, 2.0)
    lam = 0.05
    dc, di = prob.solve_step(eq, lam)
    H = _dense(prob, eq)
    _, gc, _, _, gi = eq
    P = prob.Pc
    D = H + lam * np.diag(np.diag(H)) + 1e-9 * np.eye(len(H))
    ref = np.linalg.solve(D, np.concatenate([gc, gi.reshape(-1)]))
    assert np.allclose(dc, ref[:P], rtol=1e-6, atol=1e-9)
    assert np.allclose(di.reshape(-1), ref[P:], rtol=1e-6, atol=1e-9)


def test_levenberg_marquardt_decreases_the_cost_and_leaves_its_start(model, small):
    rig, lm = small
    cfg, setup, prob = _problem(model, rig, lm, focal="fixed")
    st0 = _initial_state(prob, setup.R0, setup.c0)
    before = st0.copy()
    opts = LMOptions.from_config(cfg)
    out = _levenberg_marquardt(prob, st0, opts)
    assert np.array_equal(st0.c, before.c) and np.array_equal(st0.z, before.z)
    c = out.history[-1]["scale"]
    assert prob.cost(out.state, c) < 0.1 * prob.cost(st0, c)
    costs = [h["cost"] for h in out.history]
    scales = [h["scale"] for h in out.history]
    assert all(s1 <= s0 for s0, s1 in zip(scales, scales[1:]))  # the robust scale only anneals downwards
    assert scales[-1] >= opts.loss_scale
    assert len(costs) == opts.max_iters or out.converged


def _fused_scale(model, setup, st, table_ratio, sigma):
    """The scale anchor by its closed form: the faces' size against the model's expected size (Monte-Carlo σ / √N),
    fused in log scale by inverse variances with the table's ratio of relative σ ``sigma`` (0: faces only)."""
    Ks = setup.Ks
    L = np.stack([model.vertices(st.z[i, :Ks] * model.shape_sigma[:Ks], np.zeros(model.n_exp))[model.landmarks]
                  for i in range(setup.N)])
    size = np.sqrt(((L - L.mean(1, keepdims=True)) ** 2).sum(-1).mean(-1)).mean()
    target, spread = expected_face_size(model, Ks, return_std=True)
    if not sigma:
        return target / size
    wf, wn = (setup.N / (spread / target) ** 2), 1 / sigma ** 2
    return math.exp((wf * math.log(target / size) + wn * math.log(table_ratio)) / (wf + wn))


def test_scale_anchor_closed_forms(model, small):
    rig, lm = small
    cfg, setup, prob = _problem(model, rig, lm, distance_sigma_rel=0.0)
    st = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), LMOptions.from_config(cfg)).state
    anchor, note = _scale_anchor(model, prob, st, setup, cfg)
    assert anchor == pytest.approx(_fused_scale(model, setup, st, None, 0.0), rel=1e-9) and note is not None
    # fused with the nominal distances: the inverse-variance weighted mean of the two log scales
    fused, _ = _scale_anchor(model, prob, st, setup, CalibrationConfig(distance_sigma_rel=0.05))
    dist_ratio = np.median(np.linalg.norm(setup.c0, axis=1) / np.linalg.norm(st.c - st.th.mean(0), axis=1))
    assert fused == pytest.approx(_fused_scale(model, setup, st, dist_ratio, 0.05), rel=1e-9)
    assert _scale_anchor(model, prob, st, setup, CalibrationConfig(anchor_scale=False)) == (1.0, None)


def test_table_distance_ratio_ignores_turned_and_guessed_entries():
    rng = np.random.default_rng(3)
    a = np.linspace(-0.5, 0.5, 7)                                     # near-frontal cameras, head at the origin
    table = np.stack([1300 * np.sin(a), rng.normal(0, 60, 7), 1300 * np.cos(a)], 1)
    head = np.array([12.0, -5.0, 30.0])
    fit = table / 1.08 + head                                          # the fit's scene, 8 % smaller
    seen = np.ones(7, bool)
    assert table_distance_ratio(table, fit, head, seen)[0] == pytest.approx(1.08, rel=1e-12)
    # the table's entries turned about the head by 3°: the spread of these cameras changes, their distances do not
    turned = np.stack([rodrigues(rng.normal(size=3) * math.radians(3.0) / math.sqrt(3)) @ c for c in table])
    spread = lambda c: np.linalg.norm(c - c.mean(0))
    assert abs(spread(turned) / spread(table) - 1) > 0.02
    assert table_distance_ratio(turned, fit, head, seen)[0] == pytest.approx(1.08, rel=1e-12)
    # two guessed entries 300 mm off, and a camera no landmark places (left at a wrong table place): the median holds
    guessed = table.copy()
    guessed[[1, 5]] += np.array([[0.0, 300.0, 0.0], [250.0, 0.0, -200.0]])
    blind = seen.copy()
    blind[3] = False
    fit_b = fit.copy()
    fit_b[3] = guessed[3] * 0.5
    r, used = table_distance_ratio(guessed, fit_b, head, blind)
    assert np.array_equal(used, blind)
    ok = np.delete(np.arange(7), [1, 3, 5])
    assert np.median(np.r_[np.full(ok.size, 1.08), np.linalg.norm(guessed[[1, 5]], axis=1)
                           / np.linalg.norm(fit[[1, 5]] - head, axis=1)]) == pytest.approx(r, rel=1e-12)
    assert r == pytest.approx(1.08, rel=1e-12)


def test_scale_anchor_uses_the_table_distances_of_the_cameras_landmarks_place(model):
    from reflectmm_cli.rig import RAISED_CAMERAS

    rig = load_rig()
    views = list(DEFAULT_VIEWS) + list(RAISED_CAMERAS)
    lm = simulate_landmarks(model, rig, views, 3, seed=7, noise_px=0.5)["landmarks"]
    blind = [views.index("09_0"), views.index("20_0")]
    lm[:, blind] = np.nan
    cfg = CalibrationConfig(max_iters=8, distance_sigma_rel=0.0)
    setup = _setup(model, lm, views, (640, 480), rig, cfg, None)
    prob = _Problem(model, setup.lm, setup.R0, setup.c0, setup.f0, setup.pp, cfg, setup.Ks, setup.Ke)
    st = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), LMOptions.from_config(cfg)).state
    seen = np.ones(len(views), bool)
    seen[blind] = False
    ratios = np.linalg.norm(setup.c0, axis=1) / np.linalg.norm(st.c - st.th.mean(0), axis=1)
    ref = _fused_scale(model, setup, st, np.median(ratios[seen]), 0.01)
    anchor, note = _scale_anchor(model, prob, st, setup, CalibrationConfig(distance_sigma_rel=0.01))
    assert anchor == pytest.approx(ref, rel=1e-9)
    assert "09_0" not in note and "20_0" not in note and "13_0, 14_0" in note
    # the blind cameras, left at their table places, would pull the median: they are not in it
    assert abs(math.log(np.median(ratios) / np.median(ratios[seen]))) > 1e-4


def test_setup_refuses_a_table_camera_at_the_head(model, small, tmp_path):
    from reflectmm_cli.rig import save_rig

    rig, lm = small
    import dataclasses

    cams = [dataclasses.replace(c, position=np.zeros(3), look_at=np.array([0.0, 0.0, -100.0]))
            if c.name == VIEWS[2] else c for c in rig.cameras]
    path = tmp_path / "rig.toml"
    save_rig(type(rig)(cams, rig.flashes, None), path, "a camera at the head")
    bad = load_rig(path)
    with pytest.raises(ReflectmmError, match=f"rig.toml: nominal rig camera {VIEWS[2]} sits at the origin"):
        _setup(model, lm, VIEWS, (640, 480), bad, CalibrationConfig(), None)


def test_reframe_centres_the_heads_and_keeps_every_projection(model, small):
    rig, lm = small
    cfg, setup, prob = _problem(model, rig, lm)
    st = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), LMOptions.from_config(cfg)).state
    rng = np.random.default_rng(2)
    st.Rh = rodrigues(rng.normal(size=(setup.N, 3)) * 0.1) @ st.Rh  # heads turned: the frame must follow
    uv0, _ = prob.project(st)
    _reframe(st)
    uv1, _ = prob.project(st)
    assert np.allclose(uv0, uv1, atol=1e-8)
    assert np.allclose(st.th.mean(0), 0.0, atol=1e-9)
    U, _, Vt = np.linalg.svd(st.Rh.mean(0))
    assert np.allclose(U @ Vt, np.eye(3), atol=1e-9)  # nearest rotation to the mean head orientation


def test_uncertainty_is_the_camera_block_of_the_dense_inverse(model, small):
    rig, lm = small
    cfg, setup, prob = _problem(model, rig, lm, focal="shared")
    opts = LMOptions.from_config(cfg)
    st = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), opts).state
    res = _residuals(prob, st, setup.lm, cfg)
    unc = _uncertainty(prob, st, res, opts.loss_scale)
    H = _dense(prob, prob.normal_equations(st, opts.loss_scale))
    N, n, P, C = prob.N, prob.n_id, prob.Pc, prob.C
    cov = np.linalg.inv(H)[:P, :P] * unc.s2
    ri = (6 * np.arange(C)[:, None] + np.arange(3)).reshape(-1)
    rot = np.degrees(np.sqrt(np.diag(cov)[ri]).reshape(C, 3).max(1) * prob.ROT_UNIT)
    assert np.allclose(unc.rotation_deg, rot, rtol=1e-5)
    assert np.allclose(unc.focal_px, prob.focal(st) * math.sqrt(cov[6 * C, 6 * C]) * prob.F_UNIT, rtol=1e-5)
    # noise scale: weighted squared residuals over the degrees of freedom
    inl = res.valid & ~res.outliers
    dof = 2 * inl.sum() - (P + N * n)
    _, wr = prob.rho((res.d / cfg.landmark_sigma_px) ** 2, opts.loss_scale)
    assert unc.s2 == pytest.approx((wr * prob.wl * (res.d / cfg.landmark_sigma_px) ** 2)[inl].sum() / dof)


def test_gauge_free_covariance_has_no_rigid_motion():
    rng = np.random.default_rng(3)
    centers = rng.normal(size=(5, 3)) * 500
    A = rng.normal(size=(15, 15))
    cov = _gauge_free_cov(A @ A.T, centers)
    w = rng.normal(size=3)
    motion = (np.cross(w, centers) + rng.normal(size=3)).reshape(-1)  # an infinitesimal rigid motion
    assert np.allclose(cov @ motion, 0.0, atol=1e-8 * np.abs(cov).max() * np.abs(motion).max())


def test_flashes_at_the_nominal_rig_stay_at_their_nominal_positions(model, small):
    rig, lm = small
    cfg, setup, prob = _problem(model, rig, lm)
    st = _initial_state(prob, setup.R0, setup.c0)
    flashes, notes = _place_flashes(rig, None, setup, st, np.ones((prob.C, 3)))
    ref = np.array([rig.flash(f).position for f in flashes.ids])
    assert np.allclose(flashes.pos, ref, atol=1e-9)
    attached = [i for i, c in enumerate(flashes.camera) if c in VIEWS]
    assert attached and np.allclose(flashes.sigma_mm[attached], math.sqrt(3.0))
    assert all(np.isnan(flashes.sigma_mm[i]) for i in range(len(flashes.ids)) if i not in attached)
    assert len(notes) >= len(flashes.ids) - len(attached)
    # moving one camera moves its flash rigidly with it
    k = VIEWS.index(flashes.camera[attached[0]])
    st.c[k] += [5.0, -3.0, 2.0]
    moved, _ = _place_flashes(rig, None, setup, st, np.ones((prob.C, 3)))
    assert np.allclose(moved.pos[attached[0]], ref[attached[0]] + [5.0, -3.0, 2.0], atol=1e-9)


def test_gauss_newton_matrix_matches_the_finite_difference_hessian_near_a_zero_residual(model):
    # noise-free landmarks, least squares, the prior made negligible: at the optimum the residuals vanish and the
    # Gauss–Newton matrix the uncertainty inverts is the Hessian of the cost (central differences of its gradient)
    rig = load_rig()
    lm = simulate_landmarks(model, rig, VIEWS, 2, seed=8, noise_px=0.0)["landmarks"]
    cfg, setup, prob = _problem(model, rig, lm, loss="l2", focal="fixed", camera_sigma_mm=1e4,
                                camera_sigma_deg=1e3)
    cfg.max_iters = 40
    st = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), LMOptions.from_config(cfg)).state
    H = _dense(prob, prob.normal_equations(st, 1.0))
    rng = np.random.default_rng(4)
    eps = 1e-4
    for _ in range(4):
        v = rng.normal(size=len(H))
        vc, vi = v[:prob.Pc], v[prob.Pc:].reshape(prob.N, prob.n_id)

        def grad(s):
            _, gc, _, _, gi = prob.normal_equations(prob.apply(st, s * vc, s * vi), 1.0)
            return -np.concatenate([gc, gi.reshape(-1)])

        fd = (grad(eps) - grad(-eps)) / (2 * eps)
        assert np.abs(fd - H @ v).max() < 1e-4 * np.abs(H @ v).max()  # measured: < 1e-5

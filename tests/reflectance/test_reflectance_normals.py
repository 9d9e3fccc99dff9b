"""Photometric normal refinement (issue 13, cause 4): analytic derivatives against finite differences, recovery of
a known normal perturbation from exact-model observations, numerical stability."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.ndimage import gaussian_filter

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.reflectance import fit_maps, simulate_observations
from reflectmm_cli.reflectance.design import design_rows, design_rows_grad
from reflectmm_cli.reflectance.fit import NORMAL_STEPS
from reflectmm_cli.reflectance.normals import MAX_STEP, correction_angle_deg, offset_normal, tangent_basis


def _rows(seed, R=64):
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 40, (R, 3))
    n = rng.normal(0, 1, (R, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5  # towards the rig
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ang = rng.uniform(-1.2, 1.2, (2, R))
    flash = np.stack([1300 * np.sin(ang[0]), rng.uniform(-300, 300, R), 1300 * np.cos(ang[0])], 1)
    cam = np.stack([1300 * np.sin(ang[1]), rng.uniform(-100, 100, R), 1300 * np.cos(ang[1])], 1)
    return x, n, flash, cam, np.full(R, 2.5 * 1300.0 ** 2)


@pytest.mark.parametrize("exponents", [(1.0, 8.0, 64.0), (0.5, 3.0, 300.0)])
def test_design_columns_derivative_matches_finite_differences(exponents):
    x, n, flash, cam, I = _rows(1)
    d, s, cos, ndh, dd, ds = design_rows_grad(x, n, flash, cam, I, exponents)
    d0, s0, c0, h0 = design_rows(x, n, flash, cam, I, exponents)  # the columns themselves are the fit's
    np.testing.assert_allclose(d, d0, rtol=1e-12, atol=0)
    np.testing.assert_allclose(s, s0, rtol=1e-12, atol=0)
    ok = (cos > 1e-3) & (ndh > 1e-3)
    assert ok.sum() > 20
    eps = 1e-6
    for k in range(3):  # central differences in each component of n (unnormalised, as the formulas)
        e = np.zeros(3)
        e[k] = eps
        dp, sp, _, _ = design_rows(x, n + e, flash, cam, I, exponents)
        dm, sm, _, _ = design_rows(x, n - e, flash, cam, I, exponents)
        np.testing.assert_allclose(dd[ok, k], ((dp - dm) / (2 * eps))[ok], rtol=1e-5, atol=1e-9 * np.abs(d).max())
        np.testing.assert_allclose(ds[ok, :, k], ((sp - sm) / (2 * eps))[ok], rtol=1e-5,
                                   atol=1e-9 * np.abs(s).max())


def test_tangent_chain_rule_matches_finite_differences():
    x, n, flash, cam, I = _rows(2)
    T = tangent_basis(n)
    np.testing.assert_allclose(np.einsum("nij,nik->njk", T, T), np.broadcast_to(np.eye(2), (len(n), 2, 2)),
                               atol=1e-12)
    np.testing.assert_allclose(np.einsum("ni,nij->nj", n, T), 0.0, atol=1e-12)
    delta = np.random.default_rng(0).normal(0, 0.05, (len(n), 2))
    nn, J = offset_normal(n, T, delta)
    np.testing.assert_allclose(np.linalg.norm(nn, axis=1), 1.0, atol=1e-12)
    p = (1.0, 8.0, 64.0)
    _, _, cos, ndh, dd, ds = design_rows_grad(x, nn, flash, cam, I, p)
    ok = (cos > 1e-3) & (ndh > 1e-3)
    eps = 1e-6
    for q in range(2):
        e = np.zeros(2)
        e[q] = eps
        dp, sp, _, _ = design_rows(x, offset_normal(n, T, delta + e)[0], flash, cam, I, p)
        dm, sm, _, _ = design_rows(x, offset_normal(n, T, delta - e)[0], flash, cam, I, p)
        np.testing.assert_allclose(np.einsum("rj,rj->r", dd, J[:, :, q])[ok], ((dp - dm) / (2 * eps))[ok],
                                   rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(np.einsum("rkj,rj->rk", ds, J[:, :, q])[ok], ((sp - sm) / (2 * eps))[ok],
                                   rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(correction_angle_deg(np.array([[np.tan(np.radians(7.0)), 0.0]])), [7.0])


def _perturbed(S, deg, seed=3):
    """Exact-model observations of the analytic face with every normal turned by a smooth field (median ~deg)."""
    obs, truth = simulate_observations(S, noise=0.02, seed=1, return_truth=True, dtype=np.float32)
    mask = obs["mask"]
    nt = obs["normal"].astype(np.float64)
    rng = np.random.default_rng(seed)
    f = np.stack([gaussian_filter(rng.standard_normal((S, S)), S / 10) for _ in range(2)], -1)
    f /= np.sqrt((f[mask] ** 2).sum(-1).mean())
    npert = offset_normal(nt.reshape(-1, 3), tangent_basis(nt.reshape(-1, 3)),
                          np.tan(np.radians(deg)) * f.reshape(-1, 2))[0].reshape(S, S, 3)
    pert = dict(obs)
    pert["normal"] = npert.astype(np.float32)
    return obs, pert, truth, nt


def _angle(a, b, mask):
    return np.degrees(np.arccos(np.clip(np.einsum("...k,...k->...", a, b), -1, 1)))[mask]


def test_refinement_recovers_a_known_normal_perturbation():
    S = 24
    obs, pert, truth, nt = _perturbed(S, 7.0)
    mask = obs["mask"]
    before = _angle(pert["normal"].astype(np.float64), nt, mask)
    assert 5.0 < np.median(before) < 9.0
    m0 = fit_maps(pert, threads=1)
    m3 = fit_maps(pert, refine_normals=3, threads=1)
    after = _angle(np.moveaxis(m3.normal, 0, -1), nt, mask & ~m3.flagged)
    assert np.median(after) < 0.25 * np.median(before)
    assert np.percentile(after, 90) < 0.5 * np.percentile(before, 90)
    assert np.all(np.isfinite(m3.normal)) and np.allclose(np.linalg.norm(m3.normal[:, mask], axis=0), 1.0)
    np.testing.assert_allclose(m3.normal_correction[mask], _angle(np.moveaxis(m3.normal, 0, -1),
                                                                  pert["normal"].astype(np.float64), mask),
                               atol=0.02)  # (arccos of float32-rounded unit vectors)
    ok = m0.observable() & m3.observable()
    sw_true = truth["weights"].sum(0)[ok]

    def sw_err(m):
        return np.mean(np.abs(m.weights.sum(0)[ok] - sw_true))

    def alb_err(m):
        return np.median(np.abs(m.albedo[:, ok] - truth["albedo"][:, ok]) / truth["albedo"][:, ok])

    assert sw_err(m3) < 0.6 * sw_err(m0)
    assert abs(np.median(m3.weights.sum(0)[ok] / sw_true) - 1) < abs(np.median(m0.weights.sum(0)[ok] / sw_true) - 1)
    assert alb_err(m3) < 0.5 * alb_err(m0)
    # the residual explains the data better with the refined normals
    assert m3.stats["residual_rms_median"] < m0.stats["residual_rms_median"]


def test_refinement_keeps_true_normals():
    S = 20
    obs, _, truth, nt = _perturbed(S, 0.0)
    m0 = fit_maps(obs, threads=1)
    m2 = fit_maps(obs, refine_normals=2, threads=1)
    mask = obs["mask"] & ~m2.flagged
    assert np.percentile(_angle(np.moveaxis(m2.normal, 0, -1), nt, mask), 90) < 1.0
    ok = m0.observable()
    e0 = np.median(np.abs(m0.albedo[:, ok] - truth["albedo"][:, ok]) / truth["albedo"][:, ok])
    e2 = np.median(np.abs(m2.albedo[:, ok] - truth["albedo"][:, ok]) / truth["albedo"][:, ok])
    assert e2 < 1.2 * e0 + 1e-3


def test_prior_strength_sets_how_far_normals_move():
    obs, pert, _, nt = _perturbed(16, 7.0)
    tight = fit_maps(pert, refine_normals=2, normal_sigma=0.05, threads=1)
    loose = fit_maps(pert, refine_normals=2, normal_sigma=20.0, threads=1)
    mask = obs["mask"] & ~loose.flagged
    assert np.median(tight.normal_correction[mask]) < 0.1
    assert np.median(loose.normal_correction[mask]) > 10 * np.median(tight.normal_correction[mask])


def test_refinement_off_leaves_the_artifact_unchanged():
    obs = simulate_observations(8)
    m = fit_maps(obs)
    assert m.normal is None and "normal" not in m.arrays() and "normal_refinement" not in m.stats
    with pytest.raises(ReflectmmError, match="refine_normals"):
        fit_maps(obs, refine_normals=-1)
    with pytest.raises(ReflectmmError, match="normal_sigma"):
        fit_maps(obs, refine_normals=1, normal_sigma=0.0)
    with pytest.raises(ReflectmmError, match="fast solver"):
        fit_maps(obs, refine_normals=1, solver="adam")


_OBS8 = simulate_observations(8, dtype=np.float32)


@settings(max_examples=10, deadline=None)
@given(case=st.sampled_from(["grazing", "unobserved", "dark", "mixed"]), seed=st.integers(0, 2 ** 16),
       sigma=st.sampled_from([0.01, 5.0, 90.0]))
def test_refinement_is_stable_on_degenerate_texels(case, seed, sigma):
    obs = {k: np.array(v, copy=True) for k, v in _OBS8.items()}
    rng = np.random.default_rng(seed)
    mask = obs["mask"]
    pick = mask & (rng.random(mask.shape) < 0.4)
    n = obs["normal"].astype(np.float64)
    if case in ("grazing", "mixed"):  # normals turned to ~89° from the frontal direction
        g = np.stack([rng.normal(size=mask.shape), rng.normal(size=mask.shape), np.full(mask.shape, 0.02)], -1)
        n[pick] = (g / np.linalg.norm(g, axis=-1, keepdims=True))[pick]
        obs["normal"] = n.astype(np.float32)
    if case in ("unobserved", "mixed"):
        obs["observed"][:, pick] = False
    if case in ("dark", "mixed"):
        obs["radiance"][:, pick] = 0
    m = fit_maps(obs, refine_normals=2, normal_sigma=sigma, threads=1)
    for a in (m.albedo, m.weights, m.normal, m.normal_correction, m.residual):
        assert np.all(np.isfinite(a))
    np.testing.assert_allclose(np.linalg.norm(m.normal[:, mask], axis=0), 1.0, atol=1e-9)
    # the prior holds: flagged (unsolved) texels and texels without data keep the geometric normal
    keep = mask & (m.flagged | (m.obs_count == 0))
    assert np.all(m.normal_correction[keep] == 0)
    # damped: no texel moves more than the clipped steps allow, and a tight prior holds every texel
    bound = np.degrees(np.arctan(2 * NORMAL_STEPS * MAX_STEP))
    assert np.all(m.normal_correction[mask] <= bound + 1e-9)
    if sigma < 0.1:
        assert np.all(m.normal_correction[mask] < 5 * sigma)

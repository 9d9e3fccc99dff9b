"""Design columns and conditioning against independent per-observation evaluations."""
import math

import numpy as np
import pytest
from hypothesis import given, strategies as st

from reflectmm_cli.reflectance import conditioning, design_columns, simulate_observations
from reflectmm_cli.reflectance.design import gram_conditioning, mirror_index
from reflectmm_cli.shading import shade_directional


def _scalar_shading(x, n, cam, flash, I, p):
    """docs/design.md §2 written out with scalar math: (diffuse column, lobe columns)."""
    def sub(a, b):
        return [a[i] - b[i] for i in range(3)]

    def unit(a):
        r = math.sqrt(sum(t * t for t in a))
        return [t / r for t in a]

    def dot(a, b):
        return sum(a[i] * b[i] for i in range(3))

    n = unit(n)
    lv = sub(flash, x)
    d2 = dot(lv, lv)
    l = unit(lv)
    v = unit(sub(cam, x))
    if dot(n, l) <= 0 or dot(n, v) <= 0:
        return 0.0, [0.0] * len(p)
    h = unit([l[i] + v[i] for i in range(3)])
    E = I / d2
    diff = E * dot(n, l) / math.pi
    lobes = [E * (q + 2) / (4 * math.pi * (2 - 2 ** (-q / 2))) * max(dot(n, h), 0.0) ** q for q in p]
    return diff, lobes


def test_design_columns_match_scalar_formula_and_shading_core():
    rng = np.random.default_rng(3)
    N, V, F = 7, 3, 4
    x = rng.normal(size=(N, 3)) * 40
    n = rng.normal(size=(N, 3))
    cams = rng.normal(size=(V, 3)) * 800
    fl = rng.normal(size=(F, 3)) * 800
    I = rng.uniform(1e5, 3e6, size=F)
    pv = np.repeat(np.arange(V), F)
    pf = np.tile(np.arange(F), V)
    p = [1.0, 8.0, 64.0]
    des = design_columns(x, n, cams, fl, I, pv, pf, p)
    n_lit = 0
    for i in range(N):
        for j in range(V * F):
            dref, lref = _scalar_shading(x[i], n[i], cams[pv[j]], fl[pf[j]], I[pf[j]], p)
            assert des.diffuse[i, j] == pytest.approx(dref, rel=1e-12, abs=1e-300)
            np.testing.assert_allclose(des.lobes[i, j], lref, rtol=1e-12, atol=1e-300)
            n_lit += dref > 0
    assert 0 < n_lit < N * V * F  # both lit and back-facing cases were exercised
    # the linear model equals the shading core for random reflectance
    c = rng.uniform(size=(N, 3))
    w = rng.uniform(size=(N, 3))
    pred = des.diffuse[..., None] * c[:, None] + np.einsum("npk,nk->np", des.lobes, w)[..., None]
    ld = fl[pf][None] - x[:, None]
    E = I[pf][None] / np.sum(ld * ld, -1)
    ref = shade_directional(np.repeat(c[:, None], V * F, 1), np.repeat(w[:, None], V * F, 1), np.array(p),
                            np.repeat(n[:, None], V * F, 1), ld, cams[pv][None] - x[:, None],
                            np.repeat(E[..., None], 3, -1))
    np.testing.assert_allclose(pred, ref, rtol=1e-12, atol=1e-15)


def test_unobserved_pairs_are_zero():
    obs = simulate_observations(8)
    S = 8
    P = obs["observed"].shape[0]
    observed = obs["observed"].reshape(P, -1).T
    des = design_columns(obs["position"].reshape(-1, 3), obs["normal"].reshape(-1, 3), obs["cam_centers"],
                         obs["flash_pos"], obs["flash_intensity"], obs["pair_view"], obs["pair_flash"], [1, 8, 64],
                         observed)
    assert np.all(des.diffuse[~observed] == 0) and np.all(des.lobes[~observed] == 0)
    assert np.all(des.valid == (observed & (des.cos_l > 0)))
    assert des.valid.reshape(S * S, P).any()


def test_gram_conditioning_is_reciprocal_condition_number_of_normalised_gram():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 30, 4)) * rng.uniform(0.01, 100, size=(20, 1, 4))
    G = np.einsum("npa,npb->nab", A, A)
    rc = gram_conditioning(G)
    for i in range(20):
        dinv = 1 / np.sqrt(np.diag(G[i]))
        assert rc[i] == pytest.approx(1 / np.linalg.cond(G[i] * np.outer(dinv, dinv)), rel=1e-8)
    # orthogonal columns -> 1; a zero column -> 0; duplicated column -> ~0
    assert gram_conditioning(np.eye(4)[None])[0] == pytest.approx(1.0)
    Z = np.diag([1.0, 2.0, 0.0, 1.0])[None]
    assert gram_conditioning(Z)[0] == 0.0
    B = A[:1].copy()
    B[..., 1] = 3 * B[..., 0]
    assert gram_conditioning(np.einsum("npa,npb->nab", B, B))[0] < 1e-12


def test_conditioning_maps_observability_and_mirror():
    obs = simulate_observations(16)
    c = conditioning(obs["position"], obs["normal"], obs["cam_centers"], obs["flash_pos"], obs["flash_intensity"],
                     obs["pair_view"], obs["pair_flash"], obs["observed"], (1, 8, 64), mask=obs["mask"])
    m = obs["mask"]
    # observability by brute force over pairs: max (n·h)^p over observed pairs
    r, col = np.argwhere(m)[len(np.argwhere(m)) // 3]
    n = obs["normal"][r, col].astype(float)
    x = obs["position"][r, col].astype(float)
    best = np.zeros(3)
    for j in range(obs["pair_view"].size):
        if not obs["observed"][j, r, col]:
            continue
        l = obs["flash_pos"][obs["pair_flash"][j]] - x
        v = obs["cam_centers"][obs["pair_view"][j]] - x
        l, v = l / np.linalg.norm(l), v / np.linalg.norm(v)
        h = (l + v) / np.linalg.norm(l + v)
        best = np.maximum(best, max(n @ h, 0) ** np.array([1, 8, 64]))
    np.testing.assert_allclose(c.observability[:, r, col], best, rtol=1e-5)
    assert np.all(c.conditioning[~m] == 0) and np.all(c.conditioning[m] > 0)
    assert np.array_equal(c.obs_count, obs["observed"].sum(0))
    # the simulated rig reproduces docs/design.md §3: many texels never see the p=64 lobe near its peak
    frac = np.mean(c.observability[2][m] < 0.1)
    assert 0.2 < frac < 0.8
    # geometry is mirror symmetric, so the conditioning map is too
    np.testing.assert_allclose(c.conditioning, c.conditioning[:, ::-1], rtol=1e-4, atol=1e-9)


def test_mirror_index():
    idx = mirror_index(4).reshape(4, 4)
    assert idx[1, 0] == 7 and idx[2, 3] == 8
    a = np.arange(16).reshape(4, 4)
    assert np.array_equal(a.reshape(-1)[mirror_index(4)].reshape(4, 4), a[:, ::-1])


@given(p=st.floats(min_value=1e-3, max_value=1e4), seed=st.integers(0, 2 ** 16))
def test_design_finite_for_extreme_exponents(p, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(5, 3))
    n = rng.normal(size=(5, 3))
    des = design_columns(x, n, rng.normal(size=(2, 3)) * 500, rng.normal(size=(2, 3)) * 500, np.ones(2) * 1e6,
                         [0, 1], [1, 0], [p, 1.0])
    assert np.all(np.isfinite(des.lobes)) and np.all(des.lobes >= 0)
    assert np.all(np.isfinite(des.diffuse)) and np.all(des.diffuse >= 0)


def test_simulated_geometry_is_mirror_symmetric_and_rig_is_multipie_like():
    obs = simulate_observations(12)
    pos, nrm = obs["position"], obs["normal"]
    np.testing.assert_allclose(pos[:, ::-1, 0], -pos[:, :, 0], atol=1e-4)
    np.testing.assert_allclose(pos[:, ::-1, 1:], pos[:, :, 1:], atol=1e-4)
    np.testing.assert_allclose(nrm[:, ::-1, 0], -nrm[:, :, 0], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1, atol=1e-6)
    assert pos[0, 6, 1] > pos[-1, 6, 1]  # row 0 is the forehead
    assert obs["pair_view"].size == 99 and list(obs["flash_ids"][-2:]) == ["14", "18"]
    d = np.linalg.norm(obs["cam_centers"], axis=1)
    np.testing.assert_allclose(d, 1300.0)
    az = np.degrees(np.arctan2(obs["cam_centers"][:, 0], obs["cam_centers"][:, 2]))
    np.testing.assert_allclose(np.diff(az), 15.0)
    assert np.all(obs["flash_pos"][-2:, 1] > 100)  # the two raised flashes


def test_design_rows_equal_design_columns():
    from reflectmm_cli.reflectance.design import design_rows

    rng = np.random.default_rng(11)
    N, V, F = 9, 3, 4
    x = rng.normal(size=(N, 3)) * 60
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cams = rng.normal(size=(V, 3)) * 900
    fl = rng.normal(size=(F, 3)) * 900
    I = rng.uniform(1e5, 3e6, size=F)
    pv, pf = np.repeat(np.arange(V), F), np.tile(np.arange(F), V)
    des = design_columns(x, n, cams, fl, I, pv, pf, [1, 8, 64])
    t, j = np.meshgrid(np.arange(N), np.arange(V * F), indexing="ij")
    t, j = t.ravel(), j.ravel()
    d, s, c, h = design_rows(x[t], n[t], fl[pf[j]], cams[pv[j]], I[pf[j]], [1, 8, 64])
    np.testing.assert_allclose(d, des.diffuse.ravel(), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(s, des.lobes.reshape(-1, 3), rtol=1e-11, atol=1e-300)
    np.testing.assert_allclose(c, des.cos_l.ravel(), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(h, des.ndh.ravel(), rtol=1e-12, atol=1e-300)

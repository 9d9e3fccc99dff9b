"""The named steps of fit_maps on small simulated observations: settings, the observations' problem, the texel
map, mirror pooling, flagging, the fast solver's passes, the normal refinement, Adam, filling and statistics."""
import numpy as np
import pytest

from reflectmm_cli.reflectance import fit as F
from reflectmm_cli.reflectance import fit_maps, simulate_observations
from reflectmm_cli.reflectance.design import mirror_index

S = 12


@pytest.fixture(scope="module")
def sim():
    return simulate_observations(S, return_truth=True)


def _problem(obs, threads=1, pair_mask=None, **settings):
    cfg = F._settings(None, settings)
    p = F._check_exponents(cfg.exponents)
    prob, _ = F._observations_problem(obs, p, pair_mask, None, 4096, threads)
    return F._texel_problem(prob, S, cfg, None, threads)


def test_settings_override_the_config_by_name_and_are_checked():
    cfg = F._settings(None, {"loss": "l2", "symmetry": 0.5})
    assert cfg == F._settings(F._settings(None, {"loss": "l2"}), {"symmetry": 0.5})
    assert F._settings(None, {}) == F.FitMapsConfig()
    with pytest.raises(TypeError, match="unknown setting"):
        F._settings(None, {"symetry": 0.5})
    with pytest.raises(F.ReflectmmError, match="symmetry must be in"):
        F._settings(None, {"symmetry": 2.0})


def test_config_is_nested_by_concern_with_one_flat_name_per_setting():
    from reflectmm_cli.reflectance import (AdamConfig, FitMapsConfig, NormalRefinementConfig, PriorConfig,
                                           SolverConfig, SymmetryConfig)

    cfg = FitMapsConfig.from_flat(solver="adam", loss="l2", symmetry=0.5, symmetry_mode="all", prior=0.0,
                                  prior_tail=3.0, prior_sigma=2.0, steps=7, device="cuda", refine_normals=0,
                                  normal_sigma=2.5, exponents=(1.0, 4.0), threads=2)
    assert cfg == FitMapsConfig(exponents=(1.0, 4.0), solver=SolverConfig(kind="adam", loss="l2", threads=2),
                                symmetry=SymmetryConfig(weight=0.5, mode="all"),
                                prior=PriorConfig(strength=0.0, tail=3.0, sigma=2.0),
                                adam=AdamConfig(steps=7, device="cuda"),
                                normals=NormalRefinementConfig(sigma=2.5))
    names = FitMapsConfig.flat_names()
    assert names["solver"] == ("solver", "kind") and names["refine_normals"] == ("normals", "iterations")
    assert names["exponents"] == (None, "exponents") and names["seed"] == ("adam", "seed")
    assert len(names) == 26  # every setting once (exponents and the 25 nested ones)
    flat = cfg.flat()
    assert list(flat) == list(names) and flat["symmetry"] == 0.5 and flat["steps"] == 7 and flat["loss"] == "l2"
    assert FitMapsConfig.from_flat(**flat) == cfg  # the flat view round-trips
    assert cfg.with_flat(symmetry=1.0).symmetry == SymmetryConfig(weight=1.0, mode="all")
    with pytest.raises(TypeError, match="unknown setting 'kind'"):
        FitMapsConfig.from_flat(kind="fast")  # nested field names are not flat names
    with pytest.raises(TypeError, match=r"FitMapsConfig.symmetry must be a SymmetryConfig.*from_flat\(symmetry="):
        FitMapsConfig(symmetry=0.5)
    # checks name the flat setting
    for bad, msg in ((dict(solver="newton"), "solver must be"), (dict(prior_tail_obs=0.0), "prior_tail_obs"),
                     (dict(refine_normals=1, solver="adam"), "needs the fast solver"),
                     (dict(normal_sigma=0.0), "normal_sigma")):
        with pytest.raises(F.ReflectmmError, match=msg):
            FitMapsConfig.from_flat(**bad).check()


def test_stage_params_map_into_the_nested_config():
    from reflectmm_cli.stages import fit_reflectance as stage

    defaults = F.FitMapsConfig().flat()
    for q in stage.PARAMS:
        if q.name in defaults:
            want = defaults[q.name]
            assert q.default == (list(want) if isinstance(want, tuple) else want), q.name
    assert set(stage._SETTINGS) == {q.name for q in stage.PARAMS} - {"flash_intensity"}
    p = {q.name: q.default for q in stage.PARAMS} | {"symmetry_mode": "all", "refine_normals": 2, "steps": 9}
    cfg = F.FitMapsConfig.from_flat(**{k: p[k] for k in stage._SETTINGS})
    assert cfg.symmetry.mode == "all" and cfg.normals.iterations == 2 and cfg.adam.steps == 9


def test_observations_problem_keeps_only_the_pairs_asked_for(sim):
    obs, _ = sim
    P = obs["pair_view"].shape[0]
    p = np.asarray(F.FitMapsConfig().exponents)
    full, pm = F._observations_problem(obs, p, None, None, 4096, 1)
    assert pm.all() and pm.shape == (P,)
    half, pm = F._observations_problem(obs, p, np.arange(0, P, 2), None, 4096, 1)
    assert pm.sum() == (P + 1) // 2 and set(np.unique(half.pair)) <= set(range(0, P, 2))
    assert 0 < half.tex.size < full.tex.size
    assert np.array_equal(full.idx, np.flatnonzero(obs["mask"].reshape(-1)))
    with pytest.raises(F.ReflectmmError, match="pair_mask"):
        F._observations_problem(obs, p, [P], None, 4096, 1)


def test_texels_to_map_and_back():
    mask = np.zeros((4, 4), bool)
    mask[1:3, 0:3] = True
    tx = F._Texels(4, np.flatnonzero(mask.reshape(-1)))
    assert np.array_equal(tx.mask, mask)
    v = np.arange(6.0)
    m = tx.to_map(v, fill=-1.0)
    assert m.shape == (4, 4) and m[1, 0] == 0 and m[2, 2] == 5 and m[0, 0] == -1
    vv = np.stack([v, 10 * v], axis=1)  # (n, 2) → (2, S, S)
    mm = tx.to_map(vv)
    assert mm.shape == (2, 4, 4) and mm[1, 2, 2] == 50 and mm[:, ~mask].sum() == 0
    assert np.array_equal(tx.from_map(mm), vv)


def test_mirror_pools_a_texel_with_its_mirror_at_its_weight():
    mir = F._Mirror(symv=np.array([0.5, 1.0, 0.0, 0.0]), mp=np.array([1, 0, 0, 3]),
                    has_m=np.array([True, True, False, True]), sym=1.0)
    a = np.array([1.0, 2.0, 3.0, 4.0])
    assert mir.pool(a).tolist() == [2.0, 3.0, 3.0, 4.0]
    H = np.arange(16.0).reshape(4, 2, 2)
    assert np.array_equal(mir.pool(H)[0], H[0] + 0.5 * H[1])
    # a band of texels 0..1 (closed under mirroring) pools as the whole does
    assert np.array_equal(mir.pool_band(a[:2], 0, 2), mir.pool(a)[:2])
    assert mir.pooled.tolist() == [True, True, False, False]
    obsv = np.array([[0.1], [0.9], [0.5], [0.2]])
    assert mir.pooled_observability(obsv)[:, 0].tolist() == [0.9, 0.9, 0.5, 0.2]
    off = F._Mirror(symv=np.zeros(4), mp=np.zeros(4, int), has_m=np.zeros(4, bool), sym=0.0)
    assert off.pool(a) is a and off.pool_band(a, 0, 4) is a


def test_mirror_weights_by_mode(sim):
    obs, _ = sim
    tp = _problem(obs, symmetry=0.7, symmetry_mode="all")
    prob = tp.prob
    mirror = mirror_index(S)
    expect_has = np.isin(mirror[prob.idx], prob.idx)
    assert np.array_equal(tp.mirror.has_m, expect_has)
    assert np.array_equal(prob.idx[tp.mirror.mp[expect_has]], mirror[prob.idx[expect_has]])
    assert np.all(tp.mirror.symv[expect_has] == 0.7) and np.all(tp.mirror.symv[~expect_has] == 0)
    cfg = F._settings(None, {"symmetry_mode": "ill-posed"})
    ill = F._mirror(prob, S, cfg, 1 + prob.K, 1)  # well-posed data everywhere: no pooling
    assert ill.symv.max() == 0 and ill.info == {}
    adaptive = F._mirror(prob, S, F._settings(None, {}), 1 + prob.K, 1)
    assert 0 <= adaptive.symv.min() and adaptive.symv.max() <= 1 and "mirror_trust_median" in adaptive.info
    # a symmetric face: the mirror deserves most of its weight
    assert adaptive.info["mirror_trust_median"] > 0.5
    adam = F._mirror(prob, S, F._settings(None, {"solver": "adam", "symmetry": 0.4}), 1 + prob.K, 1)
    assert np.all(adam.symv[expect_has] == 0.4)  # Adam flips whole maps


def test_texel_problem_flags_texels_without_enough_pooled_data(sim):
    obs, _ = sim
    obs = dict(obs)
    hole = np.zeros((S, S), bool)
    hole[5:7, 1:3] = True  # a hole on one side only: the mirror's data fill it when pooling
    obs["observed"] = obs["observed"] & ~hole[None]
    alone = _problem(obs, symmetry=0.0)
    flagged = alone.texels.to_map(alone.flag.astype(float)) > 0
    assert np.array_equal(flagged, hole & obs["mask"])
    assert np.array_equal(alone.solve, ~alone.flag) and alone.min_obs == 1 + alone.prob.K
    assert alone.prior_sigma == max(S / 16.0, 1.0)
    assert np.allclose(alone.delta, 1e-3 * alone.prob.rms)
    pooled = _problem(obs, symmetry=1.0, min_obs=2, prior_sigma=3.0)
    assert not pooled.flag.any() and pooled.min_obs == 2 and pooled.prior_sigma == 3.0


def test_setup_stats_describe_settings_and_problem(sim):
    obs, _ = sim
    tp = _problem(obs, symmetry=0.0, loss="l2")
    st = F._setup_stats(tp, tp.cfg, n_pairs_used=7)
    assert st["loss"] == "l2" and st["symmetry"] == 0.0 and st["n_pooled"] == 0 and st["n_pairs_used"] == 7
    assert st["n_texels"] == int(obs["mask"].sum()) and st["n_flagged"] == 0 and st["min_obs"] == 4
    ad = _problem(obs, solver="adam", loss="l2", symmetry_mode="ill-posed")
    st = F._setup_stats(ad, ad.cfg, n_pairs_used=7)
    assert st["loss"] == "l1" and st["symmetry_mode"] == "all"  # Adam's own loss and flips


def test_first_pass_solves_exact_data_and_the_prior_smooths_it(sim):
    obs, truth = sim
    tp = _problem(obs, symmetry=0.0)
    x, Hp, gp = F._first_pass(tp, tp.prob.bands(S))
    want = np.concatenate([truth["albedo"], truth["weights"]]).reshape(6, -1).T[tp.prob.idx]
    assert np.median(np.abs(x - want) / want) < 1e-2  # noise-free data: least squares is the truth
    H, g = tp.prob.normal_equations(None, "l1", tp.delta)[:2]  # no pooling: the ⟨l,n⟩-weighted system
    assert np.allclose(Hp, H) and np.allclose(gp, g)
    pooled = _problem(obs, symmetry=1.0, symmetry_mode="all")
    Hq = F._first_pass(pooled, pooled.prob.bands(S))[1]
    assert np.allclose(Hq, pooled.mirror.pool(H))
    x0m, x0, glob = F._neighbourhood_prior(tp, x)
    assert x0m.shape == (6, S, S) and np.array_equal(tp.texels.from_map(x0m), x0)
    assert np.allclose(glob[:3], np.median(x[:, :3], axis=0))  # (every texel is solved; lobes: observable ones)
    # a smooth truth: the neighbourhood value is near the texel's own
    assert np.median(np.abs(x0[:, :3] - x[:, :3]) / x[:, :3]) < 0.1


def test_neighbourhood_prior_ignores_unobservable_lobes(sim):
    obs, _ = sim
    tp = _problem(obs, symmetry=0.0)
    x = np.ones((tp.prob.idx.size, 6))
    x[:, 5] = 100.0
    obsv = tp.obsv.copy()
    obsv[:, 2] = 0.0  # the third lobe is never observable
    import dataclasses

    tp = dataclasses.replace(tp, obsv=obsv)
    x0m, x0, glob = F._neighbourhood_prior(tp, x)
    assert glob[5] == 0.0 and np.all(x0[:, 5] == 0.0)
    assert np.allclose(x0[:, :5], 1.0)


def test_irls_band_converges_on_its_band_and_reports(sim):
    obs, truth = sim
    tp = _problem(obs, symmetry=0.0, prior=0.0)
    bands = tp.prob.bands(S, target_rows=2000)
    assert len(bands) > 1
    x, Hp, gp = F._first_pass(tp, bands)
    a, b = bands[1]
    want = np.concatenate([truth["albedo"], truth["weights"]]).reshape(6, -1).T[tp.prob.idx]
    ra, rb, xb, stat = F._irls_band(tp, Hp, gp, x, np.zeros_like(x), (a, b))
    assert (ra, rb) == (a, b) and xb.shape == (b - a, 6)
    rel = np.abs(xb - want[a:b]) / want[a:b]
    ok = tp.obsv[a:b] >= 0.1
    assert rel[:, :3].max() < 1e-3 and all(rel[ok[:, k], 3 + k].max() < 1e-2 for k in range(3))
    assert 1 <= stat[3] <= tp.cfg.solver.irls_iterations and stat[1] == 0 and stat[2] < 1e-6
    # a strong prior pulls the band towards x0
    strong = _problem(obs, symmetry=0.0, prior=1e3)
    xs = F._irls_band(strong, Hp, gp, x, np.full_like(x, 0.05), (a, b))[2]
    assert np.abs(xs - 0.05).max() < 0.01
    # a band without a solved texel is returned as is
    import dataclasses

    none = dataclasses.replace(tp, solve=np.zeros_like(tp.solve))
    assert F._irls_band(none, Hp, gp, x, x, (a, b))[3] == [0, 0, 0.0, 0]


def test_fast_solver_recovers_the_truth_and_calls_progress(sim):
    obs, truth = sim
    calls = []

    def progress(it, **kw):
        calls.append(kw)
        return it

    import dataclasses

    tp = dataclasses.replace(_problem(obs, prior=1e-6), progress=progress)
    x, x0m, info = F._fast(tp)
    want = np.concatenate([truth["albedo"], truth["weights"]]).reshape(6, -1).T[tp.prob.idx]
    assert np.median(np.abs(x - want) / want) < 1e-3
    assert x0m.shape == (6, S, S) and info["n_bands"] == len(tp.prob.bands(S)) and len(info["prior_global"]) == 6
    assert calls and calls[0]["desc"] == "IRLS"
    assert info["nnls_unconverged"] == 0 and info["irls_iterations"] >= 1


def test_refine_normals_corrects_perturbed_normals(sim):
    obs, _ = sim
    pert = dict(obs)
    rng = np.random.default_rng(0)
    n = obs["normal"] + 0.05 * rng.normal(size=obs["normal"].shape)
    pert["normal"] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    tp = _problem(pert, refine_normals=2)
    x, _, _ = F._fast(tp)
    x2, prior_map, info, tp2, ref = F._refine_normals(tp, x)
    assert ref.stats["iterations"] == 2 and len(ref.stats["history"]) == 2 and ref.stats["angle_median_deg"] > 0
    assert ref.normal_map.shape == (3, S, S) and ref.correction_map.shape == (S, S)
    # the refined normals are closer to the true ones than the perturbed
    true_n = obs["normal"].reshape(-1, 3)[tp.prob.idx]
    err = lambda a: np.degrees(np.arccos(np.clip(np.sum(a * true_n, 1), -1, 1)))  # noqa: E731
    assert np.median(err(tp2.prob.nm)) < np.median(err(tp.prob.nm0))
    assert tp2.cond.shape == tp.cond.shape and tp2.obsv.shape == tp.obsv.shape and prior_map.shape == (6, S, S)


def test_adam_runs_on_the_same_problem(sim):
    obs, _ = sim
    tp = _problem(obs, solver="adam", steps=5)
    x, info = F._adam(tp)
    assert x.shape == (tp.prob.idx.size, 6) and np.all(x >= 0) and np.all(np.isfinite(x))


def test_filled_maps_fill_flagged_texels_and_clip(sim):
    obs, _ = sim
    obs = dict(obs)
    hole = np.zeros((S, S), bool)
    hole[5:7, 4:6] = True
    obs["observed"] = obs["observed"] & ~hole[None]
    tp = _problem(obs, symmetry=0.0)
    x = np.full((tp.prob.idx.size, 6), 0.25)
    x[tp.flag] = 99.0  # never read: flagged texels are filled
    x[0, 1] = -1.0  # clipped at 0
    xfill, finfo = F._filled_maps(tp, x, None)
    mask = obs["mask"]
    assert xfill.shape == (6, S, S) and np.all(xfill[:, ~mask] == 0)
    assert np.allclose(xfill[0, hole & mask], 0.25) and finfo["filled_neighbours"] == (hole & mask).sum()
    assert tp.texels.from_map(xfill)[0, 1] == 0.0 and tp.texels.from_map(xfill)[0, 0] == 0.25


def test_residual_rms_is_zero_for_the_truth_and_grows_with_error(sim):
    obs, truth = sim
    tp = _problem(obs)
    tmap = np.concatenate([truth["albedo"], truth["weights"]])
    r = F._residual_rms(tp.prob, tmap, tp.texels)
    assert r.shape == (tp.prob.idx.size,)
    assert np.median(r) < 1e-2 * np.median(tp.prob.rms)  # float16 radiance
    assert np.all(F._residual_rms(tp.prob, 1.5 * tmap, tp.texels) > r)


def test_observable_stats_count_lobes_below_the_threshold(sim):
    obs, _ = sim
    tp = _problem(obs, observable_min=0.1)
    import dataclasses

    obsv = np.ones_like(tp.obsv)
    obsv[:3, 1] = 0.05
    st = F._observable_stats(dataclasses.replace(tp, obsv=obsv))
    assert st == {"n_observable": int(tp.solve.sum()) - 3, "n_unobservable_lobe": [0, 3, 0]}


def test_fit_maps_is_its_steps_in_order(sim):
    obs, _ = sim
    m = fit_maps(obs, threads=1)
    tp = _problem(obs)
    x, prior_map, _ = F._fast(tp)
    xfill, _ = F._filled_maps(tp, x, prior_map)
    assert np.array_equal(m.albedo, xfill[:3]) and np.array_equal(m.prior, prior_map)

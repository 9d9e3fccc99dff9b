"""Baseline models from ground truth, and Table 3's coefficient fit and albedo errors."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.albedo_eval import (albedo_errors, albedo_table_rows, evaluate_albedo,
                                                  fit_coefficients, observation_normal_equations)
from reflectmm_cli.evaluation.baselines import (ALBEDOMM_EXPONENT, build_baseline, diffuse_only_model,
                                                global_exponent_model, is_diffuse_only, write_baseline_model)
from reflectmm_cli.evaluation.representation import render_pairs_uv
from reflectmm_cli.model.pca import MODEL_KIND, fit_reflectance_pca, model_from_arrays, sample_model
from reflectmm_cli.reflectance.simulate import simulate_observations

S = 24


@pytest.fixture(scope="module")
def world():
    """6 identities rendered with the exact 3-lobe model (views/flashes subset to stay fast)."""
    out = []
    for k in range(6):
        obs, tr = simulate_observations(size=S, seed=k, return_truth=True, views=[2, 4, 6], flashes=[1, 4, 7, 9],
                                        dtype=np.float32)
        tr = dict(tr)
        tr["spec_albedo"] = tr["weights"].sum(0)
        tr["uv_mask"] = np.asarray(obs["mask"], bool)
        out.append((obs, tr))
    return out


def test_baselines_are_reflectance_models_with_the_documented_lobes(world, tmp_path):
    truths = [t for _, t in world]
    ids = [f"{i:03d}" for i in range(6)]
    d = diffuse_only_model(truths, components=3, ids=ids)
    a = global_exponent_model(truths, components=3, ids=ids)
    assert d.n_lobes == 1 and is_diffuse_only(d) and not is_diffuse_only(a)
    assert list(a.exponents) == [ALBEDOMM_EXPONENT]
    # the same diffuse PCA in both: identical albedo bases and sigma
    assert np.allclose(d.albedo_basis, a.albedo_basis) and np.allclose(d.sigma, a.sigma)
    # with all N-1 components every training identity is reproduced, incl. Σw = spec albedo (AlbedoMM transfer)
    full = global_exponent_model(truths, components=5, ids=ids)
    C, W = sample_model(full, full.train_coeffs[2].astype(np.float64))
    m = full.mask
    assert np.allclose(C[:, m], truths[2]["albedo"][:, m], atol=1e-5)
    assert np.allclose(W[0][m], truths[2]["spec_albedo"][m], atol=1e-5)
    # artifact round trip, the same kind as build-pca's, recognised as diffuse only from its arrays
    p = write_baseline_model(d, tmp_path / "bfm.npz", params={"components": 3})
    art = read_artifact(p, MODEL_KIND)
    assert art.meta["baseline"] == "diffuse-only" and art.meta["role"] == "BFM09"
    assert is_diffuse_only(art.arrays)
    back = model_from_arrays(art.arrays)
    assert np.array_equal(back.albedo_basis, d.albedo_basis)
    with pytest.raises(ReflectmmError, match="unknown baseline"):
        build_baseline("bfm17", truths)
    with pytest.raises(ReflectmmError, match="spec_albedo"):
        diffuse_only_model([{"albedo": truths[0]["albedo"]}] * 2)


def test_diffuse_only_model_renders_pure_lambert(world):
    """The all-zero lobe makes the shading exactly Lambert (closed form c/π·E·max(n·l,0))."""
    obs, tr = world[0]
    d = diffuse_only_model([t for _, t in world], components=3)
    C, W = sample_model(d, np.array([0.5, -1.0, 0.3]))
    img = render_pairs_uv(C, W, d.exponents, obs, [0])[0]
    n = np.asarray(obs["normal"], np.float64)
    f, v = int(obs["pair_flash"][0]), int(obs["pair_view"][0])
    ld = obs["flash_pos"][f] - np.asarray(obs["position"], np.float64)
    vd = obs["cam_centers"][v] - np.asarray(obs["position"], np.float64)
    E = obs["flash_intensity"][f] / (ld ** 2).sum(-1)
    cos = np.maximum((n * ld).sum(-1) / np.linalg.norm(ld, axis=-1), 0)
    front = (n * vd).sum(-1) > 0
    ref = np.moveaxis(C, 0, -1) / np.pi * (E * cos * front)[..., None]
    m = np.asarray(obs["mask"], bool)
    assert np.allclose(img[m], ref[m], rtol=1e-6, atol=1e-12)


def test_normal_equations_match_direct_rendering(world):
    """‖Aβ − y‖² from the accumulated normal equations equals the squared misfit of the rendered model."""
    truths = [t for _, t in world]
    model = fit_reflectance_pca([t["albedo"] for t in truths], [t["weights"] for t in truths], [1.0, 8.0, 64.0],
                                components=4)
    obs, _ = world[5]
    ne = observation_normal_equations(model, obs)
    beta = np.array([0.3, -0.7, 1.1, 0.2])
    C, W = sample_model(model, beta)
    J = len(obs["pair_flash"])
    img = render_pairs_uv(C, W, model.exponents, obs, range(J))
    sel = np.asarray(obs["observed"], bool) & model.mask[None]
    direct = float(((img - np.asarray(obs["radiance"], np.float64)) ** 2)[sel].sum())
    via = float(beta @ ne.AtA @ beta - 2 * beta @ ne.Aty + ne.yty)
    assert via == pytest.approx(direct, rel=1e-8)
    assert ne.n == int(sel.sum()) * 3


def test_fit_recovers_an_identity_in_the_model_span_and_scale_removes_intensity_error(world):
    truths = [t for _, t in world]
    model = fit_reflectance_pca([t["albedo"] for t in truths], [t["weights"] for t in truths], [1.0, 8.0, 64.0],
                                components=5)
    obs, tr = world[3]
    beta, st = fit_coefficients(model, obs, prior=1e-9)
    assert np.allclose(beta, model.train_coeffs[3], atol=1e-3)
    assert st["rms_residual"] < 1e-3 * st["rms_radiance"]
    res = evaluate_albedo({"exact": model}, {"003": (obs, tr)}, prior=1e-9, oracle=True)
    e = res.per_identity["exact"]["003"]
    assert e["raw"]["diffuse_psnr"] > 60 and e["raw"]["specular_psnr"] > 50 and e["scale"] == pytest.approx(1, 1e-4)
    assert res.per_identity["exact (oracle)"]["003"]["raw"]["diffuse_psnr"] > 60
    # a user who does not know the flash intensity (here: 1.6× too bright): raw albedo off, one scale fixes it
    obs2 = dict(obs)
    obs2["flash_intensity"] = np.asarray(obs["flash_intensity"]) * 1.6
    e2 = evaluate_albedo({"exact": model}, {"003": (obs2, tr)}, prior=1e-9).per_identity["exact"]["003"]
    assert e2["raw"]["diffuse_psnr"] < 35
    assert e2["scaled"]["diffuse_psnr"] > e2["raw"]["diffuse_psnr"] + 5
    rows = albedo_table_rows(res)
    assert {r["model"] for r in rows} == {"exact", "exact (oracle)"}


def test_baselines_rank_below_the_exact_representation_on_specular(world):
    truths = [t for _, t in world]
    ids = [f"{i:03d}" for i in range(6)]
    ours = fit_reflectance_pca([t["albedo"] for t in truths], [t["weights"] for t in truths], [1.0, 8.0, 64.0],
                               components=5)
    models = {"ours": ours, "diffuse-only": diffuse_only_model(truths, components=5, ids=ids),
              "albedomm": global_exponent_model(truths, components=5, ids=ids)}
    res = evaluate_albedo(models, {"004": world[4]}, prior=1e-6)
    sp = {k: v["004"]["raw"]["specular_psnr"] for k, v in res.per_identity.items()}
    df = {k: v["004"]["raw"]["diffuse_psnr"] for k, v in res.per_identity.items()}
    assert sp["ours"] > sp["albedomm"] and sp["ours"] > sp["diffuse-only"]
    assert df["ours"] > df["diffuse-only"]  # a diffuse-only model puts the highlights into the albedo


def test_albedo_errors_closed_form():
    rng = np.random.default_rng(0)
    t = rng.uniform(0.2, 0.6, (3, 8, 8))
    ts = rng.uniform(0.02, 0.1, (8, 8))
    reg = np.ones((8, 8), bool)
    e = albedo_errors(0.5 * t, 0.5 * ts, t, ts, reg)
    assert e["scale"] == pytest.approx(2.0)
    assert e["raw"]["diffuse_rel"] == pytest.approx(0.5) and e["raw"]["specular_rel"] == pytest.approx(0.5)
    assert e["raw"]["diffuse_psnr"] == pytest.approx(10 * np.log10(1 / np.mean((0.5 * t) ** 2)))
    assert e["scaled"]["diffuse_rel"] == pytest.approx(0, abs=1e-12)
    with pytest.raises(ReflectmmError, match="empty"):
        albedo_errors(t, ts, t, ts, np.zeros((8, 8), bool))


def test_resample_truth_box_and_bilinear():
    from reflectmm_cli.evaluation.albedo_eval import resample_truth

    rng = np.random.default_rng(5)
    a = rng.uniform(size=(3, 8, 8))
    s = rng.uniform(size=(8, 8))
    m = np.ones((8, 8), bool)
    m[0, 0] = False
    r = resample_truth({"albedo": a, "spec_albedo": s, "uv_mask": m}, 4)
    assert r["albedo"][1, 2, 3] == pytest.approx(a[1, 4:6, 6:8].mean())
    assert not r["uv_mask"][0, 0] and r["uv_mask"][0, 1]
    # a linear ramp is reproduced exactly by bilinear resampling at texel centres (inside the border)
    c = (np.arange(8) + 0.5) / 8
    ramp = np.broadcast_to(c[None, :], (8, 8))
    r2 = resample_truth({"albedo": np.stack([ramp] * 3), "spec_albedo": ramp}, 6)
    c6 = (np.arange(6) + 0.5) / 6
    inner = (c6 > 1 / 16) & (c6 < 15 / 16)
    assert np.allclose(r2["spec_albedo"][:, inner], np.broadcast_to(c6[None, inner], (6, inner.sum())))


def test_load_truths_from_synth_truth_artifacts(world, tmp_path):
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.stages.build_baseline import load_truths

    paths = []
    for i, (_, t) in enumerate(world[:3]):
        paths.append(write_artifact(tmp_path / f"{i + 1:03d}.npz", "synth-truth",
                                    {"albedo": t["albedo"], "spec_albedo": t["spec_albedo"], "uv_mask": t["uv_mask"],
                                     "weights": t["weights"]}, extra_meta={"identity": f"{i + 1:03d}"}))
    truths, ids = load_truths(paths)
    assert ids == ["001", "002", "003"] and set(truths[0]) == {"albedo", "spec_albedo", "uv_mask"}
    m = global_exponent_model(truths, components=2, ids=ids)
    assert m.ids == ids and m.n_components == 2
    bad = write_artifact(tmp_path / "bad.npz", "synth-truth", {"albedo": world[0][1]["albedo"]})
    with pytest.raises(ReflectmmError, match="bad.npz: truth has no 'spec_albedo'"):
        load_truths([bad])

"""benchmarks/bench_update_budget.py's summary (docs/benchmarks.md, "The two model updates at equal CPU time"): the
per-seed means, the median CPU time, the paired intervals over images × seeds and identities × seeds, the gaps to
the oracle, each against a direct computation on made-up rows; and the oracle built as a model carries the oracle's
arrays and σ."""

import json

import numpy as np
import pytest

from _benchmarks import load_benchmark
from reflectmm_cli.evaluation.face_metrics import mean_ci


def _row(run, seed, options, cpu, rng, shift=0.0):
    return {"run": run, "seed": seed, "options": options, "cpu_s": cpu,
            "psnr": (15 + shift + rng.normal(0, 1, 5)).tolist(), "ssim": (0.6 + rng.normal(0, 0.01, 5)).tolist(),
            "refined_psnr": (22 + shift + rng.normal(0, 1, 5)).tolist(),
            "refined_ssim": (0.75 + rng.normal(0, 0.01, 5)).tolist(),
            "albedo_residual": 0.16 + shift / 100, "albedo_residuals": (0.16 + shift / 100 + rng.normal(0, .01, 3)).tolist(),
            "weights_residual": 0.55, "weights_residuals": [0.55] * 3,
            "albedo_residual_oracle": 0.11, "weights_residual_oracle": 0.2}


def test_summary_against_direct_computation(tmp_path):
    b = load_benchmark("bench_update_budget")
    rng = np.random.default_rng(0)
    rows = [_row("control2", s, {"model-lr": "0", "epochs2": "2"}, 10 + s, rng) for s in (0, 1)]
    rows += [_row("sgd2", s, {"epochs2": "2"}, [11, 14][s], rng, shift=0.5) for s in (0, 1)]
    oracle = _row("oracle", None, {}, None, rng, shift=0.25)
    path = tmp_path / "r.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows + [oracle]))
    text = b.summarise([path], ["sgd2:control2"])
    ctl, sgd = rows[:2], rows[2:]
    ref = lambda rs, k: np.mean([np.mean(r[k]) for r in rs])  # noqa: E731
    gap = 100 * (ref(sgd, "refined_psnr") - ref(ctl, "refined_psnr")) / (np.mean(oracle["refined_psnr"])
                                                                        - ref(ctl, "refined_psnr"))
    sgd_line = next(x for x in text.splitlines() if x.startswith("| sgd2 |"))
    assert f"| {ref(sgd, 'refined_psnr'):.2f} ({gap:+.0f} %) |" in sgd_line
    assert f"| {np.median([11, 14]):.0f} | {ref(sgd, 'psnr'):.2f} |" in sgd_line
    assert "| oracle | the training identities' truth |" in text
    d = np.concatenate([np.subtract(sgd[s]["psnr"], ctl[s]["psnr"]) for s in (0, 1)])
    c = mean_ci(d)
    pair = next(x for x in text.splitlines() if x.startswith("| sgd2 − control2 |"))
    assert pair.split("|")[2].strip() == f"{c['mean']:+.2f} ± {c['half_width']:.2f}"
    assert pair.rstrip(" |").endswith(f"{12.5 / 10.5:.2f}")


def test_the_oracle_as_a_model_carries_its_arrays():
    b = load_benchmark("bench_update_budget")

    class M:
        vertex_albedo_mean = np.zeros((4, 3))
        vertex_albedo_basis = np.zeros((2, 4, 3))
        vertex_weights_mean = np.zeros((4, 3))
        vertex_weights_basis = np.zeros((2, 4, 3))
        sigma = np.ones(2)
        exponents = np.array([1.0, 8.0, 64.0])

    rng = np.random.default_rng(1)
    orc = {k: rng.normal(size=np.shape(getattr(M, k))) for k in ("vertex_albedo_mean", "vertex_albedo_basis",
                                                               "vertex_weights_mean", "vertex_weights_basis", "sigma")}
    m = b.oracle_as_model(M(), orc)
    for k, v in orc.items():
        assert np.array_equal(getattr(m, k), v.astype(np.float32)), k
    assert np.array_equal(M.sigma, np.ones(2))  # the model given is not changed
    with pytest.raises(KeyError):
        b.oracle_as_model(M(), {"vertex_albedo_mean": orc["vertex_albedo_mean"]})


def test_phase1_mode_of_a_run():
    b = load_benchmark("bench_update_budget")
    name, kw = b._run_spec("own:solver=ls,epochs2=2,phase1=own")
    assert b.phase1_mode(name, kw) == ({"solver": "ls", "epochs2": "2"}, True)
    assert b.phase1_mode(*b._run_spec("ctl:model-lr=0")) == ({"model-lr": "0"}, False)
    with pytest.raises(SystemExit, match="phase1 must be shared or own"):
        b.phase1_mode(*b._run_spec("x:phase1=mine"))


def test_a_run_from_the_oracle(tmp_path):
    """``model=oracle``: the run's start model is build-baseline's oracle of the workspace (per-vertex arrays and σ
    equal to the expressive-power measure's oracle, of the size of the workspace's model); a bad mode is refused;
    and the summary's initial-model row is a frozen run from the initial model, not the oracle's control."""
    from reflectmm_cli.artifacts import read_artifact, write_artifact
    from reflectmm_cli.evaluation.expressive import oracle_model
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.model.pca import MODEL_KIND, ReflectanceModel, model_arrays
    from reflectmm_cli.stages.evaluate_expressive import load_wild_truth
    from reflectmm_cli.synth.wild import WildConfig, synth_wild

    b = load_benchmark("bench_update_budget")
    assert b.model_mode("o", {"model": "oracle", "epochs2": "2"}) == ({"epochs2": "2"}, "oracle")
    assert b.model_mode("c", {"model-lr": "0"}) == ({"model-lr": "0"}, "initial")
    with pytest.raises(SystemExit, match="model must be initial or oracle"):
        b.model_mode("x", {"model": "truth"})

    ws = tmp_path / "ws"
    fm = procedural_face_model(grid=(31, 25), n_shape=4, n_exp=2, seed=2)
    synth_wild(ws / "synth-wild", WildConfig(count=12, size=48, images_per_identity=2, envmaps=1, envmap_width=32,
                                             prefilter_width=16, uv_size=32, occluder_fraction=0.0, seed=1,
                                             split=(0.6, 0.2, 0.2)), face_model=fm)
    tr = load_wild_truth(ws / "synth-wild")
    rng = np.random.default_rng(3)
    V, M, K = fm.uv.shape[0], 2, 3
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    init = ReflectanceModel(albedo_mean=f(3, 16, 16), albedo_basis=f(M, 3, 16, 16), weights_mean=f(K, 16, 16),
                            weights_basis=f(M, K, 16, 16), sigma=np.array([2.0, 1.0], np.float32),
                            explained_variance=np.array([4.0, 1.0], np.float32),
                            explained_variance_ratio=np.array([0.8, 0.2], np.float32),
                            exponents=np.array([1.0, 8.0, 64.0], np.float32), mask=np.ones((16, 16), bool),
                            train_coeffs=f(3, M), vertex_albedo_mean=f(V, 3), vertex_albedo_basis=f(M, V, 3),
                            vertex_weights_mean=f(V, K), vertex_weights_basis=f(M, V, K))
    write_artifact(ws / "build-pca" / "build-pca.npz", MODEL_KIND, model_arrays(init))
    path = b.write_oracle_model(ws, tmp_path / "scratch" / "oracle.npz")
    got = read_artifact(path, MODEL_KIND)
    want = oracle_model(np.stack([tr["albedo"][i] for i in tr["train"]]),
                        np.stack([tr["weights"][i] for i in tr["train"]]), [1, 8, 64], M)
    for k in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis", "sigma"):
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert got["albedo_mean"].shape == (3, 16, 16)  # the workspace model's UV size

    rows = [_row("oracle2own", s, {"model": "oracle", "model-lr": "0", "phase1": "own"}, 20, rng, shift=1.0)
            for s in (0, 1)]
    rows += [_row("control2", s, {"model-lr": "0", "epochs2": "2"}, 10, rng) for s in (0, 1)]
    jl = tmp_path / "r.jsonl"
    jl.write_text("".join(json.dumps(r) + "\n" for r in rows))
    text = b.summarise([jl], [])
    ctl_line = next(x for x in text.splitlines() if x.startswith("| control2 |"))
    assert "(+0 %)" in ctl_line  # the gaps are measured from the control's model, not from the oracle run's

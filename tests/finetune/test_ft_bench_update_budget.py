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

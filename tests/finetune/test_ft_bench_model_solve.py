"""benchmarks/bench_model_solve.py's solve options (docs/benchmarks.md, "The exact minimiser against the
early-stopped CG"): its exact solve equals the map-reduce's and the CG's run to convergence, its default equals
the one-process CG, and its paired table computes the gains it says."""
import json

import numpy as np
import pytest
from scipy import stats

from _benchmarks import load_benchmark
from _shards import make_dataset, wrong_initial
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune import model_mapreduce as MR
from reflectmm_cli.finetune import model_solve as MS
from reflectmm_cli.finetune.shards import load_shards
from reflectmm_cli.threads import torch_threads


def _bench():
    return load_benchmark("bench_model_solve")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = make_dataset(tmp_path_factory.mktemp("bench_solve"), n_images=8, size=16, mesh_n=5, seed=4)
    return d, load_shards(d["shards"]), wrong_initial(d["truth"], d["V"])


def test_the_exact_option_is_the_map_reduce_solve_and_the_converged_cg(data):
    """shard_images = 2 with 6 harmonics, one round: the arrays of alternate_sharded (serial, 1 thread) bit for bit,
    and those of the one-process CG run to a 1e-13 residual to 1e-6 of the largest value; the report names the
    Cholesky solve (0 CG iterations) and its residual is round-off."""
    d, ss, wrong = data
    mesh = (d["V"], d["tri"])
    cfg = MS.SolveConfig(rounds=1, pull=1e-2, max_pixels=0, harmonics=6, cg_iterations=100, shard_images=2)
    got, rep = _bench().solve_variant(wrong, d["light"], ss, cfg, mesh, threads=1)
    mr, _ = MR.alternate_sharded(wrong, d["light"], ss, cfg, mesh=mesh, keep_best=False, threads=1)
    conv = MS.SolveConfig(**{**cfg.__dict__, "shard_images": 0, "cg_iterations": 3000, "cg_tol": 1e-13})
    with torch_threads(1):
        cg, _ = MS.alternate(wrong, d["light"], ss, conv, mesh=mesh, keep_best=False)
    for k in mr:
        np.testing.assert_array_equal(got[k], mr[k])
        np.testing.assert_allclose(got[k], cg[k], rtol=0, atol=1e-6 * np.abs(cg[k]).max())
    last = rep.rounds[-1]
    assert last["cg_iterations"] == 0 and last["cg_rel_residual"] < 1e-10
    assert last["solve_end"] < last["solve_start"]


def test_without_shards_the_option_is_the_one_process_cg(data):
    """shard_images = 0: alternate's arrays bit for bit (its early-stopped CG: 5 iterations stop short)."""
    d, ss, wrong = data
    mesh = (d["V"], d["tri"])
    cfg = MS.SolveConfig(rounds=1, pull=1e-2, max_pixels=0, harmonics=6, cg_iterations=5)
    got, rep = _bench().solve_variant(wrong, d["light"], ss, cfg, mesh)
    want, _ = MS.alternate(wrong, d["light"], ss, cfg, mesh=mesh, keep_best=False)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k])
    assert rep.rounds[-1]["cg_iterations"] == 5 and rep.rounds[-1]["cg_rel_residual"] > 1e-4


def test_the_exact_option_per_vertex_is_refused(data):
    d, ss, wrong = data
    cfg = MS.SolveConfig(rounds=1, harmonics=0, shard_images=2)
    with pytest.raises(ReflectmmError, match="needs harmonics"):
        _bench().solve_variant(wrong, d["light"], ss, cfg, (d["V"], d["tri"]))


def test_the_paired_table_against_an_independent_t_interval(tmp_path):
    """``--pair A:B``: the mean and 95 % Student-t half-width of A − B per image and per identity, and the gap
    closed per identity over the initial model's mean span to the oracle."""
    rng = np.random.default_rng(0)

    def row(name):
        return {"variant": name, "psnr": rng.normal(22, 1, 12).tolist(), "ssim": rng.normal(0.75, 0.02, 12).tolist(),
                "albedo_residuals": rng.uniform(0.1, 0.2, 6).tolist(),
                "weights_residuals": rng.uniform(0.5, 0.7, 6).tolist(), "albedo_residual_oracle": 0.05,
                "weights_residual_oracle": 0.2}

    rows = [row("initial"), row("a"), row("b")]
    p = tmp_path / "rows.jsonl"
    p.write_text("".join(json.dumps(r) + "\n" for r in rows))
    line = _bench().pairs([p], ["a:b"]).splitlines()[-1]
    cells = [c.strip() for c in line.strip("|").split("|")]

    def ci(x):
        x = np.asarray(x)
        return x.mean(), stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x))

    m, h = ci(np.subtract(rows[1]["psnr"], rows[2]["psnr"]))
    assert cells[1] == f"{m:+.2f} ± {h:.2f}"
    m, h = ci(np.subtract(rows[1]["albedo_residuals"], rows[2]["albedo_residuals"]))
    assert cells[3] == f"{m:+.4f} ± {h:.4f}"
    span = np.mean(rows[0]["weights_residuals"]) - 0.2
    m, h = ci((np.subtract(rows[2]["weights_residuals"], rows[1]["weights_residuals"])) / span)
    assert cells[6] == f"{100 * m:+.1f} ± {100 * h:.1f} %"

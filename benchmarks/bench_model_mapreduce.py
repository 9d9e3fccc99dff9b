"""The least-squares model update in one process against its map-reduce over groups of images, on 1 and 2 worker
processes (docs/benchmarks.md, "The model update as a map-reduce").

Usage:
    python benchmarks/bench_model_mapreduce.py [--images 116] [--size 112] [--mesh-n 187] [--components 8]
        [--max-pixels 1000] [--harmonics 0,50] [--shard-images 16] [--cg-iterations 100] [--threads 1]
        [--exact-iterations 0] [--dask] [--jsonl out.jsonl]

The data are the test suite's synthetic wild shards (tests/finetune/_shards.py) at the demo's sizes: a 35k-vertex
mesh (``--mesh-n 187``), a per-vertex model with M = 8 components and 3 lobes, 104 training and 12 validation
images of 112² with at most 1000 fitted skin pixels each, an order-8 light model (6 components, where the demo's
has 80: only the per-image refinement depends on it). One round (refine the training images, solve, refine the
validation images), from a model whose mean and third basis are wrong. Rows per constraint (per vertex, and each
``--harmonics`` Q):

- ``one process``: :func:`~reflectmm_cli.finetune.model_solve.alternate` with ``--cg-iterations`` (the benchmark
  table's 100) and tolerance 1e-4, as ``finetune --solver ls`` runs it;
- with harmonics and ``--exact-iterations N`` also ``one process, CG to 1e-12``: at most N iterations, tolerance
  1e-12 (the exact solution the sharded Cholesky solve should equal);
- ``map-reduce, N workers``: :func:`~reflectmm_cli.finetune.model_mapreduce.alternate_sharded` with
  ``--shard-images`` per map task, serially (1) and on a process pool of 2 (and on a 2-worker Dask LocalCluster
  with ``--dask``).

Measured: the wall time of the update (workers included; torch threads ``--threads`` per process), split into
the map calls (refinements and the tasks' summaries; with the CPU seconds the tasks report, whose ratio to the
map's wall time is the parallelism reached) and the reduce + solve; and the largest absolute difference of the
four solved arrays (float32) to each reference row. The one-process rows count their CG solve as the solve.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests", "finetune"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # its sibling bench_model_solve

from bench_model_solve import append_jsonl  # noqa: E402


def _model(V, m: int):
    """The test suite's smooth per-vertex truth model (tests/finetune/_shards.py) with ``m`` components: orthonormal
    smooth diffuse bases, σ falling by 0.7 per component, transferred lobe-weight bases."""
    import dataclasses

    from _shards import RADIUS, _orthonormal, truth_model

    base = truth_model(V, 3)
    nv = V.shape[0]
    x, y = V[:, 0] / RADIUS, V[:, 1] / RADIUS
    fields = [np.stack([np.sin((k + 1) * x + c) * np.cos((k % 4 + 2) * y - c) for c in (0.3, 1.1, 2.0)], -1).ravel()
              for k in range(m)]
    B = _orthonormal(np.stack(fields)).reshape(m, nv, 3)
    sigma = 0.08 * np.sqrt(3 * nv) * 0.7 ** np.arange(m)
    wb = np.stack([np.stack([np.cos((k + 1) * x + j) for j in range(3)], -1) for k in range(m)])
    wb = wb * (0.01 / sigma[:, None, None]) * np.array([0.3, 0.5, 0.2])
    S = base.albedo_basis.shape[-1]
    return dataclasses.replace(
        base, albedo_basis=np.zeros((m, 3, S, S), np.float32), weights_basis=np.zeros((m, 3, S, S), np.float32),
        sigma=sigma.astype(np.float32), explained_variance=(sigma ** 2).astype(np.float32),
        explained_variance_ratio=np.full(m, 1.0 / m, np.float32), train_coeffs=np.zeros((2, m), np.float32),
        vertex_albedo_basis=B.astype(np.float32), vertex_weights_basis=wb.astype(np.float32))


def _data(tmp: Path, a):
    from _shards import cap_mesh, make_dataset, small_light_model, wrong_initial

    V, _, _ = cap_mesh(a.mesh_n)
    n_val = 12
    split = ["train"] * (a.images - n_val) + ["val"] * n_val
    d = make_dataset(tmp, n_images=a.images, size=a.size, seed=3, order=8, split=split, m=a.components,
                     mesh_n=a.mesh_n, truth=_model(V, a.components), light=small_light_model(8, 6))
    return d, wrong_initial(d["truth"], d["V"])


class _Clock:
    """Wall seconds of the map calls (with the CPU seconds the tasks report) and of the solves, by wrapping the
    modules' functions for the benchmark only."""

    def __init__(self):
        import reflectmm_cli.finetune.model_mapreduce as MR
        import reflectmm_cli.finetune.model_solve as MS

        self.t = {"map_s": 0.0, "task_cpu_s": 0.0, "solve_s": 0.0}
        clock = self

        class TimedMap(MR.OrderedMap):
            def __call__(self, fn, items):
                t = time.perf_counter()
                out = super().__call__(fn, items)
                clock.t["map_s"] += time.perf_counter() - t
                clock.t["task_cpu_s"] += sum(r.get("cpu_s", 0.0) for r in out)
                return out

        def timed(f):
            def g(*args, **kw):
                t = time.perf_counter()
                out = f(*args, **kw)
                clock.t["solve_s"] += time.perf_counter() - t
                return out
            return g

        MR.OrderedMap = TimedMap
        MR._reduce = timed(MR._reduce)
        MS.solve_model = timed(MS.solve_model)

    def take(self) -> dict:
        out, self.t = self.t, {k: 0.0 for k in self.t}
        return out


def _diff(x: dict, y: dict) -> float:
    return float(max(np.abs(np.asarray(x[k], np.float64) - np.asarray(y[k], np.float64)).max() for k in x))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=116)
    ap.add_argument("--size", type=int, default=112)
    ap.add_argument("--mesh-n", type=int, default=187)
    ap.add_argument("--components", type=int, default=8)
    ap.add_argument("--max-pixels", type=int, default=1000)
    ap.add_argument("--harmonics", default="0,50", help="comma list of Q (0: per vertex)")
    ap.add_argument("--shard-images", type=int, default=16)
    ap.add_argument("--cg-iterations", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--exact-iterations", type=int, default=0,
                    help="with harmonics, also the one-process CG run to 1e-12 with at most this many iterations")
    ap.add_argument("--dask", action="store_true", help="also a 2-worker Dask LocalCluster")
    ap.add_argument("--jsonl", type=Path, default=None)
    a = ap.parse_args()
    import torch

    from reflectmm_cli.finetune.model_mapreduce import alternate_sharded
    from reflectmm_cli.finetune.model_solve import SolveConfig, alternate
    from reflectmm_cli.finetune.shards import load_shards

    torch.set_num_threads(a.threads)
    clock = _Clock()
    with tempfile.TemporaryDirectory() as tmp:
        d, wrong = _data(Path(tmp), a)
        ss = load_shards(d["shards"])
        mesh = (d["V"], d["tri"])
        print(f"# {d['V'].shape[0]} vertices, {len(ss.indices('train'))} training / {len(ss.indices('val'))} "
              f"validation images of {a.size}²", file=sys.stderr, flush=True)
        for q in (int(x) for x in a.harmonics.split(",")):
            base = dict(rounds=1, pull=1.0, max_pixels=a.max_pixels, harmonics=q)
            runs = [("one process", lambda: alternate(wrong, d["light"], ss, SolveConfig(
                cg_iterations=a.cg_iterations, **base), mesh=mesh, keep_best=False))]
            if q and a.exact_iterations:
                runs.append(("one process, CG to 1e-12", lambda: alternate(wrong, d["light"], ss, SolveConfig(
                    cg_iterations=a.exact_iterations, cg_tol=1e-12, **base), mesh=mesh, keep_best=False)))
            sharded = SolveConfig(cg_iterations=a.cg_iterations, shard_images=a.shard_images, **base)
            for name, ex, jobs in [("map-reduce, 1 worker", "serial", 1), ("map-reduce, 2 workers (pool)", "pool", 2)] \
                    + ([("map-reduce, 2 workers (Dask)", "dask", 2)] if a.dask else []):
                runs.append((name, lambda ex=ex, jobs=jobs: alternate_sharded(
                    wrong, d["light"], ss, sharded, mesh=mesh, keep_best=False, executor=ex, jobs=jobs,
                    threads=a.threads)))
            got = {}
            for name, fn in runs:
                clock.take()
                t = time.perf_counter()
                arrays, rep = fn()
                dt = time.perf_counter() - t
                got[name] = arrays
                row = {"harmonics": q, "run": name, "wall_s": dt, **clock.take(), "threads": a.threads,
                       "shard_images": a.shard_images, "solve_end": rep.rounds[-1]["solve_end"],
                       "max_diff_vs_one_process": _diff(arrays, got["one process"]),
                       "max_diff_vs_exact": _diff(arrays, got["one process, CG to 1e-12"])
                       if "one process, CG to 1e-12" in got else None, "rounds": rep.rounds}
                print(json.dumps(row), flush=True)
                append_jsonl(a.jsonl, row)
    return 0


if __name__ == "__main__":
    sys.exit(main())

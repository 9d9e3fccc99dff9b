"""Planner benchmark: a no-op rerun of a 100-identity recipe must plan in well under 2 s.

Builds a workspace with N identities (F files of B bytes each), runs a checksum recipe
(one task per identity + one aggregate) once, then times:

* no-op rerun planning (``run_recipe``: plan + nothing to execute), median of R repeats,
  asserting that no task executes;
* the same planning with the hash memo deleted (every input re-read and re-hashed);
* a whole ``reflectmm run`` no-op in a fresh interpreter (import + plan + exit).

Usage: python benchmarks/bench_planner.py [--ids 100] [--files 4] [--bytes 262144] [--repeats 5]
Prints a markdown table and the command line that produced it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RECIPE = """
schema = "reflectmm.recipe/1"
name = "bench"

[stages.manifest]
verb = "checksum"
foreach = { file = "ids.txt" }
inputs = { files = "data/{id}" }

[stages.summary]
verb = "checksum"
inputs = { files = "@manifest.output" }
"""


def build(ws: Path, n_ids: int, n_files: int, nbytes: int) -> None:
    rng = __import__("numpy").random.default_rng(0)
    ids = [f"{i:03d}" for i in range(1, n_ids + 1)]
    for i in ids:
        d = ws / "data" / i
        d.mkdir(parents=True)
        for k in range(n_files):
            (d / f"img_{k:02d}.bin").write_bytes(rng.integers(0, 256, nbytes, dtype="uint8").tobytes())
    (ws / "ids.txt").write_text("\n".join(ids) + "\n")
    (ws / "recipe.toml").write_text(RECIPE)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ids", type=int, default=100)
    ap.add_argument("--files", type=int, default=4)
    ap.add_argument("--bytes", type=int, default=256 * 1024)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    from reflectmm_cli.recipes import run_recipe

    tmp = Path(tempfile.mkdtemp(prefix="reflectmm-bench-"))
    try:
        ws = tmp / "ws"
        build(ws, args.ids, args.files, args.bytes)
        t0 = time.perf_counter()
        first = run_recipe(ws / "recipe.toml", ws)
        first_s = time.perf_counter() - t0
        assert first.ok and len(first.by_status("ok")) == args.ids + 1

        plan_times, total_times = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            rep = run_recipe(ws / "recipe.toml", ws)
            total_times.append(time.perf_counter() - t0)
            plan_times.append(rep.plan_seconds)
            assert rep.ok and len(rep.by_status("skipped")) == args.ids + 1, rep.counts()
            assert not rep.by_status("ok"), "a no-op rerun executed a task"

        cold = []
        for _ in range(args.repeats):
            (ws / ".reflectmm" / "hashes.json").unlink()
            t0 = time.perf_counter()
            rep = run_recipe(ws / "recipe.toml", ws, dry_run=True)
            cold.append(time.perf_counter() - t0)
            assert {t.status for t in rep.tasks} == {"skip"}

        cli = []
        env = dict(os.environ)
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "reflectmm_cli", "-q", "run", str(ws / "recipe.toml"),
                                "-w", str(ws)], capture_output=True, text=True, env=env)
            cli.append(time.perf_counter() - t0)
            assert r.returncode == 0 and r.stdout == "", r.stderr

        med = statistics.median
        n_tasks = args.ids + 1
        data_mb = args.ids * args.files * args.bytes / 2**20
        print(f"Workspace: {args.ids} identities x {args.files} files x {args.bytes // 1024} KiB "
              f"({data_mb:.0f} MiB), {n_tasks} tasks; median of {args.repeats}.\n")
        print("| measurement | median | per task |")
        print("|---|---|---|")
        print(f"| first run (hash + write {n_tasks} artifacts, serial) | {first_s:.3f} s | "
              f"{first_s / n_tasks * 1e3:.2f} ms |")
        print(f"| no-op rerun: planning | {med(plan_times):.3f} s | {med(plan_times) / n_tasks * 1e3:.2f} ms |")
        print(f"| no-op rerun: `run_recipe` total (plan, log, memo) | {med(total_times):.3f} s | "
              f"{med(total_times) / n_tasks * 1e3:.2f} ms |")
        print(f"| no-op planning without the hash memo (re-hash {data_mb:.0f} MiB) | {med(cold):.3f} s | "
              f"{med(cold) / n_tasks * 1e3:.2f} ms |")
        print(f"| `reflectmm run` no-op, fresh interpreter | {med(cli):.3f} s | |")
        print(f"\nmemo speed-up of planning: {med(cold) / med(plan_times):.1f}x; tasks executed in no-op reruns: 0")
        print(f"\nCommand: python benchmarks/bench_planner.py --ids {args.ids} --files {args.files} "
              f"--bytes {args.bytes} --repeats {args.repeats}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

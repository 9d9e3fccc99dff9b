"""Whole synthetic recipe, end to end: the main job of the README timed on this machine.

Runs ``reflectmm run recipes/synthetic.toml`` in a fresh workspace, then

* a rerun with nothing changed (must execute no stage),
* a change to one PNG of one identity followed by ``--dry-run`` (must rerun only that identity's
  stages and the aggregates that read them) and the real rerun,

and prints a markdown table with wall times, per-stage task durations (from the run log) and the
command line that produced it.

Usage: python benchmarks/bench_recipe.py [--workspace DIR] [--jobs 2] [--recipe recipes/synthetic.toml]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(args: list[str]) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "reflectmm_cli", "-q", *args], capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"reflectmm {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
    return dt, proc.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--recipe", type=Path, default=ROOT / "recipes" / "synthetic.toml")
    a = ap.parse_args()
    ws = a.workspace or Path(tempfile.mkdtemp(prefix="reflectmm-bench-recipe-"))
    if ws.exists():
        shutil.rmtree(ws)
    base = ["run", str(a.recipe), "-w", str(ws), "--jobs", str(a.jobs)]

    t_first, _ = run(base)
    t_noop, out = run([*base, "--json"])
    counts = json.loads(out)["counts"]
    if counts.get("ok", 0) or counts.get("failed", 0):
        sys.exit(f"a rerun with nothing changed executed tasks: {counts}")
    log = [json.loads(line) for line in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    per_stage: dict[str, list[float]] = defaultdict(list)
    for r in log:
        if r.get("status") == "ok":
            per_stage[r["stage"]].append(float(r.get("duration") or 0.0))

    # change one identity's image: one pixel of one flash shot of the second identity
    import cv2

    pngs = sorted((ws / "synth-multipie" / "data").rglob("002_01_01_051_07.png"))
    if not pngs:
        sys.exit("no image of identity 002 found to modify")
    img = cv2.imread(str(pngs[0]))
    img[0, 0] = 255 - img[0, 0]
    cv2.imwrite(str(pngs[0]), img)
    _, plan = run([*base, "--dry-run", "--json"])
    to_run = sorted(f"{t['stage']}/{t.get('id') or '-'}" for t in json.loads(plan)["tasks"] if t["status"] == "run")
    t_one, _ = run(base)

    print(f"Command: `python benchmarks/bench_recipe.py --jobs {a.jobs}` ({a.recipe.name}, workspace {ws})\n")
    print("| run | wall time (s) |")
    print("|---|---:|")
    print(f"| first run, everything | {t_first:.1f} |")
    print(f"| rerun, nothing changed (no stage runs) | {t_noop:.2f} |")
    print(f"| one image of identity 002 changed | {t_one:.1f} |")
    print(f"\nAfter the change, the planner reruns {len(to_run)} tasks: {', '.join(to_run)}.\n")
    print("| stage | tasks | median task (s) | total task time (s) |")
    print("|---|---:|---:|---:|")
    for stage, ds in per_stage.items():
        print(f"| {stage} | {len(ds)} | {statistics.median(ds):.2f} | {sum(ds):.1f} |")


if __name__ == "__main__":
    main()

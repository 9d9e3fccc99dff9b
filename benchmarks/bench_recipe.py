"""Whole synthetic recipe, end to end: the main job of the README timed on this machine.

Runs ``reflectmm run recipes/synthetic.toml`` in a fresh workspace, then

* a rerun with nothing changed (must execute no stage),
* a change to one PNG of one identity followed by ``--dry-run`` (must rerun only that identity's
  stages and the aggregates that read them) and the real rerun,

and prints a markdown table with wall times, per-stage task durations (from the run log) and the
command line that produced it.

Usage: python benchmarks/bench_recipe.py [--workspace DIR] [--jobs 2] [--recipe recipes/synthetic.toml]
       python benchmarks/bench_recipe.py --runlogs WS [WS ...] [--names A,B,...]

``--runlogs`` runs nothing: it compares finished runs of the same recipe from their workspaces' run logs (the
last run in each), one column per workspace: the span from the first task's start to the last task's end, the
summed task time, and each stage's summed task time.
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


def last_run(ws: Path) -> list[dict]:
    """The run log lines of the last run in workspace ``ws`` whose tasks ran."""
    log = [json.loads(line) for line in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    ran = [r for r in log if r.get("status") == "ok"]
    if not ran:
        sys.exit(f"{ws}: no task ran in its run log")
    return [r for r in ran if r["run"] == ran[-1]["run"]]


def run_summary(rows: list[dict]) -> tuple[float, float, dict[str, float]]:
    """(span s, summed task s, stage -> summed task s) of one run's log lines. A line's time is its task's end
    (whole seconds), so the span is the last end minus the earliest start (end − duration)."""
    from datetime import datetime

    ends = [datetime.fromisoformat(r["time"]).timestamp() for r in rows]
    starts = [e - float(r.get("duration") or 0.0) for e, r in zip(ends, rows)]
    per_stage: dict[str, float] = defaultdict(float)
    for r in rows:
        per_stage[r["stage"]] += float(r.get("duration") or 0.0)
    return max(ends) - min(starts), sum(per_stage.values()), dict(per_stage)


def compare_runlogs(workspaces: list[Path], names: list[str]) -> None:
    runs = [run_summary(last_run(ws)) for ws in workspaces]
    print(f"Command: `python benchmarks/bench_recipe.py --runlogs {' '.join(str(w) for w in workspaces)}`\n")
    print("| | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    print("| span of the tasks (s) | " + " | ".join(f"{r[0]:.0f}" for r in runs) + " |")
    print("| summed task time (s) | " + " | ".join(f"{r[1]:.0f}" for r in runs) + " |")
    stages = sorted({s for r in runs for s in r[2]}, key=lambda s: -max(r[2].get(s, 0.0) for r in runs))
    for s in stages:
        print(f"| {s} | " + " | ".join(f"{r[2][s]:.1f}" if s in r[2] else "–" for r in runs) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--recipe", type=Path, default=ROOT / "recipes" / "synthetic.toml")
    ap.add_argument("--runlogs", type=Path, nargs="+", default=None,
                    help="compare the last runs of these workspaces instead of running")
    ap.add_argument("--names", default=None, help="comma-separated column names for --runlogs")
    a = ap.parse_args()
    if a.runlogs:
        names = a.names.split(",") if a.names else [w.name for w in a.runlogs]
        if len(names) != len(a.runlogs):
            sys.exit(f"--names: {len(names)} names for {len(a.runlogs)} workspaces")
        compare_runlogs(a.runlogs, names)
        return
    ws = a.workspace or Path(tempfile.mkdtemp(prefix="reflectmm-bench-recipe-"))
    if ws.exists():
        shutil.rmtree(ws)
    base = ["run", str(a.recipe), "-w", str(ws), "--jobs", str(a.jobs)]

    t_first, _ = run(base)
    t_noop, out = run([*base, "--json"])
    counts = json.loads(out)["counts"]
    if counts.get("ok", 0) or counts.get("failed", 0):
        sys.exit(f"a rerun with nothing changed executed tasks: {counts}")
    per_stage: dict[str, list[float]] = defaultdict(list)
    for r in last_run(ws):  # the first run's tasks (the rerun ran none)
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

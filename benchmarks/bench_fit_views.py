"""Per-identity fit-geometry cost of two settings (issue 13). ``--compare views`` (default): 9 views with the
nominal table (the old default) against 11 views (the raised 08_1 / 19_1 added for flashes 14 / 18) with the
calibrated rig and its tight prior (`--rig-sigma 3`). ``--compare flash``: on the calibrated rig, the room-light
photometric rounds (the default) against the flash term (`--photo-rounds 0 --flash-rounds 3`). Prints a markdown
table on stdout.

    python benchmarks/bench_calibrate.py --pipeline 8 --workspace W     # once: the rendered captures and the rig
    python benchmarks/bench_fit_views.py --workspace W [--ids 001,002,003] [--repeats 2] [--compare flash]

Each fit runs in its own process (the CLI, as a user runs it); the two settings alternate per identity so both see
the same machine load; wall and CPU time (user + system of the child) are reported as medians, with the ratio.
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _run(cmd: list[str]) -> tuple[float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: {r.stderr.strip()[-400:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", required=True, help="a bench_calibrate.py --pipeline workspace")
    ap.add_argument("--ids", default="001,002,003")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--compare", choices=("views", "flash"), default="views")
    args = ap.parse_args(argv)
    from reflectmm_cli.artifacts import read_artifact

    ws = Path(args.workspace).resolve()
    out = ws / "fit_views"
    def calibrated(i):
        return ["--capture", ws / "preprocess-multipie" / f"{i}.npz", "--rig", ws / "calibrate-rig" / "rig.toml",
                "--rig-sigma", "3", "--rig-rot-sigma", "0.3"]

    flash_cases = {
        "11 views, calibrate-rig, room light (--photo-rounds 2, the default)": calibrated,
        "11 views, calibrate-rig, flash term (--photo-rounds 0 --flash-rounds 3)":
            lambda i: calibrated(i) + ["--photo-rounds", "0", "--flash-rounds", "3"],
    }
    cases = flash_cases if args.compare == "flash" else {
        "9 views, nominal table (before)": lambda i: ["--capture", ws / "cap9" / f"{i}.npz", "--rig",
                                                       ws / "nominal_rig.toml"],
        "11 views, calibrate-rig, --rig-sigma 3 (now)": lambda i: ["--capture", ws / "preprocess-multipie" /
                                                                    f"{i}.npz", "--rig",
                                                                    ws / "calibrate-rig" / "rig.toml",
                                                                    "--rig-sigma", "3"],
    }
    for need in (ws / "cap9", ws / "preprocess-multipie", ws / "calibrate-rig" / "rig.toml"):
        if not need.exists():
            raise SystemExit(f"{need}: missing — run benchmarks/bench_calibrate.py --pipeline N --workspace {ws}")
    res: dict[str, list] = {k: [] for k in cases}
    for rep in range(args.repeats):
        for n_id, i in enumerate(args.ids.split(",")):
            order = list(enumerate(cases.items()))
            for c, (k, extra) in (order if n_id % 2 == 0 else order[::-1]):
                g = out / f"case{c}" / f"{i}.npz"
                cmd = [sys.executable, "-m", "reflectmm_cli", "-q", "fit-geometry", "--id", i, "--output", g,
                       "--no-overlay", "-w", ws, *extra(i)]
                wall, cpu = _run([str(c) for c in cmd])
                ga = read_artifact(g, "geometry")
                res[k].append((wall, cpu, float(ga["err_vertex_rmse_mm"]),
                               float(np.median(ga["err_cam_center_mm"]))))
    print(f"`python benchmarks/bench_fit_views.py {' '.join(argv if argv is not None else sys.argv[1:])}` — "
          f"identities {args.ids}, {args.repeats} repeat(s); load average {os.getloadavg()[0]:.1f}\n")
    print("| fit-geometry | wall s / identity (median) | CPU s / identity (median) | vertex RMS mm (median / max) | "
          "camera centre err mm (median) |")
    print("|---|---|---|---|---|")
    med = {}
    for k, r in res.items():
        a = np.array(r)
        med[k] = (statistics.median(a[:, 0]), statistics.median(a[:, 1]))
        print(f"| {k} | {med[k][0]:.1f} | {med[k][1]:.1f} | {np.median(a[:, 2]):.2f} / {a[:, 2].max():.2f} | "
              f"{np.median(a[:, 3]):.1f} |")
    (b, n) = list(med.values())
    print(f"\nratio second / first: wall {n[0] / b[0]:.2f}, CPU {n[1] / b[1]:.2f}")


if __name__ == "__main__":
    main()

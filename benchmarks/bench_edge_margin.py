"""unwrap-uv's edge margin against the geometry it trusts: the albedo error of fit-reflectance for several margins,
on fitted geometry from a detector's landmarks and on the same captures with landmarks on every view.

For each geometry set and each margin, every identity is unwrapped (``reflectmm unwrap-uv --edge-margin M`` plus
the extra unwrap arguments of the set), fitted (``fit-reflectance``, the demo's solver settings) and compared with
its truth (``evaluate truth``). Printed per set and margin: the mean over identities of the relative diffuse
albedo RMSE over the fitted (observable) texels, over every texel (the filled ones too), the mean of the median
texel's error, and the per-identity observable errors. Each run is one process per step, as the recipe runs it.

    python benchmarks/bench_edge_margin.py --truth WS/synth-multipie/truth \\
        --face-model WS/synth-multipie/face_model.npz \\
        --set detector WS/preprocess-multipie WS/fit-geometry "--views landmarked --flashes landmarked" \\
        --set annotated WS/preprocess-annotated WS/fit-geometry-annotated "" \\
        --ids 001-008 --margins 1,2,3,5,8 --scratch /tmp/edge
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

from reflectmm_cli.params import parse_ids


def _run(args: list[str]) -> str:
    """One reflectmm command in its own process; its stdout."""
    return subprocess.run([sys.executable, "-m", "reflectmm_cli", *args], check=True, capture_output=True, text=True,
                          env={**os.environ, "REFLECTMM_QUIET": "1"}).stdout


def measure(capture_dir: Path, geometry_dir: Path, extra: list[str], margin: int, ids: list[str], truth: Path,
            face_model: Path, out: Path) -> dict:
    """Unwrap, fit and evaluate every identity at one margin; the errors per identity."""
    out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for i in ids:
        uv, maps, ev = out / f"uv_{i}.npz", out / f"maps_{i}.npz", out / f"ev_{i}.npz"
        _run(["unwrap-uv", "-w", str(out), "--id", i, "--capture", str(capture_dir / f"{i}.npz"),
              "--geometry", str(geometry_dir / f"{i}.npz"), "--face-model", str(face_model),
              "--edge-margin", str(margin), *extra, "-o", str(uv)])
        _run(["fit-reflectance", "-w", str(out), "-i", str(uv), "--solver", "fast", "--exponents", "1,8,64",
              "--symmetry", "1.0", "-o", str(maps)])
        res = _run(["evaluate", "truth", "-w", str(out), "--id", i, "--maps", str(maps),
                    "--truth", str(truth / f"{i}.npz"), "-o", str(ev)])
        raw = json.loads(res)["errors"]["reflectance"]["raw"]
        rows[i] = {"observable": raw["observable"]["albedo_rel"], "all": raw["all"]["albedo_rel"],
                   "median": raw["observable"]["albedo_rel_median"]}
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", nargs=4, action="append", required=True,
                    metavar=("LABEL", "CAPTURE_DIR", "GEOMETRY_DIR", "UNWRAP_ARGS"))
    ap.add_argument("--truth", required=True, type=Path, help="folder of the identities' truth NPZ")
    ap.add_argument("--face-model", required=True, type=Path)
    ap.add_argument("--ids", required=True, help="e.g. 001-008 or 001,003")
    ap.add_argument("--margins", default="1,3", help="edge margins (px), comma separated")
    ap.add_argument("--scratch", required=True, type=Path)
    args = ap.parse_args(argv)
    ids = parse_ids(args.ids)
    margins = [int(m) for m in args.margins.split(",")]
    print("| set | edge margin | albedo rel. error: observable / all texels / median texel (mean over identities) "
          "| per identity, observable |")
    print("|---|---|---|---|")
    for label, cap, geo, extra in args.set:
        for m in margins:
            rows = measure(Path(cap), Path(geo), shlex.split(extra), m, ids, args.truth, args.face_model,
                           args.scratch / label / f"m{m}")
            mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in ("observable", "all", "median")}
            per = ", ".join(f"{100 * r['observable']:.1f}" for r in rows.values())
            print(f"| {label} | {m} | {100 * mean['observable']:.2f} % / {100 * mean['all']:.2f} % / "
                  f"{100 * mean['median']:.2f} % | {per} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

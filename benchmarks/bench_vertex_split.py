"""Where a fitted face's vertex error lies: its place in model space (centroid shift, rotation) or its shape.

fit-geometry's vertex error is measured in model space, vertex by vertex against the true mesh (same topology).
The face can be off there as a whole (a shift or a turn that the cameras follow: a near-gauge that the landmarks and
images see weakly) or in its shape. Per identity and per stage this prints the raw RMS, the centroid shift (x / y / z
in mm; +z points out of the face), the rotation of the best rigid alignment (degrees) and the RMS after it, and for
two stages the ratio of each to the first's.

    python benchmarks/bench_vertex_split.py --workspace WS [--stages fit-geometry,fit-geometry-annotated]
        [--truth-dir WS/synth-multipie/truth]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.geometry.align import rigid_align


def split(fitted: np.ndarray, true: np.ndarray) -> dict[str, float | np.ndarray]:
    """Raw RMS, centroid shift (3,), rotation angle (degrees) of the best rigid alignment and the RMS after it, of
    (N, 3) fitted vertices against the (N, 3) true ones."""
    X, T = np.asarray(fitted, np.float64), np.asarray(true, np.float64)
    R, t, _ = rigid_align(X, T)
    aligned = X @ R.T + t
    angle = float(np.degrees(Rotation.from_matrix(R).magnitude()))  # not arccos of the trace: flat near 0
    return {"rms": float(np.sqrt(((X - T) ** 2).sum(1).mean())), "shift": X.mean(0) - T.mean(0),
            "rotation_deg": angle, "aligned_rms": float(np.sqrt(((aligned - T) ** 2).sum(1).mean()))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--stages", default="fit-geometry,fit-geometry-annotated")
    ap.add_argument("--truth-dir", type=Path, default=None, help="default WS/synth-multipie/truth")
    args = ap.parse_args(argv)
    stages = [s for s in args.stages.split(",") if s]
    truth_dir = args.truth_dir or args.workspace / "synth-multipie" / "truth"
    ids = sorted(p.stem for p in (args.workspace / stages[0]).glob("*.npz")
                 if (truth_dir / p.name).is_file() and all((args.workspace / s / p.name).is_file() for s in stages))
    if not ids:
        print(f"no identity with a fit in every stage and a truth file in {truth_dir}", file=sys.stderr)
        return 1
    head = " | ".join(f"{s}: RMS, shift x / y / z, rotation °, aligned RMS" for s in stages)
    print(f"| identity | {head} |" + (" × the second: RMS, aligned |" if len(stages) == 2 else ""))
    print("|---" * (len(stages) + 1 + (len(stages) == 2)) + "|")
    ratios = []
    for i in ids:
        true = read_artifact(truth_dir / f"{i}.npz", members=("vertices",))["vertices"]
        cells, res = [], []
        for s in stages:
            r = split(read_artifact(args.workspace / s / f"{i}.npz", "geometry", members=("vertices",))["vertices"],
                      true)
            res.append(r)
            d = r["shift"]
            cells.append(f"{r['rms']:.2f}, {d[0]:+.2f} / {d[1]:+.2f} / {d[2]:+.2f}, {r['rotation_deg']:.2f}, "
                         f"{r['aligned_rms']:.2f}")
        extra = ""
        if len(stages) == 2:
            ratios.append((res[0]["rms"] / res[1]["rms"], res[0]["aligned_rms"] / res[1]["aligned_rms"]))
            extra = f" {ratios[-1][0]:.2f}, {ratios[-1][1]:.2f} |"
        print(f"| {i} | " + " | ".join(cells) + " |" + extra)
    if ratios:
        r = np.array(ratios)
        print(f"\nmedian ratio: raw {np.median(r[:, 0]):.2f} ({int((r[:, 0] <= 1.3).sum())} of {len(r)} within 1.3), "
              f"aligned {np.median(r[:, 1]):.2f} ({int((r[:, 1] <= 1.3).sum())} of {len(r)} within 1.3)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

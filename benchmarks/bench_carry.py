"""How calibrate-rig carries the nominal table's cameras that no identity annotates (``--carry``,
``--carry-scale``), measured on the rig itself against the true one.

For each choice, ``reflectmm calibrate-rig`` runs on the same captures, face model and nominal table (the extra
arguments are passed through); each camera's calibrated centre is compared with the true rig's, in the rig frame
(head at the origin, as the table convention has it) without any alignment, and after the rigid motion that best
aligns the annotated cameras' centres (the rig frame's own gauge, the identities' mean head pose, taken out).
Printed: per carried camera the two errors, and the carrying similarity's scale.

    python benchmarks/bench_carry.py --capture W/detect/cap/001.npz ... --face-model FM --rig W/nominal_rig.toml \\
        --true-rig W/true_rig.toml --scratch /tmp/carry -- --focal 1000 --landmark-weights jaw=0
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CHOICES = (("centres", "fit"), ("centres", "distances"), ("poses", "fit"), ("poses", "distances"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", action="append", required=True)
    ap.add_argument("--face-model", required=True)
    ap.add_argument("--rig", required=True, help="the nominal table")
    ap.add_argument("--true-rig", required=True)
    ap.add_argument("--scratch", required=True)
    ap.add_argument("--label", default="")
    ap.add_argument("extra", nargs="*", help="further calibrate-rig arguments (after --)")
    args = ap.parse_args(argv)
    from reflectmm_cli.geometry.align import rigid_align
    from reflectmm_cli.rig import load_rig

    true = load_rig(args.true_rig)
    rows = []
    for carry, scale in CHOICES:
        out = Path(args.scratch) / f"{carry}_{scale}" / "rig.npz"
        cmd = [sys.executable, "-m", "reflectmm_cli", "calibrate-rig", "--face-model", args.face_model,
               "--rig", args.rig, "-o", str(out), "--carry", carry, "--carry-scale", scale, *args.extra]
        for c in args.capture:
            cmd += ["--capture", c]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env={**os.environ, "REFLECTMM_QUIET": "1"})
        z = np.load(out)
        names = [str(n) for n in z["camera_names"]]
        C = z["centers"]
        T = np.stack([np.asarray(true.camera(n).position, np.float64) for n in names])
        seen = np.isfinite(z["center_sigma_mm"]).all(-1)
        R, t, _ = rigid_align(C[seen], T[seen])
        direct = np.linalg.norm(C - T, axis=1)
        aligned = np.linalg.norm(C @ R.T + t - T, axis=1)
        meta = json.loads(str(z["__meta__"]))
        note = next((a for a in meta["assumptions"] if "no identity has landmarks" in a), "")
        sa = note.split("(x")[1].split(",")[0] if "(x" in note else "-"
        rows.append(dict(carry=carry, scale=scale, names=names, seen=seen, direct=direct, aligned=aligned, sa=sa,
                         seconds=time.perf_counter() - t0))
    un = ~rows[0]["seen"]
    if not un.any():
        print(f"{args.label}: every camera is annotated; nothing is carried")
        return 0
    names = [n for n, u in zip(rows[0]["names"], un) if u]
    print(f"{args.label} cameras without landmarks: {', '.join(names)}; error mm in the rig frame / after the "
          f"rigid alignment of the annotated cameras")
    print("| carry | scale | carried scale | " + " | ".join(names) + " | median | annotated, max |")
    print("|---|---|---|" + "---|" * (len(names) + 2))
    for r in rows:
        cells = [f"{d:.0f} / {a:.0f}" for d, a in zip(r["direct"][un], r["aligned"][un])]
        med = f"{np.median(r['direct'][un]):.0f} / {np.median(r['aligned'][un]):.0f}"
        ann = f"{r['direct'][~un].max():.0f} / {r['aligned'][~un].max():.0f}"
        print(f"| {r['carry']} | {r['scale']} | x{r['sa']} | " + " | ".join(cells) + f" | {med} | {ann} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

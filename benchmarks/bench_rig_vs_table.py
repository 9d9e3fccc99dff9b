"""Each camera of calibrated rigs against the table the captures were rendered with: centre distance (mm) and the
angle between the viewing directions (degrees), the frames compared as they are (calibrate-rig's frame has its
origin at the identities' mean head, the synthetic table's at the head), with the carry's residual from the rig's
header.

    python benchmarks/bench_rig_vs_table.py --table WS/synth-multipie/rig.toml WS_A/calibrate-rig/rig.toml ...
"""
from __future__ import annotations

import argparse
import re
import sys
import tomllib
from pathlib import Path

import numpy as np


def cameras(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name → (centre, unit viewing direction) of a rig TOML."""
    out = {}
    for c in tomllib.loads(path.read_text())["camera"]:
        p = np.asarray(c["position"], np.float64)
        d = np.asarray(c["look_at"], np.float64) - p
        out[c["name"]] = (p, d / np.linalg.norm(d))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", required=True, type=Path)
    ap.add_argument("rigs", nargs="+", type=Path)
    args = ap.parse_args(argv)
    table = cameras(args.table)
    for rig in args.rigs:
        cams = cameras(rig)
        header = rig.read_text().split("\n[[camera]]", 1)[0]
        carry = re.search(r"carried by the similarity of the calibrated cameras' ([^(]*)\(([^)]*)\)", header)
        cells = []
        for name, (p, d) in cams.items():
            tp, td = table[name]
            ang = np.degrees(np.arccos(np.clip(d @ td, -1.0, 1.0)))
            cells.append(f"{name} {np.linalg.norm(p - tp):.0f} mm / {ang:.1f}°")
        print(f"{rig}: " + ", ".join(cells))
        print(f"  carry: {carry.group(1).strip()} ({carry.group(2)})" if carry else "  carry: none")
    return 0


if __name__ == "__main__":
    sys.exit(main())

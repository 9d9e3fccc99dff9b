"""The detector's per-camera offsets (face-model embed-landmarks' ``landmark_view_bias``), measured against the
synthetic truth of a workspace made by recipes/synthetic.toml.

Per camera: the detector's inner points (17-67) against the projection of the embedded landmark vertices of the
true mesh with the true camera (RMS per coordinate, px), the part of it that repeats on every face (the RMS of the
mean over identities), and the same RMS after the face model's offsets are taken off, for the identities the
offsets were measured on and for the others.

    python benchmarks/bench_view_bias.py --workspace WS [--measured-on 001,002,003,004]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", required=True, type=Path)
    ap.add_argument("--face-model", type=Path, default=None,
                    help="default: WS/face-model-embed/face-model-embed.npz")
    ap.add_argument("--measured-on", default="001,002,003,004", help="identities the offsets were measured on")
    args = ap.parse_args(argv)
    from reflectmm_cli.geometry.camera import project
    from reflectmm_cli.geometry_fit.embedding import apply_view_bias

    ws = args.workspace
    fm_path = args.face_model or ws / "face-model-embed" / "face-model-embed.npz"
    fm = np.load(fm_path)
    idx = fm["landmarks"]
    cams = json.loads(str(fm["__meta__"]))["info"].get("landmark_view_bias", {}).get("cameras", {})
    measured = set(args.measured_on.split(","))
    inner = np.arange(17, 68)
    rows: dict[str, dict[str, list]] = {}
    for cap in sorted((ws / "preprocess-multipie").glob("*.npz")):
        ident = cap.stem
        truth = np.load(ws / "synth-multipie" / "truth" / f"{ident}.npz")
        tn = [str(n) for n in truth["camera_names"]]
        c = np.load(cap)
        names = [str(v) for v in c["view_names"]]
        lm = np.asarray(c["landmarks"], np.float64)
        fixed, _ = apply_view_bias(lm, names, cams)
        for k, n in enumerate(names):
            if not np.isfinite(lm[k][inner]).all():
                continue
            j = tn.index(n)
            x = project(np.asarray(truth["vertices"], np.float64)[idx], truth["K"][j], truth["R"][j],
                        truth["t"][j])[0]
            r = rows.setdefault(n, {"raw": [], "in": [], "out": []})
            r["raw"].append((lm[k] - x)[inner])
            r["in" if ident in measured else "out"].append((fixed[k] - x)[inner])

    def rms(a):
        return float(np.sqrt(np.mean(np.square(a)))) if len(a) else float("nan")

    print(f"{fm_path}: offsets for {', '.join(sorted(cams)) or 'no camera'}; measured on {args.measured_on}")
    print("| camera | identities | detector vs truth, px | of it on every face | after the offsets: measured on "
          "| others |")
    print("|---|---|---|---|---|---|")
    for n, r in rows.items():
        raw = np.stack(r["raw"])
        print(f"| {n} | {len(raw)} | {rms(raw):.2f} | {rms(raw.mean(0)):.2f} | {rms(r['in']):.2f} | "
              f"{rms(r['out']):.2f} |")
    alls = {k: [a for r in rows.values() for a in r[k]] for k in ("raw", "in", "out")}
    print(f"| all | {len(alls['raw'])} | {rms(alls['raw']):.2f} | – | {rms(alls['in']):.2f} | {rms(alls['out']):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

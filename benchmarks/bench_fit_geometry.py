"""Benchmark of ``fit-geometry``: seconds per identity and errors against ground truth on the synthetic world.

Generates (or reuses, ``--data``) a synthetic Multi-PIE set — the 9 default views at 640×480, landmark noise
σ = 1 px, sensor noise 0.002 — preprocesses it, then fits every identity with several configurations and prints a
markdown table of medians over identities: fit seconds, landmark error (px, fitted vs true projections of the 68
landmark vertices), vertex reprojection error (px), vertex RMSE (mm and % of the inter-ocular distance) and
camera-centre error (mm).

    python benchmarks/bench_fit_geometry.py --identities 2 --work /tmp/bench_fg
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

VIEWS = ("09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0")
CONFIGS = {
    "landmarks only": {"photo_rounds": 0},
    "landmarks + photometric (default)": {},
    "default, rig σ 2 mm": {"rig_sigma_mm": 2.0},
}


def make_data(work: Path, identities: int, face_vertices: int) -> Path:
    from reflectmm_cli.capture.preprocess import CaptureOptions, preprocess_identity
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.synth.multipie import SynthConfig, synth_multipie

    root = work / "syn"
    if not (root / "truth").is_dir():
        cfg = SynthConfig(identities=identities, cameras=VIEWS, flashes=("07",), landmark_noise=1.0, noise=0.002,
                          face_vertices=face_vertices)
        synth_multipie(root, cfg)
    for k in range(identities):
        ident = f"{k + 1:03d}"
        out = work / "capture" / f"{ident}.npz"
        if not out.exists():
            arrays, plan, report = preprocess_identity(root, ident, CaptureOptions(views=VIEWS, flashes=("07",)))
            write_artifact(out, "capture", arrays, inputs=[{"role": "root", "path": "../syn"}])
    return root


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--identities", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_fit_geometry"))
    ap.add_argument("--face-vertices", type=int, default=20000)
    ap.add_argument("--configs", default=",".join(str(i) for i in range(len(CONFIGS))),
                    help="indices of the configurations to run")
    args = ap.parse_args(argv)
    from reflectmm_cli.geometry_fit.identity import fit_identity
    from reflectmm_cli.geometry_fit import FitConfig

    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    root = make_data(args.work, args.identities, args.face_vertices)
    print(f"data ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    names = list(CONFIGS)
    rows = []
    for ci in (int(c) for c in args.configs.split(",")):
        name = names[ci]
        res = []
        for k in range(args.identities):
            ident = f"{k + 1:03d}"
            t = time.perf_counter()
            a, _, _ = fit_identity(args.work / "capture" / f"{ident}.npz", root / "face_model.npz", ident,
                                   rig_path=root / "rig.toml", truth_path=root / "truth" / f"{ident}.npz",
                                   config=FitConfig(**CONFIGS[name]))
            sec = time.perf_counter() - t
            res.append([sec, np.median(a["err_landmark_px"]), np.median(a["err_vertex_px"]),
                        float(a["err_vertex_rmse_mm"]), 100 * float(a["err_vertex_rmse_iod"]),
                        np.median(a["err_cam_center_mm"]), np.median(a["landmark_rmse_px"])])
            print(f"{name} {ident}: " + " ".join(f"{x:.3f}" for x in res[-1]), file=sys.stderr)
        rows.append((name, np.median(np.array(res), axis=0), float(np.min(np.array(res)[:, 0]))))
    print(f"\n{args.identities} synthetic identities, 9 views 640x480, landmark noise 1 px, "
          f"{args.face_vertices}-vertex procedural face model; medians over identities "
          "(per-view errors: median over views)\n")
    print("| configuration | s / identity (median, min) | landmark err (px) | vertex reproj. (px) | vertex RMSE (mm) "
          "| vertex RMSE (% IOD) | camera centre (mm) | landmark residual (px) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, m, tmin in rows:
        print(f"| {name} | {m[0]:.1f}, {tmin:.1f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.2f} | {m[4]:.1f} | {m[5]:.1f} "
              f"| {m[6]:.2f} |")
    print(f"\ncommand: python benchmarks/bench_fit_geometry.py --identities {args.identities} "
          f"--face-vertices {args.face_vertices}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

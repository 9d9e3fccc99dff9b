"""calibrate-rig: one rig for all identities from their landmarks (issue 13).

Synthetic landmarks (no rendering): identities drawn from the face model's prior (expression 0.5 σ, head turned
up to 5° and shifted ~20 mm), projected by the packaged rig (the synth code's projection, ``RigCamera.project``)
on the 9 default views + the raised 08_1 / 19_1, 1 px Gaussian noise, 2 % of the landmarks displaced by 40 px
(outliers).  The nominal rig handed to the calibration is deliberately wrong: every camera 10 % further away,
positions and aims turned by 3°, the raised cameras moved by another 300 mm, focal +8 %.

Cases: ``focal shared`` (the focal is estimated, starting from the wrong nominal value) and ``focal given``
(the user passes the true focal, as from EXIF; the rest is estimated).  Errors against the true rig, after the
rigid alignment of the fitted camera centres to the true ones (the landmarks fix the rig only up to a rigid
motion; the scale is *not* aligned away): camera centres, flashes 14/18 (on 08_1/19_1), focal, face vertices
(full mesh of every identity in the rig frame), outlier recall/precision, and the time (wall, process CPU).

    python benchmarks/bench_calibrate.py [--identities 128] [--vertices 35000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--identities", type=int, default=128)
    ap.add_argument("--vertices", type=int, default=35000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cases", default="shared,given")
    args = ap.parse_args(argv)

    from reflectmm_cli.fitting.calibrate import CalibrationConfig, calibrate_rig, perturb_rig, simulate_landmarks
    from reflectmm_cli.fitting.init import rigid_align
    from reflectmm_cli.fitting.model import ShapeModel
    from reflectmm_cli.geometry.procedural import procedural_face_model
    from reflectmm_cli.rig import DEFAULT_VIEWS, RAISED_CAMERAS, load_rig

    model = ShapeModel.from_face_model(procedural_face_model(args.vertices))
    true = load_rig()
    views = list(DEFAULT_VIEWS) + list(RAISED_CAMERAS)
    sim = simulate_landmarks(model, true, views, args.identities, seed=args.seed, noise_px=1.0,
                             outlier_fraction=0.02, outlier_px=40.0)
    nominal = perturb_rig(true, distance_scale=1.1, angle_deg=3.0, raised_offset_mm=300.0, focal_scale=1.08,
                          seed=args.seed + 1)
    tc = np.array([true.camera(n).center for n in views])
    nc = np.array([nominal.camera(n).center for n in views])
    _, _, nom_err = rigid_align(nc, tc)
    fl = ["14", "18"]
    true_fl = np.array([true.flash(f).position for f in fl])
    rows = []
    for case in [c for c in args.cases.split(",") if c]:
        cfg = CalibrationConfig(focal="shared") if case == "shared" else \
            CalibrationConfig(focal="fixed", focal_px=true.camera(views[0]).focal_px)
        t0, c0 = time.perf_counter(), time.process_time()
        cal = calibrate_rig(model, sim["landmarks"], views, (640, 480), nominal, cfg)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        Ra, ta, cam_err = rigid_align(cal.centers, tc)
        fpos = np.array([cal.flash_pos[cal.flash_ids.index(f)] for f in fl]) @ Ra.T + ta
        fl_err = np.linalg.norm(fpos - true_fl, axis=1)
        anchor = cal.report["scale_anchor"]
        verr = []
        for i in range(args.identities):
            vt = model.vertices(sim["shape"][i], sim["exp"][i]) @ sim["head_R"][i].T + sim["head_t"][i]
            vf = anchor * model.vertices(cal.shape_coeffs[i], cal.exp_coeffs[i]) @ cal.head_R[i].T + cal.head_t[i]
            vf = vf @ Ra.T + ta
            verr.append(float(np.sqrt(((vf - vt) ** 2).sum(-1).mean())))
        out = cal.outliers
        tp = int((out & sim["outlier"]).sum())
        rows.append((case, wall, cpu, cam_err, fl_err, float(cal.focal[0]), float(np.median(verr)),
                     float(np.max(verr)), tp / max(int(sim["outlier"].sum()), 1), tp / max(int(out.sum()), 1),
                     cal.report["iterations"], float(np.nanmedian(np.linalg.norm(cal.center_sigma_mm, axis=1)))))
    cmd = "python benchmarks/bench_calibrate.py " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"`{cmd.strip()}` — {args.identities} identities x {len(views)} views, face model {model.n_vertices} "
          f"vertices ({model.n_shape} shape + {model.n_exp} expression components), {os.cpu_count()} CPUs, load "
          f"average {os.getloadavg()[0]:.1f}; nominal rig camera error (rigidly aligned) median "
          f"{np.median(nom_err):.0f} mm, max {nom_err.max():.0f} mm; true focal "
          f"{true.camera(views[0]).focal_px:.0f} px, nominal {nominal.camera(views[0]).focal_px:.0f} px\n")
    print("| focal | wall s | CPU s | LM iterations | camera centre err median / max (mm) | flash 14 / 18 err (mm) | "
          "focal px | vertex RMS median / max (mm) | outlier recall / precision | reported centre σ median (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case, wall, cpu, ce, fe, f, vm, vx, rec, prec, its, sig in rows:
        print(f"| {case} | {wall:.1f} | {cpu:.1f} | {its} | {np.median(ce):.1f} / {ce.max():.1f} | "
              f"{fe[0]:.1f} / {fe[1]:.1f} | {f:.1f} | {vm:.2f} / {vx:.2f} | {rec:.3f} / {prec:.3f} | {sig:.1f} |")


if __name__ == "__main__":
    main()

"""Views without landmarks (issue 23 §1): the capture half with landmarks only where a detector finds a face.

One rendered world per run: a true rig (``--radius`` mm, ``--focal`` px at ``--size``), a nominal table as a user
has it (10 % too close — ``--table-distance-scale`` — positions and aims off by 3°, raised cameras another
300 mm; the focal given), GGX faces rendered by ``synth multipie`` (``--skin``, ``--features``) on the paper's 9
views + the raised 08_1 / 19_1 with the 11 default flashes, 1 px landmark noise.  Landmark sets, each through the real
chain (``preprocess-multipie --landmarks DIR`` → ``calibrate-rig`` from the nominal table → ``fit-geometry`` on
the calibrated rig):

* ``all``: the synthetic landmarks of every view (the control);
* ``side``: none on the views beyond ±30° of yaw (09_0, 08_0, 19_0, 20_0) nor on the raised 08_1 / 19_1;
* ``detect``: ``detect-landmarks`` (dlib) on the room-light images, used wherever it finds a face.

Reported per set: views with landmarks, vertex RMS (median / max over identities), its ratio to ``all``, the
camera centre error (fit-geometry's own, model space; largest over all views and over the views without
landmarks), the wall time of calibrate-rig + fit-geometry, and with ``--reflectance`` the albedo error of
``fit-reflectance`` (unwrap-uv on the paper's 9 views → fit-reflectance → evaluate truth).

    python benchmarks/bench_unmarked.py --workspace W [--identities 3] [--size 320x240] [--radius 1300]
        [--focal 500] [--skin single] [--features plain] [--seed 1] [--sets all,side,detect] [--fit-args "..."]
        [--reflectance]
        [--unwrap-views landmarks] [--unwrap-flashes landmarked] [--edge-margin M] [--table-distance-scale 0.9]
        [--cal-args "..."] [--reuse] [--detect-face-model FM] [--detect-args "..."] [--tag T]

On the workspace of such a run (sets ``all`` and ``side``), the cameras no identity annotates
(docs/benchmarks.md, "Issue 23 §1: joint registration"): ``--cameras`` (centre and aim errors per path: control,
nominal only, per identity, ``calibrate-rig --geometry`` — run here if missing — and, if ``side/fit/geo2`` holds
fit-geometry outputs on the joint rig, the joint rig fitted again), ``--objective`` (the summed joint objective
at the start, the truth, each identity's registration and the joint pose), ``--ceiling`` (the joint
registration with the faces and heads held at the truth) and ``--scale`` (the control's camera errors split
into a global scale and the rest).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sys
import time
from pathlib import Path

import numpy as np

SIDE = ("09_0", "08_0", "19_0", "20_0", "08_1", "19_1")
FIT_ARGS = "--rig-sigma 3 --rig-rot-sigma 0.3 --photo-rounds 0 --flash-rounds 3 --unmarked-sigma 100"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", required=True)
    ap.add_argument("--identities", type=int, default=3)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--radius", type=float, default=1300.0, help="camera distance of the true rig (mm)")
    ap.add_argument("--focal", type=float, default=500.0, help="focal of the true rig at --size (px)")
    ap.add_argument("--skin", default="single", choices=("single", "two-lobe"))
    ap.add_argument("--features", default="plain", choices=("plain", "painted"),
                    help="synth multipie's facial features (painted: what dlib locks onto)")
    ap.add_argument("--vertices", type=int, default=35000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sets", default="all,side,detect")
    ap.add_argument("--fit-args", default=FIT_ARGS)
    ap.add_argument("--cal-args", default="", help="extra calibrate-rig arguments (e.g. '--distance-sigma 0.01')")
    ap.add_argument("--table-distance-scale", type=float, default=0.9,
                    help="the nominal table's camera distances against the true rig's (1 = a measured distance)")
    ap.add_argument("--tag", default="", help="suffix of the result folders (to compare fit arguments)")
    ap.add_argument("--detect-face-model", default=None,
                    help="face model of the detect set (e.g. one from `face-model embed-landmarks`); the others "
                         "keep the world's")
    ap.add_argument("--detect-args", default="",
                    help="extra calibrate-rig and fit-geometry arguments of the detect set (e.g. "
                         "'--landmark-weights jaw=0')")
    ap.add_argument("--detect-fit-args", default="",
                    help="extra fit-geometry arguments of the detect set only (e.g. '--jaw-contour', with "
                         "'--landmark-weights jaw=0' for calibrate-rig in --detect-cal-args)")
    ap.add_argument("--detect-cal-args", default="",
                    help="extra calibrate-rig arguments of the detect set only")
    ap.add_argument("--raised-aim", default="kept", choices=("kept", "head"),
                    help="the nominal table's raised cameras, moved 300 mm: keep their true aim direction (may look "
                         "past the head) or look at the head from the wrong place (use with --tag)")
    ap.add_argument("--detect-synthetic", action="store_true",
                    help="the detect set with the world's synthetic landmarks (1 px noise) on exactly the views where "
                         "the detector found a face: what the view set alone costs (use with --tag)")
    ap.add_argument("--reflectance", action="store_true")
    ap.add_argument("--unwrap-flashes", default=None, choices=("landmarked",),
                    help="unwrap-uv --flashes: only the flashes on cameras that landmarks placed")
    ap.add_argument("--unwrap-views", default="default", choices=("default", "landmarks"),
                    help="views of unwrap-uv: its default (the paper's 9) or those of them with landmarks")
    ap.add_argument("--edge-margin", type=int, default=None,
                    help="unwrap-uv --edge-margin (default: unwrap-uv's own); the results go to folders ending _mM")
    ap.add_argument("--reuse", action="store_true", help="reuse the fitted geometry of an earlier run (no times)")
    ap.add_argument("--scale", action="store_true",
                    help="only the split of the control's camera errors: along / across each optical axis, distance "
                         "and face-size ratios, the error left after a similarity (set 'all' of an earlier run)")
    ap.add_argument("--objective", action="store_true",
                    help="only the summed joint objective at the start, at the true poses (mapped into the rig by "
                         "the annotated cameras), at each per-identity registration and at the joint pose")
    ap.add_argument("--ceiling", action="store_true",
                    help="only the joint registration with the faces and heads held at the truth, on the true rig, "
                         "from the true poses and from poses displaced by 50 mm / 3 deg (set 'side' of an earlier run)")
    ap.add_argument("--cameras", action="store_true",
                    help="only the camera table of an earlier run's sets 'all' and 'side': control, nominal-only, "
                         "per-identity and joint registration (calibrate-rig --geometry on the side fits)")
    ap.add_argument("--landmark-error", action="store_true",
                    help="only the detector's landmarks (lm_detect) against the truth: inner points against the "
                         "projected landmark vertices of --detect-face-model (or the world's), per group, and the "
                         "cheek points' distance across the true face's outline (fit-geometry --jaw-contour)")
    args = ap.parse_args(argv)
    if args.landmark_error:
        return landmark_error(args)
    if args.cameras:
        return camera_table(args)
    if args.ceiling:
        return ceiling(args)
    if args.scale:
        return scale_split(args)
    if args.objective:
        return objective_values(args)
    rows = run(args)
    print(f"`python benchmarks/bench_unmarked.py {' '.join(argv if argv is not None else sys.argv[1:])}` — "
          f"{args.identities} GGX identities ({args.skin} skin), {args.size}, true rig {args.radius:g} mm / focal "
          f"{args.focal:g} px; load average {os.getloadavg()[0]:.1f}\n")
    print("| landmarks | views with landmarks | vertex RMS mm (median / max) | × all-landmarks (median id) | camera "
          "centre err mm, max: all views / views without landmarks | calibrate-rig + fit-geometry s | albedo rel. "
          "err (median): observable / all texels |")
    print("|---|---|---|---|---|---|---|")
    base = rows.get("all")
    base = None if base is None or "error" in base else base
    for name, r in rows.items():
        if "error" in r:
            print(f"| {name} | refused: {r['error']} | | | | | |")
            continue
        ratio = (f"{np.median(r['vert'] / base['vert']):.2f} ({(r['vert'] / base['vert']).max():.2f} max)"
                 if base is not None else "")
        um = f"{r['cam_unmarked']:.1f}" if np.isfinite(r["cam_unmarked"]) else "–"
        secs = f"{r['seconds']:.0f}" if np.isfinite(r["seconds"]) else "–"
        alb = (f"{np.median([a for a, _ in r['albedo']]):.3f} / {np.median([b for _, b in r['albedo']]):.3f}"
               if r["albedo"] else "–")
        print(f"| {name} | {r['marked']} / {r['views']} | {np.median(r['vert']):.2f} / {r['vert'].max():.2f} | "
              f"{ratio} | {r['cam_all']:.1f} / {um} | {secs} | {alb} |")
    for name, r in rows.items():
        if "error" in r:
            continue
        print(f"\n{name}: per view (largest camera error over identities, mm; evidence of identity 001): "
              + ", ".join(f"{v} {e:.1f} ({ev})" for v, e, ev in r["per_view"]))
        if r["albedo"]:
            print(f"{name}: albedo rel. err per identity (observable / all texels): "
                  + ", ".join(f"{a:.3f} / {b:.3f}" for a, b in r["albedo"]))


def run(args) -> dict:
    from click.testing import CliRunner

    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.cli import main as cli_main
    from reflectmm_cli.geometry_fit.calibrate import perturb_rig
    from reflectmm_cli.rig import DEFAULT_FLASHES, DEFAULT_VIEWS, RAISED_CAMERAS, build_default_rig, save_rig

    ws = Path(args.workspace).resolve()
    ws.mkdir(parents=True, exist_ok=True)
    runner = CliRunner()

    def cli(*a, ok=(0,)):
        r = runner.invoke(cli_main, ["-q", *map(str, a), "-w", str(ws)], catch_exceptions=False)
        if r.exit_code not in ok:
            raise SystemExit(f"{a[0]}: {r.output}")
        return r

    W, H = (int(x) for x in args.size.lower().split("x"))
    true = build_default_rig(radius=args.radius, focal_px=args.focal, width=W, height=H)
    save_rig(true, ws / "true_rig.toml", "true rig of the benchmark")
    save_rig(perturb_rig(true, distance_scale=args.table_distance_scale, angle_deg=3.0, raised_offset_mm=300.0,
                         seed=args.seed, raised_aim=args.raised_aim),
             ws / "nominal_rig.toml", "nominal rig of the benchmark (deliberately wrong)")
    views = list(DEFAULT_VIEWS) + list(RAISED_CAMERAS)
    ids = [f"{i:03d}" for i in range(1, args.identities + 1)]
    syn = ws / "syn"
    if not (syn / "truth" / f"{ids[-1]}.npz").is_file():
        cli("synth", "multipie", "--out", syn, "--identities", args.identities, "--rig", ws / "true_rig.toml",
            "--cameras", ",".join(views), "--flashes", ",".join(DEFAULT_FLASHES), "--landmark-noise", "1.0",
            "--noise", "0.002", "--brdf", "ggx", "--skin", args.skin, "--features", args.features, "--seed", args.seed,
            "--face-vertices", args.vertices, "--image-size", f"{W}x{H}")
    lm_files = sorted(syn.rglob("*_00_lm.pts"))
    dirs = {"side": ws / "lm_side", "detect": ws / "lm_detect"}
    if not dirs["side"].is_dir():
        dirs["side"].mkdir()
        for f in lm_files:
            if not any(f.name.endswith(f"_{v.replace('_', '')}_00_lm.pts") for v in SIDE):
                shutil.copy(f, dirs["side"] / f.name)
    if not dirs["detect"].is_dir():
        rooms = sorted(p for p in syn.rglob("*_00.png") if "multiview" in str(p))
        cli("detect-landmarks", *rooms, "--out", dirs["detect"], ok=(0, 1))
    if args.detect_synthetic:
        found = {f.stem for f in dirs["detect"].glob("*.pts")}
        dirs["detect"] = ws / "lm_detect_synthetic"
        dirs["detect"].mkdir(exist_ok=True)
        for f in lm_files:
            if f.name[:-len("_lm.pts")] in found:
                shutil.copy(f, dirs["detect"] / f.name)
    rows = {}
    for name in [s for s in args.sets.split(",") if s]:
        try:
            rows[name] = _one_set(args, ws, name, dirs.get(name), ids, views, true, cli, read_artifact)
        except SystemExit as exc:  # a set the chain refuses (e.g. too few annotated cameras): say so, go on
            rows[name] = {"error": str(exc).strip().splitlines()[-1]}
    return rows


def _one_set(args, ws, name, lm_dir, ids, views, true, cli, read_artifact) -> dict:
    from reflectmm_cli.rig import DEFAULT_VIEWS

    base = ws / (name + ("_synthetic" if name == "detect" and args.detect_synthetic else ""))
    caps = []
    for i in ids:
        c = base / "cap" / f"{i}.npz"
        if not c.is_file():
            cli("preprocess-multipie", "--root", ws / "syn", "--id", i, "--views", ",".join(views), "--output", c,
                *(["--landmarks", lm_dir] if lm_dir is not None else []))
        caps.append(c)
        c9 = ws / "cap9" / f"{i}.npz"
        if args.reflectance and not c9.is_file():
            cli("preprocess-multipie", "--root", ws / "syn", "--id", i, "--views", ",".join(DEFAULT_VIEWS),
                "--output", c9)
    marked = 0
    for c in caps:  # views with landmarks (only the landmarks are read, not the image stacks)
        lm = np.asarray(read_artifact(c, "capture", members=("landmarks",))["landmarks"])
        marked += int(np.isfinite(lm).all(-1).any(-1).sum())
    out = base / f"fit{args.tag}"
    t0 = time.perf_counter()
    if args.reuse and all((out / "geo" / f"{i}.npz").is_file() for i in ids):
        geos = [read_artifact(out / "geo" / f"{i}.npz", "geometry") for i in ids]
        return _summary(args, ws, out, ids, views, geos, marked, float("nan"), cli, read_artifact)
    fm = ws / "syn" / "face_model.npz"
    extra, fit_extra = [], []
    if name == "detect":
        fm = Path(args.detect_face_model) if args.detect_face_model else fm
        extra = shlex.split(args.detect_args)
        fit_extra = shlex.split(args.detect_fit_args)
    cli("calibrate-rig", *[a for c in caps for a in ("--capture", c)], "--face-model", fm,
        "--rig", ws / "nominal_rig.toml", "--focal", true.camera("05_1").focal_px, "-o", out / "cal" / "rig.npz",
        *shlex.split(args.cal_args), *extra, *(shlex.split(args.detect_cal_args) if name == "detect" else []))
    geos = []
    for i, c in zip(ids, caps):
        g = out / "geo" / f"{i}.npz"
        cli("fit-geometry", "--id", i, "--capture", c, "--face-model", fm, "--rig",
            out / "cal" / "rig.toml", "--truth", ws / "syn" / "truth" / f"{i}.npz", "--no-overlay", "-o", g,
            *shlex.split(args.fit_args), *extra, *fit_extra)
        geos.append(read_artifact(g, "geometry"))
    return _summary(args, ws, out, ids, views, geos, marked, time.perf_counter() - t0, cli, read_artifact)


def _summary(args, ws, out, ids, views, geos, marked, seconds, cli, read_artifact) -> dict:
    from reflectmm_cli.rig import DEFAULT_VIEWS

    albedo = []
    if args.reflectance:
        for i, g in zip(ids, geos):
            sub = ("" if args.unwrap_views == "default" else "_lmviews") + \
                ("" if args.unwrap_flashes is None else f"_{args.unwrap_flashes}") + \
                ("" if args.edge_margin is None else f"_m{args.edge_margin}")
            o, mp, ev = (out / f"obs{sub}" / f"{i}.npz", out / f"maps{sub}" / f"{i}.npz",
                         out / f"eval{sub}" / f"{i}.npz")
            uv = []
            if args.unwrap_views == "landmarks":
                uv = ["--views", ",".join(str(v) for v, e in zip(g["view_names"], g["view_evidence"])
                                          if str(v) in DEFAULT_VIEWS and str(e).startswith("landmarks"))]
            if args.unwrap_flashes is not None:
                uv += ["--flashes", args.unwrap_flashes]
            if args.edge_margin is not None:
                uv += ["--edge-margin", str(args.edge_margin)]
            cli("unwrap-uv", "--id", i, "--capture", ws / "cap9" / f"{i}.npz", "--geometry", g.path, "--face-model",
                ws / "syn" / "face_model.npz", "--output", o, *uv)
            cli("fit-reflectance", "--id", i, "--input", o, "--output", mp)
            cli("evaluate", "truth", "--id", i, "--maps", mp, "--truth", ws / "syn" / "truth" / f"{i}.npz",
                "--output", ev)
            e = read_artifact(ev).meta["errors"]
            raw = (e["reflectance"] if "reflectance" in e else e)["raw"]
            albedo.append((raw["observable"]["albedo_rel"], raw["all"]["albedo_rel"]))
    cam = np.array([np.asarray(g["err_cam_center_mm"]) for g in geos])                      # (N, V)
    um = np.array([[not str(e).startswith("landmarks") for e in g["view_evidence"]] for g in geos])
    vnames = [str(v) for v in geos[0]["view_names"]]
    return {"views": len(ids) * len(views), "marked": marked,
            "vert": np.array([float(g["err_vertex_rmse_mm"]) for g in geos]),
            "cam_all": float(cam.max()), "cam_unmarked": float(cam[um].max()) if um.any() else float("nan"),
            "seconds": seconds, "albedo": albedo,
            "per_view": [(v, float(cam[:, k].max()), str(geos[0]["view_evidence"][k])) for k, v in enumerate(vnames)]}


def _aligned(centers, R, true, names, ref):
    """Centre error (mm) and optical-axis error (deg) per camera after the similarity that best aligns the centres
    of the cameras ``ref`` (bool) to the true rig's: the landmarks fix a scene only up to a similarity, so this
    measures where a camera sits relative to the annotated ones."""
    from reflectmm_cli.geometry.align import rigid_align

    ct = np.array([true.camera(n).center for n in names])
    zt = np.array([true.camera(n).R[2] for n in names])
    Ra, ta, s = rigid_align(centers[ref], ct[ref], scale=True)
    err = np.linalg.norm(s * centers @ Ra.T + ta - ct, axis=-1)
    z = np.einsum("ij,vj->vi", Ra, R[:, 2])
    return err, np.degrees(np.arccos(np.clip((z * zt).sum(-1), -1.0, 1.0)))


def camera_table(args) -> None:
    """Camera centre / aim errors of the cameras without landmarks, per path (module docstring, ``--cameras``)."""
    from click.testing import CliRunner

    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.cli import main as cli_main
    from reflectmm_cli.rig import load_rig

    ws = Path(args.workspace).resolve()
    ids = [f"{i:03d}" for i in range(1, args.identities + 1)]
    true = load_rig(ws / "true_rig.toml")
    side = ws / "side" / f"fit{args.tag}"
    joint = side / "cal_joint" / "rig.npz"
    t0 = time.perf_counter()
    if not joint.is_file():
        r = CliRunner().invoke(cli_main, ["-q", "calibrate-rig", "-w", str(ws),
                                          *[a for i in ids for a in ("--capture", ws / "side" / "cap" / f"{i}.npz")],
                                          *[a for i in ids for a in ("--geometry", side / "geo" / f"{i}.npz")],
                                          "--face-model", ws / "syn" / "face_model.npz", "--rig",
                                          ws / "nominal_rig.toml", "--focal", true.camera("05_1").focal_px,
                                          "-o", joint, *shlex.split(args.cal_args)], catch_exceptions=False)
        if r.exit_code:
            raise SystemExit(r.output)
    secs = time.perf_counter() - t0
    rows = {}
    for name, path in (("control (all landmarks)", ws / "all" / f"fit{args.tag}" / "cal" / "rig.npz"),
                       ("nominal only", side / "cal" / "rig.npz"), ("joint", joint)):
        a = read_artifact(path, "rig")
        names = [str(n) for n in a["camera_names"]]
        ref = np.array([n not in SIDE for n in names])
        rows[name] = (names, *_aligned(np.asarray(a["centers"]), np.asarray(a["R"]), true, names, ref))
        if name == "joint":
            by = a.meta["report"]["camera_placed_by"]
            place = {p["camera"]: p for p in a.meta["report"].get("camera_placement", [])}
    per = _per_identity(side / "geo", load_rig(side / "cal" / "rig.toml"), ids, true)
    again = None  # fit-geometry on the joint rig (its views registered per identity from the joint pose), if run:
    if all((side / "geo2" / f"{i}.npz").is_file() for i in ids):  # --rig side/fit/cal_joint/rig.toml -o geo2/<id>
        again = _per_identity(side / "geo2", load_rig(joint.with_suffix(".toml")), ids, true)
    per_c, per_a = np.array([p[0] for p in per]), np.array([p[1] for p in per])
    if again is not None:
        ag_c, ag_a = np.array([p[0] for p in again]), np.array([p[1] for p in again])
    print(f"`python benchmarks/bench_unmarked.py {' '.join(sys.argv[1:])}` — joint registration {secs:.0f} s "
          f"(calibrate-rig with --geometry, {len(ids)} identities); load {os.getloadavg()[0]:.1f}\n")
    print("| camera | control (all landmarks) | nominal only | per identity (median, max over ids) | joint "
          "| joint: evidence, flash RMS, σ centre mm |"
          + (" joint, then per identity (median, max) |" if again else ""))
    print("|---|---|---|---|---|---|" + ("---|" if again else ""))
    names = rows["joint"][0]
    for k, n in enumerate(names):
        if n not in SIDE:
            continue
        cells = [f"{rows[r][1][k]:.0f} mm / {rows[r][2][k]:.1f}°" for r in ("control (all landmarks)", "nominal only")]
        cells.append(f"{np.median(per_c[:, k]):.0f} ({per_c[:, k].max():.0f}) mm / {np.median(per_a[:, k]):.1f}°")
        cells.append(f"{rows['joint'][1][k]:.0f} mm / {rows['joint'][2][k]:.1f}°")
        p = place.get(n, {})
        cells.append(f"{by.get(n)}, {p.get('residual')}, {p.get('center_sigma_mm')}")
        if again is not None:
            cells.append(f"{np.median(ag_c[:, k]):.0f} ({ag_c[:, k].max():.0f}) mm / {np.median(ag_a[:, k]):.1f}°")
        print(f"| {n} | " + " | ".join(cells) + " |")
    vert = {k: np.array([float(read_artifact(d / f"{i}.npz", "geometry")["err_vertex_rmse_mm"]) for i in ids])
            for k, d in (("all", ws / "all" / f"fit{args.tag}" / "geo"), ("side", side / "geo"),
                         ("joint", side / "geo2")) if all((d / f"{i}.npz").is_file() for i in ids)}
    for k, v in vert.items():
        print(f"\nvertex RMS {k}: " + ", ".join(f"{x:.2f}" for x in v) + " mm; × all-landmarks: "
              + ", ".join(f"{x:.2f}" for x in v / vert["all"]))


def ceiling(args) -> None:
    """The joint registration's evidence without the fit's errors: each identity's face and head at the truth, the
    cameras without landmarks started at their true pose and displaced by 50 mm / 3° (random directions, --seed)."""
    from reflectmm_cli.artifacts import read_artifact, write_artifact
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.geometry.rotations import rodrigues, rotation_angle
    from reflectmm_cli.geometry_fit.joint import JointOptions, held_identity, register_jointly
    from reflectmm_cli.geometry_fit.model import ShapeModel
    from reflectmm_cli.rig import load_rig

    ws = Path(args.workspace).resolve()
    ids = [f"{i:03d}" for i in range(1, args.identities + 1)]
    true = load_rig(ws / "true_rig.toml")
    model = ShapeModel.from_face_model(load_face_model(ws / "syn" / "face_model.npz"))
    held = []
    for i in ids:  # a geometry artifact with the true face and poses (the side fit's views and landmarks)
        g = read_artifact(ws / "side" / f"fit{args.tag}" / "geo" / f"{i}.npz", "geometry")
        tr = read_artifact(ws / "syn" / "truth" / f"{i}.npz")
        tn = [str(n) for n in tr["camera_names"]]
        k = [tn.index(str(n)) for n in g["view_names"]]
        ev = np.array(["landmarks" if str(e).startswith("landmarks") else "rig" for e in g["view_evidence"]])
        arrays = {"view_names": g["view_names"], "view_evidence": ev, "K": g["K"],  # "rig": no start from the truth
                  "landmarks_given": g["landmarks_given"], "R": np.asarray(tr["R"])[k], "t": np.asarray(tr["t"])[k],
                  "shape_coeffs": tr["shape_coeffs"], "exp_coeffs": tr["exp_coeffs"]}
        path = write_artifact(ws / "ceiling" / f"{i}.npz", "geometry", arrays)
        cams = [str(n) for n, e in zip(g["view_names"], g["view_evidence"]) if not str(e).startswith("landmarks")]
        held.append(held_identity(model, ws / "side" / "cap" / f"{i}.npz", path, true, cams))
    R0 = np.array([true.camera(n).R for n in cams])
    c0 = np.array([true.camera(n).center for n in cams])
    rng = np.random.default_rng(args.seed)
    d = rng.normal(size=c0.shape)
    w = rng.normal(size=c0.shape)
    starts = {"true pose": (R0, c0),
              "50 mm / 3° off": (np.array([rodrigues(np.radians(3.0) * w[k] / np.linalg.norm(w[k])) @ R0[k]
                                           for k in range(len(cams))]),
                                 c0 + 50.0 * d / np.linalg.norm(d, axis=1, keepdims=True))}
    print(f"`python benchmarks/bench_unmarked.py {' '.join(sys.argv[1:])}` — {len(ids)} identities held at the "
          f"truth; load {os.getloadavg()[0]:.1f}\n")
    print("| start | " + " | ".join(cams) + " | s |")
    print("|---|" + "---|" * len(cams) + "---|")
    for name, (R, c) in starts.items():
        t0 = time.perf_counter()
        res = register_jointly(held, cams, R, c, JointOptions())
        e = np.linalg.norm(res.centers - c0, axis=1)
        a = [np.degrees(rotation_angle(res.R[k], R0[k])) for k in range(len(cams))]
        print(f"| {name} | " + " | ".join(f"{e[k]:.1f} mm / {a[k]:.2f}°{'' if res.accepted[k] else ' (rejected)'}"
                                          for k in range(len(cams))) + f" | {time.perf_counter() - t0:.0f} |")


def scale_split(args) -> None:
    """Per identity of set 'all': fit-geometry's camera centre errors split along / across each true optical axis,
    the fitted / true camera distance and face size, and the error after the best similarity of the centres."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry.align import rigid_align

    ws = Path(args.workspace).resolve()
    print(f"`python benchmarks/bench_unmarked.py {' '.join(sys.argv[1:])}`\n")
    print("| id | along the axis mm (+ closer) | across mm | distance ratio | face size ratio | after a similarity mm "
          "| its scale |")
    print("|---|---|---|---|---|---|---|")
    for i in [f"{i:03d}" for i in range(1, args.identities + 1)]:
        g = read_artifact(ws / "all" / f"fit{args.tag}" / "geo" / f"{i}.npz", "geometry")
        tr = read_artifact(ws / "syn" / "truth" / f"{i}.npz")
        tn = [str(n) for n in tr["camera_names"]]
        k = [tn.index(str(n)) for n in g["view_names"]]
        cf, ct, z = np.asarray(g["cam_centers"]), np.asarray(tr["cam_centers"])[k], np.asarray(tr["R"])[k][:, 2]
        d = cf - ct
        along = (d * z).sum(-1)
        across = np.linalg.norm(d - along[:, None] * z, axis=-1)
        ratio = np.linalg.norm(cf, axis=-1) / np.linalg.norm(ct, axis=-1)
        vf, vt = np.asarray(g["vertices"], np.float64), np.asarray(tr["vertices"], np.float64)
        size = np.linalg.norm(vf - vf.mean(0)) / np.linalg.norm(vt - vt.mean(0))
        R, t, s = rigid_align(cf, ct, scale=True)
        left = np.linalg.norm(s * cf @ R.T + t - ct, axis=-1)
        print(f"| {i} | {along.min():+.1f} … {along.max():+.1f} | {across.min():.1f} … {across.max():.1f} | "
              f"{ratio.min():.3f} … {ratio.max():.3f} | {size:.3f} | {left.min():.1f} … {left.max():.1f} | {s:.3f} |")


def objective_values(args) -> None:
    """The joint objective (blur 0) of set 'side' at the start (the calibrated rig), at the true poses mapped into
    the rig frame by the similarity of the annotated cameras, at each identity's own registration (moved into the
    rig by its head) and at the joint pose: whether its optimum is near the truth with the fitted faces."""
    import torch
    from scipy.spatial.transform import Rotation

    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.geometry.align import rigid_align
    from reflectmm_cli.geometry.camera import camera_centers
    from reflectmm_cli.geometry_fit.joint import JointOptions, _Shared, held_identity, joint_objective
    from reflectmm_cli.geometry_fit.model import ShapeModel
    from reflectmm_cli.rig import load_rig

    ws = Path(args.workspace).resolve()
    ids = [f"{i:03d}" for i in range(1, args.identities + 1)]
    side = ws / "side" / f"fit{args.tag}"
    rig, true = load_rig(side / "cal" / "rig.toml"), load_rig(ws / "true_rig.toml")
    model = ShapeModel.from_face_model(load_face_model(ws / "syn" / "face_model.npz"))
    cams = [n for n in SIDE if n in rig.camera_names]
    held = [held_identity(model, ws / "side" / "cap" / f"{i}.npz", side / "geo" / f"{i}.npz", rig, cams) for i in ids]
    R0, c0 = np.array([rig.camera(n).R for n in cams]), np.array([rig.camera(n).center for n in cams])
    opts = JointOptions()
    shared = _Shared(R0, c0, opts)
    for d in held:
        shared.attach(d)

    def value(R, c):
        th = np.zeros((len(cams), 6))
        th[:, 3:] = (c - c0) / opts.unit_mm
        dist = shared.dist.numpy()[:, 0]
        for k in range(len(cams)):
            th[k, :3] = Rotation.from_matrix(R[k] @ R0[k].T).as_rotvec() * dist[k] / opts.unit_mm
        with torch.no_grad():
            shared.theta.copy_(torch.as_tensor(th))
            total, _, _ = joint_objective(held, shared, 0.0, opts.w_flash)
            return float(total())

    ann = [n for n in rig.camera_names if n not in SIDE]
    Ra, ta, s = rigid_align(np.array([true.camera(n).center for n in ann]), np.array([rig.camera(n).center
                                                                                     for n in ann]), scale=True)
    rows = [("start (calibrated rig)", value(R0, c0)),
            ("true poses", value(np.array([true.camera(n).R for n in cams]) @ Ra.T,
                                 s * np.array([true.camera(n).center for n in cams]) @ Ra.T + ta))]
    for i, d in zip(ids, held):
        g = read_artifact(side / "geo" / f"{i}.npz", "geometry")
        names = [str(n) for n in g["view_names"]]
        k = [names.index(n) for n in cams]
        R, t = np.asarray(g["R"]), np.asarray(g["t"])
        rows.append((f"identity {i}'s registration", value(R[k] @ d.Rh, (camera_centers(R, t)[k] - d.th) @ d.Rh)))
    joint = side / "cal_joint" / "rig.npz"
    if joint.is_file():
        a = read_artifact(joint, "rig")
        k = [[str(n) for n in a["camera_names"]].index(n) for n in cams]
        rows.append(("joint pose", value(np.asarray(a["R"])[k], np.asarray(a["centers"])[k])))
    print(f"`python benchmarks/bench_unmarked.py {' '.join(sys.argv[1:])}` — cameras {', '.join(cams)}\n")
    print("| poses | summed objective |\n|---|---|")
    for name, v in rows:
        print(f"| {name} | {v:.1f} |")


def _per_identity(folder, cal, ids, true):
    """Per identity: its fitted cameras moved into the rig frame by its own head (from its views with landmarks,
    against the rig ``cal`` it was fitted on), then :func:`_aligned` by those views."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry.camera import camera_centers
    from reflectmm_cli.geometry_fit.init import place_by_rig

    out = []
    for i in ids:
        g = read_artifact(folder / f"{i}.npz", "geometry")
        names = [str(n) for n in g["view_names"]]
        marked = np.array([str(e).startswith("landmarks") for e in g["view_evidence"]])
        R, t = np.asarray(g["R"]), np.asarray(g["t"])
        _, _, Rh, th = place_by_rig(R, t, marked, np.array([cal.camera(n).R for n in names]),
                                    np.array([cal.camera(n).t for n in names]))
        out.append(_aligned((camera_centers(R, t) - th) @ Rh, R @ Rh, true, names, marked))
    return out


def landmark_error(args) -> None:
    """The detector's points against the truth of the world: each view's true mesh and camera."""
    from reflectmm_cli.capture.layout import camera_name
    from reflectmm_cli.geometry.camera import project
    from reflectmm_cli.geometry_fit.contour import SLIDING, jaw_contour, slide
    from reflectmm_cli.landmarks import GROUPS, read_landmarks

    ws = Path(args.workspace)
    fm = np.load(args.detect_face_model or ws / "syn" / "face_model.npz")
    L, S = fm["landmarks"], list(SLIDING)
    contour = jaw_contour(fm["mean_shape"], fm["triangles"], L)
    inner, across = [], []
    for f in sorted((ws / "lm_detect").glob("*.pts")):
        parts = f.stem.split("_")
        truth = np.load(ws / "syn" / "truth" / f"{parts[0]}.npz")
        k = [str(c) for c in truth["camera_names"]].index(camera_name(parts[3]))
        X, K, R, t = truth["vertices"].astype(np.float64), truth["K"][k], truth["R"][k], truth["t"][k]
        det = read_landmarks(f)
        inner.append(det - project(X[L], K, R, t)[0])
        across.append(slide(contour, X, K, R, t, det[S], L[S])[2])
    D, A = np.array(inner), np.array(across)
    A = A[np.isfinite(A)]  # (a point not on any outline keeps its vertex: no distance)
    print(f"{len(D)} views with the detector's landmarks; px, against the truth's projected landmark vertices")
    print("| group | RMS | per-view shift of the group (RMS) | within the group, shift removed (RMS) |")
    print("|---|---|---|---|")
    for g, (a, b) in GROUPS.items():
        x = D[:, a:b]
        shift = x.mean(1)
        print(f"| {g} | {np.sqrt((x ** 2).sum(-1).mean()):.2f} | {np.sqrt((shift ** 2).sum(-1).mean()):.2f} | "
              f"{np.sqrt(((x - shift[:, None]) ** 2).sum(-1).mean()):.2f} |")
    print(f"\ninner points (17-67) RMS {np.sqrt((D[:, 17:] ** 2).sum(-1).mean()):.2f} px; cheek points across the "
          f"true outline: median {np.median(A):.2f}, 90th percentile {np.percentile(A, 90):.2f}, max {A.max():.2f} px")


if __name__ == "__main__":
    main()

"""Benchmark of the in-the-wild inputs (issue 10): synth wild speed and accuracy, prepare-wild speed, G-buffer
size, shard loader throughput, landmark detection rate vs yaw.  Prints markdown tables and the command.

    python benchmarks/bench_wild.py [--count 24] [--size 224] [--face-vertices 35000] [--ref-pixels 200]

synth wild and prepare-wild run on one core (BLAS/OpenCV threads 1); the loader is measured with 1 and 2
reader threads.  The reference is the rendering integral summed over every pixel of the full-resolution map
with one shadow ray per map pixel (reflectmm_cli.synth.wild.reference_radiance).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _synth(out: Path, args):
    import cv2

    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.synth.wild import WildConfig, synth_wild

    cv2.setNumThreads(1)
    fm = procedural_face_model(n_vertices=args.face_vertices)
    cfg = WildConfig(count=args.count, size=args.size, envmaps=args.envmaps, seed=args.seed)
    t0 = time.perf_counter()
    summary = synth_wild(out, cfg, face_model=fm)
    return fm, cfg, summary, time.perf_counter() - t0


def _reference(out: Path, fm, cfg, n_pixels: int, images: int = 4):
    import numpy as np

    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry.gbuffer import model_to_light
    from reflectmm_cli.synth.envmaps import make_envmap
    from reflectmm_cli.synth.wild import WildSkin, reference_radiance, render_wild, sample_scene
    from reflectmm_cli.synth.wild_light import split_map

    rows = []
    for i in range(images):
        sc = sample_scene(fm, cfg, i)
        sc.envmap = sc.envmap % cfg.envmaps
        img, kind = make_envmap(cfg.seed, sc.envmap, cfg.envmap_width)
        env = split_map(img, prefilter_width=cfg.prefilter_width)
        ia = read_artifact(out / "identities" / f"id{sc.identity:05d}.npz", "wild-truth")
        skin = WildSkin(ia["vertex_albedo"], ia["vertex_roughness"], ia["vertex_spec_intensity"],
                        ia["vertex_spec_albedo"], ia["vertex_weights"], ia["vertex_skin"], {})
        r = render_wild(fm, skin, sc, env, cfg)
        gb = r["gbuffer"]
        vis = gb["visible"]
        yx = gb["pix_yx"][vis].astype(int)
        rng = np.random.default_rng(i)
        pick = rng.choice(len(yx), size=min(n_pixels // images, len(yx)), replace=False)
        ids, b = gb["vert_ids"][vis][pick], gb["bary"][vis][pick].astype(float)
        from reflectmm_cli.geometry import Camera
        cam = Camera(sc.K, sc.R, sc.t, cfg.size, cfg.size)
        ras_pos = np.einsum("pk,pkc->pc", b, r["vertices"][ids])
        nrm = np.einsum("pk,pkc->pc", b, r["scene"].normals[ids].astype(float))
        alb = np.einsum("pk,pkc->pc", b, skin.albedo[ids].astype(float))
        rho = (b * skin.spec_intensity[ids]).sum(1)
        al = (b * skin.roughness[ids]).sum(1)
        t0 = time.perf_counter()
        rd, rs = reference_radiance(r["scene"], ras_pos, nrm, cam.center, model_to_light(sc.R), env,
                                    sc.env_rotation, alb, rho, al)
        t_ref = time.perf_counter() - t0
        d = r["diffuse"][yx[pick, 0], yx[pick, 1]].astype(float)
        s = r["specular"][yx[pick, 0], yx[pick, 1]].astype(float)
        tot_ref = (rd + rs).sum(1)
        rows.append({"kind": kind, "n": len(pick), "sec": t_ref,
                     "total": np.abs((d + s).sum(1) - tot_ref) / np.maximum(tot_ref, 1e-9),
                     "diffuse": np.abs(d.sum(1) - rd.sum(1)) / np.maximum(tot_ref, 1e-9),
                     "specular": np.abs(s.sum(1) - rs.sum(1)) / np.maximum(tot_ref, 1e-9),
                     "bias": ((d + s).sum() - tot_ref.sum()) / tot_ref.sum()})
    return rows


def _prepare(out: Path, fm, cfg, tmp: Path, n_fit: int):
    import numpy as np

    from reflectmm_cli.finetune.data import (PrepareConfig, list_wild_inputs, open_shard, prepare_wild_images,
                                             prepare_wild_shard)
    from reflectmm_cli.geometry.gbuffer import GBUFFER_KEYS

    pc = PrepareConfig(size=cfg.size, from_truth=True, aligned=True, shard_size=cfg.count)
    t0 = time.perf_counter()
    path, rep, _ = prepare_wild_shard(out / "images", tmp / "shards", fm, out / "face_model.npz", pc, 0, truth_dir=out)
    t_truth = (time.perf_counter() - t0) / cfg.count
    sh = open_shard(path)
    n = len(sh)
    gb_bytes = sum(sh[k].nbytes for k in GBUFFER_KEYS) / n
    px = float(np.diff(np.asarray(sh["pix_offset"])).mean())
    # fitted geometry (landmarks + order-2 SH photometric), aligned crops
    inputs = list_wild_inputs(out / "images")[:n_fit]
    pf = PrepareConfig(size=cfg.size, aligned=True)
    t0 = time.perf_counter()
    _, rep_fit, err = prepare_wild_images(inputs, fm, pf, truth_dir=out)
    t_fit = (time.perf_counter() - t0) / max(1, len(inputs))
    return path, {"s_truth": t_truth, "s_fit": t_fit, "gb_bytes": gb_bytes, "px": px,
                  "shard_bytes": path.stat().st_size / n, "lm_fit": rep_fit["landmark_rmse_px"],
                  "vert_fit": rep_fit["vertex_error_mm"], "vert_fit_c": rep_fit.get("vertex_error_centred_mm", [])}


def _read_all(paths, epochs):
    from reflectmm_cli.finetune.shards import iter_batches, load_shards

    n = 0
    ss = load_shards(paths)  # opened (and checked) once per run, as training does
    for e in range(epochs):
        # ShardSet.batch with the linear targets: exactly what a training step reads
        for b in iter_batches(ss, 16, split=None, seed=1, epoch=e, with_target=True):
            n += len(b["names"])
            _ = float(b["images"][:, ::7, ::7].mean()) + float(b["normal"][::97].sum())
    return n


def _loader(path: Path, copies: int, tmp: Path, epochs: int = 5):
    """images/s of ShardSet.batch (the training reader) over ``copies`` copies of a shard, in 1 process and in 2 processes (2 cores)."""
    import shutil
    from concurrent.futures import ProcessPoolExecutor

    paths = []
    for c in range(copies):
        p = tmp / f"copy_{c}.npz"
        shutil.copy(path, p)
        paths.append(p)
    _read_all(paths, 1)  # warm the page cache
    out = {}
    for procs in (1, 2):
        rates = []
        for _ in range(3):
            t0 = time.perf_counter()
            with ProcessPoolExecutor(procs) as ex:
                n = sum(ex.map(_read_all, [paths[k::procs] for k in range(procs)], [epochs] * procs))
            rates.append(n / (time.perf_counter() - t0))
        out[procs] = statistics.median(rates)
    return out


def _detection(out: Path, cfg):
    import numpy as np

    from reflectmm_cli.artifacts import read_artifact, read_image_u8
    from reflectmm_cli.detection import detect_landmarks, pick_face

    man = read_artifact(out / "manifest.npz", "wild-manifest")
    rows = {}
    for n, pose in zip(man["names"].tolist(), man["pose_deg"]):
        tr = read_artifact(out / "truth" / f"{n}.npz", "wild-truth")
        f = pick_face(detect_landmarks(read_image_u8(out / "images" / f"{n}.png")))
        b = "0-15" if abs(pose[0]) < 15 else "15-30" if abs(pose[0]) < 30 else "30-50"
        r = rows.setdefault(b, {"n": 0, "hit": 0, "err": []})
        r["n"] += 1
        if f is not None:
            r["hit"] += 1
            iod = np.linalg.norm(tr["landmarks_true"][36] - tr["landmarks_true"][45])
            r["err"].append(float(np.linalg.norm(f.landmarks - tr["landmarks_true"], axis=1).mean() / iod))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=24)
    ap.add_argument("--size", type=int, default=224)
    ap.add_argument("--face-vertices", type=int, default=35000)
    ap.add_argument("--envmaps", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ref-pixels", type=int, default=200)
    ap.add_argument("--fit-images", type=int, default=6)
    args = ap.parse_args()
    import numpy as np

    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        fm, cfg, summary, wall = _synth(tmp / "wild", args)
        st = summary["stages"]
        print(f"\n### synth wild ({args.count} images, {args.size}², {fm.n_vertices} vertices, one core)\n")
        print("| quantity | value |\n|---|---|")
        print(f"| seconds per image (render + encode + write; mean over {args.count}) | "
              f"{summary['seconds_per_image']:.3f} |")
        for k, v in st.items():
            print(f"| of which {k.replace('_s', '')} | {v / args.count:.3f} s |")
        print(f"| map setup (split + prefilter), per map | {summary['envmap_setup_seconds'] / args.envmaps:.2f} s |")
        rows = _reference(tmp / "wild", fm, cfg, args.ref_pixels)
        print("\n### synth wild vs brute-force reference (every map pixel, one shadow ray each)\n")
        print("| map | pixels | median rel. error (total) | p90 | median diffuse part | median specular part | "
              "total bias | reference s |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['kind']} | {r['n']} | {np.median(r['total']):.3f} | {np.percentile(r['total'], 90):.3f} | "
                  f"{np.median(r['diffuse']):.3f} | {np.median(r['specular']):.3f} | {r['bias']:+.3f} | "
                  f"{r['sec']:.1f} |")
        path, pr = _prepare(tmp / "wild", fm, cfg, tmp, args.fit_images)
        print("\n### prepare-wild\n")
        print("| quantity | value |\n|---|---|")
        print(f"| s/image, --from-truth (G-buffer + masks + truth) | {pr['s_truth']:.3f} |")
        print(f"| s/image, fitted (landmarks + order-2 SH photometric, one view) | {pr['s_fit']:.2f} |")
        print(f"| fitted landmark RMSE median | {np.median(pr['lm_fit']):.2f} px |")
        print(f"| fitted vertex RMSE median (camera space / mean offset removed) | "
              f"{np.median(pr['vert_fit']):.1f} / {np.median(pr['vert_fit_c']) if pr['vert_fit_c'] else float('nan'):.1f} mm |")
        print(f"| face pixels per image | {pr['px']:.0f} |")
        print(f"| G-buffer bytes per image | {pr['gb_bytes'] / 1024:.0f} KiB |")
        print(f"| shard bytes per image (incl. image, masks, truth) | {pr['shard_bytes'] / 1024:.0f} KiB |")
        ld = _loader(path, 8, tmp)
        print("\n### shard loader (ShardSet.batch with targets via iter_batches, batch 16, page cache warm, process start included)\n")
        print("| reader processes | images/s |\n|---|---|")
        for k, v in ld.items():
            print(f"| {k} | {v:.0f} |")
        try:
            det = _detection(tmp / "wild", cfg)
            print("\n### dlib detection on synth wild renders\n")
            print("| abs yaw | images | detected | mean landmark error / inter-ocular |\n|---|---|---|---|")
            for b in ("0-15", "15-30", "30-50"):
                if b in det:
                    r = det[b]
                    e = f"{np.mean(r['err']):.3f}" if r["err"] else "–"
                    print(f"| {b}° | {r['n']} | {r['hit']} | {e} |")
        except Exception as exc:  # noqa: BLE001 - the extra is optional
            print(f"\n(detection skipped: {exc})")
    print(f"\ncommand: python benchmarks/bench_wild.py {' '.join(sys.argv[1:])}  (wall {wall:.0f} s for synth)")


if __name__ == "__main__":
    main()

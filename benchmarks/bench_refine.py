"""Per-image refinement (``reconstruct --refine``): PSNR and CPU time per image against the encoder alone, and the
ceiling (the same refinement with each image's true per-vertex reflectance), on the held-out wild test images of a
demo workspace (docs/benchmarks.md, "Per-image refinement").

Usage: python benchmarks/bench_refine.py [--workspace work] [--size 112|224 ...] [--threads 1]

At 112² the workspace's own shards are used. Other sizes need shards at that size: the script makes them next to the
workspace (``<ws>/bench-refine-<size>/``, or under ``--scratch``: ``synth wild`` with the workspace's face model and other seeds, then
``prepare-wild --from-truth``), once. Methods: the initial model with the control encoder (or the phase-1 encoder
when there is no control run), the finetuned model with its encoder; each encoder-only, refined from the encoder,
and refined from zero coefficients. One thread; CPU time measured per call with ``time.process_time``.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _shards(ws: Path, size: int, scratch: Path | None) -> list[Path]:
    if size == 112:
        return sorted((ws / "prepare-wild").glob("shard_*.npz"))
    d = (scratch or ws) / f"bench-refine-{size}"
    if not sorted(d.glob("prep/shard_*.npz")):
        fm = ws / "synth-multipie" / "face_model.npz"
        run = lambda *a: subprocess.run(["reflectmm", *map(str, a)], check=True)  # noqa: E731
        run("synth", "wild", "--face-model", fm, "--count", 24, "--seed", 7, "--size", size, "--envmaps", 4,
            "--out", d / "wild")
        run("prepare-wild", "--images", d / "wild" / "images", "--truth", d / "wild", "--face-model", fm,
            "--from-truth", "--size", size, "--encoding", "gamma1.2", "--out", d / "prep")
    return sorted(d.glob("prep/shard_*.npz"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=Path("work"))
    ap.add_argument("--size", type=int, nargs="+", default=[112, 224])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--scratch", type=Path, default=None, help="where shards of other sizes go (default: the ws)")
    a = ap.parse_args()
    import torch

    from reflectmm_cli.evaluation.reconstruction_eval import image_metrics_table
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.reconstruct import reconstruct, reconstruct_truth
    from reflectmm_cli.finetune.refine import RefineConfig
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import load_models

    torch.set_num_threads(a.threads)
    ws = a.workspace
    light = ws / "build-light-pca" / "build-light-pca.npz"
    ctrl = ws / "finetune-control" / "finetune-control_encoder.safetensors"
    init_enc = ctrl if ctrl.is_file() else ws / "finetune" / "finetune_encoder_phase1.safetensors"
    methods = [("initial", ws / "build-pca" / "build-pca.npz", init_enc),
               ("finetuned", ws / "finetune" / "finetune.npz", ws / "finetune" / "finetune_encoder.safetensors")]
    cfg = RefineConfig()
    print("| size | model | start | PSNR (dB) | SSIM | CPU s / image | % of ceiling |")
    print("|---|---|---|---|---|---|---|")
    for size in a.size:
        ss = load_shards(_shards(ws, size, a.scratch))
        split = "test" if len(ss.indices("test")) else None

        def score(rec):
            fm = image_metrics_table(rec.full, rec.image, rec.face_mask, str(rec.encoding[0]))["per_image"]
            return float(np.mean(fm.per_image["psnr"])), float(np.mean(fm.per_image["ssim"]))

        m0, lt = load_models(methods[0][1], light)
        t = time.process_time()
        rec = reconstruct_truth(ss, lt, m0.exponents, cfg, split=split)
        ceil_t = (time.process_time() - t) / len(rec.names)
        ceil = score(rec)
        rows = []
        for name, model, enc in methods:
            m, lt = load_models(model, light)
            e = load_encoder(enc, "cpu")[0]
            for start, kw in (("encoder only", dict(encoder=e)), ("encoder + refine", dict(encoder=e, refine=cfg)),
                              ("zero + refine", dict(encoder=None, refine=cfg))):
                t = time.process_time()
                rec = reconstruct(ss, kw["encoder"], m, lt, split=split, refine=kw.get("refine"))
                dt = (time.process_time() - t) / len(rec.names)
                p, s = score(rec)
                rows.append((name, start, p, s, dt))
        for name, start, p, s, dt in rows:
            print(f"| {size}² | {name} | {start} | {p:.2f} | {s:.3f} | {dt:.3f} | {100 * p / ceil[0]:.0f} % |")
        print(f"| {size}² | true reflectance | zero + refine (ceiling) | {ceil[0]:.2f} | {ceil[1]:.3f} | "
              f"{ceil_t:.3f} | 100 % |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark of the reflectance model and the evaluation (issue 6): PCA build time against N at UV 256, and the
representation comparison (time and the table itself) on GGX-rendered synthetic observations.

    python benchmarks/bench_model.py [--size 256] [--ns 8,25,50,100] [--rep-size 64] [--rep-ids 3] [--repeat 3]

Prints markdown tables (medians of --repeat runs) and the command line that produced them.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np


def _median_time(fn, repeat):
    ts = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def bench_pca(size, ns, repeat):
    from reflectmm_cli.model import add_vertex_model, fit_reflectance_pca, sample_model

    rng = np.random.default_rng(0)
    S = size
    yy, xx = np.mgrid[0:S, 0:S]
    mask = ((xx - S / 2 + 0.5) / (0.5 * S)) ** 2 + ((yy - S / 2 + 0.5) / (0.5 * S)) ** 2 <= 1
    rows = ["| N | UV | components | PCA build (s) | thin SVD of the same data (s) | speed-up | "
            "+ vertex model, 35k vertices (s) | sample_model UV (ms) |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    uv = rng.uniform(0, 1, (35709, 2))
    for n in ns:
        A = [(rng.uniform(0.1, 0.8, (3, S, S)) * mask).astype(np.float32) for _ in range(n)]
        W = [(rng.uniform(0.0, 0.2, (3, S, S)) * mask).astype(np.float32) for _ in range(n)]
        t, m = _median_time(lambda: fit_reflectance_pca(A, W, (1, 8, 64), masks=[mask] * n, components=80), repeat)
        X = np.stack([a[:, mask].reshape(-1) for a in A]).astype(np.float64)
        X -= X.mean(0)
        tsvd, _ = _median_time(lambda: np.linalg.svd(X, full_matrices=False), repeat)
        del X
        tv, _ = _median_time(lambda: add_vertex_model(m, uv), 1)
        beta = rng.normal(size=m.n_components)
        ts, _ = _median_time(lambda: sample_model(m, beta), max(repeat, 3))
        rows.append(f"| {n} | {S} | {m.n_components} | {t:.2f} | {tsvd:.2f} | {tsvd / t:.1f}× | {tv:.2f} | "
                    f"{1000 * ts:.1f} |")
        del A, W, m
    return "\n".join(rows)


def bench_representation(size, n_ids, repeat, noise):
    from reflectmm_cli.evaluation.representation import (compare_representations, default_representations,
                                                         margin_of_multilobe, markdown_table)
    from reflectmm_cli.evaluation.synthetic import simulate_ggx_observations

    obs = [simulate_ggx_observations(size=size, seed=s, noise=noise)[0] for s in range(n_ids)]
    reps = default_representations("8;16;32;64;1,8,64")
    t, res = _median_time(lambda: compare_representations(obs, [f"{i:03d}" for i in range(n_ids)], reps), repeat)
    mg = margin_of_multilobe(res)
    text = markdown_table(res)
    text += (f"\nWhole comparison: {t:.1f} s for {n_ids} identities × {len(reps)} representations at UV {size} "
             f"(median of {repeat}). {mg['multilobe']} vs best global exponent ({mg['best_global']}): "
             f"{mg['psnr_margin_db']:+.2f} dB PSNR, {mg['ssim_margin']:+.5f} SSIM; beats every global exponent: "
             f"PSNR {mg['beats_every_global_psnr']}, SSIM {mg['beats_every_global_ssim']}; 3-lobe best in "
             f"{mg['identities_where_multilobe_wins_psnr']}/{n_ids} identities.\n")
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ns", default="8,25,50,100")
    ap.add_argument("--rep-size", type=int, default=64)
    ap.add_argument("--rep-ids", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--noise", default="0,0.01", help="multiplicative radiance noise levels (comma separated)")
    ap.add_argument("--skip-pca", action="store_true")
    ap.add_argument("--skip-rep", action="store_true")
    a = ap.parse_args(argv)
    print(f"`python benchmarks/bench_model.py {' '.join(sys.argv[1:])}` — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, numpy {np.__version__}\n")
    if not a.skip_pca:
        print("### PCA build\n")
        print(bench_pca(a.size, [int(x) for x in a.ns.split(",")], a.repeat))
        print()
    if not a.skip_rep:
        for nz in (float(x) for x in a.noise.split(",")):
            print(f"### Representation comparison (GGX truth, noise {100 * nz:g} %)\n")
            print(bench_representation(a.rep_size, a.rep_ids, max(1, a.repeat // 3), nz))


if __name__ == "__main__":
    main()

"""Benchmark of the Table 2 / Table 3 / relighting evaluation library (issue 12): cost of the face-region metrics
per image at 224², of the released batch protocol, of the Table 3 coefficient fit (normal equations over all
observed pairs) per identity and model, and of relighting one reconstruction under the held-out flashes.

    python benchmarks/bench_evaluation.py [--images 32] [--uv 64] [--components 80] [--repeat 3]

Prints markdown tables (medians of --repeat runs) and the command line that produced them.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np


def _median_time(fn, repeat):
    ts, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def bench_metrics(n, repeat):
    from reflectmm_cli.evaluation.face_metrics import face_region_metrics, released_protocol

    rng = np.random.default_rng(0)
    S = 224
    t = rng.uniform(0.1, 0.9, (n, S, S, 3))
    p = np.clip(t + rng.normal(0, 0.03, t.shape), 0, 1)
    yy, xx = np.mgrid[:S, :S]
    m = np.broadcast_to(((yy - 112) / 90.0) ** 2 + ((xx - 112) / 70.0) ** 2 < 1, (n, S, S))
    tf, _ = _median_time(lambda: face_region_metrics(p, t, m), repeat)
    tr, _ = _median_time(lambda: released_protocol(p ** 1.2, t, m, batch_size=32), repeat)
    return ["| step | images | total (s) | per image (ms) |", "|---|---:|---:|---:|",
            f"| per-image PSNR + SSIM (11×11) + t-CI | {n} | {tf:.2f} | {1000 * tf / n:.1f} |",
            f"| released protocol (PSNR + SSIM window 3, batches of 32) | {n} | {tr:.2f} | {1000 * tr / n:.1f} |"]


def bench_albedo(uv, comps, repeat):
    from reflectmm_cli.evaluation.albedo_eval import fit_coefficients, observation_normal_equations
    from reflectmm_cli.model.pca import fit_reflectance_pca
    from reflectmm_cli.reflectance.simulate import simulate_observations

    n_id = comps + 1
    rng = np.random.default_rng(1)
    obs, tr = simulate_observations(size=uv, seed=0, return_truth=True, dtype=np.float32)
    A = [np.clip(tr["albedo"] * rng.uniform(0.7, 1.3, (3, 1, 1)) + rng.normal(0, 0.02, tr["albedo"].shape), 0, 1)
         for _ in range(n_id)]
    W = [np.clip(tr["weights"] * rng.uniform(0.5, 1.5, (3, 1, 1)), 0, None) for _ in range(n_id)]
    model = fit_reflectance_pca(A, W, (1.0, 8.0, 64.0), masks=[obs["mask"]] * n_id, components=comps)
    J = len(obs["pair_flash"])
    tn, ne = _median_time(lambda: observation_normal_equations(model, obs), repeat)
    ts, _ = _median_time(lambda: fit_coefficients(model, obs, equations=ne), repeat)
    return ["| UV | pairs | components | observed rows | normal equations (s) | solve (ms) |",
            "|---:|---:|---:|---:|---:|---:|",
            f"| {uv} | {J} | {model.n_components} | {ne.n} | {tn:.2f} | {1000 * ts:.1f} |"]


def bench_relight(repeat):
    from reflectmm_cli.evaluation.relighting import RelightScene, relight
    from reflectmm_cli.geometry import has_embree, look_at, procedural_face_model

    if not has_embree():
        return ["(relighting skipped: no Embree)"]
    fm = procedural_face_model(n_vertices=35000)
    v = fm.mean_shape.astype(np.float64)
    cam = look_at((0.0, 10.0, 650.0), (0.0, 10.0, 0.0), focal_px=700.0, width=224, height=224)
    pos = np.array([[0.0, 50.0, 900.0], [350.0, 80.0, 700.0], [-450.0, 0.0, 500.0]])
    fids = ["07", "05", "11"]
    albedo = np.full((len(v), 3), 0.4)
    weights = np.full((len(v), 3), 0.02)

    def run():
        rs = RelightScene(v, fm.triangles, cam, pos, np.full(3, 1e6), fids)
        return relight(rs, albedo, weights, [1.0, 8.0, 64.0], fids)

    t, _ = _median_time(run, repeat)
    return ["| mesh vertices | image | flashes | scene + shadows + renders (s) |", "|---:|---:|---:|---:|",
            f"| {len(v)} | 224² | 3 | {t:.2f} |"]


def table3_synthetic(size, n_train, n_test, comps):
    """Table 3 on GGX-rendered identities: ours = PCA of 3-lobe maps fitted by fit-reflectance to each training
    identity's observations; baselines = PCAs of the training identities' ground truth; all fitted to held-out
    identities' observations."""
    from reflectmm_cli.evaluation.albedo_eval import albedo_table_rows, evaluate_albedo
    from reflectmm_cli.evaluation.baselines import diffuse_only_model, global_exponent_model
    from reflectmm_cli.evaluation.synthetic import simulate_ggx_observations
    from reflectmm_cli.model.pca import fit_reflectance_pca
    from reflectmm_cli.reflectance import fit_maps

    train = [simulate_ggx_observations(size=size, seed=s) for s in range(n_train)]
    test = {f"t{s}": simulate_ggx_observations(size=size, seed=1000 + s) for s in range(n_test)}
    t0 = time.perf_counter()
    maps = [fit_maps(o, exponents=(1.0, 8.0, 64.0)) for o, _ in train]
    t_fit = time.perf_counter() - t0
    truths = [dict(t, uv_mask=np.asarray(o["mask"], bool)) for o, t in train]
    masks = [np.asarray(o["mask"], bool) for o, _ in train]
    models = {"ours (3-lobe, fitted maps)": fit_reflectance_pca([m.albedo for m in maps], [m.weights for m in maps],
                                                                (1.0, 8.0, 64.0), masks=masks, components=comps),
              "AlbedoMM role (truth, p=20)": global_exponent_model(truths, components=comps),
              "BFM09 role (truth, diffuse)": diffuse_only_model(truths, components=comps)}
    ids = {k: (o, dict(t, uv_mask=np.asarray(o["mask"], bool))) for k, (o, t) in test.items()}
    t0 = time.perf_counter()
    res = evaluate_albedo(models, ids, oracle=True)
    t_eval = time.perf_counter() - t0
    rows = ["| model | diffuse PSNR raw (dB) | specular PSNR raw (dB) | diffuse rel (scaled) | specular rel (scaled) |",
            "|---|---:|---:|---:|---:|"]
    for r in albedo_table_rows(res):
        c = lambda k, d=2: f"{r[k]['mean']:.{d}f} ± {r[k]['half_width']:.{d}f}"  # noqa: E731
        rows.append(f"| {r['model']} | {c('raw.diffuse_psnr')} | {c('raw.specular_psnr')} | "
                    f"{c('scaled.diffuse_rel', 3)} | {c('scaled.specular_rel', 3)} |")
    rows.append(f"\n{n_train} training / {n_test} held-out GGX identities, UV {size}, {comps} components; "
                f"fit-reflectance {t_fit:.1f} s, evaluation {t_eval:.1f} s")
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=int, default=32)
    ap.add_argument("--uv", type=int, default=64)
    ap.add_argument("--components", type=int, default=80)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--table3", action="store_true", help="also run Table 3 on GGX-rendered identities")
    ap.add_argument("--t3-size", type=int, default=32)
    ap.add_argument("--t3-train", type=int, default=8)
    ap.add_argument("--t3-test", type=int, default=4)
    a = ap.parse_args()
    print(f"# bench_evaluation — {platform.processor() or platform.machine()}, python {platform.python_version()}")
    print("command: python " + " ".join(sys.argv))
    for title, rows in (("Face-region metrics at 224²", bench_metrics(a.images, a.repeat)),
                        ("Table 3 coefficient fit (one identity, one model)",
                         bench_albedo(a.uv, a.components, a.repeat)),
                        ("Relighting one reconstruction", bench_relight(a.repeat))):
        print(f"\n## {title}\n")
        print("\n".join(rows))
    if a.table3:
        print("\n## Table 3 on GGX-rendered identities\n")
        print("\n".join(table3_synthetic(a.t3_size, a.t3_train, a.t3_test, a.t3_train - 1)))


if __name__ == "__main__":
    main()

"""Benchmark of one finetuning step (issue 11). Prints a markdown report on stdout.

    python benchmarks/bench_finetune.py            # resnet18 and resnet50, 224², batch 8 (~1–2 min on 2 cores)
    python benchmarks/bench_finetune.py --quick    # resnet18 only, 2 repetitions

Setup (the paper's sizes): a face mesh of ~35k vertices (a tessellated spherical cap) ray-cast once at 224² (≈ the
face pixels of an aligned crop), a per-vertex model with M = 80 components and 3 lobes, an order-8 light model with
N_L = 80, batch 8, phase 2 (encoder and model both trained: the more expensive phase). Each arch runs in its own
process so its peak memory (max RSS) is its own. Times are medians of repeated steps after one warm-up step:
loading (batch assembly from the in-memory shard + tensors), encoder forward+backward (surrogate gradient on its
outputs), shading + photometric loss forward+backward (encoder outputs as leaves; the G-buffer SH bases cached as in
training), the other losses (L_upd over the whole model, L_coef, L_light) forward+backward,
optimiser (Adam on encoder and model), and a real full step for comparison.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests", "finetune"))


def _setup(size=224, batch=8, mesh_n=187, M=80, NL=80):
    from _shards import cap_mesh, gbuffer

    from reflectmm_cli.finetune.shards import ShardSet
    from reflectmm_cli.model.pca import ReflectanceModel
    from reflectmm_cli.model.light import LightModel

    rng = np.random.default_rng(0)
    V, tri, _ = cap_mesh(mesh_n)
    gb = gbuffer(V, tri, size, distance=330.0, frame=1.1)
    nv, P = V.shape[0], len(gb["pix_yx"])
    S = 4
    q, _ = np.linalg.qr(rng.normal(size=(nv * 3, M)))
    model = ReflectanceModel(
        albedo_mean=np.zeros((3, S, S), np.float32), albedo_basis=np.zeros((M, 3, S, S), np.float32),
        weights_mean=np.zeros((3, S, S), np.float32), weights_basis=np.zeros((M, 3, S, S), np.float32),
        sigma=np.linspace(3, 0.3, M).astype(np.float32), explained_variance=np.ones(M, np.float32),
        explained_variance_ratio=np.ones(M, np.float32) / M, exponents=np.array([1, 8, 64], np.float32),
        mask=np.ones((S, S), bool), train_coeffs=np.zeros((2, M), np.float32), ids=["a", "b"],
        vertex_albedo_mean=np.full((nv, 3), 0.5, np.float32), vertex_albedo_basis=q.T.reshape(M, nv, 3).astype(
            np.float32), vertex_weights_mean=np.full((nv, 3), 0.03, np.float32),
        vertex_weights_basis=(0.003 * rng.normal(size=(M, nv, 3))).astype(np.float32))
    n = 81
    mean = np.zeros((3, n))
    mean[:, 0] = 1
    b = np.linalg.qr(rng.normal(size=(3 * n, NL)))[0].T
    light = LightModel(order=8, mean=mean.ravel(), bases=b, sigma=np.linspace(0.5, 0.01, NL),
                       explained_variance=np.ones(NL), explained_variance_ratio=np.ones(NL) / NL, dc=np.ones((1, 3)),
                       sample_map=np.zeros(1, int), sample_rotation=np.eye(3)[None], map_names=["a"])
    N = batch
    img = rng.integers(0, 255, (N, size, size, 3), dtype=np.uint8)
    ss = ShardSet(names=np.array([f"i{i}" for i in range(N)]), split=np.array(["train"] * N), image=img,
                  face_mask=np.repeat(gb["mask"][None], N, 0), skin_mask=np.repeat(gb["mask"][None], N, 0),
                  pix_offset=np.arange(N + 1, dtype=np.int64) * P, pix_yx=np.tile(gb["pix_yx"], (N, 1)),
                  vert_ids=np.tile(gb["vert_ids"], (N, 1)), bary=np.tile(gb["bary"], (N, 1)),
                  normal=np.tile(gb["normal"], (N, 1)).astype(np.float16),
                  view=np.tile(gb["view"], (N, 1)).astype(np.float16), visible=np.tile(gb["visible"], N),
                  encoding=np.full(N, "gamma1.2"), size=size, sh_order=8)
    return ss, model, light, {"vertices": nv, "face_pixels_per_image": P, "components": M, "light_components": NL}


def run_arch(arch: str, reps: int, batch: int) -> dict:
    import torch

    from reflectmm_cli.finetune import losses as L
    from reflectmm_cli.finetune.config import FinetuneConfig
    from reflectmm_cli.finetune.render import batch_gbuffer, lighting, shade_gbuffer
    from reflectmm_cli.finetune.train import Trainer

    torch.set_num_threads(2)
    ss, model, light, info = _setup(batch=batch)
    cfg = FinetuneConfig(arch=arch, epochs1=0, epochs2=1, batch_size=batch)
    tr = Trainer(ss, model, light, cfg, "/tmp/bench_finetune_work", progress=False)
    tr._enter_phase2()
    idx = np.arange(batch)
    T = {k: [] for k in ("loading", "encoder", "shading", "losses", "optimiser", "full_step")}
    b = ss.batch(idx)
    x = torch.as_tensor(b["images"]).permute(0, 3, 1, 2).float() / 255.0

    def encoder_pass():
        t1 = time.perf_counter()
        beta, gamma, z = tr.encoder(x)
        torch.autograd.backward([beta, gamma, z], [torch.full_like(beta, 1e-3), torch.full_like(gamma, 1e-3),
                                                   torch.full_like(z, 1e-3)])
        return time.perf_counter() - t1, (beta, gamma, z)

    def shading_pass(outs):
        t0 = time.perf_counter()
        b = ss.batch(idx)
        gb = batch_gbuffer(b)
        torch.as_tensor(b["images"]).permute(0, 3, 1, 2).float() / 255.0
        t2 = time.perf_counter()
        bl, gl, zl = (v.detach().requires_grad_(True) for v in outs)
        sh = lighting(light, gl, zl)
        # as in training: each image's SH basis is evaluated on first use and cached (the warm-up pass fills it)
        d, s, _, _ = shade_gbuffer(tr.params, bl, sh, gb, bases=tr._bases(idx, gb, 8), check_finite=False)
        (2 * L.photometric(d + s, gb.target, gb.skin)).backward()
        t3 = time.perf_counter()
        # the other losses in their own backward pass (gradients add up as in one pass), timed separately
        cur = dict(zip(("albedo_mean", "albedo_basis", "weights_mean", "weights_basis"), tr.params.effective()))
        loss = (1e-3 * L.coefficient_prior(bl, gl) + 10 * L.light_monochrome(lighting(light, gl, zl))
                + 10 * L.model_update_l1(cur, tr.initial))
        loss.backward()
        t4 = time.perf_counter()
        tr.opt.step()
        tr.opt.zero_grad(set_to_none=True)
        return t2 - t0, t3 - t2, t4 - t3, time.perf_counter() - t4

    # encoder and shading passes alternate, so both see the same machine load (the ratio is what matters)
    for r in range(reps + 1):
        te, outs = encoder_pass()
        parts = [shading_pass(outs) for _ in range(2)]
        if r:
            T["encoder"].append(te)
            for p_ in parts:
                for k, v in zip(("loading", "shading", "losses", "optimiser"), p_):
                    T[k].append(v)
    for r in range(max(2, reps - 1)):  # real steps
        t4 = time.perf_counter()
        total, _, _ = tr._forward(idx, True)
        total.backward()
        tr.opt.step()
        tr.opt.zero_grad(set_to_none=True)
        T["full_step"].append(time.perf_counter() - t4)
    med = {k: statistics.median(v) for k, v in T.items()}
    med["shading_losses"] = statistics.median([a + b for a, b in zip(T["shading"], T["losses"])])
    parts = sum(med[k] for k in ("loading", "encoder", "shading", "losses", "optimiser"))
    enc_params = sum(p.numel() for p in tr.encoder.parameters())
    model_params = sum(p.numel() for p in tr.params.parameters())
    return {"arch": arch, "batch": batch, **info, "median_s": med, "sum_of_parts_s": parts,
            "shading_losses_share": med["shading_losses"] / parts, "images_per_s": batch / med["full_step"],
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "encoder_params": enc_params,
            "model_params": model_params, "reps": reps, "load_average": os.getloadavg()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--arch", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--compare-thp", action="store_true",
                    help="also run each arch with THP_MEM_ALLOC_ENABLE=0 (4 KiB pages for torch's large buffers)")
    a = ap.parse_args()
    if a.arch:
        print(json.dumps(run_arch(a.arch, a.reps, a.batch)))
        return
    archs = ["resnet18"] if a.quick else ["resnet18", "resnet50"]
    reps = 2 if a.quick else a.reps
    rows = []
    for arch in archs:
        for thp in (("1", "0") if a.compare_thp else (os.environ.get("THP_MEM_ALLOC_ENABLE", "1"),)):
            env = {**os.environ, "THP_MEM_ALLOC_ENABLE": thp}
            out = subprocess.run([sys.executable, __file__, "--arch", arch, "--reps", str(reps), "--batch",
                                  str(a.batch)], check=True, capture_output=True, text=True, env=env).stdout
            rows.append({**json.loads(out.strip().splitlines()[-1]), "thp": thp})
    r0 = rows[0]
    print(f"Finetuning step, phase 2, batch {r0['batch']}, 224², {r0['vertices']} vertices, "
          f"{r0['face_pixels_per_image']} face pixels/image, M = {r0['components']}, N_L = {r0['light_components']}, "
          f"order-8 SH, 2 threads; medians of {reps} encoder passes and {2 * reps} shading/loss/optimiser passes "
          f"(interleaved), {max(2, reps - 1)} real steps; "
          f"load average during the runs "
          + ", ".join("%.1f" % r["load_average"][0] for r in rows) + ".\n")
    print("| arch | huge pages | loading | encoder fwd+bwd | shading + L_photo fwd+bwd | "
          "L_upd + L_coef + L_light fwd+bwd | optimiser | full step | shading+losses share | images/s | peak RSS |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        m = r["median_s"]
        print(f"| {r['arch']} | {'on' if r['thp'] != '0' else 'off'} | {m['loading'] * 1e3:.0f} ms | "
              f"{m['encoder'] * 1e3:.0f} ms | {m['shading'] * 1e3:.0f} ms | {m['losses'] * 1e3:.0f} ms | "
              f"{m['optimiser'] * 1e3:.0f} ms | {m['full_step'] * 1e3:.0f} ms | "
              f"{100 * r['shading_losses_share']:.1f} % | {r['images_per_s']:.2f} | {r['peak_rss_mb']:.0f} MB |")
    print()
    for r in rows[::2 if a.compare_thp else 1]:
        print(f"- {r['arch']}: {r['encoder_params'] / 1e6:.1f} M encoder parameters, "
              f"{r['model_params'] / 1e6:.1f} M model parameters (phase 2)")


if __name__ == "__main__":
    main()

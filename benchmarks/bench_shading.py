"""Benchmarks of the shading core (issue 3). Prints a markdown report on stdout.

    python benchmarks/bench_shading.py            # full run (~1–2 min on 2 cores)
    python benchmarks/bench_shading.py --quick    # smaller sizes, for a smoke test
    python benchmarks/bench_shading.py --only speed --compare-old /tmp/env_old.py   # old vs new, same run
    python benchmarks/bench_shading.py --only kernels   # compiled (numba) vs numpy kernel, same run, JIT times

Sections:
1. accuracy of ``shade_env`` (SH order × lobe exponent × view angle) against brute-force integration of the
   *true* half-vector Blinn-Phong lobe over procedural HDR environment maps;
2. throughput of ``shade_env`` (order 8, 3 lobes, float32) against a roofline of this machine (the kernel's own
   operation counts and the measured rate of each operation at the kernel's block size); with
   ``--compare-old FILE`` also a copy of an earlier ``reflectmm_cli/shading/env.py`` (imported from its path),
   timed interleaved with the current one in the same process; and the compiled (numba) kernel against the
   blocked numpy kernel, interleaved, with its JIT compile and cache-load times (``--only kernels`` alone);
3. what skipping buys (band truncation, zero-weight lobes, masks, back-facing texels);
4. equirectangular projection (2048×1024) against ducc0.
All timings are medians of repeated runs.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from reflectmm_cli.shading import (  # noqa: E402
    blinn_phong_norm,
    envmap_from_sh,
    equirect_directions,
    equirect_weights,
    project_envmap,
    shade_env,
)

EXPONENTS = (1.0, 8.0, 64.0)


CPU_TIMES = {}


def median_time(fn, repeat=5, warmup=1, label=None):
    """Median wall time; the median CPU time (all threads of this process) is kept in CPU_TIMES[label]."""
    for _ in range(warmup):
        fn()
    ts, cs = [], []
    for _ in range(repeat):
        c = time.process_time()
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    if label is not None:
        CPU_TIMES[label] = statistics.median(cs)
    return statistics.median(ts)


# ------------------------------------------------------------------------------------------------ env maps


def procedural_envmaps(width, height, seed=0, count=3):
    """Sky gradient + sun(s) + a coloured ground: smooth to sharp HDR maps, (H, W, 3) float64."""
    rng = np.random.default_rng(seed)
    d = equirect_directions(width, height)
    maps = []
    for k in range(count):
        up = np.clip(d[..., 1], -1, 1)[..., None]
        sky = np.where(up > 0, 0.3 + 0.5 * up * np.array([0.6, 0.8, 1.0]), 0.15 * np.array([0.5, 0.4, 0.3]))
        img = sky.copy()
        for _ in range(1 + k):
            s = rng.normal(size=3)
            s[1] = abs(s[1]) + 0.3
            s /= np.linalg.norm(s)
            sharp = [200.0, 2000.0, 20000.0][k % 3]
            img += rng.uniform(2, 10) * np.maximum(d @ s, 0)[..., None] ** sharp * rng.uniform(0.7, 1.0, 3)
        maps.append(img)
    return maps


# ------------------------------------------------------------------------------------------------ 1. accuracy


def brute_force_specular(img, n, v, p):
    """∫ L(l) f (n·h)^p [n·l > 0] dω over every pixel of the map (true half-vector lobe, unit weight)."""
    H, W, _ = img.shape
    d = equirect_directions(W, H).reshape(-1, 3)
    dw = np.repeat(equirect_weights(W, H, "area"), W)
    L = img.reshape(-1, 3) * dw[:, None]
    f = float(blinn_phong_norm(p))
    out = np.zeros((n.shape[0], 3))
    for i in range(n.shape[0]):
        ndl = d @ n[i]
        h = d + v[i]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        ndh = np.maximum(h @ n[i], 0)
        wgt = np.where(ndl > 0, f * ndh ** p, 0.0)
        out[i] = wgt @ L
    return out


def load_maps(paths, W, H):
    """Real HDR maps (EXR/HDR), box-downsampled to W×H (the map must be an integer multiple of it or larger)."""
    from reflectmm_cli.artifacts import read_image
    from reflectmm_cli.model.light import find_envmaps

    out = []
    for f in find_envmaps(paths):
        img = read_image(f)[..., :3].astype(np.float64)
        h, w = img.shape[:2]
        fy, fx = max(1, h // H), max(1, w // W)
        img = img[: fy * H, : fx * W].reshape(H, fy, W, fx, 3).mean((1, 3)) if h >= H and w >= W else img
        if img.shape[:2] == (H, W) and np.isfinite(img).all():
            out.append(img)
    if not out:
        raise SystemExit(f"no usable maps of at least {W}x{H} in {paths}")
    return out


def accuracy(quick, maps_from=None):
    W, H = (128, 64) if quick else (256, 128)
    maps = load_maps(maps_from, W, H) if maps_from else procedural_envmaps(W, H, count=2 if quick else 3)
    orders = (2, 4, 6, 8, 12)
    angles = (0, 30, 60, 80) if quick else (0, 15, 30, 45, 60, 75, 85)
    nsamp = 12 if quick else 24
    rng = np.random.default_rng(5)
    rows = {}
    lobe_only = {}
    for mi, img in enumerate(maps):
        coeffs = {L: project_envmap(img, L, quadrature="area") for L in orders}
        n = rng.normal(size=(nsamp, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        for ang in angles:
            # view at angle `ang` from the normal, random azimuth
            t = rng.normal(size=(nsamp, 3))
            t -= (t * n).sum(1, keepdims=True) * n
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            a = math.radians(ang)
            v = math.cos(a) * n + math.sin(a) * t
            for p in EXPONENTS:
                truth = brute_force_specular(img, n, v, p)
                for L in orders:
                    _, s = shade_env(np.zeros((nsamp, 3)), np.ones((nsamp, 1)), [p], n, v, coeffs[L])
                    err = np.sqrt(((s - truth) ** 2).mean()) / np.sqrt((truth ** 2).mean())
                    rows.setdefault((p, L, ang), []).append(err)
                _, s = shade_env(np.zeros((nsamp, 3)), np.ones((nsamp, 1)), [p], n, v, coeffs[8],
                                 view_correction=True)
                rows.setdefault((p, "vc", ang), []).append(
                    np.sqrt(((s - truth) ** 2).mean()) / np.sqrt((truth ** 2).mean()))
                # lobe-shape error alone: order-12 band-limited lighting, brute force over its own map
                bl = envmap_from_sh(coeffs[12], W, H).astype(np.float64)
                truth_bl = brute_force_specular(bl, n, v, p)
                _, s = shade_env(np.zeros((nsamp, 3)), np.ones((nsamp, 1)), [p], n, v, coeffs[12])
                lobe_only.setdefault((p, ang), []).append(
                    np.sqrt(((s - truth_bl) ** 2).mean()) / np.sqrt((truth_bl ** 2).mean()))
    out = [f"### 1. Specular accuracy vs the true half-vector lobe\n",
           f"Relative RMS error of `shade_env` specular (unit weight) against brute-force integration of the true "
           f"lobe `f (n·h)^p [n·l>0]` over every pixel of {len(maps)} "
           + (f"HDR maps from {maps_from} ({W}×{H})" if maps_from else
              f"procedural HDR maps ({W}×{H}: sky, ground, 1–3 suns of increasing sharpness)")
           + f", {nsamp} random normals per map and view angle; median over maps. "
           f"Error includes SH truncation of the lighting and the lobe-shape approximation. The last column is "
           f"order 8 with the opt-in `view_correction=True` (each lobe scaled by the true lobe's directional "
           f"albedo ρ_p(n·v)).\n"]
    # run time per order: the other axis of the trade-off
    c, w, nn, vv = texels(1 << 16)
    Pf = np.array(EXPONENTS, np.float32)
    cells = []
    for L in orders:
        KL = np.zeros((3, (L + 1) ** 2), np.float32)
        KL[:, 0] = 1
        median_time(lambda: shade_env(c, w, Pf, nn, vv, KL, threads=1), 5, label=f"order{L}")
        cells.append(f"{1e3 * CPU_TIMES[f'order{L}'] * 16:.0f} ms")
    out.append("Cost (median CPU time per 1 M texels, 3 lobes, float32, one thread):\n\n| | "
               + " | ".join(f"L={L}" for L in orders) + " |\n|---|" + "---|" * len(orders)
               + "\n| CPU time | " + " | ".join(cells) + " |\n")
    for p in EXPONENTS:
        out.append(f"\n**p = {p:g}**\n\n| view angle | " + " | ".join(f"L={L}" for L in orders)
                   + " | lobe-shape only (L=12 lighting) | L=8 + view correction |\n|---|"
                   + "---|" * (len(orders) + 2))
        for ang in angles:
            cells = [f"{100 * statistics.median(rows[(p, L, ang)]):.1f}%" for L in orders]
            out.append(f"| {ang}° | " + " | ".join(cells) + f" | {100 * statistics.median(lobe_only[(p, ang)]):.1f}% "
                       f"| {100 * statistics.median(rows[(p, 'vc', ang)]):.1f}% |")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------ 2/3. speed


def machine_roofline():
    a = np.random.default_rng(0).random((2048, 2048), dtype=np.float32)
    t = median_time(lambda: a @ a, repeat=3)
    gflops = 2 * 2048 ** 3 / t / 1e9
    big = np.ones(1 << 25, np.float32)
    dst = np.empty_like(big)
    t = median_time(lambda: np.copyto(dst, big), repeat=3)
    gbs = 2 * big.nbytes / t / 1e9
    # elementwise float32 multiply on an L2-resident block (what the SH recurrences do)
    x = np.ones(1 << 14, np.float32)
    y = np.ones_like(x)
    z = np.empty_like(x)

    def ew():
        for _ in range(200):
            np.multiply(x, y, out=z)

    t = median_time(ew, repeat=5)
    ew_rate = 200 * x.size / t / 1e9
    return gflops, gbs, ew_rate


def texels(N, seed=0, dtype=np.float32):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(N, 3))
    n[:, 2] = np.abs(n[:, 2])  # facing the viewer
    v = np.tile([0.0, 0.0, 1.0], (N, 1)) + 0.2 * rng.normal(size=(N, 3))
    c = rng.random((N, 3))
    w = rng.random((N, 3))
    return [a.astype(dtype) for a in (c, w, n, v)]


def comparison_case(quick):
    """The inputs both kernel comparisons time: N texels, (c, w, P, n, v, K) in float32 (order 8, 3 lobes, light
    coefficients with a dominant constant term), a 30 % mask, and the same arrays in float64."""
    N = (1 << 18) if quick else (1 << 20)
    K = (np.random.default_rng(1).normal(size=(3, 81)) * 0.3).astype(np.float32)
    K[:, 0] = 3
    c, w, n, v = texels(N)
    P = np.array(EXPONENTS, np.float32)
    mask = np.random.default_rng(2).random(N) < 0.3
    f32 = (c, w, P, n, v, K)
    return N, f32, mask, tuple(a.astype(np.float64) for a in f32)


def throughput(quick):
    N = (1 << 18) if quick else (1 << 20)
    order = 8
    K = (np.random.default_rng(1).normal(size=(3, 81)) * 0.3).astype(np.float32)
    K[:, 0] = 3
    c, w, n, v = texels(N)
    P = np.array(EXPONENTS, np.float32)
    rep = 3
    res = {}

    def median_time_l(fn, rep_, key):
        return median_time(fn, rep_, label=key)

    res["full"] = median_time_l(lambda: shade_env(c, w, P, n, v, K), rep, "full")
    res["full, 1 thread"] = median_time_l(lambda: shade_env(c, w, P, n, v, K, threads=1), rep, "full, 1 thread")
    for tol in (1e-3, 1e-2):
        res[f"band_tol={tol:g}"] = median_time_l(lambda: shade_env(c, w, P, n, v, K, band_tol=tol), rep, f"band_tol={tol:g}")
    w0 = w.copy()
    w0[:, 0] = 0
    res["one lobe all-zero"] = median_time_l(lambda: shade_env(c, w0, P, n, v, K), rep, "one lobe all-zero")
    wz = np.zeros_like(w)
    res["all lobes zero (diffuse only)"] = median_time_l(lambda: shade_env(c, wz, P, n, v, K), rep, "all lobes zero (diffuse only)")
    mask = np.random.default_rng(2).random(N) < 0.3
    res["mask 30% of texels"] = median_time_l(lambda: shade_env(c, w, P, n, v, K, mask=mask), rep, "mask 30% of texels")
    nb = n.copy()
    nb[: N // 2, 2] *= -1
    res["half the texels back-facing"] = median_time_l(lambda: shade_env(c, w, P, nb, v, K), rep, "half the texels back-facing")
    res["view_correction=True"] = median_time_l(lambda: shade_env(c, w, P, n, v, K, view_correction=True), rep,
                                                "view_correction=True")
    c64, w64, P64, n64, v64, K64 = (a.astype(np.float64) for a in (c, w, P, n, v, K))
    res["float64"] = median_time_l(lambda: shade_env(c64, w64, P64, n64, v64, K64), rep, "float64")
    import torch

    tt = [torch.from_numpy(a) for a in (c, w, P, n, v, K)]
    with torch.no_grad():
        res["torch (no grad)"] = median_time_l(lambda: shade_env(*tt), rep, "torch (no grad)")
    tg = [x.clone().requires_grad_(i in (0, 1, 5)) for i, x in enumerate(tt)]

    def fb():
        d, s = shade_env(*tg)
        (d.sum() + s.sum()).backward()

    res["torch forward+backward"] = median_time_l(fb, max(1, rep - 2), "torch forward+backward")
    return N, order, res


def kernel_roofline(order=8, lobes=3, block=None, repeat=7):
    """Best texels/s of the blocked numpy kernel on one core, from its operation counts and the measured rate of
    each operation at the sizes the kernel uses (single-threaded BLAS, one block of texels).

    Per texel: ``ew`` elementwise float32 operations (the two bases — T_j recurrence, azimuthal factors, one
    product per basis row — and ~30 for normalising, reflecting, weighting and scattering), one (3 × n_d) @
    (n_d × m) and one (3·lobes × n_s) @ (n_s × m) product, and 72 B of input/output from memory.
    """
    from threadpoolctl import threadpool_limits

    from reflectmm_cli.shading import env as E
    from reflectmm_cli.shading.sh import lambert_sh_coeffs

    m = block or E.DEFAULT_CHUNK
    A = lambert_sh_coeffs(order)
    pd = E._cheb_plan(order, tuple(l for l in range(order + 1) if A[l] != 0))
    ps = E._cheb_plan(order, tuple(range(order + 1)))

    def basis_ops(p):
        return 2 + 2 * max(0, p.jmax - 1) + 6 * max(0, order - 1) + (p.n_rows - p.jmax - 1)

    ew_ops = basis_ops(pd) + basis_ops(ps) + 30
    rng = np.random.default_rng(0)
    Yd = rng.random((pd.n_rows, m), dtype=np.float32)
    Ys = rng.random((ps.n_rows, m), dtype=np.float32)
    Rd = rng.random((3, pd.n_rows), dtype=np.float32)
    Rs = rng.random((3 * lobes, ps.n_rows), dtype=np.float32)
    od, os_ = np.empty((3, m), np.float32), np.empty((3 * lobes, m), np.float32)
    x, y, z = (rng.random(m, dtype=np.float32) for _ in range(3))
    with threadpool_limits(limits=1, user_api="blas"):
        t_md = median_time(lambda: [np.matmul(Rd, Yd, out=od) for _ in range(20)], repeat) / 20 / m
        t_ms = median_time(lambda: [np.matmul(Rs, Ys, out=os_) for _ in range(20)], repeat) / 20 / m
    t_ew = median_time(lambda: [np.multiply(x, y, out=z) for _ in range(200)], repeat) / 200 / m
    big = np.ones(1 << 25, np.float32)
    dst = np.empty_like(big)
    gbs = 2 * big.nbytes / median_time(lambda: np.copyto(dst, big), 3) / 1e9
    bytes_io = 4 * 6 * 3
    parts = {"elementwise": ew_ops * t_ew, "diffuse product": t_md, "lobe product": t_ms,
             "memory": bytes_io / (gbs * 1e9)}
    return dict(block=m, ew_ops=ew_ops, t_ew=t_ew, rows=(pd.n_rows, ps.n_rows),
                flops_d=2 * 3 * pd.n_rows, flops_s=2 * 3 * lobes * ps.n_rows,
                gflops_d=2 * 3 * pd.n_rows / t_md / 1e9, gflops_s=2 * 3 * lobes * ps.n_rows / t_ms / 1e9,
                gbs=gbs, bytes_io=bytes_io, parts=parts, per_core=1.0 / sum(parts.values()))


def load_module_from(path):
    """A copy of reflectmm_cli/shading/env.py at another path, imported as a sibling module of the package (its
    relative imports resolve against the installed reflectmm_cli.shading)."""
    import importlib.util

    name = "reflectmm_cli.shading._env_compare"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def compare_old(path, quick, repeat=7):
    """Old (module at ``path``) against current ``shade_env``, interleaved repeats in this process."""
    from reflectmm_cli.shading import env as new

    old = load_module_from(path)
    N, (c, w, P, n, v, K), mask, (c64, w64, P64, n64, v64, K64) = comparison_case(quick)
    cases = {
        "order 8, 3 lobes, float32, 2 threads": (lambda m: m.shade_env(c, w, P, n, v, K, threads=2)),
        "same, 1 thread": (lambda m: m.shade_env(c, w, P, n, v, K, threads=1)),
        "float64, 2 threads": (lambda m: m.shade_env(c64, w64, P64, n64, v64, K64, threads=2)),
        "mask 30 %, 2 threads": (lambda m: m.shade_env(c, w, P, n, v, K, mask=mask, threads=2)),
        "view_correction, 2 threads": (lambda m: m.shade_env(c, w, P, n, v, K, view_correction=True, threads=2)),
    }
    rows = ["### 2b. Old against new kernel, same run\n",
            f"Old: `{path}`; new: the current `reflectmm_cli/shading/env.py`. {N} texels; each case runs old, "
            f"new, old, new, … ({repeat} repeats each after one warm-up); medians of wall time. Load average at "
            f"the start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs.\n"]
    rows += interleaved(cases, old, new, ("old", "new"), N, repeat)
    rows.append(f"\nLoad average at the end: {os.getloadavg()[0]:.1f}.")
    return "\n".join(rows)


def interleaved(cases, a, b, names, N, repeat):
    """Table rows: each case ``f(x)`` run for x = a, b, a, b, … (``repeat`` each after one warm-up, which also
    gives the agreement of b's result with a's); medians of wall and CPU time (all threads)."""
    na, nb = names
    rows = [f"| case | {na} median wall | {nb} median wall | {na} M texels/s | {nb} M texels/s | {nb}/{na} (wall) | "
            f"M texels per CPU-s, {na} / {nb} (ratio) | max abs({nb} − {na}) / max abs({na}) |",
            "|---|---|---|---|---|---|---|---|"]
    for name, f in cases.items():
        ro, rn = f(a), f(b)  # warm-up, and the agreement check
        diff = max(float(np.abs(x.astype(np.float64) - y).max() / max(np.abs(y).max(), 1e-30))
                   for x, y in zip(rn, ro))
        to, tn, co, cn = [], [], [], []
        for _ in range(repeat):
            for x, tl, cl in ((a, to, co), (b, tn, cn)):
                c0 = time.process_time()
                t = time.perf_counter()
                f(x)
                tl.append(time.perf_counter() - t)
                cl.append(time.process_time() - c0)
        mo, mn = statistics.median(to), statistics.median(tn)
        qo, qn = statistics.median(co), statistics.median(cn)
        rows.append(f"| {name} | {1e3 * mo:.0f} ms | {1e3 * mn:.0f} ms | {N / mo / 1e6:.2f} | {N / mn / 1e6:.2f} "
                    f"| {mo / mn:.2f}× | {N / qo / 1e6:.2f} / {N / qn / 1e6:.2f} ({qo / qn:.2f}×) | {diff:.1e} |")
    return rows


_JIT_PROBE = """
import json, time
t0 = time.perf_counter()
import numpy as np
from reflectmm_cli.shading import env as E
k = E.compiled_kernel()
t1 = time.perf_counter()
rng = np.random.default_rng(0)
out = {"import": t1 - t0}
for dt in ("float32", "float64"):
    n = rng.normal(size=(512, 3)).astype(dt)
    t = time.perf_counter()
    E.shade_env(np.ones((512, 3), dt), np.ones((512, 3), dt), np.array([1, 8, 64], dt), n, n,
                np.ones((3, 81), dt), backend="compiled")
    out[dt] = time.perf_counter() - t
print(json.dumps(out))
"""


def jit_times():
    """First-call times of the compiled kernel in fresh processes: with an empty numba cache (compilation), then
    with the cache that run left (loading). Returns [(label, {import, float32, float64} seconds)]."""
    import json
    import subprocess
    import tempfile

    root = os.path.join(os.path.dirname(__file__), "..")
    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=os.pathsep.join(
            [root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
        for label in ("cold cache (compile)", "warm cache (load)"):
            r = subprocess.run([sys.executable, "-c", _JIT_PROBE], env=env, capture_output=True, text=True,
                               check=True)
            out.append((label, json.loads(r.stdout.strip().splitlines()[-1])))
    return out


def compare_kernels(quick, repeat=7):
    """The compiled kernel against the blocked numpy kernel (``shade_env(..., backend=...)``), interleaved in this
    process, and the compiled kernel's JIT times."""
    from reflectmm_cli.shading import env as E

    if E.compiled_kernel() is None:
        return "### 2c. Compiled against numpy kernel\n\nnumba is not installed: nothing to compare."
    import numba

    N, (c, w, P, n, v, K), mask, (c64, w64, P64, n64, v64, K64) = comparison_case(quick)
    cases = {
        "order 8, 3 lobes, float32, 2 threads": (lambda b: shade_env(c, w, P, n, v, K, threads=2, backend=b)),
        "same, 1 thread": (lambda b: shade_env(c, w, P, n, v, K, threads=1, backend=b)),
        "float64, 2 threads": (lambda b: shade_env(c64, w64, P64, n64, v64, K64, threads=2, backend=b)),
        "float64, 1 thread": (lambda b: shade_env(c64, w64, P64, n64, v64, K64, threads=1, backend=b)),
        "mask 30 %, 2 threads": (lambda b: shade_env(c, w, P, n, v, K, mask=mask, threads=2, backend=b)),
        "view_correction, 2 threads": (lambda b: shade_env(c, w, P, n, v, K, view_correction=True, threads=2,
                                                           backend=b)),
    }
    load0 = os.getloadavg()
    jit = jit_times()
    rows = ["### 2c. Compiled (numba) against numpy kernel, same run\n",
            f"`shade_env(..., backend=\"numpy\")` (the blocked numpy kernel) against `backend=\"compiled\"` "
            f"(numba {numba.__version__}, `reflectmm_cli/shading/_env_numba.py`); {N} texels, order 8, lobes p = "
            f"{', '.join(f'{p:g}' for p in EXPONENTS)}; each case runs numpy, compiled, numpy, compiled, … "
            f"({repeat} repeats each after one warm-up); medians. Load average (1, 5, 15 min) at the start: "
            f"{load0[0]:.2f}, {load0[1]:.2f}, {load0[2]:.2f} on {os.cpu_count()} CPUs.\n"]
    rows += interleaved(cases, "numpy", "compiled", ("numpy", "compiled"), N, repeat)
    rows += ["\nFirst call in a fresh process (512 texels; `NUMBA_CACHE_DIR` an empty folder, then the same folder "
             "again):\n", "| | import of the kernel module | first float32 call | first float64 call |",
             "|---|---|---|---|"]
    for label, t in jit:
        rows.append(f"| {label} | {t['import']:.2f} s | {t['float32']:.2f} s | {t['float64']:.2f} s |")
    load1 = os.getloadavg()
    rows.append(f"\nLoad average at the end: {load1[0]:.2f}, {load1[1]:.2f}, {load1[2]:.2f}.")
    return "\n".join(rows)


def speed_report(quick, compare=None):
    gflops, gbs, ew = machine_roofline()
    rl = kernel_roofline()
    N, order, res = throughput(quick)
    p = rl["parts"]
    out = ["### 2. Throughput of `shade_env` (order 8, 3 lobes, float32)\n",
           f"Machine (measured now, {os.cpu_count()} CPUs visible, shared): sgemm 2048² {gflops:.1f} GFLOP/s, "
           f"memory copy {gbs:.1f} GB/s, L2-resident float32 elementwise multiply {ew:.2f} G elem/s.\n",
           f"Roofline of the blocked kernel (one core, blocks of {rl['block']} texels, each operation timed at "
           f"that size with single-threaded BLAS): {rl['ew_ops']} elementwise operations "
           f"({1e9 * rl['t_ew']:.3f} ns per element and operation → {1e9 * p['elementwise']:.0f} ns), the "
           f"diffuse product (3 × {rl['rows'][0]}) @ ({rl['rows'][0]} × m), {rl['flops_d']} flops at "
           f"{rl['gflops_d']:.1f} GFLOP/s ({1e9 * p['diffuse product']:.0f} ns), the lobe product "
           f"(9 × {rl['rows'][1]}) @ ({rl['rows'][1]} × m), {rl['flops_s']} flops at {rl['gflops_s']:.1f} "
           f"GFLOP/s ({1e9 * p['lobe product']:.0f} ns), {rl['bytes_io']} B of input/output "
           f"({1e9 * p['memory']:.1f} ns) → **{rl['per_core'] / 1e6:.1f} M texels per core-second, "
           f"≈ {2 * rl['per_core'] / 1e6:.0f} M texels/s on 2 idle cores**.\n",
           f"\nLoad average when measured: {os.getloadavg()[0]:.1f} (the machine is shared; wall times vary with "
           f"it, CPU times much less). *texels per CPU-s* = N / CPU time of all threads; on 2 idle cores the "
           f"wall throughput of the threaded path approaches twice that.\n",
           f"\n| case ({N} texels) | median wall | texels/s (wall) | median CPU | texels per CPU-s | CPU vs full |"
           f"\n|---|---|---|---|---|---|"]
    cfull = CPU_TIMES["full"]
    for k, t in res.items():
        cpu = CPU_TIMES.get(k, float("nan"))
        out.append(f"| {k} | {1e3 * t:.0f} ms | {N / t / 1e6:.2f} M | {1e3 * cpu:.0f} ms | {N / cpu / 1e6:.2f} M "
                   f"| {cfull / cpu:.2f}× |")
    if compare:
        out.append("\n" + compare_old(compare, quick))
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------ 4. projection


def projection_report(quick):
    W, H = (1024, 512) if quick else (2048, 1024)
    order = 8
    img = procedural_envmaps(W, H, seed=3, count=1)[0]
    out = [f"### 4. Equirectangular projection ({W}×{H}, order {order})\n"]
    t_ours = median_time(lambda: project_envmap(img, order), 3)
    t_area = median_time(lambda: project_envmap(img, order, quadrature="area"), 3)
    out.append(f"| method | median time |\n|---|---|\n| `project_envmap` (Fejér) | {1e3 * t_ours:.0f} ms |\n"
               f"| `project_envmap` (pixel area) | {1e3 * t_area:.0f} ms |")
    try:
        import ducc0
    except ImportError:
        out.append("\nducc0 is not installed: no reference comparison.")
        return "\n".join(out)
    phi0 = math.pi / W - math.pi
    x = np.ascontiguousarray(np.moveaxis(img, 2, 0))
    nth = min(2, os.cpu_count() or 1)
    wq = ducc0.sht.experimental.get_gridweights("F1", H)
    sx = ducc0.sht.experimental

    def ducc_adjoint():  # spin-0 transforms take one component: one call per colour channel
        return [sx.adjoint_synthesis_2d(map=x[c:c + 1] * (wq[:, None] / W), spin=0, lmax=order, geometry="F1",
                                        phi0=phi0, nthreads=nth)[0] for c in range(3)]

    def ducc_analysis():
        return [sx.analysis_2d(map=x[c:c + 1], spin=0, lmax=order, geometry="F1", phi0=phi0,
                               nthreads=nth)[0] for c in range(3)]

    t_d = median_time(ducc_adjoint, 3)
    alm = np.stack(ducc_adjoint())
    t_a = median_time(ducc_analysis, 3)
    alm_a = np.stack(ducc_analysis())
    out.append(f"| ducc0 adjoint_synthesis_2d × Fejér weights ({nth} threads) | {1e3 * t_d:.0f} ms |\n"
               f"| ducc0 analysis_2d ({nth} threads) | {1e3 * t_a:.0f} ms |")
    # agreement as functions at random directions
    from reflectmm_cli.shading import direction_to_equirect, sh_basis

    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u, vv = direction_to_equirect(d)
    loc = np.stack([vv * math.pi, (u * 2 * math.pi - math.pi) % (2 * math.pi)], -1)
    ours = sh_basis(d, order) @ project_envmap(img, order).T
    def synth(a):
        return np.stack([sx.synthesis_general(alm=a[c:c + 1], spin=0, lmax=order, loc=loc, epsilon=1e-12)[0]
                         for c in range(3)], -1)

    ref, ref_a = synth(alm), synth(alm_a)
    scale = np.abs(ref).max()
    out.append(f"\nAgreement (max |difference| of the order-{order} expansions at 2000 random directions, relative "
               f"to the max value): same quadrature through ducc0 {np.abs(ours - ref).max() / scale:.1e}; "
               f"ducc0's own `analysis_2d` (exact only for maps band-limited to L, so it differs on a real HDR map "
               f"by the aliasing of higher bands) {np.abs(ours - ref_a).max() / scale:.1e}.")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", choices=["accuracy", "speed", "kernels", "projection"], default=None)
    ap.add_argument("--maps", nargs="*", default=None,
                    help="real equirectangular HDR maps (files or folders) for the accuracy section")
    ap.add_argument("--compare-old", default=None, metavar="FILE",
                    help="a copy of an earlier reflectmm_cli/shading/env.py: time it against the current one")
    args = ap.parse_args()
    parts = []
    if args.only in (None, "speed"):
        parts.append(speed_report(args.quick, args.compare_old))
    if args.only in (None, "speed", "kernels"):
        parts.append(compare_kernels(args.quick))
    if args.only in (None, "projection"):
        parts.append(projection_report(args.quick))
    if args.only in (None, "accuracy"):
        parts.append(accuracy(args.quick, args.maps))
    print("\n\n".join(parts))


if __name__ == "__main__":
    main()

"""Trial (not wired in): torch.compile (inductor, CPU) of shade_env's blocked kernel, order 8, 3 lobes, float32.

The Chebyshev basis of the numpy kernel and the products written as per-row pointwise multiply-adds over the
texels, so inductor may fuse basis and products into one loop; compared with the numpy kernel in the same process.
Prints one JSON line: compile time (first call), agreement, M texels per CPU-second and per second.

    python benchmarks/bench_shading_inductor.py          # TT=2 for two torch threads
"""
import os, sys, time, json
import numpy as np
import torch
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from bench_shading import texels
from reflectmm_cli.shading import env as E, shade_env

torch.set_num_threads(int(os.environ.get("TT", "1")))
N = 1 << 20
K = (np.random.default_rng(1).normal(size=(3, 81)) * 0.3).astype(np.float32); K[:, 0] = 3
c, w, n, v = texels(N)
P = np.array([1, 8, 64], np.float32)
bl = E._blocked_setup(c, w, n, v, K, P.astype(np.float64), 0.0, False, (N,), None, np.float32)
pd, ps = bl.plan_d, bl.plan_s

def basis_rows(x, y, z, plan):
    rows = [None] * plan.n_rows
    T = [torch.ones_like(z), z]
    for j in range(2, plan.jmax + 1):
        T.append((z + z) * T[j - 1] - T[j - 2])
    for j in range(plan.jmax + 1):
        rows[j] = T[j]
    cm, sm, m_cur = x, y, 1
    for m, js, rc, rs in plan.m_rows:
        while m_cur < m:
            cm, sm = x * cm - y * sm, x * sm + y * cm
            m_cur += 1
        for k, j in enumerate(js):
            rows[rc + k] = cm if j == 0 else T[j] * cm
            rows[rs + k] = sm if j == 0 else T[j] * sm
    return rows

def product(R, rows):
    out = []
    for q in range(R.shape[0]):
        acc = R[q, 0] * rows[0]
        for k in range(1, len(rows)):
            acc = acc + R[q, k] * rows[k]
        out.append(acc)
    return out

def kernel(c, w, n, v, Rd, Rs):
    n = n * torch.rsqrt(torch.clamp_min((n * n).sum(1, keepdim=True), 1e-30))
    v = v * torch.rsqrt(torch.clamp_min((v * v).sum(1, keepdim=True), 1e-30))
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    E_ = product(Rd, basis_rows(x, y, z, pd))
    d = torch.stack(E_, 1) * c
    ndv = (n * v).sum(1)
    r = (ndv + ndv)[:, None] * n - v
    S = product(Rs, basis_rows(r[:, 0], r[:, 1], r[:, 2], ps))
    s = sum(torch.stack(S[3 * j:3 * j + 3], 1) * w[:, j:j + 1] for j in range(3))
    s = torch.where((ndv > 0)[:, None], s, torch.zeros_like(s))
    return d, s

T = [torch.from_numpy(a) for a in (c, w, n, v, bl.terms.diffuse, bl.terms.lobes)]
out = {}
t = time.perf_counter()
ck = torch.compile(kernel, dynamic=False)
with torch.no_grad():
    d, s = ck(*T)
out["compile_s"] = time.perf_counter() - t
ref = shade_env(c, w, P, n, v, K, backend="numpy", threads=1)
out["rel_diff"] = [float(np.abs(a.numpy().astype(np.float64) - b).max() / np.abs(b).max()) for a, b in zip((d, s), ref)]
def tm(f):
    f(); cs = []
    for _ in range(5):
        q = time.process_time(); t0 = time.perf_counter(); f(); cs.append((time.process_time() - q, time.perf_counter() - t0))
    cs.sort(); return cs[len(cs) // 2]
with torch.no_grad():
    cpu, wall = tm(lambda: ck(*T))
out["inductor_Mtexels_per_cpu_s"] = N / cpu / 1e6
out["inductor_Mtexels_per_s_wall"] = N / wall / 1e6
cpu, wall = tm(lambda: shade_env(c, w, P, n, v, K, backend="numpy", threads=1))
out["numpy_Mtexels_per_cpu_s"] = N / cpu / 1e6
out["torch_threads"] = torch.get_num_threads()
out["load"] = os.getloadavg()
print(json.dumps(out))

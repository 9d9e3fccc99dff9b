"""The paper's reference solver (docs/design.md §3): Adam on the cos-weighted L1 loss, random horizontal flips.

Loss per step (C (3,S,S), W (K,S,S) are the optimised maps; ``flip`` is a horizontal flip of both maps,
applied with probability 1/2 each step when symmetry > 0):

    L = (1/N) Σ_t Σ_j ⟨l_j, n⟩ · Σ_c |Î_tjc − I_tjc| + w_reg · (1/N) · (−Σ negative entries of C and W)

N = number of masked texels (both terms are per-texel means, so ``lr`` and ``w_reg`` do not depend on the
UV size).  Initial value: constant C = 0.3, W = 0.1 (``init``); Adam, lr 5e-3, w_reg 100 as in the paper.
Only observed (texel, pair) entries are stored (a compact list), so memory is that of the observations.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from reflectmm_cli.threads import torch_threads

from .design import mirror_index

__all__ = ["fit_adam"]

#: Below this many observations Adam runs single-threaded.
SMALL_PROBLEM_ROWS = 200_000


def fit_adam(prob, idx: np.ndarray, S: int, K: int, *, steps: int = 1000, lr: float = 5e-3, w_reg: float = 100.0,
             symmetry: float = 1.0, init: Sequence[float] | None = None, device: str = "cpu", seed: int = 0,
             progress: Callable | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Run Adam on the design cached in ``prob`` (see :mod:`.fit`); return (x (n, 3+K), info)."""
    import torch

    # small problems lose more to thread start-up than they gain (and the CPU is usually shared)
    with torch_threads(1 if prob.tex.size < SMALL_PROBLEM_ROWS else None):
        return _run(torch, prob, idx, S, K, steps, lr, w_reg, symmetry, init, device, seed, progress)


def _run(torch, prob, idx, S, K, steps, lr, w_reg, symmetry, init, device, seed, progress):
    dev = torch.device(device)
    n = idx.size
    tex_t = torch.as_tensor(prob.tex, device=dev)
    d_t = torch.as_tensor(prob.d, dtype=torch.float32, device=dev)
    s_t = torch.as_tensor(prob.s, dtype=torch.float32, device=dev)
    c_t = torch.as_tensor(prob.cos, dtype=torch.float32, device=dev)
    y_t = torch.as_tensor(prob.y, dtype=torch.float32, device=dev)
    c0, w0 = (0.3, 0.1) if init is None else (float(init[0]), float(init[1]))
    C = torch.full((S * S, 3), c0, dtype=torch.float32, device=dev, requires_grad=True)
    W = torch.full((S * S, K), w0, dtype=torch.float32, device=dev, requires_grad=True)
    opt = torch.optim.Adam([C, W], lr=lr)
    own = torch.as_tensor(idx.astype(np.int64), device=dev)
    mir = torch.as_tensor(mirror_index(S)[idx].astype(np.int64), device=dev)
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    flips = (torch.rand(int(steps), generator=gen) < 0.5).tolist() if symmetry > 0 else [False] * int(steps)
    inv_n = 1.0 / max(n, 1)
    it = range(int(steps))
    if progress is not None:
        it = progress(it, desc="Adam", total=int(steps))
    last = float("nan")
    rows_own = own[tex_t]
    rows_mir = mir[tex_t]
    for step in it:
        rows = rows_mir if flips[step] else rows_own
        Ct = C.index_select(0, rows)
        Wt = W.index_select(0, rows)
        pred = d_t[:, None] * Ct + (s_t * Wt).sum(-1, keepdim=True)
        data = (c_t[:, None] * (pred - y_t).abs()).sum() * inv_n
        neg = -(torch.clamp(C, max=0.0).sum() + torch.clamp(W, max=0.0).sum()) * inv_n
        loss = data + w_reg * neg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        last = float(loss.detach())
    x = torch.cat([C[own], W[own]], dim=1).detach().cpu().numpy().astype(np.float64)
    return x, {"steps": int(steps), "lr": lr, "w_reg": w_reg, "init": [c0, w0], "final_loss": last,
               "negative_entries": int((x < 0).sum())}

"""Batched non-negative quadratic programs: ``min ½ xᵀHx − gᵀx  s.t.  x ≥ 0`` for N small systems at once.

Lawson–Hanson active-set method run on all systems in lock step (one batched linear solve per iteration):
finite termination, exact KKT at the solution —

    x ≥ 0,   ∇ = Hx − g ≥ −tol,   x_j · ∇_j = 0   (∇_j = 0 on the free set, x_j = 0 on the active set).

Systems whose unconstrained solution is already non-negative (most texels) finish after one solve.
"""

from __future__ import annotations

import numpy as np

__all__ = ["nnls_batched", "kkt_violation"]


def _solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Batched solve with a relative jitter of 1e-13 · trace (keeps a semidefinite H solvable)."""
    m = H.shape[-1]
    tr = np.einsum("nii->n", H)
    jitter = 1e-13 * np.where(tr > 0, tr, 1.0) / m
    Hj = H + jitter[:, None, None] * np.eye(m)
    try:
        return np.linalg.solve(Hj, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.empty_like(g)
        for i in range(H.shape[0]):
            out[i] = np.linalg.lstsq(Hj[i], g[i], rcond=None)[0]
        return out


def _restricted_solve(H: np.ndarray, g: np.ndarray, free: np.ndarray) -> np.ndarray:
    m = H.shape[-1]
    pair = free[:, :, None] & free[:, None, :]
    Hr = np.where(pair, H, np.eye(m)[None])
    gr = np.where(free, g, 0.0)
    z = _solve(Hr, gr)
    return np.where(free, z, 0.0)


def nnls_batched(H: np.ndarray, g: np.ndarray, tol: float = 1e-12, max_iter: int | None = None
                 ) -> tuple[np.ndarray, dict]:
    """Solve N non-negative QPs ``min ½xᵀHx − gᵀx, x ≥ 0`` (H symmetric positive (semi)definite).

    Args:
        H: (N, m, m); g: (N, m).
        tol: relative tolerance of the dual feasibility test (× max(|g|) of each system).
        max_iter: cap on Lawson–Hanson iterations (default 6·m + 10).
    Returns:
        (x (N, m), info) with info = {"iterations", "unconverged", "n_constrained"}.
    """
    H = np.asarray(H, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    N, m = g.shape
    x = _solve(H, g) if N else np.zeros((0, m))
    done = np.all(x >= 0, axis=1)
    todo = np.flatnonzero(~done)
    info = {"iterations": 1, "unconverged": 0, "n_constrained": int(todo.size)}
    if todo.size == 0:
        return x, info
    Hs, gs = H[todo], g[todo]
    n = todo.size
    xs = np.zeros((n, m))
    free = np.zeros((n, m), bool)
    scale = np.maximum(np.abs(gs).max(axis=1), 1e-300)
    outer = np.ones(n, bool)  # state: True = look for a variable to free; False = inner (feasibility) loop
    finished = np.zeros(n, bool)
    it_cap = max_iter if max_iter is not None else 6 * m + 10
    it = 0
    while it < it_cap and not finished.all():
        it += 1
        # outer step: dual feasibility test, free the most violating variable
        o = np.flatnonzero(outer & ~finished)
        if o.size:
            w = gs[o] - np.einsum("nij,nj->ni", Hs[o], xs[o])
            w = np.where(free[o], -np.inf, w)
            j = np.argmax(w, axis=1)
            wmax = w[np.arange(o.size), j]
            stop = wmax <= tol * scale[o]
            finished[o[stop]] = True
            go = o[~stop]
            free[go, j[~stop]] = True
            outer[go] = False
        # inner step: solve on the free set, step back to stay feasible
        q = np.flatnonzero(~outer & ~finished)
        if q.size:
            z = _restricted_solve(Hs[q], gs[q], free[q])
            ok = np.all((z > 0) | ~free[q], axis=1)
            acc = q[ok]
            xs[acc] = z[ok]
            outer[acc] = True
            bad = np.flatnonzero(~ok)
            if bad.size:
                qb = q[bad]
                zb, xb, fb = z[bad], xs[qb], free[qb]
                neg = fb & (zb <= 0)
                with np.errstate(divide="ignore", invalid="ignore"):
                    ratio = np.where(neg, xb / np.where(neg, xb - zb, 1.0), np.inf)
                alpha = np.clip(ratio.min(axis=1), 0.0, 1.0)
                xn = xb + alpha[:, None] * (zb - xb)
                drop = fb & ((xn <= 1e-15 * np.maximum(np.abs(xn).max(axis=1, keepdims=True), 1e-300)) | (
                    neg & (ratio <= alpha[:, None])))
                xn = np.where(drop, 0.0, xn)
                xs[qb] = xn
                free[qb] = fb & ~drop
    info["iterations"] = it + 1
    info["unconverged"] = int((~finished).sum())
    x[todo] = np.maximum(xs, 0.0)
    return x, info


def kkt_violation(H: np.ndarray, g: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(N,) largest KKT violation of ``min ½xᵀHx − gᵀx, x ≥ 0`` relative to max(|g|):
    max of −x_j, −∇_j and |x_j ∇_j| / max|x| (∇ = Hx − g)."""
    grad = np.einsum("nij,nj->ni", H, x) - g
    scale = np.maximum(np.abs(g).max(axis=1), 1e-300)
    xs = np.maximum(np.abs(x).max(axis=1), 1e-300)
    v = np.maximum.reduce([np.max(-x, axis=1) / xs, np.max(-grad, axis=1) / scale,
                           np.max(np.abs(x * grad), axis=1) / (xs * scale)])
    return np.maximum(v, 0.0)

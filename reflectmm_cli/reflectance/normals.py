"""Photometric normal refinement for the per-texel reflectance fit (issue 13, cause 4; docs/fit-reflectance.md).

With fitted geometry the unwrapped normal n_g of a texel is off by a few degrees; the linear reflectance model then
explains the shading error with the wrong unknowns (mostly the p = 1 lobe, nearly collinear with the diffuse
term).  The flashes are at known positions, so the observations also measure the normal (photometric stereo).
Per texel the normal is parametrised in the tangent plane of the geometric normal,

    n(δ) = normalize(n_g + T δ),    T = [t1 t2] an orthonormal tangent basis of n_g,  δ ∈ R²

(|δ| = tan of the correction angle), and with the reflectance x = (C, W) fixed, one damped Gauss–Newton step
minimises the IRLS surrogate of the fit's loss plus a Gaussian prior towards n_g:

    F(δ) = ½ Σ_jc w_jc r_jc(δ)² + ½ λ |δ|²,     r_jc = C_c d_j(n) + Σ_i W_i s_ji(n) − I_jc

with the design columns of :mod:`.design` (same visibility, n·l > 0 and n·v > 0 rules; the rows are the pairs the
fit uses, fixed by the geometric normal) and their analytic derivatives (:func:`.design.design_rows_grad`),
``∂n/∂δ = (I − n nᵀ) T / |n_g + T δ|``.  Weights and prior scale follow the loss as a likelihood:

* ``l1`` (the paper's ``Σ ⟨l,n⟩|r|``, Laplace noise of scale b): ``w = ⟨l,n⟩ / max(|r|, δ_t)``,
  ``λ = b / σ²`` with ``b = Σ⟨l,n⟩|r| / Σ⟨l,n⟩`` the texel's weighted mean absolute residual;
* ``l2`` (Gaussian noise of variance s²): ``w = ⟨l,n⟩``, ``λ = s² / σ²``, ``s² = Σ⟨l,n⟩ r² / Σ⟨l,n⟩``;

σ is the prior's standard deviation of the correction angle (radians here, degrees in the API).  b and s² are
floored at the IRLS δ_t (1e-3 × the texel's RMS radiance), so an all-dark texel keeps its geometric normal.  The
step solves ``(JᵀWJ + λ I + μ I) Δ = −(JᵀW r + λ δ)`` (μ = 1e-9 · trace, numerical only), is clipped to
``max_step`` (tangent units) and halved up to twice until F decreases (else no step).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from reflectmm_cli.threads import parallel_map

from .design import DEFAULT_CHUNK, design_rows, design_rows_grad, iter_chunks

__all__ = ["tangent_basis", "offset_normal", "NormalRefinement", "correction_angle_deg"]

#: Largest tangent-plane step of one Gauss–Newton iteration (tan of ~5.7°).
MAX_STEP = 0.1
#: Step halvings tried before a texel keeps its normal for this iteration.
BACKTRACKS = 2


def tangent_basis(n: np.ndarray) -> np.ndarray:
    """(N, 3, 2) orthonormal tangent basis [t1 t2] of (N, 3) unit normals (branchless, Duff et al. 2017)."""
    n = np.asarray(n, np.float64)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return np.stack([t1, t2], axis=2)


def offset_normal(ng: np.ndarray, T: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``n = normalize(ng + T δ)`` (N, 3) and its Jacobian ``∂n/∂δ = (I − n nᵀ) T / |ng + T δ|`` (N, 3, 2)."""
    u = ng + np.einsum("nij,nj->ni", T, delta)
    ln = np.linalg.norm(u, axis=1)
    ln = np.where(ln > 0, ln, 1.0)
    n = u / ln[:, None]
    J = (T - n[:, :, None] * np.einsum("ni,nij->nj", n, T)[:, None, :]) / ln[:, None, None]
    return n, J


def correction_angle_deg(delta: np.ndarray) -> np.ndarray:
    """Angle (degrees) between n_g and n(δ): ``atan |δ|``."""
    return np.degrees(np.arctan(np.linalg.norm(delta, axis=-1)))


class NormalRefinement:
    """Per-texel normal state of a :class:`reflectmm_cli.reflectance.fit._Problem` and its Gauss–Newton step.

    Args:
        prob: the problem (rows, pair index, positions, rig).
        sigma_deg: σ of the Gaussian prior on the correction angle (degrees).
        loss: ``l1`` or ``l2`` (the fit's loss).
        delta_irls: (n,) IRLS δ_t of each texel (1e-3 × its RMS radiance).
        active: (n,) bool texels whose normal may move (the solved ones).
    """

    def __init__(self, prob, sigma_deg: float, loss: str, delta_irls: np.ndarray, active: np.ndarray,
                 chunk: int = DEFAULT_CHUNK, threads: int = 1, ridge: float = 1e-4):
        self.prob = prob
        self.ng = prob.nm0.copy()
        self.T = tangent_basis(self.ng)
        self.delta = np.zeros((self.ng.shape[0], 2))
        self.sig2 = float(np.radians(sigma_deg)) ** 2
        self.loss = loss
        self.dirls = np.maximum(np.asarray(delta_irls, np.float64), 1e-30)
        self.active = np.asarray(active, bool) & (prob.count > 0)
        self.chunk = int(chunk)
        self.threads = int(threads)
        self.ridge = max(float(ridge), 1e-9)

    @property
    def normals(self) -> np.ndarray:
        return offset_normal(self.ng, self.T, self.delta)[0]

    def _rows(self, a: int, b: int):
        pr = self.prob
        r0, r1 = pr.start[a], pr.start[b]
        cnt = pr.count[a:b]
        pj = pr.pair[r0:r1]
        return r0, r1, cnt, np.repeat(pr.xm[a:b], cnt, axis=0), pr.fpos[pj], pr.cpos[pj], pr.Ip[pj]

    def _residual(self, d, s, C, W, y):
        r = C * d[:, None]
        r += np.einsum("rk,rk->r", s, W)[:, None]
        r -= y
        return r

    def _chunk_step(self, ab: tuple[int, int], x: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """New δ and x of texels a..b−1 (one Gauss–Newton step with backtracking) and statistics."""
        a, b = ab
        pr = self.prob
        nt = b - a
        K = pr.K
        m = 3 + K
        r0, r1, cnt, xr, fr, cr, ir = self._rows(a, b)
        tex = pr.tex[r0:r1] - a
        xt = x[a:b]
        dlt = self.delta[a:b]
        n, Jn = offset_normal(self.ng[a:b], self.T[a:b], dlt)
        d, s, cos, _, dd, ds = design_rows_grad(xr, np.repeat(n, cnt, axis=0), fr, cr, ir, pr.p)
        C = np.repeat(xt[:, :3], cnt, axis=0)
        W = np.repeat(xt[:, 3:], cnt, axis=0)
        y = pr.y[r0:r1]
        r = self._residual(d, s, C, W, y)
        den = np.maximum(np.bincount(tex, weights=3.0 * cos, minlength=nt), 1e-300)
        if self.loss == "l1":  # Laplace scale b
            ar = np.abs(r)
            w = cos[:, None] / np.maximum(ar, np.repeat(self.dirls[a:b], cnt)[:, None])
            scale = np.bincount(tex, weights=cos * (ar[:, 0] + ar[:, 1] + ar[:, 2]), minlength=nt) / den
            scale = np.maximum(scale, self.dirls[a:b])
        else:  # Gaussian variance s²
            w = np.repeat(cos[:, None], 3, axis=1)
            scale = np.bincount(tex, weights=cos * np.einsum("rc,rc->r", r, r), minlength=nt) / den
            scale = np.maximum(scale, self.dirls[a:b] ** 2)
        lam = scale / self.sig2

        def bc(v):
            return np.bincount(tex, weights=v, minlength=nt)

        Jr = np.repeat(Jn, cnt, axis=0)                                  # (R, 3, 2)
        gd = np.einsum("rj,rjq->rq", dd, Jr)                             # ∂d/∂δ (R, 2)
        gs = np.einsum("rk,rkj,rjq->rq", W, ds, Jr)                      # Σ_i W_i ∂s_i/∂δ (R, 2)
        H = np.zeros((nt, 2, 2))          # JᵀWJ of δ
        g = np.zeros((nt, 2))             # JᵀW r
        M = np.zeros((nt, m, m))          # AᵀWA of the reflectance unknowns
        B = np.zeros((nt, m, 2))          # AᵀWJ (coupling)
        f0 = np.zeros(nt)
        wJ = np.zeros((r.shape[0], 2))    # Σ_c w_c J_c
        for c in range(3):
            Jc = C[:, c:c + 1] * gd + gs                                 # ∂r_c/∂δ (R, 2)
            wc = w[:, c]
            wJc = wc[:, None] * Jc
            wJ += wJc
            M[:, c, c] = bc(wc * d * d)
            for k in range(K):
                M[:, c, 3 + k] = M[:, 3 + k, c] = bc(wc * d * s[:, k])
            for q in range(2):
                g[:, q] += bc(wJc[:, q] * r[:, c])
                B[:, c, q] = bc(wJc[:, q] * d)
                for q2 in range(q, 2):
                    H[:, q, q2] += bc(wJc[:, q] * Jc[:, q2])
            f0 += 0.5 * bc(wc * r[:, c] ** 2)
        ws = w[:, 0] + w[:, 1] + w[:, 2]
        for k in range(K):
            for k2 in range(k, K):
                M[:, 3 + k, 3 + k2] = M[:, 3 + k2, 3 + k] = bc(ws * s[:, k] * s[:, k2])
            for q in range(2):
                B[:, 3 + k, q] = bc(wJ[:, q] * s[:, k])
        H[:, 1, 0] = H[:, 0, 1]
        f0 += 0.5 * lam * np.einsum("nq,nq->n", dlt, dlt)
        g += lam[:, None] * dlt
        # variable projection: the reflectance's linear response to the normal is eliminated (Schur complement
        # of the joint Gauss–Newton system in (x, δ); x is the minimiser of its own solve, so its gradient is ~0)
        tr = np.einsum("nii->n", M)
        Mr = M + (self.ridge * tr + 1e-300)[:, None, None] * np.eye(m)
        okm = np.all(np.isfinite(Mr), axis=(1, 2)) & (tr > 0)
        MiB = np.zeros_like(B)
        if okm.any():
            MiB[okm] = np.linalg.solve(Mr[okm], B[okm])
        Hs = H - np.einsum("nip,niq->npq", B, MiB)
        A = Hs + (lam + 1e-9 * np.abs(Hs[:, 0, 0] + Hs[:, 1, 1]) + 1e-300)[:, None, None] * np.eye(2)
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        ok = (self.active[a:b] & okm & np.isfinite(det) & (det > 0) & (A[:, 0, 0] > 0)
              & np.all(np.isfinite(g), axis=1))
        safe = np.where(ok, det, 1.0)
        step = -np.stack([A[:, 1, 1] * g[:, 0] - A[:, 0, 1] * g[:, 1],
                          A[:, 0, 0] * g[:, 1] - A[:, 1, 0] * g[:, 0]], axis=1) / safe[:, None]
        step = np.where(ok[:, None] & np.all(np.isfinite(step), axis=1, keepdims=True), step, 0.0)
        sn = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, MAX_STEP / np.maximum(sn, 1e-300))[:, None]
        dx = -np.einsum("nmq,nq->nm", MiB, step)
        dx = np.where(np.isfinite(dx), dx, 0.0)
        new, newx = dlt.copy(), xt.copy()
        todo = ok & (np.linalg.norm(step, axis=1) > 0)
        accepted = np.zeros(nt, bool)
        alpha = 1.0
        for _ in range(BACKTRACKS + 1):
            if not todo.any():
                break
            trial = dlt + alpha * step
            xtr = np.maximum(xt + alpha * dx, 0.0)
            nn, _ = offset_normal(self.ng[a:b], self.T[a:b], trial)
            d1, s1, _, _ = design_rows(xr, np.repeat(nn, cnt, axis=0), fr, cr, ir, pr.p)
            r1_ = self._residual(d1, s1, np.repeat(xtr[:, :3], cnt, axis=0), np.repeat(xtr[:, 3:], cnt, axis=0), y)
            f1 = 0.5 * bc(np.einsum("rc,rc->r", w * r1_, r1_))
            f1 += 0.5 * lam * np.einsum("nq,nq->n", trial, trial)
            better = todo & np.isfinite(f1) & (f1 < f0)
            new[better] = trial[better]
            newx[better] = xtr[better]
            accepted |= better
            todo &= ~better
            alpha *= 0.5
        return new, newx, {"accepted": int(accepted.sum()), "tried": int(ok.sum())}

    def step(self, x: np.ndarray) -> dict[str, Any]:
        """One Gauss–Newton iteration of every active texel's normal from the reflectance x (n, 3+K).

        ``self.x`` is then x moved along the eliminated linear response (clipped at 0): the start of a next
        step before the exact reflectance solve.
        """
        n = self.ng.shape[0]
        chunks = [(sl.start, sl.stop) for sl in iter_chunks(n, self.chunk)]
        res = parallel_map(lambda ab: self._chunk_step(ab, x), chunks, self.threads)
        acc = tried = 0
        xn = np.array(x, np.float64, copy=True)
        for (a, b), (new, newx, st) in zip(chunks, res):
            self.delta[a:b] = new
            xn[a:b] = newx
            acc += st["accepted"]
            tried += st["tried"]
        self.x = xn
        ang = correction_angle_deg(self.delta[self.active]) if self.active.any() else np.zeros(1)
        return {"accepted": acc, "tried": tried, "angle_median_deg": float(np.median(ang)),
                "angle_p90_deg": float(np.percentile(ang, 90))}

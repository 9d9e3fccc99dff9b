"""Per-identity reflectance fitting: the exact batched solver, the Adam reference, rendering (docs/design.md §3).

Model (per texel t, pair j, channel c; design columns of :mod:`.design`):
``Î_jc = C_c · d_j + Σ_i W_i · s_ji`` — linear in the 3 + K unknowns ``x = (C_r, C_g, C_b, W_1..W_K)``.

Fast solver (``solver="fast"``), per texel, exact and batched over texels:

* loss ``l2``: ``Σ_jc ⟨l_j,n⟩ r_jc²``; loss ``l1``: the paper's ``Σ_jc ⟨l_j,n⟩ |r_jc|`` by IRLS with weights
  ``⟨l_j,n⟩ / max(|r_jc|, δ)``, δ = ``irls_delta`` × RMS of the texel's observed radiance.
* symmetry: the normal equations of texel t are pooled with its mirror's,
  ``H_t + s_t · H_mirror(t)``; s_t = ``symmetry`` where the texel's own data are ill-posed and
  ``symmetry`` × the mirror trust elsewhere (``symmetry_mode="adaptive"``: the trust fades to 0 where the face
  measurably differs from its mirror, so pooling adds no bias where the texel's own data decide).
* tail prior: lobe weight W_i additionally gets ``λ_t · prior_tail · (1 − o_i/prior_tail_obs)₊²`` where
  its lobe's observability o_i is low (seen only in its tail).
* prior (Tikhonov): ``+ λ_t ‖x − x0_t‖²`` with ``λ_t = prior · trace(H_t)`` (the pooled data term), so
  its relative strength is the same in every texel and every IRLS iteration.  ``x0`` is a neighbourhood
  value: a first pass (one weighted least-squares solve with the prior towards 0) is smoothed by normalised
  convolution (Gaussian, σ = S/16 texels) over the texels where each unknown is observable (C: every solved
  texel; W_i: lobe observability ≥ ``observable_min``); where no such texel is near, the median of those
  texels is used.  Both C and W are in albedo units, so one isotropic λ serves both.
* non-negativity exactly: every solve is the non-negative QP of :func:`.nnls.nnls_batched` (KKT checked).
* flagged texels (in the mask, pooled conditioning < ``cond_min`` or fewer than ``min_obs`` pooled
  observations) are not solved: they are filled from the mirror texel (if it is solved and s > 0), else by
  normalised convolution of the solved neighbours (σ = 1.5 texels, doubled until every texel is reached),
  else the prior value.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable, Mapping

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.threads import default_threads, parallel_map

from .design import (DEFAULT_CHUNK, check_observations, design_columns, design_rows, gram_conditioning,
                     iter_chunks, mirror_index, pair_irradiance)
from .nnls import kkt_violation, nnls_batched
from .normals import NormalRefinement, correction_angle_deg

log = logging.getLogger("reflectmm")

#: Where mirror pooling applies: ``adaptive`` (every ill-posed texel fully; a well-posed texel with the weight its
#: mirror deserves given the measured local asymmetry), only texels whose own data are ill-posed, or every texel
#: (the paper's random flip).
SYMMETRY_MODES = ("adaptive", "ill-posed", "all")

#: Ridge of the first pass relative to the trace of each texel's data term (numerical safety only).
PASS1_RIDGE = 1e-9

#: Gauss–Newton steps of the normals per alternation of the normal refinement.
NORMAL_STEPS = 2
#: Default σ (degrees) of the normal refinement's prior towards the geometric normal.
DEFAULT_NORMAL_SIGMA = 5.0

__all__ = ["ReflectanceMaps", "fit_maps", "render_uv", "maps_from_arrays", "normalized_convolution", "fill_flagged",
           "FitMapsConfig", "SolverConfig", "SymmetryConfig", "PriorConfig", "AdamConfig", "NormalRefinementConfig"]


@dataclass
class ReflectanceMaps:
    """Result of :func:`fit_maps` (the ``reflectance-maps`` arrays, docs/fit-reflectance.md).

    albedo (3,S,S) linear diffuse C; weights (K,S,S) lobe weights W; exponents (K,); mask (S,S);
    residual (S,S) RMS radiance residual over the texel's fitted observations; conditioning (S,S) pooled
    rcond; observability (K,S,S) pooled lobe observability; flagged (S,S); obs_count (S,S) fitted observations
    of the texel itself; prior (3+K,S,S) the prior target x0; with normal refinement normal (3,S,S) the refined
    unit normals and normal_correction (S,S) their angle to the geometric normals (degrees); stats: solver
    statistics.
    """

    albedo: np.ndarray
    weights: np.ndarray
    exponents: np.ndarray
    mask: np.ndarray
    residual: np.ndarray
    conditioning: np.ndarray
    flagged: np.ndarray
    obs_count: np.ndarray
    observability: np.ndarray | None = None
    prior: np.ndarray | None = None
    normal: np.ndarray | None = None
    normal_correction: np.ndarray | None = None
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return int(self.albedo.shape[-1])

    def observable(self, observable_min: float = 0.1) -> np.ndarray:
        """(S,S) texels in the mask, not flagged, where every lobe reaches ``observable_min`` of its peak."""
        ok = self.mask & ~self.flagged
        if self.observability is not None:
            ok &= np.all(self.observability >= observable_min, axis=0)
        return ok

    def arrays(self) -> dict[str, np.ndarray]:
        out = {"albedo": self.albedo.astype(np.float32), "weights": self.weights.astype(np.float32),
               "exponents": np.asarray(self.exponents, np.float64), "mask": self.mask.astype(bool),
               "residual": self.residual.astype(np.float32), "conditioning": self.conditioning.astype(np.float32),
               "flagged": self.flagged.astype(bool), "obs_count": self.obs_count.astype(np.int32)}
        if self.observability is not None:
            out["observability"] = self.observability.astype(np.float32)
        if self.prior is not None:
            out["prior"] = self.prior.astype(np.float32)
        if self.normal is not None:
            out["normal"] = self.normal.astype(np.float32)
        if self.normal_correction is not None:
            out["normal_correction"] = self.normal_correction.astype(np.float32)
        return out


def maps_from_arrays(arrays: Mapping[str, np.ndarray], stats: dict | None = None) -> ReflectanceMaps:
    """A :class:`ReflectanceMaps` from artifact arrays (``read_artifact(path, 'reflectance-maps').arrays``)."""
    a = arrays
    alb = np.asarray(a["albedo"], np.float64)
    S = alb.shape[-1]
    return ReflectanceMaps(
        albedo=alb, weights=np.asarray(a["weights"], np.float64), exponents=np.asarray(a["exponents"], np.float64),
        mask=np.asarray(a["mask"], bool) if "mask" in a else np.ones((S, S), bool),
        residual=np.asarray(a.get("residual", np.zeros((S, S)))),
        conditioning=np.asarray(a.get("conditioning", np.zeros((S, S)))),
        flagged=np.asarray(a.get("flagged", np.zeros((S, S), bool)), bool),
        obs_count=np.asarray(a.get("obs_count", np.zeros((S, S), np.int32))),
        observability=np.asarray(a["observability"]) if "observability" in a else None,
        prior=np.asarray(a["prior"]) if "prior" in a else None,
        normal=np.asarray(a["normal"]) if "normal" in a else None,
        normal_correction=np.asarray(a["normal_correction"]) if "normal_correction" in a else None,
        stats=dict(stats or {}))


# --------------------------------------------------------------------------- helpers

def normalized_convolution(values: np.ndarray, weight: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian normalised convolution of (C,S,S) ``values`` with (S,S) or (C,S,S) confidence ``weight``.

    Returns (smoothed values, smoothed weight); values are meaningful where the smoothed weight > 0.
    """
    from scipy.ndimage import gaussian_filter

    w = np.broadcast_to(np.asarray(weight, np.float64), values.shape)
    num = np.stack([gaussian_filter(values[i] * w[i], sigma, mode="constant") for i in range(values.shape[0])])
    den = np.stack([gaussian_filter(w[i], sigma, mode="constant") for i in range(values.shape[0])])
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), 0.0)
    return out, den


def _as_arrays(obj) -> Mapping[str, np.ndarray]:
    """Arrays of an Artifact (``.arrays``) or the mapping itself."""
    return obj.arrays if hasattr(obj, "arrays") and isinstance(obj.arrays, Mapping) else obj


def _parse_pair_mask(pair_mask, P: int) -> np.ndarray:
    if pair_mask is None:
        return np.ones(P, bool)
    pm = np.asarray(pair_mask)
    if pm.dtype != bool:
        idx = pm.astype(int).reshape(-1)
        pm = np.zeros(P, bool)
        if idx.size and (idx.min() < 0 or idx.max() >= P):
            raise ReflectmmError(f"pair_mask indices out of range 0..{P - 1}")
        pm[idx] = True
    if pm.shape != (P,):
        raise ReflectmmError(f"pair_mask must be (P,) = ({P},) bool, got {pm.shape}")
    return pm


def _check_exponents(exponents) -> np.ndarray:
    """The fit's guard: :func:`shading.brdf.check_exponents` with the positivity and non-empty rules (one line
    that names the exponents), then its collinearity rule (:func:`check_distinct_exponents`)."""
    from reflectmm_cli.shading.brdf import ExponentError, check_distinct_exponents, check_exponents

    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    try:
        check_exponents(p, max_exponent=None, distinct=False)
    except ExponentError:
        raise ReflectmmError(f"exponents must be finite and > 0, got {p.tolist()}") from None
    check_distinct_exponents(p)
    return p


def _rowsum(a: np.ndarray) -> np.ndarray:
    """Sum of the 3 columns of an (R, 3) array (faster than .sum(1) for 3 columns)."""
    return a[:, 0] + a[:, 1] + a[:, 2]


class _Problem:
    """Observed (texel, pair) entries of the masked texels in compact, texel-sorted float64 arrays.

    ``tex (R,)`` texel position (0..n−1, sorted), ``d (R,)``, ``s (R,K)``, ``cos (R,)``, ``y (R,3)``;
    ``start (n+1,)`` row offsets.  Normal equations are segment sums over each texel's rows.
    """

    def __init__(self, obs, p, used, I, chunk, threads=1):
        S = np.asarray(obs["position"]).shape[0]
        self.S = S
        self.K = K = p.size
        self.chunk = int(chunk)
        mask = np.asarray(obs["mask"], bool)
        self.idx = np.flatnonzero(mask.reshape(-1))
        pos = np.asarray(obs["position"], np.float64).reshape(-1, 3)
        nrm = np.asarray(obs["normal"], np.float64).reshape(-1, 3)
        n = self.idx.size
        P = used.shape[0]
        # texel-major copies (one pass each) so that the per-texel gathers below are local
        rad = np.ascontiguousarray(np.moveaxis(np.asarray(obs["radiance"]).reshape(P, -1, 3), 0, 1)[self.idx])
        usedT = np.ascontiguousarray(used.reshape(P, -1).T[self.idx])
        pv = np.asarray(obs["pair_view"], np.int64)
        pf = np.asarray(obs["pair_flash"], np.int64)
        fpos = np.asarray(obs["flash_pos"], np.float64)[pf]  # (P,3)
        cpos = np.asarray(obs["cam_centers"], np.float64)[pv]
        Ip = np.asarray(I, np.float64)[pf]
        xm, nm = pos[self.idx], nrm[self.idx]
        nm = nm / np.where(np.linalg.norm(nm, axis=1, keepdims=True) > 0, np.linalg.norm(nm, axis=1,
                                                                                          keepdims=True), 1.0)
        # pass A: which (texel, pair) entries are valid (observed, n·l > 0, n·v > 0): sign tests by BLAS
        valid_chunks = []
        self.count = np.zeros(n, np.int64)
        for sl in iter_chunks(n, chunk):
            nx = np.einsum("nk,nk->n", nm[sl], xm[sl])[:, None]
            v = usedT[sl].copy()
            v &= (nm[sl] @ fpos.T - nx) > 0
            v &= (nm[sl] @ cpos.T - nx) > 0
            valid_chunks.append(v)
            self.count[sl] = v.sum(1)
        self.start = np.concatenate([[0], np.cumsum(self.count)]).astype(np.int64)
        R = int(self.start[-1])
        # pass B: design rows of the valid entries, written in place (texel-sorted)
        self.A = np.empty((R, 1 + K + 3))
        self.cos = np.empty(R)
        self.tex = np.empty(R, np.int64)
        self.pair = np.empty(R, np.int32)  # (view, flash) pair of each row (normal refinement rebuilds rows)
        ndh = np.empty(R)
        def fill(item):
            sl, v = item
            ti, pj = np.nonzero(v)
            r0, r1 = self.start[sl.start], self.start[sl.stop]
            cnt = self.count[sl]
            d, s_, c_, h_ = design_rows(np.repeat(xm[sl], cnt, axis=0), np.repeat(nm[sl], cnt, axis=0), fpos[pj],
                                        cpos[pj], Ip[pj], p)
            self.A[r0:r1, 0] = d
            self.A[r0:r1, 1:1 + K] = s_
            self.A[r0:r1, 1 + K:] = rad[sl][v]  # boolean gather: same (texel, pair) order as np.nonzero
            self.cos[r0:r1] = c_
            self.tex[r0:r1] = ti + sl.start
            self.pair[r0:r1] = pj
            ndh[r0:r1] = h_

        parallel_map(fill, list(zip(iter_chunks(n, chunk), valid_chunks)), threads)  # disjoint slices
        self.xm, self.nm0, self.nm = xm, nm, nm
        self.fpos, self.cpos, self.Ip, self.p = fpos, cpos, Ip, p
        self.threads = threads
        self.y = self.A[:, 1 + K:]
        self.rms = np.sqrt(np.bincount(self.tex, weights=_rowsum(self.y * self.y), minlength=n)
                           / (3 * np.maximum(self.count, 1)))
        self._cols = np.arange(self.tex.size, dtype=np.int64)
        self._iu = np.triu_indices(K)
        self._derived(ndh)

    def _derived(self, ndh: np.ndarray) -> None:
        """Column views, the per-texel Gram of the design columns and the lobe observability."""
        K, n, p = self.K, self.idx.size, self.p
        self.d = self.A[:, 0]
        self.s = np.ascontiguousarray(self.A[:, 1:1 + K])
        B = np.ascontiguousarray(self.A[:, :1 + K])
        self.G = (np.stack([self._segsum(B[:, a], B) for a in range(1 + K)], axis=1) if n
                  else np.zeros((0, 1 + K, 1 + K)))
        self.obsv = np.zeros((n, K))
        has = self.count > 0
        if ndh.size:  # max_j ndh_j^p = (max_j ndh_j)^p for p > 0
            with np.errstate(under="ignore"):
                self.obsv[has] = np.maximum.reduceat(ndh, self.start[:-1][has])[:, None] ** p
        self.ls_system = None

    def set_normals(self, nm: np.ndarray) -> None:
        """Re-evaluate the design columns of every row at new per-texel unit normals (n, 3).

        The rows (texel, pair) stay those chosen with the geometric normal; a row whose pair is behind the new
        normal (n·l ≤ 0 or n·v ≤ 0) gets zero columns and weight ⟨l,n⟩ = 0, like the model.
        """
        self.nm = np.asarray(nm, np.float64)
        n = self.idx.size
        ndh = np.empty(self.tex.size)

        def fill(sl):
            r0, r1 = self.start[sl.start], self.start[sl.stop]
            pj = self.pair[r0:r1]
            d, s_, c_, h_ = design_rows(np.repeat(self.xm[sl], self.count[sl], axis=0),
                                        np.repeat(self.nm[sl], self.count[sl], axis=0), self.fpos[pj],
                                        self.cpos[pj], self.Ip[pj], self.p)
            self.A[r0:r1, 0] = d
            self.A[r0:r1, 1:1 + self.K] = s_
            self.cos[r0:r1] = c_
            ndh[r0:r1] = h_

        parallel_map(fill, list(iter_chunks(n, self.chunk)), self.threads)
        self._derived(ndh)

    def _segsum(self, w: np.ndarray, X: np.ndarray, a: int = 0, b: int | None = None) -> np.ndarray:
        """(b−a, q) per-texel sums Σ_rows w_r · X_r over texels a..b−1 (a CSR product; rows sorted by texel)."""
        from scipy.sparse import csr_matrix

        b = self.idx.size if b is None else b
        r0 = self.start[a]
        R = self.start[b] - r0
        if getattr(self, "_cols", None) is None or self._cols.size < R:
            self._cols = np.arange(self.tex.size, dtype=np.int64)
        M = csr_matrix((w, self._cols[:R], self.start[a:b + 1] - r0), shape=(b - a, R))
        return np.asarray(M @ X)

    def residuals(self, x: np.ndarray, a: int = 0, b: int | None = None) -> np.ndarray:
        """(R, 3) model minus observation over texels a..b−1 for their solution x (b−a, 3+K)."""
        b = self.idx.size if b is None else b
        r0, r1 = self.start[a], self.start[b]
        cnt = self.count[a:b]
        C = np.repeat(x[:, :3], cnt, axis=0)
        W = np.repeat(x[:, 3:], cnt, axis=0)
        spec = np.einsum("rk,rk->r", self.s[r0:r1], W)
        r = C
        r *= self.d[r0:r1, None]
        r += spec[:, None]
        r -= self.y[r0:r1]
        return r

    def rss(self, x: np.ndarray) -> np.ndarray:
        """(n,) sum of squared residuals over each texel's rows and channels."""
        r = self.residuals(x)
        return np.bincount(self.tex, weights=_rowsum(r * r), minlength=self.idx.size)

    def normal_equations(self, x: np.ndarray | None, loss: str, delta: np.ndarray, a: int = 0,
                         b: int | None = None):
        """(H, g, objective, rss) of texels a..b−1 for their current solution x (b−a, m).

        x = None: weights ⟨l,n⟩ (the least-squares system).  Objective: Σ cos·|r| (l1) or Σ cos·r² (l2).
        Shapes: H (b−a, m, m), g (b−a, m), objective and rss (b−a,).
        """
        K = self.K
        b = self.idx.size if b is None else b
        n = b - a
        m = 3 + K
        r0, r1 = self.start[a], self.start[b]
        H = np.zeros((n, m, m))
        g = np.zeros((n, m))
        obj = np.zeros(n)
        rss = np.zeros(n)
        cos = self.cos[r0:r1]
        d, s, y = self.d[r0:r1], self.s[r0:r1], self.y[r0:r1]
        cnt = self.count[a:b]
        if x is not None:
            tex = self.tex[r0:r1] - a
            r = self.residuals(x, a, b)
            aa = np.abs(r)
            r2 = _rowsum(r * r)
            if loss == "l1":
                w = np.maximum(aa, np.repeat(delta[a:b], cnt)[:, None])
                np.divide(cos[:, None], w, out=w)
                o = cos * _rowsum(aa)
            else:
                w = np.repeat(cos[:, None], 3, axis=1)
                o = cos * r2
            obj = np.bincount(tex, weights=o, minlength=n)
            rss = np.bincount(tex, weights=r2, minlength=n)
        else:
            w = np.repeat(cos[:, None], 3, axis=1)
        X = self.A[r0:r1]  # [d, s, y]
        for c in range(3):
            blk = self._segsum(w[:, c] * d, X, a, b)  # Σ w_c d · [d, s_1..s_K, y_0, y_1, y_2]
            H[:, c, c] = blk[:, 0]
            H[:, c, 3:] = blk[:, 1:1 + K]
            H[:, 3:, c] = blk[:, 1:1 + K]
            g[:, c] = blk[:, 1 + K + c]
        ws = _rowsum(w)
        for k in range(K):
            H[:, 3 + k, 3:] = self._segsum(ws * s[:, k], s, a, b)
        g[:, 3:] = self._segsum(_rowsum(w * y), s, a, b)
        return H, g, obj, rss

    def bands(self, S: int, target_rows: int = 1 << 17) -> list[tuple[int, int]]:
        """Texel ranges made of whole UV rows (so closed under mirroring) with about ``target_rows`` observations."""
        n = self.idx.size
        if n == 0:
            return []
        row_start = np.searchsorted(self.idx, np.arange(S + 1) * S)  # first texel position of each UV row
        out, a = [], 0
        for r in range(1, S + 1):
            b = row_start[r]
            if b > a and (self.start[b] - self.start[a] >= target_rows or r == S):
                out.append((int(a), int(b)))
                a = b
        if a < n:
            out.append((int(a), n))
        return out


def fill_flagged(xmap: np.ndarray, solved: np.ndarray, flagged: np.ndarray, symmetry: float,
                  fallback: np.ndarray) -> tuple[np.ndarray, dict]:
    """Fill the ``flagged (S,S)`` texels of ``xmap (m,S,S)`` from their mirror texel where it is ``solved``,
    then by the normalised convolution of the solved neighbours (σ = 1.5 texels, doubled until reached), then
    from ``fallback (m,S,S)``.  Returns the filled map and the counts of each kind."""
    out = xmap.copy()
    todo = flagged.copy()
    n_mirror = 0
    if symmetry > 0:
        mir = solved[:, ::-1] & todo
        out[:, mir] = xmap[:, :, ::-1][:, mir]
        n_mirror = int(mir.sum())
        todo &= ~mir
    n_nb = 0
    sigma = 1.5
    while todo.any() and solved.any() and sigma <= 2 * xmap.shape[-1]:
        sm, den = normalized_convolution(xmap, solved.astype(np.float64), sigma)
        hit = todo & (den[0] > 1e-6)
        out[:, hit] = sm[:, hit]
        n_nb += int(hit.sum())
        todo &= ~hit
        sigma *= 2
    out[:, todo] = fallback[:, todo]
    return out, {"filled_mirror": n_mirror, "filled_neighbours": n_nb, "filled_prior": int(todo.sum())}


# --------------------------------------------------------------------------- public API

def _flat(name: str, default: Any) -> Any:
    """A settings field whose flat name (stage parameter, ``fit_maps(**settings)``) is ``name``, not its own."""
    return field(default=default, metadata={"flat": name})


@dataclass(frozen=True)
class SolverConfig:
    """The solver and the fast solver's settings.

    Fields (flat name in brackets where it differs):
        kind [solver]: ``fast`` (exact batched, default) or ``adam`` (the paper's reference, torch).
        loss: ``l1`` (cos-weighted L1, IRLS) or ``l2`` (cos-weighted least squares); Adam always uses L1.
        irls_iterations, irls_delta, irls_tol, irls_obj_tol: IRLS settings (l1): at most ``irls_iterations``
            reweighted solves per band of UV rows, stopping when the largest change of any unknown is below
            ``irls_tol`` × max |x| or the band's L1 objective changes by less than ``irls_obj_tol`` (relative).
        cond_min, min_obs: flagging thresholds (default min_obs = 1 + K pooled observations).
        observable_min: lobe observability needed to count a texel as observable for a lobe.
        chunk: texels per design block (memory).
        threads: worker threads of the fast solver (default min(cpu count, 4)); results do not depend on it.
    """

    kind: str = _flat("solver", "fast")
    loss: str = "l1"
    irls_iterations: int = 10
    irls_delta: float = 1e-3
    irls_tol: float = 1e-3
    irls_obj_tol: float = 1e-3
    cond_min: float = 1e-4
    min_obs: int | None = None
    observable_min: float = 0.1
    chunk: int = DEFAULT_CHUNK
    threads: int | None = None


@dataclass(frozen=True)
class SymmetryConfig:
    """Mirror pooling.

    Fields (flat name in brackets):
        weight [symmetry]: mirror pooling weight s ∈ [0, 1] (fast); Adam uses random flips when s > 0.
        mode [symmetry_mode]: ``adaptive`` (default): pool a texel whose own data are ill-posed with its mirror
            at weight s, and a well-posed one at weight s · (mirror trust), the trust being 1 where the face is as
            symmetric as the noise can tell and → 0 where it measurably is not (:func:`_mirror_trust`);
            ``ill-posed``: pool only texels whose own data cannot determine their unknowns (fewer than
            ``min_obs`` observations or conditioning < ``cond_min``); ``all``: pool every texel (the minimiser of
            the paper's random-flip objective). Fast solver only; the Adam solver always flips whole maps (the
            paper).
    """

    weight: float = _flat("symmetry", 1.0)
    mode: str = _flat("symmetry_mode", "adaptive")


@dataclass(frozen=True)
class PriorConfig:
    """The fast solver's prior.

    Fields (flat name in brackets):
        strength [prior]: Tikhonov strength relative to the trace of each texel's data term (0 = off).
        tail, tail_obs [prior_tail, prior_tail_obs]: extra prior on lobe weight W_i where the lobe is seen only in
            its tail: ``+ λ_t · tail · (1 − o_i / tail_obs)₊² · (W_i − x0_i)²`` (λ_t = strength · trace(H_t), so
            it scales with ``strength``; default 100 × 1e-4 = 1e-2 × trace at o_i = 0) with o_i the lobe's pooled
            observability (the largest fraction of its peak any fitted observation reaches). A weight fitted
            from the tail of its lobe extrapolates badly to views that see the peak, and the tail is where a
            Blinn-Phong lobe matches a real (GGX) lobe least. 0 = off; off also when ``strength`` is 0.
        sigma [prior_sigma]: σ (texels) of the neighbourhood prior (default S/16).
    """

    strength: float = _flat("prior", 1e-4)
    tail: float = _flat("prior_tail", 100.0)
    tail_obs: float = _flat("prior_tail_obs", 0.5)
    sigma: float | None = _flat("prior_sigma", None)


@dataclass(frozen=True)
class AdamConfig:
    """The Adam reference solver: steps, lr, w_reg, init (the constant (C, W) start, default 0.3, 0.1), device,
    seed (of the random flips). Flat names are the field names."""

    steps: int = 1000
    lr: float = 5e-3
    w_reg: float = 100.0
    init: tuple[float, float] | None = None
    device: str = "cpu"
    seed: int = 0


@dataclass(frozen=True)
class NormalRefinementConfig:
    """Photometric normal refinement (fast solver; :mod:`.normals`).

    Fields (flat name in brackets):
        iterations [refine_normals]: this many alternations of ``NORMAL_STEPS`` damped Gauss–Newton steps of each
            solved texel's normal (reflectance fixed) and the reflectance solve (normals fixed); 0 = off.
        sigma [normal_sigma]: σ (degrees) of the Gaussian prior of the refined normal towards the geometric one.
    """

    iterations: int = _flat("refine_normals", 0)
    sigma: float = _flat("normal_sigma", DEFAULT_NORMAL_SIGMA)


#: The nested settings of :class:`FitMapsConfig`: field name → its class.
_GROUPS = {"solver": SolverConfig, "symmetry": SymmetryConfig, "prior": PriorConfig, "adam": AdamConfig,
           "normals": NormalRefinementConfig}


@dataclass(frozen=True)
class FitMapsConfig:
    """Settings of :func:`fit_maps`, declared once and nested by concern (the fit-reflectance stage takes its
    defaults from here).

    Fields:
        exponents: (K,) lobe exponents (K = 1 is the global-exponent representation).
        solver: :class:`SolverConfig`; symmetry: :class:`SymmetryConfig`; prior: :class:`PriorConfig`;
        adam: :class:`AdamConfig`; normals: :class:`NormalRefinementConfig`.

    Every setting also has one flat name (:meth:`flat_names`: the stage parameters and CLI options, and
    ``fit_maps(obs, loss="l2")``): :meth:`from_flat` and :meth:`with_flat` build a config from flat settings,
    :meth:`flat` gives them back.
    """

    exponents: tuple[float, ...] = tuple(DEFAULT_EXPONENTS)
    solver: SolverConfig = field(default_factory=SolverConfig)
    symmetry: SymmetryConfig = field(default_factory=SymmetryConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    adam: AdamConfig = field(default_factory=AdamConfig)
    normals: NormalRefinementConfig = field(default_factory=NormalRefinementConfig)

    def __post_init__(self) -> None:
        for name, cls in _GROUPS.items():
            if not isinstance(getattr(self, name), cls):
                raise TypeError(f"FitMapsConfig.{name} must be a {cls.__name__}, got {getattr(self, name)!r} "
                                f"(flat settings: FitMapsConfig.from_flat({name}=...))")

    @staticmethod
    def flat_names() -> dict[str, tuple[str | None, str]]:
        """Flat name → (nested settings field or None for a top-level one, field name), in declaration order."""
        out: dict[str, tuple[str | None, str]] = {}
        for f in fields(FitMapsConfig):
            if f.name in _GROUPS:
                for g in fields(_GROUPS[f.name]):
                    out[g.metadata.get("flat", g.name)] = (f.name, g.name)
            else:
                out[f.name] = (None, f.name)
        return out

    @classmethod
    def from_flat(cls, **settings: Any) -> "FitMapsConfig":
        """The defaults with flat settings (``FitMapsConfig.from_flat(loss="l2", symmetry=0.5)``)."""
        return cls().with_flat(**settings)

    def with_flat(self, **settings: Any) -> "FitMapsConfig":
        """A copy with flat settings replaced; an unknown name is a TypeError naming it."""
        names = self.flat_names()
        top: dict[str, Any] = {}
        nested: dict[str, dict[str, Any]] = {}
        for k, v in settings.items():
            if k not in names:
                raise TypeError(f"unknown setting {k!r}")
            group, name = names[k]
            if group is None:
                top[name] = v
            else:
                nested.setdefault(group, {})[name] = v
        return replace(self, **top, **{g: replace(getattr(self, g), **kw) for g, kw in nested.items()})

    def flat(self) -> dict[str, Any]:
        """Flat name → value of every setting."""
        return {k: getattr(self, name) if group is None else getattr(getattr(self, group), name)
                for k, (group, name) in self.flat_names().items()}

    def check(self) -> None:
        """Raise ReflectmmError naming the first bad setting (by its flat name)."""
        s, sym, pr, nr = self.solver, self.symmetry, self.prior, self.normals
        _check_exponents(self.exponents)
        if s.kind not in ("fast", "adam"):
            raise ReflectmmError(f"solver must be 'fast' or 'adam', got {s.kind!r}")
        if s.loss not in ("l1", "l2"):
            raise ReflectmmError(f"loss must be 'l1' or 'l2', got {s.loss!r}")
        if not (0.0 <= float(sym.weight) <= 1.0):
            raise ReflectmmError(f"symmetry must be in [0, 1], got {sym.weight}")
        if sym.mode not in SYMMETRY_MODES:
            raise ReflectmmError(f"symmetry_mode must be one of {', '.join(SYMMETRY_MODES)}, "
                                 f"got {sym.mode!r}")
        if not (np.isfinite(pr.strength) and pr.strength >= 0):
            raise ReflectmmError(f"prior must be finite and >= 0, got {pr.strength}")
        if not (np.isfinite(pr.tail) and pr.tail >= 0):
            raise ReflectmmError(f"prior_tail must be finite and >= 0, got {pr.tail}")
        if not (np.isfinite(pr.tail_obs) and 0 < pr.tail_obs <= 1):
            raise ReflectmmError(f"prior_tail_obs must be in (0, 1], got {pr.tail_obs}")
        if int(nr.iterations) != nr.iterations or nr.iterations < 0:
            raise ReflectmmError(f"refine_normals must be an integer >= 0, got {nr.iterations}")
        if not (np.isfinite(nr.sigma) and nr.sigma > 0):
            raise ReflectmmError(f"normal_sigma must be finite and > 0 (degrees), got {nr.sigma}")
        if nr.iterations > 0 and s.kind != "fast":
            raise ReflectmmError("normal refinement (refine_normals > 0) needs the fast solver; use "
                                 "refine_normals=0 with solver='adam'")


def fit_maps(obs: Mapping[str, np.ndarray], config: FitMapsConfig | None = None, *, pair_mask=None,
             flash_intensity=None, progress: Callable | None = None, path=None, **settings) -> ReflectanceMaps:
    """Fit diffuse albedo C (3,S,S) and lobe weights W (K,S,S) to one identity's uv-observations.

    Args:
        obs: uv-observations arrays (docs/pipeline.md); ``radiance`` may be float16.
        config: the solver's settings (:class:`FitMapsConfig`; default: its defaults).
        settings: single settings overriding ``config`` by their flat names (``fit_maps(obs, loss="l2", prior=0)``;
            :meth:`FitMapsConfig.flat_names`).
        pair_mask: (P,) bool or indices of the (view, flash) pairs used for fitting (default all).
        flash_intensity: scalar or (F,) radiant intensity replacing the artifact's (global scale ambiguity:
            multiplying it by k divides C and W by k).
        progress: optional wrapper ``progress(iterable, desc=..., total=...)`` for progress bars.
        path: file name used in error messages.
    Returns:
        :class:`ReflectanceMaps`.
    Raises:
        ReflectmmError on malformed observations (shapes, NaN/inf radiance in observed texels), bad settings.
    """
    t0 = time.perf_counter()
    cfg = _settings(config, settings)
    threads = cfg.solver.threads if cfg.solver.threads is not None else default_threads(4)
    obs = _as_arrays(obs)
    S = check_observations(obs, path)
    p = _check_exponents(cfg.exponents)
    prob, pm = _observations_problem(obs, p, pair_mask, flash_intensity, cfg.solver.chunk, threads)
    tp = _texel_problem(prob, S, cfg, progress, threads)
    stats = _setup_stats(tp, cfg, n_pairs_used=int(pm.sum()))
    normal_map = correction_map = None
    if cfg.solver.kind == "fast":
        x, prior_map, info = _fast(tp)
        if cfg.normals.iterations > 0:
            x, prior_map, info, tp, ref = _refine_normals(tp, x)
            normal_map, correction_map = ref.normal_map, ref.correction_map
            stats["normal_refinement"] = ref.stats
        stats.update(info)
    else:
        x, info = _adam(tp)
        prior_map = None
        stats.update(info)
        # flagged texels (a property of the data, not of the solver) are filled as for the fast solver
    xfill, finfo = _filled_maps(tp, x, prior_map)
    stats.update(finfo)
    resid = _residual_rms(tp.prob, xfill, tp.texels)
    stats["residual_rms_median"] = float(np.median(resid[prob.count > 0])) if np.any(prob.count > 0) else 0.0
    stats["time_s"] = time.perf_counter() - t0
    stats.update(_observable_stats(tp))
    to_map = tp.texels.to_map
    return ReflectanceMaps(
        albedo=xfill[:3], weights=xfill[3:], exponents=p, mask=tp.texels.mask, residual=to_map(resid),
        conditioning=to_map(tp.cond), flagged=to_map(tp.flag.astype(float)) > 0,
        obs_count=to_map(prob.count).astype(np.int32), observability=to_map(tp.obsv), prior=prior_map,
        normal=normal_map, normal_correction=correction_map, stats=stats)


def _settings(config: FitMapsConfig | None, settings: dict) -> FitMapsConfig:
    """``config`` (default: the defaults) with the single ``settings`` overriding it by name, checked."""
    try:
        cfg = (config or FitMapsConfig()).with_flat(**settings)
    except TypeError as e:
        raise TypeError(f"fit_maps: {e}; the settings are FitMapsConfig.flat_names()") from None
    cfg.check()
    return cfg


def _observations_problem(obs, p: np.ndarray, pair_mask, flash_intensity, chunk: int, threads: int):
    """(:class:`_Problem` of the fitted (texel, pair) entries, (P,) bool mask of the pairs used)."""
    P = np.asarray(obs["pair_view"]).shape[0]
    pm = _parse_pair_mask(pair_mask, P)
    used = np.asarray(obs["observed"], bool) & pm[:, None, None]
    F = np.asarray(obs["flash_pos"]).shape[0]
    I = pair_irradiance(obs["flash_intensity"], F, flash_intensity)
    return _Problem(obs, p, used, I, chunk, threads), pm


@dataclass(frozen=True)
class _Texels:
    """The masked texels of an S×S map: ``idx`` (n,) their positions in the flattened map, in order."""

    S: int
    idx: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(S, S) bool."""
        m = np.zeros(self.S * self.S, bool)
        m[self.idx] = True
        return m.reshape(self.S, self.S)

    def to_map(self, v: np.ndarray, fill=0.0) -> np.ndarray:
        """Per-texel values (n, ...) as a float64 map (..., S, S); ``fill`` outside the mask."""
        S = self.S
        v = np.asarray(v)
        out = np.full((S * S,) + v.shape[1:], fill, dtype=np.float64)
        out[self.idx] = v
        return np.moveaxis(out.reshape((S, S) + v.shape[1:]), (0, 1), (-2, -1)) if v.ndim > 1 else out.reshape(S, S)

    def from_map(self, a: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`to_map` for a (m, S, S) map: (n, m)."""
        return np.moveaxis(a.reshape(a.shape[0], -1), 0, 1)[self.idx]


@dataclass(frozen=True)
class _Mirror:
    """Mirror pooling of per-texel quantities: texel t gets its own plus s_t × its mirror's.

    ``symv`` (n,) s_t (0 where the mirror is not a masked texel), ``mp`` (n,) the mirror's position among the
    masked texels (0 where there is none), ``has_m`` (n,) whether there is one, ``sym`` the symmetry setting
    (0: pooling is the identity), ``info`` the mirror-trust statistics.
    """

    symv: np.ndarray
    mp: np.ndarray
    has_m: np.ndarray
    sym: float
    info: dict = field(default_factory=dict)

    def pool(self, a: np.ndarray) -> np.ndarray:
        """``a`` (n, ...) pooled over every masked texel."""
        if self.sym == 0:
            return a
        sh = (-1,) + (1,) * (a.ndim - 1)
        return a + self.symv.reshape(sh) * a[self.mp]

    def pool_band(self, a_: np.ndarray, lo: int, hi: int) -> np.ndarray:
        """:meth:`pool` for the texels lo..hi−1 of a band closed under mirroring (a_ holds that band only)."""
        if self.sym == 0:
            return a_
        hm = self.has_m[lo:hi]
        loc = np.where(hm, self.mp[lo:hi] - lo, 0)
        return a_ + self.symv[lo:hi].reshape((-1,) + (1,) * (a_.ndim - 1)) * a_[loc]

    @property
    def pooled(self) -> np.ndarray:
        """(n,) texels pooled with their mirror."""
        return self.symv > 0

    def pooled_observability(self, obsv: np.ndarray) -> np.ndarray:
        """(n, K) the better of a pooled texel's and its mirror's lobe observability."""
        return np.where(self.pooled[:, None], np.maximum(obsv, obsv[self.mp]), obsv)


def _mirror(prob: _Problem, S: int, cfg: FitMapsConfig, min_obs: int, threads: int) -> _Mirror:
    """The mirror pooling of ``cfg``: weight s everywhere ("all", the paper's flip), s only where the texel's own
    data cannot determine its unknowns ("ill-posed": fewer than ``min_obs`` observations or conditioning <
    ``cond_min``), or s × the mirror trust where they can ("adaptive"); 0 where the mirror is not masked."""
    idx = prob.idx
    n = idx.size
    sym = float(cfg.symmetry.weight)
    mirror = mirror_index(S)
    pos_of = -np.ones(S * S, np.int64)
    pos_of[idx] = np.arange(n)
    mpos = pos_of[mirror[idx]]  # position of each masked texel's mirror among the masked texels (-1: none)
    has_m = mpos >= 0
    mp = np.where(has_m, mpos, 0)
    symv = np.full(n, sym)
    sym_info: dict[str, Any] = {}
    if sym > 0 and cfg.symmetry.mode in ("ill-posed", "adaptive") and cfg.solver.kind == "fast":
        own_cond = gram_conditioning(prob.G) if n else np.zeros(0)
        ill = (prob.count < min_obs) | (own_cond < cfg.solver.cond_min)
        if cfg.symmetry.mode == "adaptive" and n:
            wt, sym_info = _mirror_trust(prob, ~ill, has_m, mp, idx=idx, S=S, m=3 + prob.K,
                                         sigma=max(S / 16.0, 1.0), threads=threads)
            symv = np.where(ill, sym, sym * wt)
        else:
            symv = np.where(ill, sym, 0.0)
    symv = np.where(has_m, symv, 0.0)
    return _Mirror(symv=symv, mp=mp, has_m=has_m, sym=sym, info=sym_info)


@dataclass(frozen=True)
class _TexelProblem:
    """What the solvers of :func:`fit_maps` share: the observations' problem, the mirror pooling, the texels
    solved (``solve``; the others are flagged: ``flag``), the pooled lobe observability ``obsv`` (n, K) and
    conditioning ``cond`` (n,), the IRLS δ per texel, the neighbourhood prior's σ, the settings and the execution
    details (progress wrapper, threads)."""

    prob: _Problem
    texels: _Texels
    mirror: _Mirror
    solve: np.ndarray
    flag: np.ndarray
    obsv: np.ndarray
    cond: np.ndarray
    delta: np.ndarray
    min_obs: int
    prior_sigma: float
    cfg: FitMapsConfig
    progress: Callable | None = None
    threads: int = 1


def _texel_problem(prob: _Problem, S: int, cfg: FitMapsConfig, progress, threads: int) -> _TexelProblem:
    """Mirror pooling, then flag the texels whose pooled data cannot be solved (fewer than ``min_obs`` pooled
    observations or pooled conditioning < ``cond_min``)."""
    n = prob.idx.size
    min_obs = 1 + prob.K if cfg.solver.min_obs is None else int(cfg.solver.min_obs)
    mirror = _mirror(prob, S, cfg, min_obs, threads)
    Gp = mirror.pool(prob.G)
    cnt_p = prob.count + np.where(mirror.pooled, prob.count[mirror.mp], 0)
    cond = gram_conditioning(Gp) if n else np.zeros(0)
    flag = (cnt_p < min_obs) | (cond < cfg.solver.cond_min)
    return _TexelProblem(prob=prob, texels=_Texels(S, prob.idx), mirror=mirror, solve=~flag, flag=flag,
                         obsv=mirror.pooled_observability(prob.obsv), cond=cond,
                         delta=cfg.solver.irls_delta * np.maximum(prob.rms, 1e-30), min_obs=min_obs,
                         prior_sigma=cfg.prior.sigma if cfg.prior.sigma is not None else max(S / 16.0, 1.0),
                         cfg=cfg, progress=progress, threads=threads)


def _setup_stats(tp: _TexelProblem, cfg: FitMapsConfig, n_pairs_used: int) -> dict[str, Any]:
    """The statistics of the settings and the problem, before solving."""
    fast = cfg.solver.kind == "fast"
    return {"solver": cfg.solver.kind, "loss": cfg.solver.loss if fast else "l1", "symmetry": tp.mirror.sym,
            "symmetry_mode": cfg.symmetry.mode if fast else "all",
            "n_pooled": int((tp.mirror.symv > 0).sum()), **tp.mirror.info,
            "prior": float(cfg.prior.strength), "prior_tail": float(cfg.prior.tail),
            "prior_tail_obs": float(cfg.prior.tail_obs), "n_texels": int(tp.prob.idx.size),
            "n_pairs_used": n_pairs_used,
            "n_flagged": int(tp.flag.sum()), "cond_min": cfg.solver.cond_min, "min_obs": tp.min_obs}


@dataclass(frozen=True)
class _RefinedNormals:
    """The normal refinement's maps: refined unit normals (3,S,S), their angle to the geometric ones (S,S) in
    degrees, and its statistics."""

    normal_map: np.ndarray
    correction_map: np.ndarray
    stats: dict


def _refine_normals(tp: _TexelProblem, x: np.ndarray):
    """Alternate Gauss–Newton steps of the normals with (C, W) fixed and the reflectance solve again with the
    design re-evaluated at the new normals (rows, flags and mirror weights stay those of the geometric normals).

    Returns (x, prior map, solver info, the problem at the refined normals (its observability and conditioning
    re-evaluated), :class:`_RefinedNormals`)."""
    cfg, prob, solve, to_map = tp.cfg, tp.prob, tp.solve, tp.texels.to_map
    ref = NormalRefinement(prob, cfg.normals.sigma, cfg.solver.loss, tp.delta, solve, chunk=cfg.solver.chunk,
                           threads=tp.threads, ridge=float(cfg.prior.strength))
    hist = []
    for _ in range(int(cfg.normals.iterations)):
        xs = x
        for _ in range(NORMAL_STEPS):
            st = ref.step(xs)
            xs = ref.x
        prob.set_normals(ref.normals)
        tp = replace(tp, obsv=tp.mirror.pooled_observability(prob.obsv))
        x, prior_map, info = _fast(tp)
        hist.append(st)
    tp = replace(tp, cond=gram_conditioning(tp.mirror.pool(prob.G)) if prob.idx.size else np.zeros(0))
    ang = correction_angle_deg(ref.delta)
    stats = {"iterations": int(cfg.normals.iterations), "gn_steps": NORMAL_STEPS,
             "sigma_deg": float(cfg.normals.sigma), "history": hist,
             "angle_median_deg": float(np.median(ang[solve])) if solve.any() else 0.0,
             "angle_p90_deg": float(np.percentile(ang[solve], 90))
             if solve.any() else 0.0}
    refined = _RefinedNormals(normal_map=np.where(tp.texels.mask[None], to_map(prob.nm), 0.0),
                              correction_map=to_map(ang), stats=stats)
    return x, prior_map, info, tp, refined


def _adam(tp: _TexelProblem) -> tuple[np.ndarray, dict]:
    """The paper's Adam reference solver (:mod:`.adam`) on the same problem: (x (n, 3+K), info)."""
    from .adam import fit_adam

    a = tp.cfg.adam
    return fit_adam(tp.prob, tp.texels.idx, tp.texels.S, tp.prob.K, steps=a.steps, lr=a.lr, w_reg=a.w_reg,
                    symmetry=tp.mirror.sym, init=a.init, device=a.device, seed=a.seed, progress=tp.progress)


def _filled_maps(tp: _TexelProblem, x: np.ndarray, prior_map: np.ndarray | None) -> tuple[np.ndarray, dict]:
    """The solution (m, S, S) with the flagged texels filled (:func:`fill_flagged`; the fallback is the prior
    map, else the median solution), clipped at 0, zero outside the mask; and the fill statistics."""
    to_map, mask = tp.texels.to_map, tp.texels.mask
    m = x.shape[1]
    xmap = to_map(x)  # (m,S,S)
    fallback = prior_map if prior_map is not None else np.broadcast_to(
        np.median(x[tp.solve], axis=0)[:, None, None] if tp.solve.any() else np.zeros((m, 1, 1)), xmap.shape)
    xfill, finfo = fill_flagged(xmap, to_map(tp.solve.astype(float)) > 0, to_map(tp.flag.astype(float)) > 0,
                                 tp.mirror.sym, fallback)
    return np.where(mask[None], np.maximum(xfill, 0.0), 0.0), finfo


def _residual_rms(prob: _Problem, xfill: np.ndarray, texels: _Texels) -> np.ndarray:
    """(n,) RMS radiance residual of the filled maps over each texel's own fitted observations."""
    rss = prob.rss(texels.from_map(xfill))
    return np.sqrt(rss / np.maximum(3 * prob.count, 1))


def _observable_stats(tp: _TexelProblem) -> dict[str, Any]:
    """Solved texels where every lobe is observable, and per lobe the solved texels where it is not."""
    omin = tp.cfg.solver.observable_min
    obs_ok = tp.solve & np.all(tp.obsv >= omin, axis=1)
    return {"n_observable": int(obs_ok.sum()),
            "n_unobservable_lobe": [int((~(tp.obsv[:, k] >= omin) & tp.solve).sum()) for k in range(tp.prob.K)]}


def _mirror_trust(prob, own_ok, has_m, mp, idx, S, m, sigma, threads=1):
    """Weight in [0, 1] of the mirror texel's data for each texel whose own data are well-posed.

    Each well-posed texel's own weighted least-squares solution x_t and its noise variance
    ``v_t = σ_t² · diag(H_t⁻¹) · mean(⟨l,n⟩)`` (σ_t² from its residuals) give, for the diffuse unknowns, the
    mirror difference ``D = x_t − x_mirror``.  Its local excess ``τ² = ⟨D²⟩ − ⟨v_t + v_mirror⟩`` (normalised
    convolution over well-posed pairs, σ = ``sigma`` texels, clipped at 0) is the variance of the face's own
    asymmetry; the mirror's data then deserve the weight ``v_mirror / (v_mirror + τ²)`` (its estimate is worth as
    much as a measurement of variance ``v_mirror + τ²``): 1 on a symmetric face (pooling halves the noise), → 0
    where the face differs from its mirror by more than the noise (no bias from pooling).  The same is done for
    every unknown the texel's data measure (noise below its value) and the texel takes the smallest weight (an
    asymmetric lobe weight vetoes pooling as much as an asymmetric albedo).
    """
    n = own_ok.size
    H = np.zeros((n, m, m))
    g = np.zeros((n, m))

    def ls_band(ab):  # weights ⟨l,n⟩ (x = None: the loss and δ do not enter)
        H[ab[0]:ab[1]], g[ab[0]:ab[1]] = prob.normal_equations(None, "l2", np.zeros(n), ab[0], ab[1])[:2]

    parallel_map(ls_band, prob.bands(S), threads)
    prob.ls_system = (H, g)  # reused by the first pass of the fast solver
    ok = own_ok & (prob.count > m)
    x = np.zeros((n, m))
    Hinv_d = np.zeros((n, m))  # (only texels with their own solution enter the statistics below)
    if ok.any():
        Hk = H[ok] + PASS1_RIDGE * np.einsum("nii->n", H[ok])[:, None, None] * np.eye(m)
        Hi = np.linalg.inv(Hk)
        x[ok] = np.einsum("nij,nj->ni", Hi, g[ok])
        Hinv_d[ok] = np.einsum("nii->ni", Hi)
    rss = prob.rss(x)
    sig2 = rss / np.maximum(3 * prob.count - m, 1)
    cbar = np.bincount(prob.tex, weights=prob.cos, minlength=n) / np.maximum(prob.count, 1)
    var = sig2[:, None] * Hinv_d * cbar[:, None]                               # (n, m)
    pair = ok & has_m & ok[mp]
    D2 = np.where(pair[:, None], (x - x[mp]) ** 2, 0.0)
    V2 = np.where(pair[:, None], var + var[mp], 0.0)
    vm = np.where(pair[:, None], var[mp], 0.0)

    def smooth(a):
        full = np.zeros((a.shape[1], S * S))
        full[:, idx] = a.T
        wfull = np.zeros(S * S)
        wfull[idx] = pair.astype(float)
        out, den = normalized_convolution(full.reshape(-1, S, S), wfull.reshape(S, S), sigma)
        return np.moveaxis(out.reshape(a.shape[1], -1), 0, 1)[idx], den[0].reshape(-1)[idx]

    sD2, den = smooth(D2)
    sV2, _ = smooth(V2)
    svm, _ = smooth(vm)
    tau2 = np.clip(sD2 - sV2, 0.0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        wj = svm / np.maximum(svm + tau2, 1e-300)
        # an unknown its data barely measure (noise above its value, e.g. a lobe seen only in its tail) can show
        # no asymmetry; it leans on the mirror anyway and does not vote
        sx2, _ = smooth(np.where(pair[:, None], x * x, 0.0))
        wj = np.where(svm < sx2, wj, 1.0)
        w = np.where(den > 1e-3, np.min(wj, axis=1), 0.0)
    w = np.where(ok, np.clip(np.nan_to_num(w), 0.0, 1.0), 0.0)
    info = {"mirror_trust_median": float(np.median(w[ok])) if ok.any() else 0.0,
            "asymmetry_rel_median": float(np.median(np.sqrt(tau2[pair, :3].mean(1)) /
                                                    np.maximum(np.abs(x[pair, :3]).mean(1), 1e-30)))
            if pair.any() else 0.0}
    return w, info


def _solve_system(H, g, lam, x0):
    """NNLS of (H + Λ) x = g + Λ x0 with Λ = diag(lam): lam (n,) isotropic or (n, m) per unknown."""
    m = H.shape[-1]
    lv = lam[:, None] * np.ones(m) if lam.ndim == 1 else lam
    Hr = H.copy()
    Hr[:, np.arange(m), np.arange(m)] += lv
    gr = g + lv * x0
    x, info = nnls_batched(Hr, gr)
    return x, info, Hr, gr


def _fast(tp: _TexelProblem):
    """The fast solver on the problem ``tp``: (x (n, m), prior map x0 (m, S, S), info).

    Pass 1 (:func:`_first_pass`) builds the neighbourhood prior (:func:`_neighbourhood_prior`); pass 2 solves the
    real objective towards it band by band (:func:`_irls_band`: whole UV rows, closed under mirroring, so each
    band's IRLS runs on cache-sized data and converges on its own).
    """
    info: dict[str, Any] = {}
    bands = tp.prob.bands(tp.texels.S)
    x, Hp, gp = _first_pass(tp, bands)
    x0m, x0, glob = _neighbourhood_prior(tp, x)
    info["prior_global"] = glob.tolist()
    if float(tp.cfg.prior.strength) == 0:
        x0 = np.zeros_like(x0)
    nn_iters = unconv = max_it = 0
    kkt = 0.0
    # bands are independent: numpy releases the GIL in the heavy loops, so threads use the cores
    results = parallel_map(lambda ab: _irls_band(tp, Hp, gp, x, x0, ab), bands, tp.threads, lazy=True)
    if tp.progress is not None and bands:
        results = tp.progress(results, desc="IRLS", total=len(bands), unit="band")
    for a, b, xb, st in results:
        x[a:b] = xb
        nn_iters, unconv = max(nn_iters, st[0]), unconv + st[1]
        kkt, max_it = max(kkt, st[2]), max(max_it, st[3])
    info.update({"irls_iterations": max_it if tp.cfg.solver.loss == "l1" else 0, "n_bands": len(bands),
                 "nnls_iterations_max": nn_iters,
                 "nnls_unconverged": unconv, "kkt_violation_max": kkt})
    return x, x0m, info


def _first_pass(tp: _TexelProblem, bands: list[tuple[int, int]]):
    """Weighted least squares (weights ⟨l,n⟩) with a negligible ridge, only to build the neighbourhood prior from
    the observable unknowns (unobservable ones never enter it): (x (n, m), pooled H (n, m, m), pooled g (n, m));
    x is 0 on the flagged texels."""
    prob = tp.prob
    n, m = prob.idx.size, 3 + prob.K
    sel = np.flatnonzero(tp.solve)
    x = np.zeros((n, m))
    H = np.zeros((n, m, m))
    g = np.zeros((n, m))
    cached = getattr(prob, "ls_system", None)  # the ⟨l,n⟩-weighted system, if the mirror trust built it already
    if cached is not None:
        H[:], g[:] = cached
    else:
        def ls_band(ab):
            H[ab[0]:ab[1]], g[ab[0]:ab[1]] = prob.normal_equations(None, tp.cfg.solver.loss, tp.delta, ab[0], ab[1])[:2]

        parallel_map(ls_band, bands, tp.threads)
    Hp, gp = tp.mirror.pool(H), tp.mirror.pool(g)
    tr = np.einsum("nii->n", Hp)
    lam = PASS1_RIDGE * tr
    if sel.size:
        x1, _, _, _ = _solve_system(Hp[sel], gp[sel], lam[sel], np.zeros((sel.size, m)))
        x[sel] = x1
    return x, Hp, gp


def _neighbourhood_prior(tp: _TexelProblem, x: np.ndarray):
    """The prior target x0 from pass 1's solution ``x``: normalised convolution (σ = ``prior_sigma``) over the
    texels where each unknown is observable (C: every solved texel; W_i: lobe observability ≥
    ``observable_min``), the median of those texels where none is near. Returns (x0 map (m, S, S), x0 (n, m),
    the medians (m,))."""
    m = x.shape[1]
    sel = np.flatnonzero(tp.solve)
    conf = np.zeros_like(x)
    conf[sel, :3] = 1.0
    conf[sel, 3:] = (tp.obsv[sel] >= tp.cfg.solver.observable_min).astype(float)
    xm = tp.texels.to_map(x)
    cm = tp.texels.to_map(conf)
    x0m, den = normalized_convolution(xm, cm, tp.prior_sigma)
    glob = np.array([np.median(x[:, j][conf[:, j] > 0]) if np.any(conf[:, j] > 0) else 0.0 for j in range(m)])
    x0m = np.where(den > 1e-3, x0m, glob[:, None, None])
    return x0m, tp.texels.from_map(x0m), glob


def _irls_band(tp: _TexelProblem, Hp: np.ndarray, gp: np.ndarray, x: np.ndarray, x0: np.ndarray,
               ab: tuple[int, int]):
    """Pass 2 on the texels a..b−1 (a band closed under mirroring): the real objective towards ``x0`` (Tikhonov
    λ_t = prior · trace(H_t), plus the tail prior on lobes seen only in their tail), non-negative, reweighted
    (l1) until the solution or the objective stops changing. Starts from pass 1's pooled system (``Hp``, ``gp``)
    and solution ``x``. Returns (a, b, the band's x (b−a, m), [NNLS iterations, unconverged, KKT violation,
    IRLS iterations])."""
    cfg, prob, solve, delta = tp.cfg, tp.prob, tp.solve, tp.delta
    loss, prior = cfg.solver.loss, float(cfg.prior.strength)
    prior_tail, prior_tail_obs = float(cfg.prior.tail), float(cfg.prior.tail_obs)
    n_it = 1 if loss == "l2" else max(int(cfg.solver.irls_iterations), 1)
    a, b = ab
    sl = slice(a, b)
    loc = np.flatnonzero(solve[sl])
    stat = [0, 0, 0.0, 0]  # NNLS iterations, unconverged, KKT violation, IRLS iterations
    xb = x[sl].copy()
    if loc.size == 0:
        return a, b, xb, stat
    Hb, gb = Hp[sl], gp[sl]
    x0b = x0[sl]
    last_obj = None
    for it in range(n_it):
        if it > 0:
            H, g, obj, _ = prob.normal_equations(xb, loss, delta, a, b)
            Hb, gb = tp.mirror.pool_band(H, a, b), tp.mirror.pool_band(g, a, b)
        # (it = 0: the ⟨l,n⟩-weighted system of pass 1 is reused as is)
        tr = np.einsum("nii->n", Hb[loc])
        lam = prior * tr
        if prior > 0 and prior_tail > 0:  # per unknown: lobes seen only in their tail lean on the prior
            short = np.clip(1.0 - tp.obsv[a:b][loc] / prior_tail_obs, 0.0, 1.0) ** 2
            lam = np.concatenate([np.repeat(lam[:, None], 3, axis=1),
                                  lam[:, None] * (1.0 + prior_tail * short)], axis=1)
        xs, nfo, Hr, gr = _solve_system(Hb[loc], gb[loc], lam, x0b[loc])
        stat[0] = max(stat[0], nfo["iterations"])
        stat[1] += nfo["unconverged"]
        stat[2] = max(stat[2], float(kkt_violation(Hr, gr, xs).max()))
        change = np.abs(xs - xb[loc]).max() / max(np.abs(xs).max(), 1e-30)
        xb[loc] = xs
        stat[3] = it + 1
        if it > 0:
            tot = float(obj[loc].sum())
            small = last_obj is not None and abs(last_obj - tot) <= cfg.solver.irls_obj_tol * max(abs(tot), 1e-300)
            if change < cfg.solver.irls_tol or small:
                break
            last_obj = tot
    return a, b, xb, stat


def render_uv(maps: ReflectanceMaps | Mapping[str, np.ndarray], obs: Mapping[str, np.ndarray], pairs=None,
              flash_intensity=None, only_observed: bool = True, chunk: int = DEFAULT_CHUNK) -> np.ndarray:
    """Predicted radiance (P', S, S, 3) float32 of ``maps`` for the (view, flash) pairs of ``obs``.

    Args:
        maps: :class:`ReflectanceMaps` or arrays with ``albedo``, ``weights``, ``exponents``.
        obs: uv-observations arrays (geometry, rig, ``observed``).
        pairs: (P,) bool mask or indices of the pairs to render (default all).
        flash_intensity: as in :func:`fit_maps` (use the same value as the fit).
        only_observed: zero where the pair is not observed (as the ``radiance`` array); else zero only
            where n·l ≤ 0 or n·v ≤ 0 (shadows are not modelled).

    Maps fitted with normal refinement carry their refined normals (``normal``): those are used instead of the
    observations' (the fit's model of the texel).
    """
    obs = _as_arrays(obs)
    if not isinstance(maps, ReflectanceMaps):
        maps = maps_from_arrays(_as_arrays(maps))
    pos = np.asarray(obs["position"], np.float64)
    S = pos.shape[0]
    if maps.albedo.shape[-1] != S:
        raise ReflectmmError(f"render_uv: maps are {maps.albedo.shape[-1]}² but observations are {S}²")
    P = np.asarray(obs["pair_view"]).shape[0]
    sel = np.flatnonzero(_parse_pair_mask(pairs, P)) if pairs is not None else np.arange(P)
    F = np.asarray(obs["flash_pos"]).shape[0]
    I = pair_irradiance(obs["flash_intensity"], F, flash_intensity)
    mask = np.asarray(obs.get("mask", np.ones((S, S), bool)), bool).reshape(-1)
    idx = np.flatnonzero(mask)
    pv = np.asarray(obs["pair_view"])[sel]
    pf = np.asarray(obs["pair_flash"])[sel]
    observed = np.asarray(obs["observed"], bool)[sel].reshape(sel.size, -1) if only_observed else None
    C = maps.albedo.reshape(3, -1).T
    W = maps.weights.reshape(maps.weights.shape[0], -1).T
    out = np.zeros((sel.size, S * S, 3), np.float32)
    nrm = (np.moveaxis(np.asarray(maps.normal, np.float64), 0, -1) if maps.normal is not None
           else np.asarray(obs["normal"], np.float64)).reshape(-1, 3)
    for sl in iter_chunks(idx.size, chunk):
        t = idx[sl]
        des = design_columns(pos.reshape(-1, 3)[t], nrm[t], obs["cam_centers"],
                             obs["flash_pos"], I, pv, pf, maps.exponents,
                             None if observed is None else observed[:, t].T)
        pred = des.diffuse[..., None] * C[t][:, None, :] + np.einsum("npk,nk->np", des.lobes, W[t])[..., None]
        out[:, t] = np.moveaxis(pred, 0, 1)
    return out.reshape(sel.size, S, S, 3)

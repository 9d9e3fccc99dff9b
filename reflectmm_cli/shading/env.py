"""Shading under SH environment lighting (docs/design.md §2).

``s_d = c/π · Σ_l A_l Σ_m K_lm Y_lm(n)`` (exact for band-limited lighting) and
``s_s = Σ_i w_i Σ_l B_l^i Σ_m K_lm Y_lm(r)``, ``r = 2(n·v)n − v`` (exact at normal view, an approximation at
other view angles — see docs/shading.md and benchmarks/bench_shading.py for its measured error).

Work that a scene does not need is skipped: bands where every active lobe has ``|B_l| ≤ band_tol`` (and where
``|A_l|/π ≤ band_tol`` for the diffuse part), lobes whose weights are all zero, texels outside ``mask``, and the
specular part of texels facing away from the viewer (n·v ≤ 0, where it is 0 by definition).

The two terms are written once (:func:`diffuse_term`, :func:`lobe_term` on the rows of :func:`diffuse_rows` and
:func:`lobe_rows`); the execution paths — blocked numpy, :class:`EnvBasis`, generic broadcasting, masked gather —
only arrange the data (blocks, masks, gathers, layouts, devices) and pass one :class:`EnvTerms` record; the
compiled kernel (:mod:`._env_numba`, ``backend=``) consumes the same rows on the same Chebyshev basis.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from reflectmm_cli.threads import default_threads

from ._array import any_torch, as_array, broadcast_shapes, check_last, compute_dtype, device_of
from .brdf import _check_exponents
from .sh import blinn_phong_sh_coeffs, lambert_sh_coeffs, phase_step, sh_basis, sh_basis_into, sh_order

__all__ = ["shade_env", "band_limits", "specular_view_albedo", "EnvBasis",
           # the two terms, written once for every execution path
           "EnvTerms", "env_terms", "diffuse_rows", "lobe_rows", "sh_sum", "diffuse_term", "lobe_term", "unit",
           "reflect"]

DEFAULT_CHUNK = 1 << 14
#: the blocked kernel gathers the front-facing texels of a block for the specular part only when fewer than this
#: fraction of them face the viewer; above it, shading every texel and zeroing the others is cheaper (measured)
COMPACT_BELOW = 0.75


def band_limits(exponents, order: int, band_tol: float = 0.0):
    """Per-part highest band actually used: (diffuse_order, [lobe_order_i]).

    A band l is dropped when it and every higher band have ``|A_l|/π ≤ band_tol`` (diffuse) or
    ``|B_l^i| ≤ band_tol`` (lobe i). With ``band_tol = 0`` nothing is dropped except exact zeros
    (the odd A_l, l ≥ 3). Dropping bands with coefficient ≤ τ changes a lobe's response to a unit-radiance
    band-l lighting by at most τ.
    """
    A = lambert_sh_coeffs(order) / math.pi
    B = blinn_phong_sh_coeffs(np.asarray(exponents, dtype=np.float64).reshape(-1), order)

    def last(c):
        big = np.flatnonzero(np.abs(c) > band_tol)
        return int(big[-1]) if big.size else 0

    return last(A), [last(b) for b in B]


def _band_of_coeff(order: int) -> np.ndarray:
    """Band l of each of the (order+1)² SH coefficients (l repeated 2l+1 times)."""
    return np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)


def _active_lobes(w, torch_mode: bool) -> list[int]:
    """Lobes to shade: those with a non-zero weight somewhere — every lobe when the weights need a gradient (the
    derivative of the radiance w.r.t. a zero weight is that lobe's shading, not 0)."""
    Kn = w.shape[-1]
    if torch_mode and w.requires_grad:
        return list(range(Kn))
    wz = w.detach() if torch_mode else w
    return [i for i in range(Kn) if bool((wz[..., i] != 0).any())]


# ---------------------------------------------------------------------------------------------------------------
# The two terms, written once (numpy or torch). Every execution path below only arranges the data — blocks,
# masks, gathers, layouts, devices — and calls these with one EnvTerms record.


def unit(x, axis: int = -1):
    """``x / |x|`` along ``axis`` (length 3), the length clamped at 1e-15 so a zero vector stays 0."""
    if any_torch(x):
        import torch

        return x * torch.rsqrt((x * x).sum(axis, keepdim=True).clamp_min(1e-30))
    return x / np.sqrt(np.maximum((x * x).sum(axis, keepdims=True), x.dtype.type(1e-30)))


def reflect(n, v, axis: int = -1):
    """Mirror direction and cosine of unit normals/views along ``axis``: ``(r, n·v)``, ``r = 2(n·v)n − v``.

    Shapes: n, v (..., 3) → r (..., 3), n·v (...) (or (3, N) → (3, N), (N,) with ``axis=0``).
    """
    ndv = (n * v).sum(axis)
    e = ndv.unsqueeze(axis) if any_torch(ndv) else np.expand_dims(ndv, axis)
    return (2.0 * e) * n - v, ndv


def diffuse_rows(K, order_d: int):
    """Coefficient rows of the diffuse term: ``K_lm A_l / π`` for the bands l ≤ order_d.

    K (..., 3, (L+1)²) → (..., 3, (order_d+1)²); dtype/device of K.
    """
    nd = (order_d + 1) ** 2
    L = sh_order(K.shape[-1])
    a = lambert_sh_coeffs(L)[_band_of_coeff(L)[:nd]] / math.pi
    if any_torch(K):
        import torch

        return K[..., :nd] * torch.as_tensor(a, dtype=K.dtype, device=K.device)
    return (K[..., :nd] * a).astype(K.dtype, copy=False)


def lobe_rows(K, B, orders, active):
    """Coefficient rows of the specular term, lobe-major: rows ``3j..3j+2`` are ``K_lm B_l^i`` of lobe
    ``i = active[j]`` for l ≤ orders[i], exact zeros beyond it (one product with the basis of r shades every lobe).

    K (..., 3, (L+1)²), B (lobes, L+1) float64 → (..., 3·len(active), (max_j orders[active[j]] + 1)²).
    """
    L = sh_order(K.shape[-1])
    lvl = _band_of_coeff(L)
    ns = (max(orders[i] for i in active) + 1) ** 2
    if any_torch(K):
        import torch

        parts = []
        for i in active:
            ni = (orders[i] + 1) ** 2
            Ki = K[..., :ni] * torch.as_tensor(B[i][lvl[:ni]], dtype=K.dtype, device=K.device)
            parts.append(torch.nn.functional.pad(Ki, (0, ns - ni)))
        return torch.cat(parts, -2)
    out = np.zeros(K.shape[:-2] + (3 * len(active), ns), K.dtype)
    for j, i in enumerate(active):
        ni = (orders[i] + 1) ** 2
        out[..., 3 * j:3 * j + 3, :ni] = K[..., :ni] * B[i][lvl[:ni]]
    return out


def sh_sum(rows, Y, coeff_major: bool = False, out=None):
    """``Σ_k rows[..., c, k] Y[..., k]``: SH rows applied to a basis.

    Texel-major: rows (C, n) or (..., C, n), Y (..., n) → (..., C).
    Coefficient-major (basis rows contiguous along the texels): rows (C, n), Y (n, N) → (C, N) (into ``out``
    if given, numpy); per-texel rows (N, C, n), Y (n, N) → (C, N).
    """
    torch_mode = any_torch(rows, Y)
    if torch_mode and Y.dtype != rows.dtype:
        Y = Y.to(rows.dtype)
    if coeff_major:
        if rows.ndim == 2:
            return rows @ Y if out is None else np.matmul(rows, Y, out=out)
        return (_torch_einsum() if torch_mode else np.einsum)("pcn,np->cp", rows, Y)
    if rows.ndim == 2:
        return Y @ rows.T if out is None else np.matmul(Y, rows.T, out=out)
    return (_torch_einsum() if torch_mode else np.einsum)("...cn,...n->...c", rows, Y)


def _torch_einsum():
    import torch

    return torch.einsum


def diffuse_term(albedo, rows, Yn, coeff_major: bool = False, out=None):
    """``c/π Σ_l A_l Σ_m K_lm Y_lm(n)`` with ``rows = diffuse_rows(K, ·)`` and Yn the basis of the unit normals.

    Texel-major: albedo (..., 3), Yn (..., n) → (..., 3). Coefficient-major: albedo (3, N), Yn (n, N) →
    (3, N). numpy ``out`` ((..., 3) or (3, N), one lighting): written in place.
    """
    E = sh_sum(rows, Yn, coeff_major, out)
    if out is not None:
        E *= albedo
        return E
    return albedo * E


def lobe_term(weights, rows, Yr, coeff_major: bool = False, out=None):
    """``Σ_j w_j Σ_l B_l^j Σ_m K_lm Y_lm(r)`` with ``rows = lobe_rows(K, B, ·, active)`` (J lobes) and Yr the
    basis of the mirror directions; ``weights`` are those of the J lobes (times ρ(n·v) for the view correction).

    Texel-major: weights (..., J), Yr (..., n) → (..., 3). Coefficient-major: weights (J, N), Yr (n, N) →
    (3, N). numpy ``out`` (3J, N): scratch for the per-lobe products.
    """
    S = sh_sum(rows, Yr, coeff_major, out)
    if coeff_major:
        J = weights.shape[0]
        S = S.reshape(J, 3, S.shape[-1])
        if out is not None:
            S *= weights[:, None, :]
            return S.sum(0)
        return (S * weights[:, None, :]).sum(0)
    J = weights.shape[-1]
    S = S.reshape(S.shape[:-1] + (J, 3))
    return (S * weights[..., None]).sum(-2)


class EnvTerms(NamedTuple):
    """Per-call constants of the two terms: what every execution path passes around instead of the loose arrays.

    ``diffuse``: (..., 3, (diffuse_order+1)²) rows of :func:`diffuse_rows`; ``lobes``: (..., 3·J, (lobe_order+1)²)
    rows of :func:`lobe_rows` (None when no lobe is active); ``active``: the J lobes shaded, in row order;
    ``view_exponents``: their exponents when the view correction is on, else None.
    """

    diffuse: object
    lobes: object
    active: tuple
    diffuse_order: int
    lobe_order: int
    view_exponents: tuple | None = None

    def lobe_weights(self, w, ndv, axis: int = -1):
        """Weights of the active lobes, (..., J) (``axis=-1``, w (..., K)) or (J, N) (``axis=0``, w (K, N)), times
        the view correction ρ_p(n·v) when it is on."""
        torch_mode = any_torch(w)
        idx = list(self.active)
        if axis == 0:
            wa = w[idx] if len(idx) != w.shape[0] else w
        else:
            wa = w[..., idx] if len(idx) != w.shape[-1] else w
        if self.view_exponents is None:
            return wa
        cols = [(wa[j] if axis == 0 else wa[..., j]) * specular_view_albedo(p, ndv)
                for j, p in enumerate(self.view_exponents)]
        if torch_mode:
            import torch

            return torch.stack(cols, 0 if axis == 0 else -1)
        return np.stack(cols, 0 if axis == 0 else -1)


def env_terms(K, exponents, active, band_tol: float = 0.0, view_correction: bool = False) -> EnvTerms:
    """The :class:`EnvTerms` of lighting K (..., 3, (L+1)²) (numpy or torch) for lobes of ``exponents`` (float64,
    (lobes,)), shading the lobes ``active``, bands dropped by :func:`band_limits` at ``band_tol``."""
    order = sh_order(K.shape[-1])
    Ld, Ls = band_limits(exponents, order, band_tol)
    active = tuple(active)
    lobes, Lsmax = None, -1
    if active:
        B = blinn_phong_sh_coeffs(exponents, order)
        lobes = lobe_rows(K, B, Ls, active)
        Lsmax = max(Ls[i] for i in active)
    vc = tuple(float(exponents[i]) for i in active) if view_correction else None
    return EnvTerms(diffuse_rows(K, Ld), lobes, active, Ld, Lsmax, vc)


_VIEW_NODES = 65


@lru_cache(maxsize=64)
def _view_albedo_table(p: float) -> np.ndarray:
    """ρ_p(μ_k) for μ_k = k/64: directional albedo of the true half-vector lobe, normalised so ρ(1) = 1."""
    f = (p + 2.0) / (4.0 * math.pi * (2.0 - 2.0 ** (-p / 2.0)))
    smax = min(1.0, 60.0 / p)  # (1 − s)^p < e^−60 beyond
    x, wx = np.polynomial.legendre.leggauss(256)
    s_ = (x + 1.0) / 2.0 * smax
    ws = wx * smax / 2.0
    t = 1.0 - s_  # n·h
    npsi = 512
    psi = 2.0 * math.pi * (np.arange(npsi) + 0.5) / npsi
    st = np.sqrt(np.maximum(0.0, 1.0 - t * t))
    cpsi = np.cos(psi)
    lobe = f * np.exp(p * np.log(t)) * ws  # (ns,)
    out = np.empty(_VIEW_NODES)
    for k, mu in enumerate(np.linspace(0.0, 1.0, _VIEW_NODES)):
        sv = math.sqrt(max(0.0, 1.0 - mu * mu))
        hv = st[:, None] * cpsi[None, :] * sv + (t * mu)[:, None]  # h·v
        nl = 2.0 * hv * t[:, None] - mu  # n·l for l = 2(h·v)h − v
        # ∫ f (n·h)^p [n·l > 0] dω_l with dω_l = 4 (h·v) dω_h
        out[k] = (np.where((hv > 0) & (nl > 0), 4.0 * hv, 0.0) * lobe[:, None]).sum() * 2.0 * math.pi / npsi
    return out / out[-1]


def specular_view_albedo(p, cos_view):
    """Directional albedo ρ_p(n·v) of the true half-vector lobe under uniform unit radiance.

    ``ρ_p(μ) = ∫_{n·l>0} f (n·h)^p dω_l`` for a view at ``n·v = μ``: 1 at normal view (the normalisation), ≈ μ
    for sharp lobes towards grazing. The SH specular of docs/design.md §2 keeps the normal-view energy (1) at every
    view; ``shade_env(..., view_correction=True)`` multiplies each lobe by ρ_p(n·v) to follow the true lobe's
    falloff. Tabulated (65 nodes in μ, product Gauss quadrature in the half-vector domain, ~1e-3) and
    interpolated linearly; numpy or torch ``cos_view`` (differentiable).
    """
    tab = _view_albedo_table(float(p))
    if any_torch(cos_view):
        import torch

        T = torch.as_tensor(tab, dtype=cos_view.dtype, device=cos_view.device)
        x = cos_view.clamp(0.0, 1.0) * (_VIEW_NODES - 1)
        i0 = x.detach().floor().clamp(0, _VIEW_NODES - 2).long()
        fr = x - i0.to(x.dtype)
        return T[i0] * (1 - fr) + T[i0 + 1] * fr
    # the nodes are uniform: the interval is an index, not a search (np.interp), in the input's float type
    cv = np.asarray(cos_view)
    dt = cv.dtype if cv.dtype.kind == "f" else np.dtype(np.float64)
    x = np.clip(cv, 0.0, 1.0).astype(dt, copy=False) * dt.type(_VIEW_NODES - 1)
    i0 = np.minimum(x.astype(np.intp), _VIEW_NODES - 2)
    fr = x - i0.astype(dt)
    T = tab.astype(dt)
    return T[i0] * (1 - fr) + T[i0 + 1] * fr


def _validate(albedo, weights, exponents, normal, view_dir, sh_coeffs, mask, check_finite=True, geometry_checked=False):
    tm = any_torch(albedo, weights, exponents, normal, view_dir, sh_coeffs)
    dt = compute_dtype(albedo, weights, exponents, normal, view_dir, sh_coeffs, torch_mode=tm)
    dev = device_of(albedo, weights, exponents, normal, view_dir, sh_coeffs)
    fin, gfin = bool(check_finite), bool(check_finite) and not geometry_checked
    c = as_array("albedo", albedo, torch_mode=tm, dtype=dt, device=dev, check_finite=fin)
    w = as_array("weights", weights, torch_mode=tm, dtype=dt, device=dev, check_finite=fin)
    p = as_array("exponents", exponents, torch_mode=tm, dtype=dt, device=dev)
    n = as_array("normal", normal, torch_mode=tm, dtype=dt, device=dev, check_finite=gfin)
    v = as_array("view_dir", view_dir, torch_mode=tm, dtype=dt, device=dev, check_finite=gfin)
    K = as_array("sh_coeffs", sh_coeffs, torch_mode=tm, dtype=dt, device=dev, check_finite=fin)
    for name, a in (("albedo", c), ("normal", n), ("view_dir", v)):
        check_last(name, a, 3)
    _check_exponents(p, tm)
    check_last("weights", w, p.shape[0])
    if K.ndim < 2 or K.shape[-2] != 3:
        raise ReflectmmError(f"shading: argument 'sh_coeffs' must have shape (..., 3, (L+1)^2), got {tuple(K.shape)}")
    order = sh_order(K.shape[-1])
    shapes = [c.shape[:-1], w.shape[:-1], n.shape[:-1], v.shape[:-1], K.shape[:-2]]
    if mask is not None:
        mask = np.asarray(mask.detach().cpu() if any_torch(mask) else mask)
        if mask.dtype != bool:
            raise ReflectmmError(f"shading: argument 'mask' must be boolean, got dtype {mask.dtype}")
        shapes.append(mask.shape)
    lead = broadcast_shapes(*shapes)
    pn = p.detach().cpu().double().numpy() if tm else p.astype(np.float64)
    return tm, dt, c, w, pn, n, v, K, order, lead, mask


def shade_env(albedo, weights, exponents, normal, view_dir, sh_coeffs, *, mask=None, band_tol: float = 0.0,
              chunk: int = DEFAULT_CHUNK, threads: int | None = None, view_correction: bool = False,
              basis: EnvBasis | None = None, check_finite: bool = True, backend: str = "auto"):
    """Diffuse and specular shading of texels under SH environment lighting.

    Args:
        albedo: (..., 3) diffuse colour c.
        weights: (..., K) lobe weights w_i.
        exponents: (K,) lobe exponents p_i > 0.
        normal: (..., 3) normals (normalised internally), same frame as the lighting (see envmap.py).
        view_dir: (..., 3) direction towards the viewer (normalised internally).
        sh_coeffs: (3, (L+1)²) one lighting for all texels, or (..., 3, (L+1)²) broadcasting against the texel
            shape (e.g. (B, 1, 3, n) for B images of N texels each). Radiance SH coefficients.
        mask: optional boolean (...) texel mask; texels outside it are 0 and cost nothing.
        band_tol: drop bands whose Funk–Hecke coefficient is ≤ band_tol (see :func:`band_limits`). 0 = exact.
        basis: an :class:`EnvBasis` of fixed geometry precomputed for these texels (then ``normal`` and
            ``view_dir`` may be None; the torch path is used). For repeated shading of the same texels; its
            normals and views were checked when it was built and are not checked again.
        check_finite: reject NaN/inf inputs naming the argument (default). ``False`` skips the scans (one pass
            and, on a GPU, one host synchronisation per argument): for callers that check their result instead,
            like the finetuning step, which refuses a non-finite loss.
        view_correction: multiply each lobe by the true lobe's directional albedo ρ_p(n·v)
            (:func:`specular_view_albedo`). Off by default (the paper's model); still exact at normal view.
        chunk: texels per block in the numpy fast path (cache blocking).
        threads: worker threads for the numpy fast path (blocks run in parallel; numpy releases the GIL);
            default: the CPUs this process may use (at most 8).
        backend: kernel of the fast path (numpy inputs, one lighting): ``"compiled"`` (numba; an error when numba
            is not installed), ``"numpy"`` (the blocked numpy kernel), ``"auto"`` (default: compiled when numba
            is installed, else numpy). The two agree to rounding (docs/shading.md); other paths ignore it.
    Returns:
        ``(diffuse, specular)``, each (..., 3). The specular part is 0 where n·v ≤ 0. numpy in → numpy out,
        torch in → torch out (differentiable w.r.t. every input, including the SH coefficients).
    """
    if basis is not None:
        normal, view_dir = basis.normal, basis.view_dir
        if not any_torch(sh_coeffs):
            import torch

            sh_coeffs = torch.as_tensor(np.asarray(sh_coeffs), dtype=basis.dtype, device=basis.normal.device)
    tm, dt, c, w, p, n, v, K, order, lead, mask = _validate(
        albedo, weights, exponents, normal, view_dir, sh_coeffs, mask, check_finite, basis is not None)
    if basis is not None and order > basis.order:
        raise ReflectmmError(f"shading: lighting of order {order} but the EnvBasis was built for order {basis.order}")
    if band_tol < 0 or not math.isfinite(band_tol):
        raise ReflectmmError(f"shading: band_tol must be finite and ≥ 0, got {band_tol}")
    if backend not in BACKENDS:
        raise ReflectmmError(f"shading: backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    vc = bool(view_correction)
    if not tm and K.ndim == 2:
        kern = _kernel_for(backend)
        if kern is not None:
            return _shade_env_compiled(kern, c, w, n, v, K, p, band_tol, vc, lead, mask, dt, chunk, threads)
        return _shade_env_numpy(c, w, n, v, K, p, band_tol, vc, lead, mask, dt, chunk, threads)
    if basis is not None:
        return _shade_env_pre(c, w, K, env_terms(K, p, _active_lobes(w, True), band_tol, vc), lead, mask, dt, basis)
    if tm and mask is not None and K.ndim == 2:
        # gather the masked texels, shade only those, scatter back (differentiable)
        import torch

        idx = torch.as_tensor(np.flatnonzero(np.broadcast_to(mask, lead).reshape(-1)), device=n.device)

        def sel(a):
            return a.expand(lead + a.shape[-1:]).reshape(-1, a.shape[-1])[idx]

        ws = sel(w)
        d_m, s_m = _shade_env_generic(tm, sel(c), ws, sel(n), sel(v), env_terms(K, p, _active_lobes(ws, tm),
                                      band_tol, vc), (int(idx.numel()),), None, dt)
        N = int(np.prod(lead)) if lead else 1
        zero = torch.zeros((N, 3), dtype=d_m.dtype, device=d_m.device)
        return (zero.index_put((idx,), d_m).reshape(lead + (3,)),
                zero.index_put((idx,), s_m).reshape(lead + (3,)))
    return _shade_env_generic(tm, c, w, n, v, env_terms(K, p, _active_lobes(w, tm), band_tol, vc), lead, mask, dt)


BACKENDS = ("auto", "compiled", "numpy")


def _kernel_for(backend: str):
    """The compiled kernel module for ``backend``, or None for the numpy kernel."""
    if backend == "numpy":
        return None
    kern = compiled_kernel()
    if kern is None and backend == "compiled":
        raise ReflectmmError("shading: backend 'compiled' needs numba, which is not installed")
    return kern


def _flat(a, lead, k):
    return np.broadcast_to(a, lead + (k,)).reshape(-1, k)


def _single_threaded_blas(enable: bool):
    """BLAS limited to one thread while the blocks run (they are already parallel).

    The lighting products are skinny ((3…9) × 81 @ 81 × 16384): single-threaded BLAS does them at ~30 GFLOP/s,
    its threaded path spin-waits for the other block threads and was 10–50× slower on a busy machine
    (measured). The limit is process-wide for the duration of the call (threadpoolctl restores it).
    """
    import contextlib

    if not enable:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _default_threads() -> int:
    """Worker threads of the blocked numpy path: the process's CPUs, at most 8 (:func:`threads.default_threads`)."""
    return default_threads(8)


class _ChebPlan(NamedTuple):
    """Basis of the blocked numpy kernel: Chebyshev polynomials in z times the azimuthal factors.

    Every real SH is ``Y_lm(d) = Q_l^|m|(z) · (√2) Re/Im (x + iy)^|m|`` with Q_l^m a polynomial of degree l − m
    in z, so ``Y = M Φ`` for the functions ``Φ = T_j(z) · Re/Im (x + iy)^m`` (T_j the Chebyshev polynomials,
    j ≡ l − m mod 2, j ≤ l − m) and a constant matrix M (float64, exact to rounding). The kernel evaluates Φ —
    one multiplication per row after the T_j and the azimuthal factors, against five or six per row for the
    Legendre recurrence — and the coefficient rows become ``rows @ M``, so the product with the basis is unchanged.
    In Chebyshev form there is no cancellation (|T_j| ≤ 1 and M has small entries), so the values agree with the
    Legendre recurrence to rounding.

    ``jmax``: rows 0..jmax of Φ are T_0..T_jmax (the m = 0 functions); ``m_rows``: (m, js, first row of the
    cosine rows, first row of the sine rows) for m ≥ 1; ``M``: ((order+1)², rows).
    """

    order: int
    jmax: int
    m_rows: tuple
    M: np.ndarray

    @property
    def n_rows(self) -> int:
        return self.M.shape[1]


@lru_cache(maxsize=64)
def _cheb_plan(order: int, bands: tuple) -> _ChebPlan:
    """Plan for the SH coefficients of the bands ``bands`` (ascending, ≤ order); coefficients of other bands map
    to nothing (their rows of M are 0)."""
    from .sh import _sh_columns

    def js(m):
        out = set()
        for l in bands:  # noqa: E741
            if l >= m:
                out.update(range((l - m) % 2, l - m + 1, 2))
        return sorted(out)

    jmax = max(js(0), default=0)
    m_rows, r = [], jmax + 1
    for m in range(1, order + 1):
        j = js(m)
        if j:
            m_rows.append((m, tuple(j), r, r + len(j)))
            r += 2 * len(j)
    # Q_l^m(z) (√2 for m > 0) at Chebyshev nodes: the SH columns at (x, y) = (1, 0), where (x + iy)^m = 1
    nodes = np.cos(math.pi * (np.arange(order + 1) + 0.5) / (order + 1))
    cols = _sh_columns(np.ones_like(nodes), np.zeros_like(nodes), nodes, order, np.ones_like(nodes))
    M = np.zeros(((order + 1) ** 2, r))
    where = {m: (jj, rc, rs) for m, jj, rc, rs in m_rows}
    for l in bands:  # noqa: E741
        for m in range(l + 1):
            cheb = np.polynomial.chebyshev.chebfit(nodes, cols[l * l + l + m], l - m)
            if m == 0:
                M[l * l + l, :l + 1] = cheb
                continue
            jj, rc, rs = where[m]
            for k, j in enumerate(jj):
                if j <= l - m:
                    M[l * l + l + m, rc + k] = cheb[j]
                    M[l * l + l - m, rs + k] = cheb[j]
    M[np.abs(M) < 1e-15 * np.abs(M).max()] = 0.0  # parity zeros of the fit
    return _ChebPlan(order, jmax, tuple(m_rows), M)


def _cheb_basis_into(x, y, z, plan: _ChebPlan, out, scratch):
    """Φ (see :class:`_ChebPlan`) of unit vectors (x, y, z) (1-D, length N) into ``out`` (plan.n_rows, N), with
    ``scratch`` (≥ 5, N) of the same dtype (row 0: 2z, then the products y·s, y·c; rows 1–4: two (c, s) pairs).
    In-place ufuncs only; returns ``out``."""
    T = out
    T[0].fill(1)
    if plan.jmax >= 1:
        np.copyto(T[1], z)
    z2 = scratch[0]
    if plan.jmax >= 2:
        np.add(z, z, out=z2)
        for j in range(2, plan.jmax + 1):  # T_j = 2z T_(j−1) − T_(j−2)
            np.multiply(z2, T[j - 1], out=T[j])
            T[j] -= T[j - 2]
    # (x + iy)^m = (x + iy)^(m−1) (x + iy), written straight into the j = 0 rows when the plan has them (they are
    # Re/Im (x + iy)^m themselves), else into one of two alternating scratch pairs
    tmp, pairs, free = scratch[0], ((scratch[1], scratch[2]), (scratch[3], scratch[4])), 0
    cm, sm = x, y
    m_cur = 1
    for m, js, rc, rs in plan.m_rows:
        while m_cur < m:
            if m_cur + 1 == m and js[0] == 0:
                dc, ds = out[rc], out[rs]
            else:
                (dc, ds), free = pairs[free], 1 - free
            phase_step(x, y, cm, sm, dc, ds, tmp)
            cm, sm = dc, ds
            m_cur += 1
        for k, j in enumerate(js):
            if j == 0:
                if m == 1:
                    np.copyto(out[rc], x)
                    np.copyto(out[rs], y)
            else:
                np.multiply(T[j], cm, out=out[rc + k])
                np.multiply(T[j], sm, out=out[rs + k])
    return out


class _Blocked(NamedTuple):
    """What both blocked kernels (numpy, compiled) shade: the flattened (N, ·) inputs, the texels to shade
    (``idx`` of the mask, None for all; ``ntex`` of them), and the :class:`EnvTerms` whose rows are on the
    Chebyshev bases of ``plan_d`` (normals) and ``plan_s`` (mirror directions; None when no lobe is active)."""

    c: np.ndarray
    w: np.ndarray
    n: np.ndarray
    v: np.ndarray
    idx: np.ndarray | None
    ntex: int
    terms: EnvTerms
    plan_d: _ChebPlan
    plan_s: _ChebPlan | None


def _blocked_setup(c, w, n, v, K, p, band_tol, vc, lead, mask, dt) -> _Blocked:
    """Flatten the inputs of one lighting (3, n), find the texels and lobes to shade, and put the two terms' rows
    (:func:`env_terms`) on the Chebyshev bases: ``rows @ plan.M`` in float64, then the compute dtype."""
    Kn = w.shape[-1]
    c2, w2, n2, v2 = _flat(c, lead, 3), _flat(w, lead, Kn), _flat(n, lead, 3), _flat(v, lead, 3)
    idx = None
    if mask is not None:
        idx = np.flatnonzero(np.broadcast_to(mask, lead).reshape(-1))
    ntex = (int(np.prod(lead)) if lead else 1) if idx is None else idx.size
    # Lobes that carry weight somewhere in the (masked) texels.
    wsel = w2 if idx is None else w2[idx]
    active = np.flatnonzero((wsel != 0).any(0)).tolist() if ntex else []
    terms = env_terms(K.astype(np.float64), p, active, band_tol, vc)
    order = sh_order(K.shape[-1])
    A = lambert_sh_coeffs(order)
    plan_d = _cheb_plan(order, tuple(l for l in range(terms.diffuse_order + 1) if A[l] != 0))
    plan_s = None
    if active:
        plan_s = _cheb_plan(order, tuple(range(terms.lobe_order + 1)))
        terms = terms._replace(lobes=(terms.lobes @ plan_s.M[:terms.lobes.shape[-1]]).astype(dt))
    terms = terms._replace(diffuse=(terms.diffuse @ plan_d.M[:terms.diffuse.shape[-1]]).astype(dt))
    return _Blocked(c2, w2, n2, v2, idx, ntex, terms, plan_d, plan_s)


def _shade_env_numpy(c, w, n, v, K, p, band_tol, vc, lead, mask, dt, chunk, threads):
    """Blocked numpy kernel for one lighting (3, n): blocks of ``chunk`` texels in threads, everything
    coefficient-major ((3, m) geometry, (rows, m) bases) in per-thread buffers reused from block to block."""
    import threading

    N = int(np.prod(lead)) if lead else 1
    bl = _blocked_setup(c, w, n, v, K, p, band_tol, vc, lead, mask, dt)
    c2, w2, n2, v2, idx, Ntex, terms, plan_d, plan_s = bl
    active = terms.active
    diffuse = np.zeros((N, 3), dt)
    specular = np.zeros((N, 3), dt)
    nb = max(plan_d.n_rows, plan_s.n_rows if active else 0)
    local = threading.local()

    def buffers(m):
        b = getattr(local, "b", None)
        if b is None:
            b = local.b = (np.empty((nb, chunk), dt), np.empty((5, chunk), dt), np.empty((3 * max(1, len(active)),
                           chunk), dt))
        return b[0][:, :m], b[1][:, :m], b[2][:, :m]

    def block(s0, s1):
        rows = slice(s0, s1) if idx is None else idx[s0:s1]
        m = s1 - s0
        Y, scratch, prod = buffers(m)
        nT = unit(np.ascontiguousarray(n2[rows].T), 0)  # (3, m)
        Yn = _cheb_basis_into(nT[0], nT[1], nT[2], plan_d, Y[:plan_d.n_rows], scratch)
        # texel-major product straight into the output rows (BLAS takes the transposed basis as it is)
        if idx is None:
            diffuse_term(c2[rows], terms.diffuse, Yn.T, False, diffuse[rows])
        else:
            diffuse[rows] = diffuse_term(c2[rows], terms.diffuse, Yn.T)
        if not active:
            return
        vT = unit(np.ascontiguousarray(v2[rows].T), 0)
        r, ndv = reflect(nT, vT, 0)
        front = ndv > 0
        nfront = int(np.count_nonzero(front))
        if nfront == 0:
            return
        back = None
        if nfront >= COMPACT_BELOW * m:  # shade all, then zero the few facing away (cheaper than gathering)
            rows_s, back = rows, (None if nfront == m else ~front)
        else:  # the specular part is 0 where n·v ≤ 0: shade the front-facing texels only
            sub = np.flatnonzero(front)
            r, ndv = np.ascontiguousarray(r[:, sub]), ndv[sub]
            rows_s = (np.arange(s0, s1) if idx is None else idx[s0:s1])[sub]
            m = sub.size
        Yr = _cheb_basis_into(r[0], r[1], r[2], plan_s, Y[:plan_s.n_rows, :m], scratch[:, :m])
        wT = terms.lobe_weights(np.ascontiguousarray(w2[rows_s].T), ndv, axis=0)  # (J, m)
        S = lobe_term(wT, terms.lobes, Yr, True, prod[:, :m])  # (3, m)
        if back is not None:
            S[:, back] = 0
        specular[rows_s] = S.T

    with _single_threaded_blas(Ntex >= 2048):
        _run_blocks(block, Ntex, chunk, threads)
    return diffuse.reshape(lead + (3,)), specular.reshape(lead + (3,))


def _run_blocks(block, ntex: int, chunk: int, threads: int | None) -> None:
    """``block(s0, s1)`` for consecutive ranges of ``chunk`` of the ``ntex`` texels, on ``threads`` worker threads
    (default: the CPUs this process may use, at most 8); the blocks must release the GIL to run in parallel."""
    starts = list(range(0, ntex, chunk))
    nthreads = min(threads if threads else _default_threads(), len(starts))
    if nthreads > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(nthreads) as ex:
            list(ex.map(lambda s0: block(s0, min(ntex, s0 + chunk)), starts))
    else:
        for s0 in starts:
            block(s0, min(ntex, s0 + chunk))


@lru_cache(maxsize=1)
def compiled_kernel():
    """The compiled kernel module (:mod:`reflectmm_cli.shading._env_numba`), or None when numba is not installed
    (then the blocked numpy kernel shades)."""
    try:
        from . import _env_numba
    except ImportError:
        return None
    return _env_numba


def _shade_env_compiled(kern, c, w, n, v, K, p, band_tol, vc, lead, mask, dt, chunk, threads):
    """The compiled kernel for one lighting (3, n): the set-up of the numpy kernel (:func:`_blocked_setup`), then
    ranges of ``chunk`` texels in threads (:func:`_run_blocks`; the kernel releases the GIL)."""
    N = int(np.prod(lead)) if lead else 1
    bl = _blocked_setup(c, w, n, v, K, p, band_tol, vc, lead, mask, dt)
    terms = bl.terms
    diffuse = np.zeros((N, 3), dt)
    specular = np.zeros((N, 3), dt)
    J = len(terms.active)
    plan_d = kern.plan_arrays(bl.plan_d)
    plan_s = kern.plan_arrays(bl.plan_s) if J else plan_d
    rows_s = np.ascontiguousarray(terms.lobes) if J else np.zeros((0, 1), dt)
    view_tab = (np.stack([_view_albedo_table(e) for e in terms.view_exponents]).astype(dt) if J and vc
                else np.zeros((max(J, 1), _VIEW_NODES), dt))
    idx = np.zeros(0, np.int64) if bl.idx is None else bl.idx.astype(np.int64)
    c2, w2, n2, v2 = (np.ascontiguousarray(a) for a in (bl.c, bl.w, bl.n, bl.v))
    rows_d, active = np.ascontiguousarray(terms.diffuse), np.asarray(terms.active, np.int64)
    consts, grid = np.array([1e-30, 1.0, _VIEW_NODES - 1], dt), np.arange(_VIEW_NODES).astype(dt)

    def block(s0, s1):
        kern.shade_range(s0, s1, c2, w2, n2, v2, idx, bl.idx is not None, rows_d, plan_d, rows_s, plan_s, active,
                         view_tab, bool(vc and J), consts, grid, diffuse, specular)

    _run_blocks(block, bl.ntex, chunk, threads)
    return diffuse.reshape(lead + (3,)), specular.reshape(lead + (3,))


def _basis_coeff_major(d, order):
    """(n, N) SH basis, coefficient-major, of unit vectors ``d`` (..., 3) (no gradient): on the CPU by the blocked
    in-place numpy kernel, elsewhere by :func:`sh_basis` and one transpose."""
    import torch

    a = d.detach().reshape(-1, 3)
    if a.device.type != "cpu":
        return sh_basis(a, order, normalize=False).T.contiguous()
    a = a.numpy()
    N = a.shape[0]
    out = np.empty(((order + 1) ** 2, N), a.dtype)
    t = np.ascontiguousarray(a.T)
    for s0 in range(0, N, DEFAULT_CHUNK):
        s1 = min(N, s0 + DEFAULT_CHUNK)
        sh_basis_into(t[0, s0:s1], t[1, s0:s1], t[2, s0:s1], order, out[:, s0:s1])
    return torch.from_numpy(out)


class EnvBasis:
    """SH bases of fixed geometry, precomputed once for many ``shade_env`` calls (torch).

    Finetuning shades the same texels (fixed precomputed normals and views) under a new lighting, albedo and
    weights every step; with ``shade_env(..., basis=EnvBasis(normal, view_dir, order))`` each step costs only
    the lighting products and their gradients. Both bases are stored coefficient-major, ``(n, N)`` for the N
    texels, so that each product is one ``(rows, n) @ (n, N)`` matrix product and the per-texel weighting runs
    along contiguous rows. The basis of n keeps only the coefficients of the bands whose clamped-cosine
    coefficient A_l is not zero (the odd l ≥ 3 are exact zeros: 48 of 81 at order 8); the basis of r keeps all.
    Memory: (n_A + (L+1)²) values per texel (516 B at order 8, float32).

    Args:
        normal, view_dir: (..., 3) numpy or torch (normalised here; no gradients flow to them).
        order: highest SH order the lighting will have.
        dtype, device: torch dtype/device of the stored bases (default float32, cpu / the input's device).
    """

    def __init__(self, normal, view_dir, order: int, *, dtype=None, device=None):
        import torch

        from .sh import _check_order

        self.order = _check_order(order)
        dev = device or device_of(normal, view_dir) or torch.device("cpu")
        dt = dtype or torch.float32
        n = as_array("normal", normal.detach() if any_torch(normal) else normal, torch_mode=True, dtype=dt,
                     device=dev)
        v = as_array("view_dir", view_dir.detach() if any_torch(view_dir) else view_dir, torch_mode=True,
                     dtype=dt, device=dev)
        check_last("normal", n, 3)
        check_last("view_dir", v, 3)
        self.lead = broadcast_shapes(n.shape[:-1], v.shape[:-1])
        n = n.expand(self.lead + (3,))
        v = v.expand(self.lead + (3,))
        self.normal = n * torch.rsqrt((n * n).sum(-1, keepdim=True).clamp_min(1e-30))
        self.view_dir = v * torch.rsqrt((v * v).sum(-1, keepdim=True).clamp_min(1e-30))
        self.ndv = (self.normal * self.view_dir).sum(-1)
        self.front = (self.ndv > 0).reshape(-1)
        self.all_front = bool(self.front.all())  # one check here instead of a mask per shading
        r = (2.0 * self.ndv)[..., None] * self.normal - self.view_dir
        lvl = _band_of_coeff(self.order)
        #: indices of the stored coefficients of the basis of n (bands with A_l ≠ 0), ascending
        self.n_cols = np.flatnonzero(lambert_sh_coeffs(self.order)[lvl] != 0)
        Yn = _basis_coeff_major(self.normal, self.order)
        self.Yn = Yn[torch.as_tensor(self.n_cols, device=Yn.device)].contiguous()
        self.Yr = _basis_coeff_major(r, self.order)

    @property
    def dtype(self):
        return self.normal.dtype

    @property
    def n_texels(self) -> int:
        return int(self.Yr.shape[1])


def _shade_env_pre(c, w, K, terms: EnvTerms, lead, mask, dt, pre):
    """``shade_env`` on an :class:`EnvBasis` (torch), coefficient-major: texels along the last axis of every
    product (``(3, n) @ (n, N)`` for the diffuse part, one ``(3·lobes, n) @ (n, N)`` for all lobes); a per-texel
    lighting (N, 3, n) is applied by one einsum per part."""
    import torch

    N = pre.n_texels
    dev = pre.Yr.device
    nd = (terms.diffuse_order + 1) ** 2
    cols = pre.n_cols[pre.n_cols < nd]  # the stored rows of the basis of n (A_l ≠ 0)
    Kn = w.shape[-1]
    rows_d = terms.diffuse[..., torch.as_tensor(cols, device=dev)]
    if K.ndim > 2:
        rows_d = rows_d.expand(lead + rows_d.shape[-2:]).reshape(N, 3, len(cols))
    diffuse = diffuse_term(c.expand(lead + (3,)).reshape(N, 3).T, rows_d, pre.Yn[:len(cols)], True)
    spec = None
    if terms.active:
        rows_s = terms.lobes
        if K.ndim > 2:
            rows_s = rows_s.expand(lead + rows_s.shape[-2:]).reshape(N, *rows_s.shape[-2:])
        wT = terms.lobe_weights(w.expand(lead + (Kn,)).reshape(N, Kn).T, pre.ndv.reshape(-1).to(dt), axis=0)
        spec = lobe_term(wT, rows_s, pre.Yr[:rows_s.shape[-1]], True)
        if not pre.all_front:
            spec = torch.where(pre.front[None, :], spec, torch.zeros_like(spec))
    diffuse = diffuse.T.reshape(lead + (3,))
    spec = torch.zeros_like(diffuse) if spec is None else spec.T.reshape(lead + (3,))
    if mask is not None:
        mt = torch.as_tensor(np.broadcast_to(mask, lead).copy(), device=dev)[..., None]
        diffuse = torch.where(mt, diffuse, torch.zeros_like(diffuse))
        spec = torch.where(mt, spec, torch.zeros_like(spec))
    return diffuse, spec


def _shade_env_generic(tm, c, w, n, v, terms: EnvTerms, lead, mask, dt):
    """Broadcasting path, texel-major: torch (differentiable) or per-texel lighting in numpy."""
    if tm:
        import torch

    nn = unit(n)
    vv = unit(v)
    # Geometry without gradients: evaluate the basis with the blocked numpy kernel and keep only the cheap linear
    # part in the autograd graph.
    fixed_geom = tm and nn.device.type == "cpu" and not (nn.requires_grad or vv.requires_grad)
    if fixed_geom:
        def basis(d, L):
            return _basis_coeff_major(d, L).T.reshape(d.shape[:-1] + ((L + 1) ** 2,))
    else:
        def basis(d, L):
            return sh_basis(d, L, normalize=False)
    diffuse = diffuse_term(c, terms.diffuse, basis(nn, terms.diffuse_order))
    spec = None
    if terms.active:
        r, ndv = reflect(nn, vv)
        spec = lobe_term(terms.lobe_weights(w, ndv), terms.lobes, basis(r, terms.lobe_order))
        spec = (torch.where if tm else np.where)((ndv > 0)[..., None], spec, spec * 0)
    if tm:
        diffuse = diffuse.expand(lead + (3,))
        spec = torch.zeros_like(diffuse) if spec is None else spec.expand(lead + (3,))
    else:
        diffuse = np.broadcast_to(diffuse, lead + (3,))
        spec = np.zeros_like(diffuse) if spec is None else np.broadcast_to(spec, lead + (3,))
    if mask is not None:
        if tm:
            mt = torch.as_tensor(np.broadcast_to(mask, lead).copy(), device=diffuse.device)[..., None]
            diffuse = torch.where(mt, diffuse, torch.zeros_like(diffuse))
            spec = torch.where(mt, spec, torch.zeros_like(spec))
        else:
            mt = np.broadcast_to(mask, lead)[..., None]
            diffuse = np.where(mt, diffuse, 0).astype(dt)
            spec = np.where(mt, spec, 0).astype(dt)
    return diffuse, spec

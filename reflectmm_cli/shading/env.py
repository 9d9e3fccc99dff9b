"""Shading under SH environment lighting (docs/design.md §2).

``s_d = c/π · Σ_l A_l Σ_m K_lm Y_lm(n)`` (exact for band-limited lighting) and
``s_s = Σ_i w_i Σ_l B_l^i Σ_m K_lm Y_lm(r)``, ``r = 2(n·v)n − v`` (exact at normal view, an approximation at
other view angles — see docs/shading.md and benchmarks/bench_shading.py for its measured error).

Work that a scene does not need is skipped: bands where every active lobe has ``|B_l| ≤ band_tol`` (and where
``|A_l|/π ≤ band_tol`` for the diffuse part), lobes whose weights are all zero, texels outside ``mask``, and the
specular part of texels facing away from the viewer (n·v ≤ 0, where it is 0 by definition).
"""
from __future__ import annotations

import math
import os
from functools import lru_cache

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from ._array import any_torch, as_array, broadcast_shapes, check_last, compute_dtype, device_of
from .brdf import _check_exponents
from .sh import blinn_phong_sh_coeffs, lambert_sh_coeffs, sh_basis, sh_basis_into

__all__ = ["shade_env", "band_limits", "specular_view_albedo", "EnvBasis"]

DEFAULT_CHUNK = 1 << 14


def _order_from_count(n: int) -> int:
    L = int(round(math.sqrt(n))) - 1
    if L < 0 or (L + 1) ** 2 != n:
        raise ReflectmmError(f"shading: argument 'sh_coeffs' has {n} coefficients per channel, not (L+1)^2")
    return L


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


def _stacked_lobe_coeffs(K, Bs, Ls, active, lvl, zeros):
    """One lighting's coefficient rows of several lobes stacked lobe-major, ``(3·lobes, n_max)``: rows
    ``3j..3j+2`` are ``K · B_l^i`` of lobe ``active[j]``, bands beyond its limit exact zeros; one product with the
    basis of r then shades every lobe (the basis is read once, and once more in the backward)."""
    nmax = (max(Ls[i] for i in active) + 1) ** 2
    Kst = zeros((3 * len(active), nmax))
    for j, i in enumerate(active):
        ni = (Ls[i] + 1) ** 2
        Kst[3 * j:3 * j + 3, :ni] = K[..., :ni] * Bs[i][lvl[:ni]]
    return Kst


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
    return np.interp(np.clip(cos_view, 0.0, 1.0), np.linspace(0.0, 1.0, _VIEW_NODES), tab).astype(
        np.asarray(cos_view).dtype if np.asarray(cos_view).dtype.kind == "f" else np.float64, copy=False)


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
    order = _order_from_count(K.shape[-1])
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
              basis: EnvBasis | None = None, check_finite: bool = True):
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
    Ld, Ls = band_limits(p, order, band_tol)
    A = lambert_sh_coeffs(order)
    B = blinn_phong_sh_coeffs(p, order)
    if not tm and K.ndim == 2:
        return _shade_env_numpy(c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, chunk, threads,
                                p if view_correction else None)
    if basis is not None:
        return _shade_env_pre(c, w, K, A, B, Ld, Ls, lead, mask, dt, basis, p if view_correction else None)
    if tm and mask is not None and K.ndim == 2:
        # gather the masked texels, shade only those, scatter back (differentiable)
        import torch

        idx = torch.as_tensor(np.flatnonzero(np.broadcast_to(mask, lead).reshape(-1)), device=n.device)

        def sel(a):
            return a.expand(lead + a.shape[-1:]).reshape(-1, a.shape[-1])[idx]

        d_m, s_m = _shade_env_generic(tm, sel(c), sel(w), sel(n), sel(v), K, A, B, Ld, Ls,
                                      (int(idx.numel()),), None, dt, p if view_correction else None)
        N = int(np.prod(lead)) if lead else 1
        zero = torch.zeros((N, 3), dtype=d_m.dtype, device=d_m.device)
        return (zero.index_put((idx,), d_m).reshape(lead + (3,)),
                zero.index_put((idx,), s_m).reshape(lead + (3,)))
    return _shade_env_generic(tm, c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, p if view_correction else None)


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
    try:
        return max(1, min(len(os.sched_getaffinity(0)), 8))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, min(os.cpu_count() or 1, 8))


def _shade_env_numpy(c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, chunk, threads, vc_exponents=None):
    N = int(np.prod(lead)) if lead else 1
    Kn = w.shape[-1]
    c2, w2, n2, v2 = _flat(c, lead, 3), _flat(w, lead, Kn), _flat(n, lead, 3), _flat(v, lead, 3)
    diffuse = np.zeros((N, 3), dt)
    specular = np.zeros((N, 3), dt)
    idx = None
    if mask is not None:
        idx = np.flatnonzero(np.broadcast_to(mask, lead).reshape(-1))
    Ntex = N if idx is None else idx.size
    # Lobes that carry weight somewhere in the (masked) texels.
    wsel = w2 if idx is None else w2[idx]
    active = [i for i in range(Kn) if np.any(wsel[:, i] != 0)] if Ntex else []
    nd = (Ld + 1) ** 2
    lvl = _band_of_coeff(len(A) - 1)
    KA = (K[:, :nd] * A[lvl[:nd]] / math.pi).astype(dt)  # (3, nd), 1/π folded in
    Lsmax = max([Ls[i] for i in active], default=-1)
    ns = (Lsmax + 1) ** 2
    # Lobes with the same band limit share one matmul: rows (3·lobes) × coefficients.
    groups = {}
    for i in active:
        groups.setdefault(Ls[i], []).append(i)
    KBg = [(lobes, (Lg + 1) ** 2,
            np.concatenate([K[:, :(Lg + 1) ** 2] * B[i][lvl[:(Lg + 1) ** 2]] for i in lobes]).astype(dt))
           for Lg, lobes in sorted(groups.items())]
    tiny = dt(1e-30)

    def block(s0, s1):
        buf_d = np.empty((nd, s1 - s0), dt)
        rows = slice(s0, s1) if idx is None else idx[s0:s1]
        nn = n2[rows]
        nn = nn / np.sqrt(np.maximum((nn * nn).sum(1, keepdims=True), tiny))
        nT = np.ascontiguousarray(nn.T)
        Yn = sh_basis_into(nT[0], nT[1], nT[2], Ld, buf_d)
        # Skinny (3…9 × n) @ (n × m) products: einsum's C loop; OpenBLAS's threaded path for this shape
        # spin-waits and is 10–50× slower on a busy machine (measured), and the blocks are already parallel.
        D = KA @ Yn  # (3, m)
        D *= c2[rows].T
        diffuse[rows] = D.T
        if not active:
            return
        vv = v2[rows]
        vv = vv / np.sqrt(np.maximum((vv * vv).sum(1, keepdims=True), tiny))
        ndv = (nn * vv).sum(1)
        front = ndv > 0
        if not front.all():
            sub = np.flatnonzero(front)
            if sub.size == 0:
                return
            nn, vv, ndv = nn[sub], vv[sub], ndv[sub]
            rows_s = (np.arange(s0, s1) if idx is None else idx[s0:s1])[sub]
        else:
            rows_s = rows
        r = (2.0 * ndv)[:, None] * nn - vv
        rT = np.ascontiguousarray(r.T)
        ms = rT.shape[1]
        Yr = sh_basis_into(rT[0], rT[1], rT[2], Lsmax, np.empty((ns, ms), dt))
        wT = np.ascontiguousarray(w2[rows_s].T)  # (K, ms)
        acc = np.zeros((3, ms), dt)
        for lobes, ng, KB in KBg:
            S = KB @ Yr[:ng]  # (3·len(lobes), ms)
            for j, i in enumerate(lobes):
                Sj = S[3 * j:3 * j + 3]
                Sj *= wT[i] if vc_exponents is None else wT[i] * specular_view_albedo(vc_exponents[i], ndv)
                acc += Sj
        specular[rows_s] = acc.T

    starts = list(range(0, Ntex, chunk))
    nthreads = min(threads if threads else _default_threads(), len(starts))
    with _single_threaded_blas(Ntex >= 2048):
        if nthreads > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(nthreads) as ex:
                list(ex.map(lambda s0: block(s0, min(Ntex, s0 + chunk)), starts))
        else:
            for s0 in starts:
                block(s0, min(Ntex, s0 + chunk))
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


def _shade_env_pre(c, w, K, A, B, Ld, Ls, lead, mask, dt, pre, vc_exponents=None):
    """``shade_env`` on an :class:`EnvBasis` (torch): the same sums as :func:`_shade_env_generic`, with texels
    along the last axis of every product (``(3, n) @ (n, N)`` for the diffuse part, one ``(3·lobes, n) @ (n, N)``
    for all lobes, the lobe weighting as a sum over the leading axis of ``(lobes, 3, N)``)."""
    import torch

    N = pre.n_texels
    dev = pre.Yr.device
    order = len(A) - 1
    lvl = _band_of_coeff(order)
    nd = (Ld + 1) ** 2
    cols = pre.n_cols[pre.n_cols < nd]
    glob = K.ndim == 2
    Kn = w.shape[-1]
    active = _active_lobes(w, True)
    c2 = c.expand(lead + (3,)).reshape(N, 3)
    w2 = w.expand(lead + (Kn,)).reshape(N, Kn)
    Acols = torch.as_tensor(A[lvl[cols]] / math.pi, dtype=dt, device=dev)
    cols_t = torch.as_tensor(cols, device=dev)
    Yn = pre.Yn[:len(cols)]
    Yn = Yn if Yn.dtype == dt else Yn.to(dt)
    Yr = pre.Yr if pre.Yr.dtype == dt else pre.Yr.to(dt)
    ndv = pre.ndv.reshape(-1).to(dt)
    if not glob:
        # per-texel lighting (..., 3, n) broadcasting against the texels: texel-major einsum
        Kx = K.expand(lead + K.shape[-2:]).reshape(N, 3, K.shape[-1])
        diffuse = c2 * torch.einsum("pcn,np->pc", Kx[..., cols_t] * Acols, Yn)
        spec = None
        for i in active:
            ni = (Ls[i] + 1) ** 2
            Bi = torch.as_tensor(B[i][lvl[:ni]], dtype=dt, device=dev)
            Si = torch.einsum("pcn,np->pc", Kx[..., :ni] * Bi, Yr[:ni]) * w2[:, i:i + 1]
            if vc_exponents is not None:
                Si = Si * specular_view_albedo(vc_exponents[i], ndv)[:, None]
            spec = Si if spec is None else spec + Si
        spec = torch.zeros_like(diffuse) if spec is None else spec
        if not pre.all_front:
            spec = torch.where(pre.front[:, None], spec, torch.zeros_like(spec))
    else:
        diffuse = ((K[:, cols_t] * Acols) @ Yn) * c2.T  # (3, N)
        spec = None
        if active:
            Kst = _stacked_lobe_coeffs(K, torch.as_tensor(B, dtype=dt, device=dev), Ls, active, lvl, K.new_zeros)
            S = (Kst @ Yr[:Kst.shape[1]]).view(len(active), 3, N)  # lobe-major rows
            wa = w2 if len(active) == Kn else w2[:, active]
            wT = wa.T.contiguous()  # (lobes, N): the weighting below then runs along contiguous rows
            if vc_exponents is not None:
                wT = torch.stack([wT[j] * specular_view_albedo(vc_exponents[i], ndv) for j, i in enumerate(active)])
            spec = (S * wT[:, None, :]).sum(0)  # (3, N)
            if not pre.all_front:
                spec = torch.where(pre.front[None, :], spec, torch.zeros_like(spec))
        diffuse = diffuse.T
        spec = torch.zeros_like(diffuse) if spec is None else spec.T
    diffuse = diffuse.reshape(lead + (3,))
    spec = spec.reshape(lead + (3,))
    if mask is not None:
        mt = torch.as_tensor(np.broadcast_to(mask, lead).copy(), device=dev)[..., None]
        diffuse = torch.where(mt, diffuse, torch.zeros_like(diffuse))
        spec = torch.where(mt, spec, torch.zeros_like(spec))
    return diffuse, spec


def _shade_env_generic(tm, c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, vc_exponents=None):
    """Broadcasting path: torch (differentiable) or per-texel lighting in numpy."""
    if tm:
        import torch

        xp_where = torch.where
        einsum = torch.einsum
        As = torch.as_tensor(A, dtype=dt, device=n.device)
        Bs = torch.as_tensor(B, dtype=dt, device=n.device)

        def norm(x):
            return x * torch.rsqrt((x * x).sum(-1, keepdim=True).clamp_min(1e-30))
    else:
        xp_where = np.where
        einsum = np.einsum
        As, Bs = A.astype(dt), B.astype(dt)

        def norm(x):
            return x / np.sqrt(np.maximum((x * x).sum(-1, keepdims=True), dt(1e-30)))

    Kn = w.shape[-1]
    active = _active_lobes(w, tm)  # an all-zero lobe costs nothing
    order = len(A) - 1
    lvl = _band_of_coeff(order)
    nd = (Ld + 1) ** 2
    nn = norm(n)
    vv = norm(v)
    # Geometry without gradients: evaluate the basis with the blocked numpy kernel and keep only the cheap linear
    # part in the autograd graph.
    fixed_geom = tm and nn.device.type == "cpu" and not (nn.requires_grad or vv.requires_grad)
    if fixed_geom:
        def basis(d, L):
            return _basis_coeff_major(d, L).T.reshape(d.shape[:-1] + ((L + 1) ** 2,))
    else:
        def basis(d, L):
            return sh_basis(d, L, normalize=False)
    Yn = basis(nn, Ld)
    KA = K[..., :nd] * As[lvl[:nd]]
    glob = K.ndim == 2

    def apply(Kx, Y):  # Σ_n Kx[c, n] Y[..., n]
        if tm and Y.dtype != Kx.dtype:
            Y = Y.to(Kx.dtype)
        return Y @ Kx.T if glob else einsum("...cn,...n->...c", Kx, Y)

    diffuse = c * apply(KA, Yn) * (1.0 / math.pi)
    ndv = (nn * vv).sum(-1)
    r = (2.0 * ndv)[..., None] * nn - vv
    spec = None
    if active:
        Lsmax = max(Ls[i] for i in active)
        Yr = basis(r, Lsmax)
        if glob and len(active) > 1 and vc_exponents is None:
            # one lighting, several lobes: one product of the stacked coefficient rows with the basis of r
            A_ = len(active)
            Kst = _stacked_lobe_coeffs(K, Bs, Ls, active, lvl,
                                       K.new_zeros if tm else (lambda shape: np.zeros(shape, K.dtype)))
            nmax = Kst.shape[1]
            S_all = apply(Kst, Yr[..., :nmax])  # (*lead, 3·A), lobe-major
            S_all = S_all.reshape(S_all.shape[:-1] + (A_, 3))
            wa = w if A_ == Kn else w[..., active]
            spec = (S_all * wa[..., None]).sum(-2)
            active = []
        for i in active:
            ni = (Ls[i] + 1) ** 2
            Si = apply(K[..., :ni] * Bs[i][lvl[:ni]], Yr[..., :ni]) * w[..., i:i + 1]
            if vc_exponents is not None:
                Si = Si * specular_view_albedo(vc_exponents[i], ndv)[..., None]
            spec = Si if spec is None else spec + Si
        spec = xp_where((ndv > 0)[..., None], spec, spec * 0)
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

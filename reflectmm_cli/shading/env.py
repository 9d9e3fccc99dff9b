"""Shading under SH environment lighting (DESIGN.md §2).

``s_d = c/π · Σ_l A_l Σ_m K_lm Y_lm(n)`` (exact for band-limited lighting) and
``s_s = Σ_i w_i Σ_l B_l^i Σ_m K_lm Y_lm(r)``, ``r = 2(n·v)n − v`` (exact at normal view, an approximation at
other view angles — see docs/shading.md and benchmarks/bench_shading.py for its measured error).

Work that a scene does not need is skipped: bands where every active lobe has ``|B_l| ≤ band_tol`` (and where
``|A_l|/π ≤ band_tol`` for the diffuse part), lobes whose weights are all zero, texels outside ``mask``, and the
specular part of texels facing away from the viewer (n·v ≤ 0, where it is 0 by definition).
"""
from __future__ import annotations

import math

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from ._array import any_torch, as_array, broadcast_shapes, check_last, compute_dtype, device_of
from .brdf import _check_exponents
from .sh import blinn_phong_sh_coeffs, lambert_sh_coeffs, sh_basis, sh_basis_into

__all__ = ["shade_env", "band_limits"]

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


def _validate(albedo, weights, exponents, normal, view_dir, sh_coeffs, mask):
    tm = any_torch(albedo, weights, exponents, normal, view_dir, sh_coeffs)
    dt = compute_dtype(albedo, weights, exponents, normal, view_dir, sh_coeffs, torch_mode=tm)
    dev = device_of(albedo, weights, exponents, normal, view_dir, sh_coeffs)
    c = as_array("albedo", albedo, torch_mode=tm, dtype=dt, device=dev)
    w = as_array("weights", weights, torch_mode=tm, dtype=dt, device=dev)
    p = as_array("exponents", exponents, torch_mode=tm, dtype=dt, device=dev)
    n = as_array("normal", normal, torch_mode=tm, dtype=dt, device=dev)
    v = as_array("view_dir", view_dir, torch_mode=tm, dtype=dt, device=dev)
    K = as_array("sh_coeffs", sh_coeffs, torch_mode=tm, dtype=dt, device=dev)
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
              chunk: int = DEFAULT_CHUNK):
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
        chunk: texels per block in the numpy fast path (cache blocking).
    Returns:
        ``(diffuse, specular)``, each (..., 3). The specular part is 0 where n·v ≤ 0. numpy in → numpy out,
        torch in → torch out (differentiable w.r.t. every input, including the SH coefficients).
    """
    tm, dt, c, w, p, n, v, K, order, lead, mask = _validate(
        albedo, weights, exponents, normal, view_dir, sh_coeffs, mask)
    if band_tol < 0 or not math.isfinite(band_tol):
        raise ReflectmmError(f"shading: band_tol must be finite and ≥ 0, got {band_tol}")
    Ld, Ls = band_limits(p, order, band_tol)
    A = lambert_sh_coeffs(order)
    B = blinn_phong_sh_coeffs(p, order)
    if not tm and K.ndim == 2:
        return _shade_env_numpy(c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, chunk)
    return _shade_env_generic(tm, c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt)


def _flat(a, lead, k):
    return np.broadcast_to(a, lead + (k,)).reshape(-1, k)


def _shade_env_numpy(c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt, chunk):
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
    lvl = np.repeat(np.arange(len(A)), 2 * np.arange(len(A)) + 1)
    KA = (K[:, :nd] * A[lvl[:nd]]).astype(dt)  # (3, nd)
    Lsmax = max([Ls[i] for i in active], default=-1)
    ns = (Lsmax + 1) ** 2
    KB = [(K[:, :(Ls[i] + 1) ** 2] * B[i][lvl[:(Ls[i] + 1) ** 2]]).astype(dt) for i in range(Kn)]
    inv_pi = dt(1.0 / math.pi)
    buf_d = np.empty((nd, chunk), dt)
    buf_s = np.empty((max(ns, 1), chunk), dt)
    for s in range(0, Ntex, chunk):
        sl = slice(s, min(Ntex, s + chunk))
        rows = sl if idx is None else idx[sl]
        nn = n2[rows]
        nn = nn / np.sqrt(np.maximum((nn * nn).sum(1, keepdims=True), dt(1e-30)))
        nT = np.ascontiguousarray(nn.T)
        m = nT.shape[1]
        Yn = sh_basis_into(nT[0], nT[1], nT[2], Ld, buf_d[:, :m])
        D = KA @ Yn  # (3, m)
        diffuse[rows] = c2[rows] * (D.T * inv_pi)
        if not active:
            continue
        vv = v2[rows]
        vv = vv / np.sqrt(np.maximum((vv * vv).sum(1, keepdims=True), dt(1e-30)))
        ndv = (nn * vv).sum(1)
        front = ndv > 0
        if not front.all():
            sub = np.flatnonzero(front)
            if sub.size == 0:
                continue
            nn, vv, ndv = nn[sub], vv[sub], ndv[sub]
            rows_s = (np.arange(sl.start, sl.stop) if idx is None else idx[sl])[sub]
        else:
            rows_s = rows
        r = (2.0 * ndv)[:, None] * nn - vv
        rT = np.ascontiguousarray(r.T)
        ms = rT.shape[1]
        Yr = sh_basis_into(rT[0], rT[1], rT[2], Lsmax, buf_s[:, :ms])
        wr = w2[rows_s]
        acc = np.zeros((3, ms), dt)
        for i in active:
            ni = (Ls[i] + 1) ** 2
            acc += (KB[i] @ Yr[:ni]) * wr[:, i]
        specular[rows_s] = acc.T
    return diffuse.reshape(lead + (3,)), specular.reshape(lead + (3,))


def _shade_env_generic(tm, c, w, n, v, K, A, B, Ld, Ls, lead, mask, dt):
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
    wz = w.detach() if tm else w
    active = [i for i in range(Kn) if bool((wz[..., i] != 0).any())]
    order = len(A) - 1
    lvl = np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)
    nd = (Ld + 1) ** 2
    nn = norm(n)
    vv = norm(v)
    Yn = sh_basis(nn, Ld, normalize=False)
    KA = K[..., :nd] * As[lvl[:nd]]
    diffuse = c * einsum("...cn,...n->...c", KA, Yn) * (1.0 / math.pi)
    ndv = (nn * vv).sum(-1)
    r = (2.0 * ndv)[..., None] * nn - vv
    spec = None
    if active:
        Lsmax = max(Ls[i] for i in active)
        Yr = sh_basis(r, Lsmax, normalize=False)
        for i in active:
            ni = (Ls[i] + 1) ** 2
            Si = einsum("...cn,...n->...c", K[..., :ni] * Bs[i][lvl[:ni]], Yr[..., :ni]) * w[..., i:i + 1]
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

"""Real spherical harmonics: basis, rotation and the Funk–Hecke kernels of docs/design.md §2.

Convention (the one of Deep3DFaceRecon): real, orthonormal over the unit sphere, Condon–Shortley phase kept,
polar axis +z, azimuth φ = atan2(y, x), flat index ``l² + l + m``::

    Y_l0        = N_l0 P_l^0(z)
    Y_lm  (m>0) = √2 N_lm P_l^m(z) cos(mφ)
    Y_l,-m(m>0) = √2 N_lm P_l^m(z) sin(mφ)

with ``P_l^m`` including the (−1)^m phase, so e.g. ``Y_1,-1 = −√(3/4π) y``, ``Y_10 = √(3/4π) z``,
``Y_11 = −√(3/4π) x`` (see docs/shading.md for l ≤ 2).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from ._array import any_torch, as_array, check_last, compute_dtype, device_of, safe_normalize, stack
from .exponents import ExponentError, check_exponents

__all__ = [
    "sh_count",
    "sh_order",
    "sh_index",
    "sh_basis",
    "sh_rotation",
    "lambert_sh_coeffs",
    "blinn_phong_sh_coeffs",
    "blinn_phong_norm",
    "fibonacci_sphere",
    "sh_from_deep3d",
]

MAX_ORDER = 64


def sh_count(order: int) -> int:
    """Number of coefficients of an order-``order`` expansion, ``(order + 1)²``."""
    return (int(order) + 1) ** 2


def sh_order(n_coeffs: int, what: str = "sh_coeffs") -> int:
    """The order L of an expansion of ``n_coeffs`` = (L+1)² coefficients (the inverse of :func:`sh_count`); a
    one-line error naming ``what`` when ``n_coeffs`` is not a square."""
    n = int(n_coeffs)
    L = int(round(math.sqrt(n))) - 1
    if L < 0 or (L + 1) ** 2 != n:
        raise ReflectmmError(f"shading: argument '{what}' has {n} coefficients per channel, not (L+1)^2")
    return L


def sh_index(l: int, m: int) -> int:  # noqa: E741 - l is the SH degree
    """Flat index ``l² + l + m`` of ``Y_lm``."""
    if abs(m) > l:
        raise ReflectmmError(f"sh_index: |m| = {abs(m)} exceeds l = {l}")
    return l * l + l + m


def _check_order(order) -> int:
    try:
        o = int(order)
    except (TypeError, ValueError):
        raise ReflectmmError(f"SH order must be an integer, got {order!r}") from None
    if o != order or o < 0 or o > MAX_ORDER:
        raise ReflectmmError(f"SH order must be an integer in 0..{MAX_ORDER}, got {order!r}")
    return o


@lru_cache(maxsize=None)
def _legendre_consts(order: int):
    """Recurrence constants (Holmes & Featherstone) for the fully normalised Q_l^m = N_lm P_l^m / sin^m θ."""
    pmm = []  # Q_m^m, scalars (CS phase included)
    v = 1.0 / math.sqrt(4.0 * math.pi)
    for m in range(order + 1):
        if m > 0:
            v *= -math.sqrt((2.0 * m + 1.0) / (2.0 * m))
        pmm.append(v)
    a = {}
    b = {}
    for m in range(order + 1):
        for l in range(m + 2, order + 1):  # noqa: E741
            a[l, m] = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
            b[l, m] = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
    return pmm, a, b


def _sh_columns(x, y, z, order: int, ones):
    """List of the (order+1)² basis columns (arrays shaped like x) for unit vectors (x, y, z).

    Uses only elementwise arithmetic so it works identically for numpy arrays and torch tensors (autograd-safe).
    Azimuthal factors sin^m θ cos(mφ), sin^m θ sin(mφ) are Re/Im of (x + iy)^m, so no atan2 and no pole issues.
    """
    pmm, a, b = _legendre_consts(order)
    n = (order + 1) ** 2
    cols = [None] * n
    sqrt2 = math.sqrt(2.0)
    cm = sm = None
    for m in range(order + 1):
        if m == 1:
            cm, sm = x, y
        elif m > 1:
            cm, sm = x * cm - y * sm, x * sm + y * cm
        # Q_m^m (constant), Q_{m+1}^m, then the three-term recurrence in l.
        q2 = None
        q1 = ones * pmm[m] if m == 0 else pmm[m]
        for l in range(m, order + 1):  # noqa: E741
            if l == m:
                q = q1
            elif l == m + 1:
                q = (math.sqrt(2.0 * m + 3.0) * pmm[m]) * z
                q2, q1 = q1, q
            else:
                q = a[l, m] * (z * q1 - b[l, m] * q2)
                q2, q1 = q1, q
            if m == 0:
                cols[l * l + l] = q
            else:
                qs = sqrt2 * q
                cols[l * l + l + m] = qs * cm
                cols[l * l + l - m] = qs * sm
    return cols


def sh_basis(dirs, order: int, *, normalize: bool = True):
    """Real orthonormal SH basis evaluated at directions.

    Args:
        dirs: (..., 3) directions (numpy or torch). Normalised internally unless ``normalize=False``
            (then they must already be unit length). Zero vectors give the value of the basis at the pole of
            a zero-length vector, i.e. only the l = 0 term is non-zero.
        order: maximum degree L (0..64; stable recurrences, tested to 16+).
    Returns:
        (..., (L+1)²) basis values, index ``l² + l + m``; float32 for float16/32 input, float64 for float64,
        torch tensor iff ``dirs`` is a tensor (differentiable).
    """
    order = _check_order(order)
    tm = any_torch(dirs)
    dt = compute_dtype(dirs, torch_mode=tm)
    d = as_array("dirs", dirs, torch_mode=tm, dtype=dt, device=device_of(dirs))
    check_last("dirs", d, 3)
    if normalize:
        d = safe_normalize(d, tm)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    if tm:
        import torch

        ones = torch.ones_like(x)
    else:
        ones = np.ones_like(x)
    cols = _sh_columns(x, y, z, order, ones)
    return stack(cols, -1, tm)


def phase_step(x, y, cm, sm, out_c, out_s, tmp) -> None:
    """One step of the azimuthal factors, numpy, in place: ``(out_c, out_s) = (x·cm − y·sm, x·sm + y·cm)``, i.e.
    Re/Im of (x + iy)^(m+1) from those of (x + iy)^m (all 1-D float arrays of one length). ``out_c`` must not be
    ``cm`` or ``sm``; ``out_s`` may be ``sm`` (not ``cm``); ``tmp`` is scratch."""
    np.multiply(x, cm, out=out_c)
    np.multiply(y, sm, out=tmp)
    out_c -= tmp
    np.multiply(x, sm, out=out_s)
    np.multiply(y, cm, out=tmp)
    out_s += tmp


def sh_basis_into(x, y, z, order: int, out: np.ndarray) -> np.ndarray:
    """numpy fast path: write the basis for 1-D unit vector components into ``out`` of shape ((L+1)², N).

    Coefficient-major layout so each basis function is one contiguous row (what a BLAS matmul wants).
    Uses in-place ufuncs and two scratch buffers; no per-column allocation.
    """
    pmm, a, b = _legendre_consts(order)
    sqrt2 = math.sqrt(2.0)
    N = x.shape[0]
    dt = out.dtype
    cm = np.empty(N, dt)
    sm = np.empty(N, dt)
    tmp = np.empty(N, dt)
    cm_new = np.empty(N, dt)
    qa = np.empty(N, dt)
    qb = np.empty(N, dt)
    qc = np.empty(N, dt)
    cm2 = np.empty(N, dt)  # √2 · cos-part, √2 · sin-part: the √2 of m > 0 applied once per m, not per row
    sm2 = np.empty(N, dt)
    for m in range(order + 1):
        if m == 1:
            cm[:] = x
            sm[:] = y
        elif m > 1:
            phase_step(x, y, cm, sm, cm_new, sm, tmp)
            cm, cm_new = cm_new, cm
        if m > 0:
            np.multiply(cm, sqrt2, out=cm2)
            np.multiply(sm, sqrt2, out=sm2)
        # q1 = Q_{l-1}, q2 = Q_{l-2}; rotate three buffers.
        q2, q1, q = qa, qb, qc
        for l in range(m, order + 1):  # noqa: E741
            if l == m:
                q1.fill(pmm[m])
                cur = q1
            elif l == m + 1:
                np.multiply(z, math.sqrt(2.0 * m + 3.0) * pmm[m], out=q)
                q2, q1, q = q1, q, q2
                cur = q1
            else:
                np.multiply(z, q1, out=q)
                np.multiply(q2, b[l, m], out=tmp)
                q -= tmp
                q *= a[l, m]
                q2, q1, q = q1, q, q2
                cur = q1
            if m == 0:
                out[l * l + l] = cur
            else:
                np.multiply(cur, cm2, out=out[l * l + l + m])
                np.multiply(cur, sm2, out=out[l * l + l - m])
    return out


# ---------------------------------------------------------------------------------------------------------------
# Rotation


def fibonacci_sphere(n: int) -> np.ndarray:
    """n quasi-uniform unit vectors (float64, (n, 3)), deterministic."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


@lru_cache(maxsize=None)
def _rotation_samples(order: int):
    """Sample directions and per-band pseudo-inverses of the basis at them (float64)."""
    npts = max(4 * (order + 1) ** 2, 32)
    pts = fibonacci_sphere(npts)
    Y = sh_basis(pts, order)  # (npts, n)
    pinvs = []
    for l in range(order + 1):  # noqa: E741
        blk = Y[:, l * l:(l + 1) ** 2]
        pinvs.append(np.linalg.pinv(blk))  # (2l+1, npts)
    return pts, pinvs


def sh_rotation(R, order: int):
    """Block-diagonal real SH rotation matrix.

    For a rotation matrix ``R`` (3×3, proper, numpy or torch) returns ``M`` ((L+1)², (L+1)²) such that, for any
    function f with coefficients ``c``, ``M @ c`` are the coefficients of the rotated function
    ``g(d) = f(Rᵀ d)`` (f carried along by R). Equivalently ``sh_basis(Rᵀ d) = Mᵀ sh_basis(d)``, so shading a
    normal n under rotated lighting equals shading Rᵀn under the original lighting.

    Exact (to rounding): each band is closed under rotation, so each (2l+1)² block is the unique solution of
    ``Y_l(Rᵀ d_k) = Aᵀ Y_l(d_k)`` over an over-determined, well-conditioned set of sample directions.
    Differentiable in ``R`` when it is a torch tensor.
    """
    order = _check_order(order)
    tm = any_torch(R)
    dt = compute_dtype(R, torch_mode=tm)
    if not tm:
        dt = np.float64
    Rm = as_array("R", R, torch_mode=tm, dtype=dt, device=device_of(R))
    if tuple(Rm.shape) != (3, 3):
        raise ReflectmmError(f"sh_rotation: R must have shape (3, 3), got {tuple(Rm.shape)}")
    Rd = Rm.detach().cpu().double().numpy() if tm else Rm
    if not np.allclose(Rd @ Rd.T, np.eye(3), atol=1e-5) or np.linalg.det(Rd) < 0:
        raise ReflectmmError("sh_rotation: R must be a proper rotation matrix (orthonormal, det +1)")
    pts, pinvs = _rotation_samples(order)
    n = (order + 1) ** 2
    if tm:
        import torch

        P = torch.as_tensor(pts, dtype=Rm.dtype, device=Rm.device)
        Yr = sh_basis(P @ Rm, order, normalize=False)  # rows: Y(Rᵀ d_k) since (d_k ᵀ R) = (Rᵀ d_k)ᵀ
        blocks = []
        for l in range(order + 1):  # noqa: E741
            pin = torch.as_tensor(pinvs[l], dtype=Rm.dtype, device=Rm.device)
            # Yr_blk (npts, 2l+1) = Y_blk (npts,2l+1) @ A  →  A = pinv(Y_blk) @ Yr_blk; M_block = A
            blocks.append(pin @ Yr[:, l * l:(l + 1) ** 2])
        return torch.block_diag(*blocks)
    Yr = sh_basis(pts @ Rm, order, normalize=False)
    M = np.zeros((n, n), dtype=np.float64)
    for l in range(order + 1):  # noqa: E741
        s = slice(l * l, (l + 1) ** 2)
        M[s, s] = pinvs[l] @ Yr[:, s]
    return M


# ---------------------------------------------------------------------------------------------------------------
# Funk–Hecke kernels


def lambert_sh_coeffs(order: int) -> np.ndarray:
    """Ramamoorthi–Hanrahan clamped-cosine coefficients A_l, l = 0..L (float64, (L+1,)).

    A_0 = π, A_1 = 2π/3, odd l > 1: 0, even l: 2π (−1)^(l/2−1) / ((l+2)(l−1)) · l! / (2^l ((l/2)!)²).
    Irradiance is ``E(n) = Σ_l A_l Σ_m K_lm Y_lm(n)``; diffuse shading is ``c/π · E``.
    """
    order = _check_order(order)
    A = np.zeros(order + 1)
    for l in range(order + 1):  # noqa: E741
        if l == 0:
            A[l] = math.pi
        elif l == 1:
            A[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            h = l // 2
            # l!/(2^l (h!)^2) = C(l, h) / 2^l, computed in logs to stay exact-ish for any l.
            ratio = math.exp(math.lgamma(l + 1) - 2 * math.lgamma(h + 1) - l * math.log(2.0))
            A[l] = 2.0 * math.pi * (-1) ** (h - 1) / ((l + 2.0) * (l - 1.0)) * ratio
    return A


def blinn_phong_norm(p):
    """Lobe normalisation ``f = (p + 2) / (4π (2 − 2^(−p/2)))`` (numpy or torch, any shape, p > 0).

    With it, ``f · ((1 + t)/2)^(p/2)`` integrates to 1 over the hemisphere t = cos θ ≥ 0, so at normal incidence
    under uniform unit radiance the specular shading of a lobe equals its weight.
    """
    if any_torch(p):
        import torch

        return (p + 2.0) / (4.0 * math.pi * (2.0 - torch.exp2(-p / 2.0)))
    p = np.asarray(p, dtype=np.float64) if not isinstance(p, np.ndarray) else p
    return (p + 2.0) / (4.0 * math.pi * (2.0 - np.exp2(-p / 2.0)))


# Above this exponent the Funk–Hecke coefficients use the closed form of _bp_coeffs_sharp (its error,
# ≤ (p + 2) 2^(−p/2−1), is below 1e-28 there); below it, Gauss–Legendre with ≤ ~110 nodes.
SHARP_LOBE_P = 200.0


def _bp_coeffs_sharp(p: float, order: int) -> tuple:
    """B_l (l = 0..order) of a sharp lobe in closed form; exact up to ≤ (p + 2) 2^(−p/2−1).

    With u = (1+t)/2 and q = p/2, ``B_l = 4π f ∫_{1/2}^1 u^q P̃_l(u) du`` where ``P̃_l(u) = P_l(2u − 1)`` is the
    shifted Legendre polynomial. Over the whole [0, 1] the moment is known in closed form (Rodrigues' formula
    and l integrations by parts):

        ∫_0^1 u^q P̃_l(u) du = q (q−1) ⋯ (q−l+1) / ((q+1)(q+2) ⋯ (q+l+1))
                              = 1/(q+l+1) · Π_{j=0}^{l−1} (q−j)/(q+j+1),

    and the dropped part ∫_0^{1/2} is at most 2^(−q−1) in magnitude (|P̃_l| ≤ 1). Cost O(order), any p.
    For large p it tends to the Gaussian-lobe asymptote B_l ≈ exp(−2 l(l+1)/p).
    """
    q = p / 2.0
    front = 4.0 * math.pi * float(blinn_phong_norm(p))
    out = np.empty(order + 1)
    prod = 1.0
    for l in range(order + 1):  # noqa: E741
        out[l] = front * prod / (q + l + 1.0)
        prod *= (q - l) / (q + l + 1.0)
    return tuple(out)


@lru_cache(maxsize=256)
def _bp_coeffs_cached(p: float, order: int) -> tuple:
    if p >= SHARP_LOBE_P:
        return _bp_coeffs_sharp(p, order)
    # B_l = 2π f ∫_0^1 ((1+t)/2)^(p/2) P_l(t) dt; substitute u = (1+t)/2 ∈ [1/2, 1], dt = 2 du.
    # The integrand u^(p/2) P_l(2u−1) is analytic on [1/2, 1] (a polynomial of degree p/2 + l when p/2 is an
    # integer), so Gauss–Legendre with ~(p/2 + L)/2 + 48 nodes is exact or converges exponentially.
    nn = int(math.ceil((p / 2.0 + order + 1) / 2.0)) + 48
    x, w = np.polynomial.legendre.leggauss(nn)
    u = 0.75 + 0.25 * x
    wu = 0.25 * w
    t = 2.0 * u - 1.0
    g = np.exp((p / 2.0) * np.log(u)) * wu * 2.0  # ((1+t)/2)^(p/2) dt
    f = float(blinn_phong_norm(p))
    out = np.empty(order + 1)
    P0 = np.ones_like(t)
    P1 = t
    for l in range(order + 1):  # noqa: E741
        if l == 0:
            P = P0
        elif l == 1:
            P = P1
        else:
            P = ((2 * l - 1) * t * P1 - (l - 1) * P0) / l
            P0, P1 = P1, P
        out[l] = 2.0 * math.pi * f * float(np.dot(g, P))
    return tuple(out)


def blinn_phong_sh_coeffs(p, order: int) -> np.ndarray:
    """Funk–Hecke coefficients B_l (l = 0..L) of the normalised half-angle lobe of docs/design.md §2.

    ``B_l = 2π ∫_0^1 f ((1+t)/2)^(p/2) P_l(t) dt`` so that ``B_0 = 1``. Accurate to ~1e-12 for any p > 0:
    Gauss–Legendre quadrature below p = 200, a closed form above (O(L) work, so p = 1e5 costs nothing).
    ``p`` may be a scalar (→ (L+1,)) or a 1-D array of K exponents (→ (K, L+1)). float64.
    """
    order = _check_order(order)
    pa = np.asarray(p, dtype=np.float64)
    try:  # the one exponent check, its positivity rule only (any p > 0 has coefficients)
        check_exponents(pa.reshape(-1), max_exponent=None, distinct=False, nonempty=False)
    except ExponentError:
        raise ReflectmmError(f"blinn_phong_sh_coeffs: exponents must be finite and > 0, got {pa.tolist()}") from None
    if pa.ndim == 0:
        return np.array(_bp_coeffs_cached(float(pa), order))
    if pa.ndim != 1:
        raise ReflectmmError(f"blinn_phong_sh_coeffs: p must be a scalar or 1-D, got shape {pa.shape}")
    return np.array([_bp_coeffs_cached(float(v), order) for v in pa]).reshape(len(pa), order + 1)


# Deep3DFaceRecon multiplies its 27 lighting numbers by a_l (and a normalisation already folded into our Y_lm)
_DEEP3D_A = (math.pi, 2.0 * math.pi / math.sqrt(3.0), 2.0 * math.pi / math.sqrt(8.0))


def sh_from_deep3d(gamma, *, add_init: bool = True):
    """Deep3DFaceRecon lighting (27 numbers, (..., 27) or (..., 3, 9)) → radiance SH coefficients (..., 3, 9).

    Deep3DFaceRecon colours a vertex ``texture · Σ a_l γ_lm Y_lm(n)`` (same basis and signs as ours, see
    :func:`sh_basis`) after adding 0.8 to γ_00 (``add_init``). Our diffuse shading is ``c/π Σ A_l K_lm Y_lm(n)``,
    so ``K_lm = π a_l γ_lm / A_l`` with a_l = (π, 2π/√3, 2π/√8). numpy or torch.
    """
    g = gamma
    if tuple(g.shape[-1:]) == (27,):
        g = g.reshape(*g.shape[:-1], 3, 9)
    if tuple(g.shape[-2:]) != (3, 9):
        raise ReflectmmError(f"sh_from_deep3d: gamma must have shape (..., 27) or (..., 3, 9), got {tuple(g.shape)}")
    A = lambert_sh_coeffs(2)
    scale = np.array([math.pi * _DEEP3D_A[l] / A[l] for l in (0, 1, 1, 1, 2, 2, 2, 2, 2)])  # noqa: E741
    init = np.zeros(9)
    if add_init:
        init[0] = 0.8
    if any_torch(g):
        import torch

        return (g + torch.as_tensor(init, dtype=g.dtype, device=g.device)) * torch.as_tensor(
            scale, dtype=g.dtype, device=g.device)
    return (np.asarray(g, dtype=np.float64) + init) * scale

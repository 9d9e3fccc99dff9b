"""Equirectangular environment maps ↔ real SH coefficients.

Equirectangular convention (latitude–longitude, viewed from *inside* the sphere, like a panorama):

- frame: right-handed, **+y up**, an un-rotated camera looks down **−z**, +x is to its right;
- row ``i`` (0 = top) has polar angle from +y ``θ_i = π (i + ½) / H``;
- column ``j`` has azimuth ``φ_j = 2π (j + ½) / W − π``; the image centre (φ = 0) is the −z direction,
  φ = +π/2 (three quarters across) is +x, the left/right edges are +z (behind the camera);
- direction ``d = (sin φ sin θ, cos θ, −cos φ sin θ)``.

SH coefficients are in the convention of :mod:`reflectmm_cli.shading.sh` (polar axis +z of that same frame).
Pixel values are radiance (linear HDR); coefficients are ``K_lm = ∫ L(d) Y_lm(d) dω``.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .sh import _check_order, sh_basis_into, sh_order, sh_rotation

__all__ = ["equirect_directions", "equirect_weights", "project_envmap", "envmap_from_sh", "direction_to_equirect",
           "envmap_rgb", "load_envmap"]

_CHUNK = 1 << 16


def _angles(width: int, height: int):
    theta = math.pi * (np.arange(height, dtype=np.float64) + 0.5) / height
    phi = 2.0 * math.pi * (np.arange(width, dtype=np.float64) + 0.5) / width - math.pi
    return theta, phi


def equirect_directions(width: int, height: int, dtype=np.float64) -> np.ndarray:
    """Unit direction of every pixel centre, (H, W, 3), in the convention of this module."""
    theta, phi = _angles(width, height)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack(np.broadcast_arrays(np.sin(phi)[None, :] * st, ct, -np.cos(phi)[None, :] * st), -1)
    return d.astype(dtype)


def direction_to_equirect(d):
    """(…, 3) directions → (u, v) in [0, 1)² (u: column fraction, v: row fraction from the top)."""
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
    phi = np.arctan2(d[..., 0], -d[..., 2])
    return (phi + math.pi) / (2.0 * math.pi) % 1.0, theta / math.pi


@lru_cache(maxsize=16)
def _fejer1(n: int) -> np.ndarray:
    # Fejér's first rule on x = cos θ, nodes θ_k = π (k + ½)/n: exact for polynomials of degree ≤ n − 1.
    theta = math.pi * (np.arange(n) + 0.5) / n
    j = np.arange(1, n // 2 + 1, dtype=np.float64)
    s = np.zeros(n)
    for start in range(0, len(j), 512):
        jj = j[start:start + 512]
        s += (np.cos(2.0 * np.outer(theta, jj)) / (4.0 * jj * jj - 1.0)).sum(1)
    return (2.0 / n) * (1.0 - 2.0 * s)


def equirect_weights(width: int, height: int, quadrature: str = "fejer") -> np.ndarray:
    """Solid-angle weight of each row's pixels, (H,) — multiply by every pixel of that row.

    ``"fejer"``: Fejér's first rule in cos θ × uniform azimuth — the pixel centres are exactly its nodes, so the
    projection is exact for maps band-limited to degree L when ``H ≥ 2L + 1`` and ``W ≥ 2L + 1``.
    ``"area"``: the exact solid angle of each pixel, ``(2π/W)(cos θ_top − cos θ_bottom)`` (box filter).
    Both sum to 4π over the map.
    """
    if quadrature == "fejer":
        wt = _fejer1(int(height))
    elif quadrature == "area":
        edges = math.pi * np.arange(height + 1, dtype=np.float64) / height
        wt = np.cos(edges[:-1]) - np.cos(edges[1:])
    else:
        raise ReflectmmError(f"project_envmap: quadrature must be 'fejer' or 'area', got {quadrature!r}")
    return wt * (2.0 * math.pi / width)


def _check_image(image, name="image"):
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ReflectmmError(f"{name}: expected an (H, W, C) equirectangular image, got shape {img.shape}")
    if img.dtype.kind not in "biuf":
        raise ReflectmmError(f"{name}: expected numeric pixels, got dtype {img.dtype}")
    if not np.isfinite(img).all():
        raise ReflectmmError(f"{name}: contains NaN or inf pixels")
    return img


def envmap_rgb(image) -> np.ndarray:
    """Check an environment map's pixels and return them as (H, W, 3) float32 linear RGB radiance.

    Accepts (H, W) or (H, W, 1) grey maps (repeated to RGB) and (H, W, C ≥ 3) maps (the first three channels
    are R, G, B; alpha and further channels are ignored). Refuses 2 channels (grey + alpha or an incomplete
    colour map is ambiguous), maps that are not 2:1 (equirectangular: 360° by 180°), non-numeric, NaN/inf and
    negative pixels with a one-line ReflectmmError (no file
    name: :func:`load_envmap` adds it). The one check shared by ``render --envmap`` and ``build-light-pca``.
    """
    img = np.asarray(image)
    if img.dtype.kind not in "fiu":
        raise ReflectmmError(f"pixels of dtype {img.dtype} are not numeric")
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ReflectmmError(f"not an (H, W, C) image (shape {img.shape})")
    if img.shape[2] == 2:
        raise ReflectmmError("has 2 channels; an environment map needs 1 (grey) or 3 or more (R, G, B first)")
    H, W = img.shape[:2]
    if abs(W - 2 * H) > 1:
        raise ReflectmmError(f"is {W}x{H}; an equirectangular environment map is twice as wide as high (W = 2H)")
    img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[..., :3]
    img = img.astype(np.float32, copy=False)
    bad = ~np.isfinite(img)
    if bad.any():
        y, x = np.argwhere(bad.any(-1))[0]
        raise ReflectmmError(f"{int(bad.any(-1).sum())} NaN or infinite pixel(s) (first at row {y}, column {x})")
    if (img < 0).any():
        raise ReflectmmError(f"{int((img < 0).any(-1).sum())} pixel(s) of negative radiance")
    return img


def load_envmap(path) -> np.ndarray:
    """Read an equirectangular environment map (EXR/HDR/any image) as checked (H, W, 3) float32 RGB
    (:func:`envmap_rgb`); every refusal is one line naming the file."""
    from pathlib import Path

    from reflectmm_cli.artifacts import read_image

    try:
        return envmap_rgb(read_image(path))
    except ReflectmmError as exc:
        msg = str(exc)
        if msg.startswith(f"{path}: "):
            raise
        raise ReflectmmError(f"environment map: {msg}", Path(path)) from None


# Proper rotation taking our directions to the map's own frame: z' = up (+y), x' = −z, y' = −x (azimuth φ' = −φ).
_TO_MAP_FRAME = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def project_envmap(image, order: int, *, quadrature: str = "fejer") -> np.ndarray:
    """SH coefficients of an equirectangular HDR map.

    Args:
        image: (H, W, C) linear radiance (any H, W; C channels, typically 3), numpy.
        order: SH order L.
        quadrature: ``"fejer"`` (default, exact for band-limited maps) or ``"area"`` (pixel solid angles).
    Returns:
        (C, (L+1)²) float64 coefficients ``K_lm = Σ_pixels L(d) Y_lm(d) ΔΩ``.

    Separable: a real Fourier sum along each row (one matmul with a W × (2L+1) table), Legendre sums over the
    rows in the map's own frame (pole = up), then one exact SH rotation into the toolkit frame.
    O(H·W·L) instead of O(H·W·L²).
    """
    order = _check_order(order)
    img = _check_image(image)
    H, W, C = img.shape
    wrow = equirect_weights(W, H, quadrature)  # (H,)
    theta, phi = _angles(W, H)
    ms = np.arange(1, order + 1)
    trig = np.concatenate([np.ones((W, 1)), np.cos(np.outer(phi, ms)), np.sin(np.outer(phi, ms))], 1)  # (W, 2L+1)
    F = np.empty((H, C, 2 * order + 1))
    rows_per = max(1, (1 << 22) // max(1, W * C))
    for r0 in range(0, H, rows_per):
        blk = np.asarray(img[r0:r0 + rows_per], dtype=np.float64)
        F[r0:r0 + rows_per] = np.matmul(np.swapaxes(blk, 1, 2), trig)
    F *= wrow[:, None, None]
    # √2 N_lm P_l^m(cos θ_i) (m > 0) and N_l0 P_l(cos θ_i): the basis at azimuth 0 of the map frame.
    n = (order + 1) ** 2
    P = np.empty((n, H))
    st, ct = np.sin(theta), np.cos(theta)
    sh_basis_into(st, np.zeros(H), ct, order, P)
    Kp = np.zeros((C, n))
    for l in range(order + 1):  # noqa: E741
        base = l * l + l
        Kp[:, base] = F[:, :, 0].T @ P[base]
        for m in range(1, l + 1):
            Kp[:, base + m] = F[:, :, m].T @ P[base + m]  # cos(mφ') = cos(mφ)
            Kp[:, base - m] = -(F[:, :, order + m].T @ P[base + m])  # sin(mφ') = −sin(mφ)
    return Kp @ sh_rotation(_TO_MAP_FRAME.T, order).T


def _project_envmap_direct(image, order: int, *, quadrature: str = "fejer") -> np.ndarray:
    """Reference O(H·W·L²) projection evaluating the basis at every pixel (used by tests and benchmarks)."""
    order = _check_order(order)
    img = _check_image(image)
    H, W, C = img.shape
    wrow = equirect_weights(W, H, quadrature)
    theta, phi = _angles(W, H)
    sphi, cphi = np.sin(phi), -np.cos(phi)
    n = (order + 1) ** 2
    out = np.zeros((C, n), dtype=np.float64)
    rows_per = max(1, _CHUNK // W)
    buf = np.empty((n, rows_per * W), dtype=np.float64)
    for r0 in range(0, H, rows_per):
        r1 = min(H, r0 + rows_per)
        st, ct = np.sin(theta[r0:r1]), np.cos(theta[r0:r1])
        x = (st[:, None] * sphi[None, :]).ravel()
        y = np.repeat(ct, W)
        z = (st[:, None] * cphi[None, :]).ravel()
        Y = sh_basis_into(x, y, z, order, buf[:, : x.shape[0]])
        L = (img[r0:r1].astype(np.float64) * wrow[r0:r1, None, None]).reshape(-1, C)
        out += (Y @ L).T
    return out


def envmap_from_sh(coeffs, width: int, height: int) -> np.ndarray:
    """Evaluate SH coefficients (C, (L+1)²) on an equirectangular grid → (height, width, C) float32."""
    K = np.asarray(coeffs, dtype=np.float64)
    if K.ndim == 1:
        K = K[None]
    if K.ndim != 2:
        raise ReflectmmError(f"envmap_from_sh: coeffs must be (C, (L+1)^2), got shape {K.shape}")
    order = sh_order(K.shape[1])
    if (order + 1) ** 2 != K.shape[1]:
        raise ReflectmmError(f"envmap_from_sh: {K.shape[1]} coefficients is not a square (L+1)^2")
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ReflectmmError(f"envmap_from_sh: width and height must be ≥ 1, got {width}×{height}")
    d = equirect_directions(width, height).reshape(-1, 3)
    out = np.empty((d.shape[0], K.shape[0]), dtype=np.float32)
    n = K.shape[1]
    buf = np.empty((n, min(_CHUNK, d.shape[0])), dtype=np.float64)
    for s in range(0, d.shape[0], _CHUNK):
        dd = d[s:s + _CHUNK]
        Y = sh_basis_into(dd[:, 0].copy(), dd[:, 1].copy(), dd[:, 2].copy(), order, buf[:, : dd.shape[0]])
        out[s:s + dd.shape[0]] = np.einsum("ck,km->mc", K, Y)  # skinny product: see env.py
    return out.reshape(height, width, K.shape[0])

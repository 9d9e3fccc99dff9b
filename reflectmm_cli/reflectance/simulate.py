"""Analytic uv-observations for tests and benchmarks (exact model, no mesh, no images).

The geometry is a face-like patch: an ellipsoid (semi-axes 75, 100, 90 mm along x, y, z) with a Gaussian
nose bump, parametrised symmetrically in UV (column → azimuth φ ∈ [−100°, 100°], row → elevation
θ ∈ [+40°, −40°], row 0 = forehead), so texel ``(row, S−1−col)`` is the exact mirror (x → −x) of
``(row, col)``.  The rig is Multi-PIE-like (docs/pipeline.md): 9 cameras on a horizontal arc, 15° apart,
1.3 m from the head (views ``09_0 … 20_0``), a flash on each of them (``03``–``11``) and two raised flashes
(``14`` on ``08_1``, ``18`` on ``19_1``, 25° above the arc at ∓45°).  With every flash near the horizontal
plane the half vectors lie near one plane: the p = 64 lobe is never seen near its peak on much of the face
(docs/design.md §3) — the observability problem is reproduced, not avoided.

Radiance is rendered with :func:`reflectmm_cli.shading.shade_directional` (the shading core, independent of
the design columns of :mod:`reflectmm_cli.reflectance.design`).  Occlusion (nose shadows) is not modelled:
``observed`` = in mask ∧ n·l > 0 ∧ n·v > ``view_cutoff``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import shade_directional
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS

from .design import conditioning

__all__ = ["face_geometry", "multipie_rig", "default_reflectance", "simulate_observations"]

ARC_VIEWS = ("09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0")
ARC_FLASHES = ("03", "04", "05", "06", "07", "08", "09", "10", "11")
RAISED_FLASHES = (("14", "08_1", -45.0), ("18", "19_1", 45.0))
RIG_RADIUS_MM = 1300.0
RAISED_ELEVATION_DEG = 25.0


def _surface(phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    ax, ay, az = 75.0, 100.0, 90.0
    nose = 22.0 * np.exp(-(phi ** 2) / (2 * 0.13 ** 2) - (theta + 0.08) ** 2 / (2 * 0.22 ** 2))
    x = ax * np.cos(theta) * np.sin(phi)
    y = ay * np.sin(theta)
    z = az * np.cos(theta) * np.cos(phi) + nose
    return np.stack([x, y, z], axis=-1)


def face_geometry(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position (S,S,3) mm, unit normal (S,S,3), mask (S,S)) of the analytic face patch."""
    S = int(size)
    if S < 2:
        raise ReflectmmError(f"simulate: size must be >= 2, got {size}")
    c = (np.arange(S) + 0.5) / S
    u, v = np.meshgrid(c, c)  # u along columns, v along rows
    phi = (u - 0.5) * 2 * np.radians(100.0)
    theta = (0.5 - v) * 2 * np.radians(40.0)
    pos = _surface(phi, theta)
    eps = 1e-6
    dphi = (_surface(phi + eps, theta) - _surface(phi - eps, theta)) / (2 * eps)
    dth = (_surface(phi, theta + eps) - _surface(phi, theta - eps)) / (2 * eps)
    n = np.cross(dphi, dth)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= np.sign(np.sum(n * pos, axis=-1, keepdims=True) + 1e-30)  # outward
    mask = ((u - 0.5) / 0.5) ** 2 + ((v - 0.5) / 0.5) ** 2 <= 1.0
    return pos, n, mask


def multipie_rig(radius_mm: float = RIG_RADIUS_MM):
    """(view_names (V,), cam_centers (V,3), flash_ids (F,), flash_pos (F,3)) of the simulated rig."""
    az = np.radians(np.arange(-60.0, 61.0, 15.0))
    cams = np.stack([radius_mm * np.sin(az), np.zeros_like(az), radius_mm * np.cos(az)], axis=-1)
    fl = [c for c in cams]
    ids = list(ARC_FLASHES)
    el = np.radians(RAISED_ELEVATION_DEG)
    for fid, _cam, a in RAISED_FLASHES:
        a = np.radians(a)
        fl.append(np.array([radius_mm * np.cos(el) * np.sin(a), radius_mm * np.sin(el),
                            radius_mm * np.cos(el) * np.cos(a)]))
        ids.append(fid)
    return np.array(ARC_VIEWS), cams, np.array(ids), np.stack(fl)


def default_reflectance(size: int, exponents: Sequence[float] = DEFAULT_EXPONENTS, asymmetric: bool = False,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth, skin-like ground truth: albedo (3,S,S) in [0.2, 0.75], weights (K,S,S) > 0.

    Symmetric in UV unless ``asymmetric`` (then a left-right gradient is added).  ``seed`` shifts the
    pattern phases, so identities differ.
    """
    S = int(size)
    K = len(exponents)
    rng = np.random.default_rng(seed)
    c = (np.arange(S) + 0.5) / S
    u, v = np.meshgrid(c, c)
    au = np.abs(u - 0.5)
    ph = rng.uniform(0, 2 * np.pi, size=4)
    pat = 0.5 + 0.25 * np.cos(6 * au + ph[0]) * np.cos(5 * v + ph[1]) + 0.25 * np.sin(9 * au * v + ph[2])
    base = np.array([0.62, 0.42, 0.33]) * rng.uniform(0.85, 1.15, size=3)
    albedo = base[:, None, None] * (0.75 + 0.45 * pat)[None]
    tzone = np.exp(-(au / 0.08) ** 2) * np.exp(-((v - 0.45) / 0.3) ** 2)
    weights = np.empty((K, S, S))
    for i in range(K):
        weights[i] = (0.06 + 0.02 * i) * (0.7 + 0.6 * pat * (1 - 0.5 * (i % 2))) + 0.08 * tzone * (i + 1) / K
    if asymmetric:
        albedo *= (1.0 + 0.3 * (u - 0.5))[None]
        weights *= (1.0 - 0.5 * (u - 0.5))[None]
    return np.clip(albedo, 0.0, None), np.clip(weights, 0.0, None)


def simulate_observations(size: int = 64, exponents: Sequence[float] = DEFAULT_EXPONENTS,
                          albedo: np.ndarray | None = None, weights: np.ndarray | None = None,
                          views: Sequence[int] | None = None, flashes: Sequence[int] | None = None, seed: int = 0,
                          noise: float = 0.0, irradiance: float = 2.5, view_cutoff: float = 0.1,
                          asymmetric: bool = False, dtype=np.float16, return_truth: bool = False):
    """Build a uv-observations mapping (docs/pipeline.md) rendered with the exact model.

    Args:
        size: UV resolution S.
        exponents: (K,) lobe exponents of the ground truth.
        albedo, weights: (3,S,S) / (K,S,S) ground truth (default :func:`default_reflectance`).
        views, flashes: indices into the 9 rig views / 11 flashes (default all: P = 99 pairs).
        seed: seeds the default reflectance pattern and the noise.
        noise: multiplicative Gaussian noise, radiance · (1 + noise · N(0,1)) (0 = exact).
        irradiance: E (linear pixel units) of a flash at 1.3 m; flash_intensity = E · 1300².
        view_cutoff: observed needs n·v > view_cutoff.
        asymmetric: default reflectance with a left-right gradient (so mirror pooling is wrong).
        dtype: radiance dtype (the artifact contract is float16).
        return_truth: also return ``{"albedo", "weights", "exponents"}``.
    Returns:
        dict of arrays (all uv-observations keys), or ``(obs, truth)``.
    """
    S = int(size)
    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    K = p.size
    pos, nrm, mask = face_geometry(S)
    names, cams, fids, fpos = multipie_rig()
    vsel = np.arange(len(names)) if views is None else np.asarray(views, dtype=int)
    fsel = np.arange(len(fids)) if flashes is None else np.asarray(flashes, dtype=int)
    names, cams = names[vsel], cams[vsel]
    fids, fpos = fids[fsel], fpos[fsel]
    V, F = len(names), len(fids)
    I = np.full(F, irradiance * RIG_RADIUS_MM ** 2)
    if albedo is None or weights is None:
        a0, w0 = default_reflectance(S, p, asymmetric=asymmetric, seed=seed)
        albedo = a0 if albedo is None else albedo
        weights = w0 if weights is None else weights
    albedo = np.asarray(albedo, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if albedo.shape != (3, S, S) or weights.shape != (K, S, S):
        raise ReflectmmError(f"simulate: albedo must be (3,{S},{S}) and weights ({K},{S},{S}), "
                             f"got {albedo.shape} and {weights.shape}")
    pair_view = np.repeat(np.arange(V), F)
    pair_flash = np.tile(np.arange(F), V)
    P = V * F
    rng = np.random.default_rng(seed + 7919)
    c_hw = np.moveaxis(albedo, 0, -1)
    w_hw = np.moveaxis(weights, 0, -1)
    view_dirs = cams[:, None, None, :] - pos[None]
    ndv = np.einsum("vhwk,hwk->vhw", view_dirs, nrm) / np.linalg.norm(view_dirs, axis=-1)
    visible = mask[None] & (ndv > view_cutoff)
    lit = np.zeros((F, S, S), bool)
    radiance = np.zeros((P, S, S, 3), dtype=dtype)
    observed = np.zeros((P, S, S), bool)
    for f in range(F):
        ld = fpos[f] - pos
        d2 = np.sum(ld * ld, axis=-1)
        lit[f] = mask & (np.einsum("hwk,hwk->hw", ld, nrm) > 0)
        E = (I[f] / d2)[..., None]
        for vi in range(V):
            j = vi * F + f
            ob = visible[vi] & lit[f]
            rad = shade_directional(c_hw, w_hw, p, nrm, ld, view_dirs[vi], np.repeat(E, 3, axis=-1))
            if noise:
                rad = rad * (1.0 + noise * rng.standard_normal(rad.shape))
            radiance[j] = np.where(ob[..., None], rad, 0.0).astype(dtype)
            observed[j] = ob
    cond = conditioning(pos, nrm, cams, fpos, I, pair_view, pair_flash, observed, p, mask=mask)
    obs = {
        "position": pos.astype(np.float32), "normal": nrm.astype(np.float32), "mask": mask,
        "view_names": names.astype(str), "flash_ids": fids.astype(str), "cam_centers": cams,
        "flash_pos": fpos, "flash_intensity": I, "pair_view": pair_view.astype(np.int32),
        "pair_flash": pair_flash.astype(np.int32), "radiance": radiance, "observed": observed,
        "visible": visible, "lit": lit, "saturated": np.zeros((P, S, S), bool),
        "obs_count": observed.sum(0).astype(np.int32), "conditioning": cond.conditioning.astype(np.float32),
        "conditioning_exponents": p,
    }
    if return_truth:
        return obs, {"albedo": albedo, "weights": weights, "exponents": p}
    return obs

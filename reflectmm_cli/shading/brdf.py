"""Multi-lobe Blinn-Phong shading under a directional light (docs/design.md §2).

Frames: all vectors are in one common frame (the caller's; the toolkit uses model/world space, +y up, camera
looking down −z). ``light_dir`` points from the surface *towards* the light, ``view_dir`` from the surface
*towards* the camera. None of them needs to be unit length.

The exponent rules (default set, bound, the one check) live in :mod:`.exponents` and are re-exported here.
"""
from __future__ import annotations

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from ._array import any_torch, as_array, broadcast_shapes, check_last, compute_dtype, device_of, safe_normalize
from .exponents import (DEFAULT_EXPONENTS, LOBE_RCOND_MIN, MAX_EXPONENT, ExponentError, check_exponents,
                        lobe_similarity)
from .sh import blinn_phong_norm

__all__ = ["blinn_phong_norm", "shade_directional", "DEFAULT_EXPONENTS", "MAX_EXPONENT", "LOBE_RCOND_MIN",
           "lobe_similarity", "check_exponents", "check_distinct_exponents", "ExponentError"]


def check_distinct_exponents(exponents, what: str = "exponents") -> None:
    """The library's own guard (fit_maps, build-pca), whatever the caller validated: a one-line ReflectmmError if
    two exponents give numerically collinear lobes (:func:`check_exponents` with only that rule; large p are
    allowed here, the shading core handles them cheaply)."""
    try:
        check_exponents(np.asarray(exponents, dtype=np.float64).reshape(-1), positive=False, max_exponent=None,
                        nonempty=False)
    except ExponentError as exc:
        s = lobe_similarity(*exc.values)
        raise ReflectmmError(
            f"{what}: {exc.values[0]:.10g} and {exc.values[1]:.10g} give numerically collinear lobes (similarity 1 − "
            f"{max(1.0 - s, 0.0):.1e}); their weights cannot be told apart — drop one or separate them further"
        ) from None


def _check_exponents(p, tm):
    """The shading functions' argument check of (K,) ``exponents`` (numpy or torch, already finite): the shape,
    then :func:`check_exponents`' positivity rule on the smallest exponent, as a ReflectmmError."""
    if p.ndim != 1 or p.shape[0] < 1:
        raise ReflectmmError(f"shading: argument 'exponents' must have shape (K,), got {tuple(p.shape)}")
    pmin = float((p.detach() if tm else p).min())
    try:
        check_exponents([pmin], max_exponent=None, distinct=False)
    except ExponentError:
        raise ReflectmmError(f"shading: argument 'exponents' must be > 0, got min {pmin}") from None


def shade_directional(albedo, weights, exponents, normal, light_dir, view_dir, irradiance, *,
                      return_parts: bool = False):
    """RGB shading of a directional light with the multi-lobe Blinn-Phong model.

    ``s = E · ( c/π · max(n·l, 0) + Σ_i w_i f_i max(n·h, 0)^p_i )`` with ``h = normalize(l + v)``,
    and ``s = 0`` wherever ``n·l ≤ 0`` or ``n·v ≤ 0``. The BRDF is never formed and divided by n·l, so grazing
    light stays finite; v = −l (zero half vector) gives 0 with finite gradients.

    Args:
        albedo: (..., 3) diffuse colour c (linear, ≥ 0 expected but not enforced).
        weights: (..., K) lobe weights w_i (white specular).
        exponents: (K,) lobe exponents p_i > 0 (default set: 1, 8, 64).
        normal: (..., 3) surface normal (normalised internally).
        light_dir: (..., 3) direction to the light (normalised internally).
        view_dir: (..., 3) direction to the viewer (normalised internally).
        irradiance: (..., 3) or scalar light irradiance E (RGB, at normal incidence).
        return_parts: also return the diffuse and specular parts separately.
    Returns:
        (..., 3) shading (or ``(total, diffuse, specular)``), broadcast over all leading shapes. numpy in →
        numpy out; any torch input → torch out (differentiable). float16 inputs are computed and returned in
        float32, float64 stays float64.
    Raises:
        ReflectmmError naming the argument on NaN/inf, wrong trailing shapes or non-positive exponents.
    """
    tm = any_torch(albedo, weights, exponents, normal, light_dir, view_dir, irradiance)
    dt = compute_dtype(albedo, weights, exponents, normal, light_dir, view_dir, irradiance, torch_mode=tm)
    dev = device_of(albedo, weights, exponents, normal, light_dir, view_dir, irradiance)
    c = as_array("albedo", albedo, torch_mode=tm, dtype=dt, device=dev)
    w = as_array("weights", weights, torch_mode=tm, dtype=dt, device=dev)
    p = as_array("exponents", exponents, torch_mode=tm, dtype=dt, device=dev)
    n = as_array("normal", normal, torch_mode=tm, dtype=dt, device=dev)
    lv = as_array("light_dir", light_dir, torch_mode=tm, dtype=dt, device=dev)
    v = as_array("view_dir", view_dir, torch_mode=tm, dtype=dt, device=dev)
    E = as_array("irradiance", irradiance, torch_mode=tm, dtype=dt, device=dev)
    for name, a, k in (("albedo", c, 3), ("normal", n, 3), ("light_dir", lv, 3), ("view_dir", v, 3)):
        check_last(name, a, k)
    _check_exponents(p, tm)
    check_last("weights", w, p.shape[0])
    if E.ndim > 0:
        check_last("irradiance", E, 3)
    broadcast_shapes(c.shape[:-1], w.shape[:-1], n.shape[:-1], lv.shape[:-1], v.shape[:-1],
                     E.shape[:-1] if E.ndim else ())

    n = safe_normalize(n, tm)
    lv = safe_normalize(lv, tm)
    v = safe_normalize(v, tm)
    h = safe_normalize(lv + v, tm)  # zero vector when v = −l; then n·l and n·v cannot both be > 0.
    ndl = (n * lv).sum(-1)
    ndv = (n * v).sum(-1)
    ndh = (n * h).sum(-1)
    f = blinn_phong_norm(p)
    if tm:
        import torch

        lit = (ndl > 0) & (ndv > 0)
        # Evaluate the power only where it is used; elsewhere use a harmless base of 1 (no inf/NaN gradients
        # for p < 1 at 0, no NaN from 0 * inf through torch.where).
        base = torch.where(lit, ndh, torch.ones_like(ndh)).clamp_min(1e-30)
        lobes = torch.pow(base.unsqueeze(-1), p) * (w * f)
        spec = torch.where(lit, lobes.sum(-1), torch.zeros_like(ndh))
        diff_cos = torch.where(lit, ndl, torch.zeros_like(ndl))
    else:
        lit = (ndl > 0) & (ndv > 0)
        # lights behind the surface (and hidden texels) cost no power evaluation
        shape = np.broadcast_shapes(ndh.shape + (p.shape[0],), w.shape)
        litk = np.broadcast_to(lit[..., None], shape)
        lobes = np.zeros(shape, dt)
        np.power(np.broadcast_to(ndh[..., None], shape), p, out=lobes, where=litk)
        lobes *= w * f.astype(dt)
        spec = lobes.sum(-1)
        diff_cos = np.where(lit, ndl, 0.0).astype(dt, copy=False)
    diffuse = E * (c * (1.0 / np.pi)) * diff_cos[..., None]
    specular = E * spec[..., None]
    if tm:
        import torch

        specular = specular.expand(torch.broadcast_shapes(specular.shape, diffuse.shape))
    else:
        specular = np.broadcast_to(specular, np.broadcast_shapes(specular.shape, diffuse.shape))
    total = diffuse + specular
    if return_parts:
        return total, diffuse, specular
    return total

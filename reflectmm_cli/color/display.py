"""Linear radiance → a display encoding: optional NaN/inf removal, exposure, clip to [0, 1], a transfer, and
optionally 8-bit codes. numpy or torch.

Transfers (:data:`TRANSFERS`):

* ``srgb``: the sRGB OETF (:func:`.linear_to_srgb`);
* ``gamma``: ``x^(1/2.2)``, or ``x^(1/gamma)`` for the ``gamma=`` given (:func:`.linear_to_gamma`);
* ``gamma1.2``: ``x^(1/1.2)``, the encoding of the Multi-PIE-style captures and synthetic wild images;
* ``linear``: the clipped values.

Exposure: ``None`` (no scaling), a number (multiplies), or ``"auto"`` (:func:`auto_exposure`: the 99.5th
percentile of the non-black pixels' largest channel maps to 0.9).
"""
from __future__ import annotations

import math

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading._array import is_torch

from ._backend import as_float, clip01, floor, nan_to_num as _nan_to_num
from .gamma import CAPTURE_GAMMA, PREVIEW_GAMMA, linear_to_gamma
from .srgb import linear_to_srgb

__all__ = ["encode_display", "auto_exposure", "to_uint8", "TRANSFERS"]

TRANSFERS = ("srgb", "gamma", "gamma1.2", "linear")


def auto_exposure(x) -> float:
    """The exposure that maps the 99.5th percentile of the non-black pixels' largest channel to 0.9.

    Args:
        x: (..., C) numpy array or torch tensor of linear values, finite.
    Returns:
        ``0.9 / p`` as a Python float; 0.9 (p taken as 1) if no pixel has a positive channel.
    """
    a = x.detach().cpu().numpy() if is_torch(x) else np.asarray(x)
    if a.ndim < 1:
        raise ReflectmmError(f"auto_exposure: expected an image (..., C), got shape {a.shape}")
    nz = a[a.max(-1) > 0]
    top = float(np.percentile(nz.max(-1), 99.5)) if nz.size else 1.0
    return 0.9 / top if top > 0 else 1.0


def to_uint8(y):
    """Display values in [0, 1] → 8-bit codes ``floor(255·y + 0.5)`` (round half up).

    Args:
        y: (*) numpy array or torch tensor in [0, 1] (not clipped here).
    Returns:
        (*) uint8 numpy array or torch tensor.
    """
    y = as_float("to_uint8", y)
    c = floor(y * 255 + 0.5)
    if is_torch(c):
        import torch

        return c.to(torch.uint8)
    return c.astype(np.uint8)


def encode_display(x, transfer: str = "srgb", exposure=None, *, gamma: float | None = None,
                   nan_to_num: bool = True, uint8: bool = False, dtype=None):
    """Linear radiance → display values in [0, 1] (or 8-bit codes).

    Steps, in this order: conversion to ``dtype`` if given; NaN → 0 and ±inf → the dtype's extremes
    (``nan_to_num=True``; with False NaN propagates); times ``exposure`` (module docstring); clip to [0, 1];
    the ``transfer``; :func:`to_uint8` if ``uint8``.

    Args:
        x: (*) numpy array or torch tensor of linear values; ``exposure="auto"`` needs (..., C).
        transfer: one of :data:`TRANSFERS`.
        exposure: None, a finite number ≥ 0, or ``"auto"``.
        gamma: only with ``transfer="gamma"``: the exponent's inverse (default 2.2).
        nan_to_num: replace NaN/inf before anything else.
        uint8: return ``floor(255·y + 0.5)`` as uint8 instead of floats.
        dtype: compute in this floating dtype (a numpy dtype for numpy input, a torch dtype for tensors);
            default: ``x``'s own.
    Returns:
        (*) same kind as ``x``; floating in ``dtype`` (default ``x``'s floating dtype, integer/bool input →
        float64 / torch's default dtype), or uint8.
    """
    if transfer not in TRANSFERS:
        raise ReflectmmError(f"unknown display transfer {transfer!r} (one of {', '.join(TRANSFERS)})")
    if gamma is not None and transfer != "gamma":
        raise ReflectmmError(f"encode_display: gamma= is only for transfer 'gamma', not {transfer!r}")
    if dtype is not None:
        x = x.to(dtype) if is_torch(x) else np.asarray(x, dtype)
    x = as_float("encode_display", x)
    if nan_to_num:
        x = _nan_to_num(x)
    if isinstance(exposure, str):
        if exposure != "auto":
            raise ReflectmmError(f"encode_display: exposure must be a number, None or 'auto', got {exposure!r}")
        exposure = auto_exposure(x)
    if exposure is not None:
        try:
            ok = math.isfinite(float(exposure)) and float(exposure) >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ReflectmmError(f"encode_display: exposure must be a finite number ≥ 0, got {exposure!r}")
        x = x * exposure
    x = clip01(x)
    if transfer == "srgb":
        y = linear_to_srgb(x)
    elif transfer == "gamma":
        y = linear_to_gamma(x, PREVIEW_GAMMA if gamma is None else gamma)
    elif transfer == "gamma1.2":
        y = linear_to_gamma(x, CAPTURE_GAMMA)
    else:
        y = x
    return to_uint8(y) if uint8 else y

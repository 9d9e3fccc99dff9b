"""numpy/torch dispatch shared by the colour transfers.

Every transfer takes a numpy array (or anything ``np.asarray`` accepts) or a torch tensor and returns the same
kind. Floating inputs keep their dtype (float16/32/64 in numpy; any floating tensor dtype); integer and bool
inputs are computed in float64 (numpy) or torch's default dtype. There is no finiteness check: NaN propagates
unless a function says otherwise.
"""
from __future__ import annotations

import math

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading._array import is_torch


def as_float(fn: str, x):
    """``x`` as a floating numpy array or torch tensor (module docstring); non-numeric → one-line error."""
    if is_torch(x):
        if x.is_floating_point():
            return x
        if x.is_complex():
            raise ReflectmmError(f"{fn}: expected a real image, got a tensor of dtype {x.dtype}")
        import torch

        return x.to(torch.get_default_dtype())
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:
        raise ReflectmmError(f"{fn}: expected a numeric array ({e})") from None
    if a.dtype.kind == "f":
        return a
    if a.dtype.kind in "biu":
        return a.astype(np.float64)
    raise ReflectmmError(f"{fn}: expected a real numeric array, got dtype {a.dtype}")


def positive(fn: str, name: str, v) -> None:
    """Reject a ``v`` that is not a finite number > 0 (the object itself is used unchanged by the caller)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ReflectmmError(f"{fn}: {name} must be a positive number, got {v!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ReflectmmError(f"{fn}: {name} must be a finite number > 0, got {v!r}")


def where(c, a, b):
    if is_torch(c):
        import torch

        return torch.where(c, a, b)
    return np.where(c, a, b)


def maximum(x, v: float):
    return x.clamp_min(v) if is_torch(x) else np.maximum(x, v)


def clip01(x):
    return x.clamp(0.0, 1.0) if is_torch(x) else np.clip(x, 0.0, 1.0)


def nan_to_num(x):
    return x.nan_to_num() if is_torch(x) else np.nan_to_num(x)


def floor(x):
    return x.floor() if is_torch(x) else np.floor(x)

"""Small numpy/torch dispatch helpers shared by the shading kernels.

Every public kernel accepts either numpy arrays or torch tensors. If any array argument is a torch tensor the
computation runs in torch (differentiable, on that tensor's device); otherwise it runs in numpy. Torch is imported
lazily so the numpy path never pays for it.
"""
from __future__ import annotations

import numpy as np

from reflectmm_cli.errors import ReflectmmError


def is_torch(x) -> bool:
    return type(x).__module__.split(".")[0] == "torch"


def any_torch(*xs) -> bool:
    return any(is_torch(x) for x in xs)


def _torch():
    import torch

    return torch


def compute_dtype(*xs, torch_mode: bool):
    """Floating dtype used for the computation: the widest floating input, but at least float32.

    float16/bfloat16 inputs are upcast (cos^1000 underflows in half precision); the result stays in that dtype.
    """
    if torch_mode:
        torch = _torch()
        dt = torch.float32
        for x in xs:
            if is_torch(x) and x.dtype == torch.float64:
                dt = torch.float64
            elif isinstance(x, np.ndarray) and x.dtype == np.float64:
                dt = torch.float64
        return dt
    dt = np.float32
    for x in xs:
        if isinstance(x, np.ndarray) and x.dtype == np.float64:
            dt = np.float64
    return dt


def as_array(name: str, x, *, torch_mode: bool, dtype, device=None, check_finite: bool = True):
    """Convert ``x`` to a floating array of the compute dtype and reject NaN/inf naming the argument."""
    if x is None:
        raise ReflectmmError(f"shading: argument '{name}' is required")
    if torch_mode:
        torch = _torch()
        if is_torch(x):
            t = x.to(dtype=dtype)
            if device is not None and t.device != device:
                t = t.to(device)
        else:
            try:
                t = torch.as_tensor(np.asarray(x), dtype=dtype, device=device)
            except (TypeError, ValueError) as e:
                raise ReflectmmError(f"shading: argument '{name}' is not numeric ({e})") from None
        if check_finite and t.numel() and not bool(torch.isfinite(t.detach()).all()):
            raise ReflectmmError(f"shading: argument '{name}' contains NaN or inf (shape {tuple(t.shape)})")
        return t
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:  # pragma: no cover - exotic input
        raise ReflectmmError(f"shading: argument '{name}' is not numeric ({e})") from None
    if a.dtype.kind not in "biuf":
        raise ReflectmmError(f"shading: argument '{name}' must be numeric, got dtype {a.dtype}")
    a = a.astype(dtype, copy=False)
    if check_finite and a.size and not np.isfinite(a).all():
        raise ReflectmmError(f"shading: argument '{name}' contains NaN or inf (shape {a.shape})")
    return a


def check_last(name: str, x, n: int):
    if x.ndim < 1 or x.shape[-1] != n:
        raise ReflectmmError(f"shading: argument '{name}' must have shape (..., {n}), got {tuple(x.shape)}")


def device_of(*xs):
    for x in xs:
        if is_torch(x):
            return x.device
    return None


def stack(xs, axis, torch_mode):
    if torch_mode:
        return _torch().stack(xs, dim=axis)
    return np.stack(xs, axis=axis)


def sqrt(x, torch_mode):
    return _torch().sqrt(x) if torch_mode else np.sqrt(x)


def clamp_min(x, v, torch_mode):
    return x.clamp_min(v) if torch_mode else np.maximum(x, v)


def safe_normalize(v, torch_mode, eps2=1e-30):
    """Normalise the last axis; zero-length vectors stay (near) zero with finite gradients."""
    n2 = (v * v).sum(-1, keepdims=True) if not torch_mode else (v * v).sum(-1, keepdim=True)
    inv = 1.0 / sqrt(clamp_min(n2, eps2, torch_mode), torch_mode)
    return v * inv


def broadcast_shapes(*shapes):
    try:
        return tuple(np.broadcast_shapes(*shapes))
    except ValueError:
        raise ReflectmmError(
            "shading: leading shapes do not broadcast: " + ", ".join(str(tuple(s)) for s in shapes)
        ) from None

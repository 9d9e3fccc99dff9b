"""Turning evaluation results into artifact arrays and JSON documents (for the evaluate stages).

The library functions return nested dicts holding floats, numpy arrays and :class:`.face_metrics.FaceMetrics`.
:func:`to_document` makes them JSON-able (arrays → lists, FaceMetrics → its ``to_dict`` plus the per-image
values); :func:`flatten_numbers` gives the ``{"a.b.c": float}`` view an ``evaluation`` artifact stores as
``names`` / ``values`` (:func:`evaluation_arrays`), arrays of per-image values as ``name[i]``.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .face_metrics import FaceMetrics

__all__ = ["to_document", "flatten_numbers", "evaluation_arrays"]


def to_document(obj: Any) -> Any:
    """JSON-able copy: dicts/lists recursively, numpy scalars → float/int, arrays → lists, non-finite floats →
    None, FaceMetrics → ``{..., "per_image": {...}}``."""
    if isinstance(obj, FaceMetrics):
        d = obj.to_dict()
        d["per_image"] = {k: v for k, v in obj.per_image.items()}
        return to_document(d)
    if isinstance(obj, dict):
        return {str(k): to_document(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_document(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_document(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def flatten_numbers(obj: Any, prefix: str = "") -> dict[str, float]:
    """``{"summary.psnr.mean": 31.2, "per_image.psnr[0]": 30.9, ...}``: every number of a nested result
    (bools and strings skipped; non-finite values kept as nan/inf)."""
    out: dict[str, float] = {}

    def rec(p: str, o: Any) -> None:
        if isinstance(o, FaceMetrics):
            rec(p, {"summary": o.summary, "per_image": o.per_image})
        elif isinstance(o, dict):
            for k, v in o.items():
                rec(f"{p}.{k}" if p else str(k), v)
        elif isinstance(o, np.ndarray) and o.dtype.kind in "fiu":
            for i, v in enumerate(o.reshape(-1)):
                out[f"{p}[{i}]"] = float(v)
        elif isinstance(o, (list, tuple)):
            for i, v in enumerate(o):
                rec(f"{p}[{i}]", v)
        elif isinstance(o, (bool, np.bool_)):
            return
        elif isinstance(o, (int, float, np.integer, np.floating)):
            out[p] = float(o)

    rec(prefix, obj)
    return out


def evaluation_arrays(obj: Any) -> dict[str, np.ndarray]:
    """``{"names": (n,) str sorted, "values": (n,) float64}`` of :func:`flatten_numbers` — the arrays of an
    ``evaluation`` artifact."""
    flat = flatten_numbers(obj)
    names = sorted(flat)
    return {"names": np.array(names, dtype=str), "values": np.array([flat[n] for n in names], np.float64)}

"""Shared by the evaluate-* stages: the ``evaluation`` artifact kind and flattening of error documents."""

from __future__ import annotations

import numpy as np

EVAL_KIND = "evaluation"


def flatten(prefix: str, obj, out: dict) -> dict:
    """Nested dict of numbers → ``{"a.b.c": float}`` (non-numbers left out)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(obj, (int, float, np.floating, np.integer)):
        out[prefix] = float(obj)
    return out

"""Pure power-law ("gamma") transfers, numpy or torch.

* :func:`linear_to_gamma`: ``x^(1/gamma)`` (encoding; gamma 2.2 for previews, 1.2 for the Multi-PIE-style
  captures and the synthetic wild images).
* :func:`gamma_to_linear`: ``v^gamma`` (decoding).

Neither clips: negative input gives NaN (numpy) as ``**`` does, so callers clip first.
"""
from __future__ import annotations

from ._backend import as_float, positive

__all__ = ["linear_to_gamma", "gamma_to_linear", "PREVIEW_GAMMA", "CAPTURE_GAMMA"]

#: The gamma of display previews (``to_display(transfer='gamma')``, tone-mapped thumbnails).
PREVIEW_GAMMA = 2.2
#: The gamma the Multi-PIE-style 8-bit images are stored in (the paper's): stored = linear^(1/1.2).
CAPTURE_GAMMA = 1.2


def linear_to_gamma(x, gamma: float = PREVIEW_GAMMA):
    """Linear values → ``x ** (1 / gamma)``.

    Args:
        x: (*) numpy array or torch tensor, ≥ 0.
        gamma: finite > 0. The exponent is ``1.0 / gamma`` evaluated on the object given (a numpy scalar
            keeps numpy's promotion rules).
    Returns:
        (*) same kind and floating dtype as ``x`` (integer/bool input → float64 / torch's default dtype).
    """
    positive("linear_to_gamma", "gamma", gamma)
    return as_float("linear_to_gamma", x) ** (1.0 / gamma)


def gamma_to_linear(v, gamma: float = PREVIEW_GAMMA):
    """Encoded values → ``v ** gamma``.

    Args:
        v: (*) numpy array or torch tensor, ≥ 0.
        gamma: finite > 0.
    Returns:
        (*) same kind and floating dtype as ``v``.
    """
    positive("gamma_to_linear", "gamma", gamma)
    return as_float("gamma_to_linear", v) ** gamma

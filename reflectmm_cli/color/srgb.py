"""The sRGB transfer (IEC 61966-2-1): linear ↔ sRGB-encoded values, numpy or torch.

* :func:`linear_to_srgb` (the OETF / "encoding"): ``12.92·x`` for ``x ≤ 0.0031308``, else
  ``1.055·x^(1/2.4) − 0.055``.
* :func:`srgb_to_linear` (the EOTF / "decoding"): ``v / 12.92`` for ``v ≤ threshold``, else
  ``((v + 0.055) / 1.055)^2.4``. ``threshold`` is the standard's printed 0.04045 by default;
  :data:`SRGB_DECODE_KNEE_EXACT` (= 12.92 · 0.0031308 = 0.040449936, the encoding of the linear knee) is the one
  colour-science uses and what ``capture``'s ``srgb`` transfer has always decoded with. The two differ only for
  inputs in (0.040449936, 0.04045], by < 3e−9.

Neither clips: values in [0, 1] map to [0, 1]; below the knee the linear segment continues (negative in,
negative out), above 1 the power segment does. The power is taken of ``max(x, knee)`` so that torch gradients
are finite everywhere (the linear branch is selected below the knee anyway; the result is unchanged).
"""
from __future__ import annotations

from reflectmm_cli.errors import ReflectmmError

from ._backend import as_float, maximum, where

__all__ = ["linear_to_srgb", "srgb_to_linear", "SRGB_LINEAR_KNEE", "SRGB_DECODE_KNEE",
           "SRGB_DECODE_KNEE_EXACT"]

#: Linear value below which the sRGB OETF is the straight line 12.92·x.
SRGB_LINEAR_KNEE = 0.0031308
#: Encoded value below which the sRGB EOTF is v / 12.92, as printed in IEC 61966-2-1.
SRGB_DECODE_KNEE = 0.04045
#: The encoding of :data:`SRGB_LINEAR_KNEE` (12.92 · 0.0031308), the EOTF knee colour-science uses.
SRGB_DECODE_KNEE_EXACT = 12.92 * 0.0031308


def linear_to_srgb(x):
    """Linear values → sRGB-encoded values (the OETF).

    Args:
        x: (*) numpy array or torch tensor of linear values (usually in [0, 1]; not clipped here).
    Returns:
        (*) the encoded values, same kind and floating dtype as ``x`` (integer/bool input → float64 /
        torch's default dtype).
    """
    x = as_float("linear_to_srgb", x)
    return where(x <= SRGB_LINEAR_KNEE, 12.92 * x, 1.055 * maximum(x, SRGB_LINEAR_KNEE) ** (1 / 2.4) - 0.055)


def srgb_to_linear(v, *, threshold: float = SRGB_DECODE_KNEE):
    """sRGB-encoded values → linear values (the EOTF).

    Args:
        v: (*) numpy array or torch tensor of encoded values (usually in [0, 1]; not clipped here).
        threshold: the encoded knee, :data:`SRGB_DECODE_KNEE` (0.04045) or :data:`SRGB_DECODE_KNEE_EXACT`.
    Returns:
        (*) linear values, same kind and floating dtype as ``v``.
    """
    v = as_float("srgb_to_linear", v)
    if not isinstance(threshold, float) or not 0.04 < threshold < 0.041:
        raise ReflectmmError(f"srgb_to_linear: threshold must be a float near 0.04045, got {threshold!r}")
    return where(v <= threshold, v / 12.92, ((maximum(v, threshold) + 0.055) / 1.055) ** 2.4)

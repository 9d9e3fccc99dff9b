"""Colour transfers, one family per module (numpy arrays and torch tensors alike):

* :mod:`.srgb`: :func:`linear_to_srgb`, :func:`srgb_to_linear` (IEC 61966-2-1);
* :mod:`.gamma`: :func:`linear_to_gamma`, :func:`gamma_to_linear` (pure power laws);
* :mod:`.display`: :func:`encode_display` (exposure, clip, transfer, 8-bit codes), :func:`auto_exposure`,
  :func:`to_uint8`.

Every display/sRGB/gamma conversion in the package goes through these functions.
"""
from .display import TRANSFERS, auto_exposure, encode_display, to_uint8
from .gamma import CAPTURE_GAMMA, PREVIEW_GAMMA, gamma_to_linear, linear_to_gamma
from .srgb import SRGB_DECODE_KNEE, SRGB_DECODE_KNEE_EXACT, SRGB_LINEAR_KNEE, linear_to_srgb, srgb_to_linear

__all__ = ["linear_to_srgb", "srgb_to_linear", "linear_to_gamma", "gamma_to_linear", "encode_display",
           "auto_exposure", "to_uint8", "TRANSFERS", "SRGB_LINEAR_KNEE", "SRGB_DECODE_KNEE",
           "SRGB_DECODE_KNEE_EXACT", "PREVIEW_GAMMA", "CAPTURE_GAMMA"]

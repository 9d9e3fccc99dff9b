"""Transfer functions: encoded pixel values in [0, 1] → linear radiance (docs/capture.md).

* ``gamma1.2`` (default, the paper's): ``x ** 1.2``.  The synthetic world writes ``clip(lin, 0, 1) ** (1/1.2)``.
* ``srgb``: the IEC 61966-2-1 sRGB EOTF (:func:`reflectmm_cli.color.srgb_to_linear` with the knee at
  12.92 · 0.0031308, as colour-science's ``cctf_decoding(x, 'sRGB')`` evaluates it).
* ``linear``: identity (RAW data, or already-linear 16-bit PNGs).
* ``gamma:G``: ``x ** G`` for any G > 0.

Integer images are decoded through a look-up table over every code value (256 or 65536 entries), so the cost
per pixel is one gather whatever the curve.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from reflectmm_cli.color import SRGB_DECODE_KNEE_EXACT, gamma_to_linear, srgb_to_linear
from reflectmm_cli.errors import ReflectmmError

TRANSFERS = ("gamma1.2", "srgb", "linear", "gamma:G")


@dataclass(frozen=True)
class Transfer:
    """A parsed transfer function: ``name`` (canonical) and ``gamma`` (None for sRGB)."""

    name: str
    gamma: float | None

    def decode(self, x: np.ndarray) -> np.ndarray:
        """Encoded values in [0, 1] (float) → linear values (float32)."""
        x = np.asarray(x, dtype=np.float64)
        if self.gamma is None:
            return srgb_to_linear(x, threshold=SRGB_DECODE_KNEE_EXACT).astype(np.float32)
        if self.gamma == 1.0:
            return x.astype(np.float32)
        return gamma_to_linear(np.clip(x, 0.0, None), self.gamma).astype(np.float32)

    def lut(self, bits: int) -> np.ndarray:
        """float32 table of ``decode(code / (2**bits − 1))`` for every integer code."""
        return _lut(self.name, self.gamma, bits)


@lru_cache(maxsize=16)
def _lut(name: str, gamma: float | None, bits: int) -> np.ndarray:
    n = (1 << bits)
    codes = np.arange(n, dtype=np.float64) / (n - 1)
    t = Transfer(name, gamma)
    table = t.decode(codes)
    table.setflags(write=False)
    return table


def parse_transfer(spec: str) -> Transfer:
    """``gamma1.2`` | ``srgb`` | ``linear`` | ``gamma:G`` (also ``gammaG``) → :class:`Transfer`."""
    s = str(spec).strip().lower()
    if s in ("srgb", "s-rgb"):
        return Transfer("srgb", None)
    if s in ("linear", "raw", "none"):
        return Transfer("linear", 1.0)
    g = None
    if s.startswith("gamma:"):
        g = s[6:]
    elif s.startswith("gamma"):
        g = s[5:]
    if g is not None:
        try:
            gv = float(g)
        except ValueError:
            gv = float("nan")
        if not np.isfinite(gv) or gv <= 0:
            raise ReflectmmError(f"--transfer {spec!r}: gamma must be a positive number (e.g. gamma:2.2)")
        if gv == 1.0:
            return Transfer("linear", 1.0)
        return Transfer(f"gamma:{gv:g}" if gv != 1.2 else "gamma1.2", gv)
    raise ReflectmmError(f"--transfer {spec!r}: expected one of gamma1.2, srgb, linear, gamma:G")


def check_transfer(spec: str) -> None:
    """A param's check: ValueError (``'gamma:0': gamma must be ...``) for a spec :func:`parse_transfer` refuses, so
    the value is refused with the other params, before any data is read."""
    try:
        parse_transfer(spec)
    except ReflectmmError as exc:
        raise ValueError(f"{spec!r}: {str(exc).split(': ', 1)[-1]}") from None

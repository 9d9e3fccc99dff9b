"""Lobe exponents: the default set, the bound, the collinearity of two lobes and the one exponent check of the
toolkit (:func:`check_exponents`).

The lowest module of :mod:`reflectmm_cli.shading` after ``_array``: :mod:`.sh` (the lobe's SH coefficients) and
:mod:`.brdf` (which re-exports everything here) both import it, so every guard calls the same check without an
import cycle.
"""
from __future__ import annotations

import math

__all__ = ["DEFAULT_EXPONENTS", "MAX_EXPONENT", "LOBE_RCOND_MIN", "lobe_similarity", "check_exponents",
           "ExponentError"]


#: The paper's three lobes: the one default set of Blinn-Phong exponents (fit, unwrap, simulate, synth).
DEFAULT_EXPONENTS = (1.0, 8.0, 64.0)

#: Largest accepted lobe exponent.  At p = 10⁴ the lobe cos^p θ_h is already 0.67° wide at half maximum
#: (θ ≈ √(2 ln 2 / p)), far below what a flash capture resolves (a UV texel at S = 256 spans about 1° of
#: normal), so larger p only add cost: the SH coefficients B_l of a lobe take time ∝ p (≈ 5 s at 10⁴, minutes
#: at 10⁵) and the sharper lobes flag every texel.
MAX_EXPONENT = 10000.0

#: Two lobes are refused as numerically collinear when the 2×2 Gram matrix of their unit-normalised
#: hemisphere profiles has reciprocal condition (1 − s)/(1 + s) below this (s = :func:`lobe_similarity`);
#: equal to fit-reflectance's default ``cond_min``, below which every texel would be flagged.
LOBE_RCOND_MIN = 1e-4


def lobe_similarity(p: float, q: float) -> float:
    """Cosine similarity of the lobes cos^p and cos^q over the hemisphere (closed form).

    ``⟨cos^p, cos^q⟩ = ∫ cos^(p+q) θ dω = 2π/(p+q+1)``, so
    ``s = √((2p+1)(2q+1)) / (p+q+1)`` ∈ (0, 1], with s = 1 iff p = q.
    """
    return math.sqrt((2 * p + 1) * (2 * q + 1)) / (p + q + 1)


def _collinear_pair(ps: list[float]) -> tuple[float, float] | None:
    """The first pair of exponents whose lobes are numerically collinear (:data:`LOBE_RCOND_MIN`), or None."""
    for i in range(len(ps)):
        for j in range(i + 1, len(ps)):
            s = lobe_similarity(ps[i], ps[j])
            if (1 - s) / (1 + s) < LOBE_RCOND_MIN:
                return ps[i], ps[j]
    return None


class ExponentError(ValueError):
    """A lobe-exponent set :func:`check_exponents` refused.  ``kind`` says which rule: ``"empty"``,
    ``"nonpositive"``, ``"too_large"`` or ``"collinear"``; ``values`` the offending exponent(s) (the pair for
    ``"collinear"``), so a caller can word its own one-line error."""

    def __init__(self, message: str, kind: str, values: tuple[float, ...] = ()):
        super().__init__(message)
        self.kind, self.values = kind, values


def check_exponents(exponents, *, positive: bool = True, max_exponent: float | None = MAX_EXPONENT,
                    distinct: bool = True, nonempty: bool = True) -> None:
    """Refuse a lobe-exponent set that no fit can use (raises :class:`ExponentError`, a ValueError, with one line
    saying why): the one exponent check of the toolkit.

    Every p must be finite and > 0, at most :data:`MAX_EXPONENT`, and no two lobes may be numerically collinear
    (:data:`LOBE_RCOND_MIN`): duplicates such as ``1,1,8`` or ``1,1.0000001,8`` would make every texel's
    design rank-deficient.  The parameter check of every stage that takes exponents; the library guards
    (:func:`check_distinct_exponents`, the shading functions' argument check) call it with only their rules
    switched on: ``positive`` (finite and > 0), ``max_exponent`` (None = no bound), ``distinct`` (no collinear
    pair), ``nonempty`` (at least one exponent).  Rules are applied exponent by exponent in order (positivity,
    then bound), then the collinearity of the first offending pair.
    """
    ps = [float(p) for p in exponents]
    if nonempty and not ps:
        raise ExponentError("no exponents", "empty")
    for p in ps:
        if positive and (not math.isfinite(p) or p <= 0):
            raise ExponentError(f"exponent {p:g} must be > 0", "nonpositive", (p,))
        if max_exponent is not None and p > max_exponent:
            raise ExponentError(f"exponent {p:g} is above the maximum {max_exponent:g} (a lobe that sharp is "
                                "narrower than a capture resolves)", "too_large", (p,))
    pair = _collinear_pair(ps) if distinct else None
    if pair is not None:
        what = "duplicate" if pair[0] == pair[1] else "near-duplicate"
        raise ExponentError(f"{what} exponents {pair[0]:.10g} and {pair[1]:.10g}: their lobes are numerically "
                            "collinear (give distinct exponents, e.g. 1,8,64)", "collinear", pair)

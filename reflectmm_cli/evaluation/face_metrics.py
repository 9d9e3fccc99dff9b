"""Face-region image metrics over a set of images: per-image PSNR / SSIM / LPIPS, their mean with a 95 %
confidence interval, and the released code's batch protocol (docs/design.md §8; docs/evaluation.md).

Two protocols, both on images in the display encoding (peak 1):

* **per image** (the project's protocol): for every image ``i`` the metrics of :mod:`.metrics` over its face mask
  (PSNR from the MSE over the masked pixels and channels; SSIM with the 11×11 Gaussian window averaged over the
  masked pixels after zeroing the background in both images; LPIPS averaged over the masked pixels of the spatial
  map), then the mean over images with a confidence interval — a Student-t interval
  ``mean ± t_{n−1, (1+level)/2} · s/√n`` (``s`` with ddof = 1), or a percentile bootstrap of the mean.
  A PSNR of identical images (∞) is capped at :data:`PSNR_CAP` dB so that the mean stays finite.
* **released** (yxuhan/ReflectanceMM's evaluation, for comparability with the paper's numbers): per batch of
  ``batch_size`` images, prediction ``max(linear, 1e−6)^(1/1.2)`` (no upper clip) and target both multiplied by
  the face mask (background zeroed); PSNR = ``10 log10(1 / MSE)`` with ONE MSE over the whole batch tensor
  (all pixels including the zeroed background, all channels); SSIM = the mean over the whole batch tensor of the
  SSIM map with a 3×3 Gaussian window (σ = 1.5, normalised), reflect-padded borders ("same" size), population
  (weighted) variances, C1 = (0.01)², C2 = (0.03)²; LPIPS = the network's image-mean distance (not masked) of the
  zeroed images, averaged over the batch. The reported numbers are the means of the per-batch values.

Arrays: ``preds``/``targets`` (N,H,W,3) float (or sequences of (H,W,3)), ``masks`` (N,H,W) bool.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from reflectmm_cli.color import linear_to_gamma
from reflectmm_cli.errors import ReflectmmError

from .lpips import lpips_image_mean
from .metrics import LPIPS, psnr, ssim

__all__ = ["PSNR_CAP", "mean_ci", "image_metrics", "FaceMetrics", "face_region_metrics", "ssim_window_map",
           "released_protocol", "RELEASED_GAMMA", "format_ci"]

#: PSNR of identical images (∞) enters means as this many dB.
PSNR_CAP = 100.0
#: display encoding of the released code (``hdr_to_ldr``: x^(1/1.2)).
RELEASED_GAMMA = 1.2


# --------------------------------------------------------------------------- confidence intervals

def mean_ci(values, level: float = 0.95, method: str = "t", n_boot: int = 4000, seed: int = 0) -> dict[str, Any]:
    """Mean of ``values`` (1-D, finite) with a two-sided confidence interval at ``level``.

    ``method="t"``: Student-t interval ``mean ± t · s/√n`` (s with ddof = 1); exact for normal data, asymptotically
    right otherwise. ``method="bootstrap"``: percentile bootstrap of the mean with ``n_boot`` resamples (seeded,
    deterministic). With one value the interval is (nan, nan).
    Returns ``{"mean", "lo", "hi", "half_width", "std", "n", "level", "method"}`` (floats / ints / str).
    """
    from scipy import stats

    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0:
        raise ReflectmmError("mean_ci: no values")
    if not np.all(np.isfinite(x)):
        raise ReflectmmError("mean_ci: values contain NaN or inf")
    if not 0 < level < 1:
        raise ReflectmmError(f"mean_ci: level must be in (0, 1), got {level}")
    n = int(x.size)
    m = float(x.mean())
    sd = float(x.std(ddof=1)) if n > 1 else float("nan")
    if n < 2:
        lo = hi = float("nan")
    elif method == "t":
        h = float(stats.t.ppf(0.5 + level / 2, n - 1)) * sd / math.sqrt(n)
        lo, hi = m - h, m + h
    elif method == "bootstrap":
        rng = np.random.default_rng(seed)
        idx = rng.integers(0, n, size=(int(n_boot), n))
        boots = x[idx].mean(1)
        lo, hi = (float(v) for v in np.quantile(boots, [0.5 - level / 2, 0.5 + level / 2]))
    else:
        raise ReflectmmError(f"mean_ci: method must be 't' or 'bootstrap', got {method!r}")
    return {"mean": m, "lo": lo, "hi": hi, "half_width": (hi - lo) / 2 if n > 1 else float("nan"), "std": sd,
            "n": n, "level": float(level), "method": method}


def format_ci(ci: dict[str, Any], digits: int = 2) -> str:
    """``"31.20 ± 0.35"`` (mean ± half width of the interval) or just the mean for one value."""
    if not np.isfinite(ci.get("half_width", float("nan"))):
        return f"{ci['mean']:.{digits}f}"
    return f"{ci['mean']:.{digits}f} ± {ci['half_width']:.{digits}f}"


# --------------------------------------------------------------------------- per image

def image_metrics(pred, target, mask, *, peak: float = 1.0, lpips: LPIPS | None = None) -> dict[str, float | None]:
    """PSNR (dB, capped at :data:`PSNR_CAP`), SSIM and LPIPS (None without a network) of one display-encoded
    (H,W,3) image pair over the (H,W) bool face ``mask`` (definitions in :mod:`.metrics`)."""
    p = psnr(pred, target, mask, peak=peak)
    return {"psnr": float(min(p, PSNR_CAP)), "ssim": float(ssim(pred, target, mask, peak=peak)),
            "lpips": None if lpips is None else float(lpips(pred, target, mask))}


@dataclass
class FaceMetrics:
    """Per-image metrics and their summaries. ``per_image[name]`` is (N,) float64 (absent for LPIPS when off);
    ``summary[name]`` a :func:`mean_ci` dict; ``lpips`` says ``"on (<net>)"`` or ``"off (no weights given)"``."""

    per_image: dict[str, np.ndarray]
    summary: dict[str, dict[str, Any]]
    lpips: str
    n_images: int
    level: float
    method: str
    extra: dict[str, Any] = field(default_factory=dict)

    def row(self, digits: int = 2) -> dict[str, str]:
        """Table cells: ``{"PSNR": "31.20 ± 0.35", "SSIM": ..., "LPIPS": ... | "off"}``."""
        out = {"PSNR": format_ci(self.summary["psnr"], digits), "SSIM": format_ci(self.summary["ssim"], 4)}
        out["LPIPS"] = format_ci(self.summary["lpips"], 4) if "lpips" in self.summary else "off"
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"n_images": self.n_images, "level": self.level, "method": self.method, "lpips": self.lpips,
                "summary": self.summary, **({"extra": self.extra} if self.extra else {})}


def _iter_images(preds, targets, masks):
    n = len(preds)
    if len(targets) != n or len(masks) != n:
        raise ReflectmmError(f"face metrics: {n} predictions, {len(targets)} targets and {len(masks)} masks "
                             "(one of each per image)")
    if n == 0:
        raise ReflectmmError("face metrics: no images")
    for i in range(n):
        yield i, preds[i], targets[i], masks[i]


def face_region_metrics(preds, targets, masks, *, peak: float = 1.0, lpips: LPIPS | None = None,
                        level: float = 0.95, method: str = "t", names: Sequence[str] | None = None,
                        progress_fn: Callable[[Iterable], Iterable] | None = None) -> FaceMetrics:
    """Per-image PSNR/SSIM(/LPIPS) over each face mask, then mean and CI over the images.

    Args:
        preds, targets: N display-encoded (H,W,3) images in [0, peak] (arrays (N,H,W,3) or sequences).
        masks: N (H,W) bool face regions (an empty mask is an error naming the image).
        lpips: an :class:`LPIPS` network with weights, or None (LPIPS is then "off").
        level, method: confidence level and ``"t"`` | ``"bootstrap"`` (:func:`mean_ci`).
        names: image ids for error messages.
    """
    cols: dict[str, list[float]] = {"psnr": [], "ssim": []}
    if lpips is not None:
        cols["lpips"] = []
    it = _iter_images(preds, targets, masks)
    if progress_fn is not None:
        it = progress_fn(it)
    for i, p, t, m in it:
        if not np.asarray(m, bool).any():
            who = names[i] if names is not None else f"#{i}"
            raise ReflectmmError(f"face metrics: image {who} has an empty face mask")
        r = image_metrics(p, t, m, peak=peak, lpips=lpips)
        for k in cols:
            cols[k].append(r[k])
    per = {k: np.asarray(v, np.float64) for k, v in cols.items()}
    summary = {k: mean_ci(v, level=level, method=method) for k, v in per.items()}
    return FaceMetrics(per, summary, f"on ({lpips.net})" if lpips is not None else "off (no weights given)",
                       len(per["psnr"]), level, method)


# --------------------------------------------------------------------------- released protocol

def _gauss1d(window: int, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(window, dtype=np.float64) - (window - 1) / 2.0
    g = np.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


def ssim_window_map(a, b, window: int = 3, sigma: float = 1.5, peak: float = 1.0) -> np.ndarray:
    """SSIM map (same shape as ``a``, (…,H,W,C) or (H,W)) with a separable ``window``×``window`` normalised
    Gaussian (σ = ``sigma``), borders reflect-padded (mirror without repeating the edge pixel), population
    (weighted) moments, C1 = (0.01·peak)², C2 = (0.03·peak)² — the released code's SSIM (window 3)."""
    from scipy.ndimage import correlate1d

    x = np.asarray(a, np.float64)
    y = np.asarray(b, np.float64)
    if x.shape != y.shape:
        raise ReflectmmError(f"ssim: shapes differ: {x.shape} vs {y.shape}")
    if window < 1 or window % 2 == 0:
        raise ReflectmmError(f"ssim: window must be odd and ≥ 1, got {window}")
    g = _gauss1d(window, sigma)
    hw = (-3, -2) if x.ndim >= 3 else (-2, -1)

    def blur(z):
        for ax in hw:
            z = correlate1d(z, g, axis=ax, mode="mirror")
        return z

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    num = (2 * mx * my + c1) * (2 * sxy + c2)
    den = (mx * mx + my * my + c1) * (sxx + syy + c2)
    return num / (den + 1e-12)


def released_protocol(preds_linear, targets_display, masks, *, batch_size: int = 32, lpips: LPIPS | None = None,
                      gamma: float = RELEASED_GAMMA, ssim_window: int = 3) -> dict[str, Any]:
    """The released code's evaluation (module docstring) over batches of ``batch_size`` consecutive images.

    Args:
        preds_linear: (N,H,W,3) LINEAR predicted radiance (encoded here as ``max(x, 1e−6)^(1/gamma)``).
        targets_display: (N,H,W,3) the input images as stored, in [0, 1] (display encoding).
        masks: (N,H,W) bool rendered-face masks.
    Returns:
        ``{"psnr", "ssim", "lpips" (float | None), "per_batch": {"psnr": [...], "ssim": [...], "lpips": [...]},
        "batch_size", "n_images", "face_fraction"}`` — psnr/ssim/lpips are means over batches.
    """
    P = np.asarray(preds_linear, np.float64)
    T = np.asarray(targets_display, np.float64)
    M = np.asarray(masks, bool)
    if P.ndim != 4 or P.shape[-1] != 3 or T.shape != P.shape or M.shape != P.shape[:3]:
        raise ReflectmmError(f"released protocol: expected preds/targets (N,H,W,3) and masks (N,H,W), got "
                             f"{P.shape}, {T.shape}, {M.shape}")
    if batch_size < 1:
        raise ReflectmmError(f"released protocol: batch_size must be ≥ 1, got {batch_size}")
    n = P.shape[0]
    per: dict[str, list[float]] = {"psnr": [], "ssim": [], "lpips": []}
    for s in range(0, n, batch_size):
        m = M[s:s + batch_size, ..., None].astype(np.float64)
        p = linear_to_gamma(np.maximum(P[s:s + batch_size], 1e-6), gamma) * m
        t = T[s:s + batch_size] * m
        mse = float(np.mean((p - t) ** 2))
        per["psnr"].append(float(min(10 * np.log10(1.0 / mse), PSNR_CAP)) if mse > 0 else PSNR_CAP)
        per["ssim"].append(float(ssim_window_map(p, t, window=ssim_window).mean()))
        if lpips is not None:
            per["lpips"].append(float(np.mean([lpips_image_mean(lpips, p[i], t[i]) for i in range(p.shape[0])])))
    return {"psnr": float(np.mean(per["psnr"])), "ssim": float(np.mean(per["ssim"])),
            "lpips": float(np.mean(per["lpips"])) if per["lpips"] else None,
            "per_batch": {k: v for k, v in per.items() if v}, "batch_size": int(batch_size), "n_images": int(n),
            "face_fraction": float(M.mean()), "lpips_status": ("off (no weights given)" if lpips is None
                                                                else f"on ({lpips.net})")}

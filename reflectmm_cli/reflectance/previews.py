"""PNG previews of reflectance maps (display only; the data are in the NPZ/EXR artifacts)."""

from __future__ import annotations

import numpy as np

from reflectmm_cli.color import encode_display

__all__ = ["albedo_preview", "weights_preview", "residual_preview", "flagged_preview",
           "normal_correction_preview"]


def albedo_preview(albedo: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(S,S,3) sRGB image of the (3,S,S) linear diffuse albedo (black outside the mask)."""
    img = encode_display(np.moveaxis(albedo, 0, -1), "srgb", dtype=np.float64)
    if mask is not None:
        img = img * mask[..., None]
    return img


def weights_preview(weights: np.ndarray, mask: np.ndarray | None = None, gain: float = 3.0) -> np.ndarray:
    """(S, K·S + 2(K−1), 3) grey panels of the lobe weights × ``gain`` (×3 as in the paper's figures)."""
    K, S, _ = weights.shape
    gap = np.ones((S, 2))
    panels = []
    for k in range(K):
        w = np.clip(weights[k] * gain, 0.0, 1.0)
        if mask is not None:
            w = w * mask
        panels.append(w)
        if k < K - 1:
            panels.append(gap)
    grey = np.concatenate(panels, axis=1)
    return np.repeat(grey[..., None], 3, axis=-1)


def residual_preview(residual: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(S,S,3) turbo colour map of the residual scaled to its 99th percentile inside the mask."""
    import cv2

    m = np.ones(residual.shape, bool) if mask is None else mask
    vals = residual[m]
    top = float(np.percentile(vals, 99)) if vals.size else 1.0
    top = top if top > 0 else 1.0
    u8 = (np.clip(residual / top, 0, 1) * 255 + 0.5).astype(np.uint8)
    rgb = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO)[..., ::-1].astype(np.float64) / 255.0
    return rgb * m[..., None]


def flagged_preview(mask: np.ndarray, flagged: np.ndarray, observability: np.ndarray | None = None,
                    observable_min: float = 0.1) -> np.ndarray:
    """(S,S,3): grey = fitted and observable, blue = a lobe below ``observable_min`` (prior-dominated),
    red = flagged (ill-conditioned, filled), black = outside the mask."""
    img = np.zeros(mask.shape + (3,))
    img[mask] = 0.6
    if observability is not None:
        weak = mask & ~flagged & np.any(observability < observable_min, axis=0)
        img[weak] = (0.15, 0.35, 0.95)
    img[mask & flagged] = (0.95, 0.1, 0.1)
    return img


def normal_correction_preview(angle_deg: np.ndarray, mask: np.ndarray | None = None, top_deg: float = 10.0
                              ) -> np.ndarray:
    """(S,S,3) turbo colour map of the normal refinement's correction angle, 0 → ``top_deg`` degrees (clipped)."""
    import cv2

    m = np.ones(angle_deg.shape, bool) if mask is None else mask
    u8 = (np.clip(np.nan_to_num(angle_deg) / top_deg, 0, 1) * 255 + 0.5).astype(np.uint8)
    rgb = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO)[..., ::-1].astype(np.float64) / 255.0
    return rgb * m[..., None]

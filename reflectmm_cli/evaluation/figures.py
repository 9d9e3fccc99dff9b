"""Side-by-side comparison figures (numpy composition; written with ``reflectmm_cli.artifacts.write_png``).

A figure is a grid: one row per method (or image), columns = panels. The usual panels of Table 2 / Fig. 7 are
(:func:`method_panels`): input (display encoding), reconstruction (same encoding), diffuse layer, specular layer
(each encoded like the images; the specular layer ×``spec_gain``), and the error map ``|recon − input|`` (mean over
channels) through a perceptually ordered black → red → yellow → white ramp scaled so that ``err_max`` is white.
Panels are (H,W,3) floats in [0, 1]; pixels outside the face region show the input's background dimmed
(``background``), so the region is visible. No text is drawn: the column order is fixed and documented, and
the caller writes the row labels next to the figure (report table or a sidecar).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["error_colormap", "method_panels", "grid", "write_figure", "PANELS"]

#: column order of :func:`method_panels`
PANELS = ("input", "reconstruction", "diffuse", "specular", "error")


def error_colormap(err: np.ndarray, err_max: float) -> np.ndarray:
    """(H,W) non-negative error → (H,W,3) in [0, 1]: black → red → yellow → white at ``err_max``."""
    t = np.clip(np.nan_to_num(np.asarray(err, np.float64)) / max(float(err_max), 1e-12), 0.0, 1.0)
    r = np.clip(3 * t, 0, 1)
    g = np.clip(3 * t - 1, 0, 1)
    b = np.clip(3 * t - 2, 0, 1)
    return np.stack([r, g, b], -1)


def method_panels(input_display: np.ndarray, recon_display: np.ndarray, diffuse_display: np.ndarray | None,
                  specular_display: np.ndarray | None, mask: np.ndarray, *, err_max: float = 0.2,
                  spec_gain: float = 1.0, background: float = 0.35) -> list[np.ndarray]:
    """The five panels of one method (:data:`PANELS`); absent layers are black panels.

    All images (H,W,3) display-encoded in [0, 1]; ``mask`` (H,W) bool face region.
    """
    inp = np.clip(np.asarray(input_display, np.float64), 0, 1)
    if inp.ndim != 3 or inp.shape[2] != 3:
        raise ReflectmmError(f"figure: input must be (H,W,3), got {inp.shape}")
    m = np.asarray(mask, bool)[..., None]
    if m.shape[:2] != inp.shape[:2]:
        raise ReflectmmError(f"figure: mask {m.shape[:2]} does not match the image {inp.shape[:2]}")
    bg = inp * background

    def face(x, gain=1.0):
        if x is None:
            return np.zeros_like(inp)
        x = np.asarray(x, np.float64)
        if x.shape != inp.shape:
            raise ReflectmmError(f"figure: panel has shape {x.shape}, expected {inp.shape}")
        return np.where(m, np.clip(x * gain, 0, 1), bg)

    rec = face(recon_display)
    err = np.abs(np.asarray(recon_display, np.float64) - inp).mean(-1)
    emap = np.where(m, error_colormap(err, err_max), 0.0)
    return [inp, rec, face(diffuse_display), face(specular_display, spec_gain), emap]


def grid(rows: Sequence[Sequence[np.ndarray]], gap: int = 2, fill: float = 0.16) -> np.ndarray:
    """Rows of equally sized (H,W,3) panels → one (R·(H+gap)+gap, C·(W+gap)+gap, 3) image (short rows padded)."""
    if not rows or not rows[0]:
        raise ReflectmmError("figure: no panels")
    h, w = np.shape(rows[0][0])[:2]
    cols = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + gap) + gap, cols * (w + gap) + gap, 3), fill, np.float64)
    for i, r in enumerate(rows):
        for j, p in enumerate(r):
            p = np.asarray(p, np.float64)
            if p.shape[:2] != (h, w):
                raise ReflectmmError(f"figure: panel ({i},{j}) has size {p.shape[:2]}, expected {(h, w)}")
            y, x = gap + i * (h + gap), gap + j * (w + gap)
            out[y:y + h, x:x + w] = p if p.ndim == 3 else p[..., None]
    return out


def write_figure(path: str | Path, rows: Sequence[Sequence[np.ndarray]], gap: int = 2) -> Path:
    """:func:`grid` written as an 8-bit PNG (atomic)."""
    from reflectmm_cli.artifacts import write_png

    return write_png(path, grid(rows, gap))

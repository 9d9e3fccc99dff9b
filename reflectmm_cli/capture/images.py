"""Reading capture images: 8/16-bit PNG (OpenCV) and camera RAW (rawpy), landmark files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reflectmm_cli.capture.layout import RAW_EXTS
from reflectmm_cli.capture.transfer import Transfer
from reflectmm_cli.color import linear_to_gamma, linear_to_srgb
from reflectmm_cli.errors import ReflectmmError

#: Allowed per-camera rotations (degrees clockwise, applied right after reading).
ROTATIONS = (0, 90, 180, 270)


@dataclass
class Image:
    """A decoded image: ``linear (h, w, 3)`` float32, ``saturated (h, w)`` bool (any channel at the code max).

    ``size`` is the full frame ``(W, H)`` after rotation; ``linear``/``saturated`` cover the requested window.
    """

    linear: np.ndarray
    saturated: np.ndarray
    bits: int
    path: Path
    size: tuple[int, int] = (0, 0)


def _rotate(a: np.ndarray, rotate: int) -> np.ndarray:
    k = {0: 0, 90: 3, 180: 2, 270: 1}[rotate]  # np.rot90 turns counter-clockwise
    return np.ascontiguousarray(np.rot90(a, k, axes=(0, 1))) if k else a


def read_codes(path: str | Path) -> tuple[np.ndarray, int]:
    """Raw integer codes ``(H, W, 3)`` (RGB order) and bit depth of a PNG/TIFF (8 or 16 bit)."""
    import cv2

    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise ReflectmmError(f"cannot read image ({exc.strerror})", path) from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ReflectmmError("not a readable image (OpenCV cannot decode it)", path)
    if img.dtype == np.uint8:
        bits = 8
    elif img.dtype == np.uint16:
        bits = 16
    else:
        raise ReflectmmError(f"unsupported image sample type {img.dtype} (expected 8- or 16-bit)", path)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise ReflectmmError(f"unsupported channel count {img.shape[2]}", path)
    return img, bits


def read_raw(path: str | Path) -> tuple[np.ndarray, int]:
    """Demosaiced linear 16-bit RGB of a camera RAW file (camera white balance, no auto-brightening)."""
    import rawpy

    path = Path(path)
    try:
        with rawpy.imread(str(path)) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True)
    except Exception as exc:  # rawpy raises its own LibRawError hierarchy
        raise ReflectmmError(f"not a readable RAW image ({type(exc).__name__}: {exc})", path) from None
    return np.ascontiguousarray(rgb), 16


def read_image(path: str | Path, transfer: Transfer, rotate: int = 0,
               window: tuple[int, int, int, int] | None = None,
               expect_size: tuple[int, int] | None = None,
               expect_what: str = "the capture's first shot") -> Image:
    """Read one shot, mark saturated pixels and linearise it.

    ``window = (x0, y0, w, h)`` keeps only that part of the (rotated) frame; ``expect_size = (W, H)`` refuses a
    frame of another size (error naming the file and ``expect_what``, the shot that set the size).  RAW files are
    linear by construction: ``transfer`` is ignored for them (documented).
    """
    path = Path(path)
    if path.suffix.lower() in RAW_EXTS:
        codes, bits = read_raw(path)
        lut = Transfer("linear", 1.0).lut(bits)
    else:
        codes, bits = read_codes(path)
        lut = transfer.lut(bits)
    if rotate:
        codes = _rotate(codes, rotate)
    H, W = codes.shape[:2]
    if expect_size is not None and (W, H) != tuple(expect_size):
        raise ReflectmmError(f"image is {W}x{H}, but {expect_what} is {expect_size[0]}x{expect_size[1]}", path)
    if window is not None:
        x0, y0, w, h = window
        codes = codes[y0:y0 + h, x0:x0 + w]
    top = (1 << bits) - 1
    sat = np.maximum(np.maximum(codes[..., 0], codes[..., 1]), codes[..., 2]) == top
    return Image(lut[codes], sat, bits, path, (W, H))


def rotate_points(pts: np.ndarray, rotate: int, width: int, height: int) -> np.ndarray:
    """Pixel coordinates in an image of size (width, height) as stored on disk → coordinates in the image
    rotated clockwise by ``rotate`` degrees (as :func:`read_image` rotates it)."""
    x, y = pts[:, 0], pts[:, 1]
    if rotate == 0:
        return pts
    if rotate == 90:
        out = np.stack([height - 1 - y, x], 1)
    elif rotate == 180:
        out = np.stack([width - 1 - x, height - 1 - y], 1)
    else:
        out = np.stack([y, width - 1 - x], 1)
    return out.astype(np.float32)


def encode_linear(linear: np.ndarray, transfer: Transfer, bits: int = 8) -> np.ndarray:
    """Inverse of decoding: linear RGB → integer codes (clipped to [0, 1], rounded to nearest)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    enc = linear_to_srgb(x) if transfer.gamma is None else linear_to_gamma(x, transfer.gamma)
    top = (1 << bits) - 1
    return np.round(enc * top).astype(np.uint8 if bits == 8 else np.uint16)


def write_png(path: str | Path, codes: np.ndarray) -> Path:
    """Write RGB integer codes ``(H, W, 3)`` (uint8/uint16) as a PNG, creating folders (Multi-PIE writer helper)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(np.asarray(codes)[..., ::-1]))
    if not ok:  # pragma: no cover
        raise ReflectmmError("cannot encode PNG", path)
    path.write_bytes(buf.tobytes())
    return path


def check_finite_images(images: np.ndarray, name: str, view_names, path: str | Path | None = None,
                        flash_ids=None) -> np.ndarray:
    """Refuse a capture's image stack with NaN or infinite pixels; return ``images`` unchanged.

    Args:
        images: ``(V, h, w, 3)`` (``room``) or ``(V, F, h, w, 3)`` (``olat``) linear pixels.
        name: the array's name in the capture; view_names (V,) and flash_ids (F,) name where the first bad pixel is.
        path: the capture file, named in the one-line error.
    """
    a = np.asarray(images)
    if not np.issubdtype(a.dtype, np.floating):
        return images
    ok = np.isfinite(a)
    if ok.all():
        return images
    bad = np.argwhere(~ok)[0]
    where = f"view {view_names[bad[0]]}" if bad[0] < len(view_names) else "an image"
    if a.ndim == 5 and flash_ids is not None and bad[1] < len(flash_ids):
        where += f", flash {flash_ids[bad[1]]}"
    raise ReflectmmError(f"capture '{name}' has {int((~ok).sum())} NaN or infinite pixel value(s) (the first in "
                         f"{where}): a corrupt capture; run preprocess-multipie again", path)

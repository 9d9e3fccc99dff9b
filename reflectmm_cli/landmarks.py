"""68-point landmark files: the one reader and writer every stage uses.

Formats: iBUG ``.pts`` (``version: 1``, ``n_points: 68``, ``{ x y ... }``; the declared count is checked),
plain text (68 rows of ``x y``, commas allowed, ``#`` comments) and ``.npy`` (68×2).  Coordinates are
pixels with the centre of the top-left pixel at (0, 0) (docs/pipeline.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

N_LANDMARKS = 68

#: iBUG-68 groups (0-based, half-open ranges).
GROUPS: dict[str, tuple[int, int]] = {
    "jaw": (0, 17),
    "brows": (17, 27),
    "nose_bridge": (27, 31),
    "nose_base": (31, 36),
    "eyes": (36, 48),
    "mouth_outer": (48, 60),
    "mouth_inner": (60, 68),
}

#: The groups of points on the face's surface: every group but the jaw, whose points a detector puts on the
#: face's silhouette (which moves over the face with the view).
SURFACE_GROUPS: tuple[str, ...] = tuple(g for g in GROUPS if g != "jaw")


def group_mask(groups) -> np.ndarray:
    """(68,) bool: the landmarks of the named groups (:data:`GROUPS`)."""
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown:
        raise ReflectmmError(f"unknown landmark group(s) {unknown}; groups: {', '.join(GROUPS)}")
    m = np.zeros(N_LANDMARKS, bool)
    for g in groups:
        m[slice(*GROUPS[g])] = True
    return m


def inter_ocular(points) -> np.ndarray:
    """Distance between the two eye centres (the means of iBUG points 36–41 and 42–47) of each set of 68 points.

    Args:
        points: (..., 68, D) points: image pixels (D = 2) or model-space vertices (D = 3).
    Returns:
        (...) float64 distances, in the points' unit (NaN where an eye point is missing or both eyes are
        infinite).
    """
    p = np.asarray(points, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # inf − inf is the documented NaN, not a fault
        return np.linalg.norm(p[..., 36:42, :].mean(-2) - p[..., 42:48, :].mean(-2), axis=-1)


def _parse_pts(text: str) -> np.ndarray:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not any(ln.startswith("{") for ln in lines) or not any(ln.startswith("}") for ln in lines):
        raise ValueError("malformed .pts file (no { ... } block)")
    pts: list[list[float]] = []
    declared = None
    inside = False
    for ln in lines:
        low = ln.lower()
        if not inside and low.startswith("version"):
            continue
        if not inside and low.startswith("n_points"):
            head, sep, count = ln.partition(":")
            if not sep or not count.strip().isdigit():
                raise ValueError(f"malformed header line {ln!r} (expected 'n_points: N')")
            declared = int(count)
            continue
        if ln.startswith("{"):
            inside = True
            continue
        if ln.startswith("}"):
            inside = False
            continue
        if inside:
            vals = ln.replace(",", " ").split()
            if len(vals) != 2:
                raise ValueError(f"line {ln!r} does not hold two numbers")
            pts.append([float(vals[0]), float(vals[1])])
    if declared is not None and declared != len(pts):
        raise ValueError(f"header says n_points: {declared} but {len(pts)} points follow")
    return np.array(pts, dtype=np.float64).reshape(-1, 2)


def read_landmarks(path: str | Path, n: int = N_LANDMARKS) -> np.ndarray:
    """``(n, 2)`` float64 landmarks (x, y pixels) from a ``.pts``, text or ``.npy`` file.

    Raises ReflectmmError naming the file when it is missing, unparsable, has the wrong shape or count,
    or holds NaN/inf.
    """
    path = Path(path)
    if not path.is_file():
        raise ReflectmmError("landmark file not found", path)
    try:
        if path.suffix.lower() == ".npy":
            arr = np.load(path, allow_pickle=False)
        else:
            text = path.read_text()
            if path.suffix.lower() == ".pts" or "{" in text:
                arr = _parse_pts(text)
            else:
                rows = [ln.replace(",", " ").split() for ln in text.splitlines()]
                rows = [r for r in rows if r and not r[0].startswith("#")]
                arr = np.array([[float(v) for v in r] for r in rows], dtype=np.float64) if rows else np.zeros((0, 2))
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        raise ReflectmmError(f"cannot parse landmark file ({exc})", path) from None
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ReflectmmError(f"landmarks must be {n}×2, got shape {arr.shape}", path)
    if arr.shape[0] != n:
        raise ReflectmmError(f"expected {n} landmarks, found {arr.shape[0]}", path)
    if not np.isfinite(arr).all():
        raise ReflectmmError("landmarks contain NaN or inf", path)
    return arr


def check_in_frame(points: np.ndarray, width: int, height: int, path: str | Path | None = None,
                   slack: float = 0.5) -> np.ndarray:
    """Refuse landmarks far outside a ``width`` × ``height`` frame; return ``points`` unchanged.

    A point may lie a little outside (a jaw point beyond the image edge, estimated by the detector), but one
    more than ``slack`` × the frame size beyond an edge belongs to another image or is in other units
    (e.g. 1e6 px): a one-line ReflectmmError naming ``path``. NaN points (missing) are ignored.
    """
    pts = np.asarray(points, dtype=np.float64)
    lo = np.array([-slack * width, -slack * height])
    hi = np.array([(1 + slack) * width, (1 + slack) * height])
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(((pts < lo) | (pts > hi)).any(-1))
    if bad.size:
        i = int(bad[0])
        raise ReflectmmError(f"{bad.size} landmark(s) far outside the {width}x{height} frame (landmark {i + 1} at "
                             f"({pts[i, 0]:.6g}, {pts[i, 1]:.6g}) px); wrong image, size or units?", path)
    return points


#: A view's landmarks place it only from this many points on (a pose and a face need more than a handful).
MIN_VIEW_LANDMARKS = 6


def check_view_landmarks(points: np.ndarray, view: str, width: int, height: int,
                         path: str | Path | None = None) -> bool:
    """Whether a view's (68, 2) landmarks (NaN: missing) place it: False with none, True with at least
    :data:`MIN_VIEW_LANDMARKS`; a one-line ReflectmmError naming ``path`` and ``view`` for 1 to 5 points (a view
    is annotated or not) and for points far outside the ``width`` × ``height`` frame (:func:`check_in_frame`)."""
    pts = np.asarray(points, dtype=np.float64)
    n = int(np.isfinite(pts).all(-1).sum())
    if n == 0:
        return False
    if n < MIN_VIEW_LANDMARKS:
        raise ReflectmmError(f"view {view} has {n} landmark(s): at least {MIN_VIEW_LANDMARKS} are needed to place a "
                             "view; give them, or none (the view is then placed by the rig and the images)", path)
    try:
        check_in_frame(pts, width, height)
    except ReflectmmError as e:
        raise ReflectmmError(f"view {view}: {e}", path) from None
    return True


def format_pts(points: np.ndarray, decimals: int = 3) -> str:
    """iBUG ``.pts`` text for ``(n, 2)`` points."""
    pts = np.asarray(points, np.float64)
    body = "\n".join(f"{x:.{decimals}f} {y:.{decimals}f}" for x, y in pts)
    return f"version: 1\nn_points:  {len(pts)}\n{{\n{body}\n}}\n"


def write_pts(path: str | Path, points: np.ndarray, decimals: int = 4) -> Path:
    """Write ``(n, 2)`` points as an iBUG ``.pts`` file (atomically)."""
    from reflectmm_cli.artifacts import atomic_write_text

    return atomic_write_text(path, format_pts(points, decimals))

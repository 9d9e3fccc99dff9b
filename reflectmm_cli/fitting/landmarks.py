"""68-point landmark files and per-landmark weights.

File formats (docs/pipeline.md): iBUG ``.pts`` (``version: 1`` / ``n_points: 68`` / ``{`` 68 lines ``x y`` ``}``),
``.txt`` (68 rows of two numbers, whitespace or comma separated) and ``.npy`` ((68, 2)).  Coordinates are pixels
with the centre of the top-left pixel at (0, 0).  NaN marks a missing point.
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

#: Default weight per group.  Deep3DFaceRecon weights the nose bridge (28–30) and the inner mouth (last 8)
#: 20× and everything else 1×; we keep its ordering (inner face > jaw) with milder ratios, since on
#: Multi-PIE-like multi-view data the jaw line of the side views is the least reliable point set (a
#: silhouette, not a surface point) and 20× makes the fit follow a few points.
DEFAULT_GROUP_WEIGHTS: dict[str, float] = {
    "jaw": 0.5,
    "brows": 1.0,
    "nose_bridge": 2.0,
    "nose_base": 2.0,
    "eyes": 2.0,
    "mouth_outer": 2.0,
    "mouth_inner": 3.0,
}


def landmark_weights(group_weights: dict[str, float] | None = None) -> np.ndarray:
    """(68,) per-landmark weights from per-group weights (defaults :data:`DEFAULT_GROUP_WEIGHTS`)."""
    gw = dict(DEFAULT_GROUP_WEIGHTS)
    if group_weights:
        unknown = set(group_weights) - set(GROUPS)
        if unknown:
            raise ReflectmmError(f"unknown landmark group(s) {sorted(unknown)}; known: {sorted(GROUPS)}")
        gw.update(group_weights)
    w = np.zeros(N_LANDMARKS)
    for name, (a, b) in GROUPS.items():
        w[a:b] = gw[name]
    return w


def read_landmarks(path: str | Path) -> np.ndarray:
    """Read one landmark file (.pts, .txt, .npy) → (68, 2) float64; a clear error for a wrong count."""
    path = Path(path)
    if not path.is_file():
        raise ReflectmmError("landmark file not found", path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".pts":
            arr = _read_pts(path)
        else:
            text = path.read_text().replace(",", " ")
            rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
            arr = np.array([[float(v) for v in r] for r in rows], dtype=np.float64) if rows else np.zeros((0, 2))
    except (ValueError, OSError) as exc:
        raise ReflectmmError(f"cannot parse landmark file ({exc})", path) from None
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ReflectmmError(f"landmarks must be {N_LANDMARKS}×2, got shape {arr.shape}", path)
    if arr.shape[0] != N_LANDMARKS:
        raise ReflectmmError(f"expected {N_LANDMARKS} landmarks, found {arr.shape[0]}", path)
    return arr


def _read_pts(path: Path) -> np.ndarray:
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    pts: list[list[float]] = []
    declared = None
    inside = not any(ln.startswith("{") for ln in lines)
    for ln in lines:
        low = ln.lower()
        if low.startswith("version"):
            continue
        if low.startswith("n_points"):
            declared = int(ln.split(":", 1)[1])
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


def write_pts(path: str | Path, landmarks: np.ndarray) -> Path:
    """Write (68, 2) landmarks as an iBUG .pts file (used by tests and the synthetic world)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    body = "\n".join(f"{x:.4f} {y:.4f}" for x, y in lm)
    Path(path).write_text(f"version: 1\nn_points: {len(lm)}\n{{\n{body}\n}}\n")
    return Path(path)


def camera_code(view_name: str) -> str:
    """Multi-PIE camera folder name → file code: ``05_1`` → ``051``."""
    return view_name.replace("_", "")


def find_landmark_file(folder: str | Path, view_name: str) -> Path | None:
    """The landmark file of a view in ``folder``: ``<view>.{pts,txt,npy}`` or a Multi-PIE style
    ``*_<CCC>_00_lm.{pts,txt,npy}`` (searched recursively); None if there is none."""
    folder = Path(folder)
    for ext in (".pts", ".txt", ".npy"):
        p = folder / f"{view_name}{ext}"
        if p.is_file():
            return p
    code = camera_code(view_name)
    for ext in (".pts", ".txt", ".npy"):
        hits = sorted(folder.rglob(f"*_{code}_00_lm{ext}"))
        if len(hits) > 1:
            raise ReflectmmError(f"several landmark files for view {view_name}: "
                                 f"{', '.join(str(h) for h in hits[:4])}", folder)
        if hits:
            return hits[0]
    return None

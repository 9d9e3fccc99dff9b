"""68-point landmark files and per-landmark weights.

File formats (docs/pipeline.md): iBUG ``.pts`` (``version: 1`` / ``n_points: 68`` / ``{`` 68 lines ``x y`` ``}``),
``.txt`` (68 rows of two numbers, whitespace or comma separated) and ``.npy`` ((68, 2)).  Coordinates are pixels
with the centre of the top-left pixel at (0, 0).  NaN marks a missing point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.capture.layout import camera_code
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.landmarks import GROUPS, N_LANDMARKS, group_mask, write_pts  # noqa: F401  (re-exported)


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


def parse_group_weights(items) -> dict[str, float]:
    """``["jaw=0", "eyes=2,brows=0.5"]`` or a mapping → ``{group: weight}`` for :func:`landmark_weights`.

    Groups are those of :data:`GROUPS`; a weight is a finite number ≥ 0 (0 leaves the group out of the fit).
    Raises :class:`~reflectmm_cli.params.ParamError` (a recipe's error then names its file and stage)."""
    from reflectmm_cli.params import ParamError, parse_pairs

    out: dict[str, float] = {}
    for k, v in parse_pairs(items, "--landmark-weights",
                            f"GROUP=WEIGHT (e.g. jaw=0); groups: {', '.join(GROUPS)}"):
        if k not in GROUPS:
            raise ParamError(f"--landmark-weights {k}={v}: unknown group {k!r}; groups: {', '.join(GROUPS)}")
        try:
            w = float(v)
        except (TypeError, ValueError):
            w = float("nan")
        if not np.isfinite(w) or w < 0:
            raise ParamError(f"--landmark-weights {k}={v}: the weight must be a finite number ≥ 0; group {k} has {v}")
        if k in out:
            raise ParamError(f"--landmark-weights {k}={v}: group {k} is given twice ({k}={out[k]:g} before)")
        out[k] = w
    if out and not landmark_weights(out).any():
        raise ParamError(f"--landmark-weights {format_group_weights(out)}: every landmark has weight 0, so nothing "
                         "is left to fit; keep at least one group above 0")
    return out


def format_group_weights(group_weights: dict[str, float] | None) -> str:
    """``"jaw=0,eyes=1"``: the groups whose weight differs from :data:`DEFAULT_GROUP_WEIGHTS`, in :data:`GROUPS`
    order, as :func:`parse_group_weights` and ``--landmark-weights`` read them ("" for the defaults)."""
    gw = group_weights or {}
    return ",".join(f"{k}={float(gw[k]):g}" for k in GROUPS if k in gw and float(gw[k]) != DEFAULT_GROUP_WEIGHTS[k])


def find_landmark_file(folder: str | Path, view_name: str) -> Path | None:
    """The landmark file of a view in ``folder``: ``<view>.{pts,txt,npy}`` or a Multi-PIE style
    ``*_<CCC>_00_lm.{pts,txt,npy}`` (searched recursively); None if there is none."""
    folder = Path(folder)
    for ext in (".pts", ".txt", ".npy"):
        p = folder / f"{view_name}{ext}"
        if p.is_file():
            return p
    try:
        code = camera_code(view_name)
    except ReflectmmError:
        return None  # not a Multi-PIE camera name: no Multi-PIE style file names to look for
    for ext in (".pts", ".txt", ".npy"):
        hits = sorted(folder.rglob(f"*_{code}_00_lm{ext}"))
        if len(hits) > 1:
            raise ReflectmmError(f"several landmark files for view {view_name}: "
                                 f"{', '.join(str(h) for h in hits[:4])}", folder)
        if hits:
            return hits[0]
    return None

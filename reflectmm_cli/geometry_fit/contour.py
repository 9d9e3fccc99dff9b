"""Jaw landmarks that follow the face's outline (landmark marching).

A detector trained on 2-D annotations (dlib's 68 points, iBUG 300-W) puts the jaw points on the face's visible
outline: on a turned or differently shaped face they sit on the occluding contour of the cheek, not on fixed
points of the skin.  A fixed model vertex per jaw point then pulls the face toward the wrong width
(docs/fit-geometry.md, "Jaw points on the outline").

Here each side of the cheeks is cut into thin horizontal slices of the model's vertices.  In a view, each slice's
outermost vertex in the image (its extreme along the projected side axis) is on the outline: the extreme of a
surface slice's projection lies on the occluding contour (or on the mesh border) (:func:`outline`).  Each sliding
point takes the outline vertex nearest to it, and its residual is measured across the outline.  The fit alternates:
fit with the current vertices, slide them to the new outline, fit again (:func:`slide`).

The axes come from the model's own landmarks (eyes, chin, nose tip, jaw ends), so no model frame is assumed.
The lower jaw and chin (5–11) are left out: their outline is the jaw line above the neck, which is neither a fixed
vertex nor the outline of a mesh that goes on under the chin.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

#: iBUG-68 jaw points that slide: the cheek contour on both sides (0–4, 12–16).
SLIDING: tuple[int, ...] = tuple(range(0, 5)) + tuple(range(12, 17))
#: The lower jaw and chin (5–11): on a detector's image they follow the jaw line above the neck, which is neither
#: a fixed vertex nor the outline of a face mesh that goes on under the chin; the sliding fit leaves them out.
CHIN: tuple[int, ...] = tuple(range(5, 12))


@dataclass
class JawContour:
    """The contour lines of the jaw region, per side of the face.

    Attributes:
        points: (J,) landmark indices (of the 68) that slide; sides: (J,) 0 or 1, the side each belongs to.
        lines: per side, a list of vertex-id arrays: horizontal slices of the jaw region, top to bottom.
        outward: (2, 3) unit model-space direction in which each side's outline lies (∓ side axis).
    """

    points: np.ndarray
    sides: np.ndarray
    lines: list[list[np.ndarray]]
    outward: np.ndarray


def model_axes(mean: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit (side, up, front) axes of a face model from its landmark vertices: up from the chin (8) to the eye
    centres (36–47), side from the jaw end 0 to the jaw end 16, front perpendicular to both, toward the nose
    tip (30)."""
    p = np.asarray(mean, dtype=np.float64)[np.asarray(landmarks)]
    up = p[36:48].mean(0) - p[8]
    up /= np.linalg.norm(up)
    side = p[16] - p[0]
    side -= (side @ up) * up
    n = np.linalg.norm(side)
    if n < 1e-9 or not np.isfinite(n):
        raise ReflectmmError("face model: jaw landmarks 0 and 16 do not span a side axis")
    side /= n
    front = np.cross(side, up)
    if (p[30] - p[[0, 16]].mean(0)) @ front < 0:
        front = -front
    return side, up, front


def jaw_contour(mean: np.ndarray, triangles: np.ndarray, landmarks: np.ndarray, behind_mm: float = 70.0,
                above_mm: float = 30.0, band: float | None = None) -> JawContour:
    """Contour lines of a model (mean shape (N, 3), triangles (T, 3), landmarks (68,)).

    Each side of the face is cut into horizontal slices ``band`` thick (default 1.5× the median edge length, at
    least 1 mm) from the chin's height to ``above_mm`` above the higher jaw end (0 or 16).  A slice holds that
    side's vertices at most ``behind_mm`` behind the jaw end (toward the ear: far enough for the near side's
    outline of the ±30° views a frontal detector annotates, not so far that the lines reach under the jaw)."""
    mean = np.asarray(mean, dtype=np.float64)
    landmarks = np.asarray(landmarks, dtype=np.int64)
    side, up, front = model_axes(mean, landmarks)
    if band is None:
        tri = np.asarray(triangles, dtype=np.int64)
        e = np.linalg.norm(mean[tri[:, [1, 2, 0]]] - mean[tri], axis=-1)
        band = max(1.0, 1.5 * float(np.median(e)))
    centre = mean[landmarks[[0, 16]]].mean(0)
    rel = mean - centre
    s, u, f = rel @ side, rel @ up, rel @ front
    ends = landmarks[[0, 16]]
    heights = np.arange(u[ends].max() + above_mm, u[landmarks[8]] - band, -band)
    lines: list[list[np.ndarray]] = []
    for sign, end in ((-1.0, ends[0]), (1.0, ends[1])):
        half = (s * sign > 0) & (f >= f[end] - behind_mm)
        lines.append([ids for h in heights if len(ids := np.nonzero(half & (np.abs(u - h) <= band / 2))[0])])
    sides = np.array([0 if s[landmarks[k]] < 0 else 1 for k in SLIDING], dtype=np.int64)
    return JawContour(np.array(SLIDING, dtype=np.int64), sides, lines, np.array([-side, side]))


def outline(contour: JawContour, vertices: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
            ) -> list[np.ndarray]:
    """Per side, the vertex ids of the face's outline in one view: on each slice, the vertex whose projection lies
    furthest along the projected outward direction (the extreme of a surface slice's projection is on its
    occluding contour, or on the mesh border).

    Args:
        contour: from :func:`jaw_contour`; vertices: (N, 3) current model-space mesh;
        K, R: (3, 3); t: (3,) the view's intrinsics and pose (``x_cam = R X + t``).
    """
    X = np.asarray(vertices, dtype=np.float64)
    out = []
    for lines, o in zip(contour.lines, contour.outward):
        ids = []
        for line in lines:
            P = X[line] @ R.T + t
            ok = P[:, 2] > 1e-9
            if not ok.any():
                continue
            uv = P[:, :2] / np.where(ok, P[:, 2], 1.0)[:, None] @ K[:2, :2].T
            c = X[line].mean(0)  # the outward direction in the image at the slice
            pc, po = R @ c + t, R @ (c + o) + t
            d = (po[:2] / po[2] - pc[:2] / pc[2]) @ K[:2, :2].T
            ids.append(line[int(np.argmax(np.where(ok, uv @ d, -np.inf)))])
        out.append(np.array(ids, dtype=np.int64))
    return out


def slide(contour: JawContour, vertices: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
          observed: np.ndarray, fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sliding points' vertices in one view, the outline's image normals there and the points' distances
    across it.

    Each observed point takes the vertex of its side's :func:`outline` whose projection is nearest to it; the
    outline's unit normal in the image at that vertex (perpendicular to the chord between its neighbours) lets the
    fit measure the point's residual across the outline only, so the spacing of the contour lines along the
    outline does not pull the face.  A point not observed (NaN) keeps its ``fixed`` vertex and a zero normal.

    Args:
        contour: from :func:`jaw_contour`; vertices: (N, 3) current model-space mesh;
        K, R: (3, 3); t: (3,) the view's intrinsics and pose (``x_cam = R X + t``);
        observed: (J, 2) the detector's points (pixels) of ``contour.points``; fixed: (J,) their model vertices.

    Returns:
        (J,) vertex ids, (J, 2) unit image normals (zero where the point keeps its fixed vertex), (J,) each
        point's distance across the outline in pixels (NaN where it keeps its fixed vertex).
    """
    X = np.asarray(vertices, dtype=np.float64)
    sil = outline(contour, X, K, R, t)
    ids_out = np.asarray(fixed, dtype=np.int64).copy()
    normals = np.zeros((len(ids_out), 2))
    across = np.full(len(ids_out), np.nan)
    for m, side in enumerate(contour.sides):
        ids = sil[side]
        if not np.isfinite(observed[m]).all() or len(ids) < 2:
            continue
        P = X[ids] @ R.T + t
        uv = P[:, :2] / P[:, 2:3] @ K[:2, :2].T + K[:2, 2]
        j = int(np.argmin(((uv - observed[m]) ** 2).sum(-1)))
        chord = uv[min(j + 1, len(ids) - 1)] - uv[max(j - 1, 0)]
        n = np.array([-chord[1], chord[0]])
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        ids_out[m], normals[m] = ids[j], n / norm
        across[m] = abs((uv[j] - observed[m]) @ normals[m])
    return ids_out, normals, across

"""Where a landmark detector puts the 68 iBUG points on a face model: a static landmark embedding.

A face model names one vertex per iBUG landmark (``FaceModel.landmarks``). A detector has its own idea of each
point (where a corner of the eye is on a shaded face, how far the brow line runs), and the fit then pulls the face
until the model's vertices sit on the detector's points: a systematic offset of a few millimetres per point
becomes a wrong face size and wrong camera distances. Every 3DMM pipeline fixes the embedding for the detector it
uses; this module measures it from views whose geometry is known.

Each detected point of such a view (a fitted or true mesh in model space and the view's ``K, R, t``) is cast as a
ray through its pixel onto that mesh. The hit, as a triangle and barycentric coordinates, is carried to the
model's mean shape (the topology is shared), so every identity and view votes in one frame. Per landmark the
component-wise median of those places, snapped to the nearest mean-shape vertex, is the new landmark vertex.

The jaw points (0–16) of a detector follow the face's silhouette, not a surface point; a static embedding cannot
hold them, so by default they keep their vertices (fit them with ``--landmark-weights jaw=0``).

A static embedding is one place per point for every view, but a detector's idea of a point also turns with the
view: at 30° of yaw its eye corners and nose points sit a pixel or two from where they sit frontally, the same way
on every face. :func:`view_bias` measures that per camera — the mean over identities of each point's offset from
the projected landmark vertex, in units of the view's inter-ocular distance (so that it carries over between faces
of other sizes and rigs at other distances) — and :func:`apply_view_bias` takes it off a capture's points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.landmarks import GROUPS, N_LANDMARKS, SURFACE_GROUPS, group_mask, inter_ocular

__all__ = ["LandmarkEmbedding", "landmark_hits", "embed_landmarks", "DEFAULT_EMBED_GROUPS", "view_bias",
           "apply_view_bias", "correct_by_face_model"]

#: The groups that a static embedding can hold (every group but the jaw's silhouette points).
DEFAULT_EMBED_GROUPS: tuple[str, ...] = SURFACE_GROUPS


@dataclass
class LandmarkEmbedding:
    """The result of :func:`embed_landmarks` (68 entries each, iBUG order)."""

    indices: np.ndarray    # (68,) int32 landmark vertices: moved where ``embedded``, the old ones elsewhere
    embedded: np.ndarray   # (68,) bool: in a chosen group and placed by at least ``min_views`` views
    moved_mm: np.ndarray   # (68,) distance on the mean shape from the old vertex to the new one (0 where kept)
    spread_mm: np.ndarray  # (68,) median distance of the per-view places from their median (NaN: no view)
    views: np.ndarray      # (68,) int: views whose ray hit the mesh's front for this landmark

    def summary(self) -> dict:
        """Per group: landmarks moved, median move and spread (mm) — for reports and artifact metadata."""
        out = {}
        for name, (a, b) in GROUPS.items():
            e = self.embedded[a:b]
            out[name] = {"moved": int(e.sum()), "of": b - a,
                         "median_move_mm": float(np.median(self.moved_mm[a:b][e])) if e.any() else 0.0,
                         "median_spread_mm": float(np.nanmedian(self.spread_mm[a:b]))
                         if np.isfinite(self.spread_mm[a:b]).any() else float("nan"),
                         "median_views": float(np.median(self.views[a:b]))}
        return out


def landmark_hits(vertices: np.ndarray, triangles: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                  points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh point under each image point of one view.

    Args:
        vertices: (N, 3) the view's mesh in model space; triangles: (T, 3).
        K, R, t: the view's intrinsics and world-to-camera pose (``x_cam = R x + t``).
        points: (L, 2) pixel coordinates (pixel centres at integers), NaN for a missing point.
    Returns:
        ``tri (L,)`` int (−1: missing point, a miss, or the back of a triangle seen through a hole of the open
        mesh) and ``bary (L, 3)`` barycentric coordinates of the hit in that triangle.
    """
    from reflectmm_cli.geometry import RayScene

    pts = np.asarray(points, dtype=np.float64)
    L = pts.shape[0]
    ok = np.isfinite(pts).all(1)
    R = np.asarray(R, dtype=np.float64)
    d = np.c_[np.where(ok[:, None], pts, 0.0), np.ones(L)] @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = -R.T @ np.asarray(t, dtype=np.float64)
    V = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles)
    hit = RayScene(V, tris).intersect(np.broadcast_to(c, d.shape), d, retry=True)
    tri = np.where(ok, hit["tri"], -1).astype(np.int64)
    tv = V[tris[np.maximum(tri, 0)]]
    front = np.einsum("ij,ij->i", np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), d) < 0
    tri = np.where(front, tri, -1)
    u = np.asarray(hit["u"], dtype=np.float64)
    v = np.asarray(hit["v"], dtype=np.float64)
    bary = np.stack([1.0 - u - v, u, v], 1)
    return tri, np.where(tri[:, None] >= 0, bary, np.nan)


def embed_landmarks(mean_shape: np.ndarray, triangles: np.ndarray, landmarks: np.ndarray,
                    views: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], *,
                    groups: Sequence[str] = DEFAULT_EMBED_GROUPS, min_views: int = 3) -> LandmarkEmbedding:
    """The landmark vertices where a detector's points fall on the model (module docstring).

    Args:
        mean_shape: (N, 3) the model's mean shape; triangles: (T, 3); landmarks: (68,) its landmark vertices.
        views: ``(vertices (N, 3), K, R, t, points (68, 2))`` per view: that identity's mesh in model space, the
            view's camera and the detector's points in its full-frame pixels (NaN: missing).
        groups: the landmark groups to move (:data:`~reflectmm_cli.geometry_fit.landmarks.GROUPS`).
        min_views: a landmark placed by fewer views keeps its vertex.
    Raises:
        ReflectmmError: an unknown group, ``min_views`` < 1, or no view at all.
    """
    chosen = group_mask(groups)
    if min_views < 1:
        raise ReflectmmError(f"min_views must be ≥ 1, got {min_views}")
    mean = np.asarray(mean_shape, dtype=np.float64)
    tris = np.asarray(triangles)
    old = np.asarray(landmarks, dtype=np.int64).reshape(-1)
    if old.shape != (N_LANDMARKS,):
        raise ReflectmmError(f"the face model has {old.size} landmark vertices, expected {N_LANDMARKS}")
    places: list[np.ndarray] = []
    for verts, K, R, t, pts in views:
        if np.asarray(verts).shape != mean.shape:
            raise ReflectmmError(f"a view's mesh has {np.asarray(verts).shape[0]} vertices, the face model "
                                 f"{mean.shape[0]}")
        tri, bary = landmark_hits(verts, tris, K, R, t, pts)
        p = np.full((N_LANDMARKS, 3), np.nan)
        hit = tri >= 0
        p[hit] = np.einsum("lk,lkj->lj", bary[hit], mean[tris[tri[hit]]])
        places.append(p)
    if not places:
        raise ReflectmmError("no view with landmarks to embed them from")
    P = np.stack(places)                                         # (views, 68, 3)
    n = np.isfinite(P).all(-1).sum(0)
    embedded = chosen & (n >= min_views)
    new = old.copy()
    moved = np.zeros(N_LANDMARKS)
    spread = np.full(N_LANDMARKS, np.nan)
    for j in np.flatnonzero(n > 0):
        pj = P[:, j][np.isfinite(P[:, j]).all(-1)]
        med = np.median(pj, axis=0)
        spread[j] = float(np.median(np.linalg.norm(pj - med, axis=1)))
        if embedded[j]:
            new[j] = int(np.argmin(((mean - med) ** 2).sum(1)))
            moved[j] = float(np.linalg.norm(mean[new[j]] - mean[old[j]]))
    return LandmarkEmbedding(indices=new.astype(np.int32), embedded=embedded, moved_mm=moved, spread_mm=spread,
                             views=n.astype(np.int64))


def view_bias(indices: np.ndarray, views: Iterable[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                          np.ndarray]], *,
              groups: Sequence[str] = DEFAULT_EMBED_GROUPS) -> dict[str, dict]:
    """Per camera, the detector's mean offset from the projected landmark vertices (module docstring).

    Args:
        indices: (68,) the landmark vertices (the embedding's).
        views: ``(camera name, vertices (N, 3), K, R, t, points (68, 2))`` per view of known geometry, as
            :func:`embed_landmarks` takes them, with the camera's name.
        groups: the landmark groups that get an offset (others 0: the jaw's silhouette points have no fixed one).
    Returns:
        ``{camera: {"offset_iod": (68, 2) float64, "identities": n}}``: the mean over the n views of that camera of
        ``(points − π(vertices[indices])) / inter-ocular distance of the points``; a point that no view of the
        camera has, or outside ``groups``, gets 0. Views without both eyes are left out.
    """
    chosen = group_mask(groups)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    if idx.shape != (N_LANDMARKS,):
        raise ReflectmmError(f"view bias: {idx.size} landmark vertices, expected {N_LANDMARKS}")
    per: dict[str, list[np.ndarray]] = {}
    for name, verts, K, R, t, pts in views:
        pts = np.asarray(pts, dtype=np.float64)
        iod = float(inter_ocular(pts))
        if not np.isfinite(iod) or iod <= 0:
            continue
        proj = project(np.asarray(verts, dtype=np.float64)[idx], K, R, t)[0]
        per.setdefault(str(name), []).append((pts - proj) / iod)
    out = {}
    for name, offs in per.items():
        o = np.stack(offs)                                     # (n, 68, 2)
        seen = np.isfinite(o).all(-1)                          # (n, 68): a point no view has averages to 0
        mean = np.where(seen[..., None], o, 0.0).sum(0) / np.maximum(seen.sum(0), 1)[:, None]
        mean[~chosen] = 0.0
        out[name] = {"offset_iod": mean, "identities": len(offs)}
    return out


def apply_view_bias(landmarks: np.ndarray, camera_names: Sequence[str], bias: dict) -> tuple[np.ndarray, list[str]]:
    """A capture's detector points with each camera's :func:`view_bias` taken off.

    Args:
        landmarks: (..., C, 68, 2) points (NaN: missing), C the cameras ``camera_names``.
        bias: ``{camera: {"offset_iod": (68, 2) array-like, ...}}`` (a face model's ``info["landmark_view_bias"]
            ["cameras"]``).
    Returns:
        (corrected copy, names of the cameras corrected in at least one point set). A camera without an entry, and a
        point set without both eyes, are left as they are.
    """
    lm = np.array(landmarks, dtype=np.float64, copy=True)
    names = [str(n) for n in camera_names]
    if lm.ndim < 3 or lm.shape[-3:] != (len(names), N_LANDMARKS, 2):
        raise ReflectmmError(f"view bias: landmarks of shape {lm.shape} for {len(names)} cameras")
    done = []
    for k, name in enumerate(names):
        entry = bias.get(name)
        if entry is None:
            continue
        off = np.asarray(entry["offset_iod"], dtype=np.float64)
        if off.shape != (N_LANDMARKS, 2) or not np.isfinite(off).all():
            raise ReflectmmError(f"view bias of camera {name}: expected (68, 2) finite offsets, got {off.shape}")
        pts = lm[..., k, :, :]
        iod = inter_ocular(pts)
        ok = np.isfinite(iod) & (iod > 0)
        if ok.any():
            pts[ok] = pts[ok] - iod[ok][..., None, None] * off
            done.append(name)
    return lm, done


def correct_by_face_model(landmarks: np.ndarray, camera_names: Sequence[str], info: dict, path=None
                          ) -> tuple[np.ndarray, str | None]:
    """:func:`apply_view_bias` with a face model's own offsets (``info["landmark_view_bias"]``, written by
    ``face-model embed-landmarks``); the points unchanged and None when the model has none. Else the corrected points
    and one line saying which cameras were corrected and which had no offsets (left as they are).  Malformed
    offsets are a one-line error naming ``path`` (the face model's file)."""
    entry = (info or {}).get("landmark_view_bias")
    if not entry:
        return np.asarray(landmarks, dtype=np.float64), None
    cams = entry.get("cameras", {})
    try:
        lm, done = apply_view_bias(landmarks, camera_names, cams)
    except ReflectmmError as e:
        raise ReflectmmError(str(e), path) from None
    has = np.isfinite(np.asarray(landmarks, dtype=np.float64)).all(-1).any(-1)       # (..., C)
    has = has.reshape(-1, len(camera_names)).any(0)
    missing = [str(n) for n, h in zip(camera_names, has) if h and str(n) not in cams]
    note = ("detector points corrected by the face model's per-camera offsets (face-model embed-landmarks) in "
            f"camera(s) {', '.join(done) or 'none'}")
    if missing:
        note += f"; no offsets for camera(s) {', '.join(missing)}: their points as detected"
    return lm, note

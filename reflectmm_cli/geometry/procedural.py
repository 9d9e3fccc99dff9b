"""The built-in procedural face model (the toolkit's embedded default; docs/design.md §4).

Construction (all in mm, model space of docs/pipeline.md):

* A regular grid over a left-right symmetric UV square: column ``i`` ↔ azimuth θ ∈ [−θmax, θmax]
  (θmax = 100°, so the sides of the face are seen at grazing angles by 90° cameras), row ``j`` ↔ height
  Y from +110 mm (top of the forehead, v ≈ 0) to −90 mm (under the chin).
* A base "head front" surface ``(a(Y)·sin θ, Y, b(Y)·cos θ)``: half-width a ≈ 75 mm narrowing towards the jaw,
  depth b ≈ 92 mm receding at the top of the forehead and under the chin.
* A height field of anatomical features, displaced along the base normal: nose (bridge, tip, alae, nostril
  pits), brow ridge, eye sockets with eyeballs, cheeks, maxilla, lips with the mouth line, chin and temples.
  Every feature is a smooth bump with a few parameters (position, size, amplitude).
* Shape basis: the surface is a smooth function of ~30 anatomical parameters (face width/length/depth, nose
  length/width/height, jaw, cheek fullness, brow, eye spacing, lips, chin, forehead slope, ...).  Each
  parameter is perturbed by a plausible 1σ amount; the displacement fields, plus a few low-frequency random
  radial-basis deformations for the remaining variance, are turned into an orthonormal basis by an SVD, so
  ``shape_sigma`` are the singular values (mm) and coefficients ~ N(0, σ²) reproduce the joint variation.
* Expression basis: jaw open, smile (both and one-sided), lip pucker, lip press, brow raise (both and one
  side), frown, eye close, cheek puff, nose wrinkle, mouth left/right, sneer...; also orthonormalised by SVD.
* 68 landmarks in iBUG order: the grid vertex nearest (in the frontal X/Y plane, front-facing) to anatomical
  target points placed on the features above.
* Skin mask: everything except the eye openings and the nostril pits.
* UVs: ``u`` linear in θ, ``v`` linear in Y (v = 0 at the top), with a half-texel margin; column i and
  column n−1−i are mirror images, so the mirror map is exact.

Deterministic for a seed (the seed drives only the random low-frequency components of the bases).
"""
from __future__ import annotations

import math

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .face_model import FaceModel

__all__ = ["procedural_face_model", "DEFAULT_PARAMS", "face_surface", "grid_shape", "MIN_VERTICES"]

#: The fewest vertices a procedural face model can have (a 20 × 21 grid); the verbs' ``--face-vertices`` range
#: starts here.
MIN_VERTICES = 400

THETA_MAX = math.radians(100.0)
Y_TOP, Y_BOTTOM = 110.0, -90.0
UV_MARGIN = 0.004
FRONT_POWER = 0.7

#: Parameters of the mean face (mm unless stated).
DEFAULT_PARAMS: dict[str, float] = {
    "half_width": 74.0, "depth": 92.0, "height_scale": 1.0, "jaw_narrow": 36.0, "forehead_recede": 0.0045,
    "chin_recede": 0.004,
    "nose_tip_y": 2.0, "nose_bridge_y": 38.0, "nose_height": 24.0, "bridge_height": 9.0, "nose_width": 7.0,
    "alar_width": 13.5, "alar_height": 5.5, "nostril_depth": 5.0,
    "eye_x": 32.0, "eye_y": 33.0, "socket_depth": 11.0, "eyeball": 6.5,
    "brow_y": 49.0, "brow_height": 6.0, "glabella": 3.0,
    "cheek_x": 40.0, "cheek_y": 6.0, "cheek_height": 8.0, "cheekbone": 4.0,
    "maxilla": 9.0, "mouth_y": -30.0, "mouth_half_width": 24.0, "upper_lip": 5.0, "lower_lip": 5.5,
    "mouth_groove": 2.5, "chin_y": -62.0, "chin_height": 8.0, "sulcus": 3.0, "temple": 5.0,
}

#: Plausible 1σ perturbations of the anatomical parameters (mm or relative units).
#: Plausible 1σ changes of the *in-place* anatomical parameters (amplitudes and overall proportions): their
#: finite differences change the surface height without sliding features across the vertex grid.
SHAPE_SIGMA: dict[str, float] = {
    "half_width": 4.5, "depth": 4.0, "height_scale": 0.04, "jaw_narrow": 6.0, "forehead_recede": 0.0012,
    "chin_recede": 0.001,
    "nose_height": 2.2, "bridge_height": 1.5, "nose_width": 0.8, "alar_height": 1.0, "socket_depth": 1.5,
    "brow_height": 1.5, "glabella": 0.8, "cheek_height": 2.0, "cheekbone": 1.2, "maxilla": 1.8,
    "upper_lip": 0.8, "lower_lip": 0.8, "chin_height": 2.0, "sulcus": 0.8, "temple": 1.2,
}

#: Feature *positions* vary by moving the vertices themselves (in-plane warps), so a vertex keeps its anatomical
#: meaning across identities (landmarks stay on their features, UV maps stay registered): name → 1σ in mm.
WARP_SIGMA: dict[str, float] = {
    "eye_spacing": 1.5, "eye_height": 1.2, "brow_height": 1.5, "nose_length": 1.5, "alar_width": 1.0,
    "mouth_height": 1.2, "mouth_width": 1.8, "chin_height": 2.5, "cheek_height": 2.0,
}


def _g(x, s):
    return np.exp(-0.5 * (x / s) ** 2)


def _odd(X):
    """A smooth sign(X) (tanh over ±4 mm): left/right-moving fields stay continuous across the midline, so the
    columns next to the nose ridge never cross."""
    return np.tanh(X / 4.0)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def grid_shape(n_vertices: int) -> tuple[int, int]:
    """(columns, rows) of the grid for about ``n_vertices`` vertices (aspect ~ arc length : height)."""
    if n_vertices < MIN_VERTICES:
        raise ReflectmmError(f"procedural face model: need at least {MIN_VERTICES} vertices, got {n_vertices}")
    aspect = (2 * THETA_MAX * 74.0) / (Y_TOP - Y_BOTTOM)  # ≈ 1.29
    rows = max(20, int(round(math.sqrt(n_vertices / aspect))))
    cols = max(21, int(round(n_vertices / rows)))
    if cols % 2 == 0:  # an odd column count puts a column on the symmetry plane (the nose ridge)
        cols += 1
    return cols, rows


def _grid(cols: int, rows: int):
    # columns equally spaced in arc length of the mean cross-section (uniform sampling, low UV distortion)
    t = np.linspace(0.0, THETA_MAX, 20001)
    a, b = DEFAULT_PARAMS["half_width"], DEFAULT_PARAMS["depth"]
    c = np.cos(t)
    xs, zs = a * np.sin(t), b * np.sign(c) * np.abs(c) ** FRONT_POWER
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(zs)))])
    s = np.linspace(-arc[-1], arc[-1], cols)
    theta = np.sign(s) * np.interp(np.abs(s), arc, t)
    theta = 0.5 * (theta - theta[::-1])  # exactly antisymmetric, so the mirror map is exact
    Y = np.linspace(Y_TOP, Y_BOTTOM, rows)
    TH, YY = np.meshgrid(theta, Y)
    return TH.ravel(), YY.ravel()


def face_surface(theta: np.ndarray, Y: np.ndarray, p: dict[str, float], *, return_base_normal: bool = False):
    """Vertex positions (N, 3) of the parametric face at grid coordinates (θ, Y) for parameters ``p``.

    Also returns the frontal feature coordinates (X, Y) used to place features and landmarks.
    """
    X = 74.0 * np.sin(theta)  # feature frame: fixed per grid vertex, scales with the face
    # base surface
    below = np.clip(10.0 - Y, 0.0, None)
    a = p["half_width"] - p["jaw_narrow"] * (below / 100.0) ** 2
    a = a - 4.0 * (np.clip(Y - 60.0, 0.0, None) / 50.0) ** 2
    b = p["depth"] - p["forehead_recede"] * np.clip(Y - 55.0, 0.0, None) ** 2 \
        - p["chin_recede"] * np.clip(-55.0 - Y, 0.0, None) ** 2 * 4.0
    # height field of features
    d = np.zeros_like(X)
    # nose: ridge from the bridge to the tip, quickly falling off to the subnasale
    ty, by = p["nose_tip_y"], p["nose_bridge_y"]
    s = np.clip((by - Y) / (by - ty), 0.0, None)  # 0 at bridge, 1 at tip
    prof = np.where(Y >= ty, p["bridge_height"] + (p["nose_height"] - p["bridge_height"]) * s ** 1.3,
                    p["nose_height"] * np.exp(-0.5 * ((Y - ty) / 5.5) ** 2))
    prof = prof * _smoothstep(by + 12.0, by - 2.0, Y)  # fade into the glabella above the bridge
    width = p["nose_width"] * (0.75 + 0.6 * _g(Y - ty, 9.0)) + 2.0 * np.clip((Y - by) / 10.0, 0, None)
    d += prof * _g(X, width)
    # alae (nose wings) and nostril pits
    for sgn in (-1.0, 1.0):
        d += p["alar_height"] * _g(X - sgn * 0.72 * p["alar_width"], 5.0) * _g(Y - (ty - 3.0), 5.5)
        d -= p["nostril_depth"] * _g(X - sgn * 7.5, 2.6) * _g(Y - (ty - 7.5), 2.0)
    # eye sockets and eyeballs, brow ridge, temples, cheeks
    for sgn in (-1.0, 1.0):
        ex = X - sgn * p["eye_x"]
        d -= p["socket_depth"] * _g(ex, 15.0) * _g(Y - p["eye_y"], 10.0)
        d += p["eyeball"] * _g(ex, 9.0) * _g(Y - p["eye_y"], 5.5)
        # eyelids: a rim around the eye opening (upper lid fuller), and the upper-lid crease above it
        ey = Y - p["eye_y"]
        rim = np.sqrt((ex / 12.0) ** 2 + (ey / 5.0) ** 2)
        d += 1.3 * _g(rim - 1.0, 0.35) * (1.0 + 0.5 * _smoothstep(-1.0, 1.0, ey))
        d -= 0.9 * _g(ex, 10.0) * _g(ey - 8.0, 2.5)
        # nasolabial fold: a shallow groove from the ala to beside the mouth corner
        t = np.clip((p["nose_tip_y"] - 3.0 - Y) / 26.0, 0.0, 1.0)
        fold_x = sgn * (17.0 + 10.0 * t)
        d -= 1.4 * _g(X - fold_x, 2.5) * _g(Y - (p["nose_tip_y"] - 3.0 - 26.0 * t), 8.0) * (Y < p["nose_tip_y"] - 2)
        # philtrum columns
        d += 0.7 * _g(X - sgn * 4.5, 1.6) * _g(Y - (p["mouth_y"] + 13.0), 4.0)
        d += p["brow_height"] * _g(X - sgn * (p["eye_x"] - 2.0), 17.0) * _g(Y - p["brow_y"] + 0.004 * ex ** 2, 5.5)
        d -= p["temple"] * _g(X - sgn * 62.0, 9.0) * _g(Y - 38.0, 16.0)
        d += p["cheek_height"] * _g(X - sgn * p["cheek_x"], 17.0) * _g(Y - p["cheek_y"], 15.0)
        d += p["cheekbone"] * _g(X - sgn * 50.0, 10.0) * _g(Y - 18.0, 7.0)
    d += p["glabella"] * _g(X, 9.0) * _g(Y - (p["brow_y"] - 4.0), 6.0)
    # mouth region: maxilla/mandible bulge, lips, mouth line, mentolabial sulcus, chin
    my = p["mouth_y"]
    d += p["maxilla"] * _g(X, 27.0) * _g(Y - (my + 6.0), 17.0)
    lipx = _g(X, p["mouth_half_width"] * 0.68)
    d += p["upper_lip"] * lipx * _g(Y - (my + 5.5), 3.6)
    d += p["lower_lip"] * _g(X, p["mouth_half_width"] * 0.6) * _g(Y - (my - 6.5), 4.2)
    d -= p["mouth_groove"] * _g(X, p["mouth_half_width"] * 0.75) * _g(Y - my, 1.3)
    d -= p["sulcus"] * _g(X, 14.0) * _g(Y - (my - 17.0), 4.0)
    d += p["chin_height"] * _g(X, 15.0) * _g(Y - p["chin_y"], 10.0)
    # features live on the front: taper towards the sides so the silhouette stays smooth
    d *= _smoothstep(math.radians(95), math.radians(60), np.abs(theta))
    # assemble: base point + displacement along the base normal.  The cross-section is flattened at the front
    # (z = b·sgn(cos θ)|cos θ|^FRONT_POWER): faces are flatter across the eyes than an ellipse and turn more
    # sharply at the cheekbones.
    c = np.cos(theta)
    cp = np.maximum(np.abs(c), 1e-6)
    x0 = a * np.sin(theta)
    z0 = b * np.sign(c) * np.abs(c) ** FRONT_POWER
    # normal ⟂ tangent (a cos θ, −b·P·|cos θ|^(P−1)·sin θ) in the xz-plane
    nx, nz = b * FRONT_POWER * cp ** (FRONT_POWER - 1.0) * np.sin(theta), a * c
    nn = np.sqrt(nx ** 2 + nz ** 2)
    pts = np.stack([x0 + d * nx / nn, Y * p["height_scale"], z0 + d * nz / nn], axis=1)
    if return_base_normal:  # the smooth normal of the feature-less base surface
        return pts, X, np.stack([nx / nn, np.zeros_like(nx), nz / nn], axis=1)
    return pts, X


def _triangles(cols: int, rows: int) -> np.ndarray:
    """Two CCW (outward) triangles per quad; diagonals mirrored about the symmetry plane."""
    j, i = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    j, i = j.ravel(), i.ravel()
    a = j * cols + i
    b = a + 1
    c = a + cols
    dd = c + 1
    left = (i + 0.5) < (cols - 1) / 2.0
    t1 = np.where(left[:, None], np.stack([a, c, b], 1), np.stack([a, c, dd], 1))
    t2 = np.where(left[:, None], np.stack([b, c, dd], 1), np.stack([a, dd, b], 1))
    return np.concatenate([t1, t2]).astype(np.int32)


# (X, Y) landmark targets in the frontal feature frame, iBUG order (0-based).
def _landmark_targets(p: dict[str, float]) -> np.ndarray:
    pts = []
    for k in range(17):  # jaw line: subject's right (−X, image left) → chin → subject's left
        t = k / 16.0
        pts.append((-66.0 * math.cos(math.pi * t), 18.0 - (18.0 - p["chin_y"] + 9.0) * math.sin(math.pi * t)))
    ex, ey, by = p["eye_x"], p["eye_y"], p["brow_y"]
    brow_x = [52.0, 43.0, 33.0, 23.0, 13.0]
    brow_dy = [-3.0, 0.5, 2.0, 1.0, -1.5]
    for x, dy in zip(brow_x, brow_dy):  # right brow, outer → inner (17-21)
        pts.append((-x, by + dy))
    for x, dy in zip(brow_x[::-1], brow_dy[::-1]):  # left brow, inner → outer (22-26)
        pts.append((x, by + dy))
    ty = p["nose_tip_y"]
    for s in (0.0, 1 / 3, 2 / 3, 1.0):  # nose ridge 27-30
        pts.append((0.0, (ey + 1.0) * (1 - s) + (ty + 1.0) * s))
    for x, dy in ((-12.0, -5.0), (-6.5, -7.0), (0.0, -8.0), (6.5, -7.0), (12.0, -5.0)):  # nose base 31-35
        pts.append((x, ty + dy))
    w = 11.5
    eye = [(-w, 0.0), (-w / 3, 3.8), (w / 3, 3.8), (w, 0.0), (w / 3, -3.4), (-w / 3, -3.4)]
    for dx, dy in eye:  # right eye 36-41: outer corner, top, inner corner, bottom (clockwise in image)
        pts.append((-ex + dx, ey + dy))
    for dx, dy in eye:  # left eye 42-47: inner corner, top, outer corner, bottom
        pts.append((ex + dx, ey + dy))
    my, mw = p["mouth_y"], p["mouth_half_width"]
    outer = [(-mw, 0.0), (-0.65 * mw, 6.0), (-0.25 * mw, 8.5), (0.0, 7.8), (0.25 * mw, 8.5), (0.65 * mw, 6.0),
             (mw, 0.0), (0.65 * mw, -7.0), (0.25 * mw, -10.0), (0.0, -10.5), (-0.25 * mw, -10.0),
             (-0.65 * mw, -7.0)]
    for dx, dy in outer:  # outer lip 48-59
        pts.append((dx, my + dy))
    inner = [(-0.85 * mw, 0.0), (-0.35 * mw, 1.5), (0.0, 1.5), (0.35 * mw, 1.5), (0.85 * mw, 0.0),
             (0.35 * mw, -1.5), (0.0, -1.5), (-0.35 * mw, -1.5)]
    for dx, dy in inner:  # inner lip 60-67
        pts.append((dx, my + dy))
    return np.asarray(pts, dtype=np.float64)


def _expression_fields(pts: np.ndarray, X: np.ndarray, Y: np.ndarray, p: dict[str, float]) -> np.ndarray:
    """(Ke0, N, 3) named expression displacement fields (mm, at a strong-but-natural amplitude)."""
    my = p["mouth_y"]
    mw = p["mouth_half_width"]
    fields = []
    zero = np.zeros_like(X)

    def vec(dx=zero, dy=zero, dz=zero):
        return np.stack([dx + zero, dy + zero, dz + zero], axis=1)

    below_mouth = _smoothstep(my + 2.0, my - 10.0, Y)  # 1 below the mouth line, smooth across the lips
    lower_face = below_mouth * _g(X, 38.0)
    mouth_reg = _g(X, mw * 1.1) * _g(Y - my, 12.0)
    # jaw open: lower lip/chin down and slightly back, rotation about the jaw hinge
    fields.append(vec(dy=-7.0 * lower_face, dz=-2.5 * lower_face))
    # smile: mouth corners up/out/back, cheeks up
    for side in (None, -1.0, 1.0):
        w = np.ones_like(X) if side is None else _smoothstep(-8.0 * side, 8.0 * side, X) if side > 0 \
            else _smoothstep(8.0, -8.0, X)
        corner = sum(_g(X - s * mw, 10.0) * _g(Y - my, 9.0) for s in (-1.0, 1.0))
        cheek = sum(_g(X - s * 38.0, 14.0) * _g(Y - 5.0, 12.0) for s in (-1.0, 1.0))
        fields.append(vec(dx=3.5 * _odd(X) * corner * w, dy=(5.0 * corner + 2.5 * cheek) * w,
                          dz=(-2.0 * corner + 2.0 * cheek) * w))
    # pucker: lips forward, mouth narrower
    fields.append(vec(dx=-0.25 * X * mouth_reg, dz=7.0 * mouth_reg))
    # lip press / lips in
    fields.append(vec(dy=-1.5 * np.sign(Y - my) * mouth_reg, dz=-3.0 * mouth_reg))
    # brow raise (both, right, left)
    brow = _g(Y - p["brow_y"], 10.0) * _smoothstep(25.0, 40.0, Y)
    for side in (None, -1.0, 1.0):
        w = np.ones_like(X) if side is None else _g(X - side * p["eye_x"], 18.0)
        fields.append(vec(dy=6.0 * brow * _g(X, 45.0) * w, dz=0.8 * brow * w))
    # frown: inner brows down and together
    inner = _g(np.abs(X) - 14.0, 9.0) * _g(Y - p["brow_y"], 7.0)
    fields.append(vec(dx=-2.5 * _odd(X) * inner, dy=-4.0 * inner, dz=1.0 * inner))
    # eye close: upper lid region down over the eyeball
    lid = sum(_g(X - s * p["eye_x"], 9.0) * _g(Y - (p["eye_y"] + 4.0), 3.5) for s in (-1.0, 1.0))
    fields.append(vec(dy=-4.5 * lid, dz=1.0 * lid))
    # cheek puff
    puff = sum(_g(X - s * 40.0, 14.0) * _g(Y - (my + 8.0), 14.0) for s in (-1.0, 1.0))
    fields.append(vec(dx=2.5 * _odd(X) * puff, dz=5.0 * puff))
    # nose wrinkle / sneer: alae and upper lip up
    sneer = _g(X, 16.0) * _g(Y - (p["nose_tip_y"] - 6.0), 9.0)
    fields.append(vec(dy=3.0 * sneer, dz=1.0 * sneer))
    # mouth left / right
    fields.append(vec(dx=5.0 * mouth_reg))
    # mouth stretch (wide, lips thin)
    fields.append(vec(dx=0.2 * X * mouth_reg, dz=-1.5 * mouth_reg))
    # chin raise (mentalis)
    chin = _g(X, 16.0) * _g(Y - (my - 18.0), 10.0)
    fields.append(vec(dy=3.0 * chin, dz=2.0 * chin))
    # jaw sideways
    fields.append(vec(dx=3.0 * lower_face))
    # lower lip down / upper lip up (showing teeth)
    fields.append(vec(dy=-4.0 * _g(X, mw * 0.8) * _g(Y - (my - 7.0), 5.0)))
    fields.append(vec(dy=3.0 * _g(X, mw * 0.8) * _g(Y - (my + 6.0), 5.0)))
    return np.stack(fields)


def _warp_fields(X: np.ndarray, Y: np.ndarray, p: dict[str, float]) -> np.ndarray:
    """(W, N, 3) in-plane displacement fields moving feature regions with their vertices, at 1σ (WARP_SIGMA)."""
    sx = _odd(X)
    eye = sum(_g(X - s * p["eye_x"], 14.0) * _g(Y - p["eye_y"], 10.0) for s in (-1.0, 1.0))
    brow = _g(np.abs(X) - p["eye_x"], 18.0) * _g(Y - p["brow_y"], 7.0)
    tip = _g(X, 16.0) * _g(Y - p["nose_tip_y"], 9.0)
    ala = sum(_g(X - s * 0.72 * p["alar_width"], 6.0) * _g(Y - (p["nose_tip_y"] - 3.0), 7.0) for s in (-1.0, 1.0))
    mouth = _g(X, p["mouth_half_width"] * 1.3) * _g(Y - p["mouth_y"], 11.0)
    chin = _g(X, 22.0) * _smoothstep(p["mouth_y"] - 8.0, p["mouth_y"] - 25.0, Y)
    cheek = sum(_g(X - s * p["cheek_x"], 16.0) * _g(Y - p["cheek_y"], 14.0) for s in (-1.0, 1.0))
    z = np.zeros_like(X)
    W = WARP_SIGMA
    fields = {
        "eye_spacing": (W["eye_spacing"] * sx * eye, z), "eye_height": (z, W["eye_height"] * eye),
        "brow_height": (z, W["brow_height"] * brow), "nose_length": (z, -W["nose_length"] * tip),
        "alar_width": (W["alar_width"] * sx * ala, z), "mouth_height": (z, W["mouth_height"] * mouth),
        "mouth_width": (W["mouth_width"] * (X / p["mouth_half_width"]) * mouth, z),
        "chin_height": (z, -W["chin_height"] * chin), "cheek_height": (z, W["cheek_height"] * cheek),
    }
    return np.stack([np.stack([dx, dy, z], axis=1) for dx, dy in (fields[k] for k in W)])


def _rbf_fields(X, Y, normal, rng, count: int, amp: float, scale: float) -> np.ndarray:
    """Random smooth radial-basis deformations: each the sum of three broad Gaussian bumps moving the
    surface along its normal and in-plane.  70 % of the bumps are mirror-symmetric (x-motion antisymmetric),
    as in real populations."""
    out = []
    for _ in range(count):
        f = np.zeros((X.shape[0], 3))
        for _b in range(3):
            cx, cy = rng.uniform(-60, 60), rng.uniform(-70, 90)
            s = rng.uniform(0.7, 1.3) * scale
            an, ax, ay = rng.normal(0.0, amp, size=3)
            right = _g(X - cx, s) * _g(Y - cy, s)
            if rng.random() < 0.7:
                left = _g(X + cx, s) * _g(Y - cy, s)
                sym, anti = 0.5 * (right + left), 0.5 * (right - left)
                f += (an * sym)[:, None] * normal
                f[:, 0] += 0.3 * ax * anti
                f[:, 1] += 0.3 * ay * sym
            else:
                f += (an * right)[:, None] * normal
                f[:, 0] += 0.3 * ax * right
                f[:, 1] += 0.3 * ay * right
        out.append(f)
    return np.stack(out)


def _orthonormal_basis(fields: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """SVD of (F, N, 3) displacement fields → k orthonormal (N, 3) basis vectors and their σ (mm)."""
    F = fields.reshape(fields.shape[0], -1).astype(np.float64)
    # thin SVD through the small Gram matrix (F is a few dozen × 3N): F Fᵀ = U S² Uᵀ, Vᵀ = S⁻¹ Uᵀ F
    w, U = np.linalg.eigh(F @ F.T)
    order = np.argsort(w)[::-1]
    w, U = np.clip(w[order], 0.0, None), U[:, order]
    S = np.sqrt(w)
    k = min(k, int(np.sum(S > 1e-9 * S[0])))
    basis = (U[:, :k].T @ F) / S[:k, None]
    # deterministic sign: largest-magnitude entry positive
    sgn = np.sign(basis[np.arange(k), np.abs(basis).argmax(1)])
    basis = basis * sgn[:, None]
    return basis.reshape(k, -1, 3), S[:k]


def procedural_face_model(n_vertices: int = 35000, n_shape: int = 40, n_exp: int = 20, seed: int = 0,
                          grid: tuple[int, int] | None = None) -> FaceModel:
    """The built-in face model (see the module docstring).

    Args:
        n_vertices: approximate vertex count (the grid is ``grid_shape(n_vertices)``); ignored if ``grid``.
        n_shape: number of identity components (≤ number of anatomical parameters + random fields).
        n_exp: number of expression components.
        seed: drives the random low-frequency parts of the bases only.
        grid: explicit (columns, rows); columns should be odd.
    Returns:
        A :class:`FaceModel` with UVs, landmarks, skin mask and an exact mirror map.
    """
    cols, rows = grid if grid is not None else grid_shape(int(n_vertices))
    if cols < 11 or rows < 11:
        raise ReflectmmError(f"procedural face model: grid {cols}x{rows} is too coarse (need ≥ 11×11)")
    theta, Y = _grid(cols, rows)
    p0 = dict(DEFAULT_PARAMS)
    mean, X, base_normal = face_surface(theta, Y, p0, return_base_normal=True)
    tri = _triangles(cols, rows)
    rng = np.random.default_rng(seed)

    # random deformations move along the smooth base normal: offsetting along the feature-rich vertex normal
    # folds the surface wherever the offset exceeds the local radius of curvature (nose ridge, lips)
    normal = base_normal
    # identity: finite differences of the anatomical parameters at 1σ, plus random smooth fields
    fields = []
    for name, sig in SHAPE_SIGMA.items():
        q = dict(p0)
        q[name] = p0[name] + sig
        fields.append(face_surface(theta, Y, q)[0] - mean)
    fields.extend(_warp_fields(X, Y, p0))
    n_named = len(fields)
    n_rand = max(0, n_shape - n_named) + 8
    fields.extend(_rbf_fields(X, Y, normal, rng, n_rand, amp=1.2, scale=32.0))
    shape_basis, shape_sigma = _orthonormal_basis(np.stack(fields), n_shape)
    # expression: named fields (each a 1σ displacement) plus a few random local ones around mouth/brows
    efields = list(0.6 * _expression_fields(mean, X, Y, p0))  # 1σ = 60 % of the strong pose
    extra = max(0, n_exp - len(efields)) + 4
    efields.extend(_rbf_fields(X, Y, normal, rng, extra, amp=1.0, scale=12.0))
    exp_basis, exp_sigma = _orthonormal_basis(np.stack(efields), n_exp)

    # landmarks: nearest front-facing vertex in the frontal (X, Y) plane
    targets = _landmark_targets(p0)
    front = np.abs(theta) < math.radians(88)
    cand = np.nonzero(front)[0]
    fx, fy = mean[cand, 0], mean[cand, 1]
    lm = np.empty(68, dtype=np.int32)
    for k, (tx, ty) in enumerate(targets):
        # targets are in the feature frame; the mean face maps feature X ≈ mean x near the front
        lm[k] = cand[np.argmin((fx - tx * p0["half_width"] / 74.0) ** 2 + (fy - ty) ** 2)]
    # skin mask: eye openings and nostril pits are not skin
    skin = np.ones(mean.shape[0], dtype=bool)
    for sgn in (-1.0, 1.0):
        eye = ((X - sgn * p0["eye_x"]) / 11.5) ** 2 + ((Y - p0["eye_y"]) / 4.2) ** 2 < 1.0
        nostril = ((X - sgn * 7.5) / 3.2) ** 2 + ((Y - (p0["nose_tip_y"] - 7.5)) / 2.4) ** 2 < 1.0
        skin &= ~(eye | nostril)
    # UVs and mirror map
    iu = np.tile(np.arange(cols), rows)
    jv = np.repeat(np.arange(rows), cols)
    u = UV_MARGIN + (1 - 2 * UV_MARGIN) * iu / (cols - 1)
    v = UV_MARGIN + (1 - 2 * UV_MARGIN) * jv / (rows - 1)
    mirror = (jv * cols + (cols - 1 - iu)).astype(np.int32)
    return FaceModel(mean_shape=mean, shape_basis=shape_basis, shape_sigma=shape_sigma, exp_basis=exp_basis,
                     exp_sigma=exp_sigma, triangles=tri, uv=np.stack([u, v], 1), landmarks=lm, skin_mask=skin,
                     name=f"procedural face (seed {seed}, {cols}x{rows} grid)", mirror=mirror,
                     info={"source": "procedural", "seed": int(seed), "grid": [int(cols), int(rows)],
                           "n_named_shape_params": n_named})

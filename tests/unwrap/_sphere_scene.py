"""A tiny analytic scene in the Multi-PIE layout: a spherical cap (mesh with planar UVs), cameras and point flashes,
rendered by exact ray–sphere intersection and shade_directional into 8-bit PNGs (``x**(1/1.2)``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import write_artifact
from reflectmm_cli.capture.images import encode_linear, write_png
from reflectmm_cli.capture.layout import camera_code
from reflectmm_cli.capture.transfer import parse_transfer
from reflectmm_cli.geometry.face_model import FaceModel, save_face_model
from reflectmm_cli.shading.brdf import shade_directional

RADIUS = 50.0
HALF = 0.65 * RADIUS
ALBEDO = np.array([0.6, 0.45, 0.35])
WEIGHTS = np.array([0.05, 0.1, 0.0])
EXPONENTS = np.array([1.0, 8.0, 64.0])
ROOM = 0.03


def look_at(eye, target=(0, 0, 0), up=(0, 1, 0)):
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def cap_mesh(n=61):
    g = np.linspace(-HALF, HALF, n)
    X, Y = np.meshgrid(g, g)
    Z = np.sqrt(RADIUS ** 2 - X ** 2 - Y ** 2)
    verts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    uv = np.stack([0.5 + verts[:, 0] / (2 * HALF) * 0.96, 0.5 - verts[:, 1] / (2 * HALF) * 0.96], 1)
    tris = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i
            tris += [(a, b, c), (a, c, d)]
    return verts, np.array(tris), uv


def quad(center, normal_dir, size):
    """Two triangles of a square occluder (degenerate UVs so it takes no texels)."""
    nd = np.asarray(normal_dir, float)
    nd /= np.linalg.norm(nd)
    u = np.cross(nd, [0, 1, 0])
    u /= np.linalg.norm(u)
    w = np.cross(nd, u)
    c = np.asarray(center, float)
    h = size / 2
    v = np.array([c - h * u - h * w, c + h * u - h * w, c + h * u + h * w, c - h * u + h * w])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def seg_hits_quad(p, q, qv):
    """(N,) bool: segment p→q (q (3,)) crosses the convex quad qv (4,3)."""
    n = np.cross(qv[1] - qv[0], qv[3] - qv[0])
    d = q - p
    denom = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((qv[0] - p) @ n) / denom
    hit = np.isfinite(s) & (s > 1e-9) & (s < 1 - 1e-9)
    x = p + np.where(hit, s, 0.0)[:, None] * d
    inside = np.ones(len(p), bool)
    for k in range(4):
        e = qv[(k + 1) % 4] - qv[k]
        inside &= (np.cross(e, x - qv[k]) @ n) >= 0
    return hit & inside


def shading(x, n, cam_center, flash_pos, intensity):
    dl = flash_pos - x
    E = intensity / np.einsum("nk,nk->n", dl, dl)
    return shade_directional(ALBEDO, WEIGHTS, EXPONENTS, n, dl, cam_center - x, E[:, None] * np.ones(3))


def make_scene(root: Path, ws: Path, *, ident="001", occluder=None, size=(160, 160), focal=600.0, n_mesh=61):
    """Write the Multi-PIE tree, the geometry artifact and the face model; return the scene description."""
    views = {"05_1": (0.0, 0.0, 400.0), "14_0": (400 * np.sin(np.radians(-20)), 0.0, 400 * np.cos(np.radians(20)))}
    flashes = {"07": (0.0, 0.0, 400.0), "14": (250.0, 180.0, 300.0)}
    intensity = 3.0 * 350.0 ** 2
    W, H = size
    K = np.array([[focal, 0, (W - 1) / 2], [0, focal, (H - 1) / 2], [0, 0, 1.0]])
    verts, tris, uv = cap_mesh(n_mesh)
    scene_v, scene_t = verts, tris
    if occluder is not None:
        qv, qt = occluder
        scene_v = np.concatenate([verts, qv])
        scene_t = np.concatenate([tris, qt + len(verts)])
        uv = np.concatenate([uv, np.full((len(qv), 2), 0.001)])
    tr = parse_transfer("gamma1.2")
    Ks, Rs, ts, cs = [], [], [], []
    for cam, eye in views.items():
        R, t = look_at(eye)
        c = -R.T @ t
        Ks.append(K), Rs.append(R), ts.append(t), cs.append(c)
        ys, xs = np.mgrid[0:H, 0:W].astype(float)
        dirs = np.stack([(xs - K[0, 2]) / focal, (ys - K[1, 2]) / focal, np.ones_like(xs)], -1).reshape(-1, 3) @ R
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        b = dirs @ c
        cc = c @ c - RADIUS ** 2
        disc = b * b - cc
        tt = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
        hit = np.isfinite(tt)
        x = c + np.where(hit, tt, 0)[:, None] * dirs
        if occluder is not None:
            blocked_cam = seg_hits_quad(x, c, occluder[0]) & hit
        else:
            blocked_cam = np.zeros(len(x), bool)
        n = x / RADIUS
        room = np.where((hit & ~blocked_cam)[:, None], ROOM * ALBEDO, 0.0)
        write_png(_shot(root, ident, cam, "00"), encode_linear(room.reshape(H, W, 3), tr))
        for fid, fpos in flashes.items():
            s = np.zeros((len(x), 3))
            s[hit] = shading(x[hit], n[hit], c, np.asarray(fpos, float), intensity)
            if occluder is not None:
                s[seg_hits_quad(x, np.asarray(fpos, float), occluder[0])] = 0.0
            s[blocked_cam] = 0.0
            write_png(_shot(root, ident, cam, fid), encode_linear((room + s).reshape(H, W, 3), tr))
    geo = {"vertices": scene_v.astype(np.float32), "view_names": np.array(list(views)),
           "K": np.array(Ks), "R": np.array(Rs), "t": np.array(ts), "cam_centers": np.array(cs),
           "image_size": np.array([W, H]), "flash_ids": np.array(list(flashes)),
           "flash_pos": np.array(list(flashes.values())), "flash_intensity": np.full(len(flashes), intensity),
           "shape_coeffs": np.zeros(0), "exp_coeffs": np.zeros(0)}
    geo_path = write_artifact(ws / "fit-geometry" / f"{ident}.npz", "geometry", geo)
    fm = FaceModel(mean_shape=scene_v, shape_basis=None, shape_sigma=None, exp_basis=None, exp_sigma=None,
                   triangles=scene_t, uv=uv, landmarks=np.zeros(0, np.int32), skin_mask=np.ones(len(scene_v), bool))
    fm_path = save_face_model(fm, ws / "face_model.npz")
    return {"views": list(views), "flashes": list(flashes), "intensity": intensity, "geometry": geo,
            "geometry_path": geo_path, "face_model_path": fm_path, "n_cap_vertices": len(verts)}


def _shot(root, ident, cam, shot):
    return (Path(root) / "data" / "session01" / "multiview" / ident / "01" / cam /
            f"{ident}_01_01_{camera_code(cam)}_{shot}.png")

"""Jaw points on the outline (landmark marching): the outline against the closed-form normals of the toy's
ellipsoid, and a fit whose 'detector' puts the jaw on the ray-cast silhouette."""

import math

import numpy as np
import pytest

import toy
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.geometry_fit import FitConfig, ViewSet, fit_geometry, initial_poses
from reflectmm_cli.geometry_fit.contour import SLIDING, jaw_contour, model_axes, outline, slide

AZ = [-30, -15, 0, 15, 30]  # what a frontal detector annotates


def test_model_axes_of_the_toy_are_its_frame():
    m = toy.toy_model()
    side, up, front = model_axes(m.mean, m.landmarks)
    # (up runs from the chin to the eyes: the toy's chin sits 2° behind its eye line)
    np.testing.assert_allclose(side, [1, 0, 0], atol=0.05)
    np.testing.assert_allclose(up, [0, 1, 0], atol=0.05)
    np.testing.assert_allclose(front, [0, 0, 1], atol=0.05)
    np.testing.assert_allclose(np.stack([side, up, front]) @ np.stack([side, up, front]).T, np.eye(3), atol=1e-12)
    # the axes do not depend on the model's frame: rotate and move the mean, the axes follow
    R = toy.rotvec_matrix([0.3, -0.5, 0.2])
    s2, u2, f2 = model_axes(m.mean @ R.T + [10, -4, 7], m.landmarks)
    np.testing.assert_allclose(np.stack([s2, u2, f2]), np.stack([side, up, front]) @ R.T, atol=1e-9)


class _Silhouette:
    """The silhouette of a mesh in one view by ray casting (independent of the contour code): along an image row,
    from a pixel on the mesh outward, the last ray that hits and the first that misses are bisected to 1e-3 px."""

    def __init__(self, verts, triangles, K, R, t):
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.ray = RayMeshIntersector(trimesh.Trimesh(vertices=verts, faces=triangles, process=False))
        self.K, self.R = K, R
        self.c = camera_centers(R[None], t[None])[0]

    def hits(self, u, v):
        d = np.linalg.solve(self.K, [u, v, 1.0]) @ self.R
        return bool(self.ray.intersects_any(self.c[None], (d / np.linalg.norm(d))[None])[0])

    def crossing(self, u, v, step):
        """u of the silhouette on row v, starting at u (on the mesh) and walking by ``step`` px (sign: outward)."""
        inside = u
        while self.hits(inside + step, v):
            inside += step
        outside = inside + step
        for _ in range(12):
            half = 0.5 * (inside + outside)
            inside, outside = (half, outside) if self.hits(half, v) else (inside, half)
        return 0.5 * (inside + outside)


@pytest.mark.parametrize("az", [0.0, 20.0, -35.0])
def test_outline_lies_on_the_silhouette(az):
    """Every outline vertex projects onto the mesh's silhouette in the image: on its image row, within half a
    median edge of the mesh (2.3 px here) of the ray-cast crossing (a slice's extreme is on the occluding contour, or
    on the slice's edge where the slice crosses the contour at a slant).  A vertex on the face, one ring inside,
    would be further (a whole edge)."""
    m = toy.toy_model(n_lon=121, n_lat=41)
    # the toy's jaw ends sit 30–70 mm in front of its silhouette: the lines reach 100 mm behind them, to its border
    c = jaw_contour(m.mean, m.triangles, m.landmarks, behind_mm=100.0)
    K, R, t = toy.arc_cameras([az])
    K, R, t = K[0], R[0], t[0]
    sil = _Silhouette(m.mean, m.triangles, K, R, t)
    mid = project(m.mean[m.landmarks[27:]], K, R, t)[0].mean(0)
    tri = m.triangles
    edge = np.median(np.linalg.norm(m.mean[tri[:, [1, 2, 0]]] - m.mean[tri], axis=-1)) * K[0, 0] / 1300.0
    assert 2.0 < edge < 6.0
    for side, ids in enumerate(outline(c, m.mean, K, R, t)):
        assert len(ids) >= 10
        uv = project(m.mean[ids], K, R, t)[0]
        for u, v in uv:
            step = 1.0 if u > mid[0] else -1.0
            want = sil.crossing(u - 3 * step, v, step)
            assert abs(u - want) < 0.5 * edge, (side, u, v, want, edge)


def _silhouette_jaw(verts, m, K, R, t):
    """A 'detector' independent of the contour code: each sliding jaw point on the ray-cast silhouette of the
    mesh, on the image row of the true jaw vertex."""
    sil = _Silhouette(verts, m.triangles, K, R, t)
    p, _ = project(verts[m.landmarks], K, R, t)
    mid = p[27:].mean(0)
    out = p.copy()
    for k in SLIDING:
        u, v = p[k]
        out[k] = [sil.crossing(u, v, 1.0 if u > mid[0] else -1.0), v]
    return out


def test_a_jaw_on_the_silhouette_fits_with_the_contour():
    """The cheek points of a detector lie on the silhouette.  With fixed jaw vertices they pull the face out of
    shape (2.1 mm vertex RMS here); with jaw=0 the face loses their information (0.55 mm); sliding them to the
    outline, the residual measured across it, keeps it without the bias (0.31 mm)."""
    m = toy.toy_model(n_lon=81, n_lat=61, n_shape=6, n_exp=2)
    rng = np.random.default_rng(4)
    zs = rng.normal(size=m.n_shape)
    verts = m.vertices(zs * m.shape_sigma, np.zeros(m.n_exp))
    K, R, t = toy.arc_cameras(AZ)
    lm = np.stack([_silhouette_jaw(verts, m, K[v], R[v], t[v]) for v in range(len(AZ))])
    lm[:, 17:] += rng.normal(size=lm[:, 17:].shape) * 0.5
    moved = np.linalg.norm(lm[:, list(SLIDING)] - np.stack([project(verts[m.landmarks[list(SLIDING)]], K[v], R[v],
                                                                    t[v])[0] for v in range(len(AZ))]), axis=-1)
    assert np.median(moved) > 5.0  # the silhouette is far from the model's jaw vertices here

    def fit(**cfg):
        R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, R, t)
        vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(640, 480),
                     rig_centers=camera_centers(R, t), rig_R=R)
        f = fit_geometry(m, vs, FitConfig(photo_rounds=0, rig_sigma_mm=3.0, rig_rot_sigma_deg=0.3,
                                          contour_behind_mm=100.0, **cfg))  # (the toy's silhouette: above)
        return float(np.sqrt(((f.vertices - verts) ** 2).sum(-1).mean()))

    fixed, off, contour = fit(), fit(group_weights={"jaw": 0.0}), fit(jaw_contour=True)
    assert contour < 0.25 * fixed, (contour, fixed)
    assert contour < 0.9 * off, (contour, off)


def test_slide_keeps_points_not_observed():
    m = toy.toy_model()
    c = jaw_contour(m.mean, m.triangles, m.landmarks)
    K, R, t = toy.arc_cameras([0.0])
    obs = np.full((len(SLIDING), 2), np.nan)
    fixed = m.landmarks[list(SLIDING)]
    ids, normals, across = slide(c, m.mean, K[0], R[0], t[0], obs, fixed)
    np.testing.assert_array_equal(ids, fixed)
    assert not normals.any() and np.isnan(across).all()
    obs[0] = project(m.mean[fixed[0]][None], K[0], R[0], t[0])[0][0] + [-40.0, 0.0]
    ids, normals, across = slide(c, m.mean, K[0], R[0], t[0], obs, fixed)
    assert ids[0] != fixed[0] and (ids[1:] == fixed[1:]).all() and not normals[1:].any()
    uv = project(m.mean[ids[0]][None], K[0], R[0], t[0])[0][0]
    assert abs(across[0] - abs((uv - obs[0]) @ normals[0])) < 1e-9 and np.isnan(across[1:]).all()
    assert ids[0] in outline(c, m.mean, K[0], R[0], t[0])[c.sides[0]]
    # the normal is across the outline: nearly horizontal on the side of a face seen from the front
    assert abs(np.linalg.norm(normals[0]) - 1) < 1e-12 and abs(normals[0, 0]) > 0.9


def test_jaw_contour_reaches_the_fit_config_and_leaves_the_chin_out():
    from reflectmm_cli.geometry_fit.contour import CHIN
    from reflectmm_cli.params import resolve_params
    from reflectmm_cli.stages import fit_geometry as stage

    cfg = stage.config_from_params(resolve_params(stage.PARAMS, {"jaw_contour": True, "contour_behind_mm": 40}))
    assert cfg.jaw_contour and cfg.contour_behind_mm == 40.0
    assert not stage.config_from_params(resolve_params(stage.PARAMS, {})).jaw_contour
    # the chin's points do not enter the sliding fit: moving them 30 px changes nothing
    m = toy.toy_model(n_shape=4, n_exp=2)
    verts = m.vertices(np.random.default_rng(1).normal(size=m.n_shape) * m.shape_sigma, np.zeros(m.n_exp))
    K, R, t = toy.arc_cameras(AZ)
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(len(AZ))])
    moved = lm.copy()
    moved[:, list(CHIN), 1] += 30.0
    fits = []
    for obs in (lm, moved):
        R0, t0, _ = initial_poses(m.mean[m.landmarks[17:]], obs[:, 17:], K, R, t)
        vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=obs, image_size=(640, 480),
                     rig_centers=camera_centers(R, t), rig_R=R)
        fits.append(fit_geometry(m, vs, FitConfig(photo_rounds=0, jaw_contour=True, contour_behind_mm=100.0)))
    np.testing.assert_allclose(fits[0].vertices, fits[1].vertices, atol=1e-6)


def test_the_gate_leaves_out_a_point_off_the_outline():
    """--contour-gate: a cheek point pushed 20 px off the silhouette is left out, so the fit equals the one
    without that point; without the gate it pulls the face."""
    m = toy.toy_model(n_lon=81, n_lat=61, n_shape=6, n_exp=2)
    verts = m.vertices(np.random.default_rng(4).normal(size=m.n_shape) * m.shape_sigma, np.zeros(m.n_exp))
    K, R, t = toy.arc_cameras(AZ)
    lm = np.stack([_silhouette_jaw(verts, m, K[v], R[v], t[v]) for v in range(len(AZ))])
    pushed, missing = lm.copy(), lm.copy()
    pushed[2, 2, 0] -= 20.0 if pushed[2, 2, 0] < pushed[2, 27:, 0].mean() else -20.0  # outward, frontal view
    missing[2, 2] = np.nan

    def fit(obs, **cfg):
        R0, t0, _ = initial_poses(m.mean[m.landmarks[17:]], lm[:, 17:], K, R, t)
        vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=obs, image_size=(640, 480),
                     rig_centers=camera_centers(R, t), rig_R=R)
        return fit_geometry(m, vs, FitConfig(photo_rounds=0, rig_sigma_mm=3.0, rig_rot_sigma_deg=0.3, jaw_contour=True,
                                             contour_behind_mm=100.0, **cfg)).vertices

    gated, without = fit(pushed, contour_gate_px=3.0), fit(missing, contour_gate_px=3.0)
    np.testing.assert_allclose(gated, without, atol=1e-3)  # (the weight sum that scales the priors counts it)
    assert np.abs(fit(pushed) - without).max() > 0.05  # (0.15 mm: one point, under the Huber loss)

"""The fit on an independent toy model: exact recovery from exact landmarks, noisy landmarks, photometric term."""

import numpy as np
import pytest
import torch

import toy
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import camera_centers, project
from reflectmm_cli.geometry_fit import FitConfig, ViewSet, fit_geometry, initial_poses
from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry.face_model import vertex_normals as vertex_normals_torch
from reflectmm_cli.geometry_fit.photometric import photometric_loss, sh_kernel

AZ = [-60, -30, 0, 30, 60]


def _scene(n_shape=4, n_exp=2, seed=3, noise=0.0, head_rot=(0.04, -0.06, 0.02), head_t=(4.0, -8.0, 15.0)):
    m = toy.toy_model(n_shape=n_shape, n_exp=n_exp)
    rng = np.random.default_rng(seed)
    zs = rng.normal(size=m.n_shape) * 0.8
    ze = rng.normal(size=m.n_exp) * 0.5
    verts = m.vertices(zs * m.shape_sigma, ze * m.exp_sigma)
    K, Rn, tn = toy.arc_cameras(AZ)
    # the head moved away from the rig's nominal position: x_cam = Rn (Rh x + th) + tn
    Rh = toy.rotvec_matrix(head_rot)
    th = np.asarray(head_t)
    R = Rn @ Rh
    t = np.einsum("vij,j->vi", Rn, th) + tn
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(len(AZ))])
    lm = lm + rng.normal(size=lm.shape) * noise
    return m, zs, ze, verts, K, R, t, Rn, tn, lm


def _fit(m, K, Rn, tn, lm, rig_R=None, **cfg):
    R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, Rn, tn)
    vs = ViewSet(names=[str(a) for a in AZ], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(640, 480),
                 rig_centers=camera_centers(Rn, tn), rig_R=rig_R)
    return fit_geometry(m, vs, FitConfig(photo_rounds=0, **cfg))


def test_exact_landmarks_recover_pose_and_shape():
    m, zs, ze, verts, K, R, t, Rn, tn, lm = _scene()
    # exact data: priors off (they would bias the exact solution; the head is 18 mm off the rig origin here);
    # the rig constraint is exact
    fit = _fit(m, K, Rn, tn, lm, w_shape=0.0, w_exp=0.0, head_sigma_mm=0.0, landmark_iters=800)
    assert fit.landmark_rmse_px.max() < 1e-3
    assert np.abs(fit.shape_coeffs / m.shape_sigma - zs).max() < 2e-3
    assert np.abs(fit.exp_coeffs / m.exp_sigma - ze).max() < 2e-3
    assert np.sqrt(((fit.vertices - verts) ** 2).sum(-1).mean()) < 0.02  # mm
    assert np.linalg.norm(fit.cam_centers - camera_centers(R, t), axis=-1).max() < 0.1  # mm
    assert np.allclose(fit.R, R, atol=1e-4)


def test_noisy_landmarks_reported_tolerance():
    # 1 px landmark noise: measured 0.44 mm vertex RMSE and 4–15 mm camera-centre error on this toy (depth along
    # each view is the weakest direction: 1 px on a ~120 px face is ~1 % of the 1.3 m distance)
    m, zs, ze, verts, K, R, t, Rn, tn, lm = _scene(noise=1.0, seed=5)
    fit = _fit(m, K, Rn, tn, lm)
    assert np.all(fit.landmark_rmse_px < 1.6) and np.all(fit.landmark_rmse_px > 0.6)  # ≈ noise level
    v_err = np.sqrt(((fit.vertices - verts) ** 2).sum(-1).mean())
    c_err = np.linalg.norm(fit.cam_centers - camera_centers(R, t), axis=-1)
    assert v_err < 1.0, v_err
    assert c_err.max() < 20.0, c_err


def test_rig_orientation_prior_ties_the_views_to_one_head_rotation():
    # an exactly known rig (a calibrated one): with the orientations tied to it every camera is the rig's camera
    # moved by one head pose, so the per-view aims no longer absorb landmark noise.  Measured on this toy (two noise
    # draws): the spread of the per-view rotation errors in the model frame 0.29° / 0.65° free, 0.016° / 0.032°
    # with σ = 0.05°; camera centres 8.1 → 7.7 mm RMS (the common head-pose error remains)
    from scipy.spatial.transform import Rotation

    for seed in (5, 6):
        m, zs, ze, verts, K, R, t, Rn, tn, lm = _scene(noise=1.0, seed=seed)
        free = _fit(m, K, Rn, tn, lm, rig_sigma_mm=3.0)
        tied = _fit(m, K, Rn, tn, lm, rig_R=Rn, rig_sigma_mm=3.0, rig_rot_sigma_deg=0.05)

        def spread(fit):  # R_true,vᵀ R_fit,v is the same rotation for every view when the views move as one
            rv = Rotation.from_matrix(np.einsum("vji,vjk->vik", R, fit.R)).as_rotvec()
            return np.degrees(np.linalg.norm(rv - rv.mean(0), axis=1)).max()

        assert spread(tied) < 0.1 and spread(tied) < 0.2 * spread(free), (spread(free), spread(tied))
        c_free = np.linalg.norm(free.cam_centers - camera_centers(R, t), axis=-1)
        c_tied = np.linalg.norm(tied.cam_centers - camera_centers(R, t), axis=-1)
        assert np.sqrt((c_tied ** 2).mean()) < np.sqrt((c_free ** 2).mean()) * 1.05, (c_free, c_tied)
        assert tied.landmark_rmse_px.max() < 1.7  # still fits the landmarks to their noise


def test_missing_landmarks_are_ignored_and_too_few_refused():
    m, zs, ze, verts, K, R, t, Rn, tn, lm = _scene()
    lm2 = lm.copy()
    lm2[0, :30] = np.nan  # a half-occluded side view
    fit = _fit(m, K, Rn, tn, lm2, w_shape=0.0, w_exp=0.0, head_sigma_mm=0.0, landmark_iters=800)
    assert np.sqrt(((fit.vertices - verts) ** 2).sum(-1).mean()) < 0.05
    lm2[1, 3:] = np.nan
    with pytest.raises(ReflectmmError, match="only 3 valid landmarks"):
        _fit(m, K, Rn, tn, lm2)


def test_vertex_normals_torch_matches_numpy():
    m = toy.toy_model()
    n_np = vertex_normals(m.mean, m.triangles, dtype=np.float64)
    n_t = vertex_normals_torch(torch.tensor(m.mean), torch.tensor(m.triangles)).numpy()
    assert np.allclose(n_np, n_t, atol=1e-12)
    front = m.mean[:, 2] > 40
    assert (n_np[front, 2] > 0).all()  # outward


# ----------------------------------------------------------------------------- photometric term

def _rendered(size=(200, 150)):
    m = toy.toy_model(n_shape=2, n_exp=1, texture=True)
    W, H = size
    K, R, t = toy.arc_cameras([-30, 0, 30], focal=1000.0 * H / 480, width=W, height=H)
    sh = np.zeros((9, 3))
    sh[0] = [1.2, 1.1, 1.0]
    sh[2] = [0.4, 0.4, 0.35]
    sh[3] = [0.3, 0.25, 0.2]
    sh[6] = [-0.1, -0.1, -0.1]
    imgs = np.stack([toy.render(m.mean, m.triangles, m.mean_tex, sh, K[v], R[v], t[v], W, H) for v in range(3)])
    return m, K, R, t, imgs, sh


def _photo(m, K, R, t, imgs, sh, verts=None):
    verts = m.mean if verts is None else verts
    d = torch.float64
    X = torch.tensor(verts, dtype=d)
    nrm = vertex_normals_torch(X, torch.tensor(m.triangles))
    front = np.nonzero(vertex_normals(verts, m.triangles)[:, 2] > 0.6)[0]
    vis = np.ones((3, len(front)))
    loss, r = photometric_loss(X, nrm, torch.tensor(front), torch.tensor(vis, dtype=d), torch.tensor(K, dtype=d),
                               torch.tensor(R, dtype=d), torch.tensor(t, dtype=d),
                               torch.tensor(imgs.transpose(0, 3, 1, 2).copy(), dtype=d),
                               torch.tensor(m.mean_tex[front], dtype=d), torch.tensor(np.repeat(sh[None], 3, 0),
                                                                                     dtype=d),
                               sh_kernel(d), scale=0.3, eps=1e-3)
    return float(loss), r.numpy()


def test_photometric_residual_vanishes_at_truth_and_grows_off_pose():
    m, K, R, t, imgs, sh = _rendered()
    l0, r0 = _photo(m, K, R, t, imgs, sh)
    # at the true pose the only residual is bilinear interpolation of the ray-traced image
    assert np.median(np.abs(r0)) < 0.01
    for dx in (2.0, 4.0):  # mm sideways ≈ 1 and 2 px at this scale
        shift = np.array([dx, 0.0, 0.0])
        l1, _ = _photo(m, K, R, t + shift, imgs, sh)
        assert l1 > l0 * 1.3, (dx, l0, l1)
    Rrot = R @ toy.rotvec_matrix([0.0, 0.06, 0.0])  # the face front moves ≈ 4 mm
    assert _photo(m, K, Rrot, t, imgs, sh)[0] > l0 * 1.3


def test_photometric_gradient_matches_finite_differences():
    m, K, R, t, imgs, sh = _rendered(size=(120, 90))
    d = torch.float64
    front = torch.tensor(np.nonzero(vertex_normals(m.mean, m.triangles)[:, 2] > 0.6)[0][::7])
    tri = torch.tensor(m.triangles)
    imgs_t = torch.tensor(imgs.transpose(0, 3, 1, 2).copy(), dtype=d)
    alb = torch.tensor(m.mean_tex[front.numpy()], dtype=d)
    L = torch.tensor(np.repeat(sh[None], 3, 0), dtype=d)
    Kt, Rt = torch.tensor(K, dtype=d), torch.tensor(R, dtype=d)
    vis = torch.ones(3, len(front), dtype=d)
    base = torch.tensor(m.mean, dtype=d)
    dirs = torch.tensor(np.random.default_rng(0).normal(size=(2, len(base), 3)), dtype=d)

    def f(params):
        X = base + params[0] * dirs[0] + params[1] * dirs[1]
        tt = torch.tensor(t, dtype=d) + params[2:5]
        return photometric_loss(X, vertex_normals_torch(X, tri), front, vis, Kt, Rt, tt, imgs_t, alb, L,
                                sh_kernel(d), scale=0.3, eps=0.02)[0]

    p = torch.tensor([0.1, -0.05, 0.3, -0.2, 0.5], dtype=d, requires_grad=True)
    (g,) = torch.autograd.grad(f(p), p)
    h = 1e-6
    fd = []
    with torch.no_grad():
        for k in range(5):
            e = torch.zeros(5, dtype=d)
            e[k] = h
            fd.append((f(p + e) - f(p - e)) / (2 * h))
    fd = torch.stack(fd)
    assert torch.allclose(g, fd, rtol=1e-4, atol=1e-7), (g, fd)
    assert g.abs().max() > 1e-4  # the term does depend on the geometry


def test_photometric_stage_improves_a_noisy_landmark_fit():
    # textured toy face, 4 views rendered by the independent ray tracer, 2 px landmark noise: the photometric
    # rounds (model texture as albedo) must pull the geometry towards the truth.  Measured: 2.27 mm vertex RMSE
    # with landmarks only, 1.11 mm with the default photometric weight.
    az = [-45, -15, 15, 45]
    m = toy.toy_model(n_shape=6, n_exp=2, texture=True)
    rng = np.random.default_rng(1)
    zs = rng.normal(size=m.n_shape) * 0.8
    ze = rng.normal(size=m.n_exp) * 0.5
    verts = m.vertices(zs * m.shape_sigma, ze * m.exp_sigma)
    W, H = 320, 240
    K, R, t = toy.arc_cameras(az, focal=1000 * H / 480, width=W, height=H)
    sh = np.zeros((9, 3))
    sh[0] = [1.2, 1.1, 1.0]
    sh[1] = [0.2, 0.2, 0.2]
    sh[2] = [0.5, 0.5, 0.45]
    sh[3] = [0.4, 0.3, 0.3]
    imgs = np.stack([toy.render(verts, m.triangles, m.mean_tex, sh, K[v], R[v], t[v], W, H)
                     for v in range(len(az))]).astype(np.float32)
    lm = np.stack([project(verts[m.landmarks], K[v], R[v], t[v])[0] for v in range(len(az))])
    lm = lm + rng.normal(size=lm.shape) * 2.0
    R0, t0, _ = initial_poses(m.mean[m.landmarks], lm, K, R, t)
    vs = ViewSet(names=[str(a) for a in az], K=K, R0=R0, t0=t0, landmarks=lm, image_size=(W, H), images=imgs,
                 rig_centers=camera_centers(R, t))

    def err(fit):
        return np.sqrt(((fit.vertices - verts) ** 2).sum(-1).mean())

    lm_only = fit_geometry(m, vs, FitConfig(landmark_sigma_px=2.0, photo_rounds=0))
    photo = fit_geometry(m, vs, FitConfig(landmark_sigma_px=2.0))
    assert np.all(np.isnan(lm_only.photo_residual))
    assert np.all(photo.photo_residual < 0.01) and np.all(photo.visible_count > 100)
    assert err(photo) < 0.7 * err(lm_only), (err(photo), err(lm_only))


def test_zero_group_weight_equals_leaving_the_group_out():
    """--landmark-weights jaw=0: jaw points pushed 25 px outwards (a detector's jaw on the silhouette) change
    nothing; the fit equals the one with the jaw points missing, and with their default weight the push shows."""
    from reflectmm_cli.geometry_fit.landmarks import GROUPS

    m, zs, ze, verts, K, R, t, Rn, tn, lm = _scene()
    a, b = GROUPS["jaw"]
    pushed = lm.copy()
    centre = lm[:, 27:68].mean(1, keepdims=True)
    out = pushed[:, a:b] - centre
    pushed[:, a:b] = centre + out * (1 + 25.0 / np.linalg.norm(out, axis=-1, keepdims=True))
    missing = lm.copy()
    missing[:, a:b] = np.nan
    off = _fit(m, K, Rn, tn, pushed, group_weights={"jaw": 0.0})
    gone = _fit(m, K, Rn, tn, missing)
    kept = _fit(m, K, Rn, tn, pushed)
    # (the two start from slightly different poses: the initial pose uses every point; optimiser tolerance)
    np.testing.assert_allclose(off.vertices, gone.vertices, atol=0.01)
    np.testing.assert_allclose(off.cam_centers, gone.cam_centers, atol=0.05)
    err = lambda f: np.sqrt(((f.vertices - verts) ** 2).sum(-1).mean())  # noqa: E731
    assert err(kept) > 3 * err(off), (err(kept), err(off))
    # the reported landmark RMS is over the points the fit weighs: the pushed jaw is not in it
    np.testing.assert_allclose(off.landmark_rmse_px, gone.landmark_rmse_px, atol=0.05)
    assert np.all(off.landmark_rmse_px < 5.0) and np.all(kept.landmark_rmse_px > off.landmark_rmse_px)


def test_parse_group_weights():
    from reflectmm_cli.geometry_fit.landmarks import GROUPS, landmark_weights, parse_group_weights

    assert parse_group_weights(["jaw=0", "eyes=2.5,brows=1"]) == {"jaw": 0.0, "eyes": 2.5, "brows": 1.0}
    assert parse_group_weights({"jaw": 0}) == {"jaw": 0.0}
    assert parse_group_weights("jaw=0") == {"jaw": 0.0}
    w = landmark_weights(parse_group_weights(["jaw=0"]))
    assert (w[:17] == 0).all() and (w[17:] > 0).all()
    for bad, msg in (("chin=0", "unknown group 'chin'"), ("jaw", "expected GROUP=WEIGHT"),
                     ("jaw=-1", "must be a finite number ≥ 0"), ("jaw=x", "must be a finite number ≥ 0"),
                     ("jaw=nan", "must be a finite number ≥ 0"), ("jaw=inf", "must be a finite number ≥ 0"),
                     ("jaw=0,jaw=1", "group jaw is given twice"),
                     (",".join(f"{g}=0" for g in GROUPS), "every landmark has weight 0")):
        with pytest.raises(ReflectmmError, match=msg):
            parse_group_weights([bad])

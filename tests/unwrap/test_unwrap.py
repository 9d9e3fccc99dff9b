import math

import numpy as np
import pytest

from _sphere_scene import RADIUS, make_scene, quad, seg_hits_quad, shading
from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.observations.unwrap import bilinear

QUANT = 2 * 1.2 * 0.5 / 255  # flash and room shot each within half an 8-bit step of x**(1/1.2)


def _pipeline(cli, tmp_path, scene, *extra, uv=64):
    root, ws = tmp_path / "mp", tmp_path / "ws"
    res = cli("preprocess-multipie", "--root", root, "--id", "001", "--views", ",".join(scene["views"]),
              "--flashes", ",".join(scene["flashes"]), "--workspace", ws)
    assert res.exit_code == 0, res.stderr
    res = cli("unwrap-uv", "--id", "001", "--uv-size", uv, "--face-model", scene["face_model_path"],
              "--workspace", ws, *extra)
    assert res.exit_code == 0, res.stderr
    out = ws / "unwrap-uv" / "001.npz"
    assert res.stdout.split() == [str(out), str(ws / "unwrap-uv" / "001_preview.png")]
    return read_artifact(out, "uv-observations")


def _truth(obs, geo, p):
    """Exact shading of the sphere point each observed texel's projection sees (ray–sphere intersection)."""
    vi, fi = int(obs["pair_view"][p]), int(obs["pair_flash"][p])
    ob = obs["observed"][p]
    x = obs["position"][ob].astype(np.float64)
    c = geo["cam_centers"][vi]
    d = x - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ c
    t = -b - np.sqrt(b * b - (c @ c - RADIUS ** 2))
    xs = c + t[:, None] * d
    return ob, shading(xs, xs / RADIUS, c, geo["flash_pos"][fi], geo["flash_intensity"][fi])


def test_unwrapped_radiance_equals_shading(tmp_path, cli):
    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    obs = _pipeline(cli, tmp_path, scene)
    S, V, F = 64, 2, 2
    P = V * F
    assert obs["radiance"].shape == (P, S, S, 3) and obs["radiance"].dtype == np.float16
    assert obs["observed"].shape == (P, S, S) and obs["visible"].shape == (V, S, S) and obs["lit"].shape == (F, S, S)
    assert obs["position"].shape == (S, S, 3) and obs["mask"].dtype == bool
    assert obs["pair_view"].tolist() == [0, 0, 1, 1] and obs["pair_flash"].tolist() == [0, 1, 0, 1]
    assert obs["conditioning"].shape == (S, S) and obs["conditioning_exponents"].tolist() == [1, 8, 64]
    np.testing.assert_array_equal(obs["obs_count"], obs["observed"].sum(0))
    from reflectmm_cli.reflectance.design import conditioning

    ref = conditioning(obs["position"], obs["normal"], obs["cam_centers"], obs["flash_pos"], obs["flash_intensity"],
                       obs["pair_view"], obs["pair_flash"], obs["observed"], (1, 8, 64), mask=obs["mask"])
    np.testing.assert_allclose(obs["conditioning"], ref.conditioning, rtol=1e-6, atol=1e-12)  # threaded = serial
    np.testing.assert_allclose(obs["observability"], ref.observability, rtol=1e-6, atol=1e-12)
    assert (obs["conditioning"][obs["obs_count"] < 4] < 1e-6).all() and (obs["conditioning"] > 1e-3).any()
    np.testing.assert_allclose(np.linalg.norm(obs["normal"][obs["mask"]], axis=-1), 1, atol=1e-5)
    # positions lie on the cap (chords are at most the sag below the sphere)
    r = np.linalg.norm(obs["position"][obs["mask"]], axis=-1)
    assert np.all(r <= RADIUS + 1e-3) and np.all(r > RADIUS - 0.2)
    assert not obs["radiance"][~obs["observed"]].any()
    geo = scene["geometry"]
    n_obs = 0
    for p in range(P):
        ob, want = _truth(obs, geo, p)
        got = obs["radiance"][p][ob].astype(np.float64)
        err = np.abs(got - want)
        n_obs += ob.sum()
        assert err.max() < QUANT + 1.5e-3, (p, err.max())
        assert np.median(err) < 0.3 * QUANT
    assert n_obs > 0.8 * P * obs["mask"].sum()
    # the sphere is convex: lit = n·l > 0 (up to the mesh's facets near the terminator)
    for f in range(F):
        x = obs["position"][obs["mask"]].astype(np.float64)
        ndl = np.einsum("nk,nk->n", obs["normal"][obs["mask"]], geo["flash_pos"][f] - x)
        lit = obs["lit"][f][obs["mask"]]
        seen = obs["visible"][:, obs["mask"]].any(0)  # shadow rays are traced only for texels some view sees
        assert seen.mean() > 0.9
        assert not lit[ndl <= 0].any() and not lit[~seen].any()
        assert lit[(ndl > 0.02 * np.linalg.norm(geo["flash_pos"][f] - x, axis=1)) & seen].all()


def test_occluder_visibility_and_shadow(tmp_path, cli):
    # a 14 mm square floating 25 mm above the cap, facing the raised flash "14"
    flash = np.array([250.0, 180.0, 300.0])
    top = np.array([0.0, 0.0, RADIUS])
    d = (flash - top) / np.linalg.norm(flash - top)
    occ = quad(top + 25 * d, d, 14.0)
    scene = make_scene(tmp_path / "mp", tmp_path / "ws", occluder=occ)
    obs = _pipeline(cli, tmp_path, scene, "--edge-margin", 0)  # the footprint test alone (the margin: below)
    geo = scene["geometry"]
    m = obs["mask"]
    x = obs["position"][m].astype(np.float64)
    n = obs["normal"][m].astype(np.float64)
    for fi in range(2):
        fpos = geo["flash_pos"][fi]
        want = (np.einsum("nk,nk->n", n, fpos - x) > 0) & ~seg_hits_quad(x, fpos, occ[0])
        got = obs["lit"][fi][m]
        seen = obs["visible"][:, m].any(0)
        mism = (got != want) & seen
        assert mism.sum() <= 0.01 * seen.sum(), (fi, mism.sum())
        if fi == 1:
            assert (~want & seen & (np.einsum("nk,nk->n", n, fpos - x) > 0)).sum() > 50  # a real cast shadow
    for vi in range(2):
        c = geo["cam_centers"][vi]
        v = c - x
        ndv = np.einsum("nk,nk->n", n, v) / np.linalg.norm(v, axis=1)
        want = (ndv > math.cos(math.radians(80))) & ~seg_hits_quad(x, c, occ[0])
        got = obs["visible"][vi][m]
        assert (got & ~want).sum() <= 0.005 * m.sum()  # never visible where the analytic test says hidden
        # hidden in addition: texels whose bilinear footprint leaves the mesh (cap border) or crosses the
        # occluder's outline (depth test of the four taps)
        assert (want & ~got).sum() <= 0.08 * m.sum()
        assert (~seg_hits_quad(x, c, occ[0])).sum() < m.sum() - 50  # the occluder hides texels from this view
    # observed radiance still equals the shading away from the occluder's outline
    for p in range(4):
        ob, want = _truth(obs, geo, p)
        err = np.abs(obs["radiance"][p][ob].astype(np.float64) - want)
        assert np.median(err) < 0.3 * QUANT
        assert np.mean(err > QUANT + 1.5e-3) < 0.02


def test_grazing_cutoff_and_saturation(tmp_path, cli):
    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    obs = _pipeline(cli, tmp_path, scene, "--grazing-deg", "30")
    geo = scene["geometry"]
    for p in range(4):
        vi = obs["pair_view"][p]
        ob = obs["observed"][p]
        x = obs["position"][ob].astype(np.float64)
        v = geo["cam_centers"][vi] - x
        ndv = np.einsum("nk,nk->n", obs["normal"][ob], v) / np.linalg.norm(v, axis=1)
        assert ndv.min() > math.cos(math.radians(30)) - 1e-6
    assert obs.params["grazing_deg"] == 30


def test_saturated_pixels_are_not_observed(tmp_path, cli):
    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    # brighten the frontal flash shot of the frontal view so its highlight clips
    import cv2
    png = tmp_path / "mp/data/session01/multiview/001/01/05_1/001_01_01_051_07.png"
    img = cv2.imread(str(png))
    img = np.clip(img.astype(np.int32) + 60, 0, 255).astype(np.uint8)
    cv2.imwrite(str(png), img)
    obs = _pipeline(cli, tmp_path, scene)
    sat = obs["saturated"][0]
    assert sat.sum() > 20
    assert not (obs["observed"][0] & sat).any()
    assert not obs["saturated"][3].any()


def test_mismatched_geometry_errors(tmp_path, cli):
    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    root, ws = tmp_path / "mp", tmp_path / "ws"
    assert cli("preprocess-multipie", "--root", root, "--id", "001", "--views", "05_1,14_0", "--flashes", "07,14",
               "--workspace", ws).exit_code == 0
    g = dict(scene["geometry"])
    g["view_names"] = np.array(["05_1", "13_0"])
    bad = write_artifact(tmp_path / "bad_geo.npz", "geometry", g)
    res = cli("unwrap-uv", "--id", "001", "--geometry", bad, "--face-model", scene["face_model_path"],
              "--workspace", ws)
    assert res.exit_code == 1 and "bad_geo.npz" in res.stderr and "view 14_0" in res.stderr
    res = cli("unwrap-uv", "--id", "002", "--face-model", scene["face_model_path"], "--workspace", ws)
    assert res.exit_code == 1 and "002.npz" in res.stderr and "capture" in res.stderr
    res = cli("unwrap-uv", "--id", "001", "--geometry", scene["face_model_path"],
              "--face-model", scene["face_model_path"], "--workspace", ws)
    assert res.exit_code == 1 and "expected a 'geometry' artifact" in res.stderr


def test_views_named_twice_and_a_face_model_of_another_order_are_refused(tmp_path, cli):
    # a view or flash named twice counted twice in the reflectance fit; a face model with the geometry's vertex
    # count but its vertices in another order unwrapped a scrambled face; both with exit 0
    from reflectmm_cli.geometry import load_face_model

    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    root, ws = tmp_path / "mp", tmp_path / "ws"
    assert cli("preprocess-multipie", "--root", root, "--id", "001", "--views", "05_1,14_0", "--flashes", "07,14",
               "--workspace", ws).exit_code == 0
    out = ws / "unwrap-uv" / "001.npz"
    fm = scene["face_model_path"]
    for extra, msg in ((["--views", "05_1,05_1"], "--views: 05_1 named more than once"),
                       (["--flashes", "07,14,07"], "--flashes: 07 named more than once"),
                       (["--views", "trusted,05_1"], "stand alone, not in a list of names")):
        res = cli("unwrap-uv", "--id", "001", "--face-model", fm, "--workspace", ws, *extra)
        assert res.exit_code == 1 and msg in res.stderr and not out.exists(), res.stderr
    geo = dict(scene["geometry"])
    model = load_face_model(fm)
    assert "shape_coeffs" in geo and np.abs(model.vertices(geo["shape_coeffs"]) - geo["vertices"]).max() < 1e-3
    perm = np.random.default_rng(0).permutation(len(model.mean_shape))
    z = dict(np.load(fm))
    for k in ("mean_shape", "uv"):
        z[k] = z[k][perm]
    z["shape_basis"] = z["shape_basis"][:, perm] if "shape_basis" in z else z.get("shape_basis")
    np.savez(tmp_path / "permuted.npz", **{k: v for k, v in z.items() if v is not None})
    res = cli("unwrap-uv", "--id", "001", "--face-model", tmp_path / "permuted.npz", "--workspace", ws)
    assert res.exit_code == 1 and not out.exists(), res.stderr
    assert "permuted.npz" in res.stderr and "not the face model it was fitted with" in res.stderr
    res = cli("unwrap-uv", "--id", "001", "--face-model", fm, "--workspace", ws)
    assert res.exit_code == 0, res.stderr


def test_bilinear_matches_cv2_remap():
    import cv2

    rng = np.random.default_rng(1)
    img = rng.random((2, 9, 11, 3)).astype(np.float32)
    uv = np.stack([rng.uniform(-1, 11, 300), rng.uniform(-1, 9, 300)], 1)
    val, inside, _ = bilinear(img, uv)
    assert inside.sum() > 100 and (~inside).sum() > 10
    for f in range(2):
        ref = cv2.remap(img[f], uv[:, 0].astype(np.float32).reshape(1, -1), uv[:, 1].astype(np.float32).reshape(1, -1),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        np.testing.assert_allclose(val[f][inside], ref[inside], atol=2e-3)  # cv2 uses 5-bit fractional weights
        assert not val[f][~inside].any()


def test_project_matches_closed_form():
    K = np.array([[500.0, 0.0, 10.0], [0, 400.0, 20.0], [0, 0, 1]])
    R = np.eye(3)
    t = np.array([0.0, 0.0, 100.0])
    uv, Z = project(np.array([[10.0, -5.0, 0.0]]), K, R, t)
    np.testing.assert_allclose(uv[0], [500 * 0.1 + 10, 400 * -0.05 + 20])
    assert Z[0] == 100.0


def test_project_matches_geometry_camera_random():
    from scipy.spatial.transform import Rotation

    from reflectmm_cli.geometry import Camera

    rng = np.random.default_rng(4)
    for _ in range(20):
        R = Rotation.random(random_state=rng).as_matrix()
        t = rng.normal(0, 50, 3)
        K = np.array([[rng.uniform(300, 2000), rng.uniform(-2, 2), rng.uniform(100, 500)],
                      [0, rng.uniform(300, 2000), rng.uniform(100, 400)], [0, 0, 1]])
        cam = Camera(K, R, t, 640, 480)
        x_cam = rng.normal(0, 80, (50, 3)) + np.array([0, 0, 800.0])  # in front of the camera
        pts = (x_cam - t) @ R  # model space: Rᵀ (x_cam − t)
        uv, Z = project(pts, K, R, t)
        uv2, Z2 = cam.project(pts)
        np.testing.assert_allclose(uv, uv2, rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(Z, Z2, rtol=1e-12)


def test_bilinear_saturation_any_of_four():
    img = np.ones((1, 4, 4, 3), np.float32)
    sat = np.zeros((1, 4, 4), bool)
    sat[0, 2, 2] = True
    uv = np.array([[1.5, 1.5], [2.0, 2.0], [0.5, 0.5], [2.9, 1.0]])
    _, inside, s = bilinear(img, uv, sat)
    assert inside.all()
    # taps: (1..2,1..2) touches (2,2); (2..3,2..3) touches; (0..1,0..1) does not; (2..3, 1..2) touches (2,2)
    assert s[0].tolist() == [True, True, False, True]


def _bad_pixels(geo, vi, occ, H, W, crop):
    """(H, W) bool, independent of the unwrapper's rays: the pixel centre's ray misses the cap (analytic sphere
    outside the cap's square) or the occluder hides the point it hits."""
    K, R, c = geo["K"][vi], geo["R"][vi], geo["cam_centers"][vi]
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    px = np.stack([xs + crop[0], ys + crop[1], np.ones_like(xs)], -1).reshape(-1, 3)
    d = (px @ np.linalg.inv(K).T) @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ c
    disc = b * b - (c @ c - RADIUS ** 2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.nan)
    x = c + np.nan_to_num(t)[:, None] * d
    on_cap = (disc > 0) & (np.abs(x[:, 0]) <= 0.65 * RADIUS) & (np.abs(x[:, 1]) <= 0.65 * RADIUS)
    return (~on_cap | seg_hits_quad(x, c, occ[0])).reshape(H, W)


def test_edge_margin_keeps_samples_away_from_borders_and_outlines(tmp_path, cli):
    """--edge-margin m: no seen texel has a pixel that misses the cap or sees the occluder within m pixels of its
    bilinear taps (checked against analytic rays), the texels far from every edge stay seen, and the margin only
    removes texels."""
    flash = np.array([250.0, 180.0, 300.0])
    top = np.array([0.0, 0.0, RADIUS])
    d = (flash - top) / np.linalg.norm(flash - top)
    occ = quad(top + 25 * d, d, 14.0)
    scene = make_scene(tmp_path / "mp", tmp_path / "ws", occluder=occ)
    base = _pipeline(cli, tmp_path, scene, "--edge-margin", 0)
    assert base.meta["report"]["edge_rejected"] == 0
    m = 2
    obs = _pipeline(cli, tmp_path, scene, "--edge-margin", m)
    assert obs.params["edge_margin"] == m and obs.meta["report"]["edge_rejected"] > 0
    assert not (obs["visible"] & ~base["visible"]).any()
    cap = read_artifact(tmp_path / "ws" / "preprocess-multipie" / "001.npz", "capture")
    H, W = cap["olat"].shape[2:4]
    geo = scene["geometry"]
    mask = obs["mask"]
    x = obs["position"][mask].astype(np.float64)
    for vi in range(2):
        crop = cap["crop_origin"][vi]
        bad = _bad_pixels(geo, vi, occ, H, W, crop)
        # Chebyshev distance of every pixel to the nearest bad pixel
        from scipy.ndimage import distance_transform_cdt
        dist = distance_transform_cdt(~bad, metric="chessboard")
        pix, _ = project(x, geo["K"][vi], geo["R"][vi], geo["t"][vi])
        pix -= crop
        x0 = np.clip(np.floor(pix[:, 0]).astype(int), 0, W - 2)
        y0 = np.clip(np.floor(pix[:, 1]).astype(int), 0, H - 2)
        near = np.min([dist[y0 + j, x0 + i] for j in (0, 1) for i in (0, 1)], axis=0)  # taps to nearest bad
        seen = obs["visible"][vi][mask]
        seen0 = base["visible"][vi][mask]
        assert seen.sum() > 0.5 * seen0.sum()
        # the window of the taps dilated by m holds no bad pixel (a facet of the mesh may differ from the sphere
        # by a fraction of a pixel along the cap's border)
        assert np.mean(near[seen] <= m) < 0.003, (vi, np.mean(near[seen] <= m))
        assert (near[seen] >= m).all()
        # far from every edge the margin changes nothing
        far = near > m + 1
        assert (seen[far] == seen0[far]).mean() > 0.997

"""Relighting against held-out OLAT images rendered independently (render_point_light with its own shadow rays)."""
import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.figures import grid
from reflectmm_cli.evaluation.relighting import RelightScene, relight, relighting_metrics, relighting_rows
from reflectmm_cli.geometry import RayScene, has_embree, look_at, procedural_face_model, render_point_light

pytestmark = pytest.mark.skipif(not has_embree(), reason="needs embreex")

FLASHES = ["07", "05", "11"]
POS = np.array([[0.0, 50.0, 900.0], [350.0, 80.0, 700.0], [-450.0, 0.0, 500.0]])
INTENSITY = np.full(3, 2.0 * 900.0 ** 2)


@pytest.fixture(scope="module")
def identity():
    fm = procedural_face_model(n_vertices=3000)
    v = fm.mean_shape.astype(np.float64)
    cam = look_at((60.0, 20.0, 650.0), (0.0, 10.0, 0.0), focal_px=200.0, width=64, height=64)
    x = (v - v.min(0)) / np.ptp(v, 0)
    albedo = np.stack([0.5 + 0.2 * x[:, 0], 0.35 + 0.1 * x[:, 1], 0.25 + 0.05 * x[:, 2]], 1)
    weights = np.stack([0.02 + 0.01 * x[:, 1], 0.03 + 0.02 * x[:, 0], 0.01 * x[:, 2]], 1)
    scene = RayScene(v, fm.triangles)
    targets = {}
    for f, p, i in zip(FLASHES, POS, INTENSITY):
        targets[f] = render_point_light(scene, cam, albedo, weights, [1.0, 8.0, 64.0], p, i, shadows=True).image
    rs = RelightScene(v, fm.triangles, cam, POS, INTENSITY, FLASHES)
    return rs, albedo, weights, targets, fm, cam


def test_truth_relights_exactly_and_region_is_the_lit_face(identity):
    rs, albedo, weights, targets, fm, cam = identity
    out = relight(rs, albedo, weights, [1.0, 8.0, 64.0], FLASHES)
    m = relighting_metrics(rs, out, targets, scale="none")
    assert m["psnr"] == 100.0 and m["ssim"] == pytest.approx(1.0)
    for f, p, i in zip(FLASHES, POS, INTENSITY):
        ref = render_point_light(RayScene(fm.mean_shape.astype(np.float64), fm.triangles), cam, albedo, weights,
                                 [1.0, 8.0, 64.0], p, i, shadows=True)
        assert np.array_equal(rs.region(f), ref.lit & ref.mask)
        assert np.allclose(out[f]["diffuse"] + out[f]["specular"], out[f]["full"])
        assert np.all(out[f]["specular"][rs.region(f)].sum(-1) > 0)
    assert rs.region("05").sum() < rs.mask.sum()  # a side flash leaves part of the face in shadow


def test_global_scale_removes_a_brightness_error_but_not_a_missing_specular(identity):
    rs, albedo, weights, targets, _, _ = identity
    bright = relight(rs, 1.5 * albedo, 1.5 * weights, [1.0, 8.0, 64.0], FLASHES)
    raw = relighting_metrics(rs, bright, targets, scale="none")
    sc = relighting_metrics(rs, bright, targets, scale="global")
    assert raw["psnr"] < 30 and sc["psnr"] == 100.0 and sc["scale"] == pytest.approx(1 / 1.5, rel=1e-6)
    diffuse_only = relight(rs, albedo, np.zeros((len(albedo), 1)), [1.0], FLASHES)
    d = relighting_metrics(rs, diffuse_only, targets)
    assert d["psnr"] < 60 and np.all([np.all(v["specular"] == 0) for v in diffuse_only.values()])


def test_unknown_flash_position_perturbed_rig(identity):
    """The user's flash position is 15 mm off: relighting still scores high but not perfectly."""
    rs, albedo, weights, targets, fm, cam = identity
    rs2 = RelightScene(fm.mean_shape, fm.triangles, cam, POS + np.array([15.0, -10.0, 5.0]), INTENSITY, FLASHES)
    m = relighting_metrics(rs2, relight(rs2, albedo, weights, [1.0, 8.0, 64.0], FLASHES), targets)
    assert 30 < m["psnr"] < 100


def test_errors_and_figure(identity):
    rs, albedo, weights, targets, _, _ = identity
    out = relight(rs, albedo, weights, [1.0, 8.0, 64.0], ["07"])
    with pytest.raises(ReflectmmError, match="no captured OLAT image for flash '07'"):
        relighting_metrics(rs, out, {})
    with pytest.raises(ReflectmmError, match="flash '99'"):
        rs.region("99")
    rows = relighting_rows(rs, np.full((64, 64, 3), 0.3), {"truth": out}, targets, "07")
    assert len(rows) == 2 and len(rows[1]) == 5
    assert grid(rows).shape == (2 * 66 + 2, 5 * 66 + 2, 3)


def test_scene_from_capture_and_geometry_artifacts_crops_the_window(identity):
    from reflectmm_cli.evaluation.relighting import capture_targets, scene_from_artifacts

    rs, albedo, weights, targets, fm, cam = identity
    x0, y0, w, h = 10, 6, 40, 50
    olat = np.stack([targets[f][y0:y0 + h, x0:x0 + w] for f in FLASHES])[None]
    capture = {"view_names": np.array(["05_1"]), "flash_ids": np.array(FLASHES), "crop_origin": np.array([[x0, y0]]),
               "olat": olat, "saturated": np.zeros(olat.shape[:4], bool)}
    geometry = {"vertices": fm.mean_shape, "view_names": np.array(["05_1"]), "K": cam.K[None], "R": cam.R[None],
                "t": cam.t[None], "flash_ids": np.array(FLASHES), "flash_pos": POS, "flash_intensity": INTENSITY}
    sc = scene_from_artifacts(capture, geometry, fm.triangles, "05_1")
    tg = capture_targets(capture, "05_1", ["05", "11"])
    assert np.array_equal(sc.region("05"), rs.region("05")[y0:y0 + h, x0:x0 + w])
    m = relighting_metrics(sc, relight(sc, albedo, weights, [1.0, 8.0, 64.0], ["05", "11"]), tg, scale="none")
    assert m["psnr"] == 100.0
    with pytest.raises(ReflectmmError, match="view '04_1'"):
        scene_from_artifacts(capture, geometry, fm.triangles, "04_1")
    with pytest.raises(ReflectmmError, match="flash '03'"):
        capture_targets(capture, "05_1", ["03"])


def test_uv_maps_render_like_per_vertex_values(identity):
    """Constant UV maps and the same constants per vertex give the same relit images."""
    rs, albedo, weights, targets, fm, cam = identity
    rs_uv = RelightScene(fm.mean_shape, fm.triangles, cam, POS, INTENSITY, FLASHES, uv=fm.uv)
    c, w = np.array([0.5, 0.4, 0.3]), np.array([0.02, 0.03, 0.01])
    maps = relight(rs_uv, np.ones((3, 16, 16)) * c[:, None, None], np.ones((3, 16, 16)) * w[:, None, None],
                   [1.0, 8.0, 64.0], ["07"])
    vert = relight(rs, np.tile(c, (len(albedo), 1)), np.tile(w, (len(albedo), 1)), [1.0, 8.0, 64.0], ["07"])
    assert np.allclose(maps["07"]["full"], vert["07"]["full"], rtol=1e-5, atol=1e-7)

"""Rig table: geometry of the default Multi-PIE-like rig, round trip, validation errors."""
import math

import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.rig import (
    ARC_CAMERAS, DEFAULT_FLASHES, DEFAULT_VIEWS, build_default_rig, default_rig_path, load_rig, rig_to_toml, save_rig,
)


@pytest.fixture(scope="module")
def rig():
    return load_rig()


def test_packaged_default_equals_builder(rig):
    assert default_rig_path().is_file()
    ref = build_default_rig()
    assert rig.camera_names == ref.camera_names and rig.flash_ids == ref.flash_ids
    for a, b in zip(rig.cameras, ref.cameras):
        np.testing.assert_allclose(a.position, b.position, atol=1e-5)
    for a, b in zip(rig.flashes, ref.flashes):
        np.testing.assert_allclose(a.position, b.position, atol=1e-5)
        assert a.intensity == pytest.approx(b.intensity) and a.camera == b.camera


def test_arc_cameras_15_degrees_apart_at_head_height(rig):
    pos = np.stack([rig.camera(c).position for c in ARC_CAMERAS])
    assert np.allclose(pos[:, 1], 0.0)
    r = np.linalg.norm(pos, axis=1)
    assert np.allclose(r, r[0]) and 1000 <= r[0] <= 1600
    u = pos / r[:, None]
    ang = np.degrees(np.arccos(np.clip((u[1:] * u[:-1]).sum(1), -1, 1)))
    np.testing.assert_allclose(ang, 15.0, atol=1e-9)
    # frontal camera on +z, arc sweeps from -x (subject's right) to +x
    np.testing.assert_allclose(u[ARC_CAMERAS.index("05_1")], [0, 0, 1], atol=1e-12)
    assert np.all(np.diff(np.arctan2(u[:, 0], u[:, 2])) > 0)
    assert set(DEFAULT_VIEWS) <= set(ARC_CAMERAS)


def test_raised_cameras_are_above_the_head(rig):
    for name, partner in (("08_1", "08_0"), ("19_1", "19_0")):
        c = rig.camera(name).position
        assert c[1] > 300
        az = math.atan2(c[0], c[2])
        p = rig.camera(partner).position
        assert az == pytest.approx(math.atan2(p[0], p[2]), abs=1e-9)


def test_cameras_look_at_the_head_with_y_up(rig):
    for cam in rig.cameras:
        R = cam.R
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # optical axis points from the centre to the origin; origin projects to the principal point
        np.testing.assert_allclose(R[2], -cam.position / np.linalg.norm(cam.position), atol=1e-12)
        np.testing.assert_allclose(cam.project(np.zeros(3)), [cam.K[0, 2], cam.K[1, 2]], atol=1e-9)
        np.testing.assert_allclose(cam.center, -R.T @ cam.t, atol=1e-9)
        # a point above the head appears above the image centre (image y down)
        assert cam.project(np.array([0.0, 100.0, 0.0]))[1] < cam.K[1, 2]


def test_face_fills_about_a_third_of_the_image_height(rig):
    cam = rig.camera("05_1")
    top, chin = cam.project(np.array([[0, 110.0, 90.0], [0, -90.0, 90.0]]))
    frac = (chin[1] - top[1]) / cam.height
    assert 0.25 <= frac <= 0.45


def test_flash_attachment(rig):
    for i, name in enumerate(ARC_CAMERAS):
        f = rig.flash(f"{i + 1:02d}")
        assert f.camera == name
        np.testing.assert_array_equal(f.position, rig.camera(name).position)
    assert rig.flash("14").camera == "08_1" and rig.flash("18").camera == "19_1"
    for fid in ("15", "16", "17"):
        f = rig.flash(fid)
        assert f.camera is None and f.position[1] > 500
        assert all(np.linalg.norm(f.position - c.position) > 100 for c in rig.cameras)
    # the default selection: 9 flashes at the 9 default views plus the two raised ones
    at = {rig.flash(f).camera for f in DEFAULT_FLASHES}
    assert at == set(DEFAULT_VIEWS) | {"08_1", "19_1"}
    # irradiance at the head is the same for every flash (stands are farther but brighter)
    E = [f.intensity / np.dot(f.position, f.position) for f in rig.flashes]
    np.testing.assert_allclose(E, E[0], rtol=1e-9)


def test_save_load_round_trip_and_resize(rig, tmp_path):
    p = save_rig(rig, tmp_path / "rig.toml", "a header\nline two")
    back = load_rig(p)
    assert rig_to_toml(back) == rig_to_toml(rig)
    small = rig.resized(160, 120)
    c0, c1 = rig.camera("09_0"), small.camera("09_0")
    x = np.array([30.0, 40.0, 80.0])
    np.testing.assert_allclose((c1.project(x) + 0.5) * 4, c0.project(x) + 0.5, atol=1e-9)


def _write(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


CAM = '[[camera]]\nname = "05_1"\nposition = [0.0, 0.0, 1300.0]\nfocal_px = 1000.0\nwidth = 640\nheight = 480\n'


@pytest.mark.parametrize("text, message", [
    (CAM + '[[flash]]\nid = "07"\ncamera = "99_9"\nintensity = 1.0\n', "unknown camera '99_9'"),
    (CAM.replace("1000.0", "-5.0"), "focal_px must be a finite number > 0"),
    (CAM.replace("[0.0, 0.0, 1300.0]", '"far"'), "position must be a list of 3"),
    (CAM.replace("width = 640", "width = 640.5"), "width must be an integer"),
    (CAM + CAM, "duplicate camera name '05_1'"),
    (CAM + '[[flash]]\nid = "7"\ncamera = "05_1"\nintensity = 1.0\n', "two-digit"),
    (CAM + '[[flash]]\nid = "07"\nintensity = 1.0\n', "exactly one of 'camera'"),
    (CAM + '[[flash]]\nid = "07"\ncamera = "05_1"\n', "missing intensity"),
    (CAM + '[[flash]]\nid = "07"\ncamera = "05_1"\nintensity = 0\n', "intensity must be"),
    (CAM.replace("position = [0.0, 0.0, 1300.0]", "position = [0.0, 0.0, 0.0]"), "look_at equals position"),
    (CAM + 'colour = 3\n', "unknown key"),
    ("[[camera]\n", "not valid TOML"),
    ("", "no [[camera]] entries"),
])
def test_validation_errors_name_file_and_problem(tmp_path, text, message):
    p = _write(tmp_path, text)
    with pytest.raises(ReflectmmError) as e:
        load_rig(p)
    assert message in str(e.value) and str(p) in str(e.value)


def test_missing_rig_file(tmp_path):
    with pytest.raises(ReflectmmError, match="rig table not found"):
        load_rig(tmp_path / "nope.toml")


def test_select_unknown_names(rig):
    with pytest.raises(ReflectmmError, match="no camera '77_7'"):
        rig.select(cameras=["05_1", "77_7"])
    sub = rig.select(cameras=["05_1"], flashes=["07", "16"])
    assert sub.camera_names == ["05_1"] and sub.flash_ids == ["07", "16"]

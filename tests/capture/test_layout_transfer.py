import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from _capture_tree import FLASHES, VIEWS, make_tree, shot_file
from reflectmm_cli.capture.images import encode_linear, read_codes, read_image, rotate_points, write_png
from reflectmm_cli.capture.layout import (camera_code, camera_name, discover_identities, plan_identity,
                                          resolve_session, sessions_of)
from reflectmm_cli.capture.transfer import parse_transfer
from reflectmm_cli.errors import ReflectmmError


@pytest.mark.parametrize("name,code", [("05_1", "051"), ("08_1", "081"), ("19_0", "190"), ("24_0", "240")])
def test_camera_name_mapping(name, code):
    assert camera_code(name) == code
    assert camera_name(code) == name


@pytest.mark.parametrize("bad", ["051", "5_1", "05-1", "05_10"])
def test_bad_camera_names(bad):
    with pytest.raises(ReflectmmError):
        camera_code(bad)


def test_layout_sessions_and_discovery(tmp_path):
    make_tree(tmp_path, ("002",), session="02", views=("05_1",), flashes=("07",))
    make_tree(tmp_path, ("002",), session="03", views=("05_1",), flashes=("07",))
    make_tree(tmp_path, ("001",), session="03", views=("05_1",), flashes=("07",))
    # identity 003 appears in session 01 only with a non-neutral recording
    make_tree(tmp_path, ("003",), session="01", rec="02", views=("05_1",), flashes=("07",))
    make_tree(tmp_path, ("003",), session="04", views=("05_1",), flashes=("07",))
    assert discover_identities(tmp_path) == ["001", "002", "003"]
    assert discover_identities(tmp_path / "data") == ["001", "002", "003"]
    assert sessions_of(tmp_path, "002") == ["02", "03"]
    assert resolve_session(tmp_path, "002") == "02"
    assert resolve_session(tmp_path, "003") == "04"  # first session holding recording 01
    assert resolve_session(tmp_path, "003", recording="02") == "01"
    with pytest.raises(ReflectmmError, match="not in session 01"):
        resolve_session(tmp_path, "002", "01")
    with pytest.raises(ReflectmmError, match="not found in any session"):
        resolve_session(tmp_path, "009")
    plan = plan_identity(tmp_path, "002", views=("05_1",), flashes=("07",))
    assert plan.session == "02"
    assert plan.images[0][0] == shot_file(tmp_path, "002", "05_1", "00", session="02")
    assert plan.images[0][1].name == "002_02_01_051_07.png"
    assert plan.landmarks[0].name == "002_02_01_051_00_lm.pts"


def test_not_a_root(tmp_path):
    with pytest.raises(ReflectmmError, match="no data/sessionNN"):
        discover_identities(tmp_path)
    with pytest.raises(ReflectmmError, match="not found"):
        discover_identities(tmp_path / "nope")


def test_transfer_closed_forms():
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(parse_transfer("gamma1.2").decode(x), x ** 1.2, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(parse_transfer("gamma:2.2").decode(x), x ** 2.2, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(parse_transfer("linear").decode(x), x, rtol=1e-6, atol=1e-7)
    # sRGB EOTF, IEC 61966-2-1 closed form
    ref = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(parse_transfer("srgb").decode(x), ref, rtol=1e-5, atol=1e-7)
    assert parse_transfer("gamma:1.2").name == "gamma1.2"
    for bad in ("gamma:-1", "gamma:x", "log", "gamma:0"):
        with pytest.raises(ReflectmmError, match="--transfer"):
            parse_transfer(bad)


@pytest.mark.parametrize("name", ["gamma1.2", "srgb", "linear", "gamma:2.2"])
@pytest.mark.parametrize("bits", [8, 16])
def test_lut_matches_decode_and_roundtrip(name, bits):
    tr = parse_transfer(name)
    top = (1 << bits) - 1
    codes = np.arange(0, top + 1, 1 if bits == 8 else 97)
    np.testing.assert_allclose(tr.lut(bits)[codes], tr.decode(codes / top), rtol=1e-6, atol=1e-9)
    # encode (colour-science for sRGB) then decode returns the value within half a code step
    lin = np.linspace(0, 1, 513)
    back = tr.lut(bits)[encode_linear(lin, tr, bits)]
    enc_step = 0.5 / top
    # derivative bound of the decode curve over [0,1] times half a code step
    slope = {"gamma1.2": 1.2, "srgb": 2.4 / 1.055 * 1.0, "linear": 1.0, "gamma:2.2": 2.2}[name]
    assert np.max(np.abs(back - lin)) <= slope * enc_step * 1.01 + 1e-7


@given(st.floats(0.05, 5.0))
def test_generic_gamma(g):
    tr = parse_transfer(f"gamma:{g}")
    x = np.array([0.0, 0.25, 0.5, 1.0])
    np.testing.assert_allclose(tr.decode(x), x ** g, rtol=1e-5, atol=1e-12)


def test_read_png_rgb_order_bits_and_saturation(tmp_path):
    codes = np.zeros((4, 5, 3), np.uint8)
    codes[0, 0] = (255, 10, 20)
    codes[1, 1] = (1, 2, 3)
    codes[2, 2] = (255, 255, 255)
    write_png(tmp_path / "a.png", codes)
    got, bits = read_codes(tmp_path / "a.png")
    assert bits == 8 and np.array_equal(got, codes)
    img = read_image(tmp_path / "a.png", parse_transfer("linear"))
    np.testing.assert_allclose(img.linear[1, 1], np.array([1, 2, 3]) / 255, rtol=1e-6)
    assert img.saturated[0, 0] and img.saturated[2, 2] and img.saturated.sum() == 2
    c16 = (codes.astype(np.uint16) * 257)
    c16[1, 1] = (1000, 2000, 3000)
    write_png(tmp_path / "b.png", c16)
    img16 = read_image(tmp_path / "b.png", parse_transfer("gamma1.2"))
    assert img16.bits == 16
    np.testing.assert_allclose(img16.linear[1, 1], (np.array([1000, 2000, 3000]) / 65535) ** 1.2, rtol=1e-5)
    assert img16.saturated.sum() == 2


def test_rotation_of_images_and_points(tmp_path):
    codes = np.zeros((4, 6, 3), np.uint8)
    codes[1, 4] = 200  # pixel x=4, y=1
    write_png(tmp_path / "r.png", codes)
    for rot in (90, 180, 270):
        img = read_image(tmp_path / "r.png", parse_transfer("linear"), rot)
        y, x = np.argwhere(img.linear[..., 0] > 0)[0]
        got = rotate_points(np.array([[4.0, 1.0]]), rot, 6, 4)  # size of the image as stored on disk
        assert (got[0, 0], got[0, 1]) == (x, y)
    img = read_image(tmp_path / "r.png", parse_transfer("linear"), 90)
    assert img.linear.shape[:2] == (6, 4)
    y, x = np.argwhere(img.linear[..., 0] > 0)[0]
    assert (x, y) == (4 - 1 - 1, 4)  # clockwise: (x, y) -> (H-1-y, x)

import json

import numpy as np
import pytest

from _capture_tree import FLASHES, VIEWS, make_tree, shot_file
from reflectmm_cli.artifacts import read_artifact, sha256_file
from reflectmm_cli.capture.images import encode_linear, write_png
from reflectmm_cli.capture.preprocess import CaptureOptions, parse_rotate, preprocess_identity
from reflectmm_cli.capture.transfer import parse_transfer
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import ParamError
from reflectmm_cli.stages import StageContext, get_stage

VIEWS_ARG = ",".join(VIEWS)
FLASH_ARG = ",".join(FLASHES)


def run(cli, root, ws, *extra):
    return cli("preprocess-multipie", "--root", root, "--views", VIEWS_ARG, "--flashes", FLASH_ARG,
               "--workspace", ws, *extra)


def test_olat_equals_flash_minus_room_within_quantisation(tmp_path, cli):
    truth = make_tree(tmp_path / "mp", ("042",))["042"]
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "042", "--crop", "none")
    assert res.exit_code == 0, res.stderr
    out = tmp_path / "ws" / "preprocess-multipie" / "042.npz"
    assert res.stdout.split() == [str(out), str(out.with_name("042_contact.png"))]
    art = read_artifact(out, "capture")
    V, F = len(VIEWS), len(FLASHES)
    assert art["olat"].shape == (V, F, 32, 48, 3) and art["olat"].dtype == np.float16
    assert art["room"].shape == (V, 32, 48, 3) and art["saturated"].shape == (V, F, 32, 48)
    assert list(art["view_names"]) == list(VIEWS) and list(art["flash_ids"]) == list(FLASHES)
    assert art["image_size"].tolist() == [48, 32]
    assert art["crop_origin"].tolist() == [[0, 0]] * V
    # independent computation: decode(encode(x)) with x**1.2, error bound from half an 8-bit step
    want = np.maximum(truth["flash"] - truth["room"][:, None], 0)
    err = np.abs(art["olat"].astype(np.float64) - want)
    assert err.max() < 2 * 1.2 * 0.5 / 255 + 2e-3  # two quantised images, float16 storage
    np.testing.assert_allclose(art["room"].astype(np.float64), truth["room"], atol=1.2 * 0.5 / 255 + 1e-3)
    assert art.params["transfer"] == "gamma1.2" and art.params["session"] == "01"
    roles = {r["role"] for r in art.meta["inputs"]}
    assert roles == {"root", "image", "landmarks"}
    img_refs = [r for r in art.meta["inputs"] if r["role"] == "image"]
    assert len(img_refs) == V * (F + 1)
    ref0 = img_refs[0]
    assert ref0["sha256"] == sha256_file(tmp_path / "mp" / ref0["path"])
    lm = art["landmarks"]
    assert lm.shape == (V, 68, 2) and lm.dtype == np.float32 and np.isfinite(lm).all()
    np.testing.assert_allclose(lm[0, 0], [0.3 * 48, 0.25 * 32], atol=1e-3)
    # rerun: byte-identical
    before = out.read_bytes()
    assert run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "042", "--crop", "none").exit_code == 0
    assert out.read_bytes() == before


def test_olat_clamped_and_saturation(tmp_path):
    root = tmp_path / "mp"
    make_tree(root, ("001",), views=("05_1",), flashes=("07",), size=(8, 6))
    room = np.full((6, 8, 3), 100, np.uint8)
    flash = np.full((6, 8, 3), 150, np.uint8)
    flash[0, 0] = (50, 50, 50)  # darker than the room: OLAT clamps to 0
    flash[1, 1] = (255, 20, 20)  # clipped in the flash shot
    room[2, 2] = (10, 255, 10)  # clipped in the room shot
    write_png(shot_file(root, "001", "05_1", "00"), room)
    write_png(shot_file(root, "001", "05_1", "07"), flash)
    arrays, _, _ = preprocess_identity(root, "001", CaptureOptions(views=("05_1",), flashes=("07",), crop="none"))
    o = arrays["olat"][0, 0].astype(np.float64)
    assert np.all(o[0, 0] == 0)
    np.testing.assert_allclose(o[3, 3], (150 / 255) ** 1.2 - (100 / 255) ** 1.2, rtol=2e-3)
    sat = arrays["saturated"][0, 0]
    assert sat[1, 1] and sat[2, 2] and sat.sum() == 2


def test_srgb_transfer_option(tmp_path, cli):
    truth = make_tree(tmp_path / "mp", ("007",), transfer="srgb")["007"]
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "007", "--transfer", "srgb", "--crop", "none")
    assert res.exit_code == 0, res.stderr
    art = read_artifact(tmp_path / "ws" / "preprocess-multipie" / "007.npz")
    np.testing.assert_allclose(art["room"].astype(np.float64), truth["room"], atol=0.5 / 255 + 1e-3)
    assert art.params["transfer"] == "srgb"


def test_landmark_crop_window(tmp_path):
    root = tmp_path / "mp"
    make_tree(root, ("001",), size=(64, 48))
    a_full, _, _ = preprocess_identity(root, "001", CaptureOptions(views=VIEWS, flashes=FLASHES, crop="none"))
    a, _, rep = preprocess_identity(root, "001", CaptureOptions(views=VIEWS, flashes=FLASHES, crop_margin=0.1))
    assert rep["crop"] == "landmarks"
    V, F, h, w, _ = a["olat"].shape
    assert h < 48 and w < 64
    for vi, (ox, oy) in enumerate(a["crop_origin"]):
        np.testing.assert_array_equal(a["olat"][vi], a_full["olat"][vi][:, oy:oy + h, ox:ox + w])
        lm = a["landmarks"][vi]
        assert (lm[:, 0] >= ox).all() and (lm[:, 0] < ox + w).all()
        assert (lm[:, 1] >= oy).all() and (lm[:, 1] < oy + h).all()


def test_missing_flash_shot_one_identity_skipped(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001", "002", "003"))
    missing = shot_file(root, "002", "05_1", "14")
    missing.unlink()
    res = run(cli, root, tmp_path / "ws", "--ids", "001-003")
    assert res.exit_code == 1
    assert "002_01_01_051_14.png" in res.stderr and "missing" in res.stderr
    assert "1 of 3 identities failed" in res.stderr
    ws = tmp_path / "ws" / "preprocess-multipie"
    assert (ws / "001.npz").exists() and (ws / "003.npz").exists() and not (ws / "002.npz").exists()
    assert str(ws / "001.npz") in res.stdout


def test_missing_view(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    for p in (root / "data/session01/multiview/001/01/08_1").iterdir():
        p.unlink()
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    assert "001_01_01_081_00.png" in res.stderr and "4 required shot(s) missing" in res.stderr


def test_wrong_size_names_file(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    bad = shot_file(root, "001", "08_1", "07")
    write_png(bad, np.zeros((30, 48, 3), np.uint8))
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    assert str(bad) in res.stderr and "48x30" in res.stderr and "48x32" in res.stderr


def test_non_image_file_names_file(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    bad = shot_file(root, "001", "13_0", "05")
    bad.write_text("this is not a PNG")
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    assert str(bad) in res.stderr and "not a readable image" in res.stderr


@pytest.mark.parametrize("n", [67, 69])
def test_landmarks_wrong_count(tmp_path, cli, n):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    lm = shot_file(root, "001", "05_1", "00", ext="_lm.pts")
    lm.write_text("version: 1\nn_points: %d\n{\n" % n + "\n".join("1 2" for _ in range(n)) + "\n}\n")
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    assert str(lm) in res.stderr and f"expected 68 landmarks, found {n}" in res.stderr


def test_landmarks_txt_npy_and_override_dir(tmp_path):
    root = tmp_path / "mp"
    make_tree(root, ("001",), landmarks=False)
    pts = np.stack([np.arange(68.0), np.arange(68.0) / 2 + 3], 1)
    np.savetxt(shot_file(root, "001", "13_0", "00", ext="_lm.txt"), pts)
    np.save(shot_file(root, "001", "05_1", "00", ext="_lm.npy"), pts + 1)
    a, plan, rep = preprocess_identity(root, "001", CaptureOptions(views=VIEWS, flashes=FLASHES))
    np.testing.assert_allclose(a["landmarks"][0], pts)
    np.testing.assert_allclose(a["landmarks"][1], pts + 1)
    assert np.isnan(a["landmarks"][2]).all()
    assert rep["crop"] == "signal" and rep["landmark_views"] == 2
    other = tmp_path / "lms"
    other.mkdir()
    np.savetxt(other / "001_01_01_081_00_lm.txt", pts + 2)
    a, _, _ = preprocess_identity(root, "001", CaptureOptions(views=VIEWS, flashes=FLASHES, landmarks_dir=other))
    np.testing.assert_allclose(a["landmarks"][2], pts + 2)
    assert np.isnan(a["landmarks"][0]).all()
    # detect-landmarks names its files after the image: <room shot stem>.pts
    from reflectmm_cli.geometry_fit.landmarks import write_pts

    write_pts(other / "001_01_01_130_00.pts", pts + 3)
    a, _, _ = preprocess_identity(root, "001", CaptureOptions(views=VIEWS, flashes=FLASHES, landmarks_dir=other))
    np.testing.assert_allclose(a["landmarks"][0], pts + 3, atol=1e-3)


def test_rotate_option(tmp_path):
    root = tmp_path / "mp"
    make_tree(root, ("001",), views=("05_1", "08_1"), flashes=("07",), size=(40, 40))
    opts = dict(views=("05_1", "08_1"), flashes=("07",), crop="none")
    a0, _, _ = preprocess_identity(root, "001", CaptureOptions(**opts))
    a1, _, _ = preprocess_identity(root, "001", CaptureOptions(rotate={"08_1": 90}, **opts))
    np.testing.assert_array_equal(a1["olat"][1, 0], np.rot90(a0["olat"][1, 0], -1))
    np.testing.assert_array_equal(a1["olat"][0], a0["olat"][0])
    lm0, lm1 = a0["landmarks"][1], a1["landmarks"][1]
    np.testing.assert_allclose(lm1, np.stack([40 - 1 - lm0[:, 1], lm0[:, 0]], 1), atol=1e-4)


def test_stage_input_files_and_discovery(tmp_path):
    root = tmp_path / "mp"
    make_tree(root, ("001", "002"))
    make_tree(root, ("005",), session="02")
    stage = get_stage("preprocess-multipie")
    ctx = stage.context(workspace=tmp_path / "ws", identity="002", inputs={"root": [root]},
                        params={"views": list(VIEWS), "flashes": list(FLASHES)})
    files = stage.files_to_hash(ctx)
    allf = files["image"] + files["landmarks"]
    assert len(files["image"]) == len(VIEWS) * (len(FLASHES) + 1) and len(files["landmarks"]) == len(VIEWS)
    assert all("/002/" in str(p) for p in allf)
    assert stage.discover_ids(ctx) == ["001", "002", "005"]
    from reflectmm_cli.stages import compute_cache_key

    k2 = compute_cache_key(stage, ctx)
    k1 = compute_cache_key(stage, ctx.with_(identity="001"))
    # changing identity 001's image changes only 001's key
    write_png(shot_file(root, "001", "05_1", "07"), np.zeros((32, 48, 3), np.uint8))
    assert compute_cache_key(stage, ctx) == k2
    assert compute_cache_key(stage, ctx.with_(identity="001")) != k1


def test_usage_errors(tmp_path, cli):
    make_tree(tmp_path / "mp", ("001",))
    res = cli("preprocess-multipie", "--root", tmp_path / "mp", "--workspace", tmp_path / "ws")
    assert res.exit_code == 2
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "001", "--rotate", "08_1=45")
    assert res.exit_code == 1 and "degrees must be" in res.stderr
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "001", "--session", "03")
    assert res.exit_code == 1 and "not in session 03" in res.stderr


def test_16bit_tree_and_corrupt_raw(tmp_path):
    root = tmp_path / "mp"
    truth = make_tree(root, ("001",), bits=16, views=("05_1",), flashes=("07",))["001"]
    a, _, _ = preprocess_identity(root, "001", CaptureOptions(views=("05_1",), flashes=("07",), crop="none"))
    assert int(a["bits"]) == 16
    want = np.maximum(truth["flash"] - truth["room"][:, None], 0)
    np.testing.assert_allclose(a["olat"].astype(np.float64), want, atol=2 * 1.2 * 0.5 / 65535 + 1e-3)
    # a RAW file replaces the PNG: it is read through rawpy, and a corrupt one is an error naming it
    png = shot_file(root, "001", "05_1", "07")
    png.unlink()
    raw = png.with_suffix(".dng")
    raw.write_bytes(b"II*\x00not really a raw file")
    with pytest.raises(ReflectmmError, match="not a readable RAW image") as exc:
        preprocess_identity(root, "001", CaptureOptions(views=("05_1",), flashes=("07",), crop="none"))
    assert str(raw) in str(exc.value)


def test_id_file_json_and_all(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001", "003"))
    (tmp_path / "ids.txt").write_text("# subjects\n001\n002  # not captured\n")
    res = run(cli, root, tmp_path / "ws", "--id-file", tmp_path / "ids.txt", "--json")
    assert res.exit_code == 1
    doc = json.loads(res.stdout)
    assert doc["outputs"][0].endswith("001.npz") and list(doc["failed"]) == ["002"]
    assert "not found in any session" in doc["failed"]["002"]
    res = run(cli, root, tmp_path / "ws2", "--all")
    assert res.exit_code == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "ws2" / "preprocess-multipie").glob("*.npz")) == ["001.npz", "003.npz"]


def _capture_recipe(ws):
    (ws / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.preprocess-multipie]\nforeach = ["001"]\n'
                               f'inputs = {{ root = "mp" }}\nparams = {{ views = {json.dumps(list(VIEWS))}, '
                               f'flashes = {json.dumps(list(FLASHES))} }}\n')
    return ws / "r.toml"


def test_all_black_flash_image_is_refused(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    black = shot_file(root, "001", "05_1", FLASHES[1])
    write_png(black, np.zeros((32, 48, 3), np.uint8))
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith(f"reflectmm: error: {black}: flash image is entirely black"), line
    assert f"flash {FLASHES[1]} of view 05_1" in line
    res = cli("run", _capture_recipe(tmp_path), "-w", tmp_path)
    assert res.exit_code == 1 and "entirely black" in res.stderr and str(black) in res.stderr


def test_landmarks_far_outside_the_frame_are_refused(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    lm = shot_file(root, "001", "13_0", "00", ext="_lm.pts")
    pts = np.stack([np.linspace(10, 30, 68), np.linspace(8, 20, 68)], 1)
    pts[30] = [1e6, 12.0]
    from reflectmm_cli.landmarks import write_pts

    write_pts(lm, pts)
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    line = res.stderr.strip().splitlines()[-1]
    assert line == (f"reflectmm: error: {lm}: 1 landmark(s) far outside the 48x32 frame (landmark 31 at (1e+06, 12) "
                    "px); wrong image, size or units?"), line
    res = cli("run", _capture_recipe(tmp_path), "-w", tmp_path)
    assert res.exit_code == 1 and "far outside" in res.stderr
    # a point a little outside (a jaw point past the edge) is fine
    pts[30] = [52.0, 12.0]
    write_pts(lm, pts)
    assert run(cli, root, tmp_path / "ws2", "--id", "001").exit_code == 0


def test_a_bad_rotation_in_a_recipe_names_the_file_and_stage(recipe_error):
    """The recipe's ``rotate`` goes through the same check as ``--rotate``, and its error names the recipe."""
    line = recipe_error("preprocess-multipie",
                        'foreach = ["001"]\ninputs = { root = "mp" }\nparams = { rotate = { "08_1" = 45 } }\n')
    assert "rotate: degrees must be 0, 90, 180 or 270 (clockwise); camera 08_1 has 45" in line
    assert parse_rotate("08_1=90, 19_1=-90") == {"08_1": 90, "19_1": 270}
    with pytest.raises(ParamError, match="expected CAMERA=DEGREES"):
        parse_rotate(["08_1"])


def _noisy_olat(rng, box, shape=(4, 240, 320), sigma=0.003, level=0.2):
    """Flash-minus-room images of a lit rectangle ``box = (x0, y0, x1, y1)`` (inclusive), both shots with
    Gaussian sensor noise of ``sigma``, clamped at 0 as preprocess stores them."""
    F, H, W = shape
    x0, y0, x1, y1 = box
    lit = np.zeros((H, W, 3))
    lit[y0:y1 + 1, x0:x1 + 1] = level
    flash = lit + rng.normal(0, sigma, (F, H, W, 3))
    room = rng.normal(0, sigma, (H, W, 3))
    return np.maximum(flash - room, 0).astype(np.float16)


def test_signal_box_ignores_sensor_noise():
    from reflectmm_cli.capture.preprocess import SIGNAL_THRESHOLD, signal_box

    rng = np.random.default_rng(3)
    box = (110, 60, 189, 169)   # an 80 x 110 px face in a 320 x 240 frame
    olat = _noisy_olat(rng, box)
    # the noise alone passes the threshold somewhere: a box of single pixels would be the whole frame
    ys, xs = np.nonzero(olat.max(axis=(0, 3)) > SIGNAL_THRESHOLD)
    assert (xs.min(), ys.min(), xs.max(), ys.max()) == (0, 0, 319, 239)
    # the averaged test finds the lit rectangle to within the averaging square (3 px here), plus the margin
    x0, y0, x1, y1 = signal_box(olat, 0.0)
    assert abs(x0 - 110) <= 2 and abs(y0 - 60) <= 2 and abs(x1 - 190) <= 2 and abs(y1 - 170) <= 2
    m = 0.25 * 110  # the margin is a fraction of the larger side, on every side, clamped to the frame
    x0, y0, x1, y1 = signal_box(olat, 0.25)
    assert abs(x0 - (110 - m)) <= 3 and abs(y0 - (60 - m)) <= 3 and abs(x1 - (190 + m)) <= 3
    assert abs(y1 - (170 + m)) <= 3
    # nothing lit: the whole frame
    dark = np.maximum(rng.normal(0, 0.003, (4, 240, 320, 3)), 0).astype(np.float16)
    assert signal_box(dark, 0.3) == (0, 0, 320, 240)


def test_signal_crop_of_a_noisy_capture_is_a_face_window(tmp_path):
    """A view without landmarks makes `auto` crop to the lit pixels; 8-bit shots with sensor noise still give a
    window around the lit face, not the whole frame (every view keeps its lit pixels)."""
    root = tmp_path / "mp"
    make_tree(root, ("001",), views=("05_1", "13_0"), flashes=("07", "05"), size=(320, 240), landmarks=False)
    rng = np.random.default_rng(0)
    tr = parse_transfer("gamma1.2")
    yy, xx = np.mgrid[0:240, 0:320]
    face = ((xx - 150) / 45.0) ** 2 + ((yy - 120) / 60.0) ** 2 < 1
    for cam in ("05_1", "13_0"):
        room = 0.05 + rng.normal(0, 0.004, (240, 320, 3))
        write_png(shot_file(root, "001", cam, "00"), encode_linear(np.clip(room, 0, 1), tr, 8))
        for f in ("07", "05"):
            img = room + 0.3 * face[..., None] + rng.normal(0, 0.004, (240, 320, 3))
            write_png(shot_file(root, "001", cam, f), encode_linear(np.clip(img, 0, 1), tr, 8))
    a, _, rep = preprocess_identity(root, "001", CaptureOptions(views=("05_1", "13_0"), flashes=("07", "05")))
    assert rep["crop"] == "signal"
    ch, cw = a["olat"].shape[2:4]
    # the face is 91 x 121 px; the default margin (0.6 / 2 of the larger side) makes the window about 164 x 194
    assert 150 <= cw <= 180 and 180 <= ch <= 210, (cw, ch)
    for v in range(2):
        x0, y0 = a["crop_origin"][v]
        assert x0 <= 105 and x0 + cw >= 195 and y0 <= 60 and y0 + ch >= 180


def test_rotate_camera_twice_or_not_a_view_is_refused_before_reading(tmp_path, cli, reflectmm_log):
    make_tree(tmp_path / "mp", ("001",))
    with pytest.raises(ParamError, match=r"--rotate 05_1=180: camera 05_1 is given twice \(05_1=90 before\)"):
        parse_rotate(["05_1=90", "05_1=180"])
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--id", "001", "--rotate", "05_1=90", "--rotate", "05_1=180")
    assert res.exit_code == 1 and "rotate: camera 05_1 is given twice (05_1=90 before)" in res.stderr
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--ids", "001,002", "--rotate", "99_9=90")
    assert res.exit_code == 1 and res.stderr.count("\n") == 1
    assert "--rotate 99_9=90: camera 99_9 is not among the views (13_0, 05_1, 08_1)" in res.stderr
    # without --views the default views (the paper's 9 and the raised cameras of the flashes used) are checked,
    # before the data is looked at (which would warn that 08_1 / 19_1 lack shots)
    res = cli("preprocess-multipie", "--root", tmp_path / "mp", "-w", tmp_path / "ws", "--id", "001",
              "--rotate", "99_9=90")
    assert res.exit_code == 1 and "camera 99_9 is not among the views (09_0, " in res.stderr and not reflectmm_log
    assert not (tmp_path / "ws" / "preprocess-multipie").exists()


def test_transfer_is_checked_with_the_options(tmp_path, cli, reflectmm_log):
    make_tree(tmp_path / "mp", ("001",))
    res = cli("preprocess-multipie", "--root", tmp_path / "mp", "-w", tmp_path / "ws", "--id", "001",
              "--transfer", "gamma:0")
    assert res.exit_code == 1 and not reflectmm_log  # no warning about the data's raised cameras first
    assert res.stderr.strip() == ("reflectmm: error: --transfer: 'gamma:0': gamma must be a positive number "
                                  "(e.g. gamma:2.2)")


def test_all_with_ids_is_refused(tmp_path, cli):
    make_tree(tmp_path / "mp", ("001", "002"))
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--all", "--id", "001")
    assert res.exit_code == 2 and "--all takes every identity found under --root" in res.stderr
    assert not (tmp_path / "ws").exists()


def test_nothing_written_is_not_said_to_be_partly_written(tmp_path, cli):
    make_tree(tmp_path / "mp", ("001", "002"))
    res = run(cli, tmp_path / "mp", tmp_path / "ws", "--ids", "001,002", "--flashes", "05,07,09")
    assert res.exit_code == 1
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("reflectmm: error: all 2 identities failed, nothing was written — 001: ")
    assert "the others were written" not in res.stderr


def test_wrong_size_flash_shot_names_its_own_view(tmp_path, cli):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    bad = shot_file(root, "001", "05_1", "07")
    write_png(bad, np.zeros((30, 40, 3), np.uint8))
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert res.exit_code == 1
    assert f"{bad}: image is 40x30, but the room shot of the same view (05_1) is 48x32" in res.stderr
    write_png(bad, np.zeros((32, 48, 3), np.uint8))
    bad = shot_file(root, "001", "08_1", "00")
    write_png(bad, np.zeros((30, 40, 3), np.uint8))
    res = run(cli, root, tmp_path / "ws", "--id", "001")
    assert f"{bad}: image is 40x30, but the room shot of view 13_0 is 48x32" in res.stderr


def test_landmarks_folder_without_this_identity_warns(tmp_path, reflectmm_log):
    root = tmp_path / "mp"
    make_tree(root, ("001",))
    (tmp_path / "lms").mkdir()
    opts = CaptureOptions(views=VIEWS, flashes=FLASHES, landmarks_dir=tmp_path / "lms")
    _, _, rep = preprocess_identity(root, "001", opts)
    assert rep["landmark_views"] == 0
    assert reflectmm_log == [f"{tmp_path / 'lms'}: no landmark file for identity 001 in any of its 3 views (such as "
                             "001_01_01_130_00_lm.pts): the capture has no landmarks"]


def test_a_16bit_shot_among_8bit_ones_is_scaled_by_its_own_depth(tmp_path):
    """Each file is decoded by its own bit depth (code / 65535 or / 255): a 16-bit shot in an 8-bit tree gives
    the same linear values as its 8-bit version, within the 8-bit quantisation."""
    root = tmp_path / "mp"
    truth = make_tree(root, ("001",), views=("05_1",), flashes=("07",))["001"]
    opts = CaptureOptions(views=("05_1",), flashes=("07",), crop="none")
    a8, _, _ = preprocess_identity(root, "001", opts)
    write_png(shot_file(root, "001", "05_1", "07"), encode_linear(truth["flash"][0, 0], parse_transfer("gamma1.2"), 16))
    a16, _, _ = preprocess_identity(root, "001", opts)
    assert int(a8["bits"]) == 8 and int(a16["bits"]) == 16
    np.testing.assert_allclose(a16["olat"].astype(np.float64), a8["olat"].astype(np.float64), atol=4e-3)


def test_a_note_of_the_default_views_is_said_once(tmp_path, cli, reflectmm_log):
    """Flash 14 without a room shot of its raised camera 08_1: the note was logged three times per identity (the
    cache key and the run each worked the default views out)."""
    from reflectmm_cli.capture.layout import DEFAULT_VIEWS

    root = tmp_path / "mp"
    make_tree(root, ("001",), views=DEFAULT_VIEWS, flashes=("07", "14"), size=(24, 16))
    r = cli("preprocess-multipie", "--root", root, "--flashes", "07,14", "--crop", "none", "--workspace",
            tmp_path / "ws", "--id", "001")
    assert r.exit_code == 0, r.stderr
    notes = [m for m in reflectmm_log if "camera 08_1 has no room shot" in m]
    assert len(notes) == 1, reflectmm_log

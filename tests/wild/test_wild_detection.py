"""detect-landmarks on a real photograph and on synth wild renders."""
import numpy as np
import pytest

pytest.importorskip("dlib")

from reflectmm_cli.detection import detect_landmarks, pick_face  # noqa: E402
from reflectmm_cli.landmarks import read_landmarks  # noqa: E402


def test_astronaut_landmarks_fall_on_her_face(tmp_path, cli):
    from skimage import data

    img = data.astronaut()
    faces = detect_landmarks(img)
    assert faces
    f = pick_face(faces)
    lm = f.landmarks
    l, t, r, b = f.box
    # the face of Eileen Collins is in the upper middle of the 512² photo (rows ~80-170, cols ~170-270)
    assert 150 < lm[30, 0] < 290 and 70 < lm[30, 1] < 190
    inside = (lm[:, 0] >= l - 10) & (lm[:, 0] <= r + 10) & (lm[:, 1] >= t - 10) & (lm[:, 1] <= b + 25)
    assert inside.mean() > 0.9
    eyes = lm[36:48, 1].mean()
    assert eyes < lm[30, 1] < lm[48:68, 1].mean()                   # eyes above nose above mouth
    assert lm[36:42, 0].mean() < lm[42:48, 0].mean()                  # image-left eye first
    # through the command: writes a .pts readable by the shared reader
    from reflectmm_cli.artifacts import write_png
    write_png(tmp_path / "astronaut.png", img)
    res = cli("detect-landmarks", tmp_path / "astronaut.png", "--out", tmp_path / "lm")
    assert res.exit_code == 0, res.stderr
    assert np.allclose(read_landmarks(tmp_path / "lm" / "astronaut.pts"), lm)


def test_no_face_is_reported_and_others_written(tmp_path, cli):
    from skimage import data

    from reflectmm_cli.artifacts import write_png
    write_png(tmp_path / "a.png", data.astronaut())
    write_png(tmp_path / "blank.png", np.full((120, 160, 3), 0.5))
    res = cli("detect-landmarks", tmp_path / "a.png", tmp_path / "blank.png", "--out", tmp_path / "lm")
    assert res.exit_code == 1
    assert "blank.png" in res.stderr and "no face" in res.stderr
    assert (tmp_path / "lm" / "a.pts").is_file() and not (tmp_path / "lm" / "blank.pts").exists()


def test_missing_extra_gives_one_line_error(monkeypatch):
    import sys

    from reflectmm_cli import detection
    from reflectmm_cli.errors import ReflectmmError

    detection._models.cache_clear()
    monkeypatch.setitem(sys.modules, "dlib", None)
    with pytest.raises(ReflectmmError, match=r"reflectmm\[landmarks\]"):
        detect_landmarks(np.zeros((8, 8, 3), np.uint8))
    detection._models.cache_clear()


def test_two_folders_with_the_same_file_name_are_refused(tmp_path, cli):
    """Issue 24 §6: two inputs named face.png (in two folders) silently wrote one face.pts."""
    from reflectmm_cli.artifacts import write_png

    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        write_png(tmp_path / d / "face.png", np.full((40, 40, 3), 0.5))
    res = cli("detect-landmarks", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "lm")
    assert res.exit_code == 1 and len(res.stderr.strip().splitlines()) == 1
    assert "face.pts" in res.stderr and str(tmp_path / "a" / "face.png") in res.stderr
    assert not (tmp_path / "lm").exists()


def test_dim_photo_is_found_after_exposure_normalisation(tmp_path, cli):
    """The astronaut at 1/16 of her exposure: dlib finds no face as given, and the same face (the same pixels) once
    the image is brightened."""
    from skimage import data

    from reflectmm_cli.artifacts import write_png

    bright = data.astronaut()
    ref = pick_face(detect_landmarks(bright, exposure="none")).landmarks
    dim = np.rint(bright.astype(np.float64) / 16).astype(np.uint8)
    assert detect_landmarks(dim, exposure="none") == []
    found = pick_face(detect_landmarks(dim, exposure="auto"))
    assert found is not None
    iod = np.linalg.norm(ref[36:42].mean(0) - ref[42:48].mean(0))
    assert np.median(np.linalg.norm(found.landmarks - ref, axis=1)) < 0.1 * iod
    write_png(tmp_path / "dim.png", dim)
    res = cli("detect-landmarks", tmp_path / "dim.png", "--out", tmp_path / "none", "--exposure", "none")
    assert res.exit_code == 1 and "no face" in res.stderr
    res = cli("detect-landmarks", tmp_path / "dim.png", "--out", tmp_path / "auto")
    assert res.exit_code == 0, res.stderr
    assert np.allclose(read_landmarks(tmp_path / "auto" / "dim.pts"), found.landmarks)


def test_allow_missing_lists_the_images_without_a_face_and_succeeds(tmp_path, cli):
    from skimage import data

    from reflectmm_cli.artifacts import write_png
    write_png(tmp_path / "a.png", data.astronaut())
    write_png(tmp_path / "blank.png", np.full((120, 160, 3), 0.5))
    res = cli("detect-landmarks", tmp_path / "a.png", tmp_path / "blank.png", "--out", tmp_path / "lm",
              "--allow-missing")
    assert res.exit_code == 0, res.stderr
    lines = (tmp_path / "lm" / "no_face.txt").read_text().splitlines()
    assert lines == [f"{tmp_path / 'blank.png'}\tno face found"]
    # one warning line says how many and where they are listed (a data set has thousands without a face)
    assert "1 of 2 image(s) with landmarks; the 1 without a face are listed in" in res.stderr
    assert "blank.png: no face found" not in res.stderr
    assert (tmp_path / "lm" / "a.pts").is_file() and not (tmp_path / "lm" / "blank.pts").exists()
    # landmarks already in the folder for an image without a face (hand-made, or an earlier run's) are kept, and
    # the run says that they will be read
    own = (tmp_path / "lm" / "a.pts").read_text()
    (tmp_path / "lm" / "blank.pts").write_text(own)
    res = cli("detect-landmarks", tmp_path / "a.png", tmp_path / "blank.png", "--out", tmp_path / "lm",
              "--allow-missing")
    assert res.exit_code == 0 and "blank.pts exists, but this run finds no face" in res.stderr
    assert (tmp_path / "lm" / "blank.pts").read_text() == own
    # every image with a face: the list is written, empty
    res = cli("detect-landmarks", tmp_path / "a.png", "--out", tmp_path / "lm2", "--allow-missing")
    assert res.exit_code == 0, res.stderr
    assert (tmp_path / "lm2" / "no_face.txt").read_text() == ""


def test_allow_missing_still_refuses_an_unreadable_image(tmp_path, cli):
    from skimage import data

    from reflectmm_cli.artifacts import write_png
    write_png(tmp_path / "a.png", data.astronaut())
    (tmp_path / "broken.png").write_bytes(b"not a png at all")
    res = cli("detect-landmarks", tmp_path / "a.png", tmp_path / "broken.png", "--out", tmp_path / "lm",
              "--allow-missing")
    assert res.exit_code == 1
    assert "broken.png" in res.stderr and "1 could not be read" in res.stderr
    assert not (tmp_path / "lm" / "no_face.txt").exists()


def test_a_glob_in_the_images_input_is_expanded_when_the_images_exist(tmp_path):
    """A recipe's `images = "@synth-multipie.dir/.../*_00.png"` is a pattern inside a folder that an upstream stage
    fills: the task expands it when it runs (StageContext.with_patterns_expanded). Before the images exist that is
    an error naming the pattern; after, the stage gets the matches, sorted."""
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.errors import ReflectmmError
    from reflectmm_cli.stages import get_stage
    from reflectmm_cli.stages.detect_landmarks import image_files

    stage = get_stage("detect-landmarks")
    pattern = tmp_path / "data" / "*" / "*_00.png"
    ctx = stage.context(workspace=tmp_path / "ws", inputs={"images": [pattern]}, params={"allow_missing": True})
    with pytest.raises(ReflectmmError, match=r"input 'images': no file matches .*\*_00\.png"):
        ctx.with_patterns_expanded()
    for cam in ("13_0", "05_1"):
        for shot in ("00", "01"):
            write_png(tmp_path / "data" / cam / f"001_{cam}_{shot}.png", np.full((8, 8, 3), 0.5))
        (tmp_path / "data" / cam / f"001_{cam}_00_lm.pts").write_text("")
    assert image_files(ctx.with_patterns_expanded()) == [tmp_path / "data" / "05_1" / "001_05_1_00.png",
                                                         tmp_path / "data" / "13_0" / "001_13_0_00.png"]
    # a path that exists is kept as given, even with glob characters in its name
    odd = tmp_path / "data" / "[x]_00.png"
    write_png(odd, np.full((8, 8, 3), 0.5))
    assert image_files(ctx.with_(inputs={"images": [odd]}).with_patterns_expanded()) == [odd]


def test_cnn_detector_finds_the_same_face(tmp_path, cli):
    """dlib's MMOD CNN detector on the astronaut: the same face as the HOG detector's (the same shape predictor,
    another box), written through the command with --detector cnn."""
    from skimage import data

    from reflectmm_cli.artifacts import write_png

    img = data.astronaut()
    hog = pick_face(detect_landmarks(img))
    cnn = pick_face(detect_landmarks(img, detector="cnn"))
    assert cnn is not None
    iod = float(np.linalg.norm(hog.landmarks[36:42].mean(0) - hog.landmarks[42:48].mean(0)))
    assert np.median(np.linalg.norm(cnn.landmarks - hog.landmarks, axis=1)) < 0.1 * iod
    write_png(tmp_path / "astronaut.png", img)
    res = cli("detect-landmarks", tmp_path / "astronaut.png", "--detector", "cnn", "--out", tmp_path / "lm")
    assert res.exit_code == 0, res.stderr
    assert np.allclose(read_landmarks(tmp_path / "lm" / "astronaut.pts"), cnn.landmarks)


def test_cnn_detector_reaches_a_45_degree_view(tmp_path):
    """A painted synthetic face seen from camera 19_0 (45° of yaw): the HOG detector finds no face, the CNN one
    finds it, with its inner points within a quarter of the inter-ocular distance of the synthetic landmarks."""
    import cv2

    from reflectmm_cli.synth.multipie import SynthConfig, synth_multipie

    synth_multipie(tmp_path, SynthConfig(identities=1, seed=0, cameras=("19_0",), flashes=("01",), noise=0.002,
                                         features="painted", image_size=(640, 480)))
    png = next(tmp_path.rglob("*_190_00.png"))
    truth = read_landmarks(png.with_name(png.stem + "_lm.pts"))
    img = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
    assert not detect_landmarks(img)
    faces = detect_landmarks(img, detector="cnn")
    assert faces
    iod = float(np.linalg.norm(truth[36:42].mean(0) - truth[42:48].mean(0)))
    err = np.linalg.norm(faces[0].landmarks[27:] - truth[27:], axis=1)
    assert np.median(err) < 0.25 * iod


def test_unknown_detector_is_a_one_line_error(tmp_path, cli):
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.errors import ReflectmmError

    with pytest.raises(ReflectmmError, match="detector must be one of hog, cnn"):
        detect_landmarks(np.zeros((8, 8, 3), np.uint8), detector="mtcnn")
    write_png(tmp_path / "a.png", np.full((40, 40, 3), 0.5))
    res = cli("detect-landmarks", tmp_path / "a.png", "--detector", "mtcnn", "--out", tmp_path / "lm")
    assert res.exit_code != 0 and "mtcnn" in res.stderr and not (tmp_path / "lm").exists()


def test_jittered_boxes_form_the_3x3x3_grid_around_the_box():
    from reflectmm_cli.detection import jittered_boxes

    box = (100, 60, 200, 180)                      # 100 wide, 120 high, centre (150, 120)
    assert jittered_boxes(box, 0.0) == [box]
    boxes = np.array(jittered_boxes(box, 0.1), float)
    assert len(boxes) == 27 and len({tuple(b) for b in boxes}) == 27
    centres = np.c_[(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2]
    sizes = np.c_[boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]]
    assert np.allclose(centres.mean(0), (150, 120), atol=0.5)
    assert set(np.round(centres[:, 0] - 150).astype(int)) == {-10, 0, 10}
    assert set(np.round(centres[:, 1] - 120).astype(int)) == {-12, 0, 12}
    assert np.allclose(sorted(set(np.round(sizes[:, 0]).astype(int))), (90, 100, 110))
    assert np.allclose(sizes[:, 1] / 120, sizes[:, 0] / 100, atol=0.02)


@pytest.mark.parametrize("bad", [-0.01, 0.5, 2.0])
def test_a_bad_box_jitter_is_refused_before_any_work(bad):
    from reflectmm_cli.detection import detect_landmarks, jittered_boxes
    from reflectmm_cli.errors import ReflectmmError

    with pytest.raises(ReflectmmError, match="box jitter"):
        jittered_boxes((0, 0, 10, 10), bad)
    with pytest.raises(ReflectmmError, match="box jitter"):
        detect_landmarks(np.zeros((8, 8, 3), np.uint8), box_jitter=bad)


def test_predict_shape_is_the_mean_over_the_jittered_boxes():
    """A stand-in predictor whose points follow the box (its centre plus fixed offsets, whole pixels like dlib's):
    the mean over the grid is the direct mean of the 27 predictions, and lands at sub-pixel positions."""
    from types import SimpleNamespace

    from reflectmm_cli.detection import jittered_boxes, predict_shape

    offsets = np.random.default_rng(0).normal(0, 20, (68, 2))

    def predictor(image, rect):
        c = np.array([(rect.left() + rect.right()) / 2, (rect.top() + rect.bottom()) / 2])
        s = (rect.right() - rect.left()) / 100
        pts = np.floor(c + s * offsets)
        return SimpleNamespace(parts=lambda: [SimpleNamespace(x=int(x), y=int(y)) for x, y in pts])

    box = (101, 57, 203, 181)
    direct = []
    for b in jittered_boxes(box, 0.05):
        direct.append([[p.x, p.y] for p in predictor(None, SimpleNamespace(
            left=lambda b=b: b[0], top=lambda b=b: b[1], right=lambda b=b: b[2], bottom=lambda b=b: b[3])).parts()])
    got = predict_shape(predictor, None, box, 0.05)
    assert got.shape == (68, 2)
    assert np.allclose(got, np.mean(direct, 0))
    assert not np.allclose(got, np.round(got))                      # sub-pixel
    assert np.allclose(predict_shape(predictor, None, box, 0.0), direct[13])  # the middle of the grid: the box


def test_box_jitter_moves_the_points_by_less_than_a_pixel_on_a_photograph(tmp_path, cli):
    from skimage import data

    from reflectmm_cli.artifacts import write_png

    img = data.astronaut()
    plain = detect_landmarks(img)[0].landmarks
    jit = detect_landmarks(img, box_jitter=0.05)[0].landmarks
    d = np.linalg.norm(plain - jit, axis=1)
    assert 0.05 < np.median(d) < 2.0
    write_png(tmp_path / "astronaut.png", img)
    res = cli("detect-landmarks", tmp_path / "astronaut.png", "--out", tmp_path / "lm", "--box-jitter", "0.05")
    assert res.exit_code == 0, res.stderr
    assert np.allclose(read_landmarks(tmp_path / "lm" / "astronaut.pts"), jit, atol=1e-3)

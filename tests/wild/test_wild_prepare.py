"""prepare-wild: alignment, masks, single-image geometry, shards, bad inputs."""
import shutil

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.align import (CELEBAMASK_SKIN_LABELS, align_image, crop_transform, five_points,
                                          model_five_points, similarity_from_five_points, skin_mask_from_labels,
                                          transform_points)
from reflectmm_cli.finetune.data import (PrepareConfig, list_wild_inputs, open_shard,
                                         prepare_wild_shard)
from reflectmm_cli.landmarks import write_pts


def test_five_point_order(small_face):
    lm3 = small_face.mean_shape[small_face.landmarks]
    p = model_five_points(small_face)
    assert np.allclose(p[0], (lm3[36] + lm3[39]) / 2) and np.allclose(p[2], lm3[30])
    # model frame: +x towards the subject's left as seen by the camera? eyes first, nose between, mouth below
    assert p[0, 0] < p[1, 0] and p[3, 0] < p[4, 0]
    assert p[0, 1] > p[2, 1] > p[3, 1] and abs(p[2, 0] - (p[0, 0] + p[1, 0]) / 2) < 5
    with pytest.raises(ReflectmmError, match="68"):
        five_points(np.zeros((67, 2)))


def test_similarity_against_hand_computed(small_face):
    X = model_five_points(small_face)
    s0, t0, H = 2.3, np.array([310.0, 205.0]), 480
    # orthographic projection by hand: x = s·X + tx; y_up = s·Y + (H − 1 − ty)  ⇒  y = ty − s·Y
    p = np.stack([s0 * X[:, 0] + t0[0], t0[1] - s0 * X[:, 1]], 1)
    t, s = similarity_from_five_points(p, X, H)
    assert s == pytest.approx(s0, rel=1e-9) and np.allclose(t, t0, atol=1e-9)
    A = crop_transform(t, s, 224)
    assert np.allclose(transform_points(A, t0[None]), [[112, 112]])
    assert A[0, 0] == pytest.approx(1.02 / s0)
    # a point 10 mm to the model's +x and +y lands 10.2 px right and up in the crop
    q = np.array([[t0[0] + 10 * s0, t0[1] - 10 * s0]])
    assert np.allclose(transform_points(A, q), [[122.2, 101.8]])


def test_alignment_is_equivariant_to_scale_and_shift(small_face):
    rng = np.random.default_rng(0)
    img = (rng.uniform(size=(24, 24, 3)) * 255).astype(np.uint8)
    import cv2
    img = cv2.resize(img, (300, 300), interpolation=cv2.INTER_CUBIC)
    from reflectmm_cli.geometry import Camera, deep3d_camera
    cam = Camera(deep3d_camera().K * [[1.3], [1.3], [1]], np.diag([1.0, -1, -1]), [0, 0, 1000], 300, 300)
    cam.K[0, 2], cam.K[1, 2] = 140, 160
    lm, _ = cam.project(small_face.mean_shape[small_face.landmarks].astype(np.float64))
    a = align_image(img, lm, small_face, 64)
    big = cv2.resize(img, (600, 600), interpolation=cv2.INTER_CUBIC)
    canvas = np.zeros((700, 800, 3), np.uint8)
    canvas[50:650, 120:720] = big
    lm2 = (lm + 0.5) * 2 - 0.5 + [120, 50]
    b = align_image(canvas, lm2, small_face, 64)
    assert np.allclose(a.landmarks, b.landmarks, atol=1e-6)
    # compare where both crops see the photo (the crop reaches past the 300² image's border)
    assert np.abs(a.image[16:48, 16:48].astype(float) - b.image[16:48, 16:48]).mean() < 4.0


def test_masks_from_label_images():
    lab = np.zeros((8, 8), np.uint8)
    lab[2:6, 2:6] = 1
    lab[3, 3] = 13   # hair
    lab[4, 4] = 12   # lower lip
    lab[5, 5] = 4    # eye
    m = skin_mask_from_labels(lab)
    assert m[2, 2] and m[4, 4] and not m[3, 3] and not m[5, 5] and not m[0, 0]
    assert set(CELEBAMASK_SKIN_LABELS) == {1, 2, 11, 12}


@pytest.fixture(scope="module")
def wild_small(tmp_path_factory):
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.synth.wild import WildConfig, synth_wild

    out = tmp_path_factory.mktemp("wildp")
    fm = procedural_face_model(grid=(61, 51), n_shape=6, n_exp=4, seed=2)
    cfg = WildConfig(count=4, size=96, images_per_identity=2, envmaps=1, envmap_width=64, prefilter_width=32,
                     uv_size=64, occluder_fraction=0.0, seed=1, landmark_noise=0.5)
    synth_wild(out, cfg, face_model=fm)
    return out, fm


def test_prepare_from_truth_shard_and_loader(wild_small, tmp_path):
    out, fm = wild_small
    cfg = PrepareConfig(size=96, from_truth=True, aligned=True, shard_size=3)
    p0, rep, err = prepare_wild_shard(out / "images", tmp_path, fm, out / "face_model.npz", cfg, 0, truth_dir=out)
    p1, _, _ = prepare_wild_shard(out / "images", tmp_path, fm, out / "face_model.npz", cfg, 1, truth_dir=out)
    assert not err and (tmp_path / "shard_00000_overlay.png").is_file()
    sh = open_shard(p0)
    assert len(sh) == 3 and len(open_shard(p1)) == 1
    assert np.allclose(rep["vertex_error_mm"], 0) and np.median(rep["landmark_rmse_px"]) < 1.5
    for k in ("truth_sh", "truth_vertex_albedo", "truth_vertex_weights", "truth_diffuse"):
        assert k in sh
    assert sh["truth_vertex_albedo"].shape == (3, fm.n_vertices, 3)
    # the shard's G-buffer, shaded with the truth reflectance's 3-lobe equivalent under the truth SH, is close to
    # the image's GGX truth layers (not equal: different BRDF, no visibility in the SH model)
    from reflectmm_cli.geometry.gbuffer import shade_gbuffer
    g = sh.gbuffer(0)
    d, s = shade_gbuffer(g, sh["truth_vertex_albedo"][0].astype(float), sh["truth_vertex_weights"][0].astype(float),
                         [1, 8, 64], sh["truth_sh"][0])
    yx = g["pix_yx"].astype(int)
    truth = (sh["truth_diffuse"][0].astype(float) + sh["truth_specular"][0])[yx[:, 0], yx[:, 1]]
    vis = g["visible"] & sh["skin_mask"][0][yx[:, 0], yx[:, 1]]
    rel = np.median(np.abs((d + s)[vis] - truth[vis]) / np.maximum(truth[vis], 1e-3))
    assert rel < 0.5
    from reflectmm_cli.finetune.shards import iter_batches

    seen = sum(len(b["names"]) for b in iter_batches([p0, p1], 2, split=None))
    assert seen == 4
    assert open_shard(p0).meta["face_model"]["path"].endswith("face_model.npz")
    # the geometry hash is reproducible and changes with the geometry
    from reflectmm_cli.finetune.data import geometry_hash
    a = {k: np.asarray(sh[k]) for k in ("image", "shape", "expression", "R", "t", "K")}
    assert sh.meta["geometry_sha256"] == geometry_hash(a, sh.meta["face_model"]["sha256"])
    a["t"] = a["t"] + 1e-9
    assert sh.meta["geometry_sha256"] != geometry_hash(a, sh.meta["face_model"]["sha256"])


def test_prepare_reports_bad_inputs_and_writes_the_others(wild_small, tmp_path, cli):
    out, fm = wild_small
    imgs, lms = tmp_path / "images", tmp_path / "landmarks"
    imgs.mkdir(), lms.mkdir()
    names = sorted(p.stem for p in (out / "images").iterdir())
    for n in names:
        shutil.copy(out / "images" / f"{n}.png", imgs / f"{n}.png")
    shutil.copy(out / "landmarks" / f"{names[0]}.pts", lms / f"{names[0]}.pts")
    write_pts(lms / f"{names[1]}.pts", np.zeros((67, 2)))                 # 67 landmarks
    (imgs / f"{names[2]}.png").write_bytes(b"not a png")                   # unreadable image
    shutil.copy(out / "landmarks" / f"{names[2]}.pts", lms / f"{names[2]}.pts")
    shutil.copy(out / "landmarks" / f"{names[3]}.pts", lms / "other_name.pts")   # name mismatch
    res = cli("prepare-wild", "--images", imgs, "--landmarks", lms, "--truth", out, "--from-truth", "--size", 96,
              "--out", tmp_path / "shards")
    assert res.exit_code == 1
    err = res.stderr
    assert f"{names[1]}.pts" in err and "67" in err
    assert f"{names[2]}.png" in err and "cannot read image" in err
    assert f"{names[3]}.png" in err and "no landmark file" in err
    sh = open_shard(tmp_path / "shards" / "shard_00000.npz")
    assert sh["names"].tolist() == [names[0]]
    assert len(sh.meta["skipped"]) == 3


def test_single_image_fit_on_synth_wild(wild_small):
    """Landmarks + order-2 SH photometric fit with one view: better than the mean face at the fitted pose."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.finetune.data import PrepareConfig, list_wild_inputs, prepare_wild_images

    out, fm = wild_small
    inputs = list_wild_inputs(out / "images")[:2]
    cfg = PrepareConfig(size=96, aligned=True, fit_landmark_iters=100, fit_photo_rounds=1, fit_photo_iters=15)
    arrays, rep, err = prepare_wild_images(inputs, fm, cfg, truth_dir=out)
    assert not err
    assert np.median(rep["landmark_rmse_px"]) < 2.0
    for i, inp in enumerate(inputs):
        tr = read_artifact(out / "truth" / f"{inp.name}.npz")
        vt = fm.vertices(tr["shape"], tr["expression"])
        vf = fm.vertices(arrays["shape"][i], arrays["expression"][i])
        vm = fm.vertices()
        R = arrays["R"][i]
        ct = vt @ tr["R"].T
        err_fit = np.sqrt((((vf @ R.T) - (vf @ R.T).mean(0) - (ct - ct.mean(0))) ** 2).sum(1).mean())
        err_mean = np.sqrt((((vm @ R.T) - (vm @ R.T).mean(0) - (ct - ct.mean(0))) ** 2).sum(1).mean())
        assert err_fit < 15.0
        assert err_fit <= err_mean + 0.5


def test_prepare_with_label_masks(wild_small, tmp_path):
    """Parsing labels written by the test: skin (1) inside the truth skin mask, hair (13) elsewhere, one lip
    pixel block (12) and one eye block (4); the shard's skin mask follows the labels."""
    import cv2

    from reflectmm_cli.artifacts import read_artifact

    out, fm = wild_small
    masks = tmp_path / "masks"
    masks.mkdir()
    names = sorted(p.stem for p in (out / "images").iterdir())[:2]
    want = {}
    for n in names:
        tr = read_artifact(out / "truth" / f"{n}.npz")
        lab = np.where(tr["skin_mask"], 1, 13).astype(np.uint8)
        lab[40:44, 40:44] = 4
        lab[60:62, 44:50] = 12
        cv2.imwrite(str(masks / f"{n}.png"), lab)
        want[n] = (np.isin(lab, [1, 2, 11, 12]), tr)
    imgs = tmp_path / "images"
    imgs.mkdir()
    for n in names:
        shutil.copy(out / "images" / f"{n}.png", imgs / f"{n}.png")
    cfg = PrepareConfig(size=96, from_truth=True, aligned=True, shard_size=8)
    p, rep, err = prepare_wild_shard(imgs, tmp_path / "s", fm, out / "face_model.npz", cfg, 0,
                                     landmarks_dir=out / "landmarks", masks_dir=masks, truth_dir=out)
    assert not err
    sh = open_shard(p)
    for i, n in enumerate(sh["names"].tolist()):
        lab_skin, tr = want[n]
        g = sh.gbuffer(i)
        vis = np.zeros((96, 96), bool)
        yx = g["pix_yx"][g["visible"]].astype(int)
        vis[yx[:, 0], yx[:, 1]] = True
        assert np.array_equal(sh["skin_mask"][i], lab_skin & vis & sh["face_mask"][i])
        assert not sh["skin_mask"][i][40:44, 40:44].any()
    assert "CelebAMask" in sh.meta["skin_labels"]


@settings(max_examples=40, deadline=None)
@given(s=st.floats(0.2, 8.0), tx=st.floats(-500, 1500), ty=st.floats(-500, 1500), H=st.integers(50, 3000),
       roll=st.floats(-0.3, 0.3))
def test_similarity_recovers_scale_and_centre(s, tx, ty, H, roll):
    """Property: for any scale, centre, image height and in-plane rotation, the orthographic fit returns the
    scale and the image position of the model origin (exactly up to rounding)."""
    X = np.array([[-32.0, 40, 90], [32, 40, 90], [0, 5, 118], [-25, -32, 92], [25, -32, 92]])
    c, sn = np.cos(roll), np.sin(roll)
    xy = X[:, :2] @ np.array([[c, -sn], [sn, c]]).T
    p = np.stack([s * xy[:, 0] + tx, ty - s * xy[:, 1]], 1)
    t, s_fit = similarity_from_five_points(p, X, H)
    assert s_fit == pytest.approx(s, rel=1e-6) and np.allclose(t, [tx, ty], atol=1e-6 * max(1, abs(tx), abs(ty)))


def test_prepare_real_alignment_path(wild_small, tmp_path):
    """Not aligned: a synth wild image pasted, enlarged, into a bigger photo is re-cropped with the Deep3D
    similarity and fitted; the fitted landmarks match the carried-over ones."""
    import cv2

    from reflectmm_cli.finetune.data import prepare_wild_images

    out, fm = wild_small
    n = sorted(p.stem for p in (out / "images").iterdir())[0]
    img = cv2.imread(str(out / "images" / f"{n}.png"))
    from reflectmm_cli.landmarks import read_landmarks
    lm = read_landmarks(out / "landmarks" / f"{n}.pts")
    big = cv2.resize(img, (192, 192), interpolation=cv2.INTER_CUBIC)
    canvas = np.full((300, 260, 3), 40, np.uint8)
    canvas[70:262, 30:222] = big
    (tmp_path / "im").mkdir()
    cv2.imwrite(str(tmp_path / "im" / "photo.png"), canvas)
    write_pts(tmp_path / "im" / "photo.pts", (lm + 0.5) * 2 - 0.5 + [30, 70])
    cfg = PrepareConfig(size=96, fit_landmark_iters=100, fit_photo_rounds=0)
    arrays, rep, err = prepare_wild_images(list_wild_inputs(tmp_path / "im"), fm, cfg)
    assert not err and arrays["image"].shape == (1, 96, 96, 3)
    assert rep["landmark_rmse_px"][0] < 2.5
    # the crop is centred on the face's centroid (the Deep3D convention), eyes above the nose
    l5 = arrays["landmarks"][0]
    assert l5[36:48, 1].mean() < l5[30, 1]
    from reflectmm_cli.finetune.align import model_centre
    from reflectmm_cli.geometry import Camera
    cam = Camera(arrays["K"][0], arrays["R"][0], arrays["t"][0], 96, 96)
    c, _ = cam.project(model_centre(fm)[None])
    assert np.abs(c[0] - 48).max() < 6
    assert arrays["skin_mask"][0].sum() > 0.3 * arrays["face_mask"][0].sum()


def test_prepare_wild_is_a_per_shard_recipe_stage(wild_small, tmp_path):
    from reflectmm_cli.recipes import run_recipe

    out, fm = wild_small
    ws = tmp_path / "ws"
    shutil.copytree(out, ws / "wild")
    (ws / "recipe.toml").write_text("""
schema = "reflectmm.recipe/1"
[stages.prepare-wild]
foreach = "all found"
inputs = { images = "wild/images", truth = "wild", face_model = "wild/face_model.npz" }
params = { shard_size = 3, from_truth = true, aligned = true, size = 96 }
""")
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok, [t.error for t in rep.tasks]
    assert sorted(t.tid for t in rep.tasks) == ["prepare-wild/shard_00000", "prepare-wild/shard_00001"]
    assert len(open_shard(ws / "prepare-wild" / "shard_00000.npz")) == 3
    again = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert {t.status for t in again.tasks} == {"skip"}
    # changing one image of the second shard reruns only that shard
    last = sorted((ws / "wild" / "images").iterdir())[-1]
    last.write_bytes((ws / "wild" / "images" / sorted(p.name for p in (ws / "wild" / "images").iterdir())[0])
                     .read_bytes())
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert {t.tid: t.status for t in plan.tasks} == {"prepare-wild/shard_00000": "skip",
                                                     "prepare-wild/shard_00001": "run"}


@pytest.mark.parametrize("allow", [False, True])
def test_a_shard_with_skipped_images_is_not_up_to_date_unless_skips_are_allowed(wild_small, tmp_path, allow):
    from reflectmm_cli.recipes import run_recipe

    out, fm = wild_small
    ws = tmp_path / "ws"
    shutil.copytree(out, ws / "wild")
    bad = sorted((ws / "wild" / "images").iterdir())[1]
    bad.write_bytes(b"not a png")
    (ws / "recipe.toml").write_text(f"""
schema = "reflectmm.recipe/1"
[stages.prepare-wild]
foreach = "all found"
inputs = {{ images = "wild/images", truth = "wild", face_model = "wild/face_model.npz" }}
params = {{ shard_size = 4, from_truth = true, aligned = true, size = 96, allow_skipped = {str(allow).lower()} }}
""")
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok == allow, [t.error for t in rep.tasks]
    shard = ws / "prepare-wild" / "shard_00000.npz"
    sh = open_shard(shard)
    assert len(sh) == 3 and len(sh.meta["skipped"]) == 1  # the others were written either way
    again = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    # without allow_skipped the failed shard is tried (and reported) again instead of being called up to date
    assert {t.status for t in again.tasks} == ({"skip"} if allow else {"run"}), [t.reason for t in again.tasks]


def test_a_shard_written_allowing_skips_is_stale_for_a_run_that_allows_none(wild_small, tmp_path):
    """allow_skipped does not key the cache (it only decides the exit status), so the shard an allowing run wrote
    keeps a valid key; a run that allows no skips must still try those images again (the stage's ``stale`` hook),
    not call the shard up to date."""
    from reflectmm_cli.recipes import run_recipe

    out, fm = wild_small
    ws = tmp_path / "ws"
    shutil.copytree(out, ws / "wild")
    sorted((ws / "wild" / "images").iterdir())[1].write_bytes(b"not a png")
    recipe = """
schema = "reflectmm.recipe/1"
[stages.prepare-wild]
foreach = "all found"
inputs = {{ images = "wild/images", truth = "wild", face_model = "wild/face_model.npz" }}
params = {{ shard_size = 4, from_truth = true, aligned = true, size = 96, allow_skipped = {allow} }}
"""
    (ws / "recipe.toml").write_text(recipe.format(allow="true"))
    assert run_recipe(ws / "recipe.toml", ws).ok
    assert {t.status for t in run_recipe(ws / "recipe.toml", ws, dry_run=True).tasks} == {"skip"}
    (ws / "recipe.toml").write_text(recipe.format(allow="false"))
    again = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert {t.status for t in again.tasks} == {"run"}
    assert any("skipped" in (t.reason or "") for t in again.tasks), [t.reason for t in again.tasks]


@pytest.mark.parametrize("from_truth", [True, False])
def test_landmarks_far_outside_the_frame_are_refused(wild_small, tmp_path, cli, from_truth):
    """Issue 24 §6: landmarks 1e6 px outside the frame went through (a vertex error of 5438 mm in the shard); now
    the image is skipped with the landmark file named, as preprocess-multipie and fit-geometry refuse it."""
    out, fm = wild_small
    imgs, lms = tmp_path / "images", tmp_path / "landmarks"
    imgs.mkdir(), lms.mkdir()
    names = sorted(p.stem for p in (out / "images").iterdir())[:2]
    for n in names:
        shutil.copy(out / "images" / f"{n}.png", imgs / f"{n}.png")
        shutil.copy(out / "landmarks" / f"{n}.pts", lms / f"{n}.pts")
    pts = np.loadtxt(out / "landmarks" / f"{names[1]}.pts", skiprows=3, comments="}")
    pts[7] = [1e6, 50.0]
    write_pts(lms / f"{names[1]}.pts", pts)
    args = ["prepare-wild", "--images", imgs, "--landmarks", lms, "--truth", out, "--size", 96, "--out",
            tmp_path / "shards"] + (["--from-truth"] if from_truth else [])
    res = cli(*args)
    assert res.exit_code == 1
    assert f"{names[1]}.pts" in res.stderr and "far outside" in res.stderr
    sh = open_shard(tmp_path / "shards" / "shard_00000.npz")
    assert sh["names"].tolist() == [names[0]]


def test_from_truth_at_another_size_resamples_the_truth_layers(wild_small, tmp_path, cli):
    """Issue 24 §6: --from-truth --size 64 on 96 px images stopped with an internal broadcast error; the truth's
    skin mask and layers are now resampled to the crop like the image (and agree with a crop at full size)."""
    out, fm = wild_small
    shards = {}
    for size in (96, 64):
        r = cli("prepare-wild", "--images", out / "images", "--truth", out, "--from-truth", "--size", size, "--out",
                tmp_path / f"s{size}")
        assert r.exit_code == 0, r.stderr
        shards[size] = open_shard(tmp_path / f"s{size}" / "shard_00000.npz")
    sh = shards[64]
    n = len(sh["names"])
    assert sh["image"].shape == (n, 64, 64, 3) and sh["skin_mask"].shape == (n, 64, 64)
    assert sh["truth_diffuse"].shape == (n, 64, 64, 3) and sh["truth_specular"].shape == (n, 64, 64, 3)
    full = np.asarray(shards[96]["truth_diffuse"], np.float32).mean(axis=(1, 2))
    small = np.asarray(sh["truth_diffuse"], np.float32).mean(axis=(1, 2))
    np.testing.assert_allclose(small, full, rtol=0.05, atol=2e-3)  # the same picture, fewer pixels
    assert abs(sh["skin_mask"].mean() - shards[96]["skin_mask"].mean()) < 0.03


def test_an_image_resized_after_synth_wild_is_named_as_the_problem(wild_small, tmp_path, cli):
    """--from-truth on an image made smaller than synth wild wrote it (its landmarks and truth at the old size): the
    refusal names the image and the size, not only the landmark file as if its points were wrong."""
    import cv2

    out, fm = wild_small
    imgs = tmp_path / "images"
    imgs.mkdir()
    names = sorted(p.stem for p in (out / "images").iterdir())[:2]
    for n in names:
        shutil.copy(out / "images" / f"{n}.png", imgs / f"{n}.png")
    small = cv2.imread(str(imgs / f"{names[1]}.png"))
    cv2.imwrite(str(imgs / f"{names[1]}.png"), cv2.resize(small, (24, 24), interpolation=cv2.INTER_AREA))
    res = cli("prepare-wild", "--images", imgs, "--landmarks", out / "landmarks", "--truth", out, "--from-truth",
              "--size", 96, "--out", tmp_path / "shards")
    assert res.exit_code == 1
    line = next(x for x in res.stderr.splitlines() if f"{names[1]}.png" in x)
    assert "24x24" in line and "resized" in line
    assert open_shard(tmp_path / "shards" / "shard_00000.npz")["names"].tolist() == [names[0]]

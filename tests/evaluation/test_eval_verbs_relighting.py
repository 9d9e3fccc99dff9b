"""evaluate relighting (Fig. 7) through the CLI: one image of a synthetic identity → encoders → held-out flashes,
against OLAT images rendered independently (render_point_light with its own shadow rays)."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "finetune"))

from _shards import small_light_model  # noqa: E402

from reflectmm_cli.artifacts import read_artifact, read_image, write_artifact  # noqa: E402
from reflectmm_cli.geometry import RayScene, has_embree, look_at, procedural_face_model, render_point_light  # noqa
from reflectmm_cli.geometry.face_model import save_face_model  # noqa: E402
from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_arrays  # noqa: E402
from reflectmm_cli.model.pca import MODEL_KIND, ReflectanceModel, model_arrays  # noqa: E402

pytestmark = pytest.mark.skipif(not has_embree(), reason="needs embreex")

FLASHES = ["07", "05", "11"]
POS = np.array([[0.0, 50.0, 900.0], [350.0, 80.0, 700.0], [-450.0, 0.0, 500.0]])
INTENSITY = np.full(3, 1.2 * 900.0 ** 2)
X0, Y0, W, H = 12, 8, 120, 136


def _model(albedo, weights, exponents, m=2, seed=0):
    rng = np.random.default_rng(seed)
    nv, K = weights.shape
    B = rng.normal(size=(m, nv, 3))
    B /= np.linalg.norm(B.reshape(m, -1), axis=1)[:, None, None]
    S = 8
    return ReflectanceModel(
        albedo_mean=np.zeros((3, S, S), np.float32), albedo_basis=np.zeros((m, 3, S, S), np.float32),
        weights_mean=np.zeros((K, S, S), np.float32), weights_basis=np.zeros((m, K, S, S), np.float32),
        sigma=np.full(m, 0.5, np.float32), explained_variance=np.full(m, 0.25, np.float32),
        explained_variance_ratio=np.full(m, 0.5, np.float32), exponents=np.asarray(exponents, np.float32),
        mask=np.ones((S, S), bool), train_coeffs=np.zeros((2, m), np.float32), ids=["a", "b"],
        vertex_albedo_mean=albedo.astype(np.float32), vertex_albedo_basis=B.astype(np.float32),
        vertex_weights_mean=weights.astype(np.float32), vertex_weights_basis=np.zeros((m, nv, K), np.float32))


def _write_world(tmp, fm, albedo, weights):
    """Capture (room + 3 OLAT of one view, cropped window), geometry and face model of one identity."""
    from reflectmm_cli.geometry.camera import project

    v = fm.mean_shape.astype(np.float64)
    cam = look_at((60.0, 20.0, 650.0), (0.0, 10.0, 0.0), focal_px=260.0, width=150, height=160)
    scene = RayScene(v, fm.triangles)
    win = (slice(Y0, Y0 + H), slice(X0, X0 + W))
    olat = np.stack([render_point_light(scene, cam, albedo, weights, [1.0, 8.0, 64.0], p, i, shadows=True).image[win]
                     for p, i in zip(POS, INTENSITY)])
    room = 0.3 * render_point_light(scene, cam, albedo, np.zeros_like(weights), [1.0, 8.0, 64.0], cam.center,
                                    INTENSITY[0], shadows=False).image[win]
    lm, _ = project(v[fm.landmarks], cam.K, cam.R, cam.t)
    capture = {"olat": olat[None].astype(np.float32), "room": room[None].astype(np.float32),
               "saturated": np.zeros((1, 3, H, W), bool), "view_names": np.array(["05_1"]),
               "flash_ids": np.array(FLASHES), "image_size": np.array([150, 160], np.int32),
               "crop_origin": np.array([[X0, Y0]]), "landmarks": lm[None].astype(np.float32)}
    write_artifact(tmp / "capture.npz", "capture", capture, extra_meta={"identity": "900"})
    geometry = {"vertices": v.astype(np.float32), "view_names": np.array(["05_1"]), "K": cam.K[None],
                "R": cam.R[None], "t": cam.t[None], "flash_ids": np.array(FLASHES), "flash_pos": POS,
                "flash_intensity": INTENSITY, "image_size": np.array([150, 160], np.int32),
                "cam_centers": cam.center[None]}
    write_artifact(tmp / "geometry.npz", "geometry", geometry, extra_meta={"identity": "900"})
    save_face_model(fm, tmp / "face_model.npz")
    return cam, room, capture, geometry


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    import torch

    from reflectmm_cli.finetune.encoder import build_encoder, save_encoder

    tmp = tmp_path_factory.mktemp("relight")
    fm = procedural_face_model(n_vertices=3000)
    v = fm.mean_shape.astype(np.float64)
    x = (v - v.min(0)) / np.ptp(v, 0)
    albedo = np.stack([0.5 + 0.2 * x[:, 0], 0.35 + 0.1 * x[:, 1], 0.25 + 0.05 * x[:, 2]], 1)
    weights = np.stack([0.02 + 0.01 * x[:, 1], 0.03 + 0.02 * x[:, 0], 0.01 * x[:, 2]], 1)
    cam, room, capture, geometry = _write_world(tmp, fm, albedo, weights)
    light = small_light_model(order=2)
    write_artifact(tmp / "light.npz", LIGHT_MODEL_KIND, light_model_arrays(light))
    write_artifact(tmp / "truth_model.npz", MODEL_KIND, model_arrays(_model(albedo, weights, [1.0, 8.0, 64.0])))
    write_artifact(tmp / "diffuse_model.npz", MODEL_KIND,
                   model_arrays(_model(albedo, np.zeros((len(v), 1)), [1.0])))
    torch.manual_seed(0)
    enc = build_encoder("resnet18", 2, light.n_components, width=8, z0=2.0)  # zero head: β = 0 (the model mean)
    save_encoder(enc, tmp / "encoder.safetensors", {})
    return {"tmp": tmp, "fm": fm, "cam": cam, "room": room, "capture": capture, "geometry": geometry}


def _args(world, *extra):
    t = world["tmp"]
    return ["evaluate", "relighting", "--id", "900", "--capture", t / "capture.npz", "--geometry",
            t / "geometry.npz", "--face-model", t / "face_model.npz", "--light-model", t / "light.npz",
            "--size", "64", "-w", t, *extra]


def test_evaluate_relighting_cli(world, cli):
    t = world["tmp"]
    r = cli("-q", *_args(world, "--input", "07", "--method", "truth", t / "truth_model.npz", t / "encoder.safetensors",
                         "--method", "diffuse-only", t / "diffuse_model.npz", t / "encoder.safetensors"))
    assert r.exit_code == 0, r.stderr
    out = t / "evaluate-relighting" / "900.npz"
    art = read_artifact(out, "evaluation")
    s = art.meta["summary"]
    assert art.meta["holdout"] == ["05", "11"] and art.meta["coefficients_from"]["truth"] == "encoder"
    # β = 0 gives the identity's own reflectance: the relit images equal the independent OLAT renders
    assert s["truth"]["psnr"] == 100.0 and s["truth"]["scale"] == pytest.approx(1.0, abs=1e-9)
    assert s["diffuse-only"]["psnr"] < 60 and s["diffuse-only"]["ssim"] < s["truth"]["ssim"]
    assert read_image(out.with_suffix(".png")).shape[:2] == (3 * (H + 2) + 2, 5 * (W + 2) + 2)
    md = out.with_suffix(".md").read_text()
    assert "| truth | encoder |" in md and "reflectmm evaluate relighting --id 900" in md
    # the room-light input works the same way (the zero head does not depend on the image)
    r = cli("-q", *_args(world, "--method", "truth", t / "truth_model.npz", t / "encoder.safetensors",
                         "-o", t / "room.npz"))
    assert r.exit_code == 0, r.stderr
    a = read_artifact(t / "room.npz", "evaluation")
    assert a.meta["holdout"] == FLASHES and a.meta["summary"]["truth"]["psnr"] == 100.0
    # the report's relighting section (one per identity); no paper table without Tables 2/3
    r = cli("-q", "evaluate", "report", "-w", t)
    assert r.exit_code == 0, r.stderr
    rep = (t / "evaluate-report" / "evaluate-report.md").read_text()
    assert "## Relighting (Fig. 7)" in rep and "### Identity 900: view 05_1, input 07" in rep
    assert "![relighting 900](../evaluate-relighting/900.png)" in rep and "## Paper vs reflectmm" not in rep


def test_input_crop_gbuffer_lines_up_with_the_aligned_image(world):
    """The crop's G-buffer (fitted geometry seen by the composed crop camera) covers the pixels where the warped
    image shows the face — also with noisy landmarks (they move the crop, and the G-buffer moves with it)."""
    from reflectmm_cli.stages.evaluation_inputs import input_crop

    cap, geo = world["capture"], world["geometry"]
    noisy = cap["landmarks"][0] + np.random.default_rng(1).normal(0, 1.5, (68, 2))  # a detector's landmarks
    for size, lm in ((64, cap["landmarks"][0]), (96, cap["landmarks"][0]), (64, noisy)):
        crop = input_crop(world["room"], cap["crop_origin"][0], lm, geo["K"][0], geo["R"][0],
                          geo["t"][0], geo["vertices"], world["fm"], size=size, encoding="linear")
        face = crop["image"].max(-1) > 3
        gb = crop["gbuffer"]["face_mask"]
        iou = (face & gb).sum() / (face | gb).sum()
        assert crop["image"].shape == (size, size, 3) and iou > 0.9, iou
        assert 0.15 < gb.mean() < 0.9


def test_evaluate_relighting_bad_inputs(world, cli, tmp_path):
    t = world["tmp"]
    m = ["--method", "truth", t / "truth_model.npz", "-", "-o", tmp_path / "x.npz"]
    r = cli(*_args(world, "--input", "07", *m))
    assert r.exit_code == 1 and "give the identity's uv-observations" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = cli(*_args(world, "--observations", t / "capture.npz", *m))
    assert r.exit_code == 1 and "needs a flash input" in r.stderr
    enc = ["--method", "truth", t / "truth_model.npz", t / "encoder.safetensors", "-o", tmp_path / "x.npz"]
    r = cli(*_args(world, "--input", "07", "--holdout", "07,05", *enc))
    assert r.exit_code == 1 and "flash '07' is the input image" in r.stderr
    r = cli(*_args(world, "--input", "03", *enc))
    assert r.exit_code == 1 and "input '03'" in r.stderr
    r = cli(*_args(world, "--view", "04_1", *enc))
    assert r.exit_code == 1 and "view '04_1'" in r.stderr
    r = cli(*_args(world, "--exposure", "0", *enc))
    assert r.exit_code == 1 and "--exposure" in r.stderr
    # another identity's geometry was relit with this identity's images (exit 0)
    from reflectmm_cli.artifacts import read_artifact, write_artifact

    g = read_artifact(t / "geometry.npz", "geometry")
    write_artifact(tmp_path / "g901.npz", "geometry", dict(g.arrays), extra_meta={"identity": "901"})
    r = cli(*[a if a != t / "geometry.npz" else tmp_path / "g901.npz" for a in _args(world, *enc)])
    assert r.exit_code == 1 and "is identity 901's geometry, but this task is for identity 900" in r.stderr
    assert not (tmp_path / "x.npz").exists()


def test_encoder_free_fit_path_recovers_a_constant_albedo(tmp_path, cli):
    """Without an encoder, β is fitted to the input flash's UV observations: a model whose mean albedo is 30 %
    too dark along its one basis recovers the identity's constant albedo, so the relit held-out flashes match the
    captures without any scale (--scale none)."""
    from reflectmm_cli.observations.unwrap import unwrap_observations

    fm = procedural_face_model(n_vertices=3000)
    nv = fm.mean_shape.shape[0]
    c, w = np.array([0.55, 0.4, 0.3]), np.array([0.02, 0.03, 0.01])
    _, _, capture, geometry = _write_world(tmp_path, fm, np.tile(c, (nv, 1)), np.tile(w, (nv, 1)))
    S = 32
    obs, _ = unwrap_observations(capture, geometry, fm.triangles, fm.uv, uv_size=S)
    write_artifact(tmp_path / "obs.npz", "uv-observations", obs, extra_meta={"identity": "900"})
    b = np.ones((3, S, S)) * c[:, None, None]
    sigma = 0.1 * np.linalg.norm(b)
    model = ReflectanceModel(
        albedo_mean=(0.7 * b).astype(np.float32), albedo_basis=(b / np.linalg.norm(b))[None].astype(np.float32),
        weights_mean=(np.ones((3, S, S)) * w[:, None, None]).astype(np.float32),
        weights_basis=np.zeros((1, 3, S, S), np.float32), sigma=np.array([sigma], np.float32),
        explained_variance=np.array([sigma ** 2], np.float32), explained_variance_ratio=np.ones(1, np.float32),
        exponents=np.array([1.0, 8.0, 64.0], np.float32), mask=np.ones((S, S), bool),
        train_coeffs=np.zeros((2, 1), np.float32), ids=["a", "b"])
    write_artifact(tmp_path / "uvmodel.npz", MODEL_KIND, model_arrays(model))
    r = cli("-q", "evaluate", "relighting", "--id", "900", "--capture", tmp_path / "capture.npz", "--geometry",
            tmp_path / "geometry.npz", "--face-model", tmp_path / "face_model.npz", "--observations",
            tmp_path / "obs.npz", "--input", "07", "--scale", "none", "--prior", "0",
            "--method", "model-fit", tmp_path / "uvmodel.npz", "-", "-w", tmp_path)
    assert r.exit_code == 0, r.stderr
    art = read_artifact(tmp_path / "evaluate-relighting" / "900.npz", "evaluation")
    beta = art["values"][list(art["names"]).index("model-fit.beta[0]")]
    # 0.3·‖b‖ = β·σ → β = 3 exactly for a perfect fit
    assert beta == pytest.approx(3.0, rel=5e-3), beta
    assert art.meta["coefficients_from"]["model-fit"] == "fit (no encoder)"
    assert art.meta["summary"]["model-fit"]["psnr"] > 60


def test_evaluate_relighting_with_refinement(world, cli):
    """--refine refines the encoder's β (and the light) on the input image before relighting; the table says
    which path each method took. A model with one component per identity-truth reflectance: β stays the truth's
    (0) within the refinement's tolerance, so relighting stays near-perfect."""
    t = world["tmp"]
    r = cli("-q", *_args(world, "--input", "07", "--method", "truth", t / "truth_model.npz", t / "encoder.safetensors",
                         "--refine", "-o", t / "refined.npz"))
    assert r.exit_code == 0, r.stderr
    art = read_artifact(t / "refined.npz", "evaluation")
    assert art.meta["coefficients_from"]["truth"] == "encoder + refine"
    assert art.meta["summary"]["truth"]["psnr"] > 35
    assert "| truth | encoder + refine |" in (t / "refined.md").read_text()

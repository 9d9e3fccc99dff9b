"""End-to-end: face-model create / import / export / info and render through the CLI."""
import json

import numpy as np
import pytest
import scipy.io
import trimesh

from reflectmm_cli.artifacts import read_artifact, read_exr, read_image, write_artifact
from reflectmm_cli.geometry import (
    RayScene,
    load_face_model,
    parse_camera_spec,
    procedural_face_model,
    rasterize,
    vertex_normals,
)
from reflectmm_cli.shading import shade_directional

EXPS = np.array([1.0, 8.0, 64.0])


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    return tmp_path_factory.mktemp("geomcli")


@pytest.fixture(scope="module")
def model_file(ws):
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    res = CliRunner().invoke(main, ["face-model", "create", "--out", str(ws / "fm.npz"), "--vertices", "3000",
                                    "--shape-components", "6", "--exp-components", "4", "--seed", "2"],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return ws / "fm.npz"


def _maps(path, S=64, const=False):
    u = (np.arange(S) + 0.5) / S
    U, V = np.meshgrid(u, u)
    if const:
        alb = np.broadcast_to(np.array([0.5, 0.35, 0.25])[:, None, None], (3, S, S))
        w = np.broadcast_to(np.array([0.03, 0.06, 0.1])[:, None, None], (3, S, S))
    else:
        alb = np.stack([0.4 + 0.2 * U, 0.3 + 0.1 * V, 0.25 + 0 * U])
        w = np.stack([0.02 + 0 * U, 0.05 * V, 0.1 * U])
    write_artifact(path, "reflectance-maps", {"albedo": alb.astype(np.float32), "weights": w.astype(np.float32),
                                              "exponents": EXPS, "mask": np.ones((S, S), bool)})
    return path


def test_create_writes_artifact_and_preview(model_file, ws):
    art = read_artifact(model_file, "face-model")
    assert art["mean_shape"].shape[0] > 2500 and art["shape_basis"].shape[0] == 6
    assert art.meta["params"]["vertices"] == 3000 and art.meta["producer"]["stage"] == "face-model-create"
    png = read_image(ws / "fm.png")
    assert png.shape[2] == 3 and png.std() > 0.05


def test_create_is_deterministic(cli, tmp_path, model_file):
    outs = []
    for name in ("a.npz", "b.npz"):
        r = cli("face-model", "create", "--out", tmp_path / name, "--vertices", 3000, "--shape-components", 6,
                "--exp-components", 4, "--seed", 2, "--no-preview")
        assert r.exit_code == 0
        outs.append((tmp_path / name).read_bytes())
    assert outs[0] == outs[1]  # byte-identical reruns
    assert not (tmp_path / "a.png").exists()
    a, b = read_artifact(tmp_path / "a.npz"), read_artifact(model_file)
    for k in b.arrays:
        np.testing.assert_array_equal(a[k], b[k])


def test_export_obj_and_ply_with_uvs(cli, model_file, tmp_path):
    m = load_face_model(model_file)
    r = cli("face-model", "export", model_file, "--out", tmp_path / "m.obj", "--coeffs", "1,0.5", "--sigma-units")
    assert r.exit_code == 0, r.output
    assert r.stdout.strip() == str(tmp_path / "m.obj")
    mesh = trimesh.load(tmp_path / "m.obj", process=False)
    np.testing.assert_allclose(mesh.vertices, m.vertices(np.array([1.0, 0.5]) * m.shape_sigma[:2]), atol=1e-4)
    np.testing.assert_array_equal(mesh.faces, m.triangles)
    np.testing.assert_allclose(mesh.visual.uv[:, 0], m.uv[:, 0], atol=1e-6)
    np.testing.assert_allclose(mesh.visual.uv[:, 1], 1 - m.uv[:, 1], atol=1e-6)  # OBJ v points up
    assert cli("face-model", "export", model_file, "--out", tmp_path / "m.ply").exit_code == 0
    ply = trimesh.load(tmp_path / "m.ply", process=False)
    np.testing.assert_allclose(ply.vertices, m.mean_shape, atol=1e-4)
    assert ply.visual.uv is not None and np.allclose(ply.visual.uv[:, 0], m.uv[:, 0], atol=1e-6)
    bad = cli("face-model", "export", model_file, "--out", tmp_path / "m.xyz")
    assert bad.exit_code == 1 and "unsupported mesh format" in bad.stderr


def test_import_bfm_front_and_info(cli, tmp_path):
    src = procedural_face_model(grid=(31, 25), n_shape=3, n_exp=2)
    n = src.n_vertices
    d = {"meanshape": (src.mean_shape * 0.01).reshape(1, -1),
         "idBase": src.shape_basis.reshape(3, -1).T * 0.01, "exBase": src.exp_basis.reshape(2, -1).T * 0.01,
         "meantex": np.full((1, 3 * n), 128.0), "texBase": np.zeros((3 * n, 2)),
         "tri": (src.triangles + 1).astype(float), "point_buf": np.ones((n, 8)),
         "keypoints": (src.landmarks + 1)[None].astype(float), "skinmask": np.ones((1, n))}
    scipy.io.savemat(str(tmp_path / "BFM_model_front.mat"), d)
    r = cli("face-model", "import", tmp_path / "BFM_model_front.mat", "--out", tmp_path / "d3d.npz")
    assert r.exit_code == 0, r.stderr
    m = load_face_model(tmp_path / "d3d.npz")
    np.testing.assert_allclose(m.mean_shape, src.mean_shape - src.mean_shape.mean(0), atol=2e-3)
    assert m.info["uv"] == "cylindrical (computed)"
    info = cli("face-model", "info", tmp_path / "d3d.npz", "--json")
    doc = json.loads(info.stdout)
    assert doc["vertices"] == n and doc["landmarks"] == 68
    dist = doc["info"]["uv_distortion"]  # the computed layout's distortion is reported
    assert 0 < dist["area_ratio_p5"] <= dist["area_ratio_median"] <= dist["area_ratio_p95"]
    assert dist["flipped_fraction"] == 0.0
    miss = cli("face-model", "import", tmp_path / "nope.mat", "--out", tmp_path / "x.npz")
    assert miss.exit_code == 1 and "nope.mat" in miss.stderr


def test_render_point_light_matches_independent_shading(cli, model_file, ws):
    maps = _maps(ws / "maps_const.npz", const=True)
    out = ws / "r.exr"
    r = cli("render", "--face-model", model_file, "--maps", maps, "--point-light", "300,100,900:2e6",
            "--camera", "yaw=15,size=160x120,focal=400", "--output", out)
    assert r.exit_code == 0, r.stderr
    assert r.stdout.split() == [str(out), str(out.with_suffix(".png"))]
    ch, meta = read_exr(out)
    assert sorted(ch) == ["B", "G", "R"] and meta["schema"] == "reflectmm.render/1"
    img = np.stack([ch["R"], ch["G"], ch["B"]], -1)
    # independent: rasterise the same geometry and evaluate the shading formula per pixel
    m = load_face_model(model_file)
    cam = parse_camera_spec("yaw=15,size=160x120,focal=400")
    np.testing.assert_allclose(meta["camera"]["K"], cam.K)
    v = m.mean_shape.astype(np.float64)
    ras = rasterize(RayScene(v, m.triangles, vertex_normals(v, m.triangles)), cam)
    x, n = ras.position[ras.mask].astype(np.float64), ras.normal[ras.mask].astype(np.float64)
    L = np.array([300.0, 100.0, 900.0])
    E = np.repeat(2e6 / ((L - x) ** 2).sum(1, keepdims=True), 3, axis=1)
    ref = shade_directional(np.array([0.5, 0.35, 0.25]), np.array([0.03, 0.06, 0.1]), EXPS, n, L - x,
                            cam.center - x, E)
    np.testing.assert_allclose(img[ras.mask], ref, rtol=1e-4, atol=1e-6)
    assert np.all(img[~ras.mask] == 0)


def test_render_shadows_darken_and_envmap(cli, model_file, ws, tmp_path):
    maps = _maps(ws / "maps.npz")
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    common = ["--face-model", model_file, "--maps", maps, "--camera", "size=160x120,focal=400"]
    assert cli("render", *common, "--point-light", "700,0,600", "-o", a).exit_code == 0
    r = cli("render", *common, "--point-light", "700,0,600", "--shadows", "-o", b)
    assert r.exit_code == 0
    rays = read_exr(b)[1]["light"]["shadow_rays"]
    assert rays["cast"] > 0 and rays["skipped"] > 0  # far-side pixels (n·l ≤ 0) cost no ray
    ia, ib = read_exr(a)[0]["R"], read_exr(b)[0]["R"]
    assert np.all(ib <= ia + 1e-7) and (ib < ia - 1e-6).sum() > 10  # the nose shadows the far cheek
    # SH from a file and an EXR environment map give finite, positive images
    np.save(tmp_path / "sh.npy", np.concatenate([np.full((3, 1), 2.0), np.zeros((3, 8))], 1))
    assert cli("render", *common, "--sh", tmp_path / "sh.npy", "-o", tmp_path / "c.exr").exit_code == 0
    c = read_exr(tmp_path / "c.exr")[0]["G"]
    assert np.isfinite(c).all() and c.max() > 0
    from reflectmm_cli.artifacts import write_exr

    env = np.full((16, 32), 1.5, np.float32)
    write_exr(tmp_path / "env.exr", {"R": env, "G": env, "B": env})
    r = cli("render", *common, "--envmap", tmp_path / "env.exr", "--sh-order", 2, "-o", tmp_path / "d.exr")
    assert r.exit_code == 0, r.stderr
    dimg = read_exr(tmp_path / "d.exr")[0]["R"]
    assert np.isfinite(dimg).all() and dimg.max() > 0


def test_render_errors(cli, model_file, ws, tmp_path):
    maps = _maps(ws / "maps.npz")
    r = cli("render", "--face-model", model_file, "--maps", maps, "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and "exactly one light" in r.stderr
    r = cli("render", "--face-model", model_file, "--maps", maps, "--point-light", "1,2", "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and "--point-light" in r.stderr
    r = cli("render", "--face-model", model_file, "--maps", model_file, "--point-light", "0,0,900",
            "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and "face-model" in r.stderr and "reflectance-maps" in r.stderr


def test_render_reflectance_model_at_coeffs_equals_maps(cli, model_file, ws, tmp_path):
    """--model at β renders exactly like --maps holding the model's sample at β (computed independently)."""
    from reflectmm_cli.model import fit_reflectance_pca, model_arrays

    rng = np.random.default_rng(0)
    S = 32
    albs = [rng.uniform(0.2, 0.7, (3, S, S)).astype(np.float32) for _ in range(4)]
    wts = [rng.uniform(0.0, 0.2, (3, S, S)).astype(np.float32) for _ in range(4)]
    model = fit_reflectance_pca(albs, wts, EXPS, components=3)
    write_artifact(tmp_path / "rm.npz", "reflectance-model", model_arrays(model))
    beta = np.array([1.0, -0.5])
    coef = beta * model.sigma[:2]
    alb = model.albedo_mean + np.tensordot(coef, model.albedo_basis[:2], axes=(0, 0))
    w = model.weights_mean + np.tensordot(coef, model.weights_basis[:2], axes=(0, 0))
    write_artifact(tmp_path / "m.npz", "reflectance-maps", {"albedo": alb.astype(np.float32),
                                                            "weights": w.astype(np.float32), "exponents": EXPS})
    common = ["--face-model", model_file, "--point-light", "0,100,900", "--camera", "size=96x72,focal=250"]
    assert cli("render", *common, "--model", tmp_path / "rm.npz", "--coeffs", "1,-0.5",
               "-o", tmp_path / "a.exr").exit_code == 0
    assert cli("render", *common, "--maps", tmp_path / "m.npz", "-o", tmp_path / "b.exr").exit_code == 0
    a, b = read_exr(tmp_path / "a.exr")[0], read_exr(tmp_path / "b.exr")[0]
    for c in "RGB":
        np.testing.assert_allclose(a[c], b[c], rtol=1e-5, atol=1e-7)
    r = cli("render", *common, "--model", tmp_path / "rm.npz", "--coeffs", "1,2,3,4,5", "-o", tmp_path / "c.exr")
    assert r.exit_code == 1 and "coefficients" in r.stderr


def test_import_bfm09_with_expressions_and_landmarks(cli, tmp_path):
    src = procedural_face_model(grid=(31, 25), n_shape=3, n_exp=2)
    n = src.n_vertices
    scipy.io.savemat(str(tmp_path / "01_MorphableModel.mat"), {
        "shapeMU": (src.mean_shape.astype(np.float64) * 1000).reshape(-1, 1),
        "shapePC": src.shape_basis.reshape(3, -1).T.astype(np.float64),
        "shapeEV": (src.shape_sigma.astype(np.float64) * 1000)[:, None],
        "tl": (src.triangles + 1).astype(np.float64)})
    K = 2
    basis = (src.exp_basis.reshape(K, -1) * 1000).astype("<f4")
    with open(tmp_path / "Exp_Pca.bin", "wb") as f:
        f.write(np.int32(K).tobytes() + np.zeros(3 * n, "<f4").tobytes() + basis.tobytes())
    np.savetxt(tmp_path / "lm.anl", src.landmarks + 1, fmt="%d")
    r = cli("face-model", "import", tmp_path / "01_MorphableModel.mat", "--out", tmp_path / "bfm.npz",
            "--exp", tmp_path / "Exp_Pca.bin", "--landmarks", tmp_path / "lm.anl", "--no-preview")
    assert r.exit_code == 0, r.stderr
    m = load_face_model(tmp_path / "bfm.npz")
    np.testing.assert_allclose(m.mean_shape, src.mean_shape, atol=1e-3)
    np.testing.assert_allclose(m.exp_basis, src.exp_basis, atol=1e-5)
    np.testing.assert_array_equal(m.landmarks, src.landmarks)
    art = read_artifact(tmp_path / "bfm.npz")
    assert {i["role"] for i in art.meta["inputs"]} == {"model", "exp", "landmarks"}
    np.savetxt(tmp_path / "bad.anl", np.arange(10), fmt="%d")
    r = cli("face-model", "import", tmp_path / "01_MorphableModel.mat", "--out", tmp_path / "x.npz",
            "--landmarks", tmp_path / "bad.anl")
    assert r.exit_code == 1 and "68" in r.stderr and "bad.anl" in r.stderr


def test_ray_scene_pickles(tmp_path):
    import pickle

    m = procedural_face_model(grid=(31, 25), n_shape=1, n_exp=1)
    s = RayScene(m.mean_shape, m.triangles)
    s2 = pickle.loads(pickle.dumps(s))
    cam = parse_camera_spec("size=64x48,focal=200")
    np.testing.assert_array_equal(rasterize(s, cam).tri_id, rasterize(s2, cam).tri_id)


def test_render_and_export_fitted_geometry(cli, model_file, ws, tmp_path):
    """--geometry (a fitted geometry artifact) renders/exports exactly like the same shape given as coefficients."""
    m = load_face_model(model_file)
    a = np.array([1.5, -1.0, 0.5]) * m.shape_sigma[:3]
    write_artifact(tmp_path / "geom.npz", "geometry", {"vertices": m.vertices(a), "shape_coeffs": a})
    maps = _maps(ws / "maps.npz")
    common = ["--face-model", model_file, "--maps", maps, "--point-light", "200,0,900",
              "--camera", "yaw=-20,size=96x72,focal=250"]
    assert cli("render", *common, "--geometry", tmp_path / "geom.npz", "-o", tmp_path / "g.exr").exit_code == 0
    assert cli("render", *common, "--shape", ",".join(map(str, a)), "-o", tmp_path / "s.exr").exit_code == 0
    g, s = read_exr(tmp_path / "g.exr")[0], read_exr(tmp_path / "s.exr")[0]
    np.testing.assert_allclose(g["G"], s["G"], rtol=1e-5, atol=1e-7)
    assert cli("face-model", "export", model_file, "--geometry", tmp_path / "geom.npz",
               "--out", tmp_path / "g.obj").exit_code == 0
    mesh = trimesh.load(tmp_path / "g.obj", process=False)
    np.testing.assert_allclose(mesh.vertices, m.vertices(a), atol=1e-4)
    write_artifact(tmp_path / "bad.npz", "geometry", {"vertices": np.zeros((5, 3))})
    r = cli("render", *common, "--geometry", tmp_path / "bad.npz", "-o", tmp_path / "b.exr")
    assert r.exit_code == 1 and "5 vertices" in r.stderr


@pytest.mark.parametrize("camera, word", [
    ("yaw=0,yaw=5", "yaw is given twice"),
    ("dist=900,distance=1000", "distance is given twice"),
    ("size=64x48,width=32", "width is given twice"),
    ("distance=1e30", "distance must be ≤"),
    ("focal=1e30", "focal must be ≤"),
    ("size=100000x48", "width must be ≤"),
])
def test_render_camera_spec_refuses_twice_given_and_absurd_values(cli, model_file, ws, tmp_path, camera, word):
    r = cli("render", "--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--point-light", "0,0,900",
            "--camera", camera, "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and word in r.stderr and "--camera" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "x.exr").exists()


def test_camera_spec_reads_exponent_notation():
    cam = parse_camera_spec("distance=1.2e3,focal=1.5e3,size=64x48")
    assert cam.K[0, 0] == pytest.approx(1500.0) and np.linalg.norm(cam.t) == pytest.approx(1200.0)
    assert (cam.width, cam.height) == (64, 48)


@pytest.mark.parametrize("light, word", [
    ("0,0,1e300", "within"),
    ("0,0,900:nan", "finite"),
    ("0,0,900:1,inf,1", "finite"),
])
def test_render_refuses_absurd_point_lights_without_numpy_warnings(cli, model_file, ws, tmp_path, light, word):
    r = cli("render", "--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--point-light", light,
            "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and word in r.stderr and "RuntimeWarning" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_render_coefficients_must_be_finite_and_named(cli, model_file, ws, tmp_path):
    from reflectmm_cli.model import fit_reflectance_pca, model_arrays

    rng = np.random.default_rng(1)
    albs = [rng.uniform(0.2, 0.7, (3, 16, 16)).astype(np.float32) for _ in range(4)]
    wts = [rng.uniform(0.0, 0.2, (3, 16, 16)).astype(np.float32) for _ in range(4)]
    write_artifact(tmp_path / "rm.npz", "reflectance-model",
                   model_arrays(fit_reflectance_pca(albs, wts, EXPS, components=3)))
    common = ["--face-model", model_file, "--point-light", "0,0,900", "-o", tmp_path / "x.exr"]
    r = cli("render", *common, "--model", tmp_path / "rm.npz", "--coeffs", "nan")
    assert r.exit_code == 1 and "--coeffs" in r.stderr and "finite" in r.stderr
    r = cli("render", *common, "--model", tmp_path / "rm.npz", "--coeffs", "1e308,1e308")
    assert r.exit_code == 1 and "--coeffs" in r.stderr and "rm.npz" in r.stderr and "RuntimeWarning" not in r.stderr
    r = cli("render", *common, "--maps", _maps(ws / "maps.npz"), "--shape", "nan,0")
    assert r.exit_code == 1 and "--shape" in r.stderr
    bad = tmp_path / "nanmaps.npz"
    alb = np.full((3, 8, 8), 0.5, np.float32)
    alb[0, 3, 3] = np.nan
    write_artifact(bad, "reflectance-maps", {"albedo": alb, "weights": np.zeros((3, 8, 8), np.float32),
                                             "exponents": EXPS})
    r = cli("render", *common, "--maps", bad)
    assert r.exit_code == 1 and "nanmaps.npz" in r.stderr and "albedo" in r.stderr
    np.save(tmp_path / "sh.npy", np.full((3, 9), np.nan))
    r = cli("render", "--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--sh", tmp_path / "sh.npy",
            "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and "sh.npy" in r.stderr and "NaN" in r.stderr
    assert not (tmp_path / "x.exr").exists()


def test_render_reads_a_text_file_of_comma_separated_shape_coefficients(cli, model_file, ws, tmp_path):
    (tmp_path / "shape.txt").write_text("1.5, -0.5,\n0.25\n")
    (tmp_path / "shape_ws.txt").write_text("1.5 -0.5\n0.25\n")
    common = ["--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--point-light", "0,0,900",
              "--camera", "size=64x48,focal=200"]
    assert cli("render", *common, "--shape", tmp_path / "shape.txt", "-o", tmp_path / "a.exr").exit_code == 0
    assert cli("render", *common, "--shape", "1.5,-0.5,0.25", "-o", tmp_path / "b.exr").exit_code == 0
    assert cli("render", *common, "--shape", tmp_path / "shape_ws.txt", "-o", tmp_path / "c.exr").exit_code == 0
    a, b, c = (read_exr(tmp_path / f"{k}.exr")[0]["R"] for k in "abc")
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    mean = cli("render", *common, "-o", tmp_path / "m.exr")
    assert mean.exit_code == 0 and not np.array_equal(read_exr(tmp_path / "m.exr")[0]["R"], a)


def test_render_refuses_shape_with_a_fitted_geometry(cli, model_file, ws, tmp_path):
    fm = load_face_model(model_file)
    write_artifact(tmp_path / "g.npz", "geometry", {"vertices": fm.mean_shape.astype(np.float32)})
    r = cli("render", "--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--point-light", "0,0,900",
            "--geometry", tmp_path / "g.npz", "--shape", "1,2", "-o", tmp_path / "x.exr")
    assert r.exit_code == 1 and "--shape" in r.stderr and "g.npz" in r.stderr
    assert not (tmp_path / "x.exr").exists()


def test_render_warns_when_no_face_pixel_is_rendered(cli, model_file, ws, tmp_path, reflectmm_log):
    r = cli("render", "--face-model", model_file, "--maps", _maps(ws / "maps.npz"), "--point-light", "0,0,900",
            "--camera", "size=4x4,focal=1", "-o", tmp_path / "x.exr")  # the face within one pixel, between rays
    assert r.exit_code == 0
    assert any("no face pixel" in m for m in reflectmm_log)


def test_render_refuses_to_replace_the_exr_beside_its_maps(cli, model_file, ws, tmp_path):
    maps = _maps(tmp_path / "m.npz")
    exr = tmp_path / "m.exr"
    exr.write_bytes(b"the maps' EXR twin")
    r = cli("render", "--face-model", model_file, "--maps", maps, "--point-light", "0,0,900",
            "--camera", "size=64x48,focal=200", "-o", exr)
    assert r.exit_code == 1 and "would overwrite its own input 'maps'" in r.stderr
    assert exr.read_bytes() == b"the maps' EXR twin"

"""calibrate-rig end to end on tiny synthetic data (synth multipie → preprocess-multipie → calibrate-rig →
fit-geometry with the calibrated rig)."""

import numpy as np
import pytest
from click.testing import CliRunner

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.cli import main
from reflectmm_cli.geometry_fit.init import rigid_align
from reflectmm_cli.rig import load_rig, save_rig

VIEWS = "13_0,14_0,05_1,05_0,04_1,19_1"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    ws = tmp_path_factory.mktemp("calrig")
    run = CliRunner()
    steps = [["synth", "multipie", "--out", ws / "syn", "--identities", "4", "--cameras", VIEWS, "--flashes",
              "07,18", "--image-size", "240x180", "--face-vertices", "2000", "--landmark-noise", "0.5"]]
    steps += [["preprocess-multipie", "--root", ws / "syn", "--id", f"{i:03d}", "--views", VIEWS,
               "--flashes", "07,18"] for i in range(1, 5)]
    for args in steps:
        r = run.invoke(main, ["-q", *map(str, args), "-w", str(ws)], catch_exceptions=False)
        assert r.exit_code == 0, r.output
    return ws


def test_calibrate_rig_cli(world, cli, tmp_path):
    from reflectmm_cli.geometry_fit.calibrate import perturb_rig

    true = load_rig(world / "syn" / "rig.toml")
    nominal = perturb_rig(true, distance_scale=1.1, angle_deg=2.0, raised_offset_mm=200.0, seed=5)
    save_rig(nominal, tmp_path / "nominal.toml")
    r = cli("calibrate-rig", "--ids", "001-004", "-w", world, "--rig", tmp_path / "nominal.toml", "--focal",
            true.camera("05_1").focal_px, "--json")
    assert r.exit_code == 0, r.output
    out = world / "calibrate-rig" / "calibrate-rig.npz"
    art = read_artifact(out, "rig")
    assert list(art["camera_names"]) == VIEWS.split(",")
    assert list(art["identities"]) == ["001", "002", "003", "004"]
    assert any("focal" in a and "given" in a for a in art.meta["assumptions"])
    names = VIEWS.split(",")
    tc = np.array([true.camera(n).center for n in names])
    _, _, err = rigid_align(np.asarray(art["centers"]), tc)
    _, _, nom_err = rigid_align(np.array([nominal.camera(n).center for n in names]), tc)
    assert nom_err.max() > 100 and err.max() < 0.5 * nom_err.max()
    rig = load_rig(world / "calibrate-rig" / "rig.toml")
    assert rig.camera_names == names and rig.flash("18").camera == "19_1"
    # fit-geometry takes the calibrated table as its rig
    r = cli("fit-geometry", "--id", "001", "-w", world, "--rig", world / "calibrate-rig" / "rig.toml", "--iters",
            "100", "--photo-rounds", "0", "--rig-sigma", "3", "--no-overlay")
    assert r.exit_code == 0, r.output
    g = read_artifact(world / "fit-geometry" / "001.npz", "geometry")
    assert np.allclose(g["K"][:, 0, 0], np.asarray(art["focal_px"]))


def test_fit_geometry_takes_the_workspace_calibrated_rig(world, cli, tmp_path):
    """Without --rig, fit-geometry takes <ws>/calibrate-rig/rig.toml with the sigmas that go with a calibrated rig
    (3 mm, 0.3°; given values win) and says so on stderr; without photometric rounds the summary says so instead
    of printing a NaN RMS. A workspace without a calibrated rig uses the capture's / the packaged one and says so."""
    from reflectmm_cli.workspace import find_fit_rig

    cal = world / "calibrate-rig" / "rig.toml"
    if not cal.is_file():
        save_rig(load_rig(world / "syn" / "rig.toml"), cal)
    out = tmp_path / "g.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "60", "--photo-rounds", "0", "--no-overlay",
            "--rig-rot-sigma", "0.5", "-o", out)
    assert r.exit_code == 0, r.output + r.stderr
    assert "calibrated rig" in r.stderr and str(cal) in r.stderr
    assert "no room-light photometric rounds" in r.stderr and "nan" not in r.stderr.lower()
    g = read_artifact(out, "geometry")
    assert g.meta["params"]["rig_sigma_mm"] == 3.0 and g.meta["params"]["rig_rot_sigma_deg"] == 0.5
    # the capture has flash images: the flash rounds that go with a calibrated rig, the room-light ones as given
    assert g.meta["params"]["flash_rounds"] == 3 and g.meta["params"]["photo_rounds"] == 0
    assert "0 room-light and 3 flash rounds" in r.stderr
    assert any(i["role"] == "rig" and i["path"].endswith("calibrate-rig/rig.toml") for i in g.meta["inputs"])
    empty = tmp_path / "ws2"
    empty.mkdir()
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    path, source = find_fit_rig(empty, cap)
    assert source == "dataset" and path.resolve() == (world / "syn" / "rig.toml").resolve()
    assert find_fit_rig(empty, None) == (None, "packaged")


def test_calibrate_rig_refuses_a_rig_of_another_size(world, cli, tmp_path):
    """No silent resize: the dataset is 240x180, the packaged table 640x480."""
    from reflectmm_cli.rig import default_rig_path

    r = CliRunner().invoke(main, ["calibrate-rig", "--ids", "001-002", "-w", str(world), "--rig",
                                  str(default_rig_path())])
    assert r.exit_code != 0
    assert "is 640x480 but its images are 240x180" in r.output


RECIPE = """
schema = "reflectmm.recipe/1"
name = "calib"

[stages.synth-multipie]
params = { identities = 3, seed = 3, brdf = "model", image_size = "160x120", uv_size = 32, face_vertices = 1500, cameras = ["13_0", "14_0", "05_1", "04_1", "19_1"], flashes = ["07", "18"], landmark_noise = 0.5 }

[stages.preprocess-multipie]
foreach = "all found"
inputs = { root = "@synth-multipie.dir" }
params = { views = ["13_0", "14_0", "05_1", "04_1", "19_1"], flashes = ["07", "18"] }

[stages.calibrate-rig]
inputs = { capture = "@preprocess-multipie.output", face_model = "@synth-multipie.outputs.face_model", rig = "@synth-multipie.outputs.rig" }

[stages.fit-geometry]
foreach = "all found"
inputs = { capture = "@preprocess-multipie.output", face_model = "@synth-multipie.outputs.face_model", rig = "@calibrate-rig.outputs.rig" }
params = { rig_sigma_mm = 3.0, photo_rounds = 0, landmark_iters = 50, no_overlay = true }
"""


@pytest.mark.slow
def test_recipe_runs_calibrate_rig(tmp_path, cli):
    (tmp_path / "calib.toml").write_text(RECIPE)
    res = cli("run", tmp_path / "calib.toml", "--workspace", tmp_path, "--executor", "serial")
    assert res.exit_code == 0, res.stderr + res.stdout
    art = read_artifact(tmp_path / "calibrate-rig" / "calibrate-rig.npz", "rig")
    assert list(art["identities"]) == ["001", "002", "003"]
    g = read_artifact(tmp_path / "fit-geometry" / "002.npz", "geometry")
    roles = {r["role"]: r["path"] for r in g.meta["inputs"]}
    assert roles["rig"].endswith("calibrate-rig/rig.toml")
    assert np.allclose(g["K"][:, 0, 0], np.asarray(art["focal_px"]))


def test_external_geometry_truth_mesh_and_cameras(world, cli, tmp_path):
    """fit-geometry --from-truth takes a registered scan (.ply) + a rig table of cameras, and gives the same
    geometry as the synth-truth artifact it was written from."""
    import trimesh

    from reflectmm_cli.errors import ReflectmmError

    truth = read_artifact(world / "syn" / "truth" / "001.npz", "synth-truth")
    fm = read_artifact(world / "syn" / "face_model.npz", "face-model")
    trimesh.Trimesh(np.asarray(truth["vertices"], np.float64), np.asarray(fm["triangles"]),
                    process=False).export(tmp_path / "scan.ply")
    a = tmp_path / "a.npz"
    b = tmp_path / "b.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--from-truth", tmp_path / "scan.ply", "--rig",
            world / "syn" / "rig.toml", "-o", a)
    assert r.exit_code == 0, r.output
    r = cli("fit-geometry", "--id", "001", "-w", world, "--from-truth", world / "syn" / "truth" / "001.npz", "-o", b)
    assert r.exit_code == 0, r.output
    ga, gb = read_artifact(a, "geometry"), read_artifact(b, "geometry")
    assert list(ga["view_names"]) == list(gb["view_names"])
    for k in ("vertices", "K", "R", "t", "cam_centers", "flash_pos"):
        np.testing.assert_allclose(ga[k], gb[k], atol=1e-3, err_msg=k)
    with pytest.raises(ReflectmmError, match="needs its cameras"):
        from reflectmm_cli.geometry_fit.identity import geometry_from_truth

        geometry_from_truth(tmp_path / "scan.ply")


def test_external_vertex_reflectance_truth(world, cli, tmp_path):
    """evaluate truth with per-vertex reflectance: a linear function of the vertex position interpolates to the
    same function of the interpolated texel position (uv_geometry), so maps made from that have zero error."""
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.observations.unwrap import uv_geometry

    fm = load_face_model(world / "syn" / "face_model.npz")
    X = fm.mean_shape.astype(np.float64)
    A = np.array([[1e-3, 2e-4, 0.0], [0.0, 1e-3, 1e-4], [2e-4, 0.0, 1e-3]])
    alb = X @ A.T + 0.5
    spec = 0.05 + 1e-4 * X[:, 1]
    np.savez(tmp_path / "refl.npz", albedo=alb, spec_albedo=spec)
    S = 32
    g = uv_geometry(X, fm.triangles, fm.uv, S)
    pos = g.position.astype(np.float64)
    C = np.moveaxis(pos @ A.T + 0.5, -1, 0) * g.mask
    W = (0.05 + 1e-4 * pos[..., 1])[None] * g.mask
    maps = {"albedo": C.astype(np.float32), "weights": W.astype(np.float32), "exponents": np.array([16.0]),
            "mask": g.mask, "flagged": np.zeros((S, S), bool)}
    write_artifact(tmp_path / "maps.npz", "reflectance-maps", maps)
    r = cli("evaluate", "truth", "--id", "001", "-w", world, "--maps", tmp_path / "maps.npz", "--truth",
            tmp_path / "refl.npz", "--face-model", world / "syn" / "face_model.npz", "-o", tmp_path / "ev.npz")
    assert r.exit_code == 0, r.output
    e = read_artifact(tmp_path / "ev.npz").meta["errors"]
    assert e["truth_format"] == "per-vertex reflectance"
    assert e["reflectance"]["raw"]["observable"]["albedo_rel"] < 1e-4
    assert abs(e["reflectance"]["raw"]["observable"]["spec_ratio_median"] - 1) < 1e-3
    r = cli("evaluate", "truth", "--id", "001", "-w", world, "--maps", tmp_path / "maps.npz", "--truth",
            tmp_path / "refl.npz", "-o", tmp_path / "ev2.npz")
    assert r.exit_code != 0 and "--face-model" in r.output


def test_calibrate_rig_and_fit_without_the_side_landmarks(world, cli, tmp_path):
    # what a face detector leaves: no landmarks on the side view 13_0 nor on the raised 19_1 in any identity; the
    # rig keeps their nominal pose (reported per camera), fit-geometry places those views by the rig and the images
    from reflectmm_cli.artifacts import write_artifact

    names = VIEWS.split(",")
    caps = []
    for i in range(1, 5):
        cap = read_artifact(world / "preprocess-multipie" / f"{i:03d}.npz", "capture")
        arrays = dict(cap.arrays)
        lm = arrays["landmarks"].copy()
        lm[[names.index("13_0"), names.index("19_1")]] = np.nan
        arrays["landmarks"] = lm
        caps.append(tmp_path / f"{i:03d}.npz")
        write_artifact(caps[-1], "capture", arrays, params=cap.params, inputs=cap.meta["inputs"],
                       extra_meta={"report": cap.meta.get("report", {})})
    true = load_rig(world / "syn" / "rig.toml")
    cap_args = [a for c in caps for a in ("--capture", c)]
    fm = world / "syn" / "face_model.npz"
    r = cli("calibrate-rig", *cap_args, "-w", world, "--face-model", fm, "--rig", world / "syn" / "rig.toml", "--focal",
            true.camera("05_1").focal_px, "-o", tmp_path / "cal" / "calibrate-rig.npz")
    assert r.exit_code == 0, r.output
    art = read_artifact(tmp_path / "cal" / "calibrate-rig.npz", "rig")
    placed = art.meta["report"]["camera_placed_by"]
    assert placed == {n: ("nominal prior only" if n in ("13_0", "19_1") else "landmarks") for n in names}
    assert any("13_0, 19_1" in a and "nominal prior only" in a for a in art.meta["assumptions"])
    sig = np.asarray(art["center_sigma_mm"])
    assert np.isnan(sig[[0, 5]]).all() and np.isfinite(sig[1:5]).all()
    rig = tmp_path / "cal" / "rig.toml"
    assert load_rig(rig).camera_names == names
    tc = np.array([true.camera(n).center for n in names])
    _, _, err = rigid_align(np.asarray(art["centers"]), tc)
    assert err.max() < 20.0, err  # the nominal table here is the true one: its carried poses are right
    r = cli("fit-geometry", "--id", "001", "-w", world, "--capture", caps[0], "--face-model", fm, "--rig", rig,
            "--iters", "100",
            "--photo-rounds", "0", "--flash-rounds", "1", "--no-overlay", "-o", tmp_path / "g.npz")
    assert r.exit_code == 0, r.output
    g = read_artifact(tmp_path / "g.npz", "geometry")
    ev = [str(e).split("+")[0] for e in g["view_evidence"]]
    assert ev == ["rig", "landmarks", "landmarks", "landmarks", "landmarks", "rig"]
    reg = [p["registered_by_flash"] for p in g.meta["report"]["placement"]]
    assert reg[1:5] == [None] * 4 and all(isinstance(r, bool) for r in (reg[0], reg[5]))
    for k in (0, 5):  # "+flash" exactly when the flash registration was kept
        assert (g["view_evidence"][k] == "rig+flash") == reg[k]
    assert np.isfinite(g["center_sigma_mm"][[0, 5]]).all()
    # the two cameras no identity annotates, registered jointly by the flash images of identities 001 and 002
    # (their fits on this rig are the preliminary fits; the calibration from their two captures)
    r = cli("fit-geometry", "--id", "002", "-w", world, "--capture", caps[1], "--face-model", fm, "--rig", rig,
            "--iters", "100", "--photo-rounds", "0", "--flash-rounds", "1", "--no-overlay", "-o", tmp_path / "g2.npz")
    assert r.exit_code == 0, r.output
    geo_args = ["--geometry", tmp_path / "g.npz", "--geometry", tmp_path / "g2.npz"]
    r = cli("calibrate-rig", *cap_args[:4], *geo_args, "-w", world, "--face-model", fm, "--rig",
            world / "syn" / "rig.toml", "--focal", true.camera("05_1").focal_px, "--joint-blur", "2,0",
            "-o", tmp_path / "joint" / "calibrate-rig.npz")
    assert r.exit_code == 0, r.output
    art = read_artifact(tmp_path / "joint" / "calibrate-rig.npz", "rig")
    rep = art.meta["report"]
    place = {p["camera"]: p for p in rep["camera_placement"]}
    assert [place[n]["evidence"] for n in names[1:5]] == ["landmarks"] * 4
    jr = rep["joint_registration"]
    assert jr["cameras"] == ["13_0", "19_1"] and all(0 <= n <= 2 for n in jr["identities"])
    for j, n in enumerate(("13_0", "19_1")):  # placed jointly, or kept at the nominal pose (rejected, or no identity
        # had a flash sample of it: on this tiny world the carried 13_0 is ~90 mm off and its face leaves the crop)
        joint = rep["camera_placed_by"][n] == "flash-joint"
        assert place[n]["evidence"] == ("flash-joint" if joint else "nominal") and jr["accepted"][j] == joint
        assert place[n]["residual_kind"].startswith("flash RMS")
        assert (place[n]["residual"] is not None) == (jr["identities"][j] > 0)
        assert (place[n]["center_sigma_mm"] is not None) == joint
    # against the same calibration without --geometry: the annotated cameras untouched, the rejected ones too
    r = cli("calibrate-rig", *cap_args[:4], "-w", world, "--face-model", fm, "--rig", world / "syn" / "rig.toml",
            "--focal", true.camera("05_1").focal_px, "-o", tmp_path / "nom" / "calibrate-rig.npz")
    assert r.exit_code == 0, r.output
    nom = read_artifact(tmp_path / "nom" / "calibrate-rig.npz", "rig")
    same = [k for k, n in enumerate(names) if rep["camera_placed_by"][n] != "flash-joint"]
    assert np.array_equal(np.asarray(art["centers"])[same], np.asarray(nom["centers"])[same])
    assert np.array_equal(np.asarray(art["R"])[same], np.asarray(nom["R"])[same])
    assert load_rig(tmp_path / "joint" / "rig.toml").camera_names == names
    # bad input: a preliminary fit per capture, in the same order; refused in one line, nothing written
    r = cli("calibrate-rig", *cap_args[:6], *geo_args, "-w", world, "--face-model", fm, "--rig",
            world / "syn" / "rig.toml", "--focal", true.camera("05_1").focal_px, "-o", tmp_path / "bad" / "c.npz")
    assert r.exit_code != 0 and "2 geometry file(s) for 3 capture(s)" in r.output
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "bad" / "c.npz").exists()


def _calibrated_with_a_copied_face_model(world, cli, tmp_path, name):
    """A workspace ``name`` whose rig calibrate-rig made from the world's four captures with a copy of the world's
    face model (``fm.npz`` in ``tmp_path``) and ``jaw=0``; returns (workspace, face model copy)."""
    import shutil

    ws = tmp_path / name
    ws.mkdir()
    fm = tmp_path / "fm.npz"
    shutil.copy(world / "syn" / "face_model.npz", fm)
    caps = [a for i in range(1, 5) for a in ("--capture", world / "preprocess-multipie" / f"{i:03d}.npz")]
    true = load_rig(world / "syn" / "rig.toml")
    r = cli("calibrate-rig", *caps, "-w", ws, "--face-model", fm, "--rig", world / "syn" / "rig.toml", "--focal",
            true.camera("05_1").focal_px, "--landmark-weights", "jaw=0")
    assert r.exit_code == 0, r.output
    return ws, fm


def test_a_calibrated_rig_brings_its_landmark_definition(world, cli, tmp_path):
    """A calibration placed the cameras from landmarks on its face model's vertices with its landmark weights.
    fit-geometry in that workspace takes both by default and says so; on that rig with other weights (given
    explicitly) it warns in one line naming the rig and what to pass; with the calibration's weights and a byte
    copy of its face model it does not.  A table that no calibration wrote has no landmark definition."""
    from reflectmm_cli.geometry_fit import FitConfig
    from reflectmm_cli.stages.fit_geometry import check_rig_landmarks
    from reflectmm_cli.workspace import rig_calibration

    ws2, fm = _calibrated_with_a_copied_face_model(world, cli, tmp_path, "ws2")
    rig = ws2 / "calibrate-rig" / "rig.toml"
    cal = rig_calibration(rig)
    assert cal.face_model.resolve() == fm.resolve() and cal.landmark_weights == {"jaw": 0.0}
    assert rig_calibration(world / "syn" / "rig.toml") is None

    cap001 = world / "preprocess-multipie" / "001.npz"
    common = ("--id", "001", "-w", ws2, "--capture", cap001, "--iters", "30", "--photo-rounds", "0", "--no-overlay")
    r = cli("fit-geometry", *common, "-o", tmp_path / "g.npz")
    assert r.exit_code == 0, r.output + r.stderr
    assert f"its calibration's face model {fm}" in r.stderr and "landmark weights jaw=0" in r.stderr
    assert "another landmark definition" not in r.stderr
    g = read_artifact(tmp_path / "g.npz", "geometry")
    assert g.meta["params"]["landmark_weights"] == {"jaw": 0.0}
    assert [i["path"] for i in g.meta["inputs"] if i["role"] == "face_model"][0].endswith("fm.npz")

    # the rig given explicitly, with the dataset's face model (the same bytes) but the weights left at 1
    r = cli("fit-geometry", *common, "--rig", rig, "--face-model", world / "syn" / "face_model.npz",
            "-o", tmp_path / "g2.npz")
    assert r.exit_code == 0, r.output + r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "another landmark definition" in ln]
    assert len(warn) == 1 and str(rig) in warn[0] and "--landmark-weights jaw=0" in warn[0]
    assert "face model" not in warn[0]  # a byte copy of the calibration's model is that model
    assert check_rig_landmarks("001", rig, fm, FitConfig(group_weights={"jaw": 0.0}))
    # the weights compare as the fit uses them: a group named at its default weight is the same definition
    assert check_rig_landmarks("001", rig, fm, FitConfig(group_weights={"jaw": 0.0, "brows": 1.0}))
    assert not check_rig_landmarks("001", rig, fm, FitConfig(group_weights={"jaw": 1.0}))
    other = tmp_path / "other.npz"
    other.write_bytes(b"not the same model")
    assert not check_rig_landmarks("001", rig, other, FitConfig(group_weights={"jaw": 0.0}))


def test_a_calibrated_rig_whose_record_is_lost_or_changed_is_refused(world, cli, tmp_path):
    """A calibrated rig's landmark definition comes from the calibration artifact beside it.  Without that artifact,
    or with the face model it records gone or changed, the defaults would silently be the dataset's model and the
    default weights (a face 19 mm off on the demo): fit-geometry refuses in one line and writes nothing.  Given both
    explicitly it runs, and says that it cannot check them; a copy of the recorded model's bytes elsewhere is that
    model."""
    import shutil

    ws, fm = _calibrated_with_a_copied_face_model(world, cli, tmp_path, "ws")
    art = ws / "calibrate-rig" / "calibrate-rig.npz"
    common = ("--id", "001", "-w", ws, "--capture", world / "preprocess-multipie" / "001.npz", "--iters", "20",
              "--photo-rounds", "0", "--flash-rounds", "0", "--no-overlay")
    out = tmp_path / "g.npz"

    def refused(*extra):
        r = cli("fit-geometry", *common, *extra, "-o", out)
        assert r.exit_code == 1 and not out.exists(), r.output + r.stderr
        return [ln for ln in r.stderr.splitlines() if ln.startswith("reflectmm: error:")][0]

    fm.write_bytes(fm.read_bytes()[:-8] + b"12345678")  # other bytes at the recorded path
    line = refused()
    assert str(art) in line and "has changed since" in line and "--face-model" in line
    fm.unlink()
    line = refused()
    assert str(art) in line and f"{fm.resolve()}, is gone" in line
    copy = tmp_path / "elsewhere.npz"  # the recorded bytes at another path: that model, no warning
    shutil.copy(world / "syn" / "face_model.npz", copy)
    r = cli("fit-geometry", *common, "--face-model", copy, "-o", out)
    assert r.exit_code == 0 and "another landmark definition" not in r.stderr, r.output + r.stderr
    out.unlink()
    art.unlink()
    line = refused()
    assert str(ws / "calibrate-rig" / "rig.toml") in line and "written by calibrate-rig" in line
    r = cli("fit-geometry", *common, "--face-model", copy, "--landmark-weights", "jaw=0", "-o", out)
    assert r.exit_code == 0 and "cannot check the fit's landmark definition" in r.stderr, r.output + r.stderr


def test_calibrate_rig_refuses_an_identity_twice_or_without_landmarks(world, cli, tmp_path):
    # the same identity twice counted double; one without landmarks got a made-up head pose and moved the rig's
    # scale; both were written over the workspace's rig
    from reflectmm_cli.artifacts import write_artifact

    ws = tmp_path / "ws"
    ws.mkdir()
    caps = [world / "preprocess-multipie" / f"{i:03d}.npz" for i in range(1, 4)]
    cap = read_artifact(caps[1], "capture")
    arrays = {k: np.array(v) for k, v in cap.arrays.items()}
    kw = {"params": cap.params, "inputs": cap.meta["inputs"], "extra_meta": {"report": cap.meta["report"]}}
    write_artifact(tmp_path / "002_copy.npz", "capture", arrays, **kw)
    arrays["landmarks"][:] = np.nan
    write_artifact(tmp_path / "002_none.npz", "capture", arrays, **kw)
    base = ("-w", ws, "--face-model", world / "syn" / "face_model.npz", "--rig", world / "syn" / "rig.toml",
            "--focal", load_rig(world / "syn" / "rig.toml").camera("05_1").focal_px)
    for extra, msg in (([caps[1], tmp_path / "002_copy.npz"], "identity 002 is given twice"),
                       ([tmp_path / "002_none.npz"], "identity 002 has no landmarks in any view")):
        files = [a for c in [caps[0], caps[2], *extra] for a in ("--capture", c)]
        r = cli("calibrate-rig", *files, *base)
        assert r.exit_code == 1 and msg in r.stderr and str(extra[-1]) in r.stderr, r.output + r.stderr
        assert not (ws / "calibrate-rig").exists()


def test_views_without_landmarks_and_no_flash_rounds_are_warned_about(world, cli, tmp_path):
    # without flash rounds a view without landmarks stays where the rig puts it: fit-geometry says so, and what to pass
    from reflectmm_cli.artifacts import write_artifact

    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    arrays = dict(cap.arrays)
    arrays["landmarks"] = arrays["landmarks"].copy()
    arrays["landmarks"][VIEWS.split(",").index("19_1")] = np.nan
    path = tmp_path / "001.npz"
    write_artifact(path, "capture", arrays, params=cap.params, inputs=cap.meta["inputs"],
                   extra_meta={"report": cap.meta.get("report", {})})
    common = ("--id", "001", "-w", world, "--capture", path, "--face-model", world / "syn" / "face_model.npz",
              "--rig", world / "syn" / "rig.toml", "--iters", "30", "--photo-rounds", "0", "--no-overlay")
    for flash, warned in (("0", True), ("1", False)):
        r = cli("fit-geometry", *common, "--flash-rounds", flash, "-o", tmp_path / f"g{flash}.npz")
        assert r.exit_code == 0, r.output + r.stderr
        lines = [ln for ln in r.stderr.splitlines() if "no flash rounds" in ln]
        assert len(lines) == int(warned) and all("19_1" in ln and "--flash-rounds 3" in ln for ln in lines)


def test_calibrate_rig_refuses_landmarks_that_do_not_fit_one_rig(world, cli, tmp_path):
    # landmarks that read the face otherwise than the model (here each view's 68 points in reverse order) leave most
    # of them far from any rig: a one-line error naming the face model and the likely causes, no rig written.  A
    # fifth of the points displaced by 25 px is a calibration that is written, with a warning that says why.
    from reflectmm_cli.artifacts import write_artifact

    rng = np.random.default_rng(4)

    def captures(name, change):
        paths = []
        for i in range(1, 5):
            cap = read_artifact(world / "preprocess-multipie" / f"{i:03d}.npz", "capture")
            arrays = dict(cap.arrays)
            arrays["landmarks"] = change(np.asarray(arrays["landmarks"], np.float64).copy())
            paths.append(tmp_path / name / f"{i:03d}.npz")
            write_artifact(paths[-1], "capture", arrays, params=cap.params, inputs=cap.meta["inputs"],
                           extra_meta={"report": cap.meta.get("report", {})})
        return [a for c in paths for a in ("--capture", c)]

    def displaced(lm):
        hit = rng.random(lm.shape[:2]) < 0.2
        lm[hit] += rng.normal(size=(int(hit.sum()), 2)) * 25.0
        return lm

    fm = world / "syn" / "face_model.npz"
    focal = load_rig(world / "syn" / "rig.toml").camera("05_1").focal_px
    common = ("-w", tmp_path, "--face-model", fm, "--rig", world / "syn" / "rig.toml", "--focal", focal)
    r = cli("-q", "calibrate-rig", *captures("reversed", lambda lm: lm[:, ::-1].copy()), *common,
            "-o", tmp_path / "bad" / "calibrate-rig.npz")
    assert r.exit_code != 0
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and str(fm) in line and "no rig written" in line and "jaw=0" in line, line
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())
    r = cli("calibrate-rig", *captures("displaced", displaced), *common, "-o", tmp_path / "ok" / "calibrate-rig.npz")
    assert r.exit_code == 0, r.output + r.stderr
    assert (tmp_path / "ok" / "rig.toml").is_file()
    warn = [ln for ln in r.stderr.splitlines() if "further than" in ln]
    assert len(warn) == 1 and "% of those used" in warn[0] and "Landmarks from a detector" in warn[0]


def test_landmark_weights_compare_as_the_fit_uses_them(monkeypatch, tmp_path):
    # a calibration with the default weights: a fit naming a group at its default weight (jaw 0.5) reads the
    # landmarks the same way; one that names another weight (jaw 1, not the default) does not
    import reflectmm_cli.workspace as workspace
    from reflectmm_cli.geometry_fit import FitConfig
    from reflectmm_cli.geometry_fit.landmarks import DEFAULT_GROUP_WEIGHTS
    from reflectmm_cli.stages.fit_geometry import check_rig_landmarks

    monkeypatch.setattr(workspace, "rig_calibration",
                        lambda rig: workspace.RigCalibration(tmp_path / "cal.npz", None, landmark_weights={}))
    rig = tmp_path / "rig.toml"
    assert DEFAULT_GROUP_WEIGHTS["jaw"] == 0.5
    assert check_rig_landmarks("001", rig, tmp_path / "fm.npz", FitConfig())
    assert check_rig_landmarks("001", rig, tmp_path / "fm.npz", FitConfig(group_weights={"jaw": 0.5}))
    assert not check_rig_landmarks("001", rig, tmp_path / "fm.npz", FitConfig(group_weights={"jaw": 1.0}))

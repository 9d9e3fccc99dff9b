"""fit-geometry end to end on a tiny synthetic identity (synth multipie → preprocess-multipie → fit-geometry)."""

import numpy as np
import pytest
from click.testing import CliRunner

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.cli import main
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.geometry_fit.landmarks import write_pts
from reflectmm_cli.geometry_fit.report import truth_errors

VIEWS = "13_0,14_0,05_1,05_0,04_1"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    ws = tmp_path_factory.mktemp("fitgeo")
    run = CliRunner()
    for args in (["synth", "multipie", "--out", ws / "syn", "--cameras", VIEWS + ",19_1", "--flashes", "07,18",
                  "--image-size", "240x180", "--face-vertices", "2000", "--landmark-noise", "0.5"],
                 ["preprocess-multipie", "--root", ws / "syn", "--id", "001", "--views", VIEWS,
                  "--flashes", "07,18"]):
        r = run.invoke(main, ["-q", *map(str, args), "-w", str(ws)], catch_exceptions=False)
        assert r.exit_code == 0, r.output
    return ws


def test_fit_recovers_geometry(world, cli):
    r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "200", "--photo-rounds", "1")
    assert r.exit_code == 0, r.output
    out = world / "fit-geometry" / "001.npz"
    assert str(out) in r.stdout.splitlines()
    assert len([ln for ln in r.stdout.splitlines() if ln.endswith(".png")]) == 5
    g = read_artifact(out, "geometry")
    for k in ("shape_coeffs", "exp_coeffs", "vertices", "view_names", "K", "R", "t", "image_size", "cam_centers",
              "flash_ids", "flash_pos", "flash_intensity", "landmark_rmse_px", "photo_residual"):
        assert k in g.arrays, k
    assert list(g["view_names"]) == VIEWS.split(",")
    assert np.allclose(g["cam_centers"], -np.einsum("vji,vj->vi", g["R"], g["t"]))
    # R orthonormal with det +1
    assert np.allclose(np.einsum("vij,vkj->vik", g["R"], g["R"]), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(g["R"]), 1.0)
    truth = read_artifact(world / "syn" / "truth" / "001.npz", "synth-truth")
    # errors measured on this data set (240x180, 5 views on one horizontal arc, 0.5 px landmark noise, the
    # procedural model of 2026-11-21): landmarks 0.25 px, vertices 0.5–0.9 px in the image and 1.9–2.6 mm RMS
    # (3–4.4 % IOD); camera centres 20–45 mm — a one-row frontal arc cannot tell head pitch / face size from
    # shape changes, so the cameras slide on their sphere while the image-space fit stays sub-pixel
    assert np.median(g["err_landmark_px"]) < 0.5
    assert np.median(g["err_vertex_px"]) < 1.0
    assert float(g["err_vertex_rmse_iod"]) < 0.08
    assert np.median(g["err_cam_center_mm"]) < 80.0
    # the fit beats the mean face at the true cameras (an independent baseline) in the image
    fm = read_artifact(world / "syn" / "face_model.npz", "face-model")
    names = list(truth["camera_names"])
    base = []
    for v, n in enumerate(g["view_names"]):
        i = names.index(n)
        u0 = project(fm["mean_shape"][fm["landmarks"]], truth["K"][i], truth["R"][i], truth["t"][i])[0]
        ut = project(truth["vertices"][fm["landmarks"]], truth["K"][i], truth["R"][i], truth["t"][i])[0]
        base.append(np.sqrt(((u0 - ut) ** 2).sum(-1).mean()))
    assert np.median(g["err_landmark_px"]) < 0.5 * np.median(base)
    # landmark residual ≈ the 0.5 px noise (per coordinate → ≈ 0.7 px per point)
    assert 0.3 < np.median(g["landmark_rmse_px"]) < 1.2
    assert np.all(np.isfinite(g["photo_residual"])) and np.all(g["photo_residual"] < 0.05)
    # flashes: 07 sits at the fitted 05_1 centre; 18 (raised 19_1, not a view) comes from the rig, aligned
    fl = list(g["flash_ids"])
    assert np.allclose(g["flash_pos"][fl.index("07")], g["cam_centers"][VIEWS.split(",").index("05_1")])
    tf = list(truth["flash_ids"])
    assert np.linalg.norm(g["flash_pos"][fl.index("18")] - truth["flash_pos"][tf.index("18")]) < 60.0
    assert np.allclose(g["flash_intensity"], truth["flash_intensity"][[tf.index(f) for f in fl]])
    assert g.meta["report"]["truth"]["err_vertex_rmse_mm"] == pytest.approx(float(g["err_vertex_rmse_mm"]), 1e-3)


def test_from_truth_round_trip(world, cli):
    out = world / "gt.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--from-truth", world / "syn" / "truth" / "001.npz",
            "-o", out)
    assert r.exit_code == 0, r.output
    g = read_artifact(out, "geometry")
    truth = read_artifact(world / "syn" / "truth" / "001.npz", "synth-truth")
    names = list(truth["camera_names"])
    idx = [names.index(n) for n in g["view_names"]]
    assert list(g["view_names"]) == VIEWS.split(",") and list(g["flash_ids"]) == ["07", "18"]
    assert np.array_equal(g["vertices"], truth["vertices"])
    assert np.allclose(g["R"], truth["R"][idx]) and np.allclose(g["t"], truth["t"][idx])
    assert np.allclose(g["cam_centers"], truth["cam_centers"][idx])
    fm = read_artifact(world / "syn" / "face_model.npz", "face-model")
    errs = truth_errors(g["vertices"], g["K"], g["R"], g["t"], truth["vertices"], truth["K"][idx],
                        truth["R"][idx], truth["t"][idx], fm["landmarks"])
    assert float(errs["err_vertex_rmse_mm"]) == 0.0 and np.all(errs["err_cam_center_mm"] < 1e-9)
    # the true geometry against the noisy (σ = 0.5 px) capture landmarks
    assert 0.3 < np.median(g["landmark_rmse_px"]) < 1.2


def _err(r):
    assert r.exit_code == 1, r.output
    return r.stderr


def test_bad_landmark_file(world, cli, tmp_path):
    write_pts(tmp_path / "05_1.pts", np.zeros((60, 2)))
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--landmarks", tmp_path, "-o", tmp_path / "g.npz"))
    assert "05_1.pts" in msg and "expected 68 landmarks, found 60" in msg
    far = np.full((68, 2), 100.0)
    far[5] = [1e6, 50.0]
    write_pts(tmp_path / "05_1.pts", far)
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--landmarks", tmp_path, "-o", tmp_path / "g.npz"))
    assert "05_1.pts: 1 landmark(s) far outside the 240x180 frame (landmark 6 at (1e+06, 50) px)" in msg


def test_view_not_in_rig(world, cli, tmp_path):
    text = (world / "syn" / "rig.toml").read_text()
    blocks = text.split("[[camera]]")
    kept = [b for b in blocks if 'name = "13_0"' not in b]
    (tmp_path / "rig.toml").write_text("[[camera]]".join(kept).replace('camera = "13_0"', 'camera = "05_1"'))
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--rig", tmp_path / "rig.toml",
                   "-o", tmp_path / "g.npz"))
    assert "13_0" in msg and "not cameras of the rig" in msg and "rig.toml" in msg


def _capture_without(world, tmp_path, views):
    """The world's capture with the landmarks of ``views`` removed (what a detector that finds no face leaves)."""
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    arrays = dict(cap.arrays)
    lm = arrays["landmarks"].copy()
    for v in views:
        lm[list(cap["view_names"]).index(v)] = np.nan
    arrays["landmarks"] = lm
    out = tmp_path / "capture.npz"
    write_artifact(out, "capture", arrays, params=cap.params, inputs=cap.meta["inputs"])
    return out


def test_no_landmarks_for_any_view(world, cli, tmp_path):
    bad = _capture_without(world, tmp_path, VIEWS.split(","))
    out = tmp_path / "g.npz"
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--capture", bad,
                   "--face-model", world / "syn" / "face_model.npz", "-o", out))
    assert "no landmarks for any view of identity 001" in msg and "001_01_01_130_00_lm.pts" in msg
    assert not out.exists()


def _capture_changed(world, tmp_path, change):
    """The world's capture with ``change(arrays, view_names)`` applied (a corrupt or hand-edited capture)."""
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    arrays = {k: np.array(v) for k, v in cap.arrays.items()}
    change(arrays, [str(v) for v in cap["view_names"]])
    out = tmp_path / "capture.npz"
    write_artifact(out, "capture", arrays, params=cap.params, inputs=cap.meta["inputs"])
    return out


@pytest.mark.parametrize("what", ["room", "olat", "few", "far"])
def test_a_corrupt_capture_is_refused_naming_the_view(world, cli, tmp_path, what):
    # NaN pixels made the flash term fail inside torch and the room-light term crash the process; landmarks far
    # outside the frame put the cameras 1e10 mm away; a view with 3 points was silently dropped
    def change(a, names):
        v = names.index("05_1")
        if what == "room":
            a["room"][v, 10:12, 10:12] = np.nan
        elif what == "olat":
            a["olat"][v, 1, 5, 5, 0] = np.inf
        elif what == "few":
            a["landmarks"][v, 3:] = np.nan
        else:
            a["landmarks"][v, 7] = [1e9, 1e9]

    bad = _capture_changed(world, tmp_path, change)
    out = tmp_path / "g.npz"
    rounds = ["--photo-rounds", "1", "--flash-rounds", "0"] if what == "room" else ["--photo-rounds", "0",
                                                                                   "--flash-rounds", "1"]
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--capture", bad, "--iters", "20", *rounds,
                   "--face-model", world / "syn" / "face_model.npz", "--rig", world / "syn" / "rig.toml",
                   "--no-overlay", "-o", out))
    assert str(bad) in msg and not out.exists()
    expected = {"room": "capture 'room' has 12 NaN or infinite pixel value(s) (the first in view 05_1)",
                "olat": "capture 'olat' has 1 NaN or infinite pixel value(s) (the first in view 05_1, flash 18)",
                "few": "view 05_1 has 3 landmark(s): at least 6 are needed",
                "far": "view 05_1: 1 landmark(s) far outside the 240x180 frame (landmark 8 at (1e+09, 1e+09) px)"}
    assert expected[what] in msg, msg


def test_views_without_landmarks_are_placed_by_the_rig_and_the_images(world, tmp_path):
    # the side views 13_0 and 04_1 without landmarks; placed by the rig under the head pose of the other three and
    # refined by the flash term; each view's evidence, residuals and uncertainty in the report and on stderr
    import os
    import subprocess
    import sys
    from pathlib import Path

    cap = _capture_without(world, tmp_path, ["13_0", "04_1"])
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    common = [sys.executable, "-m", "reflectmm_cli", "fit-geometry", "--id", "001", "-w", str(world), "--iters",
              "200", "--photo-rounds", "1", "--flash-rounds", "1", "--no-overlay",
              "--truth", str(world / "syn" / "truth" / "001.npz")]
    runs = {}
    fm = ["--face-model", str(world / "syn" / "face_model.npz"), "--rig", str(world / "syn" / "rig.toml")]
    for name, extra in (("all", fm), ("some", fm + ["--capture", str(cap)])):
        r = subprocess.run(common + extra + ["-o", str(tmp_path / f"{name}.npz")], capture_output=True, text=True,
                           timeout=600, env=env)
        assert r.returncode == 0, r.stderr
        runs[name] = (read_artifact(tmp_path / f"{name}.npz", "geometry"), r.stderr)
    g, err = runs["some"]
    g_all = runs["all"][0]
    ev = dict(zip(g["view_names"], g["view_evidence"]))
    rep = {p["view"]: p for p in g.meta["report"]["placement"]}
    # the room light does not move a view without landmarks (docs/benchmarks.md); the flash registration does
    # when it lowers the residual within 3 σ of the rig
    assert ev == {"13_0": "rig+flash" if rep["13_0"]["registered_by_flash"] else "rig",
                  "14_0": "landmarks+photo+flash", "05_1": "landmarks+photo+flash", "05_0": "landmarks+photo+flash",
                  "04_1": "rig+flash" if rep["04_1"]["registered_by_flash"] else "rig"}
    side = [0, 4]
    assert np.all(np.isnan(g["landmark_rmse_px"][side])) and np.all(np.isfinite(g["landmark_rmse_px"][1:4]))
    assert np.all(np.isfinite(g["center_sigma_mm"][side])) and np.all(np.isnan(g["center_sigma_mm"][1:4]))
    assert rep["13_0"]["evidence"] == ev["13_0"] and rep["13_0"]["landmark_rmse_px"] is None
    assert rep["04_1"]["center_sigma_mm"] == pytest.approx(float(g["center_sigma_mm"][4]), abs=0.01)
    assert any(ln.startswith(f"fit-geometry 001: view 13_0 placed by {ev['13_0']}: photometric RMS n/a")
               for ln in err.splitlines()), err
    assert "view 14_0 placed" not in err
    # against the all-landmarks run on the same data and schedule
    assert float(g["err_vertex_rmse_mm"]) < 1.3 * float(g_all["err_vertex_rmse_mm"]), (
        float(g["err_vertex_rmse_mm"]), float(g_all["err_vertex_rmse_mm"]))
    # cameras: on this one-row frontal arc every camera is 32–40 mm off with all landmarks; without the side
    # views' landmarks the head rotation rests on three near-frontal views and acts on the side cameras' 1 m lever
    # (measured 94 and 46 mm); the 20 mm goal is measured on the full rig (docs/benchmarks.md, issue 23)
    assert np.max(g["err_cam_center_mm"][side]) < 3.0 * np.max(g_all["err_cam_center_mm"]), (
        g["err_cam_center_mm"], g_all["err_cam_center_mm"])


def test_missing_face_model_and_capture(world, cli, tmp_path):
    msg = _err(cli("fit-geometry", "--id", "001", "-w", world, "--face-model", tmp_path / "nope.npz",
                   "-o", tmp_path / "g.npz"))
    assert "nope.npz" in msg
    msg = _err(cli("fit-geometry", "--id", "002", "-w", world))
    assert "capture artifact not found" in msg and "002.npz" in msg


def test_flash_intensity_override_and_no_overlay(world, cli, tmp_path):
    out = tmp_path / "g.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "30", "--photo-rounds", "0",
            "--flash-intensity", "1", "--dtype", "float32", "--albedo", "constant", "--no-overlay", "-o", out)
    assert r.exit_code == 0, r.output
    assert r.stdout.split() == [str(out)]
    g = read_artifact(out, "geometry")
    assert np.array_equal(g["flash_intensity"], np.ones(2))
    assert np.all(np.isnan(g["photo_residual"]))
    assert g.params["flash_intensity"] == 1.0 and g.params["photo_rounds"] == 0 and g.params["dtype"] == "float32"
    assert g.params["albedo"] == "constant"
    assert np.median(g["landmark_rmse_px"]) < 1.5


def test_jaw_contour_end_to_end(world, cli, tmp_path):
    """--jaw-contour --contour-gate through the CLI: the options reach the artifact's params and the fit runs its
    sliding rounds (named in the report's history)."""
    out = tmp_path / "g.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "60", "--photo-rounds", "0", "--jaw-contour",
            "--contour-gate", "3", "--no-overlay", "-o", out)
    assert r.exit_code == 0, r.output
    g = read_artifact(out, "geometry")
    assert g.params["jaw_contour"] is True and g.params["contour_gate_px"] == 3.0
    stages = [h["stage"] for h in g.meta["report"]["history"]]
    assert stages[:3] == ["landmarks without the sliding jaw", "landmarks, jaw on the outline 1",
                          "landmarks, jaw on the outline 2"]
    assert np.all(np.isfinite(g["landmark_rmse_px"])) and float(g["err_vertex_rmse_iod"]) < 0.12


def test_rerun_is_byte_identical(world, cli, tmp_path):
    outs = [tmp_path / "a" / "g.npz", tmp_path / "b" / "g.npz"]
    for out in outs:
        r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "30", "--photo-rounds", "1", "--no-overlay",
                "--capture", world / "preprocess-multipie" / "001.npz", "-o", out)
        assert r.exit_code == 0, r.output
    assert outs[0].read_bytes() == outs[1].read_bytes()


def test_landmarks_dir_overrides_capture(world, cli, tmp_path):
    truth = read_artifact(world / "syn" / "truth" / "001.npz", "synth-truth")
    lv = list(truth["landmark_views"])
    shifted = truth["landmarks_2d"][lv.index("05_1")] + np.array([3.0, -2.0])
    write_pts(tmp_path / "05_1.pts", shifted)  # one view from the folder, the others from the capture
    out = tmp_path / "g.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--landmarks", tmp_path, "--iters", "30",
            "--photo-rounds", "0", "--no-overlay", "-o", out)
    assert r.exit_code == 0, r.output
    g = read_artifact(out, "geometry")
    v = list(g["view_names"]).index("05_1")
    assert np.allclose(g["landmarks_given"][v], shifted, atol=1e-4)
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    assert np.allclose(g["landmarks_given"][0], cap["landmarks"][0])
    src = g.meta["report"]["landmark_sources"]
    assert src[v].endswith("05_1.pts") and src[0] == "capture"
    # a view-wide shift of 3 px is absorbed by that view's own pose (its camera slides sideways, ≈ 10 mm here)
    assert g["landmark_rmse_px"][v] < 1.2
    ref_path = world / "fit-geometry" / "001.npz"
    ref = read_artifact(ref_path, "geometry") if ref_path.exists() else None
    tc = truth["cam_centers"][list(truth["camera_names"]).index("05_1")]
    assert np.linalg.norm(g["cam_centers"][v] - tc) > 5.0
    if ref is not None:
        assert np.linalg.norm(g["cam_centers"][v] - tc) > np.linalg.norm(ref["cam_centers"][v] - tc)


@pytest.mark.parametrize("from_truth", [False, True])
def test_recipe_at_two_paths_gives_identical_bytes(world, cli, tmp_path, from_truth):
    # the report's truth_file is stored relative to the artifact, like its inputs
    import shutil

    params = '{ from_truth = true }' if from_truth else \
        '{ landmark_iters = 30, photo_rounds = 1, photo_iters = 5, no_overlay = true }'
    recipe = ('schema = "reflectmm.recipe/1"\n[stages.fit-geometry]\nforeach = ["001"]\n'
              'inputs = { capture = "preprocess-multipie/{id}.npz", face_model = "syn/face_model.npz", '
              'rig = "syn/rig.toml", truth = "syn/truth/{id}.npz" }\n'
              f'params = {params}\n')
    outs = []
    for where in ("one", "two/deeper"):
        w = tmp_path / where
        for sub in ("syn", "preprocess-multipie"):
            shutil.copytree(world / sub, w / sub)
        (w / "r.toml").write_text(recipe)
        r = cli("-q", "run", w / "r.toml", "-w", w)
        assert r.exit_code == 0, r.stderr
        outs.append(w / "fit-geometry" / "001.npz")
    g = read_artifact(outs[0], "geometry")
    assert g.meta["report"]["truth_file"] == "../syn/truth/001.npz"
    assert outs[0].read_bytes() == outs[1].read_bytes()


def test_inputs_of_another_identity_are_refused(world, cli, tmp_path):
    cap = world / "preprocess-multipie" / "001.npz"
    truth = world / "syn" / "truth" / "001.npz"
    msg = _err(cli("fit-geometry", "--id", "999", "-w", world, "--capture", cap, "--from-truth", truth,
                   "-o", tmp_path / "g999.npz"))
    assert f"{cap}: is identity 001's capture, but this task is for identity 999" in msg
    geo = tmp_path / "g001.npz"
    assert cli("fit-geometry", "--id", "001", "-w", world, "--from-truth", truth, "-o", geo).exit_code == 0
    fm = world / "syn" / "face_model.npz"
    msg = _err(cli("unwrap-uv", "--id", "999", "-w", tmp_path, "--capture", cap, "--geometry", geo,
                   "--face-model", fm, "--uv-size", "32"))
    assert f"{cap}: is identity 001's capture, but this task is for identity 999; pass the matching file or " \
           "--id 001" in msg
    assert not (tmp_path / "unwrap-uv" / "999.npz").exists()
    (tmp_path / "r.toml").write_text(
        'schema = "reflectmm.recipe/1"\n[stages.unwrap-uv]\nforeach = ["999"]\n'
        f'inputs = {{ capture = "{cap}", geometry = "{geo}", face_model = "{fm}" }}\nparams = {{ uv_size = 32 }}\n')
    r = cli("run", tmp_path / "r.toml", "-w", tmp_path)
    assert r.exit_code == 1 and "is identity 001's capture, but this task is for identity 999" in r.stderr


@pytest.mark.slow
def test_summary_line_survives_in_captured_logs(world, tmp_path):
    # stderr to a file or pipe: progress as plain lines, no carriage return overwriting the summary
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    r = subprocess.run([sys.executable, "-m", "reflectmm_cli", "fit-geometry", "--id", "001", "-w", str(world),
                        "--iters", "20", "--photo-rounds", "1", "--no-overlay", "-o", str(tmp_path / "g.npz")],
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr
    lines = r.stderr.splitlines()
    assert any(ln.startswith("fit-geometry 001: landmark RMS") for ln in lines), lines
    assert any(ln.startswith("fit-geometry: 2/2 stage (100%") for ln in lines), lines


def test_flash_rounds(world, cli, tmp_path):
    # the flash term on the tiny world: flash 07 sits on the fitted view 05_1, flash 18 on the raised 19_1, which
    # is not a view (its rig position moves with the fitted head pose)
    common = ["fit-geometry", "--id", "001", "-w", world, "--iters", "200", "--photo-rounds", "0", "--no-overlay"]
    r = cli(*common, "-o", tmp_path / "lm.npz")
    assert r.exit_code == 0, r.output
    r = cli(*common, "--flash-rounds", "2", "-o", tmp_path / "fl.npz")
    assert r.exit_code == 0, r.output
    lm, fl = read_artifact(tmp_path / "lm.npz", "geometry"), read_artifact(tmp_path / "fl.npz", "geometry")
    assert "flash_residual" not in lm.arrays and "flash_residual" in fl.arrays
    assert fl.params["flash_rounds"] == 2 and fl.params["w_flash"] == 30.0
    assert np.all(np.isfinite(fl["flash_residual"])) and np.all(fl["flash_residual"] < 0.05)
    gain = fl["flash_gain"]
    assert gain.shape == (2,) and np.prod(gain) == pytest.approx(1.0) and np.all(np.abs(gain - 1) < 0.1)
    assert [h["stage"] for h in fl.meta["report"]["history"]] == ["landmarks", "flash round 1", "flash round 2"]
    # this 2000-vertex, 240x180, 2-flash world is where the flash term helps least (docs/fit-geometry.md: coarse
    # meshes and few flashes; measured 1.87 → 2.18 mm, cameras 71 → 46 mm); the accuracy gain is tested on the
    # toy (test_flash.py) and measured on the 35k-vertex worlds (docs/benchmarks.md)
    assert float(fl["err_vertex_rmse_mm"]) < 1.5 * float(lm["err_vertex_rmse_mm"])
    assert np.max(fl["err_cam_center_mm"]) < np.max(lm["err_cam_center_mm"])


def test_flash_iters_option_caps_each_round(world, cli, tmp_path):
    # --flash-iters reaches the fit and is recorded: torch's L-BFGS evaluates at most 1.25 × max_iter times
    r = cli("fit-geometry", "--id", "001", "-w", world, "--iters", "200", "--photo-rounds", "0", "--no-overlay",
            "--flash-rounds", "2", "--flash-iters", "4", "-o", tmp_path / "fl.npz")
    assert r.exit_code == 0, r.output
    fl = read_artifact(tmp_path / "fl.npz", "geometry")
    assert fl.params["flash_iters"] == 4
    rounds = [h for h in fl.meta["report"]["history"] if h["stage"].startswith("flash round")]
    assert len(rounds) == 2 and all(1 <= h["evals"] <= 5 for h in rounds), rounds


def test_flash_rounds_need_flash_images(world, cli, tmp_path):
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    arrays = {k: v for k, v in cap.arrays.items() if k != "olat"}
    bad = tmp_path / "001.npz"
    write_artifact(bad, "capture", arrays, params=cap.params, inputs=[], producer=cap.meta["producer"])
    out = tmp_path / "g.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--capture", bad, "--face-model",
            world / "syn" / "face_model.npz", "--rig", world / "syn" / "rig.toml", "--flash-rounds", "1", "-o", out)
    assert r.exit_code != 0
    msg = _err(r)
    assert "flash images ('olat')" in msg and str(bad) in msg
    assert not out.exists()


def test_face_model_embed_landmarks_end_to_end(world, cli, tmp_path):
    """face-model embed-landmarks: a 'detector' whose inner points are other vertices of the true mesh (each
    landmark moved to the vertex nearest 6 mm above it) is measured back through the CLI, from the capture's
    landmarks and the true geometry; the jaw keeps its vertices; a capture without a geometry of its identity is
    a one-line error and writes nothing."""
    truth = read_artifact(world / "syn" / "truth" / "001.npz", "synth-truth")
    fm_path = world / "syn" / "face_model.npz"
    fm = read_artifact(fm_path, "face-model")
    mean, lmk = np.asarray(fm["mean_shape"], float), np.asarray(fm["landmarks"])
    front = mean[:, 2] > np.percentile(mean[:, 2], 40)
    det = lmk.copy()
    for j in range(17, 68):
        p = mean[lmk[j]] + [0.0, 6.0, 0.0]
        det[j] = np.flatnonzero(front)[np.argmin(((mean[front] - p) ** 2).sum(1))]
    cap = read_artifact(world / "preprocess-multipie" / "001.npz", "capture")
    names = list(truth["camera_names"])
    lm = np.full((len(cap["view_names"]), 68, 2), np.nan)
    for k, v in enumerate(cap["view_names"]):
        i = names.index(str(v))
        lm[k] = project(np.asarray(truth["vertices"], float)[det], truth["K"][i], truth["R"][i], truth["t"][i])[0]
    arrays = dict(cap.arrays)
    arrays["landmarks"] = lm
    cap2 = write_artifact(tmp_path / "cap_det.npz", "capture", arrays, extra_meta={"report": {"identity": "001"}})
    geo = tmp_path / "gt.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "--from-truth", world / "syn" / "truth" / "001.npz",
            "-o", geo)
    assert r.exit_code == 0, r.output
    out = tmp_path / "fm_det.npz"
    r = cli("face-model", "embed-landmarks", "--face-model", fm_path, "--capture", cap2, "--geometry", geo,
            "-o", out, "-w", tmp_path)
    assert r.exit_code == 0, r.stderr
    assert r.stdout.split() == [str(out), str(out.with_suffix(".png"))]
    new = read_artifact(out, "face-model")
    got = np.asarray(new["landmarks"])
    # a sample point of a vertex is hit within its triangle fan: the nearest vertex is the detector's, or one at
    # most a grid step away on this 2000-vertex model
    err = np.linalg.norm(mean[got[17:]] - mean[det[17:]], axis=1)
    assert np.median(err) == 0.0 and err.max() < 4.0, err
    np.testing.assert_array_equal(got[:17], lmk[:17])
    emb = new.meta["info"]["landmark_embedding"]
    assert emb["views"] == 5 and emb["per_group"]["eyes"]["moved"] >= 10
    np.testing.assert_array_equal(new["mean_shape"], fm["mean_shape"])
    # the per-camera offsets: one identity per camera, none for the jaw, small for a detector that is exact up to
    # the snap to a vertex; --no-view-bias writes none
    vb = new.meta["info"]["landmark_view_bias"]
    assert sorted(vb["cameras"]) == sorted(str(v) for v in cap["view_names"])
    offs = np.stack([np.asarray(c["offset_iod"]) for c in vb["cameras"].values()])
    assert all(c["identities"] == 1 for c in vb["cameras"].values()) and (offs[:, :17] == 0).all()
    assert np.median(np.abs(offs[:, 17:])) < 0.01, np.median(np.abs(offs[:, 17:]))
    out2 = tmp_path / "fm_nobias.npz"
    r = cli("face-model", "embed-landmarks", "--face-model", fm_path, "--capture", cap2, "--geometry", geo,
            "-o", out2, "-w", tmp_path, "--no-view-bias")
    assert r.exit_code == 0, r.stderr
    assert "landmark_view_bias" not in read_artifact(out2, "face-model").meta["info"]
    # a capture whose identity has no geometry: refused, nothing written
    arrays_other = dict(arrays)
    cap3 = write_artifact(tmp_path / "cap_other.npz", "capture", arrays_other,
                          extra_meta={"report": {"identity": "002"}})
    bad = tmp_path / "never.npz"
    r = cli("face-model", "embed-landmarks", "--face-model", fm_path, "--capture", cap3, "--geometry", geo,
            "-o", bad, "-w", tmp_path)
    assert r.exit_code != 0 and "no geometry of identity 002" in r.stderr and not bad.exists()
    assert len(r.stderr.strip().splitlines()) == 1
    # a geometry of another face model (fewer vertices): refused, naming that file
    g = read_artifact(geo, "geometry")
    small = write_artifact(tmp_path / "gt_small.npz", "geometry", {**g.arrays, "vertices": g["vertices"][:100]},
                           extra_meta={"report": {"identity": "001"}})
    r = cli("face-model", "embed-landmarks", "--face-model", fm_path, "--capture", cap2, "--geometry", small,
            "-o", bad, "-w", tmp_path)
    assert r.exit_code != 0 and str(small) in r.stderr and "has 100 vertices" in r.stderr and not bad.exists()


@pytest.mark.parametrize("args, msg", [(["--joint-rounds", "-1"], "--joint-rounds"),
                                       (["--joint-gate", "-5"], "--joint-gate"),
                                       (["--joint-blur", "-1"], "--joint-blur"),
                                       (["--joint-unmarked-weight", "1.5"], "--joint-unmarked-weight"),
                                       (["--joint-unmarked-weight", "-0.1"], "--joint-unmarked-weight")])
def test_bad_joint_round_settings_are_refused_before_any_work(world, cli, args, msg):
    out = world / "fit-geometry" / "bad_joint.npz"
    r = cli("fit-geometry", "--id", "001", "-w", world, "-o", out, *args)
    assert r.exit_code != 0 and msg in r.stderr and not out.exists()

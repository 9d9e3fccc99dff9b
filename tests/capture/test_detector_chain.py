"""The demo's capture chain from images alone, end to end on a small painted world: dlib's landmarks where it finds
a face, an annotated reference for the landmark embedding, calibrate-rig and fit-geometry on dlib's points, and
unwrap-uv on the views and flashes that landmarks placed (recipes/synthetic.toml, docs/capture.md)."""
import json

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact

VIEWS = ["13_0", "14_0", "05_1", "05_0", "04_1", "19_0"]
FLASHES = ["05", "06", "07", "08", "09"]

RECIPE = f"""schema = "reflectmm.recipe/1"
name = "detector-chain"

[stages.synth-multipie]
params = {{ identities = 3, seed = 0, brdf = "ggx", features = "painted", image_size = "640x480", uv_size = 64, noise = 0.002, landmark_noise = 1.0, face_vertices = 6000, cameras = {json.dumps(VIEWS)}, flashes = {json.dumps(FLASHES)} }}

[stages.detect-landmarks]
inputs = {{ images = "@synth-multipie.dir/data/session01/multiview/*/01/*/*_00.png" }}
params = {{ allow_missing = true }}

[stages.preprocess-multipie]
foreach = "all found"
inputs = {{ root = "@synth-multipie.dir", landmarks = "@detect-landmarks.dir" }}
params = {{ views = {json.dumps(VIEWS)}, flashes = {json.dumps(FLASHES)} }}

[stages.preprocess-annotated]
verb = "preprocess-multipie"
foreach = "all found"
inputs = {{ root = "@synth-multipie.dir" }}
params = {{ views = {json.dumps(VIEWS)}, flashes = {json.dumps(FLASHES)} }}

[stages.calibrate-annotated]
verb = "calibrate-rig"
inputs = {{ capture = "@preprocess-annotated.output", face_model = "@synth-multipie.outputs.face_model", rig = "@synth-multipie.outputs.rig" }}
params = {{ focal_mode = "fixed", distance_sigma_rel = 0.01 }}

[stages.fit-geometry-annotated]
verb = "fit-geometry"
foreach = "all found"
inputs = {{ capture = "@preprocess-annotated.output", face_model = "@synth-multipie.outputs.face_model", rig = "@calibrate-annotated.outputs.rig", truth = "@synth-multipie.dir/truth/{{id}}.npz" }}
params = {{ rig_sigma_mm = 3.0, rig_rot_sigma_deg = 0.3, photo_rounds = 0, flash_rounds = 1 }}

[stages.face-model-embed]
inputs = {{ face_model = "@synth-multipie.outputs.face_model", capture = ["@preprocess-multipie.dir/001.npz", "@preprocess-multipie.dir/002.npz"], geometry = ["@fit-geometry-annotated.dir/001.npz", "@fit-geometry-annotated.dir/002.npz"] }}

[stages.calibrate-rig]
inputs = {{ capture = "@preprocess-multipie.output", face_model = "@face-model-embed.output", rig = "@synth-multipie.outputs.rig" }}
params = {{ focal_mode = "fixed", distance_sigma_rel = 0.01, landmark_weights = {{ jaw = 0 }} }}

[stages.fit-geometry]
foreach = "all found"
inputs = {{ capture = "@preprocess-multipie.output", face_model = "@face-model-embed.output", rig = "@calibrate-rig.outputs.rig", truth = "@synth-multipie.dir/truth/{{id}}.npz" }}
params = {{ rig_sigma_mm = 3.0, rig_rot_sigma_deg = 0.3, photo_rounds = 0, flash_rounds = 1, landmark_weights = {{ jaw = 0 }}, landmark_sigma_px = 3.0 }}

[stages.unwrap-uv]
foreach = "all found"
inputs = {{ capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output", face_model = "@synth-multipie.outputs.face_model" }}
params = {{ uv_size = 64, views = ["landmarked"], flashes = ["landmarked"] }}
"""


def test_the_capture_chain_runs_on_dlib_landmarks(tmp_path, cli):
    pytest.importorskip("dlib")
    (tmp_path / "r.toml").write_text(RECIPE)
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--jobs", "1", "--json")
    assert res.exit_code == 0, res.stderr
    # dlib finds no face on the 45° view: it has no landmarks in any capture and is listed as such
    no_face = (tmp_path / "detect-landmarks" / "no_face.txt").read_text()
    assert "_190_00.png" in no_face
    for ident in ("001", "002", "003"):
        cap = read_artifact(tmp_path / "preprocess-multipie" / f"{ident}.npz", "capture")
        names = [str(v) for v in cap["view_names"]]
        assert np.isnan(cap["landmarks"][names.index("19_0")]).all()
        geo = read_artifact(tmp_path / "fit-geometry" / f"{ident}.npz", "geometry")
        ref = read_artifact(tmp_path / "fit-geometry-annotated" / f"{ident}.npz", "geometry")
        evidence = dict(zip([str(v) for v in geo["view_names"]], [str(e) for e in geo["view_evidence"]]))
        assert not evidence["19_0"].startswith("landmarks")
        assert all(str(e).startswith("landmarks") for e in ref["view_evidence"])
        # dlib's points of the cameras the embedding has offsets for are corrected by them, in the fit and the rig
        assert "corrected by the face model's per-camera offsets" in geo.meta["report"]["landmark_view_bias"]
        # the face from dlib's points (embedded, jaw left out) is a face: within a few times the reference
        assert float(geo["err_vertex_rmse_mm"]) < 4.0 * float(ref["err_vertex_rmse_mm"]) + 2.0
        # reflectance only from the views (and their flashes) that landmarks placed
        obs = read_artifact(tmp_path / "unwrap-uv" / f"{ident}.npz", "uv-observations")
        placed = [v for v in VIEWS if evidence[v].startswith("landmarks")]
        assert [str(v) for v in obs["view_names"]] == placed
    rig = read_artifact(tmp_path / "calibrate-rig" / "calibrate-rig.npz", "rig")
    assert any("per-camera offsets" in a for a in rig.meta["assumptions"])
    # nothing to do the second time
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--jobs", "1", "--json")
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}

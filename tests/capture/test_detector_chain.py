"""The demo's capture chain from images alone, end to end on a small painted world: dlib's landmarks where it finds
a face, an annotated reference for the landmark embedding, calibrate-rig and fit-geometry on dlib's points, and
unwrap-uv on the views and flashes that landmarks placed, and on those whose placement checks out (the demo's
`trusted`; recipes/synthetic.toml, docs/capture.md)."""
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

[stages.unwrap-trusted]
verb = "unwrap-uv"
foreach = "all found"
inputs = {{ capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output", face_model = "@synth-multipie.outputs.face_model" }}
params = {{ uv_size = 64, views = ["trusted"], flashes = ["trusted"] }}
"""


def _trusted_by_hand(geo):
    """The views and flashes that `trusted` should keep, computed here from the geometry's own arrays: landmarked
    views, and views registered by their images whose centre 1-sigma <= 10 mm and flash residual <= 3x the
    landmarked views' median; the flashes that sit exactly on a kept view's centre."""
    names = [str(v) for v in geo["view_names"]]
    ev = [str(e) for e in geo["view_evidence"]]
    lm = np.array([e.startswith("landmarks") for e in ev])
    res, sig = np.asarray(geo["flash_residual"], float), np.asarray(geo["center_sigma_mm"], float)
    med = np.median(res[lm & np.isfinite(res)])
    keep = [n for v, n in enumerate(names)
            if lm[v] or ("+" in ev[v] and np.isfinite(sig[v]) and sig[v] <= 10.0 and res[v] <= 3.0 * med)]
    centers = {n: np.asarray(geo["cam_centers"], float)[i] for i, n in enumerate(names)}
    flashes = [str(f) for f, p, carried in zip(geo["flash_ids"], np.asarray(geo["flash_pos"], float),
                                               geo["flash_from_view"])
               if carried and any(np.array_equal(p, centers[n]) for n in keep)]
    return keep, flashes


def test_the_capture_chain_runs_on_dlib_landmarks(tmp_path, cli):
    pytest.importorskip("dlib")
    (tmp_path / "r.toml").write_text(RECIPE)
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--jobs", "1", "--json")
    assert res.exit_code == 0, res.stderr
    # dlib finds no face on the 45° view: it has no landmarks in any capture and is listed as such
    no_face = (tmp_path / "detect-landmarks" / "no_face.txt").read_text()
    assert "_190_00.png" in no_face
    kept_registered = left_registered = 0
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
        # the trusted selection: those, and the registered views (and their flashes) that check out
        trusted = read_artifact(tmp_path / "unwrap-trusted" / f"{ident}.npz", "uv-observations")
        views, flashes = _trusted_by_hand(geo)
        assert [str(v) for v in trusted["view_names"]] == [v for v in VIEWS if v in views]
        assert sorted(str(f) for f in trusted["flash_ids"]) == sorted(flashes)
        assert set(placed) <= set(views) and set(str(f) for f in obs["flash_ids"]) <= set(flashes)
        registered = [v for v in VIEWS if "+" in evidence[v] and not evidence[v].startswith("landmarks")]
        kept_registered += sum(v in views for v in registered)
        left_registered += sum(v not in views for v in registered)
    # this world has both: a registered view that checks out (kept) and one that does not (left out)
    assert kept_registered >= 1 and left_registered >= 1
    rig = read_artifact(tmp_path / "calibrate-rig" / "calibrate-rig.npz", "rig")
    assert any("per-camera offsets" in a for a in rig.meta["assumptions"])
    # nothing to do the second time
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--jobs", "1", "--json")
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}

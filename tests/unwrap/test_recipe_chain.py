"""unwrap-uv as a recipe stage after synth → preprocess → fit-geometry (ground truth), as recipes/synthetic.toml."""

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact

RECIPE = """
schema = "reflectmm.recipe/1"
name = "mini"

[stages.synth-multipie]
params = { identities = 2, seed = 3, brdf = "model", image_size = "160x120", uv_size = 32, face_vertices = 1500, cameras = ["13_0", "05_1", "04_1"], flashes = ["05", "07"] }

[stages.preprocess-multipie]
foreach = "all found"
inputs = { root = "@synth-multipie.dir" }
params = { views = ["13_0", "05_1", "04_1"], flashes = ["05", "07"] }

[stages.fit-geometry]
foreach = "all found"
inputs = { capture = "@preprocess-multipie.output", face_model = "@synth-multipie.outputs.face_model", rig = "@synth-multipie.outputs.rig", truth = "@synth-multipie.dir/truth/{id}.npz" }
params = { from_truth = true }

[stages.unwrap-uv]
foreach = "all found"
inputs = { capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output" }
params = { uv_size = 32 }
"""


@pytest.mark.slow
def test_recipe_chain_and_cache(tmp_path, cli):
    (tmp_path / "mini.toml").write_text(RECIPE)
    res = cli("run", tmp_path / "mini.toml", "--workspace", tmp_path, "--executor", "serial")
    assert res.exit_code == 0, res.stderr + res.stdout
    outs = sorted((tmp_path / "unwrap-uv").glob("*.npz"))
    assert [p.name for p in outs] == ["001.npz", "002.npz"]
    obs = read_artifact(outs[0], "uv-observations")
    assert obs["radiance"].shape == (6, 32, 32, 3) and obs["observed"].any()
    np.testing.assert_array_equal(obs["obs_count"], obs["observed"].sum(0))
    # the face model came from the default rule (the capture's dataset folder)
    roles = {r["role"]: r for r in obs.meta["inputs"]}
    assert set(roles) == {"capture", "geometry", "face_model"}
    assert roles["face_model"]["path"].endswith("synth-multipie/face_model.npz")
    before = {p.name: p.stat().st_mtime_ns for p in outs}
    res = cli("run", tmp_path / "mini.toml", "--workspace", tmp_path, "--executor", "serial")
    assert res.exit_code == 0
    assert {p.name: p.stat().st_mtime_ns for p in sorted((tmp_path / "unwrap-uv").glob("*.npz"))} == before

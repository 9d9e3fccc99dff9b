"""preprocess-multipie as a recipe stage: identities discovered under the root, only the changed one reruns."""

import json

import numpy as np

from _capture_tree import FLASHES, VIEWS, make_tree, shot_file
from reflectmm_cli.capture.images import write_png

RECIPE = f"""
schema = "reflectmm.recipe/1"
name = "capture"

[stages.preprocess]
verb = "preprocess-multipie"
foreach = "all found"
inputs = {{ root = "mp" }}
params = {{ views = {json.dumps(list(VIEWS))}, flashes = {json.dumps(list(FLASHES))}, rotate = {{ "08_1" = 180 }} }}
"""


def _mtimes(ws):
    return {p.name: p.stat().st_mtime_ns for p in (ws / "preprocess").glob("*.npz")}


def test_recipe_runs_all_found_and_reruns_only_changed_identity(tmp_path, cli):
    ws = tmp_path
    make_tree(ws / "mp", ("001", "002"))
    (ws / "capture.toml").write_text(RECIPE)
    res = cli("run", ws / "capture.toml", "--workspace", ws, "--executor", "serial")
    assert res.exit_code == 0, res.stderr
    first = _mtimes(ws)
    assert sorted(first) == ["001.npz", "002.npz"]
    from reflectmm_cli.artifacts import read_artifact

    art = read_artifact(ws / "preprocess" / "001.npz", "capture")
    assert art.params["rotate"] == {"08_1": 180}
    write_png(shot_file(ws / "mp", "002", "13_0", "05"), np.full((32, 48, 3), 7, np.uint8))
    res = cli("run", ws / "capture.toml", "--workspace", ws, "--executor", "serial")
    assert res.exit_code == 0, res.stderr
    second = _mtimes(ws)
    assert second["001.npz"] == first["001.npz"]
    assert second["002.npz"] != first["002.npz"]

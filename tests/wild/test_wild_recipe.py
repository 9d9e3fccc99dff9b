"""The in-the-wild stages in a recipe: synth-wild → prepare-wild (foreach all found) through `reflectmm run`,
a no-op rerun, recipe params validated exactly like the command line's options."""
import json
from dataclasses import fields

import numpy as np
import pytest

from reflectmm_cli.finetune.data import PrepareConfig, open_shard
from reflectmm_cli.stages import get_stage
from reflectmm_cli.synth.wild import WildConfig

TINY = ("count = 3, size = 48, images_per_identity = 1, envmaps = 1, envmap_width = 32, prefilter_width = 16, "
        "uv_size = 16, face_vertices = 2000, ao_rays = 2, spec_rays = 2, occluder_fraction = 0.0")


def _recipe(synth_params: str = TINY, prepare_params: str = "shard_size = 2, from_truth = true, size = 48") -> str:
    return f"""schema = "reflectmm.recipe/1"
[stages.synth-wild]
params = {{ {synth_params} }}

[stages.prepare-wild]
foreach = "all found"
inputs = {{ images = "@synth-wild.dir/images", truth = "@synth-wild.dir", face_model = "@synth-wild.outputs.face_model" }}
params = {{ {prepare_params} }}
"""


def test_params_take_the_config_defaults_and_are_config_fields():
    """One default per value: every declared param of synth-wild / prepare-wild is a field of the library
    config with the same default (allow_skipped is the stage's own: it only decides the exit status)."""
    for verb, cfg in (("synth-wild", WildConfig()), ("prepare-wild", PrepareConfig())):
        names = {f.name for f in fields(cfg)}
        for p in get_stage(verb).params:
            if p.name == "allow_skipped":
                assert not p.invalidates_cache
                continue
            assert p.name in names, (verb, p.name)
            d = getattr(cfg, p.name)
            assert p.default == (list(d) if isinstance(d, tuple) else d), (verb, p.name)
    # the resolved defaults build the default config
    from reflectmm_cli.stages.prepare_wild import prepare_config
    from reflectmm_cli.stages.synth_wild import wild_config
    assert wild_config(get_stage("synth-wild").resolve({})) == WildConfig()
    assert prepare_config(get_stage("prepare-wild").resolve({})) == PrepareConfig()


def test_synth_wild_then_prepare_wild_recipe_runs_then_reruns_nothing(tmp_path, cli):
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "r.toml").write_text(_recipe())
    res = cli("run", ws / "r.toml", "--workspace", ws, "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    assert {(t["stage"], t["id"], t["status"]) for t in doc["tasks"]} == {
        ("synth-wild", None, "ok"), ("prepare-wild", "shard_00000", "ok"), ("prepare-wild", "shard_00001", "ok")}
    a, b = open_shard(ws / "prepare-wild" / "shard_00000.npz"), open_shard(ws / "prepare-wild" / "shard_00001.npz")
    assert len(a) == 2 and len(b) == 1 and a.image_size == 48 and "truth_sh" in a
    # a rerun executes nothing
    res = cli("run", ws / "r.toml", "--workspace", ws, "--json")
    assert res.exit_code == 0, res.stderr
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}
    # the command line with the same params gives the same key: the shard is recognised as up to date
    res = cli("prepare-wild", "--images", ws / "synth-wild" / "images", "--shard-size", 2, "--from-truth",
              "--size", 48, "--shard", "shard_00001", "--workspace", ws)
    assert res.exit_code == 0, res.stderr
    res = cli("run", ws / "r.toml", "--workspace", ws, "--json")
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}
    assert np.array_equal(open_shard(ws / "prepare-wild" / "shard_00001.npz")["image"], b["image"])
    # one shard's image changed: only that shard reruns
    img = ws / "synth-wild" / "images" / f"{b['names'][0]}.png"
    img.write_bytes((ws / "synth-wild" / "images" / f"{a['names'][0]}.png").read_bytes())
    res = cli("run", ws / "r.toml", "--workspace", ws, "--dry-run", "--json")
    assert {(t["id"], t["status"]) for t in json.loads(res.stdout)["tasks"]} == {
        (None, "skip"), ("shard_00000", "skip"), ("shard_00001", "run")}


@pytest.mark.parametrize("synth, prepare, msg", [
    (TINY.replace("size = 48", "size = 2.5"), "shard_size = 2", "[stages.synth-wild] params: size: 2.5 is not an integer"),
    (TINY.replace("size = 48", "size = 8"), "shard_size = 2", "size: 8 is below the minimum 32"),
    (TINY + ", encoding = 'jpeg'", "shard_size = 2", "encoding: 'jpeg' is not one of gamma1.2, srgb"),
    (TINY.replace("occluder_fraction = 0.0", "occluder_fraction = 1.5"), "shard_size = 2", "occluder_fraction: 1.5 is above the maximum 1"),
    (TINY, "shard_sise = 2", "[stages.prepare-wild] params: unknown param 'shard_sise' (did you mean 'shard_size'?)"),
    (TINY, "shard_size = 0", "shard_size: 0 is below the minimum 1"),
    (TINY, "from_truth = 'maybe'", "from_truth: 'maybe' is not true or false"),
])
def test_bad_recipe_params_are_one_line_errors(tmp_path, cli, synth, prepare, msg):
    (tmp_path / "r.toml").write_text(_recipe(synth, prepare))
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path)
    assert res.exit_code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("reflectmm: error: ") and msg in lines[0], res.stderr
    assert not (tmp_path / "synth-wild").exists()


def test_the_command_line_refuses_the_same_values(tmp_path, cli):
    res = cli("synth", "wild", "--size", "2.5", "--out", tmp_path / "w")
    assert res.exit_code == 1 and "--size: 2.5 is not an integer" in res.stderr
    res = cli("synth", "wild", "--envmap-width", "33", "--out", tmp_path / "w")
    assert res.exit_code == 1 and "--envmap-width: 33 is not even" in res.stderr
    assert not (tmp_path / "w").exists()


def test_the_recipes_in_the_wild_docs_parse_and_their_params_resolve():
    import re
    from pathlib import Path

    from reflectmm_cli.recipes import parse_recipe_text

    doc = Path(__file__).resolve().parents[2] / "docs" / "wild.md"
    blocks = [b for b in re.findall(r"```toml\n(.*?)```", doc.read_text(), re.S) if "schema" in b]
    assert blocks
    for text in blocks:
        recipe = parse_recipe_text(text, doc)
        for spec in recipe.stages.values():
            get_stage(spec.verb).resolve(spec.params)


def test_detect_landmarks_is_a_recipe_stage_over_a_folder(tmp_path, cli):
    pytest.importorskip("dlib")
    from skimage import data

    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.landmarks import read_landmarks

    write_png(tmp_path / "photos" / "astronaut.png", data.astronaut())
    (tmp_path / "photos" / "notes.txt").write_text("not an image")
    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.detect-landmarks]\n'
                                     'inputs = { images = "photos" }\nparams = { upsample = 1 }\n')
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--json")
    assert res.exit_code == 0, res.stderr
    assert json.loads(res.stdout)["outputs"] == [str(tmp_path / "detect-landmarks" / "astronaut.pts")]
    assert read_landmarks(tmp_path / "detect-landmarks" / "astronaut.pts").shape == (68, 2)
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--json")
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}
    (tmp_path / "r.toml").write_text((tmp_path / "r.toml").read_text().replace("upsample = 1", "upsample = 4"))
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path)
    assert res.exit_code == 1 and "upsample: 4 is above the maximum 3" in res.stderr


def test_detect_landmarks_with_allow_missing_feeds_a_recipe_and_reruns_nothing(tmp_path, cli):
    """A capture's side views have no face a frontal detector finds: with allow_missing the stage succeeds, its
    no_face.txt lists them, a rerun is a no-op, and a deleted landmark file makes it run again."""
    pytest.importorskip("dlib")
    import numpy as np
    from skimage import data

    from reflectmm_cli.artifacts import write_png

    write_png(tmp_path / "photos" / "astronaut.png", data.astronaut())
    write_png(tmp_path / "photos" / "side.png", np.full((120, 160, 3), 0.4))
    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.detect-landmarks]\n'
                                     'inputs = { images = "photos" }\nparams = { allow_missing = true }\n')
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--json")
    assert res.exit_code == 0, res.stderr
    out = tmp_path / "detect-landmarks"
    assert set(json.loads(res.stdout)["outputs"]) == {str(out / "no_face.txt"), str(out / "astronaut.pts")}
    assert "side.png" in (out / "no_face.txt").read_text() and not (out / "side.pts").exists()
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--json")
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"skipped"}
    (out / "astronaut.pts").unlink()
    res = cli("run", tmp_path / "r.toml", "--workspace", tmp_path, "--json")
    assert res.exit_code == 0, res.stderr
    assert {t["status"] for t in json.loads(res.stdout)["tasks"]} == {"ok"}
    assert (out / "astronaut.pts").is_file()

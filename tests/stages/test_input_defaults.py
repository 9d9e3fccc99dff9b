"""A command's default inputs come from the stage's declaration (``Input(..., upstream=, default=Default(...))``):
each declared default resolves to its upstream stage's artifact, which is what a recipe naming that upstream
(``@<upstream>.output``) resolves to; the commands take their defaults from there."""
from __future__ import annotations

from pathlib import Path

import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.plan import make_plan
from reflectmm_cli.recipes.recipe import Ref, parse_recipe_text
from reflectmm_cli.stages import STAGE_MODULES, all_stages, get_stage
from reflectmm_cli.stages.defaults import default_inputs, default_paths
from reflectmm_cli.workspace import stage_output

ROOT = Path(__file__).resolve().parents[2]
IDS = ["001", "002"]


def _declared(rule: str | None = None):
    out = []
    for verb, stage in sorted(all_stages().items()):
        if verb not in STAGE_MODULES:
            continue
        for inp in stage.inputs or ():
            if inp.default is not None and (rule is None or inp.default.rule == rule):
                out.append((verb, inp))
    return out


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def _upstream_outputs(verb: str, ws: Path, identity: str | None) -> list[Path]:
    """What a recipe stage named after ``verb`` writes (the planner's ``Task.outputs``)."""
    stage = get_stage(verb)
    ctx = stage.context(workspace=ws, identity=identity if stage.per_identity else None)
    return [Path(p) for p in stage.expected_outputs(ctx)]


def test_every_default_names_an_upstream_stage_and_a_known_rule():
    known = {"output", "all", "folder", "face-model", "truth", "rig", "fit-rig"}
    for verb, inp in _declared():
        assert inp.upstream in STAGE_MODULES, (verb, inp.role)
        assert inp.default.rule in known, (verb, inp.role)
        assert not inp.prefix, (verb, inp.role)


@pytest.mark.parametrize("verb,inp", _declared("output"), ids=lambda x: x if isinstance(x, str) else x.role)
def test_an_output_default_is_the_upstream_stages_output(tmp_path, verb, inp):
    """``output``: the upstream's primary output (or its named output) for the identity, one per --ids id for a
    ``many`` role — exactly the file the upstream stage writes."""
    up = get_stage(inp.upstream)
    ident = "001" if up.per_identity else None
    ids = IDS if inp.many and up.per_identity else ()
    paths, _ = default_paths(inp, tmp_path, identity=ident, ids=ids)
    if ids:
        assert paths == [_upstream_outputs(inp.upstream, tmp_path, i)[0] for i in ids]
    elif inp.default.name is None:
        assert paths == [_upstream_outputs(inp.upstream, tmp_path, ident)[0]]
    else:
        assert len(paths) == 1 and paths[0] in _upstream_outputs(inp.upstream, tmp_path, ident)


@pytest.mark.parametrize("verb,inp", _declared("all") + _declared("folder"), ids=lambda x: x if isinstance(x, str) else x.role)
def test_an_all_or_folder_default_is_the_upstream_stages_folder(tmp_path, verb, inp):
    folder = _upstream_outputs(inp.upstream, tmp_path, "shard_00000")[0].parent
    assert folder == tmp_path / inp.upstream
    sfx = inp.default.suffix
    written = [_touch(folder / f"shard_00001{sfx}"), _touch(folder / f"shard_00000{sfx}")]
    _touch(folder / f".shard_00002.tmp{sfx}")  # a hidden temp file is not an artifact
    paths, missing = default_paths(inp, tmp_path)
    assert missing is None
    assert paths == (sorted(written) if inp.default.rule == "all" else [folder])


@pytest.mark.parametrize("verb,inp", _declared("face-model"), ids=lambda x: x if isinstance(x, str) else x.role)
def test_a_face_model_default_finds_the_upstream_stages_face_model(tmp_path, verb, inp):
    """The workspace's face model search ends at what ``synth-multipie`` writes (``@synth-multipie.outputs
    .face_model`` in the recipes)."""
    assert inp.upstream == "synth-multipie"
    fm = next(p for p in _upstream_outputs("synth-multipie", tmp_path, None) if p.name == "face_model.npz")
    assert default_paths(inp, tmp_path)[0] == []
    _touch(fm)
    assert default_paths(inp, tmp_path) == ([fm], None)
    _touch(tmp_path / "face_model.npz")  # the workspace's own comes first (workspace.find_face_model)
    assert default_paths(inp, tmp_path)[0] == [tmp_path / "face_model.npz"]


@pytest.mark.parametrize("verb,inp", _declared("truth"), ids=lambda x: x if isinstance(x, str) else x.role)
def test_a_truth_default_is_the_upstream_stages_truth_folder(tmp_path, verb, inp):
    """``@synth-multipie.dir/truth`` in the recipes: the folder for a ``many`` role, ``<folder>/<id>.npz`` else."""
    assert inp.upstream == "synth-multipie"
    written = next(p for p in _upstream_outputs("synth-multipie", tmp_path, None) if p.parent.name == "truth")
    folder = written.parent
    paths, missing = default_paths(inp, tmp_path, identity="001")
    assert paths == [] and missing == tmp_path
    _touch(written)
    assert default_paths(inp, tmp_path, identity=written.stem) == ([folder] if inp.many else [written], None)


def test_the_calibrated_rig_default_is_what_calibrate_rig_writes(tmp_path):
    inp = next(i for i in get_stage("fit-geometry").inputs if i.role == "rig")
    assert inp.upstream == "calibrate-rig" and inp.default.rule == "fit-rig"
    rig = next(p for p in _upstream_outputs("calibrate-rig", tmp_path, None) if p.name == "rig.toml")
    assert default_paths(inp, tmp_path)[0] == []
    _touch(rig)
    assert default_paths(inp, tmp_path) == ([rig], None)


# --------------------------------------------------------------------------- the recipe resolves the same paths

_RECIPE = """
schema = "reflectmm.recipe/1"
name = "defaults"
[stages.preprocess-multipie]
foreach = ["001", "002"]
inputs = { root = "data" }
[stages.fit-geometry]
foreach = ["001", "002"]
inputs = { capture = "@preprocess-multipie.output", face_model = "face_model.npz" }
[stages.unwrap-uv]
foreach = ["001", "002"]
inputs = { capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output", face_model = "face_model.npz" }
[stages.fit-reflectance]
foreach = ["001", "002"]
inputs = { observations = "@unwrap-uv.output" }
[stages.build-pca]
inputs = { maps = "@fit-reflectance.output" }
[stages.build-light-pca]
inputs = { envmaps = "envmaps" }
[stages.finetune]
inputs = { model = "@build-pca.output", light_model = "@build-light-pca.output", data = "shards" }
[stages.reconstruct]
inputs = { model = "@finetune.output", encoder = "@finetune.outputs.finetune_encoder", light_model = "@build-light-pca.output", data = "shards" }
[stages.evaluate-truth]
foreach = ["001", "002"]
inputs = { maps = "@fit-reflectance.output", truth = "truth/{id}.npz" }
[stages.evaluate-representation]
inputs = { observations = "@unwrap-uv.output", capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output", face_model = "face_model.npz" }
[stages.evaluate-relighting]
foreach = ["001"]
inputs = { capture = "@preprocess-multipie.output", geometry = "@fit-geometry.output", face_model = "face_model.npz", model_a = "@build-pca.output" }
params = { methods = ["a"] }
"""


def test_a_commands_default_is_the_path_the_recipe_resolves(tmp_path):
    """For every input a recipe takes from the role's declared upstream stage (stages named after their verbs),
    the planned path equals the command's default for that role, with the upstream outputs in place."""
    ws = tmp_path / "ws"
    for d in ("data", "envmaps", "shards", "truth"):
        (ws / d).mkdir(parents=True)
    _touch(ws / "face_model.npz")
    for i in IDS:
        _touch(ws / "truth" / f"{i}.npz")
    plan = make_plan(parse_recipe_text(_RECIPE, ws / "r.toml"), ws)
    for t in plan.tasks.values():
        for p in t.outputs:
            _touch(p)
    compared = set()
    for t in plan.tasks.values():
        spec, stage = plan.recipe.stages[t.stage_name], get_stage(t.verb)
        decl = {i.role: i for i in stage.inputs}
        for role, items in spec.inputs.items():
            inp = decl.get(role)
            if not (inp and inp.default and all(isinstance(x, Ref) and x.stage == inp.upstream for x in items)):
                continue
            ids = IDS if t.identity is None else ()
            assert t.ctx.inputs[role] == default_paths(inp, ws, identity=t.identity, ids=ids)[0], (t.stage_name, role)
            # and through the function the commands call, with nothing given
            got = default_inputs(stage, ws, {}, identity=t.identity, ids=ids, roles=(role,))
            assert got[role] == t.ctx.inputs[role], (t.stage_name, role)
            compared.add((t.verb, role))
    assert {("fit-geometry", "capture"), ("unwrap-uv", "geometry"), ("fit-reflectance", "observations"),
            ("build-pca", "maps"), ("finetune", "model"), ("reconstruct", "encoder"), ("evaluate-truth", "maps"),
            ("evaluate-representation", "capture"), ("evaluate-relighting", "geometry")} <= compared


# --------------------------------------------------------------------------- the special cases, declared

def test_image_space_inputs_are_passed_all_together_or_not_at_all(tmp_path):
    """evaluate representation: with --ids each identity's capture and geometry and a face model are passed when
    every one exists (the stage then re-renders in image space, as a recipe naming them does), else none of
    them, a given face model included; --space uv passes none."""
    st = get_stage("evaluate-representation")
    fm = _touch(tmp_path / "fm.npz")
    given = {"observations": [], "face_model": [fm]}
    got = default_inputs(st, tmp_path, given, ids=IDS)
    assert set(got) == {"observations"}
    assert got["observations"] == [stage_output(tmp_path, "unwrap-uv", i) for i in IDS]
    for i in IDS:
        _touch(stage_output(tmp_path, "preprocess-multipie", i))
    _touch(stage_output(tmp_path, "fit-geometry", "001"))
    assert set(default_inputs(st, tmp_path, given, ids=IDS)) == {"observations"}  # 002's geometry is missing
    _touch(stage_output(tmp_path, "fit-geometry", "002"))
    got = default_inputs(st, tmp_path, given, ids=IDS)
    assert got["capture"] == [stage_output(tmp_path, "preprocess-multipie", i) for i in IDS]
    assert got["geometry"] == [stage_output(tmp_path, "fit-geometry", i) for i in IDS] and got["face_model"] == [fm]
    assert set(default_inputs(st, tmp_path, given, ids=IDS, params={"space": "uv"})) == {"observations"}
    # without a face model (none given, none in the workspace) the group is dropped
    assert set(default_inputs(st, tmp_path, {}, ids=IDS)) == {"observations"}
    _touch(tmp_path / "face_model.npz")
    assert default_inputs(st, tmp_path, {}, ids=IDS)["face_model"] == [tmp_path / "face_model.npz"]
    # --input without --ids: UV space
    obs = _touch(tmp_path / "o.npz")
    assert default_inputs(st, tmp_path, {"observations": [obs], "face_model": [fm]}) == {"observations": [obs]}


def test_ids_come_before_the_given_paths_and_a_missing_one_is_named(tmp_path):
    st = get_stage("calibrate-rig")
    extra = _touch(tmp_path / "extra.npz")
    with pytest.raises(ReflectmmError) as e:
        default_inputs(st, tmp_path, {"capture": [extra]}, ids=IDS)
    assert str(e.value) == (f"{stage_output(tmp_path, 'preprocess-multipie', '001')}: capture artifact not found "
                            "(run preprocess-multipie first)")
    with pytest.raises(ReflectmmError, match="nope.npz: capture artifact not found"):
        default_inputs(st, tmp_path, {"capture": [tmp_path / "nope.npz"]})


def test_missing_defaults_say_the_option_and_the_path(tmp_path):
    st = get_stage("reconstruct")
    with pytest.raises(ReflectmmError) as e:
        default_inputs(st, tmp_path, {}, roles=("encoder", "model"))
    assert str(e.value) == f"--encoder: not given and {tmp_path / 'finetune' / 'finetune_encoder.safetensors'} does not exist"
    with pytest.raises(ReflectmmError) as e:
        default_inputs(get_stage("finetune"), tmp_path, {}, roles=("data",))
    assert str(e.value) == f"--data: not given and no shards in {tmp_path / 'prepare-wild'}"
    with pytest.raises(ReflectmmError) as e:
        default_inputs(get_stage("build-baseline"), tmp_path, {})
    assert str(e.value) == (f"no --truth given and no truth folder in {tmp_path} (looked for truth/, synth/truth/, "
                            "synth-multipie/truth/)")
    # an optional default that is not there leaves the role out; a given path is kept as given
    assert default_inputs(get_stage("evaluate-truth"), tmp_path, {"truth": [tmp_path / "t.npz"]},
                          identity="001") == {"truth": [tmp_path / "t.npz"]}


def test_the_command_reports_its_declared_default(cli, tmp_path):
    """The command line goes through the declaration: the error names the default the declaration composes."""
    r = cli("fit-reflectance", "--id", "001", "-w", str(tmp_path))
    want = default_paths(next(i for i in get_stage("fit-reflectance").inputs if i.role == "observations"),
                         tmp_path.resolve(), identity="001")[0][0]
    assert r.exit_code == 1
    assert f"{want}: uv-observations not found (run unwrap-uv first or give --input)" in r.stderr
    r = cli("unwrap-uv", "--id", "001", "-w", str(tmp_path))
    assert r.exit_code == 1 and (f"{stage_output(tmp_path.resolve(), 'preprocess-multipie', '001')}: capture "
                                 "artifact not found (run preprocess-multipie first or pass --capture)") in r.stderr


def test_the_reports_inputs_are_what_each_stage_wrote(tmp_path):
    """evaluate report: every role is what its upstream stage wrote (``*.npz``, the viewer's ``*.html``), the truth
    folder stands for its files; a stage with no outputs leaves its role out."""
    st = get_stage("evaluate-report")
    assert default_inputs(st, tmp_path, {"truth": [None]}) == {}
    geo = [_touch(stage_output(tmp_path, "fit-geometry", i)) for i in IDS]
    page = _touch(tmp_path / "view" / "model.html")
    truth = [_touch(tmp_path / "synth" / "truth" / f"{i}.npz") for i in IDS]
    got = default_inputs(st, tmp_path, {"truth": [None]})
    assert got == {"geometry": geo, "viewer": [page], "truth": truth}
    other = tmp_path / "elsewhere"
    mine = _touch(other / "001.npz")
    assert default_inputs(st, tmp_path, {"truth": [other]})["truth"] == [mine]
    assert "truth" not in default_inputs(st, tmp_path, {"truth": [tmp_path / "missing"]})

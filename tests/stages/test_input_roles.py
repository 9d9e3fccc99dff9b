"""Stages declare their input roles once (``Stage.inputs``): recipes and the command line are checked against the
declaration, and ``--help`` shows it."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.recipe import load_recipe, parse_recipe_text
from reflectmm_cli.stages import Input, all_stages, get_stage, run_stage
from reflectmm_cli.stages.registry import STAGE_MODULES

ROOT = Path(__file__).resolve().parents[2]

#: The ways a stage module reads a role.
_READS = re.compile(r"""(?:\.input|\.input_list|_one\(ctx,|inputs\.get|files\.get)\(?\s*["']([a-z_0-9]+)["']""")


def test_every_built_in_stage_declares_its_inputs():
    for verb, stage in all_stages().items():
        if verb in STAGE_MODULES:
            assert stage.inputs is not None, verb
            roles = [i.role for i in stage.inputs]
            assert len(roles) == len(set(roles)), verb


@pytest.mark.parametrize("verb", sorted(STAGE_MODULES))
def test_every_role_a_stage_reads_is_declared(verb):
    src = (ROOT / "reflectmm_cli" / "stages" / f"{STAGE_MODULES[verb]}.py").read_text()
    stage = get_stage(verb)
    for role in set(_READS.findall(src)):
        assert any(i.matches(role) for i in stage.inputs), f"{verb} reads input '{role}' but does not declare it"


@pytest.mark.parametrize("recipe", sorted((ROOT / "recipes").glob("*.toml")), ids=lambda p: p.name)
def test_the_recipes_use_declared_roles_only(recipe):
    r = load_recipe(recipe)
    for name, spec in r.stages.items():
        get_stage(spec.verb).check_roles(spec.inputs, f"[stages.{name}]")


def test_prefix_roles():
    i = Input("model", prefix=True)
    assert i.matches("model_initial") and not i.matches("model") and not i.matches("model_")
    assert not i.matches("models_x")
    assert Input("model").matches("model") and not Input("model").matches("model_x")


def test_unknown_role_in_a_recipe_is_one_line_naming_the_valid_ones(tmp_path):
    from reflectmm_cli.recipes.plan import make_plan

    text = ('schema = "reflectmm.recipe/1"\nname = "t"\n[stages.fit-reflectance]\nforeach = ["001"]\n'
            'inputs = { observatons = "x.npz" }\n')
    (tmp_path / "x.npz").write_bytes(b"")
    recipe = parse_recipe_text(text, tmp_path / "r.toml")
    with pytest.raises(ReflectmmError) as e:
        make_plan(recipe, tmp_path)
    msg = str(e.value)
    assert "\n" not in msg and "unknown input 'observatons'" in msg and "did you mean 'observations'" in msg
    assert "[stages.fit-reflectance]" in msg and "r.toml" in msg


def test_unknown_role_on_the_python_api_is_refused(tmp_path):
    with pytest.raises(ReflectmmError, match=r"unknown input 'mdel' \(did you mean 'model'\?"):
        run_stage("view", workspace=tmp_path, inputs={"mdel": [tmp_path]})


def test_help_lists_the_roles(cli):
    r = cli("view", "--help")
    assert r.exit_code == 0 and "Input roles" in r.output and "compare (reflectance-model; made by build-pca)" in r.output
    r = cli("evaluate", "albedo", "--help")
    assert "model_<name> (reflectance-model)" in r.output

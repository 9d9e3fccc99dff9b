"""``reflectmm run --set STAGE.PARAM=VALUE``: one parameter changed on the command line equals the same change in
the recipe file (same plan, same cache keys); bad overrides are one-line errors that write nothing."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from recipe_testdata import BASIC, IDS

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.recipe import load_recipe, parse_override, parse_recipe_text

EDITED = BASIC.replace("[stages.summary]\n", '[stages.summary]\nparams = { fail_if_contains = "ZZZ" }\n')


def _keys(cli, recipe, ws, *extra):
    r = cli("run", recipe, "-w", ws, "-n", "--json", *extra)
    assert r.exit_code == 0, r.stderr
    return {(t["stage"], t["id"]): t["cache_key"] for t in json.loads(r.stdout)["tasks"]}


def test_set_equals_editing_the_file(cli, ws):
    (ws / "edited.toml").write_text(EDITED)
    assert cli("run", ws / "recipe.toml", "-w", ws).exit_code == 0  # the summary's key needs the manifests
    base = _keys(cli, ws / "recipe.toml", ws)
    by_file = _keys(cli, ws / "edited.toml", ws)
    by_set = _keys(cli, ws / "recipe.toml", ws, "--set", 'summary.fail_if_contains="ZZZ"')
    bare = _keys(cli, ws / "recipe.toml", ws, "--set", "summary.fail-if-contains=ZZZ")
    assert by_set == by_file == bare
    assert by_set[("summary", None)] != base[("summary", None)]  # the change reaches the summary's cache key
    assert all(by_set[("manifest", i)] == base[("manifest", i)] for i in IDS)  # and nothing else's

    r = cli("run", ws / "recipe.toml", "-w", ws, "--set", 'summary.fail_if_contains="ZZZ"')
    assert r.exit_code == 0, r.stderr
    r = cli("run", ws / "edited.toml", "-w", ws, "-n")  # what --set ran is what the edited file asks for
    assert r.exit_code == 0 and "5 skip" in r.stdout.splitlines()[0]
    log = [json.loads(x) for x in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    runs = sorted({x["run"] for x in log}, key=[x["run"] for x in log].index)
    assert [{tuple(x.get("overrides", ())) for x in log if x["run"] == r} for r in runs] == \
        [{()}, {('summary.fail_if_contains="ZZZ"',)}]


def test_the_last_set_wins_and_replaces_defaults(ws):
    r = load_recipe(ws / "recipe.toml", ["manifest.fail_if_contains=A", "manifest.fail_if_contains=B"])
    assert r.stages["manifest"].params["fail_if_contains"] == "B"
    assert r.stages["summary"].params["fail_if_contains"] == "BAD"  # [defaults] still reach the other stage
    assert r.overrides == ("manifest.fail_if_contains=A", "manifest.fail_if_contains=B")


@pytest.mark.parametrize("override, message", [
    ("summary=1", "expected STAGE.PARAM=VALUE"),
    ("summary.fail_if_contains", "expected STAGE.PARAM=VALUE"),
    (".x=1", "expected STAGE.PARAM=VALUE"),
    ("nostage.x=1", "no stage 'nostage' in the recipe (stages: manifest, summary)"),
    ("summary.fail_if_contains=[1,", "cannot read '[1,' as a TOML value"),
    ("summary.fail_if_contains=a b", "cannot read 'a b' as a TOML value"),
])
def test_bad_overrides_one_line_nothing_written(cli, ws, override, message):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--set", override)
    assert r.exit_code == 1 and r.stdout == ""
    err = r.stderr.strip()
    assert err.count("\n") == 0 and message in err and "recipe.toml" in err
    assert not (ws / "manifest").exists() and not (ws / "summary").exists()


@pytest.mark.parametrize("override, message", [
    ("synth-wild.cuont=384", "[stages.synth-wild] params: unknown param 'cuont' (did you mean 'count'?)"),
    ("synth-wild.count=abc", "[stages.synth-wild] params: count: 'abc' is not an integer"),
    ("finetune.solver=newton", "solver"),
])
def test_overrides_checked_by_the_stage_declaration(cli, tmp_path, override, message):
    """The stage's own parameter declaration checks an override before anything runs (the synthetic recipe)."""
    from pathlib import Path

    recipe = Path(__file__).resolve().parents[2] / "recipes" / "synthetic.toml"
    r = cli("run", recipe, "-w", tmp_path / "w", "--set", override)
    assert r.exit_code == 1 and r.stdout == ""
    assert r.stderr.strip().count("\n") == 0 and message in r.stderr and "synthetic.toml" in r.stderr
    assert not any(p.name != ".reflectmm" for p in (tmp_path / "w").iterdir())


@given(st.one_of(st.integers(-10**12, 10**12), st.floats(allow_nan=False, allow_infinity=False), st.booleans(),
                 st.lists(st.integers(0, 99), max_size=4),
                 st.text(st.characters(min_codepoint=32, max_codepoint=126, blacklist_characters='"\\'))))
def test_toml_values_round_trip(value):
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = f'"{value}"'
    else:
        text = repr(value).replace("e+", "e")
    stage, param, got = parse_override(f"a.b-c={text}", BASIC_PATH)
    assert (stage, param) == ("a", "b_c")
    assert type(got) is type(value)
    assert got == value or (isinstance(value, float) and math.isclose(got, value))


def test_bare_words_are_strings():
    for word in ("ls", "ggx", "cuda:0", "data/weights.safetensors", "two-lobe"):
        assert parse_override(f"a.b={word}", BASIC_PATH)[2] == word
    assert parse_override("a.b=true", BASIC_PATH)[2] is True  # a TOML value first


def test_stage_names_with_dots_are_refused(tmp_path):
    """A dot in a stage name made @fit.v2.output and --set fit.v2.x=1 read two ways: such a name is refused."""
    doc = 'schema = "reflectmm.recipe/1"\n[stages."fit.v2"]\nverb = "checksum"\ninputs = { files = "x" }\n'
    with pytest.raises(ReflectmmError, match=r"\[stages.fit.v2\]: bad stage name"):
        parse_recipe_text(doc, tmp_path / "r.toml", ["fit.v2.fail_if_contains=Q"])
    with pytest.raises(ReflectmmError, match="no stage 'fit'"):
        parse_recipe_text(doc, tmp_path / "r.toml", ["fit.fail_if_contains=Q"])
    r = parse_recipe_text(doc.replace('"fit.v2"', "fit-v2"), tmp_path / "r.toml", ["fit-v2.fail_if_contains=Q"])
    assert r.stages["fit-v2"].params == {"fail_if_contains": "Q"}


BASIC_PATH = __import__("pathlib").Path("recipe.toml")


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_the_override_reaches_the_task(cli, ws, jobs):
    """The task runs with the overridden value, in this process and in a pool worker: a marker that only the
    override names fails the one identity whose file holds it."""
    r = cli("run", ws / "recipe.toml", "-w", ws, "--jobs", jobs, "--set", 'manifest.fail_if_contains="identity 002"')
    assert r.exit_code == 1
    assert "reflectmm: failed: manifest/002" in r.stderr and "failed: manifest/001" not in r.stderr
    assert "contains the marker 'identity 002'" in r.stderr
    assert sorted(p.name for p in (ws / "manifest").glob("*.npz")) == ["001.npz", "003.npz", "004.npz"]

"""One parameter declaration per stage: the command line and a recipe validate through it and resolve to the
same params, so they give the same cache key (and a no-op `reflectmm run` after a CLI run executes nothing)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.params import Param, ParamError, parse_list, resolve_params
from reflectmm_cli.recipes import plan_recipe, run_recipe
from reflectmm_cli.reflectance import simulate_observations
from reflectmm_cli.shading.brdf import MAX_EXPONENT, check_exponents, lobe_similarity
from reflectmm_cli.stages import compute_cache_key, get_stage

RECIPE_HEAD = 'schema = "reflectmm.recipe/1"\n'


def _obs(ws: Path, ident: str = "001", S: int = 8) -> Path:
    obs = simulate_observations(S)
    return write_artifact(ws / "unwrap-uv" / f"{ident}.npz", "uv-observations", obs)


def _actions(plan) -> dict[str, str]:
    return {t.tid: t.action for t in plan.tasks.values()}


# --------------------------------------------------------------------------- the declaration itself

def test_parse_list_refuses_empty_items_and_parses_lists():
    assert parse_list("1, 8,64", "x", float) == [1.0, 8.0, 64.0]
    assert parse_list([1, 8], "x", float) == [1.0, 8.0]
    for bad in ("1,,8", "1,8,", ",1"):
        with pytest.raises(ParamError, match="empty item"):
            parse_list(bad, "exponents", float)
    with pytest.raises(ParamError, match="'x' is not a valid item"):
        parse_list("1,x", "exponents", float)


def test_resolve_fills_defaults_canonicalises_and_names_the_closest_param():
    decl = (Param("uv_size", "int", 256, range=(8, 4096)), Param("exponents", "floats", [1.0, 8.0]),
            Param("solver", "str", "fast", choices=("fast", "adam")), Param("focal", "float", None))
    assert resolve_params(decl, {}) == {"exponents": [1.0, 8.0], "solver": "fast", "uv_size": 256}
    # the same value written three ways resolves to one canonical value
    assert resolve_params(decl, {"uv_size": "64", "exponents": "1,8"}) == \
        resolve_params(decl, {"uv_size": 64.0, "exponents": [1, 8]})
    for given, msg in (({"uv_size": 2.5}, "2.5 is not an integer"), ({"uv_size": "abc"}, "'abc' is not an integer"),
                       ({"uv_size": 4}, "below the minimum 8"), ({"uv_size": 100000}, "above the maximum 4096"),
                       ({"uv_size": True}, "boolean"), ({"solver": "slow"}, "not one of fast, adam"),
                       ({"uv_sise": 64}, "did you mean 'uv_size'")):
        with pytest.raises(ParamError, match=msg):
            resolve_params(decl, given)
    assert resolve_params(decl, {"nope": 1}, strict=False) == resolve_params(decl, {})


def test_a_list_that_may_be_empty_says_so_in_its_declaration():
    # fit-geometry's --register-blur is documented "empty = off": an empty list is a value there, and still an
    # error for a list that has no meaning empty
    blur = Param("register_blur_px", "floats", [4.0, 2.0, 0.0], range=(0.0, None), allow_empty=True)
    rounds = Param("exponents", "floats", [1.0, 8.0])
    assert blur.coerce("") == [] and blur.coerce([]) == [] and blur.coerce("2,0") == [2.0, 0.0]
    for v in ("", []):
        with pytest.raises(ParamError, match="exponents: empty list"):
            rounds.coerce(v)
    with pytest.raises(ParamError, match="empty item"):
        blur.coerce("2,,0")
    from reflectmm_cli.stages.fit_geometry import PARAMS, config_from_params

    decl = {p.name: p for p in PARAMS}
    assert decl["register_blur_px"].allow_empty
    assert config_from_params({"register_blur_px": decl["register_blur_px"].coerce("")}).register_blur_px == ()


def test_lobe_similarity_matches_quadrature():
    # <cos^p, cos^q> over the hemisphere by Gauss-Legendre quadrature in mu = cos(theta)
    x, w = np.polynomial.legendre.leggauss(400)
    mu = (x + 1) / 2
    for p, q in ((1.0, 8.0), (8.0, 64.0), (64.0, 70.0), (3.0, 3.0)):
        dot = lambda a, b: np.sum(w / 2 * mu ** (a + b))  # noqa: E731
        ref = dot(p, q) / np.sqrt(dot(p, p) * dot(q, q))
        assert lobe_similarity(p, q) == pytest.approx(ref, rel=1e-10)


def test_check_exponents_refuses_duplicates_near_duplicates_and_huge_exponents():
    check_exponents([1, 8, 64])
    check_exponents([64, 70])  # distinct enough: rcond 5e-4 > 1e-4
    for bad, msg in (([1, 1, 8], "duplicate exponents 1 and 1"), ([1, 1.0000001, 8], "near-duplicate"),
                     ([64, 65], "near-duplicate"), ([1, 8, 1e5], "above the maximum"), ([0, 8], "> 0"),
                     ([-1.0], "> 0")):
        with pytest.raises(ValueError, match=msg):
            check_exponents(bad)
    check_exponents([MAX_EXPONENT])


# --------------------------------------------------------------------------- CLI and recipe: one cache key

def test_cli_and_recipe_give_the_same_cache_key_and_the_rerun_is_a_no_op(cli, tmp_path):
    ws = tmp_path / "ws"
    _obs(ws)
    # command line with no options (every default) ...
    r = cli("fit-reflectance", "--id", "001", "-w", ws)
    assert r.exit_code == 0, r.stderr
    r = cli("synth", "envmaps", "-n", "2", "--width", "16", "-w", ws)
    assert r.exit_code == 0, r.stderr
    r = cli("build-light-pca", ws / "synth-envmaps", "--order", "2", "--components", "2", "-w", ws)
    assert r.exit_code == 0, r.stderr
    cli_keys = {"fit-reflectance/001": read_artifact(ws / "fit-reflectance" / "001.npz").meta["cache_key"],
                "build-light-pca": read_artifact(ws / "build-light-pca" / "build-light-pca.npz").meta["cache_key"]}
    # ... and a recipe that spells some defaults out, in other types (ints for floats), and leaves others out
    (ws / "r.toml").write_text(RECIPE_HEAD + """
[stages.fit-reflectance]
foreach = ["001"]
inputs = { observations = "unwrap-uv/{id}.npz" }
params = { solver = "fast", exponents = [1, 8, 64], symmetry = 1 }

[stages.synth-envmaps]
params = { count = 2, width = 16, seed = 0 }

[stages.build-light-pca]
inputs = { envmaps = "@synth-envmaps.dir" }
params = { order = 2, components = 2.0 }
""")
    plan = plan_recipe(ws / "r.toml", ws)
    assert _actions(plan) == {"fit-reflectance/001": "skip", "synth-envmaps": "skip", "build-light-pca": "skip"}
    for tid, key in cli_keys.items():
        assert plan.tasks[tid].cache_key == key
    before = {p: p.stat().st_mtime_ns for p in ws.rglob("*") if p.is_file() and ".reflectmm" not in p.parts}
    r = cli("run", ws / "r.toml", "-w", ws)
    assert r.exit_code == 0, r.stderr
    assert "3 skipped" in r.stderr and "0 ran" in r.stderr
    after = {p: p.stat().st_mtime_ns for p in before}
    assert after == before  # nothing was rewritten


def test_a_default_change_invalidates_by_itself(tmp_path, monkeypatch):
    from reflectmm_cli.stages import registry

    ws = tmp_path / "ws"
    src = _obs(ws)
    st = get_stage("fit-reflectance")
    k1 = compute_cache_key(st, st.context(workspace=ws, identity="001", inputs={"observations": [src]}))
    # the same stage version, one default changed: a different key, no hand-bumped version needed
    changed = replace(st, params=tuple(replace(p, default=2e-4) if p.name == "prior" else p for p in st.params))
    monkeypatch.setitem(registry._REGISTRY, "fit-reflectance", changed)
    k2 = compute_cache_key(changed, changed.context(workspace=ws, identity="001", inputs={"observations": [src]}))
    assert k1 != k2
    # giving the old default explicitly gives the old key back
    k3 = compute_cache_key(changed, changed.context(workspace=ws, identity="001", params={"prior": 1e-4},
                                                    inputs={"observations": [src]}))
    assert k3 == k1


# --------------------------------------------------------------------------- recipe params validated like the CLI's

UNWRAP = """
[stages.unwrap-uv]
foreach = ["001"]
inputs = { capture = "c/{id}.npz", geometry = "g/{id}.npz" }
params = { uv_size = VALUE }
"""

FIT = """
[stages.fit-reflectance]
foreach = ["001"]
inputs = { observations = "unwrap-uv/{id}.npz" }
params = { NAME = VALUE }
"""


@pytest.mark.parametrize("value, cli_value, message", [
    ("2.5", "2.5", "uv_size: 2.5 is not an integer"),
    ("4", "4", "4 is below the minimum 8"),
    ("100000", "100000", "100000 is above the maximum 4096"),
    ('"abc"', "abc", "'abc' is not an integer"),
])
def test_recipe_uv_size_is_validated_like_the_cli(cli, tmp_path, value, cli_value, message):
    ws = tmp_path / "ws"
    ws.mkdir()
    recipe = ws / "bad.toml"
    recipe.write_text(RECIPE_HEAD + UNWRAP.replace("VALUE", value))
    r = cli("run", recipe, "-w", ws)
    assert r.exit_code == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert str(recipe) in lines[0] and "[stages.unwrap-uv]" in lines[0] and message.split(": ")[-1] in lines[0]
    assert not (ws / "unwrap-uv").exists()
    # the command line refuses the same value with the same words
    r = cli("unwrap-uv", "--id", "001", "--uv-size", cli_value, "-w", ws)
    assert r.exit_code == 1 and "--uv-size" in r.stderr and message.split(": ")[-1] in r.stderr


@pytest.mark.parametrize("name, value, message", [
    ("exponets", "[1, 8, 64]", "unknown param 'exponets' (did you mean 'exponents'?)"),
    ("symetry", "1.0", "unknown param 'symetry' (did you mean 'symmetry'?)"),
    ("exponents", "[1, 1, 8]", "duplicate exponents 1 and 1"),
    ("exponents", "[1, 1.0000001, 8]", "near-duplicate exponents"),
    ("exponents", '"1,,8"', "empty item"),
    ("exponents", "[1, 8, 100000]", "above the maximum 10000"),
    ("symmetry", "2", "2 is above the maximum 1"),
])
def test_recipe_fit_params_are_validated_like_the_cli(cli, tmp_path, name, value, message):
    ws = tmp_path / "ws"
    _obs(ws)
    recipe = ws / "bad.toml"
    recipe.write_text(RECIPE_HEAD + FIT.replace("NAME", name).replace("VALUE", value))
    r = cli("run", recipe, "-w", ws)
    assert r.exit_code == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert str(recipe) in lines[0] and "[stages.fit-reflectance]" in lines[0] and message in lines[0]
    assert not (ws / "fit-reflectance").exists()


@pytest.mark.parametrize("value, message", [
    ("1,1,8", "duplicate exponents 1 and 1"), ("1,1.0000001,8", "near-duplicate exponents"),
    ("1,,8", "empty item"), ("1,8,100000", "above the maximum 10000"),
])
def test_cli_exponents_are_refused_in_one_line(cli, tmp_path, value, message):
    ws = tmp_path / "ws"
    _obs(ws)
    r = cli("fit-reflectance", "--id", "001", "-w", ws, "--exponents", value)
    assert r.exit_code == 1 and "--exponents" in r.stderr and message in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (ws / "fit-reflectance").exists()


def test_defaults_table_params_apply_only_to_the_stages_that_declare_them(tmp_path):
    ws = tmp_path / "ws"
    _obs(ws)
    (ws / "r.toml").write_text(RECIPE_HEAD + """
[defaults]
device = "cpu"
uv_size = 64          # declared by unwrap-uv only: not an error for fit-reflectance

[stages.fit-reflectance]
foreach = ["001"]
inputs = { observations = "unwrap-uv/{id}.npz" }
""")
    rep = run_recipe(ws / "r.toml", ws)
    assert rep.ok
    assert "uv_size" not in read_artifact(ws / "fit-reflectance" / "001.npz").params


def test_execution_details_never_key_the_cache(tmp_path):
    st = get_stage("fit-geometry")
    keys = set()
    for given in ({}, {"threads": 4}, {"device": "cpu"}):
        ctx = st.context(workspace=tmp_path, identity="001", params=given)
        assert "threads" not in ctx.resolved_params()
        keys.add(compute_cache_key(st, ctx))
    assert len(keys) == 1
    # a result-changing param does key it
    ctx = st.context(workspace=tmp_path, identity="001", params={"w_photo": 2.0})
    assert compute_cache_key(st, ctx) not in keys


def test_a_name_given_twice_in_a_list_param_is_refused():
    # preprocess-multipie --views 05_1,05_1 wrote a capture holding the view twice (and --flashes likewise)
    from reflectmm_cli.params import resolve_params
    from reflectmm_cli.stages import preprocess_multipie

    with pytest.raises(Exception, match="views: 05_1 named more than once"):
        resolve_params(preprocess_multipie.PARAMS, {"views": "05_1,14_0,05_1"})
    with pytest.raises(Exception, match="07 named more than once"):
        resolve_params(preprocess_multipie.PARAMS, {"flashes": ["07", "07"]})
    assert resolve_params(preprocess_multipie.PARAMS, {"views": "05_1,14_0"})["views"] == ["05_1", "14_0"]

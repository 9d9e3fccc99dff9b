"""The ready task with the longest chain of stages after it starts first (recipe.chain_lengths,
executors.take_ready): a side branch does not hold up the critical path, and no result changes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from recipe_testdata import make_workspace

from reflectmm_cli.recipes import run_recipe
from reflectmm_cli.recipes.executors import TaskSpec, take_ready
from reflectmm_cli.recipes.recipe import chain_lengths, load_recipe, task_priorities

ROOT = Path(__file__).resolve().parents[2]

# "side" is declared first and is ready first; "a" gates two more stages
CHAIN = """
schema = "reflectmm.recipe/1"
name = "chain"

[stages.side]
verb = "checksum"
inputs = { files = "data/001" }

[stages.a]
verb = "checksum"
inputs = { files = "data/002" }

[stages.b]
verb = "checksum"
inputs = { files = "@a.output" }

[stages.c]
verb = "checksum"
inputs = { files = "@b.output" }
"""


def _longest_by_paths(recipe) -> dict[str, int]:
    """Every path from each stage enumerated (no memo): the independent count."""
    downs = {n: [m for m in recipe.stages if n in recipe.stages[m].upstream()] for n in recipe.stages}

    def paths(n):
        return [[n]] if not downs[n] else [[n] + p for d in downs[n] for p in paths(d)]

    return {n: max(len(p) for p in paths(n)) for n in recipe.stages}


def _below_by_paths(recipe) -> dict[str, int]:
    """The stages reachable downstream of each stage, by walking every path."""
    downs = {n: [m for m in recipe.stages if n in recipe.stages[m].upstream()] for n in recipe.stages}

    def reach(n):
        return set(downs[n]).union(*[reach(d) for d in downs[n]]) if downs[n] else set()

    return {n: len(reach(n)) for n in recipe.stages}


def test_chain_lengths_of_the_shipped_recipe_equal_the_longest_path():
    rec = load_recipe(ROOT / "recipes" / "synthetic.toml")
    got = chain_lengths(rec)
    assert got == _longest_by_paths(rec)
    assert got["evaluate-report"] == 1
    # the annotated reference gates the main chain through the landmark embedding
    assert got["fit-geometry-annotated"] > got["face-model-embed"] > got["fit-geometry"] > got["build-pca"]


def test_task_priorities_are_chain_length_then_downstream_stages():
    rec = load_recipe(ROOT / "recipes" / "synthetic.toml")
    chains, below = _longest_by_paths(rec), _below_by_paths(rec)
    declared = {n: rec.stages[n].priority for n in rec.stages}
    assert task_priorities(rec) == {n: 10 ** 6 * declared[n] + 1000 * chains[n] + below[n] for n in rec.stages}
    pr = task_priorities(rec)
    # equal chains: the one more stages wait for goes first
    assert chains["finetune-diffuse"] == chains["finetune-albedomm"] == 3
    # the demo declares its long finetuning chain, which the stage counts alone put behind the held-out captures
    assert chains["finetune"] < chains["preprocess-heldout"] and pr["finetune"] > pr["preprocess-heldout"]
    assert declared["finetune"] == declared["finetune-control"] == 1


def _recipe(tmp_path, extra: str) -> Path:
    (tmp_path / "data").mkdir(exist_ok=True)
    (tmp_path / "data" / "x.txt").write_text("x")
    p = tmp_path / "r.toml"
    p.write_text('schema = "reflectmm.recipe/1"\nname = "p"\n[stages.s]\nverb = "checksum"\n'
                 'inputs = { files = "data" }\n' + extra)
    return p


def test_a_declared_priority_comes_first(tmp_path):
    rec = load_recipe(_recipe(tmp_path, "priority = -3\n[stages.t]\nverb = \"checksum\"\n"
                                        "inputs = { files = \"@s.output\" }\n"))
    pr = task_priorities(rec)
    assert pr == {"s": -3 * 10 ** 6 + 2001, "t": 1000}
    assert pr["t"] > pr["s"]  # the declared -3 outweighs the longer chain


@pytest.mark.parametrize("value,msg", [('"high"', "priority"), ("true", "priority"), ("1000", "between -999 and 999"),
                                       ("1.5", "priority")])
def test_a_bad_priority_is_a_one_line_error_naming_the_recipe(tmp_path, value, msg):
    from reflectmm_cli.errors import ReflectmmError

    p = _recipe(tmp_path, f"priority = {value}\n")
    with pytest.raises(ReflectmmError) as e:
        load_recipe(p)
    text = str(e.value)
    assert msg in text and "r.toml" in text and "\n" not in text


def _spec(tid, priority=0, deps=()):
    return TaskSpec(tid, "checksum", None, list(deps), priority=priority)


def test_take_ready_picks_the_highest_priority_whose_deps_are_done():
    pending = [_spec("x", 1), _spec("y", 3, deps=["z"]), _spec("w", 2), _spec("v", 2)]
    spec, rest = take_ready(pending, {})
    assert spec.tid == "w" and [s.tid for s in rest] == ["x", "y", "v"]  # y waits; w before v (given first)
    spec, rest = take_ready(pending, {"z": {}})
    assert spec.tid == "y"
    assert take_ready([_spec("y", 3, deps=["z"])], {}) == (None, [_spec("y", 3, deps=["z"])])


@pytest.mark.parametrize("executor,jobs", [("pool", 1), ("serial", 1)])
def test_the_longest_chain_starts_first_and_the_results_are_the_same(tmp_path, executor, jobs):
    ws = make_workspace(tmp_path / executor)
    (ws / "recipe.toml").write_text(CHAIN)
    rep = run_recipe(ws / "recipe.toml", ws, executor=executor, jobs=jobs)
    assert rep.ok
    order = [json.loads(x)["stage"] for x in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    if executor == "pool":
        # a (chain 3) before side (chain 1), although side was given first; once b is done, c and side tie and
        # side, given first, goes first
        assert order == ["a", "b", "side", "c"]
    else:  # one process in the order given: the same artifacts
        ref = {p.name: p.read_bytes() for d in ("side", "a", "b", "c") for p in (ws / d).iterdir()}
        other = make_workspace(tmp_path / "pool_ref")
        (other / "recipe.toml").write_text(CHAIN)
        assert run_recipe(other / "recipe.toml", other, executor="pool", jobs=1).ok
        assert {p.name: p.read_bytes() for d in ("side", "a", "b", "c") for p in (other / d).iterdir()} == ref

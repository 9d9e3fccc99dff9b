"""Bad recipes give one clear error naming the file and the problem, and run nothing."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes import load_recipe, run_recipe
from reflectmm_cli.recipes.recipe import Ref

HEAD = 'schema = "reflectmm.recipe/1"\n'


def write(ws, text):
    p = ws / "r.toml"
    p.write_text(text)
    return p


def err(ws, text, **kw):
    p = write(ws, text)
    with pytest.raises(ReflectmmError) as ei:
        run_recipe(p, ws, dry_run=True, **kw)
    msg = str(ei.value)
    assert "\n" not in msg
    return msg


def test_bad_toml_names_file_line_and_column(ws):
    msg = err(ws, HEAD + '[stages.a]\nverb = "checksum"\ninputs = { files = "data" \n')
    assert str(ws / "r.toml") in msg and "invalid TOML" in msg
    assert "line 4" in msg and "column" in msg


def test_cycle_is_named(ws):
    msg = err(ws, HEAD + """
[stages.a]
verb = "checksum"
inputs = { files = "@c.output" }
[stages.b]
verb = "checksum"
inputs = { files = "@a.output" }
[stages.c]
verb = "checksum"
inputs = { files = ["@b.output", "data"] }
[stages.d]
verb = "checksum"
inputs = { files = "@a.output" }
""")
    assert "cycle" in msg
    cycle = msg.split("cycle: ", 1)[1]
    nodes = cycle.split(" -> ")
    assert nodes[0] == nodes[-1] and sorted(nodes[:-1]) == ["a", "b", "c"]
    # written in data-flow order: each stage feeds the next
    flows = {("a", "b"), ("b", "c"), ("c", "a")}
    assert all((x, y) in flows for x, y in zip(nodes, nodes[1:]))


def test_self_reference_is_a_cycle(ws):
    msg = err(ws, HEAD + '[stages.a]\nverb = "checksum"\ninputs = { files = "@a.output" }\n')
    assert "cycle: a -> a" in msg


def test_unknown_stage_reference(ws):
    msg = err(ws, HEAD + '[stages.a]\nverb = "checksum"\ninputs = { files = "@nope.output" }\n')
    assert "unknown stage 'nope'" in msg and str(ws / "r.toml") in msg


def test_unknown_verb(ws):
    msg = err(ws, HEAD + '[stages.a]\nverb = "no-such-verb"\n')
    assert "[stages.a]" in msg and "unknown stage verb 'no-such-verb'" in msg and "checksum" in msg


@pytest.mark.parametrize("text, what", [
    ('name = "x"\n[stages.a]\nverb = "checksum"\n', "missing schema"),
    ('schema = "other/1"\n[stages.a]\nverb = "checksum"\n', "not a reflectmm recipe"),
    ('schema = "reflectmm.recipe/9"\n[stages.a]\nverb = "checksum"\n', "newer than this reflectmm reads"),
    (HEAD, "no [stages.<name>] tables"),
    (HEAD + 'stage = 1\n[stages.a]\nverb = "checksum"\n', "unknown top-level key(s): stage"),
    (HEAD + '[stages.a]\nverb = "checksum"\nparam = { x = 1 }\n', "unknown key(s) param"),
    (HEAD + '[stages.a]\nverb = "checksum"\nforeach = "everything"\n', '"all found"'),
    (HEAD + '[stages.a]\nverb = "checksum"\nforeach = ["1", "1"]\n', "duplicate id(s) 1"),
    (HEAD + '[stages.a]\nverb = "checksum"\ninputs = { files = 3 }\n', "inputs.files"),
    (HEAD + '[stages.a]\nverb = "checksum"\ninputs = { files = "@b.result" }\n', "malformed reference"),
    (HEAD + '[stages.a]\nverb = "checksum"\nforeach = { file = "nope.txt" }\n', "foreach file not found"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { memory = "lots" }\n', "cannot read 'lots' as a size"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { cpus = -1 }\n', "resources.cpus: must be >= 0"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { cpus = nan }\n', "resources.cpus: must be a finite"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { memory = inf }\n', "resources.memory: must be a finite"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { cpus = "4GB" }\n', "resources.cpus: expected a number"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { cpu = 1 }\n', "resources.cpu: not a resource name; did you mean 'cpus'"),
    (HEAD + '[stages.a]\nverb = "checksum"\nresources = { mem = "2GB" }\n', "did you mean 'memory'"),
    (HEAD + '[stages.a]\nverb = "checksum"\nforeach = [1, 2]\n', 'ids are strings such as "001", got int 1'),
    (HEAD + '[stages.a]\nverb = "checksum"\nforeach = [["001"]]\n', "ids are strings such as"),
    (HEAD + '[stages."a.output"]\nverb = "checksum"\n', "[stages.a.output]: bad stage name"),
    (HEAD + '[stages.a]\nverb = "checksum"\n[stages.b]\nverb = "checksum"\ninputs = { files = "@a.output.output" }\n',
     "malformed reference"),
])
def test_malformed_recipes(ws, text, what):
    msg = err(ws, text)
    assert what in msg and str(ws / "r.toml") in msg


def test_custom_resource_names_are_kept(ws):
    """A name a cluster's workers may declare (not a near miss of cpus, memory, gpus) stays allowed."""
    p = write(ws, HEAD + '[stages.a]\nverb = "checksum"\nresources = { cpus = 1, gpus = 1, licence = 1 }\n')
    assert load_recipe(p).stages["a"].resources == {"cpus": 1, "gpus": 1, "licence": 1}


def test_missing_recipe_file(ws):
    with pytest.raises(ReflectmmError, match="recipe not found"):
        load_recipe(ws / "absent.toml")


def test_unknown_force_or_only_stage(ws):
    msg = err(ws, (ws / "recipe.toml").read_text(), force="nope")
    assert "--force: unknown stage 'nope'" in msg and "manifest" in msg
    msg = err(ws, (ws / "recipe.toml").read_text(), only="nope")
    assert "--only: unknown stage 'nope'" in msg


def test_reference_parsing():
    r = load_recipe.__globals__["parse_ref"]("@synth.dir/multipie/{id}", "x", None)
    assert r == Ref("synth", "dir", None, "/multipie/{id}")
    assert str(r) == "@synth.dir/multipie/{id}"
    r = load_recipe.__globals__["parse_ref"]("@synth.outputs.face_model", "x", None)
    assert r == Ref("synth", "outputs", "face_model", None)
    assert load_recipe.__globals__["parse_ref"]("data/x", "x", None) is None


def test_bad_recipe_loses_nothing(ws):
    run_recipe(ws / "recipe.toml", ws)
    before = {p: p.read_bytes() for p in (ws / "manifest").iterdir()}
    write(ws, HEAD + "[stages.a\n")
    with pytest.raises(ReflectmmError):
        run_recipe(ws / "r.toml", ws)
    assert {p: p.read_bytes() for p in (ws / "manifest").iterdir()} == before


@given(st.integers(2, 7).flatmap(lambda n: st.tuples(
    st.just(n), st.sets(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=14))))
def test_random_graphs_order_or_name_a_real_cycle(graph):
    """Against an independent check: acyclic graphs get a topological order, cyclic ones a real cycle."""
    from pathlib import Path

    from reflectmm_cli.recipes import parse_recipe_text

    n, edges = graph  # (a, b): stage s{b} reads s{a}
    lines = [HEAD]
    for b in range(n):
        srcs = sorted({f"@s{a}.output" for a, bb in edges if bb == b})
        lines.append(f"[stages.s{b}]\nverb = \"checksum\"\ninputs = {{ files = {srcs + ['data']!r} }}\n"
                     .replace("'", '"'))
    text = "\n".join(lines)
    # independent acyclicity check: repeatedly strip nodes without incoming edges
    remaining, es = set(range(n)), set(edges)
    while True:
        free = {v for v in remaining if not any(b == v and a in remaining for a, b in es)}
        if not free:
            break
        remaining -= free
    if not remaining:
        order = parse_recipe_text(text, Path("g.toml")).order()
        pos = {f"s{i}": k for k, i in enumerate(int(s[1:]) for s in order)}
        assert sorted(pos) == sorted(f"s{i}" for i in range(n))
        assert all(pos[f"s{a}"] < pos[f"s{b}"] for a, b in edges)
    else:
        with pytest.raises(ReflectmmError, match="cycle") as ei:
            parse_recipe_text(text, Path("g.toml"))
        nodes = str(ei.value).split("cycle: ", 1)[1].split(" -> ")
        assert nodes[0] == nodes[-1]
        hops = list(zip(nodes, nodes[1:]))
        assert all((int(x[1:]), int(y[1:])) in edges for x, y in hops)  # every hop is a real edge


def test_a_defaults_param_no_stage_declares_is_refused(tmp_path):
    # a typo in [defaults] was dropped silently, while the same name in a stage's params is refused
    from reflectmm_cli.recipes import plan_recipe

    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[defaults]\nsolverr = "adam"\n'
                                     '[stages.fit-reflectance]\nforeach = ["001"]\n'
                                     'inputs = { observations = "o/001.npz" }\n')
    with pytest.raises(ReflectmmError, match=r"r.toml: \[defaults\]: solverr is not a param of any verb"):
        plan_recipe(tmp_path / "r.toml", tmp_path)


def test_a_dry_run_that_plans_an_error_exits_1(tmp_path, cli):
    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.fit-reflectance]\nforeach = ["001"]\n'
                                     'inputs = { observations = "o/001.npz" }\n')
    r = cli("run", tmp_path / "r.toml", "-w", tmp_path, "--dry-run")
    assert r.exit_code == 1 and "1 task(s) would fail as planned" in r.stderr and "fit-reflectance/001" in r.stderr

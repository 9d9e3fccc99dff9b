"""Recipe runs that must not fail or pass silently: forced runs with discovered identities, empty foreach."""

from __future__ import annotations

import pytest

from recipe_testdata import DISCOVER_STAGES

from reflectmm_cli.recipes import run_recipe

DISCOVER = 'schema = "reflectmm.recipe/1"\n' + DISCOVER_STAGES + """
[stages.summary]
verb = "checksum"
inputs = { files = "@found.output" }
"""


def statuses(report):
    return {t.tid: t.status for t in report.tasks}


@pytest.mark.parametrize("force", ["*", "manifest"])
def test_force_replans_deferred_all_found_stages(ws, force):
    (ws / "recipe.toml").write_text(DISCOVER)
    assert run_recipe(ws / "recipe.toml", ws).ok
    rep = run_recipe(ws / "recipe.toml", ws, force=force)
    assert rep.ok, [(t.tid, t.status, t.error) for t in rep.tasks]
    st = statuses(rep)
    assert st["manifest/002"] == st["manifest/004"] == "ok"
    assert set(st) == {"manifest/002", "manifest/004", "found/002", "found/004", "summary"}
    if force == "*":
        assert st["found/002"] == st["found/004"] == st["summary"] == "ok"
    else:  # the forced manifests are byte-identical: downstream is up to date
        assert st["found/002"] == st["found/004"] == st["summary"] == "skipped"


def test_force_through_cli_exits_zero(cli, ws):
    (ws / "recipe.toml").write_text(DISCOVER)
    assert cli("run", ws / "recipe.toml", "-w", ws).exit_code == 0
    r = cli("run", ws / "recipe.toml", "-w", ws, "--force")
    assert r.exit_code == 0, r.stderr
    assert len(r.stdout.splitlines()) == 5


EMPTY = """
schema = "reflectmm.recipe/1"
[stages.found]
verb = "checksum"
foreach = "all found"
params = { discover = "nothing-here/*" }
inputs = { files = "data/{id}" }
"""


def test_foreach_matching_nothing_fails_unless_allowed(cli, ws):
    (ws / "recipe.toml").write_text(EMPTY)
    r = cli("run", ws / "recipe.toml", "-w", ws)
    assert r.exit_code == 1
    assert "stage found: foreach matched no identity" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("reflectmm: error: recipe: stage found: foreach matched no "
                                                        "identity, so nothing ran")
    r = cli("run", ws / "recipe.toml", "-w", ws, "--allow-empty")
    assert r.exit_code == 0 and "foreach matched no identity" in r.stderr  # still warned
    (ws / "ids.txt").write_text("# nobody yet\n")
    (ws / "recipe.toml").write_text(EMPTY.replace('"all found"', '{ file = "ids.txt" }'))
    assert cli("run", ws / "recipe.toml", "-w", ws).exit_code == 1
    assert cli("run", ws / "recipe.toml", "-w", ws, "-n").exit_code == 0  # a dry run only warns

"""``reflectmm run`` through the CLI: dry-run text, JSON, exit codes, failures on stderr."""

from __future__ import annotations

import json

import pytest
from recipe_testdata import IDS


def test_dry_run_table(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--dry-run")
    assert r.exit_code == 0
    lines = r.stdout.splitlines()
    assert lines[0] == "recipe basic: 5 task(s): 5 run"
    assert lines[1].split() == ["stage", "id", "action", "reason"]
    rows = [ln.split(None, 3) for ln in lines[2:]]
    assert rows == [["manifest", i, "run", "no output"] for i in IDS] + \
        [["summary", "-", "run", "upstream reruns (manifest/001 +3)"]]
    assert not (ws / "manifest").exists()


def test_run_prints_written_paths_then_noop(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws)
    assert r.exit_code == 0
    assert r.stdout.splitlines() == [str(ws / "manifest" / f"{i}.npz") for i in IDS] + \
        [str(ws / "summary" / "summary.npz")]
    r = cli("run", ws / "recipe.toml", "-w", ws)
    assert r.exit_code == 0 and r.stdout == ""
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n")
    assert "5 skip" in r.stdout.splitlines()[0]


def test_force_option_forms(cli, ws):
    cli("run", ws / "recipe.toml", "-w", ws)
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--force")
    assert [ln.split(None, 3)[3] for ln in r.stdout.splitlines()[2:]] == ["forced"] * 5
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--force=summary")
    rows = {tuple(ln.split(None, 3)[:2]): ln.split(None, 3)[3] for ln in r.stdout.splitlines()[2:]}
    assert rows[("summary", "-")] == "forced" and rows[("manifest", "001")] == "up to date"
    r = cli("run", "-w", ws, "-n", "--force", "summary", ws / "recipe.toml")
    assert r.exit_code == 0 and "forced" in r.stdout


def test_only_and_ids(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--ids", "002-003", "--json")
    doc = json.loads(r.stdout)
    assert r.exit_code == 0
    assert [(t["stage"], t["id"], t["status"]) for t in doc["tasks"]] == [("manifest", "002", "ok"),
                                                                         ("manifest", "003", "ok")]
    r = cli("run", ws / "recipe.toml", "-w", ws, "--only", "summary")
    assert r.exit_code == 1
    assert "summary" in r.stderr and "not selected by --only" in r.stderr


def test_ids_that_no_stage_has_are_refused_and_a_partly_unknown_list_warned(cli, ws, reflectmm_log):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--ids", "777", "--dry-run")
    assert r.exit_code == 1 and "--ids: no stage has identity 777" in r.stderr and "001" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = cli("run", ws / "recipe.toml", "-w", ws, "--ids", "002,777", "--dry-run")
    assert r.exit_code == 0 and any("no stage has identity 777" in m for m in reflectmm_log)


def test_failure_lines_and_exit_status(cli, ws):
    (ws / "data" / "004" / "a.txt").write_text("BAD")
    r = cli("run", ws / "recipe.toml", "-w", ws)
    assert r.exit_code == 1
    assert r.stdout.splitlines() == [str(ws / "manifest" / f"{i}.npz") for i in ("001", "002", "003")]
    err = r.stderr.strip().splitlines()
    assert any(ln.startswith("reflectmm: failed: manifest/004: ") and "a.txt" in ln for ln in err)
    assert any(ln.startswith("reflectmm: blocked: summary: upstream manifest/004 failed") for ln in err)
    assert err[-1].startswith("reflectmm: error: 1 task(s) failed, 1 blocked")
    (ws / "data" / "004" / "a.txt").write_text("ok")
    r = cli("run", ws / "recipe.toml", "-w", ws, "--json")
    assert r.exit_code == 0
    doc = json.loads(r.stdout)
    assert doc["counts"] == {"ok": 2, "skipped": 3}


def test_bad_recipe_exit_1_one_line(cli, ws):
    (ws / "bad.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.a]\nverb = "checksum"\n'
                                 'inputs = { files = "@a.output" }\n')
    r = cli("run", ws / "bad.toml", "-w", ws)
    assert r.exit_code == 1 and r.stdout == ""
    assert r.stderr.strip().count("\n") == 0 and "cycle: a -> a" in r.stderr
    r = cli("run", ws / "nope.toml", "-w", ws)
    assert r.exit_code == 1 and "recipe not found" in r.stderr


def test_scheduler_needs_dask(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--executor", "pool", "--scheduler", "tcp://127.0.0.1:1")
    assert r.exit_code == 1 and "--scheduler needs --executor dask" in r.stderr


def test_dry_run_checks_the_scheduler_as_the_run_does(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--executor", "serial", "--scheduler", "tcp://127.0.0.1:1")
    assert r.exit_code == 1 and "--scheduler needs --executor dask" in r.stderr and r.stdout == ""
    for bad in ("notaurl", "tcp://127.0.0.1", "foo://h:1"):
        r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--scheduler", bad)
        assert r.exit_code == 1 and r.stdout == "", bad
        line = r.stderr.strip()
        assert "\n" not in line and f"--scheduler {bad}: not a scheduler address such as tcp://HOST:8786" in line
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--scheduler", "tcp://127.0.0.1:1")
    assert r.exit_code == 0  # a well-formed address: whether a scheduler answers there is known on connect


def test_force_outside_only_is_a_warning(cli, ws, reflectmm_log):
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--only", "manifest", "--force=summary")
    assert r.exit_code == 0
    assert [m for m in reflectmm_log if "--force" in m] == [
        "--force=summary: stage summary is not selected by --only manifest, so it is not forced (nothing of it runs)"]
    reflectmm_log.clear()
    r = cli("run", ws / "recipe.toml", "-w", ws, "-n", "--only", "manifest", "--force=manifest")
    assert r.exit_code == 0 and not [m for m in reflectmm_log if "--force" in m]


def test_force_before_the_recipe_still_means_force_all(cli, ws):
    r = cli("run", "-w", ws, "-n", "--force", ws / "recipe.toml")
    assert r.exit_code == 0 and [ln.split(None, 3)[3] for ln in r.stdout.splitlines()[2:]] == ["forced"] * 5
    r = cli("run", "-w", ws)
    assert r.exit_code == 2 and "Missing argument 'RECIPE'" in r.stderr


def test_artifact_made_by_hand_is_recognised_by_the_recipe(cli, ws):
    r = cli("checksum", ws / "data" / "002", "--id", "002", "-w", ws)
    assert r.exit_code == 0
    (ws / "hand.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.checksum]\nforeach = ["001", "002"]\n'
                                  'inputs = { files = "data/{id}" }\n')
    r = cli("run", ws / "hand.toml", "-w", ws, "-n")
    rows = {ln.split(None, 3)[1]: ln.split(None, 3)[3] for ln in r.stdout.splitlines()[2:]}
    assert rows == {"001": "no output", "002": "up to date"}


@pytest.mark.parametrize("discovers", [True, False], ids=["verb-may-discover", "verb-takes-upstream-ids"])
def test_ids_leaving_a_stage_without_tasks_is_not_an_empty_foreach(cli, ws, reflectmm_log, monkeypatch, discovers):
    # `held-again` takes its identities from `held` (003, 004); --ids 001 leaves both without tasks, which is
    # what was asked, not "foreach matched no identity". A verb without discover_ids (fit-geometry, unwrap-uv)
    # goes straight to the upstream's ids; checksum first resolves its inputs to try its own discovery
    if not discovers:
        import dataclasses

        from reflectmm_cli.recipes import plan

        real = plan.get_stage
        monkeypatch.setattr(plan, "get_stage", lambda verb: dataclasses.replace(real(verb), discover_ids=None))
    (ws / "recipe.toml").write_text("""
schema = "reflectmm.recipe/1"
[stages.manifest]
verb = "checksum"
foreach = ["001", "002"]
inputs = { files = "data/{id}" }

[stages.held]
verb = "checksum"
foreach = ["003", "004"]
inputs = { files = "data/{id}" }

[stages.held-again]
verb = "checksum"
foreach = "all found"
inputs = { files = "@held.output" }
""")
    for extra in (("--dry-run",), ()):
        r = cli("run", ws / "recipe.toml", "-w", ws, "--only", "manifest", "--ids", "001", *extra)
        assert r.exit_code == 0, r.stderr
        assert "foreach matched no identity" not in r.stderr
        assert not any("foreach matched no identity" in m for m in reflectmm_log)
    r = cli("run", ws / "recipe.toml", "-w", ws, "--ids", "003", "--json")
    assert r.exit_code == 0, r.stderr
    assert [(t["stage"], t["id"]) for t in json.loads(r.stdout)["tasks"]] == [("held", "003"), ("held-again", "003")]

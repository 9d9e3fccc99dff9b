"""Planner and runner with the built-in checksum verb on real files: run, skip, rerun and why."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.recipes import plan_recipe, run_recipe

from recipe_testdata import DISCOVER_STAGES, IDS, sha


def statuses(report):
    return {t.tid: t.status for t in report.tasks}


def reasons(report):
    return {t.tid: t.reason for t in report.tasks}


def test_first_run_then_noop(ws):
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok
    assert statuses(rep) == {**{f"manifest/{i}": "ok" for i in IDS}, "summary": "ok"}
    # the artifacts hold the right hashes (independent hashlib computation)
    for i in IDS:
        art = read_artifact(ws / "manifest" / f"{i}.npz", "checksum")
        assert list(art["names"]) == ["a.txt", "b.txt"]
        assert list(art["sha256"]) == [sha(ws / "data" / i / "a.txt"), sha(ws / "data" / i / "b.txt")]
        assert art.meta["cache_key"] == rep.tasks[IDS.index(i)].cache_key
    summ = read_artifact(ws / "summary" / "summary.npz", "checksum")
    assert list(summ["sha256"]) == [sha(ws / "manifest" / f"{i}.npz") for i in IDS]

    mtimes = {p: p.stat().st_mtime_ns for p in (ws / "manifest").iterdir()}
    rep2 = run_recipe(ws / "recipe.toml", ws)
    assert rep2.ok and set(statuses(rep2).values()) == {"skipped"}
    assert set(reasons(rep2).values()) == {"up to date"}
    assert {p: p.stat().st_mtime_ns for p in (ws / "manifest").iterdir()} == mtimes  # nothing rewritten


def test_changed_input_reruns_that_identity_and_downstream_only(ws):
    run_recipe(ws / "recipe.toml", ws)
    (ws / "data" / "002" / "a.txt").write_text("changed\n")
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert statuses(plan) == {"manifest/001": "skip", "manifest/002": "run", "manifest/003": "skip",
                              "manifest/004": "skip", "summary": "run"}
    assert reasons(plan)["manifest/002"] == "input changed (files)"
    assert reasons(plan)["summary"] == "upstream reruns (manifest/002)"
    rep = run_recipe(ws / "recipe.toml", ws)
    assert statuses(rep)["manifest/002"] == "ok" and statuses(rep)["summary"] == "ok"
    assert statuses(rep)["manifest/001"] == "skipped"
    art = read_artifact(ws / "manifest" / "002.npz")
    assert art["sha256"][0] == sha(ws / "data" / "002" / "a.txt")


def test_same_content_rewritten_does_not_rerun(ws):
    run_recipe(ws / "recipe.toml", ws)
    f = ws / "data" / "003" / "b.txt"
    f.write_bytes(f.read_bytes())  # new mtime, same content: the memo rehashes and finds the same digest
    os.utime(f, ns=(1, 1))
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_added_file_in_input_folder_reruns(ws):
    run_recipe(ws / "recipe.toml", ws)
    (ws / "data" / "004" / "c.txt").write_text("new")
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert statuses(plan)["manifest/004"] == "run" and reasons(plan)["manifest/004"] == "input changed (files)"


def test_params_change_and_defaults_merge(ws):
    run_recipe(ws / "recipe.toml", ws)
    text = (ws / "recipe.toml").read_text()
    # a stage param overrides the default only for that stage
    (ws / "recipe.toml").write_text(text.replace('inputs = { files = "@manifest.output" }',
                                                 'inputs = { files = "@manifest.output" }\n'
                                                 'params = { fail_if_contains = "OTHER" }'))
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert statuses(plan)["summary"] == "run" and reasons(plan)["summary"] == "params changed (fail_if_contains)"
    assert all(statuses(plan)[f"manifest/{i}"] == "skip" for i in IDS)
    run_recipe(ws / "recipe.toml", ws)
    assert read_artifact(ws / "summary" / "summary.npz").params == {"fail_if_contains": "OTHER"}
    # an execution-only param (NON_INVALIDATING) never invalidates
    (ws / "recipe.toml").write_text((ws / "recipe.toml").read_text().replace(
        'fail_if_contains = "BAD"', 'fail_if_contains = "BAD"\nprogress = false\njobs = 3'))
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_missing_corrupt_or_foreign_output_reruns(ws):
    run_recipe(ws / "recipe.toml", ws)
    (ws / "manifest" / "001.npz").unlink()
    p2 = ws / "manifest" / "002.npz"
    p2.write_bytes(p2.read_bytes()[:100])
    write_artifact(ws / "manifest" / "003.npz", "checksum", {"x": np.zeros(1)}, cache_key="0" * 64)
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    r = reasons(plan)
    assert r["manifest/001"] == "no output"
    assert r["manifest/002"].startswith("output invalid (truncated or corrupt NPZ")
    assert statuses(plan)["manifest/003"] == "run" and r["manifest/003"] == "cache key changed"
    assert r["manifest/004"] == "up to date"
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_stage_version_change_reruns(ws, monkeypatch):
    from dataclasses import replace

    from reflectmm_cli.stages import registry as stages

    run_recipe(ws / "recipe.toml", ws)
    st = stages.get_stage("checksum")
    monkeypatch.setitem(stages._REGISTRY, "checksum", replace(st, version=st.version + 1))
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert reasons(plan)["manifest/001"] == f"stage version changed ({st.version} -> {st.version + 1})"


def test_force_all_and_force_stage(ws):
    run_recipe(ws / "recipe.toml", ws)
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True, force="*")
    assert set(reasons(plan).values()) == {"forced"}
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True, force="summary")
    assert reasons(plan)["summary"] == "forced" and reasons(plan)["manifest/001"] == "up to date"
    before = (ws / "summary" / "summary.npz").stat().st_mtime_ns
    rep = run_recipe(ws / "recipe.toml", ws, force="summary")
    assert statuses(rep)["summary"] == "ok"
    assert (ws / "summary" / "summary.npz").stat().st_mtime_ns != before


def test_only_uses_existing_upstream_outputs_or_fails(ws):
    rep = run_recipe(ws / "recipe.toml", ws, only="summary")
    assert not rep.ok and statuses(rep) == {"summary": "failed"}
    assert "needs manifest/001" in rep.tasks[0].error and "is missing" in rep.tasks[0].error
    assert not (ws / "manifest").exists()  # nothing upstream was run
    run_recipe(ws / "recipe.toml", ws, only="manifest")
    assert not (ws / "summary" / "summary.npz").exists()
    (ws / "data" / "001" / "a.txt").write_text("changed")  # stale upstream is not rerun with --only
    rep = run_recipe(ws / "recipe.toml", ws, only="summary")
    assert rep.ok and statuses(rep) == {"summary": "ok"}


def test_ids_restrict_foreach_and_leave_aggregates_alone(ws):
    rep = run_recipe(ws / "recipe.toml", ws, ids=["002", "004", "999"])
    assert statuses(rep) == {"manifest/002": "ok", "manifest/004": "ok"}
    assert not (ws / "manifest" / "001.npz").exists() and not (ws / "summary").exists()


def test_dry_run_writes_no_artifact(ws):
    run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert not (ws / "manifest").exists() and not (ws / "summary").exists()


def test_failing_identity_keeps_others_and_resumes(ws):
    (ws / "data" / "003" / "b.txt").write_text("has a BAD marker")
    rep = run_recipe(ws / "recipe.toml", ws)
    assert not rep.ok
    st = statuses(rep)
    assert st == {"manifest/001": "ok", "manifest/002": "ok", "manifest/003": "failed", "manifest/004": "ok",
                  "summary": "blocked"}
    failed = next(t for t in rep.tasks if t.status == "failed")
    assert "b.txt" in failed.error and "BAD" in failed.error
    assert "manifest/003" in next(t for t in rep.tasks if t.status == "blocked").error
    assert not (ws / "manifest" / "003.npz").exists()
    for i in ("001", "002", "004"):
        assert read_artifact(ws / "manifest" / f"{i}.npz").kind == "checksum"
    # runlog has one line per task with the failure
    lines = [json.loads(x) for x in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    assert len(lines) == 5
    assert {(x["stage"], x["id"], x["status"]) for x in lines} == {
        ("manifest", "001", "ok"), ("manifest", "002", "ok"), ("manifest", "003", "failed"),
        ("manifest", "004", "ok"), ("summary", None, "blocked")}
    for x in lines:
        assert set(x) >= {"stage", "id", "cache_key", "status", "duration", "error", "time", "run"}
        if x["status"] == "ok":
            assert len(x["cache_key"]) == 64 and x["error"] is None and x["duration"] >= 0
    # fix the input: only the failed identity and the aggregate run
    (ws / "data" / "003" / "b.txt").write_text("fine now")
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok
    assert statuses(rep) == {"manifest/001": "skipped", "manifest/002": "skipped", "manifest/003": "ok",
                             "manifest/004": "skipped", "summary": "ok"}


def test_missing_input_for_one_identity_fails_only_that_task(ws):
    import shutil

    shutil.rmtree(ws / "data" / "002")
    rep = run_recipe(ws / "recipe.toml", ws)
    st = statuses(rep)
    assert st["manifest/002"] == "failed" and st["summary"] == "blocked"
    assert all(st[f"manifest/{i}"] == "ok" for i in ("001", "003", "004"))
    assert "input 'files' not found" in next(t.error for t in rep.tasks if t.tid == "manifest/002")


def test_foreach_file_all_found_dir_and_named_outputs(ws):
    (ws / "ids.txt").write_text("# the subset\n001\n003  # trailing comment\n")
    (ws / "recipe.toml").write_text("""
schema = "reflectmm.recipe/1"
[stages.manifest]
verb = "checksum"
foreach = { file = "ids.txt" }
inputs = { files = "data/{id}" }

[stages.again]
verb = "checksum"
foreach = "all found"                     # the upstream foreach's ids
inputs = { files = ["@manifest.output", "data/{id}/a.txt"] }

[stages.folder]
verb = "checksum"
inputs = { files = "@manifest.dir" }      # the whole output folder

[stages.named]
verb = "checksum"
inputs = { files = "@folder.outputs.folder" }
""")
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)  # ids known before anything ran
    assert statuses(plan)["again/003"] == "run" and reasons(plan)["again/003"] == "upstream reruns (manifest/003)"
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok, [t.error for t in rep.tasks]
    assert set(statuses(rep)) == {"manifest/001", "manifest/003", "again/001", "again/003", "folder", "named"}
    again = read_artifact(ws / "again" / "003.npz")
    assert list(again["sha256"]) == [sha(ws / "manifest" / "003.npz"), sha(ws / "data" / "003" / "a.txt")]
    folder = read_artifact(ws / "folder" / "folder.npz")
    assert list(folder["names"]) == ["001.npz", "003.npz"]
    named = read_artifact(ws / "named" / "named.npz")
    assert list(named["sha256"]) == [sha(ws / "folder" / "folder.npz")]


def test_all_found_by_discovery_waits_for_upstream(ws):
    (ws / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n' + DISCOVER_STAGES)
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert statuses(plan)["found"] == "deferred"
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok and statuses(rep) == {"manifest/002": "ok", "manifest/004": "ok", "found/002": "ok",
                                        "found/004": "ok"}
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_only_leaves_a_deferred_stage_it_does_not_select_out_of_the_run(ws):
    # --only other on a fresh workspace: "found" waits for manifest's outputs, and neither is selected, so "found"
    # neither waits nor counts as blocked (it did: the run failed with "0 task(s) failed, 1 blocked"); --only found
    # before manifest has run is blocked, as its upstream outputs must exist
    (ws / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n' + DISCOVER_STAGES
                                    + '[stages.other]\nverb = "checksum"\ninputs = { files = "data/001" }\n')
    rep = run_recipe(ws / "recipe.toml", ws, only="other")
    assert rep.ok and statuses(rep) == {"other": "ok"}
    rep = run_recipe(ws / "recipe.toml", ws, only="found")
    assert not rep.ok and statuses(rep) == {"found": "blocked"}
    rep = run_recipe(ws / "recipe.toml", ws, only="manifest")
    assert rep.ok and statuses(rep) == {"manifest/002": "ok", "manifest/004": "ok"}
    rep = run_recipe(ws / "recipe.toml", ws, only="found")
    assert rep.ok and statuses(rep) == {"found/002": "ok", "found/004": "ok"}


def test_id_placeholder_in_aggregate_stage_is_a_task_error(ws):
    (ws / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.s]\nverb = "checksum"\n'
                                    'inputs = { files = "data/{id}" }\n')
    rep = run_recipe(ws / "recipe.toml", ws)
    assert statuses(rep) == {"s": "failed"} and "{id}" in rep.tasks[0].error


def test_hash_memo_avoids_rehashing(ws, monkeypatch):
    run_recipe(ws / "recipe.toml", ws)
    memo = json.loads((ws / ".reflectmm" / "hashes.json").read_text())
    assert str((ws / "data" / "001" / "a.txt").resolve()) in memo
    import reflectmm_cli.stages.base as stages

    calls = []
    real = stages.sha256_file
    monkeypatch.setattr(stages, "sha256_file", lambda p, *a, **k: calls.append(p) or real(p, *a, **k))
    plan = plan_recipe(ws / "recipe.toml", ws)
    assert {t.action for t in plan.tasks.values()} == {"skip"}
    assert calls == []  # a no-op plan reads no file content


def test_workspace_move_keeps_cache(ws, tmp_path):
    import shutil

    run_recipe(ws / "recipe.toml", ws)
    moved = tmp_path / "moved"
    shutil.copytree(ws, moved)
    plan = run_recipe(moved / "recipe.toml", moved, dry_run=True)
    assert set(statuses(plan).values()) == {"skip"}


@pytest.mark.parametrize("bad", ["manifest", "summary"])
def test_deleting_state_dir_is_safe(ws, bad):
    import shutil

    run_recipe(ws / "recipe.toml", ws)
    shutil.rmtree(ws / ".reflectmm")  # artifacts carry their key: still up to date
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_param_reference_resolves_to_path_and_orders_stages(ws):
    (ws / "recipe.toml").write_text("""
schema = "reflectmm.recipe/1"
[stages.b]
verb = "checksum"
inputs = { files = "data/001" }
params = { model = "@a.output" }     # a param naming another stage's output: a dependency too

[stages.a]
verb = "checksum"
inputs = { files = "data/002" }
""")
    rep = run_recipe(ws / "recipe.toml", ws)
    assert rep.ok and [t.tid for t in rep.tasks] == ["a", "b"]
    assert read_artifact(ws / "b" / "b.npz").params["model"] == str(ws / "a" / "a.npz")
    (ws / "data" / "002" / "a.txt").write_text("changed")
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert reasons(plan) == {"a": "input changed (files)", "b": "upstream reruns (a)"}


def test_runlog_logs_skipped_tasks_and_groups_by_run(ws):
    run_recipe(ws / "recipe.toml", ws)
    run_recipe(ws / "recipe.toml", ws)
    lines = [json.loads(x) for x in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    runs = sorted({x["run"] for x in lines}, key=[x["run"] for x in lines].index)
    assert len(runs) == 2
    second = [x for x in lines if x["run"] == runs[1]]
    assert [x["status"] for x in second] == ["skipped"] * 5
    assert all(x["reason"] == "up to date" and x["duration"] == 0 for x in second)
    first_keys = {(x["stage"], x["id"]): x["cache_key"] for x in lines if x["run"] == runs[0]}
    assert {(x["stage"], x["id"]): x["cache_key"] for x in second} == first_keys


def test_dry_run_json(cli, ws):
    r = cli("run", ws / "recipe.toml", "-w", ws, "--dry-run", "--json")
    doc = json.loads(r.stdout)
    assert doc["dry_run"] is True and doc["counts"] == {"run": 5}
    assert doc["tasks"][0]["outputs"] == [str(ws / "manifest" / "001.npz")]


def test_force_on_a_fresh_workspace_and_keys_follow_new_inputs(ws):
    rep = run_recipe(ws / "recipe.toml", ws, force="*")  # nothing exists yet: keys are computed at run time
    assert rep.ok and {t.status for t in rep.tasks} == {"ok"}
    (ws / "data" / "001" / "a.txt").write_text("changed")
    rep = run_recipe(ws / "recipe.toml", ws, force="*")
    assert rep.ok
    # the stored keys are those of the new inputs: a plain rerun has nothing to do
    assert set(statuses(run_recipe(ws / "recipe.toml", ws, dry_run=True)).values()) == {"skip"}


def test_second_concurrent_run_in_a_workspace_is_refused(ws):
    import subprocess
    import sys
    import time as _time

    from reflectmm_cli.errors import ReflectmmError

    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from reflectmm_cli.recipes.runner import workspace_lock\n"
        "with workspace_lock(sys.argv[1]):\n"
        "    print('locked', flush=True)\n"
        "    time.sleep(60)\n"), str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(ReflectmmError, match=rf"another reflectmm run is using this workspace \(pid {holder.pid}\)"):
            run_recipe(ws / "recipe.toml", ws)
        assert not (ws / "manifest").exists()
        assert run_recipe(ws / "recipe.toml", ws, dry_run=True).tasks  # planning alone is allowed
    finally:
        holder.kill()
        holder.wait()
    _time.sleep(0.05)
    assert run_recipe(ws / "recipe.toml", ws).ok  # the lock dies with its holder


def test_noop_rerun_of_100_identities_plans_fast_and_runs_nothing(tmp_path):
    import time as _time

    w = tmp_path / "big"
    ids = [f"{i:03d}" for i in range(1, 101)]
    for i in ids:
        (w / "data" / i).mkdir(parents=True)
        (w / "data" / i / "x.bin").write_bytes(i.encode() * 100)
    (w / "ids.txt").write_text("\n".join(ids))
    (w / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.m]\nverb = "checksum"\n'
                              'foreach = { file = "ids.txt" }\ninputs = { files = "data/{id}" }\n'
                              '[stages.all]\nverb = "checksum"\ninputs = { files = "@m.output" }\n')
    assert run_recipe(w / "r.toml", w).ok
    t0 = _time.perf_counter()
    rep = run_recipe(w / "r.toml", w)
    elapsed = _time.perf_counter() - t0
    assert rep.counts() == {"skipped": 101}
    assert elapsed < 2.0, f"no-op rerun took {elapsed:.2f} s"


def test_hidden_folders_in_inputs_are_ignored(ws):
    (ws / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.all]\nverb = "checksum"\n'
                                    'inputs = { files = "data" }\n')
    hidden = ws / "data" / ".state"  # like .reflectmm/ or .git/: changes without being data
    hidden.mkdir()
    (hidden / "x").write_text("not hashed")
    assert run_recipe(ws / "recipe.toml", ws).ok
    names = list(read_artifact(ws / "all" / "all.npz")["names"])
    assert "x" not in names and len(names) == 8
    (hidden / "x").write_text("changed, still not an input")
    assert set(statuses(run_recipe(ws / "recipe.toml", ws)).values()) == {"skipped"}


@pytest.fixture
def named_output_stages():
    """Registers, for one test, ``tally`` (aggregate: one summary file and a named side output ``extra.txt``) and
    ``use-extra`` (per identity, reading ``@tally.outputs.extra``): the shape of calibrate-rig's ``rig`` feeding
    the held-out fits."""
    from reflectmm_cli.stages.registry import _REGISTRY, register_stage

    def tally_outputs(ctx):
        return [ctx.output_path(), ctx.output_path().parent / "extra.txt"]

    @register_stage("tally", outputs=tally_outputs, open_params=True)
    def _tally(ctx):
        outs = tally_outputs(ctx)
        outs[0].parent.mkdir(parents=True, exist_ok=True)
        write_artifact(outs[0], "checksum", {"n": np.int64(len(ctx.inputs["files"]))}, params={})
        outs[1].write_text("extra\n")
        return outs

    @register_stage("use-extra", per_identity=True, open_params=True)
    def _use_extra(ctx):
        out = ctx.output_path()
        out.parent.mkdir(parents=True, exist_ok=True)
        write_artifact(out, "checksum", {"text": np.array(ctx.inputs["extra"][0].read_text())}, params={})
        return [out]

    yield
    for verb in ("tally", "use-extra"):  # other tests enumerate the registry
        _REGISTRY.pop(verb, None)


def test_ids_outside_an_aggregate_still_resolve_its_named_outputs(ws, named_output_stages):
    """``--ids 005`` leaves out the aggregate (built from 001–004), yet its named output stays resolvable for
    the stage downstream of it (before: "stage 'tally' has no output named 'extra'")."""
    (ws / "recipe.toml").write_text(
        (ws / "recipe.toml").read_text()
        + '\n[stages.tally]\nverb = "tally"\ninputs = { files = "@manifest.output" }\n'
        + '\n[stages.late]\nverb = "use-extra"\nforeach = ["005"]\ninputs = { extra = "@tally.outputs.extra" }\n')
    assert run_recipe(ws / "recipe.toml", ws).ok
    plan = run_recipe(ws / "recipe.toml", ws, ids=["005"], force="late", dry_run=True)
    assert statuses(plan) == {"late/005": "run"}, reasons(plan)
    rep = run_recipe(ws / "recipe.toml", ws, ids=["005"], force="late")
    assert rep.ok and statuses(rep) == {"late/005": "ok"}
    assert str(read_artifact(ws / "late" / "005.npz")["text"]) == "extra\n"

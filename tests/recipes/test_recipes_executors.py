"""Process pool and Dask executors give the same, byte-identical artifacts as the serial one."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from recipe_testdata import DISCOVER_STAGES, IDS, make_workspace

from reflectmm_cli.recipes import run_recipe


def _artifacts(ws):
    return {str(p.relative_to(ws)): p.read_bytes() for d in ("manifest", "summary") for p in sorted((ws / d).iterdir())}


@pytest.fixture
def serial_reference(tmp_path):
    ref = make_workspace(tmp_path / "serial")
    rep = run_recipe(ref / "recipe.toml", ref, executor="serial")
    assert rep.ok
    return _artifacts(ref)


def _workers(ws):
    lines = [json.loads(x) for x in (ws / ".reflectmm" / "runlog.jsonl").read_text().splitlines()]
    return {x["worker"] for x in lines if x["status"] == "ok"}


def test_pool_matches_serial_bytes(tmp_path, serial_reference):
    ws = make_workspace(tmp_path / "pool")
    rep = run_recipe(ws / "recipe.toml", ws, executor="pool", jobs=2)
    assert rep.ok
    assert _artifacts(ws) == serial_reference
    workers = _workers(ws)
    assert all(not w.endswith(f":{os.getpid()}") for w in workers)  # ran in other processes


def test_pool_failure_isolation_and_resume(tmp_path):
    ws = make_workspace(tmp_path / "pool")
    (ws / "data" / "001" / "a.txt").write_text("BAD")
    rep = run_recipe(ws / "recipe.toml", ws, executor="pool", jobs=2)
    st = {t.tid: t.status for t in rep.tasks}
    assert st == {"manifest/001": "failed", "manifest/002": "ok", "manifest/003": "ok", "manifest/004": "ok",
                  "summary": "blocked"}
    (ws / "data" / "001" / "a.txt").write_text("fine")
    rep = run_recipe(ws / "recipe.toml", ws, executor="pool", jobs=2)
    assert rep.ok and sum(t.status == "ok" for t in rep.tasks) == 2


def test_dask_localcluster_matches_serial_bytes(tmp_path, serial_reference):
    from distributed import LocalCluster

    ws = make_workspace(tmp_path / "dask")
    (ws / "data" / "003" / "b.txt").write_text("BAD")  # one failing identity travels back as a message
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        rep = run_recipe(ws / "recipe.toml", ws, executor="dask", scheduler=cluster.scheduler_address)
        st = {t.tid: t.status for t in rep.tasks}
        assert st["manifest/003"] == "failed" and st["summary"] == "blocked"
        assert "BAD" in next(t.error for t in rep.tasks if t.tid == "manifest/003")
        (ws / "data" / "003" / "b.txt").write_text((tmp_path / "serial" / "data" / "003" / "b.txt").read_text())
        rep = run_recipe(ws / "recipe.toml", ws, executor="dask", scheduler=cluster.scheduler_address)
        assert rep.ok
        assert {t.tid for t in rep.tasks if t.status == "ok"} == {"manifest/003", "summary"}
    assert _artifacts(ws) == serial_reference
    workers = _workers(ws)
    assert all(not w.endswith(f":{os.getpid()}") for w in workers)


def test_dask_without_scheduler_starts_a_localcluster(tmp_path, serial_reference):
    from reflectmm_cli.recipes import DaskExecutor

    ws = make_workspace(tmp_path / "dask2")
    with DaskExecutor(jobs=2) as ex:  # one LocalCluster of 2 worker processes, reused by two runs
        rep = run_recipe(ws / "recipe.toml", ws, executor=ex)
        assert rep.ok and len(rep.tasks) == len(IDS) + 1
        assert _artifacts(ws) == serial_reference
        cluster = ex._cluster
        assert cluster is not None and len(cluster.workers) == 2
        assert len(_workers(ws)) >= 1 and all(not w.endswith(f":{os.getpid()}") for w in _workers(ws))
        shutil.rmtree(ws / "manifest")
        rep = run_recipe(ws / "recipe.toml", ws, executor=ex)
        assert rep.ok and {t.status for t in rep.tasks} == {"ok"} and _artifacts(ws) == serial_reference
    assert ex._cluster is None


def test_pool_survives_a_killed_worker(tmp_path):
    """A worker killed mid-task fails that task with a message; the executor carries on with a new pool."""
    import signal
    import threading

    from reflectmm_cli.recipes import PoolExecutor, TaskSpec
    from reflectmm_cli.stages import get_stage

    stage = get_stage("checksum")
    fifo = tmp_path / "blocks.fifo"
    os.mkfifo(fifo)  # opening it for reading blocks until someone writes: the task hangs in the worker
    ok_file = tmp_path / "ok.txt"
    ok_file.write_text("fine")

    def spec(name, path):
        ctx = stage.context(workspace=tmp_path, stage_name=name, inputs={"files": [path]})
        return TaskSpec(name, "checksum", ctx)

    results = {}
    with PoolExecutor(jobs=2) as ex:
        def on_result(res):
            results[res["tid"]] = res
            if res["tid"] == "quick":  # the hanging task is still running: kill every worker of the pool
                def kill():
                    for pid in list(ex._pool._processes):
                        os.kill(pid, signal.SIGKILL)
                threading.Timer(0.3, kill).start()

        ex.run([spec("hang", fifo), spec("quick", ok_file)], on_result)
        assert results["quick"]["status"] == "ok"
        assert results["hang"]["status"] == "failed" and "died" in results["hang"]["error"]
        again = ex.run([spec("after", ok_file)], lambda r: None)
        assert again["after"]["status"] == "ok"
    assert (tmp_path / "after" / "after.npz").exists()


def test_worker_with_another_version_refuses_the_task(tmp_path):
    from reflectmm_cli.recipes import TaskSpec, execute_task
    from reflectmm_cli.stages import get_stage

    f = tmp_path / "x.txt"
    f.write_text("x")
    ctx = get_stage("checksum").context(workspace=tmp_path, inputs={"files": [f]})
    res = execute_task(TaskSpec("checksum", "checksum", ctx, tool_version="0.0.0-other"))
    assert res["status"] == "failed" and "planned with 0.0.0-other" in res["error"]
    assert not (tmp_path / "checksum").exists()
    res = execute_task(TaskSpec("checksum", "checksum", ctx))
    assert res["status"] == "ok" and res["outputs"] == [str(tmp_path / "checksum" / "checksum.npz")]


def test_dask_resources_are_honoured_or_refused(tmp_path):
    from distributed import LocalCluster

    ws = make_workspace(tmp_path / "res")
    text = (ws / "recipe.toml").read_text()
    text = text.replace('inputs = { files = "data/{id}" }',
                        'inputs = { files = "data/{id}" }\nresources = { cpus = 1, memory = "1GB" }')
    text += 'resources = { cpus = 3 }\n'  # the aggregate asks for more than any worker has
    (ws / "recipe.toml").write_text(text)
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, dashboard_address=None,
                      resources={"cpus": 2}) as cluster:
        rep = run_recipe(ws / "recipe.toml", ws, executor="dask", scheduler=cluster.scheduler_address)
    st = {t.tid: t.status for t in rep.tasks}
    assert all(st[f"manifest/{i}"] == "ok" for i in IDS)  # cpus=1 fits, undeclared memory is ignored
    assert st["summary"] == "failed"
    assert "needs resources cpus=3 but the largest worker declares cpus=2" in rep.tasks[-1].error


def test_a_worker_returns_the_digests_it_computed_and_the_run_keeps_them(tmp_path, monkeypatch):
    # a task planned before its inputs existed computes its key in the worker; those digests come back with the
    # result into the workspace's hash memo, so the next plan does not hash the files again
    import os

    from reflectmm_cli.recipes import TaskSpec, execute_task
    from reflectmm_cli.recipes.plan import load_hash_memo
    from reflectmm_cli.artifacts import sha256_file
    from reflectmm_cli.stages import get_stage

    f = tmp_path / "x.txt"
    f.write_text("x")
    ctx = get_stage("checksum").context(workspace=tmp_path, inputs={"files": [f]})
    res = execute_task(TaskSpec("checksum", "checksum", ctx))
    st = os.stat(f)
    assert res["status"] == "ok"
    assert res["hashes"] == {str(f.resolve()): [st.st_size, st.st_mtime_ns, sha256_file(f)]}
    # through a run: files that only a worker hashed are in the memo afterwards, and a replan hashes nothing
    from reflectmm_cli.recipes import run_recipe

    ws = make_workspace(tmp_path / "ws")
    assert run_recipe(ws / "recipe.toml", ws).ok
    memo = load_hash_memo(ws)
    calls = []
    import reflectmm_cli.stages.base as base

    real = base.sha256_file
    monkeypatch.setattr(base, "sha256_file", lambda p: calls.append(p) or real(p))
    plan = run_recipe(ws / "recipe.toml", ws, dry_run=True)
    assert {t.status for t in plan.tasks} == {"skip"} and calls == [], calls
    assert memo


DISCOVERED = """
schema = "reflectmm.recipe/1"
[stages.first]
verb = "checksum"
inputs = { files = "data/001" }

# reads a FIFO: it runs until the test feeds it
[stages.hang]
verb = "checksum"
inputs = { files = ["@first.output", "blocks.fifo"] }
""" + DISCOVER_STAGES


@pytest.mark.parametrize("executor", ["pool", "dask"])
def test_a_discovered_stage_starts_while_other_tasks_still_run(tmp_path, executor):
    """A stage whose identities are found in its upstream's outputs is planned as soon as that upstream has
    finished, and its tasks run on the free worker while a task of the first batch is still running."""
    import threading
    import time

    ws = make_workspace(tmp_path / "ws")
    (ws / "recipe.toml").write_text(DISCOVERED)
    fifo = ws / "blocks.fifo"
    os.mkfifo(fifo)
    done = threading.Event()

    def feed():  # once released: every open of the FIFO for reading gets one byte, then end of file
        while not done.is_set():
            try:
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            except OSError:  # no reader yet
                time.sleep(0.01)
                continue
            os.write(fd, b"x")
            os.close(fd)
            time.sleep(0.01)

    reports = []
    runner = threading.Thread(target=lambda: reports.append(run_recipe(ws / "recipe.toml", ws, executor=executor,
                                                                       jobs=2)))
    runner.start()
    outputs = [ws / "found" / f"{i}.npz" for i in ("002", "004")]
    deadline = time.monotonic() + 90
    while not all(p.exists() for p in outputs) and time.monotonic() < deadline and runner.is_alive():
        time.sleep(0.05)
    found_first = all(p.exists() for p in outputs) and not (ws / "hang" / "hang.npz").exists()
    feeder = threading.Thread(target=feed)
    feeder.start()
    runner.join(120)
    done.set()
    feeder.join()
    assert found_first, "the discovered stage waited for the whole first batch"
    rep = reports[0]
    assert rep.ok and {t.tid: t.status for t in rep.tasks} == {
        "first": "ok", "hang": "ok", "manifest/002": "ok", "manifest/004": "ok", "found/002": "ok",
        "found/004": "ok"}


def test_an_executor_that_takes_no_specs_from_on_result_still_runs_every_task(tmp_path):
    """Executors written before on_result could return more tasks ignore its return: the tasks planned while
    their batch ran are then run in the next batch, none is lost and none runs twice."""
    from reflectmm_cli.recipes import Executor
    from reflectmm_cli.recipes.executors import execute_task

    class OldStyle(Executor):
        name = "old-style"
        ran: list[str] = []

        def run(self, specs, on_result):
            results = {}
            for spec in specs:
                results[spec.tid] = execute_task(spec, *[results[d] for d in spec.deps])
                self.ran.append(spec.tid)
                on_result(results[spec.tid])  # its return value is dropped
            return results

    ws = make_workspace(tmp_path / "ws")
    (ws / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n' + DISCOVER_STAGES)
    ex = OldStyle()
    rep = run_recipe(ws / "recipe.toml", ws, executor=ex)
    assert rep.ok and {t.tid: t.status for t in rep.tasks} == {
        "manifest/002": "ok", "manifest/004": "ok", "found/002": "ok", "found/004": "ok"}
    assert sorted(ex.ran) == ["found/002", "found/004", "manifest/002", "manifest/004"]


def test_an_input_changed_while_the_task_runs_writes_nothing(cli, tmp_path, monkeypatch):
    """Another process rewrites an input while the stage computes: the outputs would carry a key that does not
    describe what was read, so none is written (the previous output is kept) and the error names the input."""
    import reflectmm_cli.stages.checksum as checksum

    f = tmp_path / "x.txt"
    f.write_text("first")
    out = tmp_path / "m.npz"
    assert cli("checksum", f, "-o", out).exit_code == 0
    before = out.read_bytes()
    real = checksum.checksum_files

    def rewritten_meanwhile(paths):
        res = real(paths)
        f.write_text("written by another process")
        return res

    monkeypatch.setattr(checksum, "checksum_files", rewritten_meanwhile)
    r = cli("checksum", f, "-o", out)
    assert r.exit_code == 1 and "x.txt: input changed while the task ran" in r.stderr
    assert out.read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_task_keys_its_outputs_by_the_inputs_it_read_not_those_it_was_planned_with(tmp_path, reflectmm_log):
    """An input replaced between planning and the task's start: the planner's key described the old file, which
    would make the output look up to date once the old file is back. The worker checks the planned inputs by stat
    and keys the outputs by what it reads."""
    from reflectmm_cli.artifacts import read_meta
    from reflectmm_cli.recipes import TaskSpec, execute_task
    from reflectmm_cli.stages import cache_key_doc, get_stage, key_of_doc

    f = tmp_path / "x.txt"
    f.write_text("as planned")
    stage = get_stage("checksum")
    ctx = stage.context(workspace=tmp_path, inputs={"files": [f]})
    used: dict = {}
    planned = cache_key_doc(stage, ctx, {}, used)
    f.write_text("replaced before the task started")
    st = os.stat(f)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    res = execute_task(TaskSpec("checksum", "checksum", ctx, key_doc=planned, inputs_used=used))
    now = key_of_doc(cache_key_doc(stage, ctx))
    assert res["status"] == "ok" and res["cache_key"] == now != key_of_doc(planned)
    assert read_meta(tmp_path / "checksum" / "checksum.npz")["cache_key"] == now
    assert any("an input changed after the run was planned" in m for m in reflectmm_log)
    # unchanged inputs: the planner's key is used as it is, without hashing the files again
    calls = []
    import reflectmm_cli.stages.base as base

    real = base.sha256_file
    base.sha256_file = lambda p, *a: calls.append(p) or real(p, *a)
    try:
        used2: dict = {}
        doc2 = cache_key_doc(stage, ctx, {}, used2)
        calls.clear()
        res = execute_task(TaskSpec("checksum", "checksum", ctx, key_doc=doc2, inputs_used=used2))
    finally:
        base.sha256_file = real
    assert res["status"] == "ok" and res["cache_key"] == key_of_doc(doc2) and calls == []

"""kill -9 of a `reflectmm run --jobs 2` takes its whole process tree with it (forkserver, tracker, workers)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")

RECIPE = """
schema = "reflectmm.recipe/1"
[stages.a]
verb = "checksum"
foreach = ["001", "002"]
inputs = { files = "data/{id}" }

[stages.b]                    # its workers block reading the FIFO until killed
verb = "checksum"
foreach = ["001", "002"]
inputs = { files = ["@a.output", "pipe"] }
"""


def _stat(pid: int) -> tuple[int, str] | None:
    """(ppid, state) of a live process, None if gone (zombies count as gone)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    state, ppid = text.rsplit(")", 1)[1].split()[:2]
    return None if state in ("Z", "X") else (int(ppid), state)


def _descendants(root: int) -> set[int]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit() and (st := _stat(int(d))) is not None:
            kids.setdefault(st[0], []).append(int(d))
    out, todo = set(), [root]
    while todo:
        for k in kids.get(todo.pop(), []):
            if k not in out:
                out.add(k)
                todo.append(k)
    return out


def test_sigkill_of_pool_run_leaves_no_process(ws):
    (ws / "recipe.toml").write_text(RECIPE)
    os.mkfifo(ws / "pipe")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[2])] +
                                                        [p for p in [os.environ.get("PYTHONPATH")] if p])}
    proc = subprocess.Popen([sys.executable, "-m", "reflectmm_cli", "run", str(ws / "recipe.toml"), "-w", str(ws),
                             "--jobs", "2", "--executor", "pool"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # forkserver, resource tracker and two workers (blocked on the FIFO)
            seen |= _descendants(proc.pid)
            if len(seen) >= 4 and (ws / "a" / "002.npz").exists():
                time.sleep(0.5)
                seen |= _descendants(proc.pid)
                break
            time.sleep(0.1)
        assert len(seen) >= 3, f"the run did not start its pool: {seen}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 8
        while time.monotonic() < deadline and any(_stat(p) for p in seen):
            time.sleep(0.1)
        alive = sorted(p for p in seen if _stat(p))
        assert not alive, f"still alive after the parent was killed: {alive}"
    finally:
        for p in seen:  # never leave a stray process behind, whatever happened
            if _stat(p):
                try:
                    os.kill(p, signal.SIGKILL)
                except OSError:
                    pass
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("sig, group, status, line", [
    (signal.SIGINT, False, 130, "reflectmm: interrupted"),  # kill -INT of the run's process: it waited for its tasks
    (signal.SIGTERM, False, 143, "reflectmm: terminated (SIGTERM)"),
    (signal.SIGTERM, True, 143, "reflectmm: terminated (SIGTERM)"),  # a scheduler's timeout or scancel
], ids=["int-run-process", "term-run-process", "term-group"])
def test_interrupt_of_pool_run_stops_its_workers_at_once(ws, slow_writes, sig, group, status, line):
    script, markers = slow_writes
    (ws / "recipe.toml").write_text(RECIPE.split("[stages.b]")[0])
    env = {**os.environ, "MARKERS": str(markers),
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[2])] +
                                         [p for p in [os.environ.get("PYTHONPATH")] if p])}
    proc = subprocess.Popen([sys.executable, str(script), "run", str(ws / "recipe.toml"), "-w", str(ws),
                             "--jobs", "2", "--executor", "pool"], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while len(list(markers.iterdir())) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # both workers are writing their task's output
        seen = _descendants(proc.pid)
        assert len(list(ws.glob("a/.*.tmp"))) == 2, "the workers were not writing"
        t0 = time.monotonic()
        os.killpg(proc.pid, sig) if group else os.kill(proc.pid, sig)
        _, stderr = proc.communicate(timeout=30)  # the tasks would sleep a minute more
        assert time.monotonic() - t0 < 15
        assert proc.returncode == status, stderr
        assert stderr.strip().splitlines()[-1] == line, stderr
        assert "Traceback" not in stderr, stderr
        assert sorted(p.name for p in ws.glob("a/.*")) == []  # the workers removed their temporary files
        assert not list(ws.glob("a/*.npz"))
        runlog = ws / ".reflectmm" / "runlog.jsonl"
        assert not runlog.exists() or runlog.read_text() == ""  # the interrupted tasks are not recorded as done
        deadline = time.monotonic() + 8
        while time.monotonic() < deadline and any(_stat(p) for p in seen):
            time.sleep(0.1)
        assert not [p for p in seen if _stat(p)], "a worker outlived the run"
    finally:
        for p in seen | ({proc.pid} if proc.poll() is None else set()):
            if _stat(p):
                try:
                    os.kill(p, signal.SIGKILL)
                except OSError:
                    pass
        proc.wait()

"""Issue 24 §6: after `kill -9` of `reflectmm run --jobs 2`, multiprocessing's resource tracker (which outlives the
run and removes the pool's semaphores) printed "There appear to be N leaked semaphore objects". The tracker now
starts with that warning filtered (the clean-up itself is unchanged: no semaphore of the run is left)."""
import os
import signal
import subprocess
import sys
import time

import pytest


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX semaphores in /dev/shm")
def test_kill_9_of_a_pool_run_prints_no_leaked_semaphore_warning(tmp_path):
    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n'
                                     '[stages.a]\nverb = "synth-envmaps"\nparams = { count = 40, width = 1024 }\n'
                                     '[stages.b]\nverb = "synth-envmaps"\n'
                                     'params = { count = 40, width = 1024, seed = 3 }\n')
    before = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    err = open(tmp_path / "err", "w")
    p = subprocess.Popen([sys.executable, "-m", "reflectmm_cli", "run", str(tmp_path / "r.toml"), "-w",
                          str(tmp_path / "ws"), "--jobs", "2"], stderr=err, stdout=subprocess.DEVNULL,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    t0 = time.time()
    while "running" not in (tmp_path / "err").read_text() and time.time() - t0 < 60:
        time.sleep(0.2)
    time.sleep(2.0)  # the workers are busy
    p.send_signal(signal.SIGKILL)
    p.wait()
    time.sleep(6.0)  # the tracker notices the closed pipe and cleans up
    err.close()
    text = (tmp_path / "err").read_text()
    assert "running" in text and "leaked semaphore" not in text, text
    if os.path.isdir("/dev/shm"):
        assert not {f for f in set(os.listdir("/dev/shm")) - before if f.startswith("sem.mp-")}

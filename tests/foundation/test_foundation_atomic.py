"""Atomic writes: a writer killed with SIGKILL mid-write leaves the previous file intact."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact

WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from reflectmm_cli.artifacts import write_artifact
    path = sys.argv[1]
    n = 4_000_000  # 32 MB of float64 per write, so a kill lands inside a write most of the time
    i = 1
    while True:
        write_artifact(path, "render", {"x": np.full(n, float(i)), "i": np.int64(i)}, params={"i": i},
                       compress=False)
        print(i, flush=True)
        i += 1
""")


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_sigkill_during_write_leaves_old_file_or_none(tmp_path):
    target = tmp_path / "big.npz"
    write_artifact(target, "render", {"x": np.full(4_000_000, 0.0), "i": np.int64(0)}, params={"i": 0},
                   compress=False)
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    rng = np.random.default_rng(0)
    killed_mid_write = 0
    for trial in range(12):
        proc = subprocess.Popen([sys.executable, str(script), str(target)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()  # at least one complete write has happened
            assert line.strip(), proc.stderr.read()
            if trial % 2 == 0:
                # aim: wait until the next temporary file appears, then kill a little later
                t_end = time.monotonic() + 5
                while time.monotonic() < t_end and not any(p.name.startswith(".big.npz.")
                                                           for p in tmp_path.iterdir()):
                    time.sleep(0.0005)
                time.sleep(float(rng.uniform(0.0, 0.005)))
            else:  # anywhere in the loop
                time.sleep(float(rng.uniform(0.0, 0.15)))
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == -signal.SIGKILL
        leftovers = [p for p in tmp_path.iterdir() if p.name.startswith(".big.npz.")]
        killed_mid_write += bool(leftovers)
        # the target is always a complete, consistent artifact from one write
        art = read_artifact(target, "render")
        i = int(art["i"])
        assert art.params == {"i": i}
        x = art["x"]
        assert x.shape == (4_000_000,) and x[0] == i and x[-1] == i and np.all(x == i)
        for p in leftovers:  # the kill left a temporary file: hidden, never the target itself
            p.unlink()
        if killed_mid_write >= 3 and trial >= 3:
            break
    assert killed_mid_write >= 3, "no kill landed inside a write; the test proved nothing"


def test_exception_during_write_leaves_old_file_and_no_temp(tmp_path):
    target = write_artifact(tmp_path / "a.npz", "render", {"x": np.arange(3)})
    before = target.read_bytes()
    with pytest.raises(Exception):
        write_artifact(target, "render", {"x": np.arange(3), "bad": np.array([object()], dtype=object)})
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]

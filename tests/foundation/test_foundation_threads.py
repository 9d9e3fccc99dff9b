import pytest

torch = pytest.importorskip("torch")

from reflectmm_cli.threads import torch_threads  # noqa: E402


def test_torch_threads_sets_and_restores_even_on_error():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("n", [None, 0, -1])
def test_torch_threads_none_or_nonpositive_leaves_the_count(n):
    before = torch.get_num_threads()
    with torch_threads(n):
        assert torch.get_num_threads() == before
    assert torch.get_num_threads() == before


def test_default_threads_is_the_available_cpus_capped(monkeypatch):
    import os

    from reflectmm_cli import threads

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3, 5}, raising=False)
    assert threads.available_cpus() == 3
    assert [threads.default_threads(c) for c in (1, 2, 3, 8)] == [1, 2, 3, 3]
    assert threads.default_threads(0) == 1  # never below one thread
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)  # no affinity API: os.cpu_count()
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert threads.available_cpus() == 6 and threads.default_threads(4) == 4
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert threads.available_cpus() == 1


def test_no_site_derives_its_own_default_thread_count():
    """threads.default_threads is the one rule: no other module reads the CPU count."""
    import re
    from pathlib import Path

    pkg = Path(__file__).resolve().parents[2] / "reflectmm_cli"
    offenders = sorted(str(p.relative_to(pkg)) for p in pkg.rglob("*.py")
                       if re.search(r"cpu_count\(|sched_getaffinity\(", p.read_text())
                       and str(p.relative_to(pkg)) != "threads.py")
    assert offenders == []


def _share_in_worker(_):
    import os

    from reflectmm_cli import threads

    return threads.available_cpus(), threads.default_threads(64), os.environ.get(threads.CPU_SHARE_ENV)


def test_a_pool_worker_gets_its_share_of_the_cpus():
    """Two task processes on this machine's CPUs each get half of them (at least one) as the toolkit's default
    thread count; the serial path keeps every CPU."""
    from reflectmm_cli import threads
    from reflectmm_cli.recipes.executors import OrderedMap

    share = max(1, threads.available_cpus() // 2)
    assert threads.cpu_share(2) == share and threads.cpu_share(1) == threads.available_cpus()
    with OrderedMap("pool", jobs=2) as pmap:
        got = pmap(_share_in_worker, [0, 1])
    assert got == [(share, share, str(share))] * 2
    cpus, default, _ = OrderedMap("serial")(_share_in_worker, [0])[0]
    assert cpus == default == threads.available_cpus()


_REPORT = """
import json, os, sys
{before}
from reflectmm_cli import threads
threads.limit_process_threads(1)
{after}
import torch
from threadpoolctl import threadpool_info
print(json.dumps([threads.default_threads(64), torch.get_num_threads(),
                  [p["num_threads"] for p in threadpool_info()], os.environ.get("OMP_NUM_THREADS")]))
"""


@pytest.mark.parametrize("loaded_first", [True, False])
def test_the_limit_holds_libraries_loaded_before_and_after(loaded_first):
    """In a fresh process without thread settings: torch's pool and every loaded BLAS/OpenMP pool end at the
    limit, whether the libraries were loaded before the limit (threadpoolctl, torch.set_num_threads) or after
    it (the environment variables)."""
    import json
    import os
    import subprocess
    import sys

    from reflectmm_cli import threads

    env = {k: v for k, v in os.environ.items() if k not in threads.NATIVE_THREAD_ENV + (threads.CPU_SHARE_ENV,)}
    code = _REPORT.format(before="import numpy, torch" if loaded_first else "",
                          after="" if loaded_first else "import numpy")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    default, torch_n, pools, omp = json.loads(out.stdout.strip().splitlines()[-1])
    assert default == torch_n == 1 and omp == "1"
    assert pools and all(n == 1 for n in pools)


def test_the_users_thread_settings_win(monkeypatch):
    """With OMP_NUM_THREADS set by the user, the limit changes only the toolkit's own share, no library pool."""
    from reflectmm_cli import threads

    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    monkeypatch.delenv(threads.CPU_SHARE_ENV, raising=False)
    before = torch.get_num_threads()
    threads.limit_process_threads(1)
    try:
        assert threads.available_cpus() == 1 and threads.default_threads(8) == 1
        assert torch.get_num_threads() == before and __import__("os").environ["OMP_NUM_THREADS"] == "7"
    finally:
        monkeypatch.delenv(threads.CPU_SHARE_ENV)
    assert threads.available_cpus() >= 1


@pytest.mark.parametrize("share", ["0", "-2", "x", ""])
def test_a_bad_share_is_ignored(monkeypatch, share):
    from reflectmm_cli import threads

    monkeypatch.setenv(threads.CPU_SHARE_ENV, share)
    monkeypatch.setattr(__import__("os"), "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    assert threads.available_cpus() == 3

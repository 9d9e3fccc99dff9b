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

"""Thread helpers: the one rule for default thread counts, scoped thread limits for torch work on small
problems or shared CPUs, and an ordered map on a thread pool."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Iterator


def available_cpus() -> int:
    """CPUs this process may run on (≥ 1): its affinity mask where the OS has one (so ``taskset`` and cgroup
    cpusets are honoured), else ``os.cpu_count()``."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def default_threads(cap: int) -> int:
    """The toolkit's default worker/thread count when the caller gives none: :func:`available_cpus` capped at
    ``cap`` (the most the site's work gains from; ≥ 1)."""
    return max(1, min(available_cpus(), int(cap)))


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(n)`` and restore the previous count after.

    ``n`` None or ≤ 0 leaves the thread count as it is.  Small problems lose more to thread
    start-up and contention than they gain, so callers pass 1 for them.
    """
    import torch

    prev = torch.get_num_threads()
    if n is not None and n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


def parallel_map(fn, items, threads: int, lazy: bool = False):
    """``map(fn, items)`` on a thread pool of ``threads`` workers (in order); plain map for one thread."""
    items = list(items)
    if int(threads) <= 1 or len(items) <= 1:
        out = map(fn, items)
        return out if lazy else list(out)
    with ThreadPoolExecutor(max_workers=int(threads)) as ex:
        futures = [ex.submit(fn, it) for it in items]
        return [f.result() for f in futures]

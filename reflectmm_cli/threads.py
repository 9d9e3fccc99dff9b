"""Thread helpers: the one rule for default thread counts, scoped thread limits for torch work on small
problems or shared CPUs, and an ordered map on a thread pool."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Iterator


#: The number of CPUs a process may use when it shares the machine with other task processes (set by
#: :func:`limit_process_threads` in the workers of ``reflectmm run --jobs N``); :func:`available_cpus` honours it.
CPU_SHARE_ENV = "REFLECTMM_CPU_SHARE"

#: The thread-count variables that the native libraries read when they load (OpenMP — torch's intra-op pool among
#: them —, OpenBLAS, MKL, numba).
NATIVE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def available_cpus() -> int:
    """CPUs this process may run on (≥ 1): its affinity mask where the OS has one (so ``taskset`` and cgroup
    cpusets are honoured), else ``os.cpu_count()``; at most its share (``REFLECTMM_CPU_SHARE``) when it runs
    tasks beside other processes."""
    try:
        n = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        n = max(1, os.cpu_count() or 1)
    share = os.environ.get(CPU_SHARE_ENV, "")
    return min(n, int(share)) if share.isdigit() and int(share) >= 1 else n


def cpu_share(processes: int) -> int:
    """The CPUs each of ``processes`` task processes gets when they share this process's CPUs (≥ 1)."""
    return max(1, available_cpus() // max(1, int(processes)))


def limit_process_threads(n: int) -> None:
    """Hold this process to ``n`` threads, its share of the CPUs when task processes run side by side: two
    workers each running BLAS, torch and numba on every core of a 2-core machine run slower than with one
    thread each (docs/benchmarks.md, "Whole synthetic recipe").

    Sets ``REFLECTMM_CPU_SHARE`` (so :func:`available_cpus` and every default thread count follow), the
    variables of :data:`NATIVE_THREAD_ENV` for the libraries loaded later, and limits those already loaded
    (BLAS/OpenMP pools through threadpoolctl, torch's and numba's pools). A variable the user has set is kept,
    and then no loaded pool is changed either: the user's thread settings win.
    """
    import sys

    n = max(1, int(n))
    os.environ[CPU_SHARE_ENV] = str(n)
    if any(v in os.environ for v in NATIVE_THREAD_ENV):
        return
    for v in NATIVE_THREAD_ENV:
        os.environ[v] = str(n)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=n)  # not a context: the limits stay for the life of the process
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        pass
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)
    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))


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

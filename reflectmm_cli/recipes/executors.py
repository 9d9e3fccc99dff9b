"""Executors: run task specs (with dependencies) serially, in a local process pool, or on Dask.

All three share one interface, :meth:`Executor.run`, which takes task specs in a
topological order and calls ``on_result`` as each finishes.  A task spec is a small
picklable description (verb + :class:`~reflectmm_cli.stages.StageContext`); the worker
imports ``reflectmm_cli``, looks the verb up with :func:`~reflectmm_cli.stages.get_stage`
and calls ``stage.run(ctx)`` (:func:`execute_task`).  A failure travels back as a message
in the result, never as a pickled exception, and a task whose upstream failed is
"blocked" without running.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from reflectmm_cli import __version__
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.signals import call_terminable, install_worker_handler
from reflectmm_cli.stages import StageContext
from reflectmm_cli.threads import cpu_share, limit_process_threads

log = logging.getLogger("reflectmm")

OK, FAILED, BLOCKED = "ok", "failed", "blocked"


@dataclass
class TaskSpec:
    """What a worker needs to run one task."""

    tid: str
    verb: str
    ctx: StageContext
    deps: list[str] = field(default_factory=list)
    key_doc: dict[str, Any] | None = None
    resources: dict[str, Any] = field(default_factory=dict)
    #: the reflectmm version of the planning process; a worker running another version refuses the task
    tool_version: str = __version__
    #: among the tasks that are ready, a higher priority starts first (the runner gives
    #: :func:`~reflectmm_cli.recipes.recipe.task_priorities`: the stage's declared priority, its chain length, then
    #: its downstream stages); it never changes a result
    priority: int = 0
    #: the planner's ``[size, mtime_ns, sha256]`` of the input files ``key_doc`` was computed from, by path: the
    #: worker checks them (by stat) when the task starts and again before its outputs are committed
    inputs_used: dict[str, Any] = field(default_factory=dict)


def _result(spec: TaskSpec, status: str, *, outputs: list[str] | None = None, cache_key: str | None = None,
            key_doc: dict[str, Any] | None = None, duration: float = 0.0, error: str | None = None,
            hashes: dict[str, Any] | None = None) -> dict[str, Any]:
    return {"tid": spec.tid, "status": status, "outputs": outputs or [], "cache_key": cache_key,
            "key_doc": key_doc, "duration": duration, "error": error,
            "worker": f"{socket.gethostname()}:{os.getpid()}", "hashes": hashes or {}}


def _error_message(exc: BaseException) -> str:
    if isinstance(exc, ReflectmmError):
        return str(exc)
    return f"{type(exc).__name__}: {' '.join(str(exc).split())[:400]}"


def blocked_by(spec: TaskSpec, upstream: list[dict[str, Any]]) -> dict[str, Any] | None:
    bad = [u for u in upstream if u["status"] != OK]
    if not bad:
        return None
    return _result(spec, BLOCKED, error=f"upstream {bad[0]['tid']} {bad[0]['status']}")


def execute_task(spec: TaskSpec, *upstream: dict[str, Any]) -> dict[str, Any]:
    """Run one task in this process; return a plain result dict (never raises).

    ``upstream`` are the results of the tasks this one depends on (a failed or blocked
    one blocks this task).  The cache key is computed here when the planner could not
    (its inputs did not exist yet).
    """
    blocked = blocked_by(spec, list(upstream))
    if blocked is not None:
        return blocked
    from reflectmm_cli.stages import cache_key_doc, check_no_overwrite, get_stage, key_of_doc, run_committed

    t0 = time.perf_counter()
    doc = spec.key_doc
    key = None
    hashes: dict[str, Any] = {}
    try:
        if spec.tool_version != __version__:
            raise ReflectmmError(f"worker runs reflectmm {__version__}, the run was planned with "
                                 f"{spec.tool_version}; install the same version on every worker")
        stage = get_stage(spec.verb)
        ctx = spec.ctx.with_patterns_expanded()  # a pattern into an upstream folder matches now
        check_no_overwrite(stage, ctx)
        used: dict[str, Any] = {}
        if doc is None:
            # the inputs' digests go back with the result into the workspace's hash memo, so the next plan does
            # not hash these files again (a worker process has no access to the planner's memo)
            doc = cache_key_doc(stage, ctx, hashes, used)
        else:
            # the key the planner computed describes the inputs as they were then: checked by stat (a file that
            # changed since is hashed again), so the outputs are never keyed by inputs that were not read
            memo = {k: list(v) for k, v in spec.inputs_used.items()}
            now = cache_key_doc(stage, ctx, memo, used)
            if key_of_doc(now) != key_of_doc(doc):
                log.warning("%s: an input changed after the run was planned; its outputs are keyed by the inputs as "
                            "they are now", spec.tid)
                hashes.update({k: v for k, v in memo.items() if spec.inputs_used.get(k) != v})
                doc = now
        key = key_of_doc(doc)
        ctx = ctx.with_(cache_key=key)
        if ctx.device and ctx.device != "cpu":
            from reflectmm_cli.stages import resolve_device

            ctx = ctx.with_(device=resolve_device(ctx.device))
        written = [str(p) for p in run_committed(stage, ctx, used)]
        missing = [str(p) for p in stage.expected_outputs(ctx) if not Path(p).exists()]
        if missing:
            raise ReflectmmError(f"stage '{spec.verb}' finished without writing {missing[0]}")
        return _result(spec, OK, outputs=written, cache_key=key, key_doc=doc,
                       duration=time.perf_counter() - t0, hashes=hashes)
    except FileNotFoundError as exc:
        return _result(spec, FAILED, cache_key=key, duration=time.perf_counter() - t0,
                       error=f"{exc.filename}: file not found" if exc.filename else _error_message(exc))
    except Exception as exc:  # noqa: BLE001 - any failure of one task is reported, the others go on
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s failed:\n%s", spec.tid, traceback.format_exc())
        return _result(spec, FAILED, cache_key=key, duration=time.perf_counter() - t0, error=_error_message(exc))


def refused_task(spec: TaskSpec, message: str) -> dict[str, Any]:
    """The result of a task that cannot be scheduled (its dependents are then blocked)."""
    return _result(spec, FAILED, error=message)


#: Called with each task's result; may return more task specs to run (see :meth:`Executor.run`).
OnResult = Callable[[dict[str, Any]], "list[TaskSpec] | None"]


class Executor:
    """Runs task specs with dependencies.  Use as a context manager (pools/clusters are shut down)."""

    name = "base"

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        pass

    def run(self, specs: list[TaskSpec], on_result: OnResult) -> dict[str, dict[str, Any]]:
        """Run ``specs`` (topologically ordered; ``deps`` name specs of this run).

        ``on_result`` is called with each result as it arrives; it may return more specs, which join the run
        (their ``deps`` name specs given earlier in it, finished or not): a runner plans the stages that wait
        for their upstream's outputs as soon as those exist, while the other tasks go on.
        """
        raise NotImplementedError


def take_ready(pending: list[TaskSpec], results: dict[str, Any]) -> tuple[TaskSpec | None, list[TaskSpec]]:
    """(the task of ``pending`` whose dependencies all have results and whose priority is highest — the earliest
    in ``pending`` among equals —, the others), or (None, ``pending``) when none is ready."""
    best = None
    for i, spec in enumerate(pending):
        if all(d in results for d in spec.deps) and (best is None or spec.priority > pending[best].priority):
            best = i
    if best is None:
        return None, pending
    return pending[best], pending[:best] + pending[best + 1:]


class SerialExecutor(Executor):
    """In this process, one task after another (the reference for the others)."""

    name = "serial"

    def run(self, specs: list[TaskSpec], on_result: OnResult) -> dict[str, dict[str, Any]]:
        results: dict[str, dict[str, Any]] = {}
        queue = list(specs)
        while queue:
            spec = queue.pop(0)
            res = execute_task(spec, *[results[d] for d in spec.deps])
            results[spec.tid] = res
            queue += on_result(res) or []
        return results


#: After ``kill -9`` of ``reflectmm run``, multiprocessing's resource tracker (a separate process that outlives it)
#: removes the pool's semaphores and warns "There appear to be N leaked semaphore objects to clean up": nothing is
#: left behind, the line only alarms. The tracker takes its warning filters from the interpreter options it is
#: started with, so this one is added before the first pool starts it.
_TRACKER_WARNING = "ignore::UserWarning:multiprocessing.resource_tracker"


def _mp_context():
    if _TRACKER_WARNING not in sys.warnoptions:
        sys.warnoptions.append(_TRACKER_WARNING)
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")


def _proc_start(pid: int) -> str | None:
    """Start time (clock ticks since boot) of a live process from /proc, None if gone or a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] in (b"Z", b"X") else fields[19].decode()


def _parent_alive(pid: int, start: str | None) -> bool:
    if start is not None or os.path.exists("/proc/self/stat"):
        return _proc_start(pid) == start  # also catches a recycled pid and a zombie parent
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except OSError:
        return True


def _die_with(pid: int, start: str | None, period: float) -> None:
    while _parent_alive(pid, start):
        time.sleep(period)
    os._exit(1)


def _worker_init(parent_pid: int, parent_start: str | None, period: float = 0.5, threads: int | None = None
                 ) -> None:
    """Pool worker initializer: the worker dies with the run that started it, even under ``kill -9``, and holds
    itself to ``threads`` threads (its share of the CPUs: :func:`reflectmm_cli.threads.limit_process_threads`).
    SIGTERM (a scheduler's, to the whole group, or the run's own on an interrupt: :meth:`PoolExecutor.terminate`)
    unwinds the task it runs, so its atomic writes remove their temporary files, and ends the worker.

    A worker's parent is the forkserver, so Linux's PR_SET_PDEATHSIG covers the forkserver's death only; a
    daemon thread watches the run's own process (pid + start time, so a recycled pid does not fool it) and
    exits the worker once it is gone. The resource tracker then sees its last writer close and exits too.
    The death signal is SIGTERM, not SIGKILL: a group SIGTERM ends the forkserver at once, and a SIGKILL would then
    cut short the clean-up of the task the worker is unwinding.
    """
    import threading

    install_worker_handler()
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # pragma: no cover - no libc symbol: the watchdog still works
            pass
    threading.Thread(target=_die_with, args=(parent_pid, parent_start, period), daemon=True,
                     name="reflectmm-parent-watchdog").start()
    if threads is not None:
        limit_process_threads(threads)


class PoolExecutor(Executor):
    """A local process pool (``--jobs N``) started with forkserver/spawn (no forked torch state)."""

    name = "pool"

    def __init__(self, jobs: int = 1):
        self.jobs = max(1, int(jobs))
        self._pool: ProcessPoolExecutor | None = None

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=_mp_context(),
                                             initializer=_worker_init,
                                             initargs=(os.getpid(), _proc_start(os.getpid()), 0.5,
                                                       cpu_share(self.jobs)))
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    #: how long :meth:`terminate` waits for the workers to clean up before it kills them
    TERMINATE_GRACE = 10.0

    def terminate(self) -> None:
        """Stop the workers now (an interrupt: Ctrl-C or SIGTERM of the run's process): SIGTERM to each, whose
        handler unwinds the running task — removing its temporary files — and ends the worker; what is left after
        :attr:`TERMINATE_GRACE` seconds is killed. Their tasks are not finished and get no result."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = [p for p in (getattr(pool, "_processes", None) or {}).values() if p.is_alive()]
        for p in procs:
            try:
                p.terminate()
            except OSError:  # pragma: no cover - already gone
                pass
        pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + self.TERMINATE_GRACE
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)

    def run(self, specs: list[TaskSpec], on_result: OnResult) -> dict[str, dict[str, Any]]:
        try:
            return self._run(specs, on_result)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM of this process only: do not wait for the running tasks
            self.terminate()
            raise

    def _run(self, specs: list[TaskSpec], on_result: OnResult) -> dict[str, dict[str, Any]]:
        results: dict[str, dict[str, Any]] = {}
        pending = list(specs)
        running: dict[Any, TaskSpec] = {}
        pool = self._get_pool() if specs else None
        while pending or running:
            # at most `jobs` tasks in the pool, so that the choice of the next one is made when a worker is free:
            # the ready task of highest priority, the earliest given among equals
            while len(running) < self.jobs:
                spec, pending = take_ready(pending, results)
                if spec is None:
                    break
                blocked = blocked_by(spec, [results[d] for d in spec.deps])
                if blocked is not None:
                    results[spec.tid] = blocked
                    pending += on_result(blocked) or []
                else:
                    running[pool.submit(call_terminable, execute_task, spec)] = spec
            if not running:
                if pending:  # deps outside the batch would never finish
                    raise ReflectmmError(f"internal: task {pending[0].tid} waits on unknown {pending[0].deps}")
                break
            done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            broken = False
            for fut in done:
                spec = running.pop(fut)
                try:
                    res = fut.result()
                except BrokenProcessPool:  # a worker died (OOM killer, segfault): the pool is unusable
                    broken = True
                    res = _result(spec, FAILED, error="worker process died while running this task")
                except Exception as exc:  # noqa: BLE001 - e.g. the task spec could not be sent
                    res = _result(spec, FAILED, error=f"worker process failed: {_error_message(exc)}")
                results[spec.tid] = res
                pending += on_result(res) or []
            if broken:
                # every task running in the broken pool is lost; the remaining ones go to a new pool
                for fut, spec in list(running.items()):
                    res = _result(spec, FAILED, error="worker pool broke while running this task")
                    results[spec.tid] = res
                    pending += on_result(res) or []
                running.clear()
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                pool = self._get_pool()
        return results


class DaskExecutor(Executor):
    """Dask distributed: an existing scheduler (``tcp://host:port``) or a new ``LocalCluster``.

    Tasks are submitted with their upstream futures as arguments, so Dask schedules the
    DAG; results are collected as they complete.  Recipe ``resources`` are passed to Dask
    only for resource names the cluster's workers declare (``dask worker --resources
    "cpus=8,memory=64e9"``), so a cluster without them still runs every task.
    """

    name = "dask"

    def __init__(self, jobs: int = 1, scheduler: str | None = None):
        self.jobs = max(1, int(jobs))
        self.scheduler = scheduler
        self._client = None
        self._cluster = None

    def _get_client(self):
        if self._client is None:
            try:
                from distributed import Client, LocalCluster
            except ImportError as exc:  # pragma: no cover - dependency is mandatory
                raise ReflectmmError(f"--executor dask needs dask[distributed]: {exc}") from None
            if self.scheduler:
                try:
                    self._client = Client(self.scheduler, timeout="20s")
                except (OSError, TimeoutError) as exc:
                    raise ReflectmmError(f"--scheduler {self.scheduler}: cannot connect ({exc})") from None
                except (ValueError, TypeError) as exc:  # e.g. "missing port number in address"
                    raise ReflectmmError(f"--scheduler {self.scheduler}: not a scheduler address such as "
                                         f"tcp://HOST:8786 ({exc})") from None
            else:
                self._cluster = LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self._client = Client(self._cluster)
                # the workers share this machine's CPUs; an external cluster's workers are set up by whoever
                # starts them (docs/recipes.md)
                self._client.run(limit_process_threads, cpu_share(self.jobs))
            log.info("dask: %s", self._client.dashboard_link if self._client.dashboard_link else self._client)
        return self._client

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def _worker_resources(self, client) -> dict[str, float]:
        """Resource name -> the largest amount one worker declares."""
        most: dict[str, float] = {}
        try:
            for w in client.scheduler_info().get("workers", {}).values():
                for k, v in (w.get("resources") or {}).items():
                    most[k] = max(most.get(k, 0.0), float(v))
        except Exception:  # noqa: BLE001 - informational only
            pass
        return most

    def run(self, specs: list[TaskSpec], on_result: OnResult) -> dict[str, dict[str, Any]]:
        if not specs:
            return {}
        from dask.utils import parse_bytes
        from distributed import as_completed

        client = self._get_client()
        known = self._worker_resources(client)
        token = os.urandom(4).hex()
        futures: dict[str, Any] = {}
        by_key: dict[str, TaskSpec] = {}

        def submit(spec: TaskSpec):
            res = {}
            for k, v in (spec.resources or {}).items():
                if k in known:
                    res[k] = parse_bytes(v) if isinstance(v, str) else float(v)
            too_big = [k for k, v in res.items() if v > known[k]]
            key = f"reflectmm-{spec.tid.replace('/', '-')}-{token}"
            if too_big:  # no worker could ever take it: fail now instead of waiting forever
                k = too_big[0]
                fut = client.submit(refused_task, spec, f"needs resources {k}={res[k]:g} but the largest worker "
                                    f"declares {k}={known[k]:g}", key=key, pure=False)
            else:
                fut = client.submit(execute_task, spec, *[futures[d] for d in spec.deps], key=key, pure=False,
                                    resources=res or None, retries=0, priority=spec.priority)
            futures[spec.tid] = fut
            by_key[fut.key] = spec
            return fut

        done = as_completed([submit(spec) for spec in specs])
        results: dict[str, dict[str, Any]] = {}
        for fut in done:
            spec = by_key[fut.key]
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker, a deserialisation error...
                res = _result(spec, FAILED, error=f"dask: {_error_message(exc)}")
            results[spec.tid] = res
            for more in on_result(res) or []:
                done.add(submit(more))
        return results


def make_executor(kind: str = "serial", jobs: int = 1, scheduler: str | None = None) -> Executor:
    kind = (kind or "serial").lower()
    if scheduler and kind != "dask":
        raise ReflectmmError("--scheduler needs --executor dask")
    if kind == "serial":
        return SerialExecutor()
    if kind == "pool":
        return PoolExecutor(jobs)
    if kind == "dask":
        return DaskExecutor(jobs, scheduler)
    raise ReflectmmError(f"unknown executor '{kind}' (serial, pool, dask)")


def executor_kind(executor: str = "auto", jobs: int = 1, scheduler: str | None = None) -> str:
    """The executor ``auto`` stands for (the rule of ``reflectmm run``): dask with a scheduler address, a process
    pool with more than one job, else serial; a given kind is checked and returned."""
    kind = (executor or "auto").lower()
    if kind == "auto":
        return "dask" if scheduler else ("pool" if int(jobs) > 1 else "serial")
    if kind not in ("serial", "pool", "dask"):
        raise ReflectmmError(f"unknown executor '{executor}' (auto, serial, pool, dask)")
    if scheduler and kind != "dask":
        raise ReflectmmError("--scheduler needs --executor dask")
    if scheduler:
        check_scheduler_address(scheduler)
    return kind


def check_scheduler_address(scheduler: str) -> None:
    """Refuse an address Dask cannot read (``notaurl``, ``tcp://host`` without a port) before anything is planned
    or run, so ``--dry-run`` says what the run would; whether a scheduler answers there is known only on connect."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, loc = parse_address(scheduler)
        if scheme not in backends:
            raise ValueError(f"unknown scheme {scheme!r}")
        if scheme in ("tcp", "tls", "ws", "wss"):
            parse_host_port(loc)
    except (ValueError, TypeError) as exc:
        raise ReflectmmError(f"--scheduler {scheduler}: not a scheduler address such as tcp://HOST:8786 "
                             f"({exc})") from None


class OrderedMap:
    """``[fn(x) for x in items]`` in this process (``serial``), on a local process pool of ``jobs`` workers
    (``pool``, the pool the recipe tasks run on) or on Dask (``dask``: the scheduler at ``scheduler``, or a new
    ``LocalCluster`` of ``jobs`` workers); a context manager whose pool or cluster serves every call until it is
    closed (workers start once). The results come back in the items' order whatever order the tasks finish in,
    so a reduction over them is the same on every executor. ``fn`` must be a module-level function and the items
    picklable; an exception of a task is raised here (the first in the items' order)."""

    def __init__(self, executor: str = "serial", jobs: int = 1, scheduler: str | None = None):
        self.kind = executor_kind(executor, jobs, scheduler)
        self.jobs = max(1, int(jobs))
        self.scheduler = scheduler
        self._pool: PoolExecutor | None = None
        self._dask: DaskExecutor | None = None

    def __enter__(self) -> "OrderedMap":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._dask is not None:
            self._dask.close()
            self._dask = None

    def __call__(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        items = list(items)
        if self.kind == "serial" or not items:
            return [fn(x) for x in items]
        if self.kind == "pool":
            if self._pool is None:
                self._pool = PoolExecutor(self.jobs)
            pool = self._pool._get_pool()
            futures = [pool.submit(call_terminable, fn, x) for x in items]
            try:
                return [f.result() for f in futures]
            except KeyboardInterrupt:  # do not wait for the running items
                self._pool.terminate()
                raise
            except BrokenProcessPool:
                self.close()
                raise ReflectmmError("a worker process died (out of memory?) while mapping "
                                     f"{getattr(fn, '__name__', 'a task')}") from None
        if self._dask is None:
            self._dask = DaskExecutor(self.jobs, self.scheduler)
        client = self._dask._get_client()
        return client.gather([client.submit(fn, x, pure=False, retries=0) for x in items])

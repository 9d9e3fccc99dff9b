"""Run a recipe: plan, execute what is missing or stale, record results, log every task.

The run log is ``<workspace>/.reflectmm/runlog.jsonl``: one JSON object per task and run
(``run``, ``time``, ``recipe``, ``stage``, ``id``, ``cache_key``, ``status``, ``reason``,
``duration``, ``error``).  Status is ``ok``, ``failed``, ``blocked`` or ``skipped``.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.executors import BLOCKED as R_BLOCKED
from reflectmm_cli.recipes.executors import FAILED as R_FAILED
from reflectmm_cli.recipes.executors import OK, Executor, TaskSpec, executor_kind, make_executor
from reflectmm_cli.recipes.plan import (BLOCKED, DEFERRED, ERROR, FAILED, RUN, RUNLOG_FILE, SKIP, Plan, make_plan,
                                        load_hash_memo, save_hash_memo, state_dir, write_record)
from reflectmm_cli.recipes.plan import RUNNING as RUNNING_PRIOR
from reflectmm_cli.recipes.recipe import Recipe, load_recipe, task_priorities

log = logging.getLogger("reflectmm")

SKIPPED = "skipped"


@dataclass
class TaskOutcome:
    stage: str
    id: str | None
    status: str  # ok, failed, blocked, skipped, (dry run:) run, skip, error, deferred
    reason: str = ""
    cache_key: str | None = None
    duration: float = 0.0
    error: str | None = None
    outputs: list[str] = field(default_factory=list)
    worker: str | None = None

    @property
    def tid(self) -> str:
        return self.stage if self.id is None else f"{self.stage}/{self.id}"

    def as_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "id": self.id, "status": self.status, "reason": self.reason,
                "cache_key": self.cache_key, "duration": round(self.duration, 4), "error": self.error,
                "outputs": self.outputs, "worker": self.worker}


@dataclass
class RunReport:
    recipe: str
    workspace: Path
    dry_run: bool
    tasks: list[TaskOutcome]
    plan_seconds: float = 0.0
    run_seconds: float = 0.0
    empty: list[str] = field(default_factory=list)  # per-identity stages whose foreach matched nothing

    def empty_error(self) -> str | None:
        """The one-line refusal of a run in which a stage's foreach matched no identity (None if none did);
        ``reflectmm run`` fails with it unless ``--allow-empty``."""
        if not self.empty:
            return None
        return (f"{self.recipe}: stage{'s' if len(self.empty) > 1 else ''} {', '.join(self.empty)}: foreach "
                f"matched no identity, so nothing ran for {'them' if len(self.empty) > 1 else 'it'} — check the "
                f"inputs it searches, or pass --allow-empty if an empty run is expected")

    def by_status(self, status: str) -> list[TaskOutcome]:
        return [t for t in self.tasks if t.status == status]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for t in self.tasks:
            out[t.status] = out.get(t.status, 0) + 1
        return out

    @property
    def ok(self) -> bool:
        return not any(t.status in (R_FAILED, R_BLOCKED, ERROR, DEFERRED) for t in self.tasks)

    def outputs(self) -> list[str]:
        return [p for t in self.tasks if t.status == OK for p in t.outputs]

    def as_dict(self) -> dict[str, Any]:
        return {"recipe": self.recipe, "workspace": str(self.workspace), "dry_run": self.dry_run,
                "counts": self.counts(), "plan_seconds": round(self.plan_seconds, 4),
                "run_seconds": round(self.run_seconds, 4), "tasks": [t.as_dict() for t in self.tasks],
                "outputs": self.outputs(), "empty": list(self.empty)}


class RunLog:
    """Appends one JSON line per task outcome to ``<workspace>/.reflectmm/runlog.jsonl``."""

    def __init__(self, workspace: Path, recipe: str, overrides: tuple[str, ...] = ()):
        self.path = state_dir(workspace) / RUNLOG_FILE
        self.run_id = uuid.uuid4().hex[:12]
        self.recipe = recipe
        self.overrides = list(overrides)
        self._warned = False

    def write(self, o: TaskOutcome) -> None:
        rec = {"run": self.run_id, "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "recipe": self.recipe, "stage": o.stage, "id": o.id, "cache_key": o.cache_key,
               "status": o.status, "reason": o.reason, "duration": round(o.duration, 4), "error": o.error,
               "worker": o.worker}
        if self.overrides:
            rec["overrides"] = self.overrides
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(json.dumps(rec, sort_keys=True) + "\n")
        except OSError as exc:  # a read-only workspace still reports its (no-op) run
            if not self._warned:
                log.warning("cannot write the run log %s: %s", self.path, exc.strerror or exc)
                self._warned = True


def plan_recipe(recipe: Recipe | str | Path, workspace: Path, **kwargs: Any) -> Plan:
    """Plan without running (uses and updates the workspace's hash memo)."""
    if not isinstance(recipe, Recipe):
        recipe = load_recipe(recipe)
    memo = load_hash_memo(workspace)
    plan = make_plan(recipe, workspace, hash_memo=memo, **kwargs)
    _save_memo(workspace, memo)
    return plan


def _save_memo(workspace: Path, memo: dict[str, Any]) -> None:
    try:
        save_hash_memo(workspace, memo)
    except (OSError, ReflectmmError) as exc:  # a read-only workspace still plans
        log.debug("cannot save the hash memo: %s", exc)


def run_recipe(recipe: Recipe | str | Path, workspace: str | Path, *, dry_run: bool = False,
               force: str | None = None, only: str | None = None, ids: list[str] | None = None,
               executor: str | Executor = "serial", jobs: int = 1, scheduler: str | None = None) -> RunReport:
    """Plan and run a recipe in ``workspace``; the Python API behind ``reflectmm run``.

    Returns a :class:`RunReport`; failed tasks do not raise (check ``report.ok``).
    """
    if not isinstance(recipe, Recipe):
        recipe = load_recipe(recipe)
    if not isinstance(executor, Executor):
        executor_kind(executor, jobs, scheduler)  # a dry run refuses what the run would (--scheduler notaurl)
    workspace = Path(workspace).resolve()
    workspace.mkdir(parents=True, exist_ok=True)
    if dry_run:
        memo = load_hash_memo(workspace)
        t0 = time.perf_counter()
        plan = make_plan(recipe, workspace, force=force, only=only, ids=ids, hash_memo=memo)
        plan_seconds = time.perf_counter() - t0
        _warn_force_outside_only(force, only)
        _save_memo(workspace, memo)
        rows = [TaskOutcome(t.stage_name, t.identity, t.action, t.reason, t.cache_key,
                            outputs=[str(p) for p in t.outputs]) for t in plan.selected()]
        rows += [TaskOutcome(s, None, DEFERRED, _deferred_reason(plan, s)) for s in plan.deferred]
        return _warn_empty(RunReport(recipe.name, workspace, True, rows, plan_seconds, empty=list(plan.empty)))

    with workspace_lock(workspace) as locked:
        memo = load_hash_memo(workspace)
        t0 = time.perf_counter()
        plan = make_plan(recipe, workspace, force=force, only=only, ids=ids, hash_memo=memo)
        plan_seconds = time.perf_counter() - t0
        _warn_force_outside_only(force, only)
        if locked is not True:  # read-only workspace: only a run with nothing to do may go on
            todo = [t.tid for t in plan.selected() if t.action == RUN] + list(plan.deferred)
            if todo:
                raise ReflectmmError(f"cannot write to the workspace ({locked}); {len(todo)} task(s) need to run "
                                     f"({todo[0]}{' ...' if len(todo) > 1 else ''}) — make it writable or use "
                                     f"another --workspace", workspace)
        return _warn_empty(_run_locked(recipe, workspace, memo, plan, plan_seconds, force=force, only=only,
                                       ids=ids, executor=executor, jobs=jobs, scheduler=scheduler))


def _warn_force_outside_only(force: str | None, only: str | None) -> None:
    """``--only A --force=B``: only A's tasks run, so B is not forced; said once, after the plan has checked both
    names."""
    if only is not None and force not in (None, "*", only):
        log.warning("--force=%s: stage %s is not selected by --only %s, so it is not forced (nothing of it runs)",
                    force, force, only)


def _warn_empty(report: RunReport) -> RunReport:
    for s in report.empty:
        log.warning("stage %s: foreach matched no identity; nothing to do for it", s)
    return report


@contextmanager
def workspace_lock(workspace: Path) -> Iterator[bool | str]:
    """Hold ``<workspace>/.reflectmm/lock`` for a run; refuse a second concurrent run in the same workspace.

    Yields True when the lock is held, or a reason string when the workspace cannot be written (read-only
    file system, no permission): the caller may then only do a run that writes nothing.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no locking
        yield True
        return
    path = state_dir(workspace) / "lock"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(path, "a+")
    except OSError as exc:
        if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        yield f"{exc.strerror or exc}: {path}"
        return
    with f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            holder = f.read().strip() or "?"
            raise ReflectmmError(f"another reflectmm run is using this workspace (pid {holder}); "
                                 f"wait for it or use another workspace", workspace) from None
        try:
            f.seek(0)
            f.truncate()
            f.write(str(os.getpid()))
            f.flush()
            yield True
        finally:
            f.seek(0)
            f.truncate()
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _run_locked(recipe: Recipe, workspace: Path, memo: dict[str, Any], plan: Plan, plan_seconds: float, *,
                force: str | None, only: str | None, ids: list[str] | None, executor: str | Executor, jobs: int,
                scheduler: str | None) -> RunReport:
    own_executor = not isinstance(executor, Executor)
    ex = make_executor(executor, jobs, scheduler) if own_executor else executor
    run = _Run(recipe, workspace, memo, plan, RunLog(workspace, recipe.name, recipe.overrides),
               dict(force=force, only=only, ids=ids))
    t1 = time.perf_counter()
    try:
        while True:
            batch = run.take_batch()
            if batch:
                run.execute(batch, ex)
                run.submitted &= set(run.outcomes)  # handed out but not run by the executor: offer them again
            _save_memo(workspace, memo)
            if batch and any(t.action == RUN and t.tid not in run.outcomes for t in run.plan.selected()):
                continue  # planned while the last batch ran but not taken by its executor
            if not run.plan.deferred or not batch:
                break
            # some stages discover their identities from upstream outputs: plan again
            run.replan()
        for s in run.plan.deferred:
            o = TaskOutcome(s, None, R_BLOCKED, _deferred_reason(run.plan, s), error=_deferred_reason(run.plan, s))
            run.outcomes[s] = o
            run.runlog.write(o)
    finally:
        if own_executor:
            ex.close()
    plan = run.plan
    order = {tid: i for i, tid in enumerate(plan.tasks)}
    ordered = sorted(run.outcomes.values(), key=lambda o: order.get(o.tid, len(order)))
    return RunReport(recipe.name, workspace, False, ordered, plan_seconds + run.plan_seconds,
                     time.perf_counter() - t1, empty=list(plan.empty))


class _Run:
    """The state of one run: its current plan, the outcomes so far and the tasks handed to the executor.

    A stage whose identities are found in its upstream's outputs is planned as soon as those outputs exist —
    when the last task of its upstream stages finishes — and its tasks join the running batch, so the other
    cores do not wait for the whole batch to end (:meth:`on_result`)."""

    def __init__(self, recipe: Recipe, workspace: Path, memo: dict[str, Any], plan: Plan, runlog: RunLog,
                 plan_kwargs: dict[str, Any]):
        self.recipe, self.workspace, self.memo, self.plan, self.runlog = recipe, workspace, memo, plan, runlog
        self.plan_kwargs = plan_kwargs
        self.outcomes: dict[str, TaskOutcome] = {}
        self.submitted: set[str] = set()
        self.tried: set[str] = set()  # deferred stages planned again once their upstream had finished
        self.plan_seconds = 0.0
        self.total = 0
        self.finished = 0

    def take_batch(self) -> list[TaskSpec]:
        """Record the plan's skipped/erroneous tasks; return the specs to execute that are not handed out yet."""
        batch = _outcomes_from_plan(self.plan, self.outcomes, self.runlog, self.submitted)
        self.submitted.update(spec.tid for spec in batch)
        self.total += len(batch)
        return batch

    def replan(self) -> None:
        running = {tid: RUNNING_PRIOR for tid in self.submitted if tid not in self.outcomes}
        prior = {tid: o.status for tid, o in self.outcomes.items()} | running
        t0 = time.perf_counter()
        self.plan = make_plan(self.recipe, self.workspace, hash_memo=self.memo, prior=prior, **self.plan_kwargs)
        self.plan_seconds += time.perf_counter() - t0

    def _ready(self) -> list[str]:
        """Deferred stages whose upstream stages are planned and all finished (not tried yet)."""
        plan = self.plan
        ready = []
        for s in plan.deferred:
            ups = plan.recipe.stages[s].upstream()
            if s not in self.tried and all(u not in plan.deferred and all(
                    tid in self.outcomes for tid in plan.stage_tasks.get(u, [])) for u in ups):
                ready.append(s)
        return ready

    def execute(self, batch: list[TaskSpec], ex: Executor) -> None:
        log.info("running %d task(s) with the %s executor", len(batch), ex.name)
        ex.run(batch, self.on_result)

    def on_result(self, res: dict[str, Any]) -> list[TaskSpec]:
        t = self.plan.tasks[res["tid"]]
        status = res["status"]
        self.finished += 1
        o = TaskOutcome(t.stage_name, t.identity, status, t.reason, res.get("cache_key"), res.get("duration", 0.0),
                        res.get("error"), list(res.get("outputs") or []), res.get("worker"))
        if status == OK:
            for path, entry in (res.get("hashes") or {}).items():  # digests of the inputs the worker hashed
                self.memo[path] = entry
            try:
                write_record(self.workspace, t.stage_name, t.identity, res["cache_key"], res.get("key_doc"),
                             [Path(p) for p in t.outputs], self.memo)
            except (OSError, ReflectmmError) as exc:
                log.warning("%s: cannot write its record: %s", t.tid, exc)
            log.info("[%d/%d] done %s (%.2f s)", self.finished, self.total, t.tid, o.duration)
        else:
            log.info("[%d/%d] %s %s: %s", self.finished, self.total, status.upper(), t.tid, o.error)
        self.outcomes[t.tid] = o
        self.runlog.write(o)
        ready = self._ready()
        if not ready:
            return []
        self.tried.update(ready)
        self.replan()
        more = self.take_batch()
        if more:
            log.info("planned %s: %d more task(s)", ", ".join(ready), len(more))
        return more


def _deferred_reason(plan: Plan, stage: str) -> str:
    ups = plan.recipe.stages[stage].upstream()
    waiting = [u for u in ups if u in plan.deferred]
    if waiting:
        return f"waits for {', '.join(waiting)} (identities not known yet)"
    return f"identities are found once {', '.join(ups) or 'upstream'} has run"


def _outcomes_from_plan(plan: Plan, outcomes: dict[str, TaskOutcome], runlog: RunLog,
                        handed_out: set[str] | frozenset[str] = frozenset()) -> list[TaskSpec]:
    """Record skipped/erroneous tasks; return the specs to execute (not those ``handed_out`` already, which
    still count as upstream of the new ones)."""
    batch: list[TaskSpec] = []
    runnable = {t.tid for t in plan.selected() if t.action == RUN and t.tid not in outcomes}
    priorities = task_priorities(plan.recipe)
    for t in plan.selected():
        if t.tid in outcomes or t.tid in handed_out:
            continue
        if t.action == SKIP:
            o = TaskOutcome(t.stage_name, t.identity, SKIPPED, t.reason, t.cache_key,
                            outputs=[str(p) for p in t.outputs])
        elif t.action in (ERROR, FAILED):
            o = TaskOutcome(t.stage_name, t.identity, R_FAILED, t.reason, t.cache_key, error=t.reason)
        elif t.action == BLOCKED:
            o = TaskOutcome(t.stage_name, t.identity, R_BLOCKED, t.reason, error=t.reason)
        elif t.action == RUN and t.tid in runnable:
            key_doc = t.key_doc
            batch.append(TaskSpec(t.tid, t.verb, t.ctx, [d for d in t.deps if d in runnable], key_doc,
                                  t.resources, priority=priorities.get(t.stage_name, 0), inputs_used=t.inputs_used))
            continue
        else:
            continue
        outcomes[t.tid] = o
        if t.action != SKIP or t.reason != "not selected":
            runlog.write(o)
    return batch

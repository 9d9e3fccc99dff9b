"""The planner: a recipe + a workspace -> tasks (stage, identity) that run or skip, and why.

A task is skipped when its cache key (:func:`reflectmm_cli.stages.cache_key_doc`: hash
version, verb, stage version, invalidating params, sha256 of every input file) is
unchanged *and* its outputs are present and valid: the primary output's meta carries
that cache key (NPZ/EXR artifacts), or the sidecar record in
``<workspace>/.reflectmm/records/`` does and the outputs' sha256 still match.

File hashes are memoised by (path, size, mtime_ns) in ``<workspace>/.reflectmm/hashes.json``
so a no-op rerun reads no file content it has hashed before.
"""

from __future__ import annotations

import glob
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from reflectmm_cli.artifacts import atomic_write_text, canonical_json, read_meta
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.recipe import ALL_FOUND, Recipe, Ref, StageSpec
from reflectmm_cli.params import ParamError
from reflectmm_cli.stages import (NON_INVALIDATING, Stage, StageContext, cache_key_doc, expand_pattern_paths,
                                  file_digest, get_stage, key_of_doc)
from reflectmm_cli.workspace import check_id

log = logging.getLogger("reflectmm")

STATE_DIR = ".reflectmm"
HASHES_FILE = "hashes.json"
RECORDS_DIR = "records"
RUNLOG_FILE = "runlog.jsonl"

# task actions
RUN, SKIP, BLOCKED, ERROR, DEFERRED, FAILED = "run", "skip", "blocked", "error", "deferred", "failed"
DONE = "ok"  # a prior status (make_plan's ``prior``): the task ran successfully earlier in this run
RUNNING = "running"  # a prior status: the task is running now (its outputs are not to be looked at yet)


def state_dir(workspace: Path) -> Path:
    return Path(workspace) / STATE_DIR


def task_id(stage: str, identity: str | None) -> str:
    return stage if identity is None else f"{stage}/{identity}"


# --------------------------------------------------------------------------- persistent state

def load_hash_memo(workspace: Path) -> dict[str, Any]:
    """The stat-keyed sha256 memo of the workspace (empty if none or unreadable)."""
    p = state_dir(workspace) / HASHES_FILE
    try:
        memo = json.loads(p.read_text())
        return memo if isinstance(memo, dict) else {}
    except (OSError, ValueError):
        return {}


def save_hash_memo(workspace: Path, memo: dict[str, Any]) -> None:
    live = {k: v for k, v in memo.items() if os.path.exists(k)}
    atomic_write_text(state_dir(workspace) / HASHES_FILE, json.dumps(live, sort_keys=True, separators=(",", ":")))


def record_path(workspace: Path, stage: str, identity: str | None) -> Path:
    return state_dir(workspace) / RECORDS_DIR / stage / f"{identity if identity is not None else '_'}.json"


def read_record(workspace: Path, stage: str, identity: str | None) -> dict[str, Any] | None:
    try:
        rec = json.loads(record_path(workspace, stage, identity).read_text())
        return rec if isinstance(rec, dict) else None
    except (OSError, ValueError):
        return None


def write_record(workspace: Path, stage: str, identity: str | None, cache_key: str, key_doc: dict[str, Any] | None,
                 outputs: list[Path], memo: dict[str, Any] | None) -> None:
    """Sidecar record of a successful task: its key, the key's parts and its outputs' sha256."""
    outs = []
    for p in outputs:
        p = Path(p)
        if p.is_file():
            outs.append({"path": os.path.relpath(p, workspace), "sha256": file_digest(p, memo)})
    rec = {"cache_key": cache_key, "doc": key_doc, "outputs": outs}
    atomic_write_text(record_path(workspace, stage, identity), canonical_json(rec))


# --------------------------------------------------------------------------- plan data

@dataclass
class Task:
    """One stage run for one identity (or once), with its planned action and reason."""

    tid: str
    stage_name: str
    verb: str
    identity: str | None
    ctx: StageContext | None
    deps: list[str] = field(default_factory=list)
    resources: dict[str, Any] = field(default_factory=dict)
    action: str = RUN
    reason: str = ""
    cache_key: str | None = None
    key_doc: dict[str, Any] | None = None
    outputs: list[Path] = field(default_factory=list)
    selected: bool = True
    outputs_error: str | None = None
    #: the memo entries ``[size, mtime_ns, sha256]`` of the input files ``key_doc`` was computed from
    inputs_used: dict[str, Any] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        return {"stage": self.stage_name, "id": self.identity, "action": self.action, "reason": self.reason,
                "cache_key": self.cache_key, "outputs": [str(p) for p in self.outputs]}


@dataclass
class Plan:
    recipe: Recipe
    workspace: Path
    tasks: dict[str, Task]
    stage_tasks: dict[str, list[str]]
    deferred: list[str]
    empty: list[str] = field(default_factory=list)  # per-identity stages whose foreach matched no identity

    def selected(self) -> list[Task]:
        return [t for t in self.tasks.values() if t.selected]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for t in self.selected():
            out[t.action] = out.get(t.action, 0) + 1
        return out


class _PlanError(Exception):
    """A problem with one task (it fails at run time; other tasks go on)."""


# --------------------------------------------------------------------------- planner

def _defer(name: str, outside_only: bool, deferred: list[str], unplanned: set[str]) -> None:
    """A stage whose identities are not known yet: deferred (planned again once its upstream has run), or, outside
    ``--only``, left unplanned (it would not run in this run, so nothing waits for it and nothing is blocked)."""
    if outside_only:
        unplanned.add(name)
    else:
        deferred.append(name)


def make_plan(recipe: Recipe, workspace: Path, *, force: str | None = None, only: str | None = None,
              ids: list[str] | None = None, hash_memo: dict[str, Any] | None = None,
              prior: dict[str, str] | None = None) -> Plan:
    """Plan a run.

    Args:
        force: ``"*"`` forces every task, a stage name forces that stage's tasks.
        only: run only this stage's tasks; upstream outputs must already exist.
        ids: restrict per-identity stages to these identities; aggregate stages that
            depend on per-identity stages are then not run.
        hash_memo: the stat-keyed sha256 memo (updated in place).
        prior: task id -> status from an earlier round of the same run (failed tasks are
            not retried, their dependents are blocked; ``"running"`` tasks stay to run, unexamined).
    """
    workspace = Path(workspace).resolve()
    prior = prior or {}
    if ids is not None:
        ids = [check_id(i, "--ids") for i in ids]
    stages: dict[str, Stage] = {}
    for name, spec in recipe.stages.items():
        try:
            stages[name] = get_stage(spec.verb)
        except ReflectmmError as exc:
            raise ReflectmmError(f"[stages.{name}]: {exc}", recipe.path) from None
        stage_params(spec, stages[name], recipe.path)  # validate before anything runs: one line per problem
        try:
            stages[name].check_roles(spec.inputs, f"[stages.{name}]")
        except ReflectmmError as exc:
            raise ReflectmmError(str(exc), recipe.path) from None
        if stages[name].per_identity and not spec.per_identity:
            raise ReflectmmError(f"[stages.{name}]: verb '{spec.verb}' runs per identity; give foreach "
                                 f'(a list of ids, {{ file = "ids.txt" }} or "{ALL_FOUND}")', recipe.path)
    _check_defaults(recipe, stages)
    for opt, val in (("--force", force), ("--only", only)):
        if val is not None and val != "*" and val not in recipe.stages:
            raise ReflectmmError(f"{opt}: unknown stage '{val}' (stages: {', '.join(recipe.stages)})")

    order = recipe.order()
    per_id_closure: dict[str, bool] = {}
    for name in order:
        spec = recipe.stages[name]
        per_id_closure[name] = spec.per_identity or any(per_id_closure[u] for u in spec.upstream())

    tasks: dict[str, Task] = {}
    stage_tasks: dict[str, list[str]] = {}
    deferred: list[str] = []
    empty: list[str] = []
    unplanned: set[str] = set()  # deferred stages outside --only: they would not run, so they wait for nothing
    recipe_ids: set[str] = set()  # every identity of the per-identity stages, before --ids selects
    # each stage's identities before --ids selects (None: not known, an upstream stage was left without tasks by
    # --ids): a stage that takes its identities from its upstream has them, even when --ids leaves it no task
    all_ids: dict[str, list[str | None] | None] = {}
    for name in order:
        spec, stage = recipe.stages[name], stages[name]
        outside = only is not None and only != name
        if any(u in deferred or u in unplanned for u in spec.upstream()):
            _defer(name, outside, deferred, unplanned)
            continue
        selected = (only is None or only == name)
        if ids is not None and not spec.per_identity and per_id_closure[name]:
            selected = False  # an aggregate over identities is never built from a --ids subset
        stage_ids = _stage_ids(recipe, spec, stage, workspace, tasks, stage_tasks, hash_memo, all_ids)
        if stage_ids is _DEFER:
            _defer(name, outside, deferred, unplanned)
            continue
        if stage_ids is _NARROWED:  # --ids left its upstream without tasks: none for it either, and not "empty"
            all_ids[name], stage_tasks[name] = None, []
            continue
        _check_ids(stage_ids, spec, recipe.path)
        all_ids[name] = list(stage_ids)
        if spec.per_identity and not stage_ids:
            empty.append(name)
        if ids is not None and spec.per_identity:
            recipe_ids.update(i for i in stage_ids if i is not None)
            wanted = set(ids)
            stage_ids = [i for i in stage_ids if i in wanted]
        stage_tasks[name] = []
        for ident in stage_ids:
            t = _make_task(spec, stage, workspace, ident, tasks, stage_tasks)
            t.selected = selected
            tasks[t.tid] = t
            stage_tasks[name].append(t.tid)
            if t.tid in prior and prior[t.tid] in (FAILED, BLOCKED):
                t.action = FAILED if prior[t.tid] == FAILED else BLOCKED
                t.reason = f"{'failed' if t.action == FAILED else 'blocked'} earlier in this run"
                continue
            if prior.get(t.tid) == RUNNING:
                t.action, t.reason = RUN, "running"
                continue
            if prior.get(t.tid) == DONE:
                # ran earlier in this run: its outputs are fresh, so it neither runs again (even when
                # forced) nor keeps a deferred "all found" stage waiting
                t.action, t.reason = SKIP, "ran earlier in this run"
                continue
            _decide(t, stage, tasks, workspace, hash_memo, forced=(force == "*" or force == name))
    if ids is not None and not deferred:
        known = {t.identity for t in tasks.values()}
        unknown = [i for i in ids if i not in known]
        named = ", ".join(unknown[:10]) + (" ..." if len(unknown) > 10 else "")
        if unknown and len(unknown) == len(ids):  # a typo: the run would do the shared stages and exit 0
            have = sorted(recipe_ids)
            raise ReflectmmError(f"--ids: no stage has identit{'y' if len(unknown) == 1 else 'ies'} {named} (the "
                                 f"recipe's: {', '.join(have[:10]) + (' ...' if len(have) > 10 else '') or 'none'})")
        if unknown:
            log.warning("--ids: no stage has identit%s %s", "y" if len(unknown) == 1 else "ies", named)
    return Plan(recipe, workspace, tasks, stage_tasks, deferred, empty)


_DEFER = object()
_NARROWED = object()  # the stage's identities cannot be known because --ids left an upstream stage without tasks


def _check_defaults(recipe: Recipe, stages: dict[str, Stage]) -> None:
    """A ``[defaults]`` param that no verb declares is a typo (it was dropped silently): one line naming the recipe
    file.  A name that some verb declares stays allowed, even if no stage of this recipe runs that verb."""
    from reflectmm_cli.stages.registry import all_stages

    known: set[str] = set(NON_INVALIDATING)
    if any(st.params is None or st.open_params for st in stages.values()):
        return  # a stage of this recipe takes any param: nothing can be said
    for st in all_stages().values():
        if st.params is not None:
            known |= {p.name for p in st.params}
    unknown = [k for k in recipe.defaults if k not in known]
    if unknown:
        raise ReflectmmError(f"[defaults]: {', '.join(unknown)} is not a param of any verb (a typo?)", recipe.path)


def stage_params(spec: StageSpec, stage: Stage, recipe_path: Path | None,
                 refs: dict[str, Any] | None = None) -> dict[str, Any]:
    """A stage's params as the command line would resolve them: validated against the verb's declaration,
    defaults filled, canonical.  ``[defaults]`` params the verb does not declare are left out; an own param it
    does not declare, or a bad value, is a one-line error naming the recipe file and the stage.  ``refs`` are
    the resolved paths of params that reference other stages (before planning they count as given)."""
    declared = None if stage.params is None else {p.name for p in stage.params}
    given: dict[str, Any] = {}
    for k, v in spec.params.items():
        if k in spec.param_refs:
            v = (refs or {}).get(k)
        if (declared is not None and not stage.open_params and k not in spec.own_params and k not in declared
                and k not in NON_INVALIDATING):
            continue  # a [defaults] param for other verbs
        given[k] = v
    try:
        return stage.resolve(given)
    except ParamError as exc:
        raise ReflectmmError(f"[stages.{spec.name}] params: {exc}", recipe_path) from None


def _check_ids(stage_ids: list[str | None], spec: StageSpec, recipe_path: Path | None) -> None:
    """Every identity of a stage is a safe id (:func:`~reflectmm_cli.workspace.check_id`), whether listed,
    read from a file, discovered or taken from the upstream stage: a one-line error before anything runs."""
    where = f"[stages.{spec.name}] foreach" + (f' = "{ALL_FOUND}"' if spec.foreach == ALL_FOUND else "")
    for ident in stage_ids:
        if ident is not None:
            try:
                check_id(ident, where)
            except ReflectmmError as exc:
                raise ReflectmmError(str(exc), recipe_path) from None


def _stage_ids(recipe: Recipe, spec: StageSpec, stage: Stage, workspace: Path, tasks: dict[str, Task],
               stage_tasks: dict[str, list[str]], memo: dict[str, Any] | None,
               all_ids: dict[str, list[str | None] | None]) -> Any:
    """The stage's identities before --ids selects (``[None]`` for an aggregate), or :data:`_DEFER` (known once
    upstream outputs exist), or :data:`_NARROWED`."""
    narrowed = any(all_ids.get(u) is None or (all_ids[u] and not stage_tasks.get(u)) for u in spec.upstream()
                   if recipe.stages[u].per_identity)
    fe = spec.foreach
    if fe is None:
        return [None]
    if isinstance(fe, list):
        return list(fe)
    if isinstance(fe, dict):
        from reflectmm_cli.params import parse_ids

        p = Path(fe["file"])
        p = p if p.is_absolute() else workspace / p
        if not p.is_file():
            raise ReflectmmError(f"[stages.{spec.name}] foreach file not found: {p}", recipe.path)
        try:
            return parse_ids(None, p)
        except ReflectmmError as exc:
            raise ReflectmmError(f"[stages.{spec.name}] foreach file {exc}", recipe.path) from None
    # "all found"
    if stage.discover_ids is not None:
        upstream_tasks = [tid for u in spec.upstream() for tid in stage_tasks.get(u, [])]
        pending = any(tasks[t].action in (RUN, ERROR, BLOCKED, FAILED) if tasks[t].selected else
                      not all(Path(p).exists() for p in tasks[t].outputs) for t in upstream_tasks)
        ctx = stage.context(workspace=workspace, stage_name=spec.name, identity=None,
                            params=stage_params(spec, stage, recipe.path))
        # discovery sees the stage's inputs as an aggregate would; per-identity paths ({id}) are left out
        lenient = StageSpec(spec.name, spec.verb, spec.params, {
            role: [it for it in items if isinstance(it, Ref) or "{id}" not in it]
            for role, items in spec.inputs.items()}, spec.foreach, spec.resources, spec.param_refs,
            spec.own_params)
        try:
            inputs, _ = _resolve_inputs(lenient, ctx, workspace, tasks, stage_tasks, identity=None, aggregate=True)
        except _PlanError as exc:
            if pending:
                return _DEFER
            if narrowed:
                return _NARROWED
            raise ReflectmmError(f'[stages.{spec.name}] foreach = "{ALL_FOUND}": {exc}', recipe.path) from None
        try:
            found = stage.discover_ids(ctx.with_(inputs=inputs))
        except (ReflectmmError, OSError) as exc:
            if pending:  # e.g. the folder to search is written by an upstream task that has to run
                return _DEFER
            raise ReflectmmError(f'[stages.{spec.name}] foreach = "{ALL_FOUND}": {exc}', recipe.path) from None
        if found is not None and pending:
            return _DEFER  # the identities are known once the upstream outputs exist
        if found is not None:
            return [str(i) for i in found]  # none found: Plan.empty, reported by the runner
    for u in spec.upstream():
        if recipe.stages[u].per_identity:
            return _NARROWED if all_ids.get(u) is None else list(all_ids[u])
    raise ReflectmmError(f'[stages.{spec.name}] foreach = "{ALL_FOUND}": verb \'{spec.verb}\' did not discover '
                         f"identities and no upstream stage runs per identity; list the ids", recipe.path)


def _make_task(spec: StageSpec, stage: Stage, workspace: Path, ident: str | None,
               tasks: dict[str, Task], stage_tasks: dict[str, list[str]]) -> Task:
    tid = task_id(spec.name, ident)
    params = stage_params(spec, stage, None)
    device = str(params.get("device", "cpu"))
    ctx = stage.context(workspace=workspace, stage_name=spec.name, identity=ident, params=params, device=device)
    task = Task(tid, spec.name, spec.verb, ident, ctx, resources=dict(spec.resources))
    try:
        inputs, deps = _resolve_inputs(spec, ctx, workspace, tasks, stage_tasks, ident, aggregate=ident is None)
        refs: dict[str, Any] = {}
        for pname, ref in spec.param_refs.items():
            paths, pdeps = _resolve_ref(ref, spec, workspace, tasks, stage_tasks, ident, ident is None)
            refs[pname] = str(paths[0]) if len(paths) == 1 else [str(p) for p in paths]
            deps += [d for d in pdeps if d not in deps]
        if refs:
            params = stage_params(spec, stage, None, refs)
        task.ctx = ctx.with_(inputs=inputs, params=params)
        task.deps = deps
        try:
            task.outputs = [Path(p) for p in stage.expected_outputs(task.ctx)]
        except Exception as exc:  # noqa: BLE001 - a hook may need inputs that do not exist yet
            task.outputs = [task.ctx.output_path()]
            task.outputs_error = f"cannot list the stage's outputs: {exc}"
    except _PlanError as exc:
        task.action, task.reason = ERROR, str(exc)
        task.outputs = _listed_outputs(stage, ctx)
    return task


def _listed_outputs(stage: Stage, ctx: StageContext) -> list[Path]:
    """The outputs a task would write, listed without its inputs where the stage can (named outputs such as
    ``rig`` stay resolvable for the stages downstream of a task that is not planned, e.g. an aggregate left out
    by ``--ids``); else its primary output."""
    try:
        return [Path(p) for p in stage.expected_outputs(ctx)]
    except Exception:  # noqa: BLE001 - a hook may need the inputs it could not get
        return [ctx.output_path()]


def _resolve_inputs(spec: StageSpec, ctx: StageContext, workspace: Path, tasks: dict[str, Task],
                    stage_tasks: dict[str, list[str]], identity: str | None, aggregate: bool
                    ) -> tuple[dict[str, list[Path]], list[str]]:
    inputs: dict[str, list[Path]] = {}
    deps: list[str] = []
    for role, items in spec.inputs.items():
        paths: list[Path] = []
        for it in items:
            if isinstance(it, Ref):
                got, d = _resolve_ref(it, spec, workspace, tasks, stage_tasks, identity, aggregate)
                paths += got
                deps += [x for x in d if x not in deps]
            else:
                paths += _resolve_path(it, role, workspace, identity)
        inputs[role] = paths
    return inputs, deps


def _resolve_path(text: str, role: str, workspace: Path, identity: str | None) -> list[Path]:
    if "{id}" in text:
        if identity is None:
            raise _PlanError(f"input '{role}': '{text}' uses {{id}} but the stage has no foreach")
        text = text.replace("{id}", identity)
    p = Path(os.path.expanduser(text))
    p = p if p.is_absolute() else workspace / p
    if glob.has_magic(str(p)):
        found = sorted(Path(q) for q in glob.glob(str(p)))
        if not found:
            raise _PlanError(f"input '{role}': no file matches {p}")
        return found
    if not p.exists():
        raise _PlanError(f"input '{role}' not found: {p}")
    return [p]


def _resolve_ref(ref: Ref, spec: StageSpec, workspace: Path, tasks: dict[str, Task],
                 stage_tasks: dict[str, list[str]], identity: str | None, aggregate: bool
                 ) -> tuple[list[Path], list[str]]:
    producer = stage_tasks.get(ref.stage, [])
    if not producer:
        raise _PlanError(f"{ref}: stage '{ref.stage}' has no tasks (no identities selected?)")
    prod_per_id = tasks[producer[0]].identity is not None
    if ref.what == "dir":
        folder = tasks[producer[0]].ctx.output_path().parent if tasks[producer[0]].ctx else workspace / ref.stage
        sub = ref.sub or ""
        if "{id}" in sub:
            if identity is None:
                raise _PlanError(f"{ref} uses {{id}} but stage '{spec.name}' has no foreach")
            sub = sub.replace("{id}", identity)
        path = folder / sub.lstrip("/") if sub.strip("/") else folder
        # a glob pattern inside the folder: its matches once they exist, else the pattern, which the task
        # expands when it runs (StageContext.with_patterns_expanded)
        return expand_pattern_paths([path]), list(producer)
    if prod_per_id and not aggregate:
        tid = task_id(ref.stage, identity)
        if tid not in tasks:
            raise _PlanError(f"{ref}: stage '{ref.stage}' has no identity '{identity}'")
        chosen = [tid]
    else:
        chosen = list(producer)
    paths: list[Path] = []
    for tid in chosen:
        outs = tasks[tid].outputs
        if ref.what == "output":
            paths.append(outs[0])
        else:
            match = [p for p in outs if p.name == ref.name or p.stem == ref.name]
            if not match:
                raise _PlanError(f"{ref}: stage '{ref.stage}' has no output named '{ref.name}' "
                                 f"(outputs: {', '.join(p.name for p in outs)})")
            paths.append(match[0])
    return paths, chosen


def _decide(t: Task, stage: Stage, tasks: dict[str, Task], workspace: Path, memo: dict[str, Any] | None,
            forced: bool) -> None:
    if t.action == ERROR:
        return
    if not t.selected:
        t.action, t.reason = SKIP, "not selected"
        return
    for d in t.deps:
        up = tasks[d]
        if up.selected and up.action in (ERROR, BLOCKED, FAILED):
            t.action, t.reason = BLOCKED, f"upstream {d} {'failed' if up.action != BLOCKED else 'is blocked'}"
            return
        if not up.selected:
            missing = [p for p in up.outputs if not Path(p).exists()]
            if missing:
                t.action = ERROR
                t.reason = f"needs {d}, whose output {missing[0]} is missing (not selected by --only/--ids)"
                return
    upstream_runs = [d for d in t.deps if tasks[d].selected and tasks[d].action == RUN]
    if upstream_runs:
        t.action = RUN
        more = f" +{len(upstream_runs) - 1}" if len(upstream_runs) > 1 else ""
        t.reason = "forced" if forced else f"upstream reruns ({upstream_runs[0]}{more})"
        return  # the key is computed by the worker, once the new inputs exist
    if forced:
        t.action, t.reason = RUN, "forced"
    if t.outputs_error:
        t.action, t.reason = ERROR, t.outputs_error
        return
    try:
        used: dict[str, Any] = {}
        doc = cache_key_doc(stage, t.ctx, memo, used)
    except (FileNotFoundError, ReflectmmError) as exc:
        t.action, t.reason = ERROR, f"cannot hash inputs: {exc}"
        return
    t.key_doc, t.cache_key, t.inputs_used = doc, key_of_doc(doc), used
    if forced:
        return
    missing = [p for p in t.outputs if not Path(p).exists()]
    if missing:
        t.action, t.reason = RUN, "no output" if len(missing) == len(t.outputs) else f"output missing: {missing[0]}"
        return
    primary = Path(t.outputs[0])
    record = read_record(workspace, t.stage_name, t.identity)
    meta_key = None
    if primary.suffix.lower() in (".npz", ".exr") and primary.is_file():
        try:
            meta = read_meta(primary)
        except ReflectmmError as exc:
            t.action, t.reason = RUN, f"output invalid ({_short(exc)})"
            return
        meta_key = meta.get("cache_key")
        if meta_key == t.cache_key:
            stale = stage.stale(t.ctx, meta) if stage.stale is not None else None
            t.action, t.reason = (RUN, stale) if stale else (SKIP, "up to date")
            return
        if meta_key is not None:
            t.action, t.reason = RUN, _why(record, doc, meta)
            return
    # no key in the output itself: the sidecar record vouches for the outputs
    if record and record.get("cache_key") == t.cache_key:
        for o in record.get("outputs", []):
            p = workspace / o["path"]
            try:
                if file_digest(p, memo) != o["sha256"]:
                    t.action, t.reason = RUN, f"output modified: {p}"
                    return
            except FileNotFoundError:
                t.action, t.reason = RUN, f"output missing: {p}"
                return
        t.action, t.reason = SKIP, "up to date"
        return
    t.action = RUN
    t.reason = _why(record, doc, None) if record else "no record of this output (unknown provenance)"


def _short(exc: Exception) -> str:
    msg = str(exc)
    return msg.split(": ", 1)[1] if ": " in msg else msg


def _why(record: dict[str, Any] | None, doc: dict[str, Any], meta: dict[str, Any] | None) -> str:
    old = (record or {}).get("doc")
    if isinstance(old, dict):
        if old.get("verb") != doc["verb"]:
            return f"verb changed ({old.get('verb')} -> {doc['verb']})"
        if old.get("stage_version") != doc["stage_version"]:
            return f"stage version changed ({old.get('stage_version')} -> {doc['stage_version']})"
        if old.get("hash") != doc["hash"]:
            return "cache key definition changed"
        op, np_ = old.get("params") or {}, doc["params"]
        changed = sorted(k for k in set(op) | set(np_) if op.get(k) != np_.get(k))
        if changed:
            return f"params changed ({', '.join(changed)})"
        oi, ni = old.get("inputs") or {}, doc["inputs"]
        roles = sorted(r for r in set(oi) | set(ni) if oi.get(r) != ni.get(r))
        if roles:
            return f"input changed ({', '.join(roles)})"
        return "cache key changed"
    if meta is not None:
        prod = meta.get("producer") or {}
        if prod.get("stage_version") not in (None, doc["stage_version"]):
            return f"stage version changed ({prod.get('stage_version')} -> {doc['stage_version']})"
        mp = meta.get("params") or {}
        changed = sorted(k for k in set(mp) | set(doc["params"]) if mp.get(k) != doc["params"].get(k))
        if changed:
            return f"params changed ({', '.join(changed)})"
        return "input changed"
    return "cache key changed"

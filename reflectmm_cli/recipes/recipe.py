"""Recipe files: parsing and validation of ``reflectmm.recipe/1`` TOML.

A recipe names stages, the verb each runs, its params, its inputs (references to other
stages' outputs or workspace paths) and whether it fans out over identities::

    schema = "reflectmm.recipe/1"
    name = "demo"

    [defaults]                      # merged into every stage's params (a stage's own params win)
    device = "cpu"

    [stages.manifest]
    verb = "checksum"
    foreach = ["001", "002"]        # or { file = "ids.txt" } or "all found"
    inputs = { files = "data/{id}" }
    params = { }
    resources = { cpus = 1, memory = "2GB" }

    [stages.summary]
    verb = "checksum"
    inputs = { files = "@manifest.output" }   # every identity's output

Paths are relative to the workspace; ``{id}`` is replaced by the identity in per-identity
stages.  See docs/recipes.md for the full semantics.
"""

from __future__ import annotations

import difflib
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import named_twice

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

RECIPE_SCHEMA = "reflectmm.recipe"
RECIPE_MAJOR = 1

ALL_FOUND = "all found"

#: a stage name: no dot, which would make a reference such as ``@a.output.output`` ambiguous
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_-]*$")
#: ``@stage.output``, ``@stage.outputs.<name>``, ``@stage.dir`` or ``@stage.dir/sub/path``.
_REF_RE = re.compile(r"^@(?P<stage>[A-Za-z0-9_][A-Za-z0-9_-]*)\.(?P<what>output|outputs\.(?P<name>[^/]+)|dir)"
                     r"(?P<sub>/.*)?$")

_STAGE_KEYS = {"verb", "params", "inputs", "foreach", "resources", "priority", "help", "description"}
_TOP_KEYS = {"schema", "name", "description", "defaults", "stages"}


@dataclass(frozen=True)
class Ref:
    """A reference to another stage's output(s): ``@stage.output`` / ``.outputs.NAME`` / ``.dir[/sub]``."""

    stage: str
    what: str  # "output", "outputs", "dir"
    name: str | None = None
    sub: str | None = None

    def __str__(self) -> str:
        base = f"@{self.stage}." + ("outputs." + self.name if self.what == "outputs" else self.what)
        return base + (self.sub or "")


@dataclass
class StageSpec:
    """One ``[stages.<name>]`` table."""

    name: str
    verb: str
    params: dict[str, Any] = field(default_factory=dict)
    #: role -> list of items, each a :class:`Ref` or a path string (may contain ``{id}`` and globs).
    inputs: dict[str, list[Ref | str]] = field(default_factory=dict)
    #: None (runs once), a list of ids, ``{"file": path}``, or :data:`ALL_FOUND`.
    foreach: list[str] | dict[str, str] | str | None = None
    resources: dict[str, Any] = field(default_factory=dict)
    #: params whose string values are references (name -> Ref), resolved to paths at plan time.
    param_refs: dict[str, Ref] = field(default_factory=dict)
    #: names given in the stage's own ``params`` table (the rest came from ``[defaults]``): an own param the
    #: verb does not declare is an error, a ``[defaults]`` param it does not declare is not for it.
    own_params: frozenset[str] = frozenset()
    #: the stage's declared priority (``priority = N``, default 0): among ready tasks a higher one starts first,
    #: before the runner's own order (:func:`task_priorities`)
    priority: int = 0

    @property
    def per_identity(self) -> bool:
        return self.foreach is not None

    def upstream(self) -> list[str]:
        """Names of the stages this one references (inputs and params), in first-seen order."""
        seen: list[str] = []
        for items in self.inputs.values():
            for it in items:
                if isinstance(it, Ref) and it.stage not in seen:
                    seen.append(it.stage)
        for ref in self.param_refs.values():
            if ref.stage not in seen:
                seen.append(ref.stage)
        return seen


@dataclass
class Recipe:
    path: Path
    name: str
    defaults: dict[str, Any]
    stages: dict[str, StageSpec]
    #: the ``STAGE.PARAM=VALUE`` overrides applied to the file (``reflectmm run --set``), in order
    overrides: tuple[str, ...] = ()

    def order(self) -> list[str]:
        """Stage names in a topological order (ties keep the file's order)."""
        return topological_order(self)


def parse_ref(value: str, where: str, path: Path) -> Ref | None:
    """A :class:`Ref` if ``value`` starts with ``@``, else None; a clear error if it is malformed."""
    if not value.startswith("@"):
        return None
    m = _REF_RE.match(value)
    if not m:
        raise ReflectmmError(f"{where}: malformed reference {value!r} (expected @stage.output, "
                             f"@stage.outputs.NAME or @stage.dir[/sub/path])", path)
    what = m.group("what")
    if what.startswith("outputs."):
        return Ref(m.group("stage"), "outputs", m.group("name"), m.group("sub"))
    if what == "output" and m.group("sub"):
        raise ReflectmmError(f"{where}: {value!r}: a sub-path is only allowed after @stage.dir", path)
    return Ref(m.group("stage"), what, None, m.group("sub"))


#: the resource names the docs and the shipped recipes use; a worker may declare others (``dask worker --resources``)
_KNOWN_RESOURCES = ("cpus", "memory", "gpus")
_COUNT_RESOURCES = ("cpus", "gpus")


def _check_resource_name(name: str, where: str, path: Path) -> None:
    """A resource name close to a known one but not it (``cpu``, ``mem``) is a typo that Dask would never match
    with a worker's resources, so the table would be ignored without a word: refused, naming the right key."""
    if name in _KNOWN_RESOURCES:
        return
    close = difflib.get_close_matches(name.lower(), _KNOWN_RESOURCES, n=1, cutoff=0.6)
    if close:
        raise ReflectmmError(f"{where} resources.{name}: not a resource name; did you mean {close[0]!r}? "
                             f"(the usual names: {', '.join(_KNOWN_RESOURCES)})", path)


def _type_error(where: str, expected: str, got: Any, path: Path) -> ReflectmmError:
    return ReflectmmError(f"{where}: expected {expected}, got {type(got).__name__} {got!r}", path)


def parse_recipe_text(text: str, path: Path, overrides: tuple[str, ...] | list[str] = ()) -> Recipe:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ReflectmmError(f"invalid TOML: {exc}", path) from None
    apply_overrides(doc, overrides, path)
    recipe = _build(doc, path)
    recipe.overrides = tuple(overrides)
    return recipe


#: A bare word that ``--set`` takes as a string without quotes (``solver=ls``, ``device=cuda:0``).
_BARE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.:\-/]*$")


def parse_override(text: str, path: Path) -> tuple[str, str, Any]:
    """Split one ``STAGE.PARAM=VALUE`` into its stage, param and value.

    VALUE is a TOML value (``16``, ``1e-3``, ``true``, ``[1, 8, 64]``, ``{ jaw = 0 }``, ``"x"``); a bare word
    that is not one is taken as a string. Dashes in PARAM read as underscores (``flash-iters``).
    """
    key, sep, raw = text.partition("=")
    stage, dot, param = key.strip().rpartition(".")
    if not sep or not dot or not stage or not param:
        raise ReflectmmError(f"--set {text!r}: expected STAGE.PARAM=VALUE (e.g. synth-wild.count=384)", path)
    param = param.replace("-", "_")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        if not _BARE_RE.match(raw):
            raise ReflectmmError(f"--set {text!r}: cannot read {raw!r} as a TOML value "
                                 f"(quote strings: {param}=\"...\")", path) from None
        value = raw
    return stage, param, value


def apply_overrides(doc: dict[str, Any], overrides: tuple[str, ...] | list[str], path: Path) -> None:
    """Set each ``STAGE.PARAM=VALUE`` of ``overrides`` in the parsed recipe ``doc``, in order (the last wins).

    The stage must exist; the value replaces the param's value from ``[defaults]`` and from the stage's own
    ``params`` alike, and the stage's parameter declaration checks it when the run is planned.
    """
    stages = doc.get("stages")
    for text in overrides:
        stage, param, value = parse_override(text, path)
        if not isinstance(stages, dict) or not isinstance(stages.get(stage), dict):
            known = ", ".join(stages) if isinstance(stages, dict) else "none"
            raise ReflectmmError(f"--set {text!r}: no stage {stage!r} in the recipe (stages: {known})", path)
        params = stages[stage].setdefault("params", {})
        if not isinstance(params, dict):
            raise _type_error(f"[stages.{stage}] params", "a table", params, path)
        params[param] = value


def load_recipe(path: str | Path, overrides: tuple[str, ...] | list[str] = ()) -> Recipe:
    """Read and validate a recipe file; raise :class:`ReflectmmError` naming the file on any problem.

    ``overrides`` are ``STAGE.PARAM=VALUE`` strings applied before validation (``reflectmm run --set``).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ReflectmmError("recipe not found", path) from None
    except IsADirectoryError:
        raise ReflectmmError("is a directory, expected a recipe .toml file", path) from None
    except UnicodeDecodeError:
        raise ReflectmmError("not a text (UTF-8) file", path) from None
    return parse_recipe_text(text, path, overrides)


def _parse_foreach(foreach: Any, where: str, path: Path) -> Any:
    """A stage's ``foreach``: None, a list of id strings, ``{ file = "ids.txt" }`` or "all found" (checked)."""
    if foreach is not None:
        if isinstance(foreach, str):
            if foreach.strip().lower() != ALL_FOUND:
                raise ReflectmmError(f'{where} foreach: expected a list of ids, {{ file = "ids.txt" }} '
                                     f'or "{ALL_FOUND}", got {foreach!r}', path)
            foreach = ALL_FOUND
        elif isinstance(foreach, list):
            bad = next((i for i in foreach if not isinstance(i, str)), None)
            if bad is not None:
                raise ReflectmmError(f"{where} foreach: ids are strings such as \"001\", got "
                                     f"{type(bad).__name__} {bad!r} (quote it: \"{bad}\")", path)
            dup = named_twice(foreach)
            if dup:
                raise ReflectmmError(f"{where} foreach: duplicate id(s) {', '.join(dup)}", path)
        elif isinstance(foreach, dict):
            if set(foreach) != {"file"} or not isinstance(foreach["file"], str):
                raise ReflectmmError(f'{where} foreach: expected {{ file = "ids.txt" }}, got {foreach!r}',
                                     path)
        else:
            raise _type_error(f"{where} foreach", 'a list, { file = ... } or "all found"', foreach, path)
    return foreach


def _parse_resources(sdoc: dict[str, Any], where: str, path: Path) -> dict[str, Any]:
    """A stage's ``resources`` table: known names, finite non-negative counts, sizes Dask can read."""
    resources = sdoc.get("resources", {})
    if not isinstance(resources, dict):
        raise _type_error(f"{where} resources", "a table { cpus = 1, memory = \"4GB\" }", resources, path)
    for rk, rv in resources.items():
        _check_resource_name(rk, where, path)
        if isinstance(rv, bool) or not isinstance(rv, (int, float, str)):
            raise _type_error(f"{where} resources.{rk}", "a number or a size like \"4GB\"", rv, path)
        if isinstance(rv, str) and rk in _COUNT_RESOURCES:
            raise _type_error(f"{where} resources.{rk}", "a number", rv, path)
        if isinstance(rv, float) and not math.isfinite(rv):
            raise ReflectmmError(f"{where} resources.{rk}: must be a finite number, got {rv}", path)
        if isinstance(rv, str):
            from dask.utils import parse_bytes

            try:
                parse_bytes(rv)
            except (ValueError, TypeError):
                raise ReflectmmError(f"{where} resources.{rk}: cannot read {rv!r} as a size "
                                     f"(e.g. \"512MB\", \"4GB\")", path) from None
        elif rv < 0:
            raise ReflectmmError(f"{where} resources.{rk}: must be >= 0, got {rv}", path)
    return dict(resources)


def _build_stage(sname: str, sdoc: Any, defaults: dict[str, Any], path: Path) -> StageSpec:
    """One ``[stages.<name>]`` table → its :class:`StageSpec` (the recipe's ``[defaults]`` under its params)."""
    where = f"[stages.{sname}]"
    if not _NAME_RE.match(sname):
        raise ReflectmmError(f"{where}: bad stage name (letters, digits, _ and - only; a dot would make "
                             f"references such as @{sname}.output ambiguous)", path)
    if not isinstance(sdoc, dict):
        raise _type_error(where, "a table", sdoc, path)
    unknown = set(sdoc) - _STAGE_KEYS
    if unknown:
        raise ReflectmmError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                             f"(allowed: {', '.join(sorted(_STAGE_KEYS))})", path)
    verb = sdoc.get("verb", sname)
    if not isinstance(verb, str):
        raise _type_error(f"{where} verb", "a string", verb, path)
    params = sdoc.get("params", {})
    if not isinstance(params, dict):
        raise _type_error(f"{where} params", "a table", params, path)
    merged = {**defaults, **params}
    param_refs = {}
    for k, v in merged.items():
        if isinstance(v, str):
            ref = parse_ref(v, f"{where} params.{k}", path)
            if ref is not None:
                param_refs[k] = ref
    inputs_doc = sdoc.get("inputs", {})
    if not isinstance(inputs_doc, dict):
        raise _type_error(f"{where} inputs", "a table { role = ... }", inputs_doc, path)
    inputs: dict[str, list[Ref | str]] = {}
    for role, val in inputs_doc.items():
        items = val if isinstance(val, list) else [val]
        out: list[Ref | str] = []
        for it in items:
            if not isinstance(it, str):
                raise _type_error(f"{where} inputs.{role}", "a path string or a list of them", it, path)
            ref = parse_ref(it, f"{where} inputs.{role}", path)
            out.append(ref if ref is not None else it)
        inputs[role] = out
    foreach = _parse_foreach(sdoc.get("foreach"), where, path)
    resources = _parse_resources(sdoc, where, path)
    priority = sdoc.get("priority", 0)
    if isinstance(priority, bool) or not isinstance(priority, int):
        raise _type_error(f"{where} priority", "an integer", priority, path)
    if not -999 <= priority <= 999:
        raise ReflectmmError(f"{where} priority: must be between -999 and 999, got {priority}", path)
    return StageSpec(sname, verb, merged, inputs, foreach, resources, param_refs, frozenset(params), priority)


def _build(doc: dict[str, Any], path: Path) -> Recipe:
    schema = doc.get("schema")
    if schema is None:
        raise ReflectmmError(f'missing schema (add: schema = "{RECIPE_SCHEMA}/{RECIPE_MAJOR}")', path)
    if not isinstance(schema, str) or not schema.startswith(RECIPE_SCHEMA + "/"):
        raise ReflectmmError(f"schema {schema!r} is not a reflectmm recipe "
                             f"(expected \"{RECIPE_SCHEMA}/{RECIPE_MAJOR}\")", path)
    try:
        major = int(schema.rsplit("/", 1)[1])
    except ValueError:
        raise ReflectmmError(f"malformed schema {schema!r}", path) from None
    if major > RECIPE_MAJOR:
        raise ReflectmmError(f"recipe schema {schema} is newer than this reflectmm reads "
                             f"(up to {RECIPE_SCHEMA}/{RECIPE_MAJOR}); upgrade reflectmm", path)
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        raise ReflectmmError(f"unknown top-level key(s): {', '.join(sorted(unknown))} "
                             f"(allowed: {', '.join(sorted(_TOP_KEYS))})", path)
    name = doc.get("name", path.stem)
    if not isinstance(name, str):
        raise _type_error("name", "a string", name, path)
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise _type_error("[defaults]", "a table", defaults, path)
    stages_doc = doc.get("stages")
    if not isinstance(stages_doc, dict) or not stages_doc:
        raise ReflectmmError("no [stages.<name>] tables", path)

    stages: dict[str, StageSpec] = {}
    for sname, sdoc in stages_doc.items():
        stages[sname] = _build_stage(sname, sdoc, defaults, path)

    recipe = Recipe(path, name, dict(defaults), stages)
    for spec in stages.values():
        for up in spec.upstream():
            if up not in stages:
                raise ReflectmmError(f"[stages.{spec.name}] refers to unknown stage '{up}' "
                                     f"(stages: {', '.join(stages)})", path)
    topological_order(recipe)  # raises on a cycle
    return recipe


def topological_order(recipe: Recipe) -> list[str]:
    """Kahn's order over stage references; a cycle raises an error naming it."""
    names = list(recipe.stages)
    ups = {n: recipe.stages[n].upstream() for n in names}
    order: list[str] = []
    done: set[str] = set()
    remaining = list(names)
    while remaining:
        ready = [n for n in remaining if all(u in done for u in ups[n])]
        if not ready:
            raise ReflectmmError(f"recipe has a cycle: {' -> '.join(_find_cycle(remaining, ups))}", recipe.path)
        for n in ready:
            order.append(n)
            done.add(n)
        remaining = [n for n in remaining if n not in done]
    return order


def chain_lengths(recipe: Recipe) -> dict[str, int]:
    """For every stage, the number of stages on the longest chain from it to a stage nothing reads (itself
    included). A runner starts the ready task with the longest chain first: the stages that gate the most work
    downstream (the critical path, counted in stages) do not wait behind side branches."""
    return _chains(*_graph(recipe))


def task_priorities(recipe: Recipe) -> dict[str, int]:
    """The order in which a runner starts ready tasks, higher first: the stage's declared ``priority`` first, then
    its :func:`chain_lengths`, then the number of stages that read its outputs, directly or not (encoded as
    ``10⁶ × priority + 10³ × chain + min(downstream, 999)``). Stage counts do not know how long a stage takes: a
    recipe whose long stages sit on short chains says so with ``priority``."""
    order, downs = _graph(recipe)
    below: dict[str, set[str]] = {}
    for n in reversed(order):
        below[n] = set(downs[n]).union(*(below[d] for d in downs[n]))
    chains = _chains(order, downs)
    return {n: 10 ** 6 * recipe.stages[n].priority + 1000 * min(chains[n], 999) + min(len(below[n]), 999)
            for n in order}


def _graph(recipe: Recipe) -> tuple[list[str], dict[str, list[str]]]:
    """(the stages in topological order, each stage's readers)."""
    order = topological_order(recipe)
    downs: dict[str, list[str]] = {n: [] for n in order}
    for n in order:
        for u in recipe.stages[n].upstream():
            if u in downs:
                downs[u].append(n)
    return order, downs


def _chains(order: list[str], downs: dict[str, list[str]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for n in reversed(order):
        out[n] = 1 + max((out[d] for d in downs[n]), default=0)
    return out


def _find_cycle(nodes: list[str], ups: dict[str, list[str]]) -> list[str]:
    """One cycle among ``nodes`` (each has an upstream within ``nodes``), written producer -> consumer."""
    node_set = set(nodes)
    start = nodes[0]
    path: list[str] = []
    seen: dict[str, int] = {}
    cur = start
    while cur not in seen:
        seen[cur] = len(path)
        path.append(cur)
        cur = next(u for u in ups[cur] if u in node_set)
    cycle = path[seen[cur]:] + [cur]
    # path follows "depends on" edges; print the data flow direction
    return list(reversed(cycle))

"""Stage machinery: :class:`Stage`, :class:`StageContext`, cache keys, the no-overwrite check.

A stage is the unit of work shared by the CLI verbs and recipes: options → read artifacts → library call →
write artifacts.  The CLI command and the recipe runner both build a :class:`StageContext` through
:meth:`Stage.context` (which validates the params against the stage's declaration and fills the defaults)
and call ``stage.run(ctx)``, so a verb behaves the same — and gets the same cache key — from the shell and
inside ``reflectmm run``.  :func:`~reflectmm_cli.stages.registry.run_stage` (run a stage given by verb or
object) is in the registry, which imports this module; this module imports no other module of
:mod:`reflectmm_cli.stages`.

Workspace convention (docs/design.md §5, :mod:`reflectmm_cli.workspace`): ``<workspace>/<stage_name>/<identity>.npz``
(``<workspace>/<stage_name>/<name>.npz`` for stages that are not per identity), overridable with an explicit
output path.

No click in this package: the planner and Dask workers import it.
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from reflectmm_cli import __version__
from reflectmm_cli.artifacts import canonical_json, input_ref, sha256_file
from reflectmm_cli.errors import ReflectmmError, WrittenThenFailed
from reflectmm_cli.params import Param, ParamError, closest_name, resolve_params
from reflectmm_cli.workspace import check_id, stage_output, walk_files  # walk_files: re-exported

#: Bump when the way cache keys are computed changes (invalidates every cache).
CACHE_HASH_VERSION = 1

#: Params that never change a result (execution details) and so never invalidate a cache.
NON_INVALIDATING = frozenset({"device", "jobs", "executor", "scheduler", "progress", "workspace"})


@dataclass
class StageContext:
    """Everything a stage needs to run once (for one identity, or once overall).

    Attributes:
        workspace: root folder of the workspace.
        stage_name: the recipe's name for this stage (defaults to the verb); names the
            output folder ``<workspace>/<stage_name>/``.
        identity: the identity this run is for (per-identity stages), else None.
        params: resolved parameters: the stage's declared params with defaults filled and values
            canonicalised (:meth:`Stage.resolve`), plus execution details (``device``).
        inputs: role -> concrete input paths (files or folders).
        output: explicit primary output path that overrides the workspace convention.
        device: torch device string (``cpu``, ``cuda``, ``cuda:1``, or ``auto``).
        cache_key: the key the planner computed (stored in the artifacts' meta).
        verb: the registered verb.
        stage_version: the registered stage version.
    """

    workspace: Path
    stage_name: str
    identity: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, list[Path]] = field(default_factory=dict)
    output: Path | None = None
    device: str = "cpu"
    cache_key: str | None = None
    verb: str = ""
    stage_version: int = 1
    #: declared params that never change a result (``Param.invalidates_cache`` False): not in meta or the key.
    volatile_params: frozenset[str] = frozenset()

    def output_path(self, name: str | None = None, suffix: str = ".npz") -> Path:
        """Primary output path: the explicit ``output`` if given (for the default name and suffix),
        else ``<workspace>/<stage_name>/<name or identity or stage_name><suffix>``."""
        if self.output is not None and name is None and suffix == ".npz":
            return Path(self.output)
        base = name or self.identity or self.stage_name
        if self.output is not None:
            return Path(self.output).parent / f"{base}{suffix}"
        return stage_output(self.workspace, self.stage_name, base, suffix)

    def input(self, role: str) -> Path:
        """The single input path for ``role``; a clear error if missing or ambiguous."""
        paths = self.inputs.get(role) or []
        if len(paths) != 1:
            what = "missing" if not paths else f"given {len(paths)} times, expected once"
            raise ReflectmmError(f"stage '{self.stage_name}': input '{role}' is {what}")
        return Path(paths[0])

    def input_list(self, role: str, required: bool = True) -> list[Path]:
        paths = [Path(p) for p in self.inputs.get(role) or []]
        if required and not paths:
            raise ReflectmmError(f"stage '{self.stage_name}': input '{role}' is missing")
        return paths

    def param(self, name: str, default: Any = None) -> Any:
        return self.params.get(name, default)

    def producer(self) -> dict[str, Any]:
        """Producer record for artifact meta."""
        return {"stage": self.verb or self.stage_name, "stage_version": self.stage_version,
                "version": __version__}

    def input_refs(self, relative_to: Path | None = None, files: Mapping[str, Iterable[Path]] | None = None
                   ) -> list[dict[str, Any]]:
        """Provenance records (role, relative path, sha256, schema) of the input files."""
        src = files if files is not None else self.inputs
        refs = []
        for role in sorted(src):
            for p in src[role]:
                p = Path(p)
                if p.is_file():
                    refs.append(input_ref(role, p, relative_to))
        return refs

    def resolved_params(self) -> dict[str, Any]:
        """Params that affect results (what goes into meta and the cache key)."""
        return {k: v for k, v in sorted(self.params.items())
                if k not in NON_INVALIDATING and k not in self.volatile_params}

    def with_(self, **changes: Any) -> "StageContext":
        return replace(self, **changes)

    def with_patterns_expanded(self) -> "StageContext":
        """The context with each input path that names no file but is a glob pattern replaced by its matches
        (sorted). A recipe's ``@stage.dir/sub/*.png`` points into a folder that an upstream task fills: the planner
        keeps it as a pattern until it matches, and the task expands it when it runs (docs/recipes.md).

        Raises:
            ReflectmmError: a pattern that still matches nothing, naming its role and the pattern.
        """
        return self.with_(inputs={role: expand_pattern_paths(paths, role=role) for role, paths in self.inputs.items()})


def expand_pattern_paths(paths: Iterable[str | Path], role: str | None = None) -> list[Path]:
    """``paths`` with each one that names no file but is a glob pattern replaced by its matches (sorted).

    A pattern without matches is an error naming ``role`` (the planner's message for a plain-path pattern), or,
    with ``role=None``, stays as it is (the planner's ``@stage.dir`` patterns, whose folder is filled later)."""
    import glob

    out: list[Path] = []
    for p in map(Path, paths):
        found = sorted(Path(q) for q in glob.glob(str(p))) if not p.exists() and glob.has_magic(str(p)) else [p]
        if not found and role is not None:
            raise ReflectmmError(f"input '{role}': no file matches {p}")
        out += found or [p]
    return out


@dataclass(frozen=True)
class Default:
    """Where a command finds an input role it was not given: the workspace convention, declared with the role
    (:func:`reflectmm_cli.stages.defaults.default_inputs` applies it; recipes name their inputs and use none).

    Attributes:
        rule: ``output``: the upstream stage's output ``<ws>/<upstream>/<name><suffix>`` (name: ``name``, else the
            identity, else the upstream's name); for a ``many`` role, one per ``--ids`` identity (placed before
            the given paths), else one for the identity.  ``all``: every ``*<suffix>`` the upstream wrote.
            ``folder``: ``<ws>/<upstream>/``.
            ``face-model``: :func:`~reflectmm_cli.workspace.find_face_model`, consulting the first file of the roles
            ``capture`` and ``geometry`` name.  ``truth``: the workspace's truth folder (a ``many`` role), else
            ``<truth folder>/<id>.npz`` (:func:`~reflectmm_cli.workspace.find_truth_dir`, consulting ``capture``).
            ``rig``: ``rig.toml`` of the capture's dataset folder; ``fit-rig``: the workspace's calibrated rig first
            (:func:`~reflectmm_cli.workspace.find_fit_rig`).
        name, suffix: the file name of an ``output`` (``suffix`` also filters ``all``).
        optional: a default that is not found leaves the role out instead of raising ``missing``.
        checked: False passes a composed path on without looking (the stage then reports a missing file).
        check_given: given paths are checked too (each must exist, else ``missing``).
        missing: the one-line error when the default is not found; ``{path}``, ``{folder}``, ``{workspace}``,
            ``{option}`` and ``{<role>}`` (the first path of that role) are filled in.  Empty: ``{option}: not given
            and {path} does not exist`` (for a search: ``{option}: not given and none found in {workspace}``).
        capture, geometry: the roles whose first file a search consults.
        wild: a role whose first path, when it is a folder (a ``synth wild`` folder), is consulted first by the
            ``face-model`` search: its ``face_model.npz`` (:func:`~reflectmm_cli.workspace.wild_face_model`).
        needs: roles that must be present for the default to be looked for.
        group: roles of one group are passed all together or not at all, given ones included (a role whose
            default is not found drops the group).
        unless: ``(param, value)``: when the command's param has that value the role is left out, given or not.
        listed: a folder (given or found) stands for the ``*<suffix>`` files in it (none if it does not exist).
    """

    rule: str = "output"
    name: str | None = None
    suffix: str = ".npz"
    optional: bool = False
    checked: bool = True
    check_given: bool = False
    missing: str = ""
    capture: str | None = None
    geometry: str | None = None
    wild: str | None = None
    needs: tuple[str, ...] = ()
    group: str | None = None
    unless: tuple[str, Any] | None = None
    listed: bool = False


@dataclass(frozen=True)
class Input:
    """One input role of a stage: declared once, it checks recipes and the command line and writes ``--help``.

    Attributes:
        role: the name in ``inputs = { role = ... }`` and ``StageContext.inputs``; with ``prefix`` a family of
            roles ``<role>_<name>`` (e.g. ``model_<method>``).
        kind: the artifact kind read (``reflectance-model`` …), or a plain description of files (``EXR/HDR maps``).
        upstream: the stage that usually makes this input (the recipes' source; the default in the workspace
            convention where the verb has one).
        many: more than one path may be given (files or folders).
        prefix: ``role`` names a family of roles (see above).
        help: one line.
        default: where a command finds this role when it is not given (:class:`Default`, from ``upstream``);
            None: the command has no default for it.
    """

    role: str
    kind: str = ""
    upstream: str | None = None
    many: bool = False
    prefix: bool = False
    help: str = ""
    default: Default | None = None

    def matches(self, role: str) -> bool:
        return role.startswith(self.role + "_") and len(role) > len(self.role) + 1 if self.prefix else role == self.role

    def describe(self) -> str:
        """``role (kind; from upstream) — help`` for ``--help`` and docs."""
        name = f"{self.role}_<name>" if self.prefix else self.role
        what = "; ".join(x for x in (self.kind, f"made by {self.upstream}" if self.upstream else "",
                                     "several" if self.many else "") if x)
        return f"{name}" + (f" ({what})" if what else "") + (f": {self.help}" if self.help else "")


@dataclass(frozen=True)
class Stage:
    """A registered verb that can run as a recipe stage.

    Attributes:
        verb: name used on the command line and in recipes.
        version: bump when the stage's results change for the same inputs and params.
        run: ``run(ctx) -> list[Path]`` does the work and returns the paths it wrote.
        per_identity: True if the stage runs once per identity (``foreach``).
        outputs: ``outputs(ctx) -> list[Path]`` the paths a run will write (for cache checks);
            default ``[ctx.output_path()]``.
        side_files: ``side_files(ctx) -> list[Path]`` files a run may also write that do not decide whether it is
            up to date (previews written only with some inputs); :func:`check_no_overwrite` checks them too.
        stale: ``stale(ctx, meta) -> reason | None``: why an output whose cache key matches must still be rebuilt
            (its meta records a state that this run refuses, e.g. images that prepare-wild skipped when skips are
            not allowed); the recipe planner then runs the task instead of calling it up to date.
        input_files: ``input_files(ctx) -> {role: [files]}`` the concrete files whose content
            keys the cache (e.g. only one identity's images inside a dataset root);
            default: every file in ``ctx.inputs`` (folders expanded recursively).
        discover_ids: ``discover_ids(ctx) -> [ids]`` for ``foreach = "all found"`` (``ctx.inputs``
            holds the stage's inputs resolved as for an aggregate; return None to let the recipe
            planner use the identities of the upstream per-identity stage).
        params: the stage's parameter declaration (tuple of :class:`~reflectmm_cli.params.Param`);
            None = undeclared (params pass through unchecked; only for ad-hoc stages registered with
            :func:`register_stage`).
        open_params: undeclared params are accepted as given (and key the cache) instead of refused.
        cache_params: for a stage without a declaration, the names of the params that key the cache (None: all
            but :data:`NON_INVALIDATING`); a declared stage says it per param (``invalidates_cache``).
        complete: ``complete(resolved) -> resolved`` fills the defaults that depend on another param (e.g. a
            preset such as finetune's ``variant``) after the declaration's own; its result keys the cache.
        help: one-line description.
    """

    verb: str
    version: int
    run: Callable[[StageContext], list[Path]]
    per_identity: bool = False
    outputs: Callable[[StageContext], list[Path]] | None = None
    side_files: Callable[[StageContext], list[Path]] | None = None
    stale: Callable[[StageContext, dict[str, Any]], str | None] | None = None
    input_files: Callable[[StageContext], dict[str, list[Path]]] | None = None
    discover_ids: Callable[[StageContext], list[str]] | None = None
    params: tuple[Param, ...] | None = None
    open_params: bool = False
    cache_params: tuple[str, ...] | None = None
    complete: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    help: str = ""
    inputs: tuple[Input, ...] | None = None

    def check_roles(self, roles: Iterable[str], where: str = "") -> None:
        """Refuse an input role the stage does not declare (one line naming the valid ones; a close name is
        suggested). A stage without a declaration (``inputs=None``, ad-hoc stages) accepts every role."""
        if self.inputs is None:
            return
        for role in roles:
            if not any(i.matches(role) for i in self.inputs):
                names = [f"{i.role}_<name>" if i.prefix else i.role for i in self.inputs]
                near = closest_name(role, [i.role for i in self.inputs])
                hint = f"did you mean '{near}'? " if near else ""
                raise ReflectmmError(f"{where or self.verb}: unknown input '{role}' ({hint}inputs of {self.verb}: "
                                     f"{', '.join(names) or 'none'})")

    def resolve(self, given: Mapping[str, Any] | None, strict: bool = True) -> dict[str, Any]:
        """Params validated against the declaration, defaults filled, canonical (what keys the cache).

        ``strict=False`` drops undeclared names instead of refusing them (recipe ``[defaults]``).
        Raises :class:`~reflectmm_cli.params.ParamError` (one line naming the param)."""
        given = dict(given or {})
        if self.params is None:
            return {k: v for k, v in sorted(given.items()) if v is not None}
        extra = {k: v for k, v in given.items() if k not in {p.name for p in self.params}
                 and k not in NON_INVALIDATING} if self.open_params else {}
        out = resolve_params(self.params, {k: v for k, v in given.items() if k not in extra}, strict=strict,
                             ignore=NON_INVALIDATING)
        out.update({k: v for k, v in extra.items() if v is not None})
        if self.complete is not None:
            out = self.complete(out)
        return dict(sorted(out.items()))

    def expected_outputs(self, ctx: StageContext) -> list[Path]:
        return list(self.outputs(ctx)) if self.outputs else [ctx.output_path()]

    def files_to_hash(self, ctx: StageContext) -> dict[str, list[Path]]:
        if self.input_files is not None:
            return {k: sorted(Path(p) for p in v) for k, v in self.input_files(ctx).items()}
        out: dict[str, list[Path]] = {}
        for role, paths in ctx.inputs.items():
            files: list[Path] = []
            for p in paths:
                p = Path(p)
                if p.is_dir():
                    files.extend(walk_files(p))
                else:
                    files.append(p)
            out[role] = files
        return out

    def key_params(self, ctx: StageContext) -> dict[str, Any]:
        params = ctx.resolved_params()
        if self.params is not None:
            skip = {p.name for p in self.params if not p.invalidates_cache}
            params = {k: v for k, v in params.items() if k not in skip}
        if self.cache_params is not None:
            params = {k: v for k, v in params.items() if k in self.cache_params}
        return params

    def context(self, *, strict: bool = True, **kwargs: Any) -> StageContext:
        """A context for this stage; ``params`` are resolved (:meth:`resolve`), so defaults are filled in
        before any cache key is computed.  Errors name the stage: ``stage 'unwrap-uv': uv_size: ...``; an
        identity that is not a safe id (:func:`~reflectmm_cli.workspace.check_id`) is refused here too."""
        kwargs.setdefault("stage_name", self.verb)
        if kwargs.get("identity") is not None:
            check_id(kwargs["identity"], f"stage '{kwargs['stage_name']}'")
        try:
            kwargs["params"] = self.resolve(kwargs.get("params"), strict=strict)
        except ParamError as exc:
            raise ParamError(f"stage '{kwargs['stage_name']}': {exc}") from None
        ctx = StageContext(**kwargs)
        volatile = frozenset(p.name for p in self.params or () if not p.invalidates_cache)
        return ctx.with_(verb=self.verb, stage_version=self.version, volatile_params=volatile)


def _file_id(path: Path) -> tuple[int, int] | None:
    """(device, inode) of an existing file (hard links and symlinks share it), else None."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def check_no_overwrite(stage: Stage, ctx: StageContext) -> None:
    """Refuse, before anything is computed, a run whose output or side file (:meth:`Stage.expected_outputs` and
    ``side_files``) is one of its input files — the same path once symlinks, ``..`` and hard links are resolved,
    whatever the paths were (ids, ``-o``, ``--input``).  An NPZ input's EXR twin beside it (fit-reflectance writes
    its maps as both) counts as that input.  One line naming the output, the input role and the file.
    :func:`run_stage` (the command line) and the recipe executors call it before ``stage.run``."""
    inputs: dict[Any, tuple[str, Path]] = {}
    explicit = {role: [Path(p) for p in paths if not Path(p).is_dir()] for role, paths in ctx.inputs.items()}
    explicit = {role: paths + [q.with_suffix(".exr") for q in paths
                               if q.suffix.lower() == ".npz" and q.with_suffix(".exr").is_file()]
                for role, paths in explicit.items()}
    for files in (explicit, stage.files_to_hash(ctx)):
        for role, paths in files.items():
            for p in paths:
                inputs.setdefault(os.path.realpath(p), (role, Path(p)))
                fid = _file_id(p)
                if fid is not None:
                    inputs.setdefault(fid, (role, Path(p)))
    if not inputs:
        return
    outputs = stage.expected_outputs(ctx) + (list(stage.side_files(ctx)) if stage.side_files else [])
    for out in outputs:
        hit = inputs.get(os.path.realpath(out)) or inputs.get(_file_id(out))
        if hit is not None:
            role, src = hit
            raise ReflectmmError(f"would overwrite its own input '{role}' ({src}); refused before computing — "
                                 f"give another output path (-o/--out) or id", out)


def file_digest(path: Path, cache: dict[str, Any] | None = None, used: dict[str, Any] | None = None) -> str:
    """sha256 of a file, memoised in ``cache`` by (path, size, mtime_ns) when given.  ``used`` (with ``cache``)
    collects the entries ``[size, mtime_ns, sha256]`` of the files digested, by resolved path."""
    if cache is None:
        return sha256_file(path)
    st = os.stat(path)
    key = str(Path(path).resolve())
    hit = cache.get(key)
    if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
        digest = hit[2]
    else:
        digest = sha256_file(path)
        cache[key] = [st.st_size, st.st_mtime_ns, digest]
    if used is not None:
        used[key] = cache[key]
    return digest


def cache_key_doc(stage: Stage, ctx: StageContext, hash_cache: dict[str, Any] | None = None,
                  used: dict[str, Any] | None = None) -> dict[str, Any]:
    """The document whose canonical JSON the cache key hashes (the planner compares its parts to say why).
    ``used`` (with ``hash_cache``) collects the memo entries of the input files, for
    :func:`check_inputs_unchanged`."""
    files = stage.files_to_hash(ctx)
    digests = {role: [file_digest(p, hash_cache, used) for p in paths] for role, paths in sorted(files.items())}
    return {"hash": CACHE_HASH_VERSION, "verb": stage.verb, "stage_version": stage.version,
            "identity": ctx.identity, "params": stage.key_params(ctx), "inputs": digests}


def check_inputs_unchanged(entries: Mapping[str, Any]) -> None:
    """Refuse a task's outputs when one of its input files changed or went away while it ran (another process
    wrote it): ``entries`` are the ``[size, mtime_ns, sha256]`` memo entries the cache key was computed from
    (:func:`cache_key_doc` ``used``).  Called before the outputs are committed, so nothing is written under a key
    that does not describe what was read."""
    for path, (size, mtime_ns, _) in entries.items():
        try:
            st = os.stat(path)
        except FileNotFoundError:
            raise ReflectmmError("input removed while the task ran; nothing written — rerun", path) from None
        if stat.S_ISREG(st.st_mode) and (st.st_size, st.st_mtime_ns) != (size, mtime_ns):  # not a pipe's reads
            raise ReflectmmError("input changed while the task ran (another process wrote it); nothing written — "
                                 "rerun", path)


def check_outputs_writable(outputs: Iterable[Path]) -> None:
    """Refuse, before computing, a task whose ``outputs`` could not be written: for each output folder (or its
    nearest existing ancestor, where the folder is yet to be made) a probe file is created and removed.  One line
    naming an output, the folder and the system's reason, as the writer would say it after the work."""
    from reflectmm_cli.artifacts import _raise_write_error

    folders: dict[Path, Path] = {}
    for o in outputs:
        folders.setdefault(Path(os.path.abspath(o)).parent, Path(o))
    for folder, output in folders.items():
        probe_in = folder
        while not probe_in.exists() and probe_in.parent != probe_in:
            probe_in = probe_in.parent
        if not probe_in.is_dir():
            continue  # a file in the way: the writer says so, naming it
        try:
            fd, tmp = tempfile.mkstemp(prefix=".reflectmm-probe.", dir=probe_in)
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            _raise_write_error(exc, output)  # named as its writer would: the output, and the folder refused
            raise


def run_committed(stage: Stage, ctx: StageContext, inputs_used: Mapping[str, Any]) -> list[Path]:
    """Run a stage so that a failed or interrupted run loses nothing: the output folders are checked writable before
    computing (:func:`check_outputs_writable`); every file the run writes is committed together at its end
    (:func:`~reflectmm_cli.artifacts.committed_together`), the primary output — the one whose cache key vouches for
    the others — last; and not at all when an input changed while it ran (``inputs_used``, the memo entries its key
    was computed from: :func:`check_inputs_unchanged`).  A stage that raises
    :class:`~reflectmm_cli.errors.WrittenThenFailed` has its files committed before the error is reported.  The
    command line and every recipe executor run stages through it.  Returns the paths the stage says it wrote."""
    from reflectmm_cli.artifacts import committed_together

    outputs = stage.expected_outputs(ctx)
    check_outputs_writable(outputs)
    partial: WrittenThenFailed | None = None
    with committed_together(last=outputs[0] if outputs else None):
        try:
            written = list(stage.run(ctx) or [])
        except WrittenThenFailed as exc:  # what it wrote is kept, then the error is reported
            partial = exc
        check_inputs_unchanged(inputs_used)
    if partial is not None:
        raise partial
    return written


def key_of_doc(doc: Mapping[str, Any]) -> str:
    """sha256 of the canonical JSON of a :func:`cache_key_doc` document."""
    return hashlib.sha256(canonical_json(doc).encode()).hexdigest()


def compute_cache_key(stage: Stage, ctx: StageContext, hash_cache: dict[str, Any] | None = None) -> str:
    """Cache key = sha256(hash version, verb, stage version, invalidating params, input digests)."""
    return key_of_doc(cache_key_doc(stage, ctx, hash_cache))


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` if available else ``cpu``; anything else is checked and returned."""
    if device == "cpu":  # the common case: no need to import torch just to say so
        return device
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if not re.fullmatch(r"cuda(:\d+)?", device):  # the one code path runs on the CPU and on CUDA only
        raise ReflectmmError(f"--device {device}: not a usable device (cpu, cuda, cuda:N or auto)")
    if not torch.cuda.is_available():
        raise ReflectmmError(f"--device {device}: CUDA is not available on this machine (use --device cpu)")
    if ":" in device and int(device.split(":")[1]) >= torch.cuda.device_count():
        raise ReflectmmError(f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device

"""Command defaults from the stages' input declarations: a role a command was not given is found by the
:class:`~reflectmm_cli.stages.base.Default` declared with it (``Input(..., upstream=, default=)``), in the workspace
convention of :mod:`reflectmm_cli.workspace`.

So ``reflectmm fit-reflectance --id 001`` reads ``<ws>/unwrap-uv/001.npz`` because the stage declares
``Input("observations", "uv-observations", upstream="unwrap-uv", default=Default("output", ...))``, and that is
the path a recipe's ``@unwrap-uv.output`` names when the recipe's stages are named after their verbs
(tests/stages/test_input_defaults.py checks both).  Recipes name their inputs and get no defaults.

No click here (the commands import it; so may the Python API).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from reflectmm_cli.artifacts import check_schema, read_meta
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.base import Input, Stage
from reflectmm_cli.workspace import (WORKSPACE_TRUTH_DIRS, files_in, find_face_model, find_fit_rig, find_rig,
                                     find_truth_dir, list_artifacts, stage_dir, stage_output, wild_face_model)

__all__ = ["default_inputs", "default_paths", "NO_TRUTH"]

#: The rules that compose a path from the upstream stage alone; the searches (which may consult the other roles'
#: files) run after them.
PATH_RULES = ("output", "all", "folder")

#: The error when ground truth is needed and the workspace has none.
NO_TRUTH = ("no --truth given and no truth folder in {workspace} (looked for "
            + ", ".join(d + "/" for d in WORKSPACE_TRUTH_DIRS) + ")")


def _option(role: str) -> str:
    return "--" + role.replace("_", "-")


def _first(found: Mapping[str, list[Path]], role: str | None, kind: str | None = None) -> Path | None:
    """The first file of ``role`` if it is one (a search consults it); a capture of the wrong kind is refused."""
    paths = found.get(role) if role else None
    if not paths or not Path(paths[0]).is_file():
        return None
    if kind == "capture":
        check_schema(read_meta(paths[0]), kind, paths[0])
    return Path(paths[0])


def default_paths(inp: Input, workspace: Path, identity: str | None = None, ids: Sequence[str] = (),
                  found: Mapping[str, list[Path]] | None = None) -> tuple[list[Path], Path | None]:
    """``(paths, missing)``: the default of one declared role and the path it looked for in vain (None: found).

    ``paths`` is empty when the rule has nothing to offer (a ``many`` output without ``--ids``, a search that found
    nothing); ``found`` holds the roles resolved so far (the searches consult them)."""
    d, up, ws, found = inp.default, inp.upstream, Path(workspace), found or {}
    if d is None:
        return [], None
    if d.rule == "output":
        if inp.many:
            paths = [stage_output(ws, up, i, d.suffix) for i in (ids or ([identity] if identity else []))]
        else:
            paths = [stage_output(ws, up, d.name or identity or up, d.suffix)]
        return paths, next((p for p in paths if not p.is_file()), None)
    if d.rule == "all":
        paths = list_artifacts(ws, up, d.suffix)
        return paths, None if paths else stage_dir(ws, up)
    if d.rule == "folder":
        folder = stage_dir(ws, up)
        return [folder], None if folder.is_dir() else folder
    geometry = _first(found, d.geometry)  # read first, as find_face_model does
    capture = _first(found, d.capture, "capture")
    if d.rule == "face-model":
        wild = found.get(d.wild) if d.wild else None
        fm = (wild_face_model(None, wild[0]) if wild and Path(wild[0]).is_dir() else None) \
            or find_face_model(ws, capture=capture, geometry=geometry)
        return ([fm], None) if fm is not None else ([], ws)
    if d.rule == "truth":
        td = find_truth_dir(ws, capture=capture)
        if td is None:
            return [], ws
        path = td if inp.many else td / f"{identity}.npz"
        return [path], None if path.exists() else path
    if d.rule in ("rig", "fit-rig"):
        rig = find_rig(capture) if d.rule == "rig" else find_fit_rig(ws, capture)[0]
        return ([rig], None) if rig is not None else ([], ws)
    raise ValueError(f"unknown default rule {d.rule!r}")


def _missing(inp: Input, looked: Path, workspace: Path, found: Mapping[str, list[Path]]) -> ReflectmmError:
    d = inp.default
    text = d.missing or (NO_TRUTH if d.rule == "truth" and looked == workspace else
                         "{option}: not given and none found in {workspace}" if d.rule not in PATH_RULES else
                         "{option}: not given and {path} does not exist")
    fields = {r: (str(v[0]) if v else "") for r, v in found.items()}
    fields.update(path=looked, folder=looked, workspace=workspace, option=_option(inp.role))
    return ReflectmmError(text.format(**fields))


def _order(decl: Mapping[str, Input], roles: Iterable[str] | None) -> list[str]:
    if roles is not None:
        return [r for r in roles if r in decl]
    return ([r for r, i in decl.items() if i.default.rule in PATH_RULES]
            + [r for r, i in decl.items() if i.default.rule not in PATH_RULES])


def default_inputs(stage: Stage, workspace: Path, given: Mapping[str, Iterable[Path | None]] | None = None, *,
                   identity: str | None = None, ids: Sequence[str] = (), params: Mapping[str, Any] | None = None,
                   roles: Iterable[str] | None = None, required: bool = True) -> dict[str, list[Path]]:
    """The inputs a command passes to ``stage``: the given ones (empty roles and None left out) and, for each
    declared role with a :class:`~reflectmm_cli.stages.base.Default` that was not given, its default.

    A ``many`` ``output`` role with ``ids`` gets one path per id before the given ones (what ``--ids`` means).
    ``roles`` limits the defaults to these roles, looked for in this order (default: every declared one, the
    path rules first, then the searches); ``required=False`` makes every default optional.  A default that is
    not found raises its one-line ``missing`` error, or leaves an optional role out."""
    ws = Path(workspace)
    out = {r: [Path(p) for p in v if p is not None] for r, v in (given or {}).items()}
    out = {r: v for r, v in out.items() if v}
    decl = {i.role: i for i in stage.inputs or () if i.default is not None}
    dropped: set[str] = set()
    for role in _order(decl, roles):
        inp, d = decl[role], decl[role].default
        if d.unless is not None and (params or {}).get(d.unless[0]) == d.unless[1]:
            out.pop(role, None)
            dropped.add(d.group or role)
            continue
        paths, looked = [], None
        if role not in out or (inp.many and d.rule == "output" and ids):  # --ids adds to the given paths
            if any(n not in out for n in d.needs):
                continue
            paths, looked = default_paths(inp, ws, identity, ids, out)
            if looked is not None and paths and not d.checked:
                looked = None  # a composed path passed on as it is: the stage reports it
            if looked is None and not paths and role not in out:
                dropped.add(d.group or role)  # nothing to offer (a per-id role without --ids)
                continue
        if looked is None and d.check_given:
            looked = next((p for p in out.get(role, []) if not p.exists()), None)
        if looked is not None:
            if not (d.optional or not required):
                raise _missing(inp, looked, ws, {**out, role: paths + out.get(role, [])})
            out.pop(role, None)
            dropped.add(d.group or role)
            continue
        out[role] = paths + out.get(role, [])
        if d.listed:
            out[role] = [q for p in out[role] for q in (files_in(p, d.suffix) if p.suffix != d.suffix else [p])]
            if not out[role]:
                out.pop(role)
    for role, inp in decl.items():
        if inp.default.group in dropped:
            out.pop(role, None)
    return out

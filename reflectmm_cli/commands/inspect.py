"""``reflectmm inspect FILE...``: what an artifact is, where it came from, what it holds.

For each NPZ or EXR artifact: kind, schema version, producer, params, inputs (role,
path, sha256, schema), cache key, and every array's name, shape, dtype and value range
(min/max ignoring NaN, count of non-finite values).  A file that is missing, corrupt or
not an artifact gives one error line; the other files are still inspected and the exit
status is 1.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import click
import numpy as np

from reflectmm_cli.artifacts import (META_KEY, SCHEMA_MAJOR, _meta_from_npz, _npz_member, _open_npz, parse_schema,
                                     read_exr, read_meta)
from reflectmm_cli.commands._common import json_option, silence_stdout
from reflectmm_cli.errors import ArtifactError, ReflectmmError


def array_summary(name: str, arr: np.ndarray) -> dict[str, Any]:
    """name, shape, dtype and, for numeric arrays, min/max over finite values and the non-finite count."""
    out: dict[str, Any] = {"name": name, "shape": list(arr.shape), "dtype": str(arr.dtype)}
    if arr.dtype.kind in "biuf" and arr.size:
        a = arr
        if a.dtype.kind == "f":
            finite = np.isfinite(a)
            out["nonfinite"] = int(a.size - np.count_nonzero(finite))
            out["nan"] = int(np.count_nonzero(np.isnan(a)))
            vals = a[finite]
        else:
            out["nonfinite"] = 0
            vals = a.reshape(-1)
        if vals.size:
            out["min"], out["max"] = vals.min().item(), vals.max().item()
            if a.dtype.kind == "b":
                out["min"], out["max"] = bool(out["min"]), bool(out["max"])
                out["true"] = int(np.count_nonzero(a))
        else:
            out["min"] = out["max"] = None
    elif arr.dtype.kind == "c" and arr.size:
        finite = np.isfinite(arr)
        out["nonfinite"] = int(arr.size - np.count_nonzero(finite))
        mag = np.abs(arr[finite])
        out["min_abs"], out["max_abs"] = (mag.min().item(), mag.max().item()) if mag.size else (None, None)
    elif arr.dtype.kind in "US" and arr.size:
        flat = arr.reshape(-1)
        out["first"] = [str(x) if len(str(x)) <= 24 else str(x)[:21] + "..." for x in flat[:3]]
    return out


def _page_arrays(path: Path) -> list[dict[str, Any]]:
    """The arrays of a viewer page's bundle, named by their place in it."""
    from reflectmm_cli.viewer import decode_blob, iter_blobs, read_bundle

    return [array_summary(name, decode_blob(rec)) for name, rec in iter_blobs(read_bundle(path) or {})]


def _check_npz_like(path: Path) -> None:
    """A file that is neither named .npz nor a zip archive (a safetensors encoder, a TOML rig, a PNG) is not of a
    type inspect reads: said so, with its suffix, instead of "not an NPZ artifact (not a zip archive)"."""
    if path.suffix.lower() == ".npz":
        return
    with open(path, "rb") as f:
        if f.read(2) == b"PK":  # a zip, maybe truncated: the NPZ reader says what is wrong with it
            return
    raise ArtifactError(f"not a supported artifact type ({path.suffix or 'no suffix'}; inspect reads NPZ and EXR "
                        f"artifacts and viewer HTML pages)", path)


def inspect_artifact(path: str | Path) -> dict[str, Any]:
    """Library function: a JSON-able description of one artifact; raises ReflectmmError if it is not one."""
    path = Path(path)
    if not path.exists():
        raise ArtifactError("file not found", path)
    if path.is_dir():
        raise ArtifactError("is a directory, expected an artifact file", path)
    arrays: list[dict[str, Any]] = []
    if path.suffix.lower() == ".exr":
        channels, meta = read_exr(path)
        if not meta:
            raise ArtifactError("not a reflectmm artifact (EXR without a reflectmm:meta header attribute)", path)
        fmt = "exr"
        for name, ch in channels.items():
            arrays.append(array_summary(name, ch))
    elif path.suffix.lower() in (".html", ".htm"):
        fmt = "html"
        meta = read_meta(path)
        arrays = _page_arrays(path)
    else:
        _check_npz_like(path)
        fmt = "npz"
        with _open_npz(path) as npz:
            meta = _meta_from_npz(npz, path)
            try:
                for name in npz.files:
                    if name != META_KEY:
                        arrays.append(array_summary(name, _npz_member(npz, name, path)))
            except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
                raise ArtifactError(f"truncated or corrupt NPZ member ({exc})", path) from None
    kind, major = parse_schema(meta.get("schema"), path)
    doc: dict[str, Any] = {
        "path": str(path), "format": fmt, "kind": kind, "schema": meta.get("schema"), "schema_major": major,
        "producer": meta.get("producer", {}), "params": meta.get("params", {}), "inputs": meta.get("inputs", []),
        "cache_key": meta.get("cache_key"), "arrays": arrays, "size_bytes": path.stat().st_size,
    }
    supported = SCHEMA_MAJOR.get(kind)
    if supported is None:
        doc["note"] = f"unknown kind '{kind}' for this reflectmm release"
    elif major > supported:
        doc["note"] = f"schema /{major} is newer than this release reads (up to /{supported})"
    extra = {k: v for k, v in meta.items() if k not in ("schema", "producer", "params", "inputs", "cache_key")}
    if extra:
        doc["meta_extra"] = extra
    return doc


#: Inputs shown per role in the text report (``--json`` lists all).
MAX_INPUTS_SHOWN = 8


def _fmt_val(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def format_inspection(doc: dict[str, Any]) -> list[str]:
    """Human-readable lines for one :func:`inspect_artifact` document."""
    prod = doc["producer"]
    lines = [f"{doc['path']}",
             f"  kind:      {doc['kind']}  (schema {doc['schema']}, {doc['format'].upper()}, "
             f"{doc['size_bytes']} bytes)"]
    if doc.get("note"):
        lines.append(f"  note:      {doc['note']}")
    lines.append(f"  producer:  {prod.get('tool', '?')} {prod.get('version', '?')}, stage {prod.get('stage', '?')} "
                 f"v{prod.get('stage_version', '?')}")
    lines.append(f"  cache_key: {doc['cache_key']}")
    params = doc["params"]
    if params:
        lines.append("  params:")
        for k in sorted(params):
            lines.append(f"    {k} = {json.dumps(params[k], sort_keys=True)}")
    else:
        lines.append("  params:    (none)")
    if doc["inputs"]:
        lines.append(f"  inputs ({len(doc['inputs'])}):")
        by_role: dict[str, list[dict]] = {}
        for ref in doc["inputs"]:
            by_role.setdefault(str(ref.get("role", "?")), []).append(ref)
        for role, refs in by_role.items():
            shown = refs if len(refs) <= MAX_INPUTS_SHOWN else refs[:MAX_INPUTS_SHOWN - 1]
            for ref in shown:
                sch = f"  [{ref['schema']}]" if ref.get("schema") else ""
                lines.append(f"    {role}: {ref.get('path', '?')}  sha256 {ref.get('sha256', '?')}{sch}")
            if len(shown) < len(refs):
                lines.append(f"    {role}: ... {len(refs) - len(shown)} more (--json lists all)")
    else:
        lines.append("  inputs:    (none)")
    for k, v in sorted((doc.get("meta_extra") or {}).items()):
        lines.append(f"  {k}: {json.dumps(v, sort_keys=True)[:200]}")
    lines.append(f"  arrays ({len(doc['arrays'])}):")
    rows = []
    for a in doc["arrays"]:
        shape = str(tuple(a["shape"]))
        if "min" in a:
            rng = f"[{_fmt_val(a['min'])}, {_fmt_val(a['max'])}]" if a["min"] is not None else "[no finite values]"
            if a.get("nonfinite"):
                rng += f"  non-finite: {a['nonfinite']}"
        elif "max_abs" in a:
            rng = f"|z| in [{_fmt_val(a['min_abs'])}, {_fmt_val(a['max_abs'])}]"
        elif "first" in a:
            rng = ", ".join(a["first"]) + (" ..." if int(np.prod(a["shape"])) > 3 else "")
        else:
            rng = "(empty)"
        rows.append((a["name"], shape, a["dtype"], rng))
    if rows:
        w = [max(len(r[i]) for r in rows) for i in range(3)]
        for r in rows:
            lines.append(f"    {r[0].ljust(w[0])}  {r[1].ljust(w[1])}  {r[2].ljust(w[2])}  {r[3]}")
    return lines


@click.command("inspect")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
@json_option
@click.pass_context
def inspect_cmd(ctx, files, as_json):
    """Show kind, schema, producer, params, inputs and array ranges of NPZ/EXR artifacts."""
    docs, errors = [], []
    for f in files:
        try:
            docs.append(inspect_artifact(f))
        except ReflectmmError as exc:
            errors.append({"path": str(f), "error": str(exc)})
            click.echo(f"reflectmm: error: {exc}", err=True)
    try:
        if as_json:
            click.echo(json.dumps({"artifacts": docs, "errors": errors}, indent=2, sort_keys=True, default=str))
        else:
            for i, d in enumerate(docs):
                if i:
                    click.echo("")
                for line in format_inspection(d):
                    click.echo(line)
    except BrokenPipeError:  # `reflectmm inspect ... | head`: the reader has gone, that is not an error
        silence_stdout()
    if errors:
        ctx.exit(1)


COMMANDS = [inspect_cmd]

"""``reflectmm checksum``: a small built-in verb that records the sha256 of input files.

It is a real, useful stage (a manifest of a data set, per identity or overall) and is
what the planner's tests use before any pipeline stage is involved.  It is also the
reference layout of a verb module: a library function, a registered stage, a thin
click command, and ``COMMANDS``.
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from reflectmm_cli.artifacts import sha256_file, write_artifact
from reflectmm_cli.commands._common import emit, json_option, output_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import StageContext, register_stage, walk_files


def checksum_files(paths: list[Path]) -> tuple[list[str], list[str], list[int]]:
    """Library function: (names, sha256 hex digests, sizes) of files, folders expanded recursively."""
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files.extend(walk_files(p))
        elif p.exists():
            files.append(p)
        else:
            raise ReflectmmError("file not found", p)
    return [f.name for f in files], [sha256_file(f) for f in files], [f.stat().st_size for f in files]


def _walk(ctx: StageContext) -> dict[str, list[Path]]:
    """The input files with folders expanded (so provenance lists every file checksummed)."""
    from reflectmm_cli.stages import get_stage

    return get_stage("checksum").files_to_hash(ctx)


def discover_checksum_ids(ctx: StageContext) -> list[str] | None:
    """``foreach = "all found"``: the names (stems) of the paths matching the ``discover`` param,
    a glob relative to the workspace (e.g. ``"data/*"`` gives one identity per folder); without
    that param, None (the recipe planner then takes the upstream per-identity stage's ids)."""
    import glob

    pattern = ctx.param("discover")
    if not pattern:
        return None  # no opinion: the planner uses the upstream per-identity stage's ids
    full = Path(pattern) if Path(pattern).is_absolute() else Path(ctx.workspace) / pattern
    return sorted({Path(p).stem for p in glob.glob(str(full))})


@register_stage("checksum", version=1, per_identity=False, discover_ids=discover_checksum_ids,
                help="sha256 manifest of input files")
def run_checksum(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    files = ctx.input_list("files")
    if ctx.param("fail_if_contains"):
        marker = str(ctx.param("fail_if_contains")).encode()
        for f in files:
            walk = walk_files(f) if f.is_dir() else [f]
            for q in walk:
                if q.is_file() and marker in q.read_bytes():
                    raise ReflectmmError(f"contains the marker {ctx.param('fail_if_contains')!r}", q)
    names, digests, sizes = checksum_files(files)
    write_artifact(out, "checksum", {"names": np.array(names, dtype=str), "sha256": np.array(digests, dtype=str),
                                     "size": np.array(sizes, dtype=np.int64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent, files=_walk(ctx)), producer=ctx.producer(),
                   cache_key=ctx.cache_key)
    return [out]


@click.command("checksum")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--id", "identity", default=None, help="Identity this manifest belongs to (names the output).")
@workspace_option
@output_option
@json_option
def checksum_cmd(files, identity, workspace, output, as_json):
    """Write a sha256 manifest of FILES (folders are walked) as a `checksum` artifact."""
    paths = run_stage_cli("checksum", workspace=workspace, identity=identity, inputs={"files": list(files)},
                          output=output)
    emit(paths, as_json)


COMMANDS = [checksum_cmd]

"""Stage ``checksum``: a small built-in verb that records the sha256 of input files.

It is a real, useful stage (a manifest of a data set, per identity or overall) and is what the planner's tests
use before any pipeline stage is involved.  Its params are open: besides the declared ones, any recipe param
is recorded in the manifest's meta (and keys its cache), which the recipe tests use to exercise params that
reference other stages' outputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import sha256_file, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Input, Stage, StageContext, walk_files

VERB = "checksum"

PARAMS = (
    Param("fail_if_contains", "str", None, option="",
          help="Fail (naming the file) if an input file contains this marker (tests a failing task)."),
    Param("discover", "str", None, option="",
          help='foreach = "all found": a glob relative to the workspace whose matches\' stems are the identities.'),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('files', 'any files', many=True),
)


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
    return STAGE.files_to_hash(ctx)


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


def run(ctx: StageContext) -> list[Path]:
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



STAGE = Stage(VERB, version=1, run=run, per_identity=False, discover_ids=discover_checksum_ids, params=PARAMS,
              open_params=True, help="sha256 manifest of input files", inputs=INPUTS)

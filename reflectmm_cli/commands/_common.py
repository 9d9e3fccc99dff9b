"""Shared click options and the helper that runs a stage from the command line."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

import click

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import compute_cache_key, default_workspace, get_stage, resolve_device


def workspace_option(f):
    return click.option("--workspace", "-w", type=click.Path(file_okay=False, path_type=Path), default=None,
                        help="Workspace root (default: $REFLECTMM_WORKSPACE or the current directory).")(f)


def json_option(f):
    return click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of paths.")(f)


def device_option(f):
    return click.option("--device", default="cpu", show_default=True,
                        help="torch device: cpu, cuda, cuda:N, or auto.")(f)


def output_option(f):
    return click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
                        help="Explicit output path (overrides <workspace>/<stage>/<id>.npz).")(f)


def parse_ids(ids: str | None, id_file: Path | None = None) -> list[str]:
    """Identities from ``--ids 001,002`` (or ranges ``001-010``) and/or a file (one per line, # comments)."""
    out: list[str] = []
    if ids:
        for tok in ids.replace(" ", ",").split(","):
            tok = tok.strip()
            if not tok:
                continue
            if "-" in tok:
                a, b = tok.split("-", 1)
                if not (a.isdigit() and b.isdigit()) or int(b) < int(a):
                    raise ReflectmmError(f"--ids: bad range '{tok}'")
                width = len(a)
                out.extend(str(i).zfill(width) for i in range(int(a), int(b) + 1))
            else:
                out.append(tok)
    if id_file is not None:
        try:
            lines = Path(id_file).read_text().splitlines()
        except OSError as exc:
            raise ReflectmmError(f"cannot read id file ({exc.strerror})", id_file) from None
        out.extend(ln.split("#", 1)[0].strip() for ln in lines if ln.split("#", 1)[0].strip())
    seen: set[str] = set()
    return [i for i in out if not (i in seen or seen.add(i))]


def emit(paths: Iterable[Path], as_json: bool = False, extra: dict[str, Any] | None = None) -> None:
    """Print results on stdout: one path per line, or one JSON document."""
    paths = [str(p) for p in paths]
    if as_json:
        doc = {"outputs": paths}
        if extra:
            doc.update(extra)
        click.echo(json.dumps(doc, indent=2, sort_keys=True, default=str))
    else:
        for p in paths:
            click.echo(p)


def run_stage_cli(verb: str, *, workspace: Path | None, identity: str | None = None,
                  params: dict[str, Any] | None = None, inputs: dict[str, list[Path]] | None = None,
                  output: Path | None = None, device: str = "cpu", stage_name: str | None = None) -> list[Path]:
    """Run a registered stage once from the CLI, with the same cache key a recipe would compute."""
    stage = get_stage(verb)
    ctx = stage.context(workspace=(workspace or default_workspace()).resolve(), stage_name=stage_name or verb,
                        identity=identity, params=dict(params or {}),
                        inputs={k: [Path(p) for p in v] for k, v in (inputs or {}).items()},
                        output=output, device=resolve_device(device) if device else "cpu")
    for role, paths in ctx.inputs.items():
        for p in paths:
            if not Path(p).exists():
                raise ReflectmmError(f"input '{role}' not found", p)
    ctx = ctx.with_(cache_key=compute_cache_key(stage, ctx))
    return list(stage.run(ctx))

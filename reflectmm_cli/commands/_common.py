"""Shared click options, and click options generated from a stage's parameter declaration.

Nothing but the command modules imports this module (it imports click); stages, the planner and the library
use :mod:`reflectmm_cli.stages` and :mod:`reflectmm_cli.workspace` instead.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Iterable

import click

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param, ParamError, parse_ids, parse_list
from reflectmm_cli.stages import get_stage, run_stage
from reflectmm_cli.workspace import check_id


def workspace_option(f):
    return click.option("--workspace", "-w", type=click.Path(file_okay=False, path_type=Path), default=None,
                        help="Workspace root (default: $REFLECTMM_WORKSPACE or the current directory).")(f)


def id_callback(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
    """click callback of ``--id``-like options: each value must be a safe id
    (:func:`reflectmm_cli.workspace.check_id`); a one-line error naming the option, the id and the rule."""
    if value is None:
        return None
    where = max(param.opts, key=len)
    if isinstance(value, tuple):
        return tuple(check_id(v, where) for v in value)
    return check_id(value, where)


def json_option(f):
    return click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of paths.")(f)


def device_option(f):
    return click.option("--device", default="cpu", show_default=True,
                        help="torch device: cpu, cuda, cuda:N, or auto.")(f)


def output_option(f=None, *, help: str = "Explicit output path (overrides <workspace>/<stage>/<id>.npz)."):
    """``-o/--output FILE``; ``@output_option`` or ``@output_option(help=...)`` for a verb's own wording."""
    deco = click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None, help=help)
    return deco(f) if f is not None else deco


class ParamType(click.ParamType):
    """A click type that validates through the stage's :class:`~reflectmm_cli.params.Param` (the same rules a
    recipe's params go through); a refused value is the same one-line error (exit 1) naming the option."""

    def __init__(self, param: Param):
        self.param = param
        self.name = param.metavar or param.kind.upper()

    def convert(self, value, p, ctx):
        if self.param.multiple:  # each repeated value is kept raw; the tuple is converted as a whole
            return value
        try:
            return self.param.coerce(value)
        except ParamError as exc:
            raise ParamError(f"{self.param.flag}: {str(exc).split(': ', 1)[-1]}") from None


def param_options(params: Iterable[Param], only: Iterable[str] | None = None,
                  exclude: Iterable[str] = ()) -> Callable:
    """Decorator adding one click option per declared param (``--name-with-dashes``, help with the unit and
    the default).  Options default to None ("not given"): the stage fills the declared default, so the
    command line and a recipe resolve to the same params (and cache key)."""
    only = set(only) if only is not None else None
    chosen = [p for p in params if p.option != "" and p.name not in set(exclude)
              and (only is None or p.name in only)]

    def deco(f):
        for p in reversed(chosen):
            help_ = p.help_text()
            if p.kind == "bool":
                if p.default is True and p.flag.startswith("--no-"):
                    f = click.option(p.flag, *p.aliases, p.name, is_flag=True, flag_value=False, default=None,
                                     help=help_)(f)
                else:
                    f = click.option(p.flag, *p.aliases, p.name, is_flag=True, flag_value=True, default=None,
                                     help=help_)(f)
                continue
            typ: Any = click.Choice(list(p.choices)) if p.choices and p.kind == "str" else ParamType(p)
            if p.range is not None:
                lo, hi = p.range
                help_ += "  [" + " ".join(x for x in (
                    f"{lo:g} {'<' if p.low_open else '≤'}" if lo is not None else "", "x",
                    f"≤ {hi:g}" if hi is not None else "") if x) + "]"
            if p.default is not None and p.default != {}:
                help_ += f"  [default: {p.default_text()}]"
            f = click.option(p.flag, *p.aliases, p.name, type=typ, default=None, multiple=p.multiple,
                             metavar=p.metavar, help=help_)(f)
        return f

    return deco


def given_params(kwargs: dict[str, Any], params: Iterable[Param]) -> dict[str, Any]:
    """Pop the declared params out of a click command's kwargs; only the ones given (not None/empty)."""
    out = {}
    for p in params:
        if p.name in kwargs:
            v = kwargs.pop(p.name)
            if v is None or (p.multiple and not v):
                continue
            out[p.name] = v
    return out


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


def silence_stdout() -> None:
    """Point stdout at /dev/null (the reader of a pipe has gone: `reflectmm ... | head`)."""
    import os
    import sys

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # not a real file (e.g. a test runner's buffer)
        pass


def run_stage_cli(verb: str, *, workspace: Path | None, identity: str | None = None,
                  params: dict[str, Any] | None = None, inputs: dict[str, list[Path]] | None = None,
                  output: Path | None = None, device: str = "cpu", stage_name: str | None = None) -> list[Path]:
    """Run a stage once from the command line (:func:`reflectmm_cli.stages.run_stage`)."""
    return run_stage(get_stage(verb), workspace=workspace, identity=identity, params=params, inputs=inputs,
                     output=output, device=device, stage_name=stage_name)


__all__ = ["ParamType", "device_option", "emit", "given_params", "id_callback", "json_option", "output_option",
           "param_options",
           "parse_ids", "parse_list", "run_stage_cli", "silence_stdout", "workspace_option", "ReflectmmError"]

"""Methods of an evaluation (Tables 2 and 3, relighting) and how stages name their inputs.

A *method* is a reflectance model, optionally with the encoder trained for it. N methods go into one stage by
input **roles named after the method**: ``model_<name>`` (a ``reflectance-model`` artifact) and
``encoder_<name>`` (the encoder safetensors that ``finetune`` writes). The order of the table rows is the
``methods`` param (default: the names found in the roles, sorted). Names are lower case letters, digits, ``-``
and ``_`` (they become role names, TOML keys and table labels):

```toml
[stages.evaluate-reconstruction]
inputs = { data = "@prepare-wild.output", light_model = "@build-light-pca.output",
           model_finetuned = "@finetune.output", encoder_finetuned = "@finetune.outputs.finetune_encoder", ... }
params = { methods = ["diffuse-only", "albedomm", "initial", "finetuned"] }
```

On the command line the same pairs are given as ``--method NAME MODEL ENCODER`` (ENCODER ``-``: none).

Also here: :func:`command_line`, the ``reflectmm ...`` command that reproduces a stage's run (stored in each
evaluation artifact so the report can print every number with the command that made it).
"""
from __future__ import annotations

import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from reflectmm_cli.errors import ReflectmmError

__all__ = ["MODEL_PREFIX", "ENCODER_PREFIX", "NAME_RE", "check_method_name", "check_method_names", "Method",
           "methods_from_inputs", "method_inputs", "command_line"]

MODEL_PREFIX = "model_"
ENCODER_PREFIX = "encoder_"
NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,39}$")


def check_method_name(name: str) -> str:
    """``name`` if it is a valid method name, else ValueError (one line)."""
    if not NAME_RE.match(str(name)):
        raise ValueError(f"method name {name!r} must be 1-40 lower-case letters, digits, '-' or '_' "
                         "(starting with a letter or digit)")
    return str(name)


def check_method_names(names: Sequence[str]) -> None:
    """Every name valid and no name twice (the ``check`` of a ``methods`` param)."""
    seen = set()
    for n in names:
        check_method_name(n)
        if n in seen:
            raise ValueError(f"method '{n}' given twice")
        seen.add(n)


@dataclass(frozen=True)
class Method:
    """One method: ``name``, ``model`` path, ``encoder`` path or None."""

    name: str
    model: Path
    encoder: Path | None = None


def methods_from_inputs(inputs: Mapping[str, Sequence[Path]], names: Sequence[str] | None = None, *,
                        need_encoder: bool = False, stage: str = "evaluate") -> list[Method]:
    """The methods of a stage's inputs (roles ``model_<name>`` / ``encoder_<name>``), in the order of ``names``
    (default: sorted names of the model roles).

    Raises one-line :class:`ReflectmmError` when a named method has no model role, a role is given more than one
    file, an encoder has no model, a role names no listed method, or (``need_encoder``) an encoder is missing.
    """
    models = {r[len(MODEL_PREFIX):]: list(v) for r, v in inputs.items() if r.startswith(MODEL_PREFIX)}
    encs = {r[len(ENCODER_PREFIX):]: list(v) for r, v in inputs.items() if r.startswith(ENCODER_PREFIX)}
    for kind, d in (("model", models), ("encoder", encs)):
        for n, v in d.items():
            if len(v) != 1:
                raise ReflectmmError(f"{stage}: input '{kind}_{n}' has {len(v)} files, expected exactly one")
    for n in encs:
        if n not in models:
            raise ReflectmmError(f"{stage}: input 'encoder_{n}' has no matching 'model_{n}'")
    order = list(names) if names else sorted(models)
    if not order:
        raise ReflectmmError(f"{stage}: no methods given (inputs 'model_<name>' / --method NAME MODEL [ENCODER])")
    for n in order:
        try:
            check_method_name(n)
        except ValueError as exc:
            raise ReflectmmError(f"{stage}: {exc}") from None
        if n not in models:
            raise ReflectmmError(f"{stage}: method '{n}' has no input 'model_{n}' (given: "
                                 f"{', '.join(sorted(models)) or 'none'})")
        if need_encoder and n not in encs:
            raise ReflectmmError(f"{stage}: method '{n}' has no input 'encoder_{n}' (the encoder trained for "
                                 "this model)")
    extra = sorted(set(models) - set(order))
    if extra:
        raise ReflectmmError(f"{stage}: input 'model_{extra[0]}' names no method of the 'methods' param "
                             f"({', '.join(order)})")
    return [Method(n, Path(models[n][0]), Path(encs[n][0]) if n in encs else None) for n in order]


def method_inputs(specs: Sequence[Sequence[Any]]) -> tuple[dict[str, list[Path]], list[str]]:
    """``--method NAME MODEL ENCODER`` values (tuples of 2 or 3 strings; an ENCODER of ``-`` or ``none`` means
    no encoder) → (inputs by role, method names in order)."""
    inputs: dict[str, list[Path]] = {}
    names: list[str] = []
    for spec in specs:
        spec = [str(s) for s in spec]
        if len(spec) not in (2, 3):
            raise ReflectmmError(f"--method takes NAME MODEL [ENCODER], got {' '.join(spec)}")
        try:
            name = check_method_name(spec[0])
        except ValueError as exc:
            raise ReflectmmError(f"--method: {exc}") from None
        if name in names:
            raise ReflectmmError(f"--method: method '{name}' given twice")
        names.append(name)
        inputs[MODEL_PREFIX + name] = [Path(spec[1])]
        if len(spec) == 3 and spec[2].lower() not in ("-", "none", ""):
            inputs[ENCODER_PREFIX + name] = [Path(spec[2])]
    return inputs, names


def _workspace_path(p: Path, base: Path) -> str:
    """``p`` as written in a command line run from the workspace ``base`` (absolute on another drive)."""
    try:
        return os.path.relpath(Path(p).resolve(), Path(base).resolve()).replace(os.sep, "/")
    except ValueError:  # another drive
        return str(p)


def command_line(words: Sequence[str], params: Mapping[str, Any], inputs: Mapping[str, Sequence[Path]], *,
                 workspace: Path, output: Path | None = None, role_options: Mapping[str, str] | None = None,
                 identity: str | None = None, skip_params: Sequence[str] = (), declared: Sequence[Any] = ()) -> str:
    """The ``reflectmm`` command (run from the workspace root) equivalent to a stage run: ``words`` (e.g.
    ``["evaluate", "reconstruction"]``), every param as ``--name value``, the methods as ``--method NAME MODEL
    [ENCODER]`` and the other roles as their options (``role_options``: role → option; roles absent from it are
    left out), paths relative to the workspace. With the stage's ``declared`` params, values equal to the default
    and recipe-only params are left out and each param uses its declared flag. Deterministic (sorted), no
    absolute paths of the workspace."""
    parts = ["reflectmm", *words]
    if identity is not None:
        parts += ["--id", identity]
    role_options = dict(role_options or {})
    for role in sorted(inputs):
        if role in role_options:
            for p in inputs[role]:
                parts += [role_options[role], _workspace_path(p, workspace)]
    names = list(params.get("methods")
                 or sorted(r[len(MODEL_PREFIX):] for r in inputs if r.startswith(MODEL_PREFIX)))
    for n in names:
        m = inputs.get(MODEL_PREFIX + n)
        if not m:
            continue
        parts += ["--method", n, _workspace_path(m[0], workspace)]
        e = inputs.get(ENCODER_PREFIX + n)
        parts.append(_workspace_path(e[0], workspace) if e else "-")
    decl = {d.name: d for d in (declared or ())}
    for k in sorted(params):
        if k in ("methods", *skip_params):
            continue
        v, d = params[k], decl.get(k)
        if d is not None and (d.option == "" or v == d.default):
            continue  # recipe-only params and defaults are not spelled out
        flag = d.flag if d is not None else "--" + k.replace("_", "-")
        if isinstance(v, bool):
            if d is not None and flag.startswith("--no-"):
                parts += [flag] if not v else []
            else:
                parts += [flag] if v else []
        elif isinstance(v, (list, tuple)):
            parts += [flag, ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)]
        elif v is not None:
            parts += [flag, f"{v:g}" if isinstance(v, float) else str(v)]
    if output is not None:
        parts += ["-o", _workspace_path(output, workspace)]
    return " ".join(shlex.quote(p) for p in parts)

"""Stage parameters declared once: name, kind, default, range or choices, unit, help, cache role.

A stage lists its parameters as a tuple of :class:`Param`.  The same declaration

* generates the stage's click options (``reflectmm_cli.commands._common.param_options``),
* validates recipe params (``reflectmm run``) with exactly the CLI's rules, and
* fills defaults and canonicalises values **before** the cache key is computed, so the command line and a
  recipe give the same key for the same work, and changing a default invalidates by itself.

Canonical values: ``int``/``float``/``str``/``bool`` scalars, lists for list kinds; a parameter whose value
is None (not given, no default) is left out of the resolved dict.

No click here: the planner and Dask workers import this module.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

from reflectmm_cli.errors import ReflectmmError

__all__ = ["Param", "ParamError", "parse_list", "parse_ids", "resolve_params", "closest_name", "named_twice"]

#: Parameter kinds: scalars, comma lists, ``WxH`` sizes, and ``custom`` (a ``convert`` function).
KINDS = ("int", "float", "str", "bool", "floats", "ints", "strs", "size", "path", "custom")

#: The range of every random seed: numpy's generators take no negative seed, torch's none of 2**63 or more.
SEED_RANGE = (0, 2 ** 63 - 1)


class ParamError(ReflectmmError):
    """A parameter value or name that the declaration refuses (one line, names the parameter)."""


def parse_list(text: Any, what: str = "value", item: Callable[[str], Any] = str, *, sep: str = ",",
               allow_empty: bool = False) -> list[Any]:
    """The one comma-list parser: ``"1,8,64"`` (spaces allowed around items) or a list/tuple → list of ``item``.

    An empty item (``"1,,8"``, a trailing comma) is an error, so is an empty list unless ``allow_empty``.
    Raises :class:`ParamError` naming ``what`` and the offending item.
    """
    if isinstance(text, (list, tuple)):
        raw = list(text)
    else:
        s = str(text).strip()
        raw = [] if s == "" else [t.strip() for t in s.split(sep)]
        if any(t == "" for t in raw):
            raise ParamError(f"{what}: empty item in {text!r} (a doubled or trailing '{sep}')")
    if not raw and not allow_empty:
        raise ParamError(f"{what}: empty list")
    out = []
    for t in raw:
        try:
            out.append(item(t))
        except (TypeError, ValueError) as exc:
            detail = f" ({exc})" if str(exc) and "invalid literal" not in str(exc) else ""
            raise ParamError(f"{what}: {t!r} is not a valid item{detail}") from None
    return out


def parse_pairs(items: Any, option: str, usage: str, *, error: type[ReflectmmError] = ParamError
                ) -> list[tuple[str, Any]]:
    """``KEY=VALUE`` settings: a mapping (a recipe's inline table), a ``"a=1,b=2"`` string or a list of such
    strings (a repeated option) → ``[(key, value), …]``, keys and string values stripped.

    A token without ``=`` raises ``error`` naming ``option``, the token and the ``usage`` expected."""
    if isinstance(items, Mapping):
        return [(str(k), v) for k, v in items.items()]
    pairs = []
    for it in ([items] if isinstance(items, str) else items or []):
        for tok in parse_list(str(it), option, allow_empty=True):
            if "=" not in tok:
                raise error(f"{option} {tok!r}: expected {usage}")
            k, v = tok.split("=", 1)
            pairs.append((k.strip(), v.strip()))
    return pairs


def _as_int(v: Any) -> int:
    if isinstance(v, bool):
        raise ValueError("a boolean, expected an integer")
    if isinstance(v, int):
        return int(v)
    if isinstance(v, float):
        if not math.isfinite(v) or not v.is_integer():
            raise ValueError(f"{v!r} is not an integer")
        return int(v)
    if isinstance(v, str):
        s = v.strip()
        try:
            return int(s)
        except ValueError:
            try:
                f = float(s)
            except ValueError:
                raise ValueError(f"{v!r} is not an integer") from None
            return _as_int(f)
    raise ValueError(f"{v!r} is not an integer")


def _as_float(v: Any) -> float:
    if isinstance(v, bool):
        raise ValueError("a boolean, expected a number")
    if isinstance(v, (int, float)):
        f = float(v)
    elif isinstance(v, str):
        try:
            f = float(v.strip())
        except ValueError:
            raise ValueError(f"{v!r} is not a number") from None
    else:
        raise ValueError(f"{v!r} is not a number")
    if not math.isfinite(f):
        raise ValueError(f"{v!r} is not a finite number")
    return f


def _as_bool(v: Any) -> bool:
    if isinstance(v, bool):
        return v
    if isinstance(v, str) and v.strip().lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
        return v.strip().lower() in ("true", "yes", "on", "1")
    if isinstance(v, int) and v in (0, 1):
        return bool(v)
    raise ValueError(f"{v!r} is not true or false")


def _as_str(v: Any) -> str:
    if isinstance(v, (str, int, float)) and not isinstance(v, bool):
        return str(v)
    raise ValueError(f"{v!r} is not a string")


def _as_size(v: Any) -> str:
    if isinstance(v, (list, tuple)) and len(v) == 2:
        w, h = _as_int(v[0]), _as_int(v[1])
    else:
        try:
            ws, hs = str(v).lower().split("x")
            w, h = _as_int(ws), _as_int(hs)
        except ValueError:
            raise ValueError(f"{v!r} is not WxH (e.g. 640x480)") from None
    return f"{w}x{h}"


@dataclass(frozen=True)
class Param:
    """One stage parameter, declared once.

    Attributes:
        name: snake_case name (recipe key; ``--name-with-dashes`` on the command line).
        kind: one of :data:`KINDS`.
        default: value when not given (None: absent unless given).
        range: (low, high) inclusive bounds (None for an open side) of a number or of every list item.
        choices: the allowed values of a ``str`` (or every item of ``strs``).
        unit: physical unit shown in the help (``px``, ``mm``, ``texels``...).
        help: one-line help.
        invalidates_cache: whether the value enters the cache key (False for execution details).
        option: the command-line option (default ``--name``; ``""`` = not on the command line; for a bool
            whose default is True a ``--no-...`` flag that sets it False).
        low_open: the lower bound is exclusive (e.g. exponents > 0).
        check: extra validation of the canonical value; raises ValueError with a message.
        convert: ``custom`` kind: value (CLI string(s) or recipe value) → canonical JSON-able value.
        multiple: the option may be repeated (``custom`` kind; the function gets the tuple).
        none_word: a string meaning "None" (e.g. ``"all"`` cameras); an empty list is refused, not taken for it.
        metavar: click metavar.
        aliases: further option names (``-n``).
        allow_empty: a list kind may be empty (``""`` on the command line, ``[]`` in a recipe), e.g. "no rounds".
    """

    name: str
    kind: str = "str"
    default: Any = None
    range: tuple[float | None, float | None] | None = None
    choices: tuple[str, ...] | None = None
    unit: str = ""
    help: str = ""
    invalidates_cache: bool = True
    option: str | None = None
    low_open: bool = False
    check: Callable[[Any], None] | None = None
    convert: Callable[[Any], Any] | None = None
    multiple: bool = False
    none_word: str | None = None
    metavar: str | None = None
    aliases: tuple[str, ...] = ()
    allow_empty: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"param {self.name}: unknown kind {self.kind!r}")

    @property
    def flag(self) -> str:
        """The command-line option name."""
        return self.option if self.option else "--" + self.name.replace("_", "-")

    def _bounds(self, x: float) -> None:
        if self.range is None:
            return
        lo, hi = self.range
        if lo is not None and (x <= lo if self.low_open else x < lo):
            raise ValueError(f"{x:g} is {'not above' if self.low_open else 'below'} the minimum {lo:g}")
        if hi is not None and x > hi:
            raise ValueError(f"{x:g} is above the maximum {hi:g}")

    def _choice(self, s: str) -> str:
        if self.choices is not None and s not in self.choices:
            raise ValueError(f"{s!r} is not one of {', '.join(self.choices)}")
        return s

    def coerce(self, value: Any) -> Any:
        """The canonical value of ``value`` (CLI string or recipe value); :class:`ParamError` if refused."""
        try:
            v = self._coerce(value)
            if v is not None and self.check is not None:
                self.check(v)
            return v
        except ParamError as exc:
            raise ParamError(f"{self.name}: {str(exc).split(': ', 1)[-1]}") from None
        except (ValueError, TypeError) as exc:
            raise ParamError(f"{self.name}: {exc}") from None

    def _coerce(self, v: Any) -> Any:
        if v is None:
            return None
        if self.none_word is not None and isinstance(v, str):
            if v.strip().lower() == self.none_word:
                return None
            if not v.strip():  # not a short way to say "all": an empty $VAR would render everything
                raise ValueError(f"empty list (name at least one, or '{self.none_word}')")
        k = self.kind
        if k == "int":
            x = _as_int(v)
            self._bounds(x)
            return x
        if k == "float":
            x = _as_float(v)
            self._bounds(x)
            return x
        if k == "bool":
            return _as_bool(v)
        if k in ("str", "path"):
            return self._choice(_as_str(v))
        if k == "size":
            s = _as_size(v)
            for x in s.split("x"):
                self._bounds(int(x))
            return s
        if k in ("floats", "ints", "strs"):
            item = {"floats": _as_float, "ints": _as_int, "strs": _as_str}[k]
            if not isinstance(v, (str, list, tuple)):
                raise ValueError(f"{v!r} is not a comma-separated list")
            out = parse_list(v, self.name, item, allow_empty=self.allow_empty)
            for x in out:
                if k == "strs":
                    self._choice(x)
                else:
                    self._bounds(x)
            if k == "strs" and self.check is None:  # a name twice would count its view or flash twice (a param
                # with its own check, e.g. the methods, says so in its own words)
                twice = named_twice(out)
                if twice:
                    raise ValueError(f"{', '.join(twice)} named more than once")
            return out
        # custom
        if self.convert is None:
            return v
        return self.convert(v)

    def default_text(self) -> str:
        """The default as shown in ``--help``."""
        d = self.default
        if isinstance(d, (list, tuple)):
            return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in d)
        if isinstance(d, float):
            return f"{d:g}"
        return str(d)

    def help_text(self) -> str:
        h = self.help
        if self.unit:
            h += f" [{self.unit}]"
        return h

    @classmethod
    def of_field(cls, config: Any, name: str, kind: str, **kw: Any) -> "Param":
        """A Param for the field ``name`` of a settings dataclass instance, its default taken from there (declared
        once; a tuple default becomes a list)."""
        default = getattr(config, name)
        return cls(name, kind, list(default) if isinstance(default, tuple) else default, **kw)


def named_twice(items: Iterable[Any]) -> list[str]:
    """The items of a list that occur more than once, sorted (as strings): a view, flash, identity or id named
    twice would count twice wherever it is used."""
    items = [str(x) for x in items]
    return sorted({x for x in items if items.count(x) > 1})


def closest_name(name: str, names: Iterable[str]) -> str | None:
    """The declared name nearest to a misspelt one (difflib), or None."""
    got = difflib.get_close_matches(name, list(names), n=1, cutoff=0.6)
    return got[0] if got else None


def resolve_params(params: Iterable[Param], given: Mapping[str, Any], *, strict: bool = True,
                   ignore: Iterable[str] = ()) -> dict[str, Any]:
    """Defaults filled in, every value validated and canonicalised; sorted by name, None values left out.

    Args:
        params: the stage's declaration.
        given: name → value (CLI values or recipe params); None means "not given".
        strict: unknown names are a :class:`ParamError` naming the closest declared one; otherwise they are
            dropped (e.g. recipe ``[defaults]`` for a stage that does not declare them).
        ignore: names that are always accepted and passed through (execution details such as ``device``).
    """
    decl = {p.name: p for p in params}
    ignore = set(ignore)
    out: dict[str, Any] = {}
    for name, value in given.items():
        if name in ignore:
            if value is not None:
                out[name] = value
            continue
        if name not in decl:
            if not strict:
                continue
            near = closest_name(name, decl)
            hint = f" (did you mean '{near}'?)" if near else (
                f" (known: {', '.join(sorted(decl))})" if decl else " (this stage takes no params)")
            raise ParamError(f"unknown param '{name}'{hint}")
    for name, p in decl.items():
        value = given.get(name)
        if value is None or (p.multiple and isinstance(value, (tuple, list)) and len(value) == 0):
            value = p.default
        v = p.coerce(value)
        if v is not None:
            out[name] = v
    return dict(sorted(out.items()))


def parse_ids(ids: str | None, id_file: Any = None) -> list[str]:
    """Identities from ``"001,002"`` (spaces also separate; ranges ``001-010`` keep the zero padding) and/or a
    file (one per line, ``#`` comments); duplicates dropped, order kept.  Each must be a safe id
    (:func:`reflectmm_cli.workspace.check_id`): a one-line error names the id, where it was read and the rule."""
    from pathlib import Path

    from reflectmm_cli.workspace import check_id

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
                out.extend(str(i).zfill(len(a)) for i in range(int(a), int(b) + 1))
            else:
                out.append(check_id(tok, "--ids"))
    if id_file is not None:
        try:
            lines = Path(id_file).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else "not a text file"
            raise ReflectmmError(f"cannot read id file ({why})", id_file) from None
        for n, ln in enumerate(lines, 1):
            tok = ln.split("#", 1)[0].strip()
            if tok:
                out.append(check_id(tok, f"{id_file}: line {n}"))
    seen: set[str] = set()
    return [i for i in out if not (i in seen or seen.add(i))]

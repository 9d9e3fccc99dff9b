"""Logging and progress bars, both on stderr (stdout carries results only)."""

from __future__ import annotations

import logging
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

log = logging.getLogger("reflectmm")


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of each message (test runners swap it)."""

    _reflectmm = True

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it; the property ignores it
        pass


def configure_logging(verbosity: int) -> None:
    """verbosity: -1 quiet (errors only), 0 normal (info), >=1 debug."""
    level = logging.ERROR if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    log.setLevel(level)
    if not any(getattr(h, "_reflectmm", False) for h in log.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
    log.propagate = False


def progress(iterable: Iterable[T], desc: str = "", total: int | None = None, unit: str = "it") -> Iterator[T]:
    """A tqdm progress bar on stderr; silent when logging is quieter than INFO."""
    from tqdm.auto import tqdm

    disable = log.getEffectiveLevel() > logging.INFO
    return iter(tqdm(iterable, desc=desc, total=total, unit=unit, file=sys.stderr, disable=disable,
                     leave=False, dynamic_ncols=True))

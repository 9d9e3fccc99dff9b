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
    """verbosity: -1 quiet (warnings and errors: no info, no progress), 0 normal (info), >=1 debug.

    Warnings are never hidden: a skipped input or a capped parameter is a result the user must see even
    with ``-q``, which only drops progress chatter.
    """
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    log.setLevel(level)
    if not any(getattr(h, "_reflectmm", False) for h in log.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
    log.propagate = False


def progress(iterable: Iterable[T], desc: str = "", total: int | None = None, unit: str = "it") -> Iterator[T]:
    """Progress on stderr; silent when logging is quieter than INFO.

    On a terminal a tqdm bar (redrawn in place with carriage returns). Otherwise (a log file, a pipe, a CI
    capture) plain lines, one per 10 % of ``total`` (or at 1, 10, 100 ... items when the total is unknown),
    so that the messages around it are never overwritten by ``\r``.
    """
    if log.getEffectiveLevel() > logging.INFO:
        return iter(iterable)
    if total is None:
        try:
            total = len(iterable)  # type: ignore[arg-type]
        except TypeError:
            total = None
    stream = sys.stderr
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    if tty:
        from tqdm.auto import tqdm

        return iter(tqdm(iterable, desc=desc, total=total, unit=unit, file=stream, leave=False, dynamic_ncols=True))
    return _progress_lines(iterable, desc, total, unit)


def _progress_lines(iterable: Iterable[T], desc: str, total: int | None, unit: str) -> Iterator[T]:
    import time

    t0 = time.perf_counter()
    label = f"{desc}: " if desc else ""
    next_pct, next_n, n = 10, 1, 0
    for item in iterable:
        yield item
        n += 1
        if total:
            pct = 100 * n // total
            if pct >= next_pct or n == total:
                print(f"{label}{n}/{total} {unit} ({pct}%, {time.perf_counter() - t0:.1f} s)", file=sys.stderr,
                      flush=True)
                next_pct = (pct // 10 + 1) * 10
        elif n >= next_n:
            print(f"{label}{n} {unit} ({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
            next_n *= 10

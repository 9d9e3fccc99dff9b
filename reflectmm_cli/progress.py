"""Logging and progress bars, both on stderr (stdout carries results only)."""

from __future__ import annotations

import logging
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

log = logging.getLogger("reflectmm")


def configure_logging(verbosity: int) -> None:
    """verbosity: -1 quiet (errors only), 0 normal (info), >=1 debug."""
    level = logging.ERROR if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    log.setLevel(level)
    if not any(getattr(h, "_reflectmm", False) for h in log.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        handler._reflectmm = True  # type: ignore[attr-defined]
        log.addHandler(handler)
    log.propagate = False


def progress(iterable: Iterable[T], desc: str = "", total: int | None = None, unit: str = "it") -> Iterator[T]:
    """A tqdm progress bar on stderr; silent when logging is quieter than INFO."""
    from tqdm.auto import tqdm

    disable = log.getEffectiveLevel() > logging.INFO
    return iter(tqdm(iterable, desc=desc, total=total, unit=unit, file=sys.stderr, disable=disable,
                     leave=False, dynamic_ncols=True))

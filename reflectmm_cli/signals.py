"""SIGTERM as an interrupt.

A batch scheduler ends a job on timeout or ``scancel`` with SIGTERM, whose default action kills the process at
once: no ``finally`` block runs, so an atomic write leaves its hidden temporary file, and nothing is said.
:func:`terminate_as_interrupt` (the CLI's entry) makes SIGTERM raise :class:`Terminated`, a KeyboardInterrupt, so
the process unwinds as on Ctrl-C: temporary files are removed, and the CLI prints one line and exits 143.
:func:`install_worker_handler` and :func:`call_terminable` do the same in the worker processes of a pool.
"""

from __future__ import annotations

import os
import signal
import threading
from contextlib import contextmanager
from typing import Any, Callable, Iterator

#: the exit status of a process ended by SIGTERM (128 + 15), as the shell and the batch schedulers report it
TERMINATED_EXIT = 128 + int(signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: unwinds like Ctrl-C (``except Exception`` does not catch it)."""


def _raise_terminated(signum, frame) -> None:
    # a second SIGTERM (the group's, then the one the run sends its workers) must not cut the clean-up short
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated()


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated` in this (main) thread; the previous handler is restored
    after. Outside the main thread signals cannot be handled: the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


_in_task = False  # a pool worker runs a task now (call_terminable); only then is there anything to clean up


def _worker_sigterm(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if _in_task:
        raise Terminated()
    os._exit(TERMINATED_EXIT)  # idle: nothing to clean up, and no traceback from the pool's loop


def install_worker_handler() -> None:
    """In a pool worker (its initializer): SIGTERM during a task unwinds it (see :func:`call_terminable`);
    an idle worker exits at once, with status 143."""
    signal.signal(signal.SIGTERM, _worker_sigterm)


def call_terminable(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in a pool worker; on SIGTERM the call unwinds (its ``finally`` blocks remove temporary
    files) and the worker exits with status 143 instead of taking the next task."""
    global _in_task
    _in_task = True
    try:
        return fn(*args)
    except Terminated:
        os._exit(TERMINATED_EXIT)
    finally:
        _in_task = False

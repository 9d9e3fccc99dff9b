"""Errors that the command line reports as one line and a non-zero exit."""

from __future__ import annotations

from pathlib import Path


class ReflectmmError(Exception):
    """A user-facing error: bad input, a refused artifact, a failed stage.

    The message should name the file (if any) and the problem.  The CLI prints
    ``reflectmm: error: <message>`` and exits with status 1; no traceback unless
    ``-v`` is given.
    """

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = Path(path) if path is not None else None
        if path is not None and not message.startswith(str(path)):
            message = f"{path}: {message}"
        super().__init__(message)


class WrittenThenFailed(ReflectmmError):
    """A stage wrote what it could and fails for the rest ("3 of 40 images skipped; the others were written"): the
    runner commits the files it wrote (:func:`~reflectmm_cli.stages.base.run_committed`), then reports the error."""


class ArtifactError(ReflectmmError):
    """An artifact is missing, truncated, corrupt, of the wrong kind or too new."""

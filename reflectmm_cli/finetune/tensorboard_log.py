"""TensorBoard events of a finetuning run (``finetune --tensorboard DIR``, docs/finetune.md "Watching training").

The scalars are the JSONL log's (:meth:`reflectmm_cli.finetune.train.Trainer._append_log`): every numeric field
of a record but its position (``phase``, ``epoch``, ``step``, ``global_step``) becomes a scalar of the same name
at ``global_step`` — ``loss``, ``photo``, ``coef``, ``light``, ``per``, ``upd``/``norm``/``ortho`` per step and
``val_total``, ``val_photo``, … per validation.  Besides them: ``images_per_s`` per step (a timing, so never in the
JSONL log, which stays reproducible) and, at each validation, ``val_reconstructions``: the first
:data:`N_PREVIEW` validation images, each row target | reconstruction (sRGB).

The ``tensorboard`` package is optional (``pip install 'reflectmm[tensorboard]'``); this module imports it only
in :func:`require_tensorboard`, so a run without ``--tensorboard`` never imports it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["TensorBoardLog", "require_tensorboard", "scalars_of_record", "preview_grid", "N_PREVIEW", "POSITION_KEYS"]

#: Validation images shown as reconstructions next to their targets.
N_PREVIEW = 4

#: Fields of a JSONL record that place it in the schedule rather than measure anything.
POSITION_KEYS = ("type", "phase", "epoch", "step", "global_step")


def require_tensorboard():
    """``torch.utils.tensorboard.SummaryWriter``, or a one-line :class:`ReflectmmError` saying how to install it."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise ReflectmmError("finetune --tensorboard needs the 'tensorboard' package: "
                             "pip install 'reflectmm[tensorboard]'") from None
    return SummaryWriter


def scalars_of_record(rec: dict) -> dict[str, float]:
    """The scalars of one JSONL record: its numeric fields but the position in the schedule."""
    return {k: float(v) for k, v in rec.items()
            if k not in POSITION_KEYS and isinstance(v, (int, float)) and not isinstance(v, bool)}


class TensorBoardLog:
    """One ``SummaryWriter`` on ``logdir``.

    ``purge_step``: TensorBoard hides the events of an earlier run in the same folder at this global step or
    later, as the JSONL log is restarted by a new run and truncated to the checkpoint on ``--resume``; give the
    global step the run starts from plus one (1 for a fresh run).
    """

    def __init__(self, logdir, purge_step: int | None = None):
        writer = require_tensorboard()
        self.logdir = Path(logdir)
        self.writer = writer(log_dir=str(self.logdir), purge_step=purge_step)

    def record(self, rec: dict) -> None:
        """The scalars of a JSONL record at its ``global_step``."""
        step = int(rec["global_step"])
        for k, v in scalars_of_record(rec).items():
            self.writer.add_scalar(k, v, step)

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.writer.add_scalar(tag, float(value), int(step))

    def image(self, tag: str, image: np.ndarray, step: int) -> None:
        """An (H, W, 3) image with values in [0, 1]."""
        self.writer.add_image(tag, np.clip(np.asarray(image, np.float32), 0.0, 1.0), int(step), dataformats="HWC")

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def preview_grid(targets: np.ndarray, recons: np.ndarray) -> np.ndarray:
    """(N, S, S, 3) linear targets and reconstructions → one (N·S, 2·S, 3) sRGB image, a row per image:
    target | reconstruction."""
    from reflectmm_cli.color import encode_display

    rows = [np.concatenate([encode_display(t, dtype=np.float64), encode_display(r, dtype=np.float64)], axis=1)
            for t, r in zip(targets, recons)]
    return np.concatenate(rows, axis=0).astype(np.float32)

"""The named steps of the training loop (Trainer.run): epoch order, batches, one optimiser step, the step and
validation records, the periodic and epoch-end checkpoints, and the progress lines."""
import io
import json
import logging

import numpy as np
import pytest
import torch

from _shards import make_dataset
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.config import FinetuneConfig
from reflectmm_cli.finetune.shards import load_shards
from reflectmm_cli.finetune.train import Trainer, _Progress
from reflectmm_cli.threads import torch_threads

TINY = dict(arch="resnet18", width=8, batch_size=4, lr1=2e-3, lr2=2e-4, model_lr=1e-3, w_upd=0.1)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    # 7 "train" images (2 steps per epoch of 4 + 3) and 2 "val" images
    return make_dataset(tmp_path_factory.mktemp("ft_steps"), n_images=9, size=32, seed=4)


@pytest.fixture
def trainer(data, tmp_path):
    def make(**cfg):
        kw = dict(epochs1=1, epochs2=1) | TINY | cfg
        return Trainer(load_shards(data["shards"]), data["truth"], data["light"], FinetuneConfig(**kw),
                       tmp_path / "w", progress=False)

    with torch_threads(1):
        yield make


def _log_lines(tr):
    return [json.loads(ln) for ln in tr.log_path.read_text().splitlines()] if tr.log_path.exists() else []


def test_epoch_order_is_a_permutation_of_the_train_split_fixed_by_seed_phase_and_epoch(trainer):
    tr = trainer()
    a = tr._epoch_order(1, 0)
    assert sorted(a.tolist()) == sorted(tr.train_idx.tolist())
    assert np.array_equal(a, tr._epoch_order(1, 0))
    assert np.array_equal(a, trainer()._epoch_order(1, 0))  # another trainer, the same order
    others = [tr._epoch_order(1, 1), tr._epoch_order(2, 0), trainer(seed=1)._epoch_order(1, 0)]
    assert all(not np.array_equal(a, o) for o in others)


def test_batch_of_one_image_takes_the_epochs_first_image_too(trainer):
    tr = trainer()
    perm = np.array([14, 10, 12, 11, 13])
    assert tr._batch(perm, 0).tolist() == [14, 10, 12, 11]
    assert tr._batch(perm, 1).tolist() == [13, 14]  # BatchNorm needs 2 images
    assert tr._batch(perm[:4], 0).tolist() == [14, 10, 12, 11]


def test_train_step_moves_the_encoder_not_the_phase1_model_and_counts_the_step(trainer):
    tr = trainer()
    tr.encoder.train()
    before = {k: v.clone() for k, v in tr.encoder.state_dict().items()}
    model = tr.params.vertex_arrays()
    total, terms = tr._train_step(tr.train_idx[:4], 1, 0)
    assert tr.global_step == 1
    assert torch.isfinite(total) and set(terms) >= {"photo", "coef", "light"}
    after = tr.encoder.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)
    for k, v in tr.params.vertex_arrays().items():
        assert v.tobytes() == model[k].tobytes(), k


def test_train_step_refuses_a_non_finite_loss_before_stepping(trainer, monkeypatch):
    tr = trainer()
    before = {k: v.clone() for k, v in tr.encoder.state_dict().items()}
    nan = torch.tensor(float("nan"))
    monkeypatch.setattr(tr, "_forward", lambda idx: (nan, {"photo": nan}, 0.0))
    with pytest.raises(ReflectmmError, match=r"loss became nan at step 0 \(phase 2, epoch 3\); lower the"):
        tr._train_step(tr.train_idx[:4], 2, 3)
    assert tr.global_step == 0
    assert all(torch.equal(before[k], v) for k, v in tr.encoder.state_dict().items())


def test_log_step_appends_the_record_to_history_and_jsonl(trainer):
    tr = trainer()
    tr.workdir.mkdir(parents=True)
    tr.global_step = 5
    rec = tr._log_step(2, 1, 3, torch.tensor(0.5), {"photo": torch.tensor(0.25), "coef": torch.tensor(2.0)})
    assert rec == {"type": "step", "phase": 2, "epoch": 1, "step": 3, "global_step": 5, "loss": 0.5,
                   "photo": 0.25, "coef": 2.0}
    assert tr.history == [rec] and _log_lines(tr) == [rec]
    assert tr.log_path.read_text() == json.dumps(rec, sort_keys=True) + "\n"


def test_checkpoint_step_saves_every_n_global_steps(trainer):
    tr = trainer(checkpoint_every=3)
    tr.global_step = 2
    tr._checkpoint_step()
    assert not tr.ckpt_path.exists()
    tr.global_step = 3
    tr._checkpoint_step()
    from safetensors import safe_open

    with safe_open(str(tr.ckpt_path), "pt") as f:
        assert json.loads(f.metadata()["__meta__"])["global_step"] == 3


def test_log_validation_records_the_val_losses_or_none_without_a_val_split(trainer):
    tr = trainer()
    tr.workdir.mkdir(parents=True)
    tr.global_step = 4
    val = tr._log_validation(1, 0)
    assert val is not None and val["total"] > 0 and tr.encoder.training
    rec = tr.history[-1]
    assert rec["type"] == "val" and rec["global_step"] == 4 and rec["val_total"] == val["total"]
    assert set(rec) == {"type", "phase", "epoch", "global_step"} | {f"val_{k}" for k in val}
    tr.val_idx = tr.val_idx[:0]
    assert tr._log_validation(1, 1) is None
    assert _log_lines(tr)[-1] == {"type": "val", "phase": 1, "epoch": 1, "global_step": 4}


def test_end_epoch_checkpoint_moves_on_and_keeps_phase1s_encoder_at_the_phase_boundary(trainer):
    tr = trainer(epochs1=2, epochs2=1)
    tr.pos = (0, 2)
    tr._end_epoch_checkpoint()
    assert tr.pos == (1, 0) and tr.ckpt_path.is_file() and not tr.phase1_encoder_path.exists()
    tr._end_epoch_checkpoint()  # the last epoch of phase 1
    assert tr.pos == (2, 0) and tr.phase1_encoder_path.is_file()
    tr.phase1_encoder_path.unlink()
    tr._enter_phase2()
    tr._end_epoch_checkpoint()  # the end of phase 2: not rewritten
    assert tr.pos == (3, 0) and not tr.phase1_encoder_path.exists()


def test_train_epoch_counts_its_images_and_stops_inside_the_epoch(trainer):
    tr = trainer()
    tr._start_log()
    tr.encoder.train()
    quiet = _Progress(False, False, tr.steps_per_epoch, 4)
    assert tr._train_epoch(0, quiet, stop_after=1) is None  # stopped after the first of 2 steps
    assert tr.pos == (0, 1) and tr.global_step == 1 and len(_log_lines(tr)) == 1
    assert tr._train_epoch(1, quiet, stop_after=None) == 3  # the rest: the 3 remaining images
    assert tr.pos == (0, 2) and tr.global_step == 2
    assert [r["step"] for r in _log_lines(tr)] == [0, 1]
    # stop_after at the epoch's last step does not stop inside the epoch (the epoch end does)
    tr.pos = (0, 0)
    assert tr._train_epoch(0, quiet, stop_after=tr.global_step + 2) == 7 and tr.global_step == 4


def test_start_log_restarts_the_log_only_at_the_very_start(trainer):
    tr = trainer()
    tr.workdir.mkdir(parents=True)
    tr.log_path.write_text("{}\n")
    tr.finished_log_path.write_text('{"finished": 1}\n')
    tr.global_step, tr.pos = 2, (1, 0)  # a resumed run keeps its log
    tr._start_log()
    assert tr.log_path.read_text() == "{}\n"
    tr.global_step, tr.pos = 0, (0, 0)
    tr._start_log()
    assert not tr.log_path.exists()
    # the log of the last run that finished is replaced only when this run finishes
    assert tr.finished_log_path.read_text() == '{"finished": 1}\n'
    tr.log_path.write_text("{}\n")
    tr._finish_log()
    assert tr.finished_log_path.read_text() == "{}\n" and not tr.log_path.exists()


def _rec(terms):
    return {"loss": 1.0, **{k: 0.5 for k in terms}}


def test_progress_plain_lines_every_tenth_of_an_epoch_and_at_its_end(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    p = _Progress(True, False, 25, 50)
    assert p.every == 2
    for k in range(25):
        p.step(1, 0, k, k + 1, _rec(["photo"]), ["photo"], 3.0)
    p.end_epoch()
    lines = err.getvalue().split("\n")
    assert "\r" not in err.getvalue() and lines[-1] == ""
    assert len(lines) - 1 == 13  # steps 2, 4, ..., 24 and the last (25)
    assert lines[0] == "finetune phase 1 epoch 1 step 2/25 [2/50] loss 1 photo 0.5 3.0 img/s"
    assert lines[-2].startswith("finetune phase 1 epoch 1 step 25/25 [25/50]")


def test_progress_on_a_terminal_redraws_one_line_and_ends_it_at_the_epoch_end(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    p = _Progress(True, True, 3, 3)
    for k in range(3):
        p.step(2, 1, k, k + 1, _rec([]), [], 1.0)
    p.end_epoch()
    assert err.getvalue().count("\r") == 3 and err.getvalue().endswith("img/s \n")
    assert err.getvalue().count("\n") == 1


def test_progress_is_silent_when_not_wanted_or_below_the_log_level(monkeypatch):
    from reflectmm_cli.progress import log as plog

    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    monkeypatch.setattr(plog, "level", logging.WARNING)
    assert not _Progress.for_run(True, 3, 3).show
    monkeypatch.setattr(plog, "level", logging.INFO)
    assert _Progress.for_run(True, 3, 3).show and not _Progress.for_run(True, 3, 3).tty  # a StringIO
    assert not _Progress.for_run(False, 3, 3).show
    _Progress(False, False, 3, 3).step(1, 0, 2, 3, _rec([]), [], 1.0)
    assert err.getvalue() == ""

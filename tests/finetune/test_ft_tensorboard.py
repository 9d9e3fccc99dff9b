"""finetune --tensorboard DIR: the events hold the JSONL log's scalars (same names, steps and values), images/s and
the validation reconstructions; a missing 'tensorboard' package is a one-line error before anything is written;
without the option nothing is imported or written, and the outputs equal those of a run with it."""
import json
import sys

import numpy as np
import pytest

from _shards import make_dataset, write_face_model, write_model, wrong_initial
from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.outputs import output_paths

TINY = ["--arch", "resnet18", "--width", "8", "--batch-size", "4", "--epochs1", "1", "--epochs2", "1",
        "--lr1", "2e-3", "--model-lr", "1e-3", "--threads", "1", "--samples", "6"]
SIZE, N_VAL = 32, 4


def _block_tensorboard(monkeypatch):
    """Make ``import tensorboard`` and ``torch.utils.tensorboard`` fail, as without the package."""
    for name in [m for m in sys.modules if m == "tensorboard" or m.startswith("tensorboard.")
                 or m.startswith("torch.utils.tensorboard")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "tensorboard", None)
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)


def _events(folder):
    return sorted(folder.rglob("events.out.tfevents.*"))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ft_tb")
    d = make_dataset(tmp, n_images=16, size=SIZE, seed=5)
    d["face_model"] = write_face_model(tmp / "face_model.npz", d["V"], d["tri"], d["uv"])
    d["init_path"] = write_model(tmp / "init.npz", wrong_initial(d["truth"], d["V"]))
    return d


def _args(data, out):
    return ["finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY]


@pytest.fixture(scope="module")
def with_tb(data, tmp_path_factory):
    """One run with --tensorboard: (output path, events folder)."""
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    tmp = tmp_path_factory.mktemp("ft_tb_run")
    out, tb = tmp / "with" / "m.npz", tmp / "events"
    r = CliRunner().invoke(main, [str(a) for a in _args(data, out) + ["--tensorboard", tb]], catch_exceptions=False)
    assert r.exit_code == 0, r.output + r.stderr
    return out, tb


def _accumulator(tb):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    return acc


def test_events_hold_the_scalars_of_the_jsonl_log_and_the_reconstructions(data, with_tb):
    out, tb = with_tb
    assert len(_events(tb)) == 1
    log = [json.loads(ln) for ln in output_paths(out)["log"].read_text().splitlines()]
    want: dict[str, list] = {}
    for rec in log:
        for k, v in rec.items():
            if k not in ("type", "phase", "epoch", "step", "global_step"):
                want.setdefault(k, []).append((rec["global_step"], v))
    # the run logged every term: photometric, prior, light, the phase-2 update, and validation totals
    assert {"loss", "photo", "coef", "light", "upd", "val_total", "val_photo", "val_upd"} <= set(want)
    acc = _accumulator(tb)
    tags = acc.Tags()
    assert set(tags["scalars"]) == set(want) | {"images_per_s"}
    for k, pairs in want.items():
        got = [(e.step, e.value) for e in acc.Scalars(k)]
        assert [s for s, _ in got] == [s for s, _ in pairs], k
        # TensorBoard stores float32
        np.testing.assert_allclose([v for _, v in got], [v for _, v in pairs], rtol=1e-6, err_msg=k)
    steps = [r["global_step"] for r in log if r["type"] == "step"]
    ips = acc.Scalars("images_per_s")
    assert [e.step for e in ips] == steps and all(np.isfinite(e.value) and e.value > 0 for e in ips)
    # one grid per validation: N_VAL rows of target | reconstruction
    vals = [r["global_step"] for r in log if r["type"] == "val"]
    assert tags["images"] == ["val_reconstructions"]
    ims = acc.Images("val_reconstructions")
    assert [e.step for e in ims] == vals == [3, 6]
    assert all((e.width, e.height) == (2 * SIZE, N_VAL * SIZE) for e in ims)
    import io

    from PIL import Image

    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.color import encode_display

    grids = [np.asarray(Image.open(io.BytesIO(e.encoded_image_string)).convert("RGB"), np.float64) / 255
             for e in ims]
    ss = load_shards(data["shards"])
    for row, i in enumerate(ss.indices("val")[:N_VAL]):
        target = encode_display(ss.linear_image(int(i)), dtype=np.float64)
        yx = ss.batch([int(i)], with_target=False)["pix_yx"]
        face = np.zeros((SIZE, SIZE), bool)
        face[yx[:, 0], yx[:, 1]] = True
        assert 0 < face.sum() < SIZE * SIZE
        for g in grids:
            left, right = g[row * SIZE:(row + 1) * SIZE, :SIZE], g[row * SIZE:(row + 1) * SIZE, SIZE:]
            assert np.abs(left - target).max() <= 1 / 255 + 1e-9  # the target, to 8-bit rounding
            assert np.abs(right[~face] - target[~face]).max() <= 1 / 255 + 1e-9  # rendered over the target
            assert np.abs(right[face] - target[face]).mean() > 1 / 255  # the face is rendered, not copied
    assert not np.array_equal(grids[0][:, SIZE:], grids[1][:, SIZE:])  # the reconstructions change with training


def test_without_the_package_a_one_line_error_before_anything(data, tmp_path, monkeypatch):
    """No 'tensorboard' package: exit 1, one line saying how to install it, no output and no events folder, and
    the inputs were not even read (the check comes before any training work)."""
    from click.testing import CliRunner

    import reflectmm_cli.finetune.train as train
    from reflectmm_cli.cli import main

    _block_tensorboard(monkeypatch)
    read = []
    real_load = train.load_models
    monkeypatch.setattr(train, "load_models", lambda *a: read.append(a) or real_load(*a))
    out, tb = tmp_path / "out" / "m.npz", tmp_path / "events"
    r = CliRunner().invoke(main, [str(a) for a in _args(data, out) + ["--tensorboard", tb]])
    assert r.exit_code == 1, r.output
    msg = r.stderr.strip()
    assert len(msg.splitlines()) == 1
    assert msg == ("reflectmm: error: finetune --tensorboard needs the 'tensorboard' package: "
                   "pip install 'reflectmm[tensorboard]'")
    assert r.stdout == "" and not read
    assert not out.parent.exists() and not tb.exists()
    # the library entry refuses the same way, before it touches its work folder
    from reflectmm_cli.finetune.config import FinetuneConfig
    from reflectmm_cli.finetune.shards import load_shards

    with pytest.raises(ReflectmmError, match=r"^finetune --tensorboard needs the 'tensorboard' package"):
        train.finetune(load_shards(data["shards"]), data["truth"], data["light"],
                       FinetuneConfig(arch="resnet18", width=8, batch_size=4, epochs1=1, epochs2=0),
                       tmp_path / "work", tensorboard=tmp_path / "events2", progress=False)
    assert not (tmp_path / "work").exists() and not (tmp_path / "events2").exists()


def test_without_the_option_nothing_is_imported_or_written_and_the_outputs_are_the_same(data, with_tb, tmp_path,
                                                                                        monkeypatch):
    """With tensorboard unimportable, a run without --tensorboard succeeds (it never imports it), writes no event
    file, and every file it writes equals, byte for byte, that of the run with --tensorboard: the option is an
    observer that neither changes training nor enters the cache key or the artifacts' meta."""
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    _block_tensorboard(monkeypatch)
    out_tb, _ = with_tb
    out = tmp_path / "without" / "m.npz"  # the same depth as the other run's, so relative input paths agree
    assert len(out.relative_to(tmp_path).parts) == len(out_tb.relative_to(out_tb.parents[1]).parts)
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(main, [str(a) for a in _args(data, out)], catch_exceptions=False)
    assert r.exit_code == 0, r.output + r.stderr
    assert _events(tmp_path) == [] and _events(data["init_path"].parent) == []
    names = sorted(p.relative_to(out.parent) for p in out.parent.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(out_tb.parent) for p in out_tb.parent.rglob("*") if p.is_file())
    assert len(names) >= 8
    for name in names:
        assert (out.parent / name).read_bytes() == (out_tb.parent / name).read_bytes(), name
    meta = read_artifact(out, "reflectance-model").meta
    assert "tensorboard" not in meta["params"]


def _scalars(acc):
    return {k: [(e.step, e.value) for e in acc.Scalars(k)] for k in acc.Tags()["scalars"]}


def test_a_resumed_run_hides_the_events_after_the_checkpoint(data, tmp_path):
    """As the JSONL log is truncated to the checkpoint on resume, the events the interrupted run wrote after it are
    hidden (purge step): the events of the two runs together hold the final log's scalars once each."""
    from reflectmm_cli.finetune.config import FinetuneConfig
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import finetune

    ss = load_shards(data["shards"])
    cfg = FinetuneConfig(arch="resnet18", width=8, batch_size=4, lr1=2e-3, epochs1=2, epochs2=1, checkpoint_every=2)
    tb = tmp_path / "events"
    kw = dict(threads=1, progress=False, tensorboard=tb)
    a = finetune(ss, data["truth"], data["light"], cfg, tmp_path / "w", stop_after=7, **kw)
    assert a.stopped_early and a.steps == 7  # steps 1..7 in the events, the checkpoint at 6
    assert [e.step for e in _accumulator(tb).Scalars("loss")] == list(range(1, 8))
    finetune(ss, data["truth"], data["light"], cfg, tmp_path / "w", resume=True, **kw)
    assert len(_events(tb)) == 2
    log = [json.loads(ln) for ln in (tmp_path / "w" / "log.jsonl").read_text().splitlines()]
    got = _scalars(_accumulator(tb))
    assert [s for s, _ in got["loss"]] == [r["global_step"] for r in log if r["type"] == "step"] == list(range(1, 10))
    assert [s for s, _ in got["images_per_s"]] == list(range(1, 10))
    np.testing.assert_allclose([v for _, v in got["loss"]], [r["loss"] for r in log if r["type"] == "step"],
                               rtol=1e-6)
    assert [s for s, _ in got["val_total"]] == [3, 6, 9]
    # a new run in the same folder hides the earlier run's events, as it restarts the JSONL log
    finetune(ss, data["truth"], data["light"], cfg.replace(epochs1=1, epochs2=0), tmp_path / "w", **kw)
    got = _scalars(_accumulator(tb))
    assert [s for s, _ in got["loss"]] == [1, 2, 3] and [s for s, _ in got["val_total"]] == [3]
    assert got.get("upd", []) == [] and got.get("val_upd", []) == []  # phase 2 of the earlier runs is hidden

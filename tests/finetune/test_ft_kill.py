"""A real SIGKILL during training: the checkpoint on disk is always whole, and resuming from it gives the same
result as an uninterrupted run."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from _shards import make_dataset
from reflectmm_cli.finetune.config import FinetuneConfig
from reflectmm_cli.finetune.shards import load_shards
from reflectmm_cli.finetune.train import finetune

CFG = dict(arch="resnet18", width=8, batch_size=4, lr1=2e-3, lr2=2e-4, model_lr=1e-3, epochs1=3, epochs2=2,
           checkpoint_every=1)


@pytest.mark.slow
def test_sigkill_then_resume_equals_uninterrupted(tmp_path):
    d = make_dataset(tmp_path / "d", n_images=14, size=32, seed=2)
    models = tmp_path / "models.py"
    # the child trains the same run (truth model, light model from the artifacts) and is killed mid-way
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from reflectmm_cli.finetune.config import FinetuneConfig
        from reflectmm_cli.finetune.shards import load_shards
        from reflectmm_cli.finetune.train import load_models
        from reflectmm_cli.finetune.train import finetune
        m, l = load_models({str(d['truth_path'])!r}, {str(d['light_path'])!r})
        finetune(load_shards([{str(d['shards'][0])!r}]), m, l, FinetuneConfig(**{CFG!r}), {str(tmp_path / 'b')!r},
                 threads=1, progress=False)
    """)
    models.write_text(code)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[2])] + sys.path))
    proc = subprocess.Popen([sys.executable, str(models)], env=env)
    ck = tmp_path / "b" / "checkpoint.safetensors"
    t0 = time.time()
    while time.time() - t0 < 120 and proc.poll() is None:
        if ck.exists() and ck.stat().st_mtime > t0:
            import json

            from safetensors import safe_open

            try:
                step = json.loads(safe_open(str(ck), "pt").metadata()["__meta__"])["global_step"]
            except Exception:
                step = 0
            if step >= 5:
                break
        time.sleep(0.05)
    assert proc.poll() is None, "training finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    from reflectmm_cli.finetune.train import load_models

    m, l = load_models(d["truth_path"], d["light_path"])
    ss = load_shards(d["shards"])
    b = finetune(ss, m, l, FinetuneConfig(**CFG), tmp_path / "b", threads=1, progress=False, resume=True)
    a = finetune(ss, m, l, FinetuneConfig(**CFG), tmp_path / "a", threads=1, progress=False)
    assert a.steps == b.steps
    for k, v in a.encoder.state_dict().items():
        assert torch.equal(v, b.encoder.state_dict()[k]), k
    va, vb = a.params.vertex_arrays(), b.params.vertex_arrays()
    for k in va:
        assert va[k].tobytes() == vb[k].tobytes(), k
    assert (tmp_path / "a" / "log.jsonl").read_text() == (tmp_path / "b" / "log.jsonl").read_text()

"""Both shipped recipes build Table 2's control as the finetune run with the model frozen (model_lr = 0) and
nothing else changed, and use it as "initial" wherever an encoder is evaluated."""
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("recipe", ["synthetic.toml", "paper.toml"])
def test_control_is_the_finetune_run_with_the_model_frozen(recipe):
    st = tomllib.loads((ROOT / "recipes" / recipe).read_text())["stages"]
    ft, ctl = st["finetune"], st["finetune-control"]
    assert ctl["verb"] == "finetune"
    assert ctl["inputs"] == dict(ft["inputs"], phase1_encoder="@finetune.outputs.finetune_encoder_phase1")
    assert ctl["params"]["model_lr"] == 0 and ft["params"]["model_lr"] > 0
    assert {k: v for k, v in ctl["params"].items() if k != "model_lr"} == \
        {k: v for k, v in ft["params"].items() if k != "model_lr"}
    for name, stage in st.items():
        enc = stage.get("inputs", {}).get("encoder_initial")
        if enc is not None:
            assert enc == "@finetune-control.outputs.finetune-control_encoder", name
            assert stage["inputs"]["model_initial"] == "@finetune-control.output", name

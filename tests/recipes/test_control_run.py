"""Both shipped recipes build Table 2's control as the finetune run with the model frozen (model_lr = 0) and
nothing but the model update changed (the SGD model learning rate, or the least-squares solver and its options),
and use the control as "initial" wherever an encoder is evaluated. With the joint SGD, phase 1 (the encoder on
the initial model in both runs) is trained once and shared; with the least-squares update the finetuned run
trains its own phase 1 on the solved model, so the two runs have the same inputs."""
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _without_update(params: dict) -> dict:
    """The run's settings but those of the model update (the SGD model learning rate, the solver, ``ls_*``)."""
    return {k: v for k, v in params.items() if k not in ("model_lr", "solver") and not k.startswith("ls_")}


@pytest.mark.parametrize("recipe", ["synthetic.toml", "paper.toml"])
def test_control_is_the_finetune_run_with_the_model_frozen(recipe):
    st = tomllib.loads((ROOT / "recipes" / recipe).read_text())["stages"]
    ft, ctl = st["finetune"], st["finetune-control"]
    assert ctl["verb"] == "finetune"
    assert ctl["params"]["model_lr"] == 0 and ctl["params"].get("solver", "sgd") == "sgd"
    assert ft["params"].get("solver") == "ls" or ft["params"]["model_lr"] > 0
    assert _without_update(ctl["params"]) == _without_update(ft["params"])
    if ft["params"].get("solver") == "ls":  # phase 1 on the solved model: nothing shared
        owner = "finetune-control"
        assert ft["inputs"] == ctl["inputs"]
    else:  # phase 1 (the encoder on the initial model in both runs) is trained once and shared
        owner, taker = ("finetune-control", ft) if "phase1_encoder" in ft["inputs"] else ("finetune", ctl)
        other = ctl if taker is ft else ft
        assert taker["inputs"] == dict(other["inputs"], phase1_encoder=f"@{owner}.outputs.{owner}_encoder_phase1")
    for name, stage in st.items():
        enc = stage.get("inputs", {}).get("encoder_initial")
        if enc is not None:
            assert enc == "@finetune-control.outputs.finetune-control_encoder", name
            assert stage["inputs"]["model_initial"] == "@finetune-control.output", name
        p1 = stage.get("inputs", {}).get("encoder_initial-phase1")
        if p1 is not None:
            assert p1 == f"@{owner}.outputs.{owner}_encoder_phase1", name


def test_the_oracle_row_is_the_control_on_the_oracle_model():
    """The demo's ceiling of the finetuning gain: finetune-oracle is finetune-control with only its model changed,
    to the oracle of the initial model's size; Table 2 reports its gain over the control."""
    st = tomllib.loads((ROOT / "recipes" / "synthetic.toml").read_text())["stages"]
    orc, ctl = st["finetune-oracle"], st["finetune-control"]
    assert orc["verb"] == "finetune" and orc["params"] == ctl["params"]
    assert orc["inputs"] == dict(ctl["inputs"], model="@baseline-oracle.output")
    base = st["baseline-oracle"]
    assert base["verb"] == "build-baseline" and base["params"]["kind"] == "oracle"
    assert base["inputs"]["like"] == ctl["inputs"]["model"] and base["inputs"]["truth"] == "@synth-wild.dir"
    ev = st["evaluate-reconstruction"]
    assert ev["inputs"]["model_oracle"] == "@finetune-oracle.output"
    assert ev["inputs"]["encoder_oracle"] == "@finetune-oracle.outputs.finetune-oracle_encoder"
    assert "oracle" in ev["params"]["methods"] and "more_gains" not in ev["params"]  # the default: oracle:initial

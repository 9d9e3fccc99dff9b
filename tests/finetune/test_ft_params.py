"""finetune's parameter declaration is generated from FinetuneConfig; the released variant is a preset completed
before the cache key; execution details never key the cache."""
import dataclasses

import pytest

from reflectmm_cli.finetune.config import RELEASED, FinetuneConfig
from reflectmm_cli.params import ParamError
from reflectmm_cli.stages.base import cache_key_doc
from reflectmm_cli.stages.registry import get_stage


def test_params_are_the_config_fields():
    st = get_stage("finetune")
    decl = {p.name: p for p in st.params}
    fields = {f.name: f for f in dataclasses.fields(FinetuneConfig) if f.name != "extra"}
    from reflectmm_cli.finetune.model_solve import SolveConfig

    solver = {"solver"} | {"ls_" + f.name for f in dataclasses.fields(SolveConfig)}
    execution = {"samples", "resume", "threads", "tensorboard", "jobs", "executor", "scheduler"}
    assert set(fields) <= set(decl) and set(decl) - set(fields) == execution | solver
    for name, f in fields.items():
        want = None if name in RELEASED and name != "variant" else f.default
        assert decl[name].default == (list(want) if isinstance(want, tuple) else want), name
        assert decl[name].help == f.metadata["help"] or decl[name].help.startswith(f.metadata["help"]), name
    # the resolved params are the full config of the variant
    assert {k: v for k, v in st.resolve({}).items() if k in fields} == \
        {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(FinetuneConfig()).items()
         if k in fields and v is not None}


def test_released_variant_is_a_preset_with_overrides():
    st = get_stage("finetune")
    p = st.resolve({"variant": "released", "w_upd": "1", "epochs1": 3})
    assert p["w_photo"] == 1.92 and p["photometric"] == "l2norm" and p["trainable"] == "albedo"
    assert p["w_upd"] == 1.0 and p["epochs1"] == 3 and p["epochs2"] == 5
    assert st.resolve({"variant": "released"}) == st.resolve({"variant": "released", "w_photo": 1.92})
    assert st.resolve({})["w_photo"] == 2.0
    with pytest.raises(ParamError, match="did you mean 'epochs2'"):
        st.resolve({"epochs_2": 1})
    with pytest.raises(ParamError, match="w_per: -1 is below the minimum 0"):
        st.resolve({"w_per": -1})
    with pytest.raises(ParamError, match="betas: expected two numbers"):
        st.resolve({"betas": [0.9]})


def test_resume_threads_device_tensorboard_do_not_key_the_cache(tmp_path):
    st = get_stage("finetune")
    a = st.context(workspace=tmp_path, params={"epochs1": 1})
    b = st.context(workspace=tmp_path, params={"epochs1": 1, "resume": True, "threads": 3, "device": "cuda",
                                               "tensorboard": str(tmp_path / "tb")})
    assert b.params["tensorboard"] == str(tmp_path / "tb")
    assert cache_key_doc(st, a) == cache_key_doc(st, b)
    assert {"resume", "threads", "tensorboard"}.isdisjoint(b.resolved_params())
    c = st.context(workspace=tmp_path, params={"epochs1": 2})
    assert cache_key_doc(st, a) != cache_key_doc(st, c)

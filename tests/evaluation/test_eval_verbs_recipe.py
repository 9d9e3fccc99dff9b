"""build-baseline and evaluate-albedo as recipe stages (methods as roles model_<name>): run, no-op rerun; the new
stages' params are validated in a recipe like on the command line (one line naming the recipe and the stage)."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.geometry import procedural_face_model
from reflectmm_cli.geometry.face_model import save_face_model
from reflectmm_cli.reflectance.simulate import simulate_observations

RECIPE = """
schema = "reflectmm.recipe/1"
name = "table3"

[stages.bfm]
verb = "build-baseline"
inputs = { truth = "truth", face_model = "face_model.npz" }
params = { kind = "diffuse-only", components = 3, ids = ["t0", "t1", "t2", "t3"] }

[stages.albedomm]
verb = "build-baseline"
inputs = { truth = "truth", face_model = "face_model.npz" }
params = { kind = "albedomm", components = 3, ids = ["t0", "t1", "t2", "t3"] }

[stages.evaluate-albedo]
inputs = { observations = "unwrap-uv/*.npz", truth = "truth", model_diffuse-only = "@bfm.output", model_albedomm = "@albedomm.output" }
params = { methods = ["albedomm", "diffuse-only"] }
"""


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    ws = tmp_path_factory.mktemp("t3recipe")
    for k, iid in enumerate(["t0", "t1", "t2", "t3", "h0"]):
        obs, tr = simulate_observations(size=12, seed=k, return_truth=True, views=[2, 4], flashes=[1, 4, 7],
                                        dtype=np.float32)
        write_artifact(ws / "truth" / f"{iid}.npz", "synth-truth",
                       {"albedo": tr["albedo"], "spec_albedo": tr["weights"].sum(0), "uv_mask": obs["mask"]})
        if iid == "h0":
            write_artifact(ws / "unwrap-uv" / f"{iid}.npz", "uv-observations", obs, extra_meta={"identity": iid})
    save_face_model(procedural_face_model(n_vertices=600), ws / "face_model.npz")
    return ws


def test_recipe_runs_then_skips(ws):
    from reflectmm_cli.recipes.runner import run_recipe

    rec = ws / "r.toml"
    rec.write_text(RECIPE)
    rep = run_recipe(rec, ws)
    assert rep.ok, [(t.stage, t.status, t.reason) for t in rep.tasks]
    assert read_artifact(ws / "bfm" / "diffuse-only.npz", "reflectance-model").meta["ids"] == ["t0", "t1", "t2", "t3"]
    art = read_artifact(ws / "evaluate-albedo" / "evaluate-albedo.npz", "evaluation")
    assert art.meta["methods"] == ["albedomm", "diffuse-only"] and art.meta["identities"] == ["h0"]
    assert "--method albedomm albedomm/albedomm.npz -" in art.meta["command"]
    rep2 = run_recipe(rec, ws)
    assert rep2.ok and rep2.counts() == {"skipped": 3}, [(t.stage, t.status, t.reason) for t in rep2.tasks]


@pytest.mark.parametrize("stage, params, message", [
    ("build-baseline", '{ kind = "bfm17" }', "kind: 'bfm17' is not one of diffuse-only, albedomm"),
    ("build-baseline", "{ components = 0 }", "components: 0 is below the minimum 1"),
    ("build-baseline", "{ exponent = -2 }", "exponent: -2 is not above the minimum 0"),
    ("build-baseline", "{ compnents = 3 }", "unknown param 'compnents' (did you mean 'components'?)"),
    ("evaluate-albedo", '{ methods = ["Ours!"] }', "methods: method name 'Ours!' must be"),
    ("evaluate-albedo", '{ methods = ["a", "a"] }', "methods: method 'a' given twice"),
    ("evaluate-albedo", "{ prior = -1 }", "prior: -1 is below the minimum 0"),
    ("evaluate-reconstruction", '{ gain = ["a"] }', "gain: give two different method names"),
    ("evaluate-reconstruction", '{ split = "dev" }', "split: 'dev' is not one of train, val, test, all"),
    ("evaluate-reconstruction", "{ released_batch = 0 }", "released_batch: 0 is below the minimum 1"),
    ("evaluate-relighting", '{ holdout = "07,,05" }', "holdout: empty item"),
    ("evaluate-relighting", '{ scale = "local" }', "scale: 'local' is not one of global, none"),
    ("evaluate-relighting", "{ size = 16 }", "size: 16 is below the minimum 32"),
])
def test_recipe_params_are_validated(cli, tmp_path, stage, params, message):
    rec = tmp_path / "bad.toml"
    foreach = 'foreach = ["900"]\n' if stage == "evaluate-relighting" else ""
    rec.write_text(f'schema = "reflectmm.recipe/1"\nname = "bad"\n\n[stages.{stage}]\n{foreach}'
                   f'inputs = {{ truth = "truth" }}\nparams = {params}\n')
    r = cli("run", rec, "-w", tmp_path)
    assert r.exit_code == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert str(rec) in lines[0] and f"[stages.{stage}]" in lines[0] and message in lines[0], lines[0]

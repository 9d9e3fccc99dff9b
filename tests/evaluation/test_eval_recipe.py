"""build-pca, evaluate-representation and evaluate-report as recipe stages: run, then a no-op rerun."""
import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.reflectance.simulate import simulate_observations

RECIPE = """
schema = "reflectmm.recipe/1"
name = "model-eval"

[stages.fit]
verb = "fit-reflectance"
foreach = ["001", "002", "003"]
inputs = { observations = "unwrap-uv/{id}.npz" }

[stages.pca]
verb = "build-pca"
inputs = { maps = "@fit.output" }
params = { components = 5 }

[stages.rep]
verb = "evaluate-representation"
inputs = { observations = "unwrap-uv/*.npz" }
params = { exponents_sets = "16;1,8,64", baselines = false }

[stages.report]
verb = "evaluate-report"
inputs = { maps = "@fit.output", model = "@pca.output", truth = "truth", representation = "@rep.output" }
"""


def test_recipe_stages_run_and_skip(tmp_path):
    from reflectmm_cli.recipes.runner import run_recipe

    for i, ident in enumerate(["001", "002", "003"]):
        obs, tr = simulate_observations(size=24, seed=i, dtype=np.float16, return_truth=True)
        write_artifact(tmp_path / "unwrap-uv" / f"{ident}.npz", "uv-observations", obs,
                       extra_meta={"identity": ident})
        write_artifact(tmp_path / "truth" / f"{ident}.npz", "synth-truth",
                       {"albedo": tr["albedo"], "weights": tr["weights"], "exponents": tr["exponents"],
                        "spec_albedo": tr["weights"].sum(0)})
    rec = tmp_path / "r.toml"
    rec.write_text(RECIPE)
    rep = run_recipe(rec, tmp_path)
    assert rep.ok, rep
    model = read_artifact(tmp_path / "pca" / "pca.npz", "reflectance-model")
    assert model["sigma"].shape == (2,)
    text = (tmp_path / "report" / "report.md").read_text()
    assert "## Reflectance maps" in text and "## PCA reflectance model" in text and "## Representation" in text
    ev = read_artifact(tmp_path / "report" / "report.npz", "evaluation")
    names = list(ev["names"])
    # exact-model data, truth geometry: observable albedo within 2 %
    for ident in ("001", "002", "003"):
        assert ev["values"][names.index(f"reflectance.{ident}.raw.observable.albedo_rel")] < 0.02
    rep2 = run_recipe(rec, tmp_path)
    assert rep2.ok
    assert len(rep2.tasks) == 6
    assert rep2.counts() == {"skipped": 6}, [(t.stage, t.id, t.status, t.reason) for t in rep2.tasks]

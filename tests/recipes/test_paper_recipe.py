"""recipes/paper.toml: the paper's settings on real data plan on a workspace with the documented layout, and its
numbers are the paper's (not a run: the data are licensed and the run needs a GPU or a cluster)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "paper.toml"

IDS = ("001", "002", "003")
VIEWS = ("09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0")
FLASHES = ("03", "04", "05", "06", "07", "08", "09", "10", "11", "14", "18")
STAGES = ("face-model-import", "preprocess-multipie", "fit-geometry", "unwrap-uv", "fit-reflectance", "build-pca",
          "build-light-pca", "evaluate-representation", "prepare-wild", "finetune", "finetune-control",
          "evaluate-reconstruction", "evaluate-report")


def _touch(p: Path, text: str = "x") -> None:
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)


def make_layout(ws: Path, n_images: int = 3, *, multipie: bool = True) -> Path:
    """The layout the recipe's header documents, with placeholder files: planning only discovers identities
    and shards and hashes files, so the contents are never decoded."""
    if multipie:
        for i in IDS:  # one view with its room shot and landmark file is enough for discovery
            cam = ws / "data/multipie/data/session01/multiview" / i / "01" / "05_1"
            _touch(cam / f"{i}_01_01_051_00.png")
            _touch(cam / f"{i}_01_01_051_00_lm.pts")
    _touch(ws / "data/bfm/BFM_model_front.mat")
    _touch(ws / "data/envmaps/indoor_0001.exr")
    _touch(ws / "data/envmaps/indoor_0002.exr", "y")
    for k in range(n_images):
        _touch(ws / f"data/ffhq/images/{k:05d}.png", str(k))
        _touch(ws / f"data/ffhq/landmarks/{k:05d}.pts", str(k))
    _touch(ws / "data/weights/arcface_r50.safetensors")
    return ws


def test_dry_run_plans_every_stage(cli, tmp_path):
    ws = make_layout(tmp_path)
    r = cli("run", RECIPE, "-w", ws, "--dry-run")
    assert r.exit_code == 0, r.stderr
    rows = [ln.split(None, 3) for ln in r.stdout.splitlines()[2:]]
    assert {row[0] for row in rows} == set(STAGES)
    assert {row[2] for row in rows} <= {"run", "deferred"}
    # the sources run; the identities come from the Multi-PIE tree
    acts = {(row[0], row[1]): row[2] for row in rows}
    assert [row[1] for row in rows if row[0] == "preprocess-multipie"] == list(IDS)
    for stage in ("face-model-import", "build-light-pca", "build-pca", "evaluate-representation"):
        assert acts[(stage, "-")] == "run", stage
    for i in IDS:
        for stage in ("preprocess-multipie", "fit-geometry", "unwrap-uv", "fit-reflectance"):
            assert acts[(stage, i)] == "run", (stage, i)
    # the shards are discovered once the face model is imported (it is prepare-wild's input); the rest waits
    for stage in ("prepare-wild", "finetune", "evaluate-reconstruction", "evaluate-report"):
        assert acts[(stage, "-")] == "deferred", stage
    assert not (ws / "face-model-import").exists()  # a dry run writes nothing


def _small_bfm_front(path: Path) -> None:
    """A Deep3DFaceRecon-style BFM_model_front.mat of a small procedural face (the keys the importer reads)."""
    import numpy as np
    import scipy.io

    from reflectmm_cli.geometry import procedural_face_model

    src = procedural_face_model(grid=(31, 25), n_shape=3, n_exp=2)
    n = src.n_vertices
    scipy.io.savemat(str(path), {
        "meanshape": (src.mean_shape * 0.01).reshape(1, -1), "idBase": src.shape_basis.reshape(3, -1).T * 0.01,
        "exBase": src.exp_basis.reshape(2, -1).T * 0.01, "meantex": np.full((1, 3 * n), 128.0),
        "texBase": np.zeros((3 * n, 2)), "tri": (src.triangles + 1).astype(float), "point_buf": np.ones((n, 8)),
        "keypoints": (src.landmarks + 1)[None].astype(float), "skinmask": np.ones((1, n))})


def test_shards_are_discovered_once_the_face_model_is_imported(cli, tmp_path):
    """prepare-wild runs per shard of 256 FFHQ images: after the import, 600 images plan as 3 shard tasks."""
    ws = make_layout(tmp_path, n_images=600)
    _small_bfm_front(ws / "data/bfm/BFM_model_front.mat")
    r = cli("run", RECIPE, "-w", ws, "--only", "face-model-import")
    assert r.exit_code == 0, r.stderr
    r = cli("run", RECIPE, "-w", ws, "--dry-run")
    assert r.exit_code == 0, r.stderr
    rows = [ln.split(None, 3) for ln in r.stdout.splitlines()[2:]]
    acts = {(row[0], row[1]): row[2] for row in rows}
    assert acts[("face-model-import", "-")] == "skip"
    assert [row[1] for row in rows if row[0] == "prepare-wild"] == ["shard_00000", "shard_00001", "shard_00002"]
    assert {acts[("prepare-wild", f"shard_0000{k}")] for k in range(3)} == {"run"}
    for stage in ("finetune", "evaluate-reconstruction", "evaluate-report"):
        assert acts[(stage, "-")] == "run", stage


def test_missing_data_is_named(cli, tmp_path):
    """A workspace without the Multi-PIE tree is refused with the path it looked for, not planned empty."""
    ws = make_layout(tmp_path, multipie=False)
    r = cli("run", RECIPE, "-w", ws, "--dry-run")
    assert r.exit_code != 0
    assert "data/multipie" in r.stderr


def _recipe() -> dict:
    with open(RECIPE, "rb") as f:
        return tomllib.load(f)


def test_the_paper_numbers():
    st = _recipe()["stages"]
    pre = st["preprocess-multipie"]
    assert pre["foreach"] == "all found"
    assert tuple(pre["params"]["views"]) == VIEWS and tuple(pre["params"]["flashes"]) == FLASHES
    assert st["build-pca"]["params"]["components"] == 80
    light = st["build-light-pca"]["params"]
    assert (light["components"], light["order"]) == (80, 8)
    assert st["fit-reflectance"]["params"]["exponents"] == [1, 8, 64]
    wild = st["prepare-wild"]["params"]
    assert wild["size"] == 224 and wild["aligned"] is False and st["prepare-wild"]["foreach"] == "all found"
    ft = st["finetune"]["params"]
    assert ft["arch"] == "resnet50"
    assert (ft["epochs1"], ft["epochs2"]) == (20, 2)
    assert (ft["lr1"], ft["lr2"]) == (1e-4, 1e-5)
    assert (ft["w_photo"], ft["w_per"], ft["w_coef"], ft["w_upd"], ft["w_light"]) == (2, 0.1, 0.001, 10, 10)
    assert ft["device"] == "cuda"
    assert st["finetune"]["inputs"]["identity_weights"] == "data/weights/arcface_r50.safetensors"
    ev = st["evaluate-reconstruction"]
    # the fair control: the same run as finetune with the model frozen in phase 2 (only model_lr differs)
    ctl = st["finetune-control"]
    assert ctl["verb"] == "finetune"
    assert ctl["inputs"] == dict(st["finetune"]["inputs"], phase1_encoder="@finetune.outputs.finetune_encoder_phase1")
    assert {k: v for k, v in ctl["params"].items() if k != "model_lr"} == \
        {k: v for k, v in ft.items() if k != "model_lr"} and ctl["params"]["model_lr"] == 0
    assert ev["inputs"]["encoder_initial"] == "@finetune-control.outputs.finetune-control_encoder"
    assert ev["inputs"]["model_initial"] == "@finetune-control.output"
    assert ev["inputs"]["encoder_initial-phase1"] == "@finetune.outputs.finetune_encoder_phase1"
    assert ev["inputs"]["encoder_finetuned"] == "@finetune.outputs.finetune_encoder"


@pytest.mark.parametrize("verb", ["finetune", "build-pca", "build-light-pca"])
def test_paper_values_are_the_declared_defaults(verb):
    """The recipe writes the paper's numbers out; they are also the toolkit's defaults (so CLI runs match)."""
    from reflectmm_cli.stages import get_stage

    stage = get_stage(verb)
    given = _recipe()["stages"][verb]["params"]
    resolved = stage.resolve({})
    for k, v in given.items():
        if k in ("device", "rotations"):
            continue
        assert resolved[k] == (list(v) if isinstance(v, list) else v), (verb, k)


def test_the_commented_multipie_detector_stage_plans_before_preprocess(cli, tmp_path):
    """The recipe's commented detect-landmarks-multipie stage, enabled as its comment says, runs on the room-light
    shots and feeds preprocess-multipie."""
    ws = make_layout(tmp_path)
    text = RECIPE.read_text()
    block = [ln[2:] for ln in text.splitlines()
             if ln.startswith("# [stages.detect-landmarks-multipie]") or ln.startswith("# verb = \"detect-landmarks\"")
             or ln.startswith("# inputs = { images = \"data/multipie") or ln.startswith("# params = { allow_missing")]
    assert len(block) == 4, block
    text = text.replace('inputs = { root = "data/multipie" }',
                        'inputs = { root = "data/multipie", landmarks = "@detect-landmarks-multipie.dir" }')
    text = text.replace("[stages.preprocess-multipie]", "\n".join(block) + "\n\n[stages.preprocess-multipie]")
    assert "landmark_weights = { jaw = 0 }" in text  # the comment's fit-geometry setting, applied as it says
    text = text.replace("params = { flash_intensity = 1.0, rig_sigma_mm = 50.0 }",
                        "params = { flash_intensity = 1.0, rig_sigma_mm = 50.0, landmark_weights = { jaw = 0 } }")
    (ws / "r.toml").write_text(text)
    r = cli("run", ws / "r.toml", "-w", ws, "--dry-run")
    assert r.exit_code == 0, r.stderr
    rows = [ln.split(None, 3) for ln in r.stdout.splitlines()[2:]]
    acts = {(row[0], row[1]): row[2] for row in rows}
    assert acts[("detect-landmarks-multipie", "-")] == "run"
    # the identities are found once the detector has run (its folder is an input of preprocess-multipie)
    assert acts[("preprocess-multipie", "-")] == "deferred"

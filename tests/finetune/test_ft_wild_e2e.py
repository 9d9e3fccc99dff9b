"""End to end on real shards: synth wild → prepare-wild --from-truth → build-light-pca → finetune → reconstruct
(shards and raw photos), through the command line and as a recipe (a rerun executes nothing)."""
import json
import shutil

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact

TINY = ["--arch", "resnet18", "--width", "8", "--batch-size", "2", "--epochs1", "1", "--epochs2", "1",
        "--threads", "1", "--samples", "4"]


@pytest.fixture(scope="module")
def wild(tmp_path_factory):
    """8 synth-wild images (4 identities, 64²), one shard prepared from the truth geometry, and an initial
    reflectance model built with build-pca's library from the identities' reflectance carried into UV space."""
    from reflectmm_cli.finetune.data import PrepareConfig, prepare_wild_shard
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.geometry.uv import rasterize_uv, vertex_to_uv_map
    from reflectmm_cli.model.pca import MODEL_KIND, add_vertex_model, fit_reflectance_pca, model_arrays
    from reflectmm_cli.synth.wild import WildConfig, synth_wild

    root = tmp_path_factory.mktemp("ft_wild")
    out = root / "wild"
    fm = procedural_face_model(grid=(61, 51), n_shape=6, n_exp=4, seed=2)
    synth_wild(out, WildConfig(count=8, size=64, images_per_identity=2, envmaps=1, envmap_width=64,
                               prefilter_width=32, uv_size=64, occluder_fraction=0.0, seed=3, encoding="srgb"),
               face_model=fm)
    shard, _, err = prepare_wild_shard(out / "images", root / "shards", fm, out / "face_model.npz",
                                       PrepareConfig(size=64, from_truth=True, aligned=True, shard_size=8), 0,
                                       truth_dir=out)
    assert not err
    r = rasterize_uv(fm.uv, fm.triangles, 32)
    ids = sorted((out / "identities").glob("id*.npz"))
    alb, wts = [], []
    for p in ids:
        a = read_artifact(p, "wild-truth")
        alb.append(vertex_to_uv_map(np.asarray(a["vertex_albedo"], np.float64), r))
        wts.append(vertex_to_uv_map(np.asarray(a["vertex_weights"], np.float64), r))
    model = fit_reflectance_pca(alb, wts, [1, 8, 64], masks=[r.mask] * len(ids), components=3,
                                ids=[p.stem for p in ids])
    add_vertex_model(model, fm.uv)
    init = write_artifact(root / "init.npz", MODEL_KIND, model_arrays(model))
    return {"root": root, "out": out, "shard": shard, "init": init, "n_vertices": fm.n_vertices}


@pytest.mark.slow
def test_cli_end_to_end_on_real_shards(cli, wild, tmp_path):
    ws = tmp_path / "ws"
    r = cli("build-light-pca", wild["out"] / "envmaps", "--order", 8, "--rotations", 8, "--components", 4, "-w", ws)
    assert r.exit_code == 0, r.stderr
    # the light model from the workspace default, the face model from the shard's meta
    r = cli("finetune", "--model", wild["init"], "--data", wild["shard"], "-w", ws, "--json", *TINY)
    assert r.exit_code == 0, r.stderr
    out = ws / "finetune" / "finetune.npz"
    assert json.loads(r.stdout)["outputs"][-1] == str(out)
    art = read_artifact(out, "reflectance-model")
    assert art["vertex_albedo_mean"].shape == (wild["n_vertices"], 3)
    assert art.meta["params"]["epochs2"] == 1 and "threads" not in art.meta["params"]
    assert (ws / "finetune" / "finetune_samples_after.png").is_file()   # face model found through the shard
    init = read_artifact(wild["init"], "reflectance-model")
    assert not np.array_equal(art["vertex_albedo_mean"], init["vertex_albedo_mean"])
    # reconstruct the shard with the workspace defaults (encoder, finetuned model, light model)
    r = cli("reconstruct", "--data", wild["shard"], "-w", ws)
    assert r.exit_code == 0, r.stderr
    rec = read_artifact(ws / "reconstruct" / "reconstruct.npz", "reconstruction")
    assert rec["full"].shape == (8, 64, 64, 3) and rec["sh"].shape == (8, 3, 81)
    assert np.isfinite(rec["full"].astype(np.float32)).all() and rec["full"].astype(np.float32).max() > 0
    # raw photos: aligned, fitted and G-buffered in memory by prepare-wild's library, then the same path
    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    (photos / "landmarks").mkdir()
    names = sorted(p.stem for p in (wild["out"] / "images").glob("*.png"))[:2]
    for n in names:
        shutil.copy(wild["out"] / "images" / f"{n}.png", photos / "images" / f"{n}.png")
        shutil.copy(wild["out"] / "landmarks" / f"{n}.pts", photos / "landmarks" / f"{n}.pts")
    r = cli("reconstruct", "--images", photos / "images", "--face-model", wild["out"] / "face_model.npz",
            "--size", 64, "-w", ws, "-o", tmp_path / "photos.npz")
    assert r.exit_code == 0, r.stderr
    ph = read_artifact(tmp_path / "photos.npz", "reconstruction")
    assert ph["names"].tolist() == names and ph["full"].shape == (2, 64, 64, 3)
    assert (tmp_path / "photos.png").is_file()
    # the photos' reconstruction sees the same face as the shard's (same images, geometry fitted instead of true)
    i = [str(x) for x in rec["names"]].index(names[0])
    both = ph["face_mask"][0] & rec["face_mask"][i]
    assert both.sum() > 0.6 * rec["face_mask"][i].sum()
    # no landmark for one image: reported, the other written, exit 1 (0 with --allow-skipped)
    (photos / "landmarks" / f"{names[1]}.pts").unlink()
    r = cli("reconstruct", "--images", photos / "images", "--face-model", wild["out"] / "face_model.npz",
            "--size", 64, "-w", ws, "-o", tmp_path / "one.npz")
    assert r.exit_code == 1 and f"{names[1]}.png" in r.stderr and "no landmark file" in r.stderr
    assert read_artifact(tmp_path / "one.npz", "reconstruction")["names"].tolist() == names[:1]


@pytest.mark.slow
def test_recipe_end_to_end_then_noop(cli, wild, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "r.toml").write_text(f'''schema = "reflectmm.recipe/1"
name = "finetune-e2e"

[stages.build-light-pca]
inputs = {{ envmaps = "{wild['out'] / 'envmaps'}" }}
params = {{ order = 8, rotations = 8, components = 4 }}

[stages.finetune]
inputs = {{ model = "{wild['init']}", light_model = "@build-light-pca.output", data = "{wild['root'] / 'shards'}" }}
params = {{ arch = "resnet18", width = 8, batch_size = 2, epochs1 = 1, epochs2 = 1, samples = 4, threads = 1 }}

[stages.reconstruct]
inputs = {{ encoder = "@finetune.outputs.finetune_encoder", model = "@finetune.output", light_model = "@build-light-pca.output", data = "{wild['shard']}" }}
params = {{ split = "train" }}
''')
    r = cli("run", ws / "r.toml", "-w", ws)
    assert r.exit_code == 0, r.stderr
    rec = read_artifact(ws / "reconstruct" / "reconstruct.npz", "reconstruction")
    assert len(rec["names"]) == int((np.asarray(read_artifact(wild["shard"])["split"]) == "train").sum())
    r = cli("run", ws / "r.toml", "-w", ws)
    assert r.exit_code == 0 and r.stdout == "", r.stdout
    r = cli("run", ws / "r.toml", "-w", ws, "-n")
    assert "3 skip" in r.stdout.splitlines()[0], r.stdout
    # the same work from the command line has the recipe's cache key (declared defaults filled in both)
    key = read_artifact(ws / "finetune" / "finetune.npz").meta["cache_key"]
    r = cli("finetune", "--model", wild["init"], "--light-model", ws / "build-light-pca" / "build-light-pca.npz",
            "--data", wild["root"] / "shards", "-w", ws, "-o", tmp_path / "cli" / "finetune.npz", *TINY[:-2],
            "--samples", 4)
    assert r.exit_code == 0, r.stderr
    assert read_artifact(tmp_path / "cli" / "finetune.npz").meta["cache_key"] == key


def test_bad_wild_inputs_are_refused_or_said(cli, wild, tmp_path):
    """reconstruct --landmarks DIR was refused as an unknown input; prepare-wild --from-truth with another mesh wrote
    a shard whose truth and vertex ids disagree; landmarks collapsed to a point placed a face 350 m away; an image
    without a skin pixel crashed the refinement."""
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.geometry.face_model import save_face_model

    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    (photos / "lms").mkdir()  # not beside the images nor ../landmarks: only --landmarks finds them
    names = sorted(p.stem for p in (wild["out"] / "images").glob("*.png"))[:3]
    for n in names:
        shutil.copy(wild["out"] / "images" / f"{n}.png", photos / "images" / f"{n}.png")
        shutil.copy(wild["out"] / "landmarks" / f"{n}.pts", photos / "lms" / f"{n}.pts")
    light = tmp_path / "light.npz"
    assert cli("build-light-pca", wild["out"] / "envmaps", "--order", 8, "--rotations", 2, "--components", 4,
               "-o", light).exit_code == 0
    enc_ws = tmp_path / "ws"
    r = cli("finetune", "--model", wild["init"], "--data", wild["shard"], "--light-model", light, "-w", enc_ws,
            *TINY)
    assert r.exit_code == 0, r.stderr
    rec = ("reconstruct", "--images", photos / "images", "--face-model", wild["out"] / "face_model.npz", "--size",
           64, "-w", enc_ws, "--light-model", light)
    r = cli(*rec, "--landmarks", photos / "lms", "-o", tmp_path / "a.npz")
    assert r.exit_code == 0 and read_artifact(tmp_path / "a.npz")["names"].tolist() == names, r.stderr
    # one image's landmarks collapsed to a point: skipped and named, the others written, exit 1
    pts = (photos / "lms" / f"{names[2]}.pts").read_text().splitlines()
    (photos / "lms" / f"{names[2]}.pts").write_text("\n".join(
        ln if not ln[:1].isdigit() else "30.0 30.0" for ln in pts) + "\n")
    r = cli(*rec, "--landmarks", photos / "lms", "-o", tmp_path / "b.npz")
    assert r.exit_code == 1 and f"{names[2]}.pts: landmarks span 0 x 0 px" in r.stderr, r.stderr
    assert read_artifact(tmp_path / "b.npz")["names"].tolist() == names[:2]
    # a shard image without a skin pixel: the refinement keeps its start and says so
    a = read_artifact(wild["shard"])
    arrays = dict(a.arrays)
    arrays["skin_mask"] = arrays["skin_mask"].copy()
    arrays["skin_mask"][0] = False
    noskin = write_artifact(tmp_path / "noskin.npz", "wild-shard", arrays, extra_meta={
        k: v for k, v in a.meta.items() if k not in ("schema", "kind", "producer", "created")}, compress=False)
    r = cli("reconstruct", "--data", noskin, "-w", enc_ws, "--light-model", light, "--refine", "--refine-iterations",
            2, "-o", tmp_path / "c.npz")
    assert r.exit_code == 0 and "has no skin pixel to fit" in r.stderr and "internal error" not in r.stderr, r.stderr
    # --from-truth with a face model of another mesh
    other = tmp_path / "other_fm.npz"
    save_face_model(procedural_face_model(grid=(31, 25), n_shape=2, n_exp=1, seed=0), other)
    r = cli("prepare-wild", "--images", wild["out"] / "images", "--truth", wild["out"], "--from-truth", "--size", 64,
            "--face-model", other, "--out", tmp_path / "shards")
    assert r.exit_code == 1 and "other_fm.npz: has" in r.stderr and "--from-truth needs the face model" in r.stderr
    assert not (tmp_path / "shards").exists() or not any((tmp_path / "shards").glob("*.npz"))

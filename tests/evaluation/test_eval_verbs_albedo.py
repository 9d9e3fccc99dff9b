"""build-baseline and evaluate albedo (Table 3) through the CLI on tiny synthetic data."""
import json

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.evaluation.baselines import is_diffuse_only
from reflectmm_cli.geometry import procedural_face_model
from reflectmm_cli.geometry.face_model import save_face_model
from reflectmm_cli.model.pca import fit_reflectance_pca, model_arrays, add_vertex_model
from reflectmm_cli.reflectance.simulate import simulate_observations

S = 16
TRAIN = ["t0", "t1", "t2", "t3", "t4"]
HELD = ["h0", "h1"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """5 'scanned' identities (truth only) and 2 held-out identities (truth + uv-observations), exact 3-lobe
    renders; a small procedural face model."""
    ws = tmp_path_factory.mktemp("albedo_ws")
    truths = {}
    for k, iid in enumerate(TRAIN + HELD):
        obs, tr = simulate_observations(size=S, seed=k, return_truth=True, views=[2, 4, 6], flashes=[1, 4, 7, 9],
                                        dtype=np.float32)
        t = {"albedo": np.asarray(tr["albedo"], np.float32), "weights": np.asarray(tr["weights"], np.float32),
             "spec_albedo": np.asarray(tr["weights"], np.float32).sum(0), "uv_mask": np.asarray(obs["mask"], bool)}
        truths[iid] = t
        folder = "truth" if iid in TRAIN else "held_truth"
        write_artifact(ws / folder / f"{iid}.npz", "synth-truth", t, extra_meta={"identity": iid})
        if iid in HELD:
            write_artifact(ws / "unwrap-uv" / f"{iid}.npz", "uv-observations", obs, extra_meta={"identity": iid})
    fm = procedural_face_model(n_vertices=800)
    save_face_model(fm, ws / "face_model.npz")
    return {"ws": ws, "truths": truths, "fm": fm}


def test_build_baseline_cli_both_kinds(world, cli):
    ws = world["ws"]
    r = cli("-q", "build-baseline", "--kind", "diffuse-only", "--components", "3", "--truth", ws / "truth",
            "--face-model", ws / "face_model.npz", "-w", ws, "--json")
    assert r.exit_code == 0, r.stderr
    out = ws / "build-baseline" / "diffuse-only.npz"
    assert json.loads(r.stdout)["outputs"][0] == str(out)
    assert (ws / "build-baseline" / "diffuse-only_components.png").is_file()
    art = read_artifact(out, "reflectance-model")
    assert art.meta["baseline"] == "diffuse-only" and art.meta["role"] == "BFM09" and is_diffuse_only(art.arrays)
    assert art["albedo_basis"].shape == (3, 3, S, S) and "vertex_albedo_mean" in art.arrays
    # independent: the PCA mean is the mean of the 5 truths' albedo inside the common mask
    m = np.asarray(art["mask"], bool)
    ref = np.mean([world["truths"][i]["albedo"] for i in TRAIN], 0)
    np.testing.assert_allclose(art["albedo_mean"][:, m], ref[:, m], rtol=1e-5, atol=1e-6)
    r = cli("-q", "build-baseline", "--kind", "albedomm", "--components", "10", "--truth", ws / "truth",
            "--face-model", ws / "face_model.npz", "-w", ws)
    assert r.exit_code == 0, r.stderr
    a = read_artifact(ws / "build-baseline" / "albedomm.npz", "reflectance-model")
    assert list(a["exponents"]) == [20.0] and a["sigma"].shape == (4,)  # capped at N − 1
    # lobe weight mean = the mean specular albedo (Σw = spec albedo)
    ref = np.mean([world["truths"][i]["spec_albedo"] for i in TRAIN], 0)
    np.testing.assert_allclose(a["weights_mean"][0][m], ref[m], rtol=1e-5, atol=1e-6)
    # rerun with nothing changed: byte-identical
    before = (ws / "build-baseline" / "albedomm.npz").read_bytes()
    cli("-q", "build-baseline", "--kind", "albedomm", "--components", "10", "--truth", ws / "truth",
        "--face-model", ws / "face_model.npz", "-w", ws)
    assert (ws / "build-baseline" / "albedomm.npz").read_bytes() == before


def test_build_baseline_bad_inputs(world, cli, tmp_path):
    ws = world["ws"]
    r = cli("build-baseline", "--kind", "bfm17", "--truth", ws / "truth", "--face-model", ws / "face_model.npz",
            "-o", tmp_path / "x.npz")
    assert r.exit_code != 0
    r = cli("build-baseline", "--ids", "t0,t9", "--truth", ws / "truth", "--face-model", ws / "face_model.npz",
            "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "no truth file for identity 't9'" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = cli("build-baseline", "--ids", "t0", "--truth", ws / "truth", "--face-model", ws / "face_model.npz",
            "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "at least 2 truth identities" in r.stderr
    r = cli("build-baseline", "--exponent", "0", "--truth", ws / "truth", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "--exponent" in r.stderr
    assert not (tmp_path / "x.npz").exists()


def _ours(world, path):
    """'ours': the exact 3-lobe PCA of the training truths (the world's own representation)."""
    tr = [world["truths"][i] for i in TRAIN]
    m = fit_reflectance_pca([t["albedo"] for t in tr], [t["weights"] for t in tr], [1.0, 8.0, 64.0],
                            masks=[t["uv_mask"] for t in tr], components=4, ids=TRAIN)
    add_vertex_model(m, world["fm"].uv)
    write_artifact(path, "reflectance-model", model_arrays(m))
    return path


def test_evaluate_albedo_cli(world, cli):
    ws = world["ws"]
    for kind in ("diffuse-only", "albedomm"):
        assert cli("-q", "build-baseline", "--kind", kind, "--components", "4", "--truth", ws / "truth",
                   "--face-model", ws / "face_model.npz", "-w", ws).exit_code == 0
    ours = _ours(world, ws / "ours.npz")
    r = cli("-q", "evaluate", "albedo", "--ids", "h0,h1", "--truth", ws / "held_truth", "-w", ws,
            "--method", "diffuse-only", ws / "build-baseline" / "diffuse-only.npz", "-",
            "--method", "albedomm", ws / "build-baseline" / "albedomm.npz", "-",
            "--method", "finetuned", ours, "-", "--json")
    assert r.exit_code == 0, r.stderr
    out = ws / "evaluate-albedo" / "evaluate-albedo.npz"
    art = read_artifact(out, "evaluation")
    assert art.meta["methods"] == ["diffuse-only", "albedomm", "finetuned"] and art.meta["identities"] == HELD
    s = art.meta["summary"]
    names = list(art["names"])
    # the world is rendered with the 3 lobes: the 3-lobe model fits the held-out images best (fit residual)
    res = {m: np.mean([art["values"][names.index(f"fits.{m}.{i}.rms_residual")] for i in HELD])
           for m in art.meta["methods"]}
    assert res["finetuned"] < res["albedomm"] < res["diffuse-only"], res
    # independent closed form: Σw = 0 for diffuse-only, so its specular PSNR is 10 log10(1 / mean(s*²)) over the
    # region (observed in some pair ∧ observation mask ∧ model domain ∧ truth mask)
    model = read_artifact(ws / "build-baseline" / "diffuse-only.npz", "reflectance-model")
    for iid in HELD:
        obs = read_artifact(ws / "unwrap-uv" / f"{iid}.npz", "uv-observations")
        t = world["truths"][iid]
        reg = np.asarray(obs["observed"], bool).any(0) & np.asarray(obs["mask"], bool) & model["mask"] & t["uv_mask"]
        ref = 10 * np.log10(1.0 / np.mean(t["spec_albedo"][reg].astype(np.float64) ** 2))
        got = art["values"][names.index(f"per_identity.diffuse-only.{iid}.raw.specular_psnr")]
        assert got == pytest.approx(ref, abs=1e-6)
    assert art.meta["paper_numbers"]["table3.diffuse_psnr"] == pytest.approx(s["finetuned"]["raw.diffuse_psnr"]["mean"])
    md = out.with_suffix(".md").read_text()
    assert "| finetuned |" in md and "Command: `reflectmm evaluate albedo" in md
    assert "--method finetuned ours.npz -" in art.meta["command"] and "--input unwrap-uv/h0.npz" in art.meta["command"]
    # the report's Table 3 section and the paper-vs-reflectmm row with the command that made it
    r = cli("-q", "evaluate", "report", "-w", ws)
    assert r.exit_code == 0, r.stderr
    rep = (ws / "evaluate-report" / "evaluate-report.md").read_text()
    assert "## Table 3: albedo of held-out identities" in rep and "Identities: h0, h1." in rep
    d = art.meta["paper_numbers"]["table3.diffuse_psnr"]
    assert f"| Table 3 | diffuse albedo PSNR (ours) | 20.13 dB | {d:.2f} dB | `reflectmm evaluate albedo" in rep
    assert "| Table 2 | PSNR gain of ours over ours w/o finetuning | +0.95 dB | not run |" in rep


def test_evaluate_albedo_bad_inputs(world, cli, tmp_path):
    ws = world["ws"]
    ours = _ours(world, tmp_path / "ours.npz")
    # a held-out identity without truth
    r = cli("evaluate", "albedo", "--ids", "h0", "--truth", ws / "truth", "-w", ws, "--method", "ours", ours, "-",
            "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "no truth file for identity 'h0'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    # a bad method name and a duplicate
    r = cli("evaluate", "albedo", "--ids", "h0", "--truth", ws / "held_truth", "-w", ws, "--method", "Ours!", ours,
            "-", "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "method name 'Ours!'" in r.stderr
    r = cli("evaluate", "albedo", "--ids", "h0", "--truth", ws / "held_truth", "-w", ws, "--method", "a", ours, "-",
            "--method", "a", ours, "-", "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "given twice" in r.stderr
    # a model of another UV size
    other = _ours({"truths": {k: {kk: (v[..., ::2, ::2] if np.ndim(v) >= 2 else v) for kk, v in t.items()}
                              for k, t in world["truths"].items()}, "fm": world["fm"]}, tmp_path / "small.npz")
    r = cli("evaluate", "albedo", "--ids", "h0", "--truth", ws / "held_truth", "-w", ws, "--method", "s", other, "-",
            "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "UV size 8" in r.stderr
    assert not (tmp_path / "a.npz").exists()


def test_evaluate_albedo_refuses_a_truth_file_of_another_identity(world, cli, tmp_path):
    # truth files are found by name: another identity's truth under this name was scored without a word
    import shutil

    ws = world["ws"]
    ours = _ours(world, tmp_path / "ours.npz")
    fake = tmp_path / "fake_truth"
    fake.mkdir()
    shutil.copy(ws / "truth" / f"{TRAIN[0]}.npz", fake / f"{HELD[0]}.npz")
    r = cli("evaluate", "albedo", "--ids", HELD[0], "--truth", fake, "-w", ws, "--method", "ours", ours, "-",
            "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and f"is identity {TRAIN[0]}'s truth" in r.stderr and str(fake) in r.stderr, r.stderr
    assert not (tmp_path / "a.npz").exists()


def test_an_encoder_given_to_evaluate_albedo_is_said_to_be_unused(world, cli, tmp_path):
    ws = world["ws"]
    ours = _ours(world, tmp_path / "ours.npz")
    enc = tmp_path / "enc.safetensors"
    enc.write_bytes(b"")
    r = cli("evaluate", "albedo", "--ids", HELD[0], "--truth", ws / "held_truth", "-w", ws, "--method", "ours", ours,
            enc, "-o", tmp_path / "a.npz")
    assert r.exit_code == 0 and "the encoder of method(s) ours is not used" in r.stderr, r.stderr


def test_build_baseline_counts_an_identity_once(world, cli, tmp_path):
    # a truth folder and one of its files counted that identity twice
    ws = world["ws"]
    r = cli("build-baseline", "--kind", "diffuse-only", "--components", "2", "--truth", ws / "truth", "--truth",
            ws / "truth" / f"{TRAIN[0]}.npz", "--face-model", ws / "face_model.npz", "-o", tmp_path / "b.npz")
    assert r.exit_code == 1 and "given twice" in r.stderr and not (tmp_path / "b.npz").exists(), r.stderr
    one = ws / "truth" / f"{TRAIN[0]}.npz"  # one file twice: said so, not "the maps are all identical"
    r = cli("-q", "build-baseline", "--truth", one, "--truth", one, "--face-model", ws / "face_model.npz", "-o",
            tmp_path / "b.npz")
    assert r.exit_code == 1 and r.stderr.strip() == (f"reflectmm: error: {one}: build-baseline: given twice (also as "
                                                     f"{one}): each identity counts once"), r.stderr


def test_build_baseline_names_a_truth_of_another_uv_size(world, cli, tmp_path):
    # the PCA's message said "build-pca: t1: albedo has shape ...": another verb, and no file
    mixed = tmp_path / "mixed"
    t0 = world["truths"][TRAIN[0]]
    write_artifact(mixed / "t0.npz", "synth-truth", t0, extra_meta={"identity": "t0"})
    half = {k: v[..., ::2, ::2] for k, v in world["truths"][TRAIN[1]].items()}
    write_artifact(mixed / "t1.npz", "synth-truth", half, extra_meta={"identity": "t1"})
    r = cli("build-baseline", "--truth", mixed, "--face-model", world["ws"] / "face_model.npz", "-o",
            tmp_path / "b.npz")
    assert r.exit_code == 1 and r.stderr.strip().splitlines()[-1] == (
        f"reflectmm: error: {mixed / 't1.npz'}: build-baseline: albedo has shape (3, 8, 8), but (3, {S}, {S}) in "
        f"{mixed / 't0.npz'}: the truths must share one UV size"), r.stderr
    assert not (tmp_path / "b.npz").exists()

"""finetune and reconstruct through the CLI on tiny data; one-line errors for bad inputs."""
import json

import numpy as np
import pytest

from _shards import (make_dataset, model_of_fewer_vertices, small_light_model, write_face_model, write_model,
                     wrong_initial)
from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.shards import load_shards

TINY = ["--arch", "resnet18", "--width", "8", "--batch-size", "4", "--epochs1", "1", "--epochs2", "1",
        "--lr1", "2e-3", "--model-lr", "1e-3", "--threads", "1", "--samples", "6"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ft_cli")
    d = make_dataset(tmp, n_images=10, size=32, seed=4)
    d["face_model"] = write_face_model(tmp / "face_model.npz", d["V"], d["tri"], d["uv"])
    d["init_path"] = write_model(tmp / "init.npz", wrong_initial(d["truth"], d["V"]))
    return d


def test_finetune_then_reconstruct_cli(cli, data, tmp_path):
    out = tmp_path / "ft" / "model.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, "--json", *TINY)
    assert r.exit_code == 0, r.output + r.stderr
    outs = json.loads(r.stdout)["outputs"]
    assert outs[-1] == str(out)
    art = read_artifact(out, "reflectance-model")
    ft = art.meta["finetune"]
    assert ft["perceptual"] == "off" and ft["steps"] == 4
    assert "update" in ft["uv_maps"] and ft["uv_update_roundtrip_rms"] < 0.5 * ft["vertex_update_rms"] + 1e-9
    init = read_artifact(data["init_path"], "reflectance-model")
    assert not np.array_equal(art["vertex_albedo_mean"], init["vertex_albedo_mean"])  # phase 2 changed it
    assert np.array_equal(art["sigma"], init["sigma"])
    for name in ("model_encoder.safetensors", "model_loss.png", "model_samples_before.png", "model_samples_after.png",
                 "model_components_before.png", "model_components_after.png", "model_work/log.jsonl"):
        assert (out.parent / name).is_file(), name
    rec = tmp_path / "rec.npz"
    r = cli("reconstruct", "--encoder", out.parent / "model_encoder.safetensors", "--model", out, "--light-model",
            data["light_path"], "--data", data["shards"][0], "--split", "val", "-o", rec)
    assert r.exit_code == 0, r.output + r.stderr
    a = read_artifact(rec, "reconstruction")
    n_val = int((load_shards(data["shards"]).split == "val").sum())
    assert a["full"].shape == (n_val, 32, 32, 3) and a["weights"].shape == (n_val, 32, 32, 3)
    assert a["beta"].shape == (n_val, 3) and a["sh"].shape == (n_val, 3, 9)
    np.testing.assert_allclose(a["full"].astype(np.float32),
                               (a["diffuse"].astype(np.float32) + a["specular"].astype(np.float32)), atol=2e-3)
    assert rec.with_suffix(".png").is_file()


def test_device_cuda_without_cuda_is_one_line_error(cli, data, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    r = CliRunner().invoke(main, ["finetune", "--model", str(data["init_path"]), "--light-model",
                                  str(data["light_path"]), "--data", str(data["shards"][0]), "--device", "cuda",
                                  "-o", str(tmp_path / "m.npz")])
    assert r.exit_code != 0
    msg = r.stderr.strip() if r.stderr else r.output.strip()
    assert "CUDA is not available" in msg and len(msg.splitlines()) == 1


def test_bad_inputs_are_one_line_errors(data, tmp_path):
    from reflectmm_cli.finetune.train import check_inputs
    from _shards import cap_mesh, truth_model

    ss = load_shards(data["shards"])
    # SH order mismatch
    with pytest.raises(ReflectmmError, match="SH order 3.*order 2"):
        check_inputs(ss, data["truth"], small_light_model(order=3))
    # vertex-count mismatch
    V, _, _ = cap_mesh(5)
    with pytest.raises(ReflectmmError, match="has 25 vertices"):
        check_inputs(ss, truth_model(V), data["light"])
    # model without per-vertex part
    m = truth_model(data["V"])
    m.vertex_albedo_mean = None
    with pytest.raises(ReflectmmError, match="per-vertex"):
        check_inputs(ss, m, data["light"])
    # empty shard
    a = read_artifact(data["shards"][0]).arrays
    empty = {k: v[:0] for k, v in a.items()}
    empty["pix_offset"] = np.zeros(1, np.int64)
    p = write_artifact(tmp_path / "empty.npz", "wild-shard", empty, compress=False)
    with pytest.raises(ReflectmmError, match="empty shard") as e:
        load_shards([p])
    assert "empty.npz" in str(e.value) and "\n" not in str(e.value)
    # NaN image
    d = make_dataset(tmp_path / "nan", n_images=3, size=24, mesh_n=9, nan_image=True)
    with pytest.raises(ReflectmmError, match="NaN") as e:
        load_shards(d["shards"])
    assert "\n" not in str(e.value)
    # wrong kind
    with pytest.raises(ReflectmmError, match="wild-shard"):
        load_shards([data["light_path"]])


def test_reconstruct_with_known_coefficients_matches_truth_layers(data):
    """An encoder whose head outputs image 0's true β, γ, z (zero weights, bias set) reconstructs image 0's
    diffuse and specular layers as rendered by the independent numpy path."""
    import math

    import torch

    from reflectmm_cli.finetune.encoder import build_encoder
    from reflectmm_cli.finetune.reconstruct import reconstruct

    ss = load_shards(data["shards"])
    enc = build_encoder("resnet18", 3, data["light"].n_components, width=8, z0=2.0)
    z = data["zs"][0]
    with torch.no_grad():
        enc.fc.bias.copy_(torch.tensor(np.concatenate([data["betas"][0], data["gammas"][0],
                                                       [math.log(math.expm1(v)) - enc.z_offset for v in z]])))
    rec = reconstruct(ss, enc, data["truth"], data["light"], indices=[0])
    np.testing.assert_allclose(rec.z[0], z, rtol=1e-5)
    np.testing.assert_allclose(rec.diffuse[0], ss.truth["truth_diffuse"][0].astype(np.float32), atol=2e-3)
    np.testing.assert_allclose(rec.specular[0], ss.truth["truth_specular"][0].astype(np.float32), atol=2e-3)
    assert rec.albedo[0][~ss.face_mask[0]].max() == 0


def test_phase1_only_leaves_the_written_model_unchanged(cli, data, tmp_path):
    """--epochs2 0 (a baseline encoder on the initial model): every array of the written model, per-vertex and UV,
    equals the initial model's."""
    out = tmp_path / "p1.npz"
    args = [a for a in TINY]
    args[args.index("--epochs2") + 1] = "0"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *args)
    assert r.exit_code == 0, r.stderr
    got, init = read_artifact(out, "reflectance-model"), read_artifact(data["init_path"], "reflectance-model")
    assert got.meta["params"]["epochs2"] == 0 and got.meta["finetune"]["steps"] == 2
    assert set(got.arrays) == set(init.arrays)
    for k in init.arrays:
        assert np.array_equal(got[k], init[k]), k


def test_samples_zero_writes_no_sample_pngs_and_keeps_the_outputs_paired(cli, data, tmp_path):
    """--samples 0 (inside the declared range) used to fail with an internal error after the encoder had been
    replaced; now it succeeds, and sample PNGs of an earlier run at the same path do not stay behind."""
    out = tmp_path / "ft" / "m.npz"
    base = ["finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out]
    r = cli(*base, *TINY)
    assert r.exit_code == 0, r.stderr
    assert (out.parent / "m_samples_after.png").is_file()
    args = list(TINY)
    args[args.index("--samples") + 1] = "0"
    args[args.index("--epochs1") + 1] = "2"
    r = cli(*base, *args)
    assert r.exit_code == 0, r.stderr
    assert not (out.parent / "m_samples_after.png").exists() and not (out.parent / "m_samples_before.png").exists()
    assert (out.parent / "m_components_after.png").is_file()
    art = read_artifact(out, "reflectance-model")
    assert art.meta["params"]["epochs1"] == 2  # the model and its encoder are the second run's
    from safetensors import safe_open

    with safe_open(str(out.parent / "m_encoder.safetensors"), "np") as f:
        assert json.loads(f.metadata()["__meta__"])["config"]["epochs1"] == 2


def test_model_lr_zero_is_the_equal_budget_control(cli, data, tmp_path):
    """Table 2's control (``--model-lr 0``, the recipe's finetune-control): the model it writes equals the initial
    model array for array, its phase-1 encoder equals the phase-1 encoder of the run that updates the model (the
    same seed, data and schedule), and its final encoder differs from that run's (phase 2 trained the encoder
    against another model) — so the two runs differ in the model update alone."""
    from safetensors.numpy import load_file

    outs = {}
    for name, lr in (("upd", "1e-3"), ("ctl", "0")):
        args = list(TINY)
        args[args.index("--model-lr") + 1] = lr
        out = tmp_path / name / "m.npz"
        r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
                data["shards"][0], "--face-model", data["face_model"], "-o", out, *args)
        assert r.exit_code == 0, r.stderr
        outs[name] = out
    ctl, init = read_artifact(outs["ctl"], "reflectance-model"), read_artifact(data["init_path"], "reflectance-model")
    for k in init.arrays:
        assert np.array_equal(ctl[k], init[k]), k
    p1 = [load_file(outs[n].parent / "m_encoder_phase1.safetensors") for n in ("upd", "ctl")]
    assert p1[0].keys() == p1[1].keys() and all(np.array_equal(p1[0][k], p1[1][k]) for k in p1[0])
    fin = [load_file(outs[n].parent / "m_encoder.safetensors") for n in ("upd", "ctl")]
    assert any(not np.array_equal(fin[0][k], fin[1][k]) for k in fin[0])


def test_an_encoder_is_refused_with_a_model_it_was_not_trained_for(cli, data, tmp_path):
    """Issue 24 §3: the encoder's meta records its model's sha256. reconstruct accepts that model and the finetune
    output made from it; another model is a one-line error naming both files, unless --allow-other-model (then a
    warning). evaluate reconstruction applies the same check per method."""
    out = tmp_path / "ft" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY)
    assert r.exit_code == 0, r.stderr
    enc = out.parent / "m_encoder.safetensors"
    base = ["--encoder", enc, "--light-model", data["light_path"], "--data", data["shards"][0], "--split", "val"]
    for model in (data["init_path"], out):  # the model it was trained for, and the finetune output made from it
        r = cli("reconstruct", *base, "--model", model, "-o", tmp_path / "ok.npz")
        assert r.exit_code == 0, r.stderr
    other = data["truth_path"]
    rec = tmp_path / "bad.npz"
    r = cli("reconstruct", *base, "--model", other, "-o", rec)
    assert r.exit_code == 1 and not rec.exists()
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and str(enc) in err and str(other) in err and "--allow-other-model" in err
    r = cli("reconstruct", *base, "--model", other, "--allow-other-model", "-o", rec)
    assert r.exit_code == 0 and rec.is_file() and "warning" in r.stderr
    r = cli("evaluate", "reconstruction", "--data", data["shards"][0], "--light-model", data["light_path"],
            "--method", "x", other, enc, "--split", "val", "-o", tmp_path / "ev.npz")
    assert r.exit_code == 1 and str(other) in r.stderr and not (tmp_path / "ev.npz").exists()
    # a NaN weight surfaced as "shading: argument 'albedo' contains NaN", naming neither file nor tensor
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    sd = load_file(str(enc))
    with safe_open(str(enc), "pt") as f:
        meta = f.metadata()
    name = sorted(k for k, v in sd.items() if v.is_floating_point())[0]
    sd[name] = sd[name].clone()
    sd[name].view(-1)[0] = float("nan")
    save_file(sd, str(tmp_path / "nan_enc.safetensors"), metadata=meta)
    r = cli("reconstruct", *base[2:], "--encoder", tmp_path / "nan_enc.safetensors", "--model", data["init_path"],
            "-o", tmp_path / "nan.npz")
    assert r.exit_code == 1 and f"nan_enc.safetensors: encoder weight '{name}' contains NaN or inf" in r.stderr


def test_a_nan_in_the_model_is_refused_at_load_naming_the_file(cli, data, tmp_path):
    """Issue 24 §6: a NaN in the model reached training ("the loss became nan … lower the learning rate"); now the
    file and the array are named before anything runs, for finetune and reconstruct alike, and reconstruct's
    errors no longer begin with "finetune:"."""
    init = read_artifact(data["init_path"], "reflectance-model")
    arrays = dict(init.arrays)
    arrays["vertex_albedo_basis"] = arrays["vertex_albedo_basis"].copy()
    arrays["vertex_albedo_basis"][0, 3, 1] = np.nan
    bad = write_artifact(tmp_path / "nan.npz", "reflectance-model", arrays, extra_meta={"stats": init.meta.get("stats")})
    r = cli("finetune", "--model", bad, "--light-model", data["light_path"], "--data", data["shards"][0], "-o",
            tmp_path / "ft" / "m.npz", *TINY)
    assert r.exit_code == 1 and "nan.npz" in r.stderr and "vertex_albedo_basis" in r.stderr and "NaN" in r.stderr
    assert not (tmp_path / "ft").exists() or not any((tmp_path / "ft").glob("m*"))
    r = cli("reconstruct", "--refine", "--refine-from", "zero", "--model", bad, "--light-model", data["light_path"],
            "--data", data["shards"][0], "-o", tmp_path / "rec.npz")
    assert r.exit_code == 1 and "nan.npz" in r.stderr and not (tmp_path / "rec.npz").exists()
    # a model of another face model: the message names the verb that failed
    small = model_of_fewer_vertices(data["init_path"], tmp_path / "small.npz")
    r = cli("reconstruct", "--refine", "--refine-from", "zero", "--model", small, "--light-model", data["light_path"],
            "--data", data["shards"][0], "-o", tmp_path / "rec.npz")
    assert r.exit_code == 1 and "reconstruct: the shards reference vertex" in r.stderr and "finetune:" not in r.stderr


def test_reconstruct_warns_when_the_images_are_not_the_encoders_size(cli, data, tmp_path):
    """Issue 24 §6: an encoder trained at one size used on images of another ran without a word."""
    from safetensors import safe_open

    out = tmp_path / "ft" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY)
    assert r.exit_code == 0, r.stderr
    enc = out.parent / "m_encoder.safetensors"
    with safe_open(str(enc), "np") as f:
        assert json.loads(f.metadata()["__meta__"])["image_size"] == 32
    base = ["reconstruct", "--encoder", enc, "--model", out, "--light-model", data["light_path"], "--split", "val"]
    r = cli(*base, "--data", data["shards"][0], "-o", tmp_path / "a.npz")
    assert r.exit_code == 0 and "trained on" not in r.stderr
    other = make_dataset(tmp_path / "d24", n_images=3, size=24, seed=9)
    r = cli(*base, "--data", other["shards"][0], "-o", tmp_path / "b.npz")
    assert r.exit_code == 0 and "trained on 32² images, these are 24²" in r.stderr


def test_finetune_progress_to_a_captured_stderr_has_no_carriage_returns(cli, data, tmp_path):
    """Issue 24 §6: finetune wrote \\r-redrawn progress into log files and captured stderr."""
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "-o", tmp_path / "m.npz", *TINY)
    assert r.exit_code == 0, r.stderr
    assert "\r" not in r.stderr and "finetune phase 1 epoch 1 step" in r.stderr


def test_capped_components_and_an_untrained_encoder_are_said(cli, data, tmp_path):
    """Issue 24 §6: --components beyond the model was capped silently; --epochs1 0 --epochs2 0 wrote an untrained
    encoder without a word."""
    base = ["finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0]]
    args = list(TINY) + ["--components", "100"]
    r = cli(*base, "-o", tmp_path / "a" / "m.npz", *args)
    assert r.exit_code == 0 and "--components 100 but the reflectance model has 3 components; using 3" in r.stderr
    args = list(TINY)
    args[args.index("--epochs1") + 1] = "0"
    args[args.index("--epochs2") + 1] = "0"
    r = cli(*base, "-o", tmp_path / "b" / "m.npz", *args)
    assert r.exit_code == 0 and "no training step" in r.stderr


def test_finetune_solver_ls_writes_a_solved_model_and_an_encoder_trained_on_it(cli, data, tmp_path):
    """--solver ls: rounds of refinement and model solves, then the encoder trained on the solved model with the
    schedule of the control (model frozen). The written model is the solved one and moved towards the truth; the
    meta records the rounds; the encoder pairs with the model."""
    out = tmp_path / "ls" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY, "--solver", "ls",
            "--ls-rounds", "2", "--ls-max-pixels", "0")
    assert r.exit_code == 0, r.stderr
    art = read_artifact(out, "reflectance-model")
    rounds = art.meta["finetune"]["model_solve"]["rounds"]
    assert len(rounds) == 3 and all(x["solve_end"] <= x["solve_start"] for x in rounds[1:])
    init = read_artifact(data["init_path"], "reflectance-model")
    # what the model can represent: the images' true per-vertex albedo projected onto its span (the mean alone is
    # not identifiable: β can absorb a shift along the bases)
    from reflectmm_cli.evaluation.expressive import projection_residuals
    from reflectmm_cli.model.pca import sample_model

    ta, _ = sample_model(data["truth"], data["betas"], "vertex")

    def residual(m):
        return projection_residuals(m["vertex_albedo_mean"], m["vertex_albedo_basis"], m["sigma"], ta,
                                    prior=0.0).mean()

    assert residual(art) < 0.95 * residual(init)  # measured 0.135 against 0.154
    assert art.meta["finetune"]["update_rms"]["vertex_albedo_mean"] > 0
    assert not {"ls_harmonics", "ls_robust", "ls_update_bases", "ls_pull_scale"} & set(art.meta["params"])
    r = cli("reconstruct", "--encoder", out.parent / "m_encoder.safetensors", "--model", out, "--light-model",
            data["light_path"], "--data", data["shards"][0], "--split", "val", "-o", tmp_path / "rec.npz")
    assert r.exit_code == 0, r.stderr


def test_finetune_solver_ls_with_harmonics_changes_the_model_by_smooth_functions_only(cli, data, tmp_path):
    """--ls-harmonics Q --ls-robust K --ls-pull-scale relative: the change of the mean and of every basis lies in the span of the face
    mesh's Q lowest harmonics (Φ Φᵀ M Δ = Δ), the options are recorded, and a run without them records none (the
    cache keys of earlier runs are unchanged); an unknown pull scale is a one-line error."""
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.geometry.harmonics import cotangent_laplacian, mesh_harmonics

    out = tmp_path / "lsh" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY, "--solver", "ls",
            "--ls-rounds", "1", "--ls-max-pixels", "0", "--ls-harmonics", "12", "--ls-robust", "4",
            "--ls-pull-scale", "relative", "--ls-pull", "0.01")
    assert r.exit_code == 0, r.stderr
    art = read_artifact(out, "reflectance-model")
    init = read_artifact(data["init_path"], "reflectance-model")
    params = art.meta["params"]
    assert params["ls_harmonics"] == 12 and params["ls_robust"] == 4.0 and "ls_update_bases" not in params
    assert params["ls_pull_scale"] == "relative"
    fm = load_face_model(data["face_model"])
    phi, _ = mesh_harmonics(fm.mean_shape, fm.triangles, 12)
    _, M = cotangent_laplacian(fm.mean_shape, fm.triangles)
    for k in ("vertex_albedo_mean", "vertex_weights_mean"):
        delta = np.asarray(art[k], np.float64) - np.asarray(init[k], np.float64)
        assert np.abs(delta).max() > 1e-4
        np.testing.assert_allclose(phi @ (phi.T @ (M @ delta)), delta, atol=1e-5)
    delta = np.asarray(art["vertex_albedo_basis"], np.float64)[0] - np.asarray(init["vertex_albedo_basis"])[0]
    np.testing.assert_allclose(phi @ (phi.T @ (M @ delta)), delta, atol=1e-5)
    rounds = art.meta["finetune"]["model_solve"]["rounds"]
    assert rounds[1]["solve_end"] < rounds[1]["solve_start"] and rounds[1]["pixels_left_out"] >= 0
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "-o", tmp_path / "bad" / "m.npz", *TINY, "--solver", "ls", "--ls-pull-scale", "norm")
    assert r.exit_code != 0 and "pull" in r.stderr and not (tmp_path / "bad" / "m.npz").exists()


def test_a_control_started_from_the_phase1_encoder_equals_a_full_control_run(cli, data, tmp_path):
    """--phase1-encoder: the control run takes phase 1 from the finetuned run (same settings, data and seed) and
    trains phase 2 only; its encoder and model equal those of a control run that trains phase 1 itself. Another
    run's phase-1 encoder (other settings) is refused in one line."""
    from safetensors.numpy import load_file

    base = ["finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"]]
    upd = tmp_path / "upd" / "m.npz"
    assert cli(*base, "-o", upd, *TINY).exit_code == 0
    ctl_args = list(TINY)
    ctl_args[ctl_args.index("--model-lr") + 1] = "0"
    full = tmp_path / "full" / "m.npz"
    assert cli(*base, "-o", full, *ctl_args).exit_code == 0
    short = tmp_path / "short" / "m.npz"
    r = cli(*base, "-o", short, *ctl_args, "--phase1-encoder", upd.parent / "m_encoder_phase1.safetensors")
    assert r.exit_code == 0, r.stderr
    for name in ("m_encoder.safetensors", "m_encoder_phase1.safetensors"):
        a, b = load_file(full.parent / name), load_file(short.parent / name)
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a), name
    fa, fb = read_artifact(full, "reflectance-model"), read_artifact(short, "reflectance-model")
    for k in fa.arrays:
        assert np.array_equal(fa[k], fb[k]), k
    other = list(ctl_args)
    other[other.index("--lr1") + 1] = "1e-3"
    r = cli(*base, "-o", tmp_path / "bad" / "m.npz", *other, "--phase1-encoder",
            upd.parent / "m_encoder_phase1.safetensors")
    assert r.exit_code == 1 and "phase-1 settings differ (lr1)" in r.stderr


def test_finetune_solver_ls_sharded_on_two_jobs_equals_the_serial_map(cli, data, tmp_path):
    """--ls-shard-images 3 --jobs 2 (process pool) and the same map run serially write the same model, bit for bit;
    the shard size is recorded, the jobs are not; --jobs without a sharded update is a one-line error and nothing
    is written."""
    base = ["finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], *TINY, "--solver", "ls", "--ls-rounds", "1",
            "--ls-harmonics", "8", "--ls-pull", "0.01", "--ls-shard-images", "3"]
    arts = []
    for name, extra in (("pool", ["--jobs", "2"]), ("serial", [])):
        out = tmp_path / name / "m.npz"
        r = cli(*base, "-o", out, *extra)
        assert r.exit_code == 0, r.stderr
        arts.append(read_artifact(out, "reflectance-model"))
    for k in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis"):
        np.testing.assert_array_equal(arts[0][k], arts[1][k])
    params = arts[0].meta["params"]
    assert params["ls_shard_images"] == 3 and "jobs" not in params and "executor" not in params
    rounds = arts[0].meta["finetune"]["model_solve"]["rounds"]
    assert rounds[1]["solve_end"] < rounds[1]["solve_start"]
    init = read_artifact(data["init_path"], "reflectance-model")
    assert np.abs(np.asarray(arts[0]["vertex_albedo_mean"]) - np.asarray(init["vertex_albedo_mean"])).max() > 1e-4
    bad = tmp_path / "bad" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "-o", bad, *TINY, "--solver", "ls", "--jobs", "2")
    assert r.exit_code != 0 and "--ls-shard-images" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not bad.exists()


def test_solver_ls_trains_phase1_on_the_solved_model(cli, data, tmp_path):
    """--solver ls without --phase1-encoder: phase 1 trains the encoder on the solved model, so the run's phase-1
    encoder equals, tensor for tensor, that of a phase-1-only run on the model the update wrote, and differs from
    a phase-1-only run on the initial model."""
    from safetensors.numpy import load_file

    base = ["--light-model", data["light_path"], "--data", data["shards"][0], "--face-model", data["face_model"]]
    args = list(TINY)
    args[args.index("--model-lr") + 1] = "0"
    ls = tmp_path / "ls" / "m.npz"
    r = cli("finetune", "--model", data["init_path"], *base, "-o", ls, *args, "--solver", "ls", "--ls-rounds", "1",
            "--ls-harmonics", "8", "--ls-pull", "0.01")
    assert r.exit_code == 0, r.stderr
    p1_only = list(args)
    p1_only[p1_only.index("--epochs2") + 1] = "0"
    encs = {}
    for name, model in (("solved", ls), ("initial", data["init_path"])):
        out = tmp_path / name / "m.npz"
        assert cli("finetune", "--model", model, *base, "-o", out, *p1_only).exit_code == 0
        encs[name] = load_file(out.parent / "m_encoder.safetensors")
    mine = load_file(ls.parent / "m_encoder_phase1.safetensors")
    assert mine.keys() == encs["solved"].keys()
    assert all(np.array_equal(mine[k], encs["solved"][k]) for k in mine)
    assert not all(np.array_equal(mine[k], encs["initial"][k]) for k in mine)


def test_finetune_refuses_before_training_what_it_used_to_find_after(cli, data, tmp_path):
    """A face model of another mesh was found only after both phases (hours at the paper's settings) and after the
    failed run had written over the previous run's work folder; a model with σ ≤ 0 trained (its components could
    only give the mean); betas of 1 failed inside torch; a learning rate that blows the loss up wrote its encoder."""
    from _shards import cap_mesh

    out = tmp_path / "ft" / "m.npz"
    base = ("--light-model", data["light_path"], "--data", data["shards"][0], "-o", out, *TINY)
    V, tri, uv = cap_mesh(5)
    other = write_face_model(tmp_path / "other_fm.npz", V, tri, uv)
    r = cli("finetune", "--model", data["init_path"], "--face-model", other, *base)
    assert r.exit_code == 1 and "other_fm.npz: has 25 vertices" in r.stderr and "built on" in r.stderr, r.stderr
    assert not (tmp_path / "ft").exists()  # refused before training: no work folder either
    init = read_artifact(data["init_path"], "reflectance-model")
    zero = write_artifact(tmp_path / "zero_sigma.npz", "reflectance-model", {**init.arrays,
                          "sigma": np.zeros_like(init["sigma"])}, extra_meta={"stats": init.meta.get("stats")})
    for verb in (("finetune", "--model", zero, "--face-model", data["face_model"], *base),
                 ("reconstruct", "--refine", "--refine-from", "zero", "--model", zero, "--light-model",
                  data["light_path"], "--data", data["shards"][0], "-o", tmp_path / "rec.npz")):
        r = cli(*verb)
        assert r.exit_code == 1 and "zero_sigma.npz: reflectance-model 'sigma' must be > 0" in r.stderr, r.stderr
    r = cli("finetune", "--model", data["init_path"], "--face-model", data["face_model"], *base, "--betas", "0.9,1")
    assert r.exit_code == 1 and "--betas: 1 is not below 1" in r.stderr and "internal error" not in r.stderr
    r = cli("finetune", "--model", data["init_path"], "--face-model", data["face_model"], *base, "--lr1", "1e6")
    assert r.exit_code == 1 and "training diverged" in r.stderr and not out.exists(), r.stderr
    # shards made with a smaller mesh: their vertex ids all lie below the model's count; their face model tells
    import dataclasses

    from reflectmm_cli.finetune.train import check_inputs

    ss = load_shards(data["shards"])
    check_inputs(ss, data["truth"], data["light"])
    with pytest.raises(ReflectmmError, match="made with a face model of 25 vertices"):
        check_inputs(dataclasses.replace(ss, face_model={"resolved": str(other)}), data["truth"], data["light"])


def test_every_learning_rate_at_zero_is_said(cli, data, tmp_path):
    # like --epochs1 0 --epochs2 0, the run changes nothing: it used to say nothing
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", tmp_path / "m.npz", *TINY,
            "--lr1", "0", "--lr2", "0", "--model-lr", "0")
    assert r.exit_code == 0 and "every learning rate of the phases that run is 0" in r.stderr, r.stderr
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", tmp_path / "n.npz", *TINY)
    assert r.exit_code == 0 and "learning rate" not in r.stderr


def test_resume_refuses_a_checkpoint_of_another_model_solve(cli, data, tmp_path):
    # --resume with another --ls-pull continued an encoder trained on the model solved with the old pull, and wrote
    # it over the output beside the new model; --epochs2 0 said "the model is the initial one" of a solved model
    out = tmp_path / "ls" / "m.npz"
    base = ("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY, "--solver", "ls",
            "--ls-rounds", "1", "--ls-max-pixels", "200")
    r = cli(*base)
    assert r.exit_code == 0, r.stderr
    before = out.read_bytes()
    r = cli(*base, "--ls-pull", "5", "--resume")
    assert r.exit_code == 1 and "checkpoint was made with other settings (ls_pull)" in r.stderr, r.stderr
    assert out.read_bytes() == before
    r = cli(*base, "--epochs1", "0", "--epochs2", "0", "-o", tmp_path / "e0.npz")
    assert r.exit_code == 0 and "the model is the model given (solved by --solver ls" in r.stderr, r.stderr


def test_ls_harmonics_beyond_the_face_model_name_the_option(cli, data, tmp_path):
    # the error came from the harmonics library ("mesh harmonics: count must be in 1..N") and named neither
    out = tmp_path / "ft" / "m.npz"
    r = cli("-q", "finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY, "--solver", "ls",
            "--ls-harmonics", "100000")
    V = len(read_artifact(data["face_model"], "face-model")["mean_shape"])
    line = r.stderr.strip()
    assert r.exit_code == 1 and len(line.splitlines()) == 1, r.stderr
    assert f"--ls-harmonics 100000: the face model {data['face_model']} has {V} vertices" in line, line
    assert f"at most {V - 2} mesh harmonics" in line and not (tmp_path / "ft").exists()


def test_ls_options_given_to_the_sgd_solver_are_said_to_be_unused(cli, data, tmp_path, reflectmm_log):
    base = ("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], *TINY, "--epochs1", "0", "--epochs2", "1")
    r = cli(*base, "-o", tmp_path / "a.npz", "--ls-rounds", "7", "--ls-harmonics", "100000", "--ls-rounds", "7")
    assert r.exit_code == 0, r.stderr
    said = [m for m in reflectmm_log if "not used by --solver sgd" in m]
    assert said == ["finetune: warning: --ls-rounds 7, --ls-harmonics 100000: option(s) of --solver ls, not used "
                    "by --solver sgd"], reflectmm_log
    reflectmm_log.clear()
    r = cli(*base, "-o", tmp_path / "b.npz", "--ls-harmonics", "0")  # the off value is not a setting
    assert r.exit_code == 0 and not [m for m in reflectmm_log if "not used" in m], reflectmm_log


def test_ls_update_bases_beyond_the_model_is_capped_with_a_warning(cli, data, tmp_path, reflectmm_log):
    r = cli("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", tmp_path / "m.npz", *TINY, "--solver", "ls",
            "--ls-rounds", "1", "--ls-max-pixels", "200", "--ls-update-bases", "5000")
    assert r.exit_code == 0, r.stderr
    assert ("finetune: warning: --ls-update-bases 5000 but the reflectance model has 3 components; using 3"
            in reflectmm_log), reflectmm_log


def test_a_robust_threshold_that_leaves_no_pixel_out_is_said(cli, data, tmp_path, reflectmm_log):
    # k so small that every pixel of every image is an outlier: each image is kept whole, the option does nothing
    base = ("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], *TINY, "--solver", "ls", "--ls-rounds", "1",
            "--ls-max-pixels", "200")
    r = cli(*base, "-o", tmp_path / "a.npz", "--ls-robust", "1e-9")
    assert r.exit_code == 0, r.stderr
    said = [m for m in reflectmm_log if "--ls-robust" in m]
    assert said == ["model solve: --ls-robust 1e-09 left no pixel out in any round, so it had no effect (an image "
                    "whose pixels all lie beyond it is kept whole)"], reflectmm_log
    reflectmm_log.clear()
    r = cli(*base, "-o", tmp_path / "b.npz", "--ls-robust", "2")
    assert r.exit_code == 0 and not [m for m in reflectmm_log if "--ls-robust" in m], reflectmm_log


def test_resume_names_a_switched_solver_and_refuses_before_the_model_solve(cli, data, tmp_path):
    # the refusal named model_lr (which --solver ls sets to 0), not the solver; another --lr2 was refused only after
    # the whole least-squares solve had run
    out = tmp_path / "ls" / "m.npz"
    base = ("finetune", "--model", data["init_path"], "--light-model", data["light_path"], "--data",
            data["shards"][0], "--face-model", data["face_model"], "-o", out, *TINY, "--ls-rounds", "1",
            "--ls-max-pixels", "200")
    r = cli(*base, "--solver", "ls")
    assert r.exit_code == 0, r.stderr
    before = out.read_bytes()
    r = cli(*base, "--solver", "sgd", "--resume")
    assert r.exit_code == 1 and "checkpoint was made with other settings (solver);" in r.stderr, r.stderr
    r = cli(*base, "--solver", "ls", "--lr2", "1e-3", "--resume")
    assert r.exit_code == 1 and "checkpoint was made with other settings (lr2);" in r.stderr, r.stderr
    assert "model solve:" not in r.stderr and out.read_bytes() == before, r.stderr


def test_a_model_without_its_per_vertex_part_is_refused_naming_the_file(cli, data, tmp_path):
    init = read_artifact(data["init_path"], "reflectance-model")
    arrays = {k: v for k, v in init.arrays.items() if not k.startswith("vertex_")}
    uv_only = write_artifact(tmp_path / "uv_only.npz", "reflectance-model", arrays,
                             extra_meta={"stats": init.meta.get("stats")})
    r = cli("finetune", "--model", uv_only, "--light-model", data["light_path"], "--data", data["shards"][0], "-o",
            tmp_path / "ft" / "m.npz", *TINY)
    assert r.exit_code == 1 and "uv_only.npz" in r.stderr and "no per-vertex part" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = cli("reconstruct", "--refine", "--refine-from", "zero", "--model", uv_only, "--light-model",
            data["light_path"], "--data", data["shards"][0], "-o", tmp_path / "rec.npz")
    assert r.exit_code == 1 and "uv_only.npz" in r.stderr and not (tmp_path / "rec.npz").exists()

"""evaluate expressive (issue 21 §4) end to end on a tiny synth wild set: the oracle built from the training
identities, a model that contains the held-out identities' truth (residual ~0) and a mean-only model (residual =
the relative distance to the scaled mean, computed here independently), the gap-closed ratio, the recipe role."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.model.pca import MODEL_KIND, ReflectanceModel, model_arrays


@pytest.fixture(scope="module")
def wild(tmp_path_factory):
    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.synth.wild import WildConfig, synth_wild

    out = tmp_path_factory.mktemp("expr") / "synth-wild"
    fm = procedural_face_model(grid=(31, 25), n_shape=4, n_exp=2, seed=2)
    cfg = WildConfig(count=12, size=48, images_per_identity=2, envmaps=1, envmap_width=32, prefilter_width=16,
                     uv_size=32, occluder_fraction=0.0, seed=1, split=(0.6, 0.2, 0.2))
    synth_wild(out, cfg, face_model=fm)
    return out


def _truth(folder):
    from reflectmm_cli.stages.evaluate_expressive import load_wild_truth

    return load_wild_truth(folder)


def _model(path, mean_a, basis_a, mean_w, basis_w, sigma):
    """A reflectance-model artifact whose per-vertex part is given (1×1 UV maps: only the vertex part is used)."""
    M, K = basis_a.shape[0], mean_w.shape[1]
    z = np.zeros
    m = ReflectanceModel(albedo_mean=z((3, 1, 1), np.float32), albedo_basis=z((M, 3, 1, 1), np.float32),
                         weights_mean=z((K, 1, 1), np.float32), weights_basis=z((M, K, 1, 1), np.float32),
                         sigma=np.asarray(sigma, np.float32), explained_variance=np.asarray(sigma, np.float32) ** 2,
                         explained_variance_ratio=np.full(M, 1.0 / max(M, 1), np.float32),
                         exponents=np.array([1.0, 8.0, 64.0], np.float32), mask=np.ones((1, 1), bool),
                         train_coeffs=z((2, M), np.float32), vertex_albedo_mean=mean_a.astype(np.float32),
                         vertex_albedo_basis=basis_a.astype(np.float32), vertex_weights_mean=mean_w.astype(np.float32),
                         vertex_weights_basis=basis_w.astype(np.float32))
    write_artifact(path, MODEL_KIND, model_arrays(m))
    return path


def test_evaluate_expressive_cli(wild, cli, tmp_path):
    from reflectmm_cli.evaluation.expressive import oracle_model

    tr = _truth(wild)
    assert tr["train"] and tr["heldout"]
    ids = tr["train"] + tr["heldout"]
    everyone = oracle_model(np.stack([tr["albedo"][i] for i in ids]), np.stack([tr["weights"][i] for i in ids]),
                            [1, 8, 64], len(ids) - 1)
    full = _model(tmp_path / "full.npz", everyone["vertex_albedo_mean"], everyone["vertex_albedo_basis"],
                  everyone["vertex_weights_mean"], everyone["vertex_weights_basis"], everyone["sigma"])
    mean = _model(tmp_path / "mean.npz", everyone["vertex_albedo_mean"], everyone["vertex_albedo_basis"][:1] * 0,
                  everyone["vertex_weights_mean"], everyone["vertex_weights_basis"][:1] * 0, everyone["sigma"][:1])
    out = tmp_path / "ex.npz"
    r = cli("evaluate", "expressive", "--truth", wild, "--method", "initial", mean, "-", "--method", "finetuned",
            full, "-", "--prior", "0", "-w", tmp_path, "-o", out)
    assert r.exit_code == 0, r.stderr
    art = read_artifact(out, "evaluation")
    means = art.meta["means"]
    assert means["finetuned"]["albedo"] < 1e-3  # the held-out truth is in this model's span
    # the mean-only model: the best scale of the mean, by hand
    res = []
    for i in tr["heldout"]:
        r_ = tr["skin"][i]
        t = tr["albedo"][i][r_].reshape(-1).astype(np.float64)
        mu = everyone["vertex_albedo_mean"][r_].reshape(-1).astype(np.float64)
        s = (mu @ t) / (mu @ mu)
        res.append(np.linalg.norm(s * mu - t) / np.linalg.norm(t))
    assert means["initial"]["albedo"] == pytest.approx(np.mean(res), rel=1e-4)
    gap = art.meta["gap_closed"]
    o = means["oracle"]["albedo"]
    assert gap["albedo"] == pytest.approx((means["initial"]["albedo"] - means["finetuned"]["albedo"])
                                          / (means["initial"]["albedo"] - o))
    assert "| oracle |" in out.with_suffix(".md").read_text()


def test_evaluate_expressive_bad_inputs(wild, cli, tmp_path):
    r = cli("evaluate", "expressive", "--truth", tmp_path, "--method", "a", tmp_path / "none.npz", "-", "-w",
            tmp_path, "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.npz").exists()


def test_build_baseline_oracle(wild, cli, tmp_path):
    """``build-baseline --kind oracle``: the model of evaluate-expressive's oracle as a reflectance-model artifact
    (per-vertex part equal, array for array), of the size of ``--like``; then evaluate expressive finds it at the
    oracle's residual. Bad inputs are one-line errors that write nothing."""
    from reflectmm_cli.evaluation.expressive import oracle_model

    tr = _truth(wild)
    fm = wild / "face_model.npz"
    assert fm.is_file()
    full = oracle_model(np.stack([tr["albedo"][i] for i in tr["train"]]),
                        np.stack([tr["weights"][i] for i in tr["train"]]), [1, 8, 64], len(tr["train"]) - 1)
    M = len(tr["train"]) - 2  # a smaller model than the population allows: the oracle takes its size
    like = _model(tmp_path / "like.npz", full["vertex_albedo_mean"], full["vertex_albedo_basis"][:M],
                  full["vertex_weights_mean"], full["vertex_weights_basis"][:M], full["sigma"][:M])
    out = tmp_path / "oracle.npz"
    r = cli("build-baseline", "--kind", "oracle", "--truth", wild, "--face-model", fm, "--like", like, "-w",
            tmp_path, "-o", out)
    assert r.exit_code == 0, r.stderr
    art = read_artifact(out, MODEL_KIND)
    want = oracle_model(np.stack([tr["albedo"][i] for i in tr["train"]]),
                        np.stack([tr["weights"][i] for i in tr["train"]]), [1, 8, 64], M)
    for k in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis", "sigma"):
        np.testing.assert_array_equal(art[k], want[k], err_msg=k)
    assert art["albedo_mean"].shape[-1] == 1  # the UV size of --like (1×1 maps here)
    assert art.meta["baseline"] == "oracle" and "synth wild" in art.meta["data"]
    ex = tmp_path / "ex.npz"
    r = cli("evaluate", "expressive", "--truth", wild, "--method", "initial", like, "-", "--method", "finetuned",
            out, "-", "-w", tmp_path, "-o", ex)
    assert r.exit_code == 0, r.stderr
    means = read_artifact(ex, "evaluation").meta["means"]
    assert means["finetuned"]["albedo"] == pytest.approx(means["oracle"]["albedo"], rel=1e-6)

    bad = tmp_path / "bad.npz"
    for args, msg in (((("--truth", tmp_path / "like.npz")), "synth wild folder"),
                      ((("--truth", wild, "--kind", "albedomm")), "--like applies to kind oracle only"),
                      ((("--truth", wild, "--ids", "a,b")), "--ids does not apply")):
        kind = [] if "--kind" in args else ["--kind", "oracle"]
        r = cli("build-baseline", *kind, *args, "--face-model", fm, "--like", like, "-w", tmp_path, "-o", bad)
        assert r.exit_code != 0 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not bad.exists()
    other = _model(tmp_path / "other.npz", full["vertex_albedo_mean"], full["vertex_albedo_basis"][:M],
                   full["vertex_weights_mean"], full["vertex_weights_basis"][:M], full["sigma"][:M])
    a = read_artifact(other, MODEL_KIND)
    from reflectmm_cli.artifacts import write_artifact
    write_artifact(other, MODEL_KIND, dict(a.arrays, exponents=np.array([1.0, 8.0, 32.0], np.float32)))
    r = cli("build-baseline", "--kind", "oracle", "--truth", wild, "--face-model", fm, "--like", other, "-w",
            tmp_path, "-o", bad)
    assert r.exit_code != 0 and "lobe exponents" in r.stderr and not bad.exists()
    fewer = _model(tmp_path / "fewer.npz", full["vertex_albedo_mean"][:-1], full["vertex_albedo_basis"][:M, :-1],
                   full["vertex_weights_mean"][:-1], full["vertex_weights_basis"][:M, :-1], full["sigma"][:M])
    r = cli("build-baseline", "--kind", "oracle", "--truth", wild, "--face-model", fm, "--like", fewer, "-w",
            tmp_path, "-o", bad)
    assert r.exit_code != 0 and "another face model?" in r.stderr and not bad.exists()


def test_build_baseline_oracle_finds_the_synth_wild_folders_face_model(wild, cli, tmp_path):
    # without --face-model it looked in the workspace only ("none found in <ws>"), although the synth wild folder
    # given as --truth holds its face_model.npz, as prepare-wild finds it
    tr = _truth(wild)
    args = ("build-baseline", "--kind", "oracle", "--truth", wild, "--components", str(len(tr["train"]) - 1),
            "--uv-size", "8", "--no-preview", "-w", tmp_path)
    r = cli(*args, "-o", tmp_path / "found.npz")
    assert r.exit_code == 0, r.stderr
    r = cli(*args, "--face-model", wild / "face_model.npz", "-o", tmp_path / "given.npz")
    assert r.exit_code == 0, r.stderr
    found, given = read_artifact(tmp_path / "found.npz", MODEL_KIND), read_artifact(tmp_path / "given.npz", MODEL_KIND)
    assert found.meta["face_model"] == given.meta["face_model"]
    for k in given.arrays:
        np.testing.assert_array_equal(found[k], given[k], err_msg=k)
    empty = tmp_path / "empty"
    empty.mkdir()
    r = cli("build-baseline", "--truth", empty, "-w", empty, "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and r.stderr.strip() == (
        f"reflectmm: error: build-baseline: no --face-model given and none found (looked for face_model.npz in the "
        f"--truth folder {empty}, and for face_model.npz, synth/face_model.npz, synth-multipie/face_model.npz in "
        f"{empty}); pass --face-model"), r.stderr

"""Per-image refinement (finetune/refine.py): the closed-form transport against the G-buffer shader, the exact
gradient against central differences, noise-free recovery of known coefficients, monotone objective, bad input."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from _shards import make_dataset
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune import refine as R
from reflectmm_cli.finetune.render import ModelParams, batch_gbuffer, lighting, shade_gbuffer
from reflectmm_cli.finetune.shards import load_shards


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = make_dataset(tmp_path_factory.mktemp("ft_refine"), n_images=4, size=24, mesh_n=9)
    ss = load_shards(d["shards"])
    gb = batch_gbuffer(ss.batch([0, 1, 2, 3]), dtype=torch.float64)
    p = ModelParams(d["truth"], dtype=torch.float64)
    beta, gamma, z = (torch.tensor(d[k]) for k in ("betas", "gammas", "zs"))
    dd, s, _, _ = shade_gbuffer(p, beta, lighting(d["light"], gamma, z), gb)
    gb.target = (dd + s).detach()  # noise-free target from the shader under test's reference path
    gb.skin[:] = True
    return dict(d=d, gb=gb, p=p, beta=beta, gamma=gamma, z=z)


def _img(sc, b=0):
    lt = R._light_tensors(sc["d"]["light"], sc["gamma"].shape[1], torch.float64, "cpu")
    return lt, R._image(sc["p"], lt, sc["gb"], b, sc["beta"].shape[1], sc["d"]["light"].order, torch.float64, 0)


def test_transport_reproduces_the_gbuffer_shader(scene):
    lt, img = _img(scene, 1)
    st_ = R._State(scene["beta"][1], scene["gamma"][1], scene["z"][1])
    I = R._forward(img, lt, st_)[0]
    np.testing.assert_allclose(I.numpy(), img.target.numpy(), atol=1e-12)


@pytest.mark.parametrize("loss", ["l2", "l1"])
def test_gradient_matches_central_differences(scene, loss):
    lt, img = _img(scene, 2)
    cfg = R.RefineConfig(w_coef=0.01, w_light=0.1, loss="l2")
    st_ = R._State(scene["beta"][2] * 0.5, scene["gamma"][2] * 0.3, scene["z"][2] * 1.2)
    irls = R._irls_weights(img, lt, st_, R.RefineConfig(loss=loss))
    H, g, _ = R._normal_equations(img, lt, st_, cfg, irls)

    def energy(s):  # the weighted least-squares surrogate whose gradient g is (½∇E)
        return R._energy(img, lt, s, cfg, irls)

    v = st_.vector()
    fd = []
    for i in range(v.numel()):
        dv = torch.zeros_like(v)
        dv[i] = 1e-6
        fd.append((energy(st_.moved(dv)) - energy(st_.moved(-dv))) / 2e-6)
    np.testing.assert_allclose(np.array(fd), 2 * g.numpy(), atol=1e-8 * max(1.0, np.abs(fd).max()))
    # the Gauss–Newton matrix is the exact Hessian of the surrogate up to the (bilinear) second-order terms:
    # it is symmetric positive semi-definite
    np.testing.assert_allclose(H.numpy(), H.numpy().T, atol=1e-12)
    assert np.linalg.eigvalsh(H.numpy()).min() > -1e-12


def test_recovers_known_coefficients_noise_free(scene):
    gb, p, d = scene["gb"], scene["p"], scene["d"]
    z0 = R.initial_z(p, d["light"], gb, torch.zeros_like(scene["gamma"]))
    res = R.refine_batch(p, d["light"], gb, torch.zeros_like(scene["beta"]), torch.zeros_like(scene["gamma"]), z0,
                         R.RefineConfig(w_coef=0.0, w_light=0.0, iterations=40))
    np.testing.assert_allclose(res.beta.numpy(), scene["beta"].numpy(), atol=1e-6)
    np.testing.assert_allclose(res.gamma.numpy(), scene["gamma"].numpy(), atol=1e-6)
    np.testing.assert_allclose(res.z.numpy(), scene["z"].numpy(), atol=1e-6)
    assert (res.objective_end < 1e-20).all()


def test_initial_z_is_the_least_squares_scale(scene):
    gb, p, d = scene["gb"], scene["p"], scene["d"]
    gamma = torch.zeros_like(scene["gamma"])
    z0 = R.initial_z(p, d["light"], gb, gamma)
    lt, img = _img(scene, 0)
    for c in range(3):  # the energy (data term only) is minimal along z_c at z0: a dense 1-D scan
        cfg = R.RefineConfig(w_coef=0, w_light=0)
        base = R._State(torch.zeros_like(scene["beta"][0]), gamma[0], z0[0].clone())
        e0 = R._energy(img, lt, base, cfg)
        for f in (0.98, 1.02):
            zz = z0[0].clone()
            zz[c] *= f
            assert R._energy(img, lt, R._State(base.beta, base.gamma, zz), cfg) > e0


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2 ** 16), noise=st.floats(0.0, 0.05), loss=st.sampled_from(["l2", "l1"]))
def test_objective_never_increases(scene, seed, noise, loss):
    """Noisy targets, random starts: every kept step lowers E_b and the result is finite."""
    gb, p, d = scene["gb"], scene["p"], scene["d"]
    rng = np.random.default_rng(seed)
    gb2 = batch_gbuffer({"offsets": gb.offsets, "pix_yx": gb.pix_yx.numpy(), "vert_ids": gb.vert_ids.numpy(),
                         "bary": gb.bary.numpy(), "normal": gb.normal.numpy(), "view": gb.view.numpy(),
                         "skin": gb.skin.numpy(), "size": gb.size,
                         "target": gb.target.numpy() + noise * rng.standard_normal(gb.target.shape)},
                        dtype=torch.float64)
    b0 = torch.tensor(rng.normal(0, 1, scene["beta"].shape))
    g0 = torch.tensor(rng.normal(0, 1, scene["gamma"].shape))
    z0 = torch.tensor(rng.uniform(0.3, 2.0, (4, 3)))
    cfg = R.RefineConfig(iterations=6, loss=loss)
    res = R.refine_batch(p, d["light"], gb2, b0, g0, z0, cfg)
    assert np.isfinite(res.objective_end).all()
    assert (res.objective_end <= res.objective_start + 1e-15).all()


def test_non_finite_start_names_the_image(scene):
    gb, p, d = scene["gb"], scene["p"], scene["d"]
    z = scene["z"].clone()
    z[2, 0] = math.nan
    with pytest.raises(ReflectmmError, match="image c.*not finite"):
        R.refine_batch(p, d["light"], gb, scene["beta"], scene["gamma"], z, names=["a", "b", "c", "d"])


def test_config_checks():
    with pytest.raises(ReflectmmError, match="loss"):
        R.RefineConfig(loss="huber")
    with pytest.raises(ReflectmmError, match="w_coef"):
        R.RefineConfig(w_coef=-1)


def test_reconstruct_refine_from_zero_cli(cli, tmp_path):
    """``reconstruct --refine --refine-from zero`` needs no encoder and recovers the shard's true layers (images
    stored as 8-bit codes: agreement to the quantisation); the objective trace is written."""
    from _shards import make_dataset as mk
    from reflectmm_cli.artifacts import read_artifact

    d = mk(tmp_path / "data", n_images=3, size=32, seed=5)
    rec = tmp_path / "rec.npz"
    r = cli("reconstruct", "--refine", "--refine-from", "zero", "--refine-w-coef", "0", "--refine-w-light", "0",
            "--refine-iterations", "30", "--model", d["truth_path"], "--light-model", d["light_path"], "--data",
            d["shards"][0], "-o", rec, "-w", tmp_path / "ws")
    assert r.exit_code == 0, r.output + r.stderr
    a = read_artifact(rec, "reconstruction")
    ss = load_shards(d["shards"])
    assert a["refine_objective"].shape == (3, 2)
    assert (a["refine_objective"][:, 1] < 0.05 * a["refine_objective"][:, 0]).all()
    np.testing.assert_allclose(a["beta"], d["betas"], atol=0.05)
    np.testing.assert_allclose(a["diffuse"].astype(np.float32), np.asarray(ss.truth["truth_diffuse"][:3], np.float32),
                               atol=0.01)

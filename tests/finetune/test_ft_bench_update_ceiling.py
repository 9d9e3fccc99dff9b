"""benchmarks/bench_update_ceiling.py's pieces (docs/benchmarks.md, "What limits the model update"): the true
coefficients are the projection of evaluate expressive, the matched images are the numpy SH shader's rendering of
the truth, the identity-group refinement ends at a stationary point of the summed objective (finite differences)
and holds a fixed β, and the form ceiling recovers a change the training identities were made with."""

import numpy as np
import pytest
import torch

from _benchmarks import load_benchmark
from _shards import make_dataset
from reflectmm_cli.evaluation.expressive import projection_residuals
from reflectmm_cli.finetune import refine as RF
from reflectmm_cli.finetune.render import ModelParams, batch_gbuffer
from reflectmm_cli.finetune.shards import load_shards
from reflectmm_cli.model.light import light_from_coeffs
from reflectmm_cli.shading import shade_env


def _bench():
    return load_benchmark("bench_update_ceiling")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = make_dataset(tmp_path_factory.mktemp("bench_ceiling"), n_images=4, size=16, mesh_n=5, seed=4)
    ss = load_shards(d["shards"])
    gb = batch_gbuffer(ss.batch([0, 1, 2, 3]), "cpu", torch.float64)
    return d, ss, gb


def _model_arrays(m):
    return (np.asarray(m.vertex_albedo_mean, np.float64), np.asarray(m.vertex_albedo_basis, np.float64),
            np.asarray(m.sigma, np.float64))


def test_true_coefficients_recover_a_scaled_model_face_and_give_the_expressive_residual(data):
    d = data[0]
    mean, B, sg = _model_arrays(d["truth"])
    beta = np.array([0.7, -1.2, 0.4])
    face = 1.3 * (mean + np.einsum("m,mvc->vc", beta * sg, B))
    skin = np.ones(mean.shape[0], bool)
    s, b = _bench().true_coefficients(mean, B, sg, face, skin, prior=0.0)
    assert s == pytest.approx(1.3, rel=1e-9)
    np.testing.assert_allclose(b, beta, rtol=0, atol=1e-8)
    # off the span: the projection's residual is evaluate expressive's (same prior)
    rng = np.random.default_rng(0)
    off = face + 0.05 * rng.normal(size=face.shape)
    s, b = _bench().true_coefficients(mean, B, sg, off, skin)
    fit = s * (mean + np.einsum("m,mvc->vc", b * sg, B))
    rel = np.linalg.norm(fit - off) / np.linalg.norm(off)
    assert rel == pytest.approx(projection_residuals(mean, B, sg, off[None], skin)[0], rel=1e-9)


def test_matched_targets_are_the_sh_shader_of_the_truth(data):
    d, ss, gb = data
    params = ModelParams(d["truth"], "cpu", dtype=torch.float64)
    rng = np.random.default_rng(1)
    V = d["V"].shape[0]
    K = params.exponents.shape[0]
    albedo = {0: rng.uniform(0.2, 0.8, (V, 3)), 1: rng.uniform(0.2, 0.8, (V, 3))}
    weights = {0: rng.uniform(0.0, 0.3, (V, K)), 1: rng.uniform(0.0, 0.3, (V, K))}
    gamma = torch.as_tensor(rng.normal(0, 1, (4, d["light"].n_components)))
    z = torch.as_tensor(rng.uniform(1.5, 2.5, (4, 3)))
    ident = np.array([0, 0, 1, 1])
    out = _bench().matched_batches(params, d["light"], [gb], gamma, z, ident, albedo, weights)[0]
    exps = np.asarray(d["truth"].exponents, np.float64)
    for b in range(4):
        s0, s1 = int(gb.offsets[b]), int(gb.offsets[b + 1])
        sel = (torch.nonzero(gb.skin[s0:s1]).reshape(-1) + s0).numpy()
        bw = gb.bary[sel].numpy()[..., None]
        vid = gb.vert_ids[sel].numpy()
        c = (albedo[ident[b]][vid] * bw).sum(1)
        w = (weights[ident[b]][vid] * bw).sum(1)
        Kl = light_from_coeffs(d["light"], gamma[b].numpy(), z[b].numpy())
        dd, sp = shade_env(c, w, exps, gb.normal[sel].numpy(), gb.view[sel].numpy(), Kl)
        np.testing.assert_allclose(out.target[sel].numpy(), dd + sp, rtol=1e-6, atol=1e-9)
        rest = np.setdiff1d(np.arange(s0, s1), sel)  # pixels outside the skin keep the image's target
        np.testing.assert_array_equal(out.target[rest].numpy(), gb.target[rest].numpy())


def _summed_energy(params, light, gb, groups_beta, gamma, z, groups, cfg, M):
    lt = RF._light_tensors(light, gamma.shape[1], torch.float64, "cpu")
    e = 0.0
    for gi, ks in enumerate(groups):
        for k in ks:
            img = RF._image(params, lt, gb, k, M, light.order, torch.float64, cfg.max_pixels)
            e += RF._energy(img, lt, RF._State(groups_beta[gi], gamma[k], z[k]), cfg)
    return e


def test_identity_groups_end_at_a_stationary_point_and_hold_a_fixed_beta(data):
    d, ss, gb = data
    params = ModelParams(d["truth"], "cpu", dtype=torch.float64)
    light, M = d["light"], params.n_components
    cfg = RF.RefineConfig(iterations=60, tol=1e-14)
    beta0 = torch.zeros((4, M), dtype=torch.float64)
    gamma0 = torch.zeros((4, light.n_components), dtype=torch.float64)
    z0 = RF.initial_z(params, light, gb, gamma0).to(torch.float64)
    groups = [np.array([0, 1]), np.array([2, 3])]
    b, g, z = _bench().refine_identity_groups(params, light, [gb], beta0, gamma0, z0, groups, cfg, 4)
    for ks in groups:
        np.testing.assert_array_equal(b[ks[0]].numpy(), b[ks[1]].numpy())
    # the gradient of the summed objective over (β of the group, γ and z of its images), by central differences
    for gi, ks in enumerate(groups):
        x0 = torch.cat([b[ks[0]]] + [torch.cat([g[k], z[k]]) for k in ks])

        def f(x):
            gg, zz = g.clone(), z.clone()
            for j, k in enumerate(ks):
                o = M + j * (g.shape[1] + 3)
                gg[k], zz[k] = x[o:o + g.shape[1]], x[o + g.shape[1]:o + g.shape[1] + 3]
            return _summed_energy(params, light, gb, [x[:M]], gg, zz, [ks], cfg, M)

        h = 1e-6
        grad = np.array([(f(x0 + h * e) - f(x0 - h * e)) / (2 * h) for e in torch.eye(len(x0), dtype=torch.float64)])
        start = torch.cat([beta0[0]] + [torch.cat([gamma0[k], z0[k]]) for k in ks])
        grad0 = np.array([(f(start + h * e) - f(start - h * e)) / (2 * h)
                          for e in torch.eye(len(x0), dtype=torch.float64)])
        assert np.linalg.norm(grad) < 1e-3 * np.linalg.norm(grad0)
        assert f(x0) < f(start)
    fixed = [np.array([0.3, -0.2, 0.1]), np.array([-0.5, 0.4, 0.0])]
    b2, g2, z2 = _bench().refine_identity_groups(params, light, [gb], beta0, gamma0, z0, groups, cfg, 4,
                                                 fixed=fixed)
    for gi, ks in enumerate(groups):
        for k in ks:
            np.testing.assert_array_equal(b2[k].numpy(), fixed[gi])
    assert not torch.equal(g2, gamma0)


def test_form_ceiling_recovers_the_change_the_identities_were_made_with(data):
    d = data[0]
    mean, B, sg = _model_arrays(d["truth"])
    M, V = B.shape[:2]
    rng = np.random.default_rng(3)
    # a change of the mean and bases orthogonal to the initial span, so that the projection keeps each identity's
    # scale and coefficients
    A = np.concatenate([mean.reshape(1, -1), (B * sg[:, None, None]).reshape(M, -1)]).T
    Qa, _ = np.linalg.qr(A)
    dU = rng.normal(0, 0.05, (M + 1, V * 3))
    dU = (dU - (dU @ Qa) @ Qa.T).reshape(M + 1, V, 3)

    def faces(n, seed):
        r = np.random.default_rng(seed)
        out = []
        for _ in range(n):
            beta, s = r.normal(size=M), r.uniform(0.5, 1.5)
            c = np.r_[1.0, beta]
            out.append(s * (mean + np.einsum("m,mvc->vc", beta * sg, B) + np.einsum("m,mvc->vc", c, dU)))
        return np.array(out)

    train, held = faces(12, 4), faces(3, 5)
    skin = [np.ones(V, bool)] * 12
    before = projection_residuals(mean, B, sg, held, np.ones(V, bool), prior=1e-3).mean()
    rows = _bench().form_ceiling(mean, B, sg, list(train), skin, held, np.ones((3, V), bool), [0], None)
    assert before > 0.05
    # what is left is the bias of the projections' prior (1e-3), in the coefficients and in the measure
    assert np.mean(rows[0]["albedo_residuals"]) < 0.05 * before

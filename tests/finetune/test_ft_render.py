"""The G-buffer shader: agreement with the numpy renderer and finite-difference gradients."""
import numpy as np
import pytest
import torch

from _shards import make_dataset
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.render import ModelParams, batch_gbuffer, lighting, scatter_pixels, shade_gbuffer
from reflectmm_cli.finetune.shards import load_shards


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("ft_render"), n_images=4, size=24, mesh_n=9)


def test_matches_independent_numpy_render(data):
    ss = load_shards(data["shards"])
    b = ss.batch([0, 2])
    gb = batch_gbuffer(b, dtype=torch.float64)
    p = ModelParams(data["truth"], dtype=torch.float64)
    sh = lighting(data["light"], torch.tensor(data["gammas"][[0, 2]]), torch.tensor(data["zs"][[0, 2]]))
    d, s, _, _ = shade_gbuffer(p, torch.tensor(data["betas"][[0, 2]]), sh, gb)
    t = ss.truth["truth_diffuse"][[0, 2]].astype(np.float64)
    ts = ss.truth["truth_specular"][[0, 2]].astype(np.float64)
    yx = b["pix_yx"]
    img = np.repeat([0, 1], np.diff(b["offsets"]))
    # the shard stores normals/views as float16 and the layers as float16: agreement to ~1e-3
    np.testing.assert_allclose(d.detach().numpy(), t[img, yx[:, 0], yx[:, 1]], atol=2e-3)
    np.testing.assert_allclose(s.detach().numpy(), ts[img, yx[:, 0], yx[:, 1]], atol=2e-3)
    full = scatter_pixels(d + s, gb)
    assert full.shape == (2, 24, 24, 3)
    assert float(full[0][~torch.as_tensor(ss.face_mask[0])].abs().max()) == 0.0


@pytest.mark.slow
def test_gradcheck_beta_gamma_z_model(data):
    """torch.autograd.gradcheck (float64 central differences) w.r.t. β, γ, z, model means and bases."""
    ss = load_shards(data["shards"])
    b = ss.batch([1, 3])
    # a few pixels keep the check fast; every input still reaches the output
    keep = np.r_[0:6, b["offsets"][1]:b["offsets"][1] + 6]
    sub = {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == (b["offsets"][-1],) else v)
           for k, v in b.items()}
    sub["offsets"] = np.array([0, 6, 12])
    gb = batch_gbuffer(sub, dtype=torch.float64)
    p = ModelParams(data["truth"], dtype=torch.float64, trainable="all")
    used = torch.unique(gb.vert_ids.reshape(-1))
    beta = torch.tensor(data["betas"][[1, 3]], requires_grad=True)
    gamma = torch.tensor(data["gammas"][[1, 3]], requires_grad=True)
    z = torch.tensor(data["zs"][[1, 3]], requires_grad=True)
    am0, ab0 = p.albedo_mean.detach()[used], p.albedo_basis.detach()[:, used]
    wm0, wb0 = p.weights_mean.detach()[used], p.weights_basis.detach()[:, used]
    leaves = [x.clone().requires_grad_(True) for x in (am0, ab0, wm0, wb0)]

    def f(beta, gamma, z, am, ab, wm, wb):
        p.albedo_mean = p.albedo_mean.detach().index_put((used,), am)
        p.albedo_basis = _put(p.albedo_basis, used, ab)
        p.weights_mean = p.weights_mean.detach().index_put((used,), wm)
        p.weights_basis = _put(p.weights_basis, used, wb)
        sh = lighting(data["light"], gamma, z)
        d, s, _, _ = shade_gbuffer(p, beta, sh, gb)
        return d + 2.0 * s

    assert torch.autograd.gradcheck(f, (beta, gamma, z, *leaves), eps=1e-6, atol=1e-6, rtol=1e-4)


def _put(base, idx, val):
    out = base.detach().clone()
    out = out.index_put((torch.arange(out.shape[0])[:, None], idx[None, :]), val)
    return out


def test_vertex_count_mismatch_is_one_line_error(data, tmp_path):
    from _shards import truth_model, cap_mesh

    V, _, _ = cap_mesh(5)
    small = truth_model(V)
    ss = load_shards(data["shards"])
    gb = batch_gbuffer(ss.batch([0]))
    p = ModelParams(small)
    sh = lighting(data["light"], torch.zeros(1, 2), torch.ones(1, 3))
    with pytest.raises(ReflectmmError, match="vertices"):
        shade_gbuffer(p, torch.zeros(1, 3), sh, gb)

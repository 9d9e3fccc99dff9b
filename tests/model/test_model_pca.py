"""PCA reflectance model: orthonormality, exact reconstruction, specular transfer, σ, caps, vertex sampling."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.model import (
    add_vertex_model,
    fit_reflectance_pca,
    model_arrays,
    model_from_arrays,
    project_maps,
    sample_model,
    sample_uv_bilinear,
)


def _data(n=6, S=8, K=3, seed=0, mask=None):
    rng = np.random.default_rng(seed)
    A = [rng.uniform(0.1, 0.9, (3, S, S)) for _ in range(n)]
    W = [rng.uniform(0.0, 0.5, (K, S, S)) for _ in range(n)]
    if mask is not None:
        for a, w in zip(A, W):
            a[:, ~mask] = 0
            w[:, ~mask] = 0
    return A, W


def test_diffuse_bases_orthonormal_and_sigma_is_sample_std():
    A, W = _data(n=7)
    m = fit_reflectance_pca(A, W, (1, 8, 64), components=80)
    assert m.n_components == 6
    B = m.albedo_basis.reshape(m.n_components, -1).astype(np.float64)
    np.testing.assert_allclose(B @ B.T, np.eye(6), atol=1e-5)
    # σ_k = sample std (ddof=1) of the projections of the training data on b_k (independent computation)
    X = np.stack(A).reshape(7, -1)
    proj = (X - X.mean(0)) @ B.T
    np.testing.assert_allclose(m.sigma, proj.std(0, ddof=1), rtol=1e-5)
    np.testing.assert_allclose(m.explained_variance, m.sigma ** 2, rtol=1e-6)
    # ratios sum to 1 when all N-1 components are kept
    assert abs(m.explained_variance_ratio.sum() - 1) < 1e-5
    # descending order
    assert np.all(np.diff(m.sigma) <= 1e-7)


def test_exact_reconstruction_with_all_components():
    A, W = _data(n=5, K=2)
    m = fit_reflectance_pca(A, W, (4, 32), components=4)
    for j in range(5):
        alb, wts = sample_model(m, m.train_coeffs[j])
        np.testing.assert_allclose(alb, A[j], atol=2e-5)
        np.testing.assert_allclose(wts, W[j], atol=2e-5)
        # projecting the albedo gives back the same β
        np.testing.assert_allclose(project_maps(m, A[j]), m.train_coeffs[j], atol=1e-3)


def test_specular_bases_are_the_same_combination_of_samples():
    """Independent computation: a_kj from a least-squares solve b_k = Σ_j a_kj (x_j − μ) (sklearn-free),
    then compare Σ_j a_kj (y_j − μ_y) with the model's specular basis."""
    A, W = _data(n=6, K=3, seed=3)
    m = fit_reflectance_pca(A, W, (1, 8, 64), components=3)
    X = np.stack(A).reshape(6, -1)
    Y = np.stack(W).reshape(6, -1)
    Xc, Yc = X - X.mean(0), Y - Y.mean(0)
    for k in range(3):
        b = m.albedo_basis[k].reshape(-1).astype(np.float64)
        a, *_ = np.linalg.lstsq(Xc.T, b, rcond=None)  # minimum-norm combination (rows of Xc sum to 0)
        np.testing.assert_allclose(Xc.T @ a, b, atol=1e-5)
        np.testing.assert_allclose(m.weights_basis[k].reshape(-1), Yc.T @ a, atol=1e-5)
    # and the means are the sample means
    np.testing.assert_allclose(m.weights_mean.reshape(-1), Y.mean(0), atol=1e-6)


def test_specular_transfer_against_sklearn_pca():
    from sklearn.decomposition import PCA

    A, W = _data(n=9, K=3, seed=5)
    X = np.stack(A).reshape(9, -1)
    m = fit_reflectance_pca(A, W, (1, 8, 64), components=4)
    p = PCA(n_components=4, svd_solver="full").fit(X)
    for k in range(4):
        b = m.albedo_basis[k].reshape(-1)
        assert abs(abs(b @ p.components_[k]) - 1) < 1e-5
    np.testing.assert_allclose(m.explained_variance, p.explained_variance_, rtol=1e-4)


def test_component_cap_message_and_rank():
    A, W = _data(n=4)
    msgs = []
    m = fit_reflectance_pca(A, W, (1, 8, 64), components=80, log=msgs.append)
    assert m.n_components == 3
    assert any("N - 1 = 3" in s for s in msgs)
    # duplicated identities reduce the rank: 4 samples, only 2 distinct → rank 1
    A2, W2 = [A[0], A[0], A[1], A[1]], [W[0], W[0], W[1], W[1]]
    msgs = []
    m2 = fit_reflectance_pca(A2, W2, (1, 8, 64), components=3, log=msgs.append)
    assert m2.n_components == 1
    assert any("rank 1" in s for s in msgs)


def test_bad_input_is_named():
    A, W = _data(n=3)
    with pytest.raises(ReflectmmError, match="at least 2"):
        fit_reflectance_pca(A[:1], W[:1], (1, 8, 64))
    W[2] = W[2][:2]
    with pytest.raises(ReflectmmError, match="c: weights have shape"):
        fit_reflectance_pca(A, W, (1, 8, 64), ids=["a", "b", "c"])
    A, W = _data(n=3)
    A[1][0, 0, 0] = np.nan
    with pytest.raises(ReflectmmError, match="b: albedo contains NaN"):
        fit_reflectance_pca(A, W, (1, 8, 64), ids=["a", "b", "c"])
    with pytest.raises(ReflectmmError, match="exponents"):
        fit_reflectance_pca(*_data(n=3), (1, 8))


def test_mask_domain_and_fill():
    S = 8
    mask = np.zeros((S, S), bool)
    mask[1:7, 2:6] = True
    A, W = _data(n=5, S=S, mask=mask)
    m = fit_reflectance_pca(A, W, (1, 8, 64), masks=[mask] * 5)
    assert np.all(m.albedo_basis[:, :, ~mask] == 0) and np.all(m.weights_mean[:, ~mask] == 0)
    assert m.stats["domain_texels"] == mask.sum() == m.stats["texels_valid_in_all"]
    # one identity misses a texel: it is filled with the others' mean → that texel's variance comes only
    # from the identities that cover it
    masks = [mask.copy() for _ in range(5)]
    masks[0][3, 3] = False
    m2 = fit_reflectance_pca(A, W, (1, 8, 64), masks=masks, components=4)
    mean_others = np.mean([a[:, 3, 3] for a in A[1:]], axis=0)
    np.testing.assert_allclose(m2.albedo_mean[:, 3, 3], mean_others, atol=1e-6)
    rec, _ = sample_model(m2, m2.train_coeffs[0])
    np.testing.assert_allclose(rec[:, 3, 3], mean_others, atol=1e-5)
    assert m2.stats["texels_valid_in_all"] == mask.sum() - 1


def test_torch_sampling_matches_numpy_and_is_differentiable():
    import torch

    A, W = _data(n=6)
    m = fit_reflectance_pca(A, W, (1, 8, 64))
    beta = np.random.default_rng(1).normal(size=(2, 3))
    a_np, w_np = sample_model(m, beta)
    bt = torch.tensor(beta, dtype=torch.float64, requires_grad=True)
    a_t, w_t = sample_model(model_arrays(m), bt)
    np.testing.assert_allclose(a_t.detach().numpy(), a_np, atol=1e-6)
    np.testing.assert_allclose(w_t.detach().numpy(), w_np, atol=1e-6)
    (a_t.sum() + w_t.sum()).backward()
    # d/dβ_k of Σ albedo = σ_k Σ b_k (closed form)
    expect = m.sigma[:3] * (m.albedo_basis[:3].reshape(3, -1).sum(1) + m.weights_basis[:3].reshape(3, -1).sum(1))
    np.testing.assert_allclose(bt.grad.numpy()[0], expect, rtol=1e-5, atol=1e-6)
    with pytest.raises(ReflectmmError, match="beta must have shape"):
        sample_model(m, np.zeros(9))


@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_bilinear_sampler_reproduces_linear_maps(u, v):
    """A map linear in (u, v) is reproduced exactly inside the texel-centre range (independent closed form)."""
    S = 16
    rows, cols = np.mgrid[0:S, 0:S]
    uu, vv = (cols + 0.5) / S, (rows + 0.5) / S
    m = np.stack([2 * uu - 3 * vv + 1, 0.5 * uu + vv])
    got = sample_uv_bilinear(m, np.array([[u, v]]))[0]
    uc, vc = np.clip(u, 0.5 / S, 1 - 0.5 / S), np.clip(v, 0.5 / S, 1 - 0.5 / S)
    np.testing.assert_allclose(got, [2 * uc - 3 * vc + 1, 0.5 * uc + vc], atol=1e-9)


def test_vertex_model_is_consistent_with_uv_model():
    A, W = _data(n=5, S=16)
    m = fit_reflectance_pca(A, W, (1, 8, 64))
    rng = np.random.default_rng(2)
    uv = rng.uniform(0, 1, (50, 2))
    add_vertex_model(m, uv)
    assert m.vertex_albedo_basis.shape == (4, 50, 3) and m.vertex_weights_basis.shape == (4, 50, 3)
    beta = rng.normal(size=4)
    a_uv, w_uv = sample_model(m, beta)
    a_v, w_v = sample_model(m, beta, space="vertex")
    # sampling the UV sample at the vertices = the vertex model's sample (linearity)
    np.testing.assert_allclose(a_v, sample_uv_bilinear(a_uv, uv), atol=1e-5)
    np.testing.assert_allclose(w_v, sample_uv_bilinear(w_uv, uv), atol=1e-5)
    # round trip through the artifact arrays keeps everything
    m2 = model_from_arrays(model_arrays(m))
    np.testing.assert_array_equal(m2.vertex_weights_basis, m.vertex_weights_basis)
    assert m2.ids == m.ids


@given(st.integers(3, 12), st.floats(1e-5, 1e-1), st.integers(0, 10_000))
def test_gram_route_matches_svd_on_ill_conditioned_data(n, ratio, seed):
    """Singular values spread over [ratio, 1]: bases orthonormal and σ equal to numpy's thin SVD (independent)."""
    rng = np.random.default_rng(seed)
    S = 6
    D = 3 * S * S
    U, _ = np.linalg.qr(rng.normal(size=(n, n)))
    U = U[:, : n - 1]
    U -= U.mean(0)  # centred samples
    U, _ = np.linalg.qr(U)
    V, _ = np.linalg.qr(rng.normal(size=(D, n - 1)))
    s = np.geomspace(1.0, ratio, n - 1)
    X = 0.5 + (U * s) @ V.T
    A = list(X.reshape(n, 3, S, S))
    W = list(rng.uniform(size=(n, 2, S, S)))
    m = fit_reflectance_pca(A, W, (8, 64))
    ref = np.linalg.svd(X - X.mean(0), compute_uv=False)[: m.n_components] / np.sqrt(n - 1)
    np.testing.assert_allclose(m.sigma, ref, rtol=1e-4)
    B = m.albedo_basis.reshape(m.n_components, -1).astype(np.float64)
    np.testing.assert_allclose(B @ B.T, np.eye(m.n_components), atol=2e-6)


def test_splat_renderer_covers_and_interpolates():
    """Fallback preview renderer: a frontal plane with colour = x is covered without holes and the colour is the
    linear function of the pixel's x back-projected (closed form of the pinhole camera)."""
    from reflectmm_cli.model.preview import render_vertex_colors

    g = 15
    x, y = np.meshgrid(np.linspace(-50, 50, g), np.linspace(-50, 50, g))
    V = np.stack([x.ravel(), y.ravel(), np.zeros(g * g)], -1)
    T = []
    for r in range(g - 1):
        for c in range(g - 1):
            i = r * g + c
            T += [(i, i + 1, i + g), (i + 1, i + g + 1, i + g)]
    col = V[:, :1].copy()
    W = 64
    eye, f = np.array([0.0, 0.0, 500.0]), 300.0
    img = render_vertex_colors(V, np.array(T), col, W, eye, f)[..., 0]
    half = f * 50 / 500  # projected half width in px
    c = W / 2
    inner = slice(int(c - half + 2), int(c + half - 2))
    assert not np.isnan(img[inner, inner]).any()
    assert np.isnan(img[0, 0])
    cols = np.arange(W)[inner]
    expect = (cols + 0.5 - c) * 500 / f  # x on the plane seen by pixel centre (col + 0.5)
    got = img[W // 2, inner]
    assert np.max(np.abs(got - expect)) <= 500 / f * 0.75  # within the splat's pixel snapping


def _plane(g, half, z0):
    x, y = np.meshgrid(np.linspace(-half, half, g), np.linspace(-half, half, g))
    V = np.stack([x.ravel(), y.ravel(), np.full(g * g, z0)], -1)
    T = [t for r in range(g - 1) for c in range(g - 1)
         for t in ((r * g + c, r * g + c + 1, (r + 1) * g + c), (r * g + c + 1, (r + 1) * g + c + 1, (r + 1) * g + c))]
    return V, np.array(T)


def test_splat_keeps_the_nearest_surface_and_reuses_its_visibility():
    """Two parallel planes, the smaller one 100 mm nearer the camera: where both project, the nearer one's colour
    is seen, elsewhere the far one's; one VertexSplat rendering two colourings gives what rendering each from
    scratch gives, and a colouring of the wrong size is refused."""
    from reflectmm_cli.errors import ReflectmmError
    from reflectmm_cli.model.preview import VertexSplat, render_vertex_colors

    Vf, Tf = _plane(9, 50.0, 0.0)
    Vn, Tn = _plane(5, 10.0, 100.0)
    V = np.concatenate([Vf, Vn])
    T = np.concatenate([Tf, Tn + len(Vf)])
    far = np.r_[np.ones(len(Vf)), np.zeros(len(Vn))][:, None]
    W, eye, f = 64, np.array([0.0, 0.0, 500.0]), 300.0
    splat = VertexSplat(V, T, W, eye, f)
    img = splat.render(far)[..., 0]
    c = W / 2
    near_half = f * 10 / 400  # the near plane's projected half width (px)
    inner = slice(int(c - near_half + 1), int(c + near_half - 1))
    assert np.all(img[inner, inner] == 0.0)  # the near plane hides the far one
    far_half = f * 50 / 500
    ring = img[int(c), int(c - far_half + 2):int(c - near_half - 1)]
    assert ring.size and np.all(ring == 1.0)
    for colours in (far, 1.0 - far, np.random.default_rng(0).random((len(V), 3))):
        np.testing.assert_array_equal(splat.render(colours), render_vertex_colors(V, T, colours, W, eye, f))
    with pytest.raises(ReflectmmError, match="colours of shape"):
        splat.render(far[:-1])


def test_trainable_torch_model_gets_gradients():
    import torch

    from reflectmm_cli.model import model_to_torch

    A, W = _data(n=5)
    m = fit_reflectance_pca(A, W, (1, 8, 64))
    tm = model_to_torch(m, requires_grad=True)
    beta = torch.tensor([0.5, -1.0], requires_grad=True)
    alb, wts = sample_model(tm, beta)
    np.testing.assert_allclose(alb.detach().numpy(), sample_model(m, np.array([0.5, -1.0]))[0], atol=1e-5)
    (alb.sum() + 2 * wts.sum()).backward()
    # d/d mean = 1 per element; d/d basis_k = β_k σ_k per element (closed form); basis 2, 3 unused → 0
    assert torch.allclose(tm["albedo_mean"].grad, torch.ones_like(tm["albedo_mean"]))
    assert torch.allclose(tm["weights_mean"].grad, 2 * torch.ones_like(tm["weights_mean"]))
    g = tm["albedo_basis"].grad
    assert torch.allclose(g[0], torch.full_like(g[0], 0.5 * float(m.sigma[0])), rtol=1e-5)
    assert torch.allclose(g[1], torch.full_like(g[1], -1.0 * float(m.sigma[1])), rtol=1e-5)
    assert float(g[2:].abs().max()) == 0.0
    assert not tm["sigma"].requires_grad

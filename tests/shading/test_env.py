"""SH environment shading against quadrature of the rendering equation; equirect projection."""
import math

import numpy as np
import pytest

from _shading_ref import bp_sh_ref, hemisphere_quadrature, real_sh_matrix_ref
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import (
    band_limits,
    direction_to_equirect,
    envmap_from_sh,
    equirect_directions,
    equirect_weights,
    project_envmap,
    shade_directional,
    shade_env,
)

torch = pytest.importorskip("torch")
P = np.array([1.0, 8.0, 64.0])
ORDER = 6


def _lighting(seed, order=ORDER):
    rng = np.random.default_rng(seed)
    K = rng.normal(size=(3, (order + 1) ** 2)) / (1 + np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1))
    K[:, 0] += 3.0
    return K


def _radiance(K, d):
    order = int(math.sqrt(K.shape[1])) - 1
    return real_sh_matrix_ref(d, order) @ K.T  # (N, 3), scipy-based, independent of the code under test


def test_diffuse_exact_against_hemisphere_quadrature():
    K = _lighting(0)
    rng = np.random.default_rng(5)
    for _ in range(4):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d, w = hemisphere_quadrature(n, 2 * ORDER + 4, 4 * ORDER + 4)
        c = np.array([0.8, 0.5, 0.3])
        ref = c / math.pi * ((_radiance(K, d) * (d @ n)[:, None]) * w[:, None]).sum(0)
        dif, _ = shade_env(c, np.zeros(3), P, n, n, K)
        np.testing.assert_allclose(dif, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("p", [1.0, 8.0, 64.0, 500.0])
def test_specular_exact_at_normal_view(p):
    # at v = n the SH specular equals the true half-vector lobe integral, ∫ L(l) w f (n·h)^p [n·l > 0] dω,
    # here integrated with the directional shader as integrand (irradiance L(l) dω from each direction).
    K = _lighting(1)
    n = np.array([0.2, 0.5, -0.8])
    n /= np.linalg.norm(n)
    d, w = hemisphere_quadrature(n, 320, 4 * ORDER + 4)
    _, _, spec = shade_directional(np.zeros(3), [0.9], [p], n, d, n, _radiance(K, d), return_parts=True)
    ref = (spec * w[:, None]).sum(0)
    _, s = shade_env(np.zeros(3), [0.9], [p], n, n, K)
    np.testing.assert_allclose(s, ref, rtol=1e-7)


def test_specular_formula_oblique_view():
    # away from normal view the contract is Σ_l B_l Σ_m K_lm Y_lm(r), r = 2(n·v)n − v
    K = _lighting(2)
    rng = np.random.default_rng(7)
    n = rng.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = n + 0.8 * rng.normal(size=(20, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    w = rng.random((20, 3))
    _, s = shade_env(np.zeros((20, 3)), w, P, n, v, K)
    ndv = (n * v).sum(1)
    r = 2 * ndv[:, None] * n - v
    lvl = np.repeat(np.arange(ORDER + 1), 2 * np.arange(ORDER + 1) + 1)
    Y = real_sh_matrix_ref(r, ORDER)
    ref = np.zeros((20, 3))
    for i, p in enumerate(P):
        B = np.array([bp_sh_ref(p, l) for l in range(ORDER + 1)])[lvl]
        ref += w[:, i:i + 1] * (Y @ (K * B).T)
    ref[ndv <= 0] = 0
    np.testing.assert_allclose(s, ref, rtol=1e-8, atol=1e-10)


def test_paths_agree_mask_skip_and_dtypes():
    K = _lighting(3)
    rng = np.random.default_rng(11)
    N = 3000
    c, w = rng.random((N, 3)), rng.random((N, 3))
    w[:, 1] = 0  # an all-zero lobe is skipped, result unchanged
    n, v = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    d64, s64 = shade_env(c, w, P, n, v, K, chunk=512)
    # numpy broadcasting path (per-texel lighting) and torch agree with the blocked fast path
    d2, s2 = shade_env(c, w, P, n, v, np.broadcast_to(K, (N, 3, K.shape[1])))
    dt_, st_ = shade_env(*(torch.tensor(a) for a in (c, w, P, n, v, K)))
    for a, b in ((d2, d64), (s2, s64), (dt_.numpy(), d64), (st_.numpy(), s64)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert np.all(s64[(n * v).sum(1) <= 0] == 0)
    mask = rng.random(N) < 0.3
    dm, sm = shade_env(c, w, P, n, v, K, mask=mask)
    np.testing.assert_array_equal(dm[~mask], 0)
    np.testing.assert_array_equal(sm[~mask], 0)
    np.testing.assert_allclose(dm[mask], d64[mask], rtol=1e-12)
    np.testing.assert_allclose(sm[mask], s64[mask], rtol=1e-12, atol=1e-14)
    dmt, smt = shade_env(*(torch.tensor(a) for a in (c, w, P, n, v, K)), mask=mask)
    np.testing.assert_allclose(smt.numpy(), sm, rtol=1e-10, atol=1e-12)
    d32, s32 = shade_env(*(a.astype(np.float32) for a in (c, w, P, n, v, K)))
    assert d32.dtype == np.float32 and s32.dtype == np.float32
    np.testing.assert_allclose(s32, s64, rtol=1e-4, atol=1e-4)
    d16, s16 = shade_env(*(a.astype(np.float16) for a in (c, w, P, n, v, K)))
    assert d16.dtype == np.float32 and np.isfinite(s16).all()


def test_band_tolerance_bounds_the_change():
    K = _lighting(4, 8)
    rng = np.random.default_rng(2)
    n, v = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    w = np.ones((500, 3))
    _, s0 = shade_env(np.ones((500, 3)), w, P, n, v, K)
    for tol in (1e-2, 1e-3):
        Ld, Ls = band_limits(P, 8, tol)
        if tol == 1e-2:  # the sharp lobe keeps all bands, the broader ones lose some
            assert Ls == [7, 3, 8] and Ld == 6
        _, s1 = shade_env(np.ones((500, 3)), w, P, n, v, K, band_tol=tol)
        # each dropped band changes a lobe by ≤ tol·|Σ_m K_lm Y_lm| ≤ tol·‖K_l‖·sqrt((2l+1)/4π)
        bound = sum(tol * np.linalg.norm(K[:, l * l:(l + 1) ** 2], axis=1).max() * math.sqrt((2 * l + 1) / (4 * math.pi))
                    for l in range(9)) * 3
        assert np.abs(s1 - s0).max() <= bound
    assert band_limits(P, 8, 0.0) == (8, [8, 8, 8])


def test_gradcheck_shade_env_float64():
    rng = np.random.default_rng(9)
    N = 5
    args = [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (
        rng.random((N, 3)), rng.random((N, 3)), [1.0, 8.0, 64.0],
        np.tile([0, 0, 1.0], (N, 1)) + 0.2 * rng.normal(size=(N, 3)),
        np.tile([0, 0.3, 1.0], (N, 1)) + 0.2 * rng.normal(size=(N, 3)), _lighting(5, 3))]
    args[2].requires_grad_(False)
    assert torch.autograd.gradcheck(lambda *a: shade_env(*a), args, eps=1e-6, atol=1e-5)


def test_rejects_nonfinite_and_bad_shapes():
    K = _lighting(0)
    with pytest.raises(ReflectmmError, match="sh_coeffs"):
        shade_env(np.ones(3), np.ones(3), P, [0, 0, 1.0], [0, 0, 1.0], np.where(K > 1, np.nan, K))
    with pytest.raises(ReflectmmError, match="sh_coeffs"):
        shade_env(np.ones(3), np.ones(3), P, [0, 0, 1.0], [0, 0, 1.0], K[:, :10])
    with pytest.raises(ReflectmmError, match="view_dir"):
        shade_env(np.ones(3), np.ones(3), P, [0, 0, 1.0], [0, np.inf, 1.0], K)


# ---------------------------------------------------------------------------------------------------------------
# equirectangular maps


@pytest.mark.parametrize("wh", [(17, 9), (32, 16), (50, 31)])
def test_projection_exact_for_band_limited_maps(wh):
    W, H = wh
    order = 4
    K = _lighting(6, order)
    img = envmap_from_sh(K, W, H).astype(np.float64)
    # the map itself is the SH function sampled at pixel centres (checked independently with scipy)
    d = equirect_directions(W, H).reshape(-1, 3)
    np.testing.assert_allclose(img.reshape(-1, 3), _radiance(K, d), rtol=1e-5, atol=1e-5)
    img = _radiance(K, d).reshape(H, W, 3)
    np.testing.assert_allclose(project_envmap(img, order), K, atol=1e-11)
    # pixel-area weights are the exact pixel solid angles (sum 4π) and converge to the same coefficients
    assert abs(equirect_weights(W, H, "area").sum() * W - 4 * math.pi) < 1e-12
    assert abs(equirect_weights(W, H, "fejer").sum() * W - 4 * math.pi) < 1e-12
    assert np.abs(project_envmap(img, order, quadrature="area") - K).max() < 30.0 / H ** 2


def test_equirect_convention():
    W, H = 64, 32
    d = equirect_directions(W, H)
    assert d[0, W // 2, 1] > 0.99  # top row is +y (up)
    np.testing.assert_allclose(d[H // 2, W // 2], [0, 0, -1], atol=0.1)  # centre looks down −z
    np.testing.assert_allclose(d[H // 2, 3 * W // 4], [1, 0, 0], atol=0.1)  # three quarters across is +x
    u, v = direction_to_equirect(d)
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    np.testing.assert_allclose(u, (jj + 0.5) / W, atol=1e-12)
    np.testing.assert_allclose(v, (ii + 0.5) / H, atol=1e-12)
    # a map bright at the top: the +y dipole term dominates, and Y_1,-1 = −√(3/4π) y → negative coefficient
    img = np.zeros((H, W, 3))
    img[:4] = 1.0
    K = project_envmap(img, 1)
    assert K[0, 1] < 0 and abs(K[0, 2]) < 1e-12 and abs(K[0, 3]) < 1e-12


def test_projection_rejects_nonfinite():
    img = np.ones((8, 16, 3))
    img[2, 3, 1] = np.nan
    with pytest.raises(ReflectmmError, match="NaN"):
        project_envmap(img, 2)


def _ducc_vs_ours(ducc0, alm, order, coeffs, rng):
    # compare as functions: evaluate both expansions at random directions
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u, v = direction_to_equirect(d)
    loc = np.stack([v * math.pi, (u * 2 * math.pi - math.pi) % (2 * math.pi)], -1)
    vals = ducc0.sht.experimental.synthesis_general(alm=alm, spin=0, lmax=order, loc=loc, epsilon=1e-12)[0]
    return vals, real_sh_matrix_ref(d, order) @ coeffs


def test_projection_agrees_with_ducc0():
    ducc0 = pytest.importorskip("ducc0")
    rng = np.random.default_rng(0)
    W, H, order = 96, 48, 8
    phi0 = math.pi / W - math.pi  # our first column's azimuth in ducc0's (θ from up, φ along columns) frame
    # map band-limited to the order (ducc0's analysis_2d is exact only then): both recover the same coefficients
    Kbig = _lighting(8, order)[:1]
    img = _radiance(Kbig, equirect_directions(W, H).reshape(-1, 3))[:, 0].reshape(H, W)
    ours = project_envmap(img[..., None], order)[0]
    alm = ducc0.sht.experimental.analysis_2d(map=img[None], spin=0, lmax=order, geometry="F1", phi0=phi0)
    a, b = _ducc_vs_ours(ducc0, alm, order, ours, rng)
    np.testing.assert_allclose(b, a, atol=1e-9)
    # arbitrary (not band-limited) map: same quadrature rule through ducc0's adjoint synthesis
    img = rng.random((H, W))
    ours = project_envmap(img[..., None], order)[0]
    wq = ducc0.sht.experimental.get_gridweights("F1", H)  # per ring, sums to 4π
    alm = ducc0.sht.experimental.adjoint_synthesis_2d(map=(img * wq[:, None] / W)[None], spin=0, lmax=order,
                                                      geometry="F1", phi0=phi0)
    a, b = _ducc_vs_ours(ducc0, alm, order, ours, rng)
    np.testing.assert_allclose(b, a, atol=1e-9)


@pytest.mark.parametrize("quadrature", ["fejer", "area"])
def test_separable_projection_equals_per_pixel_sum(quadrature):
    from reflectmm_cli.shading.envmap import _project_envmap_direct

    img = np.random.default_rng(4).random((21, 38, 2)) * 5
    np.testing.assert_allclose(project_envmap(img, 7, quadrature=quadrature),
                               _project_envmap_direct(img, 7, quadrature=quadrature), atol=1e-12)


@pytest.mark.parametrize("p", [1.0, 8.0, 64.0, 1000.0])
def test_view_correction_matches_true_lobe_under_uniform_light(p):
    from reflectmm_cli.shading import specular_view_albedo

    n = np.array([0.0, 0.0, 1.0])
    K = np.zeros((3, 9))
    K[:, 0] = math.sqrt(4 * math.pi)  # uniform unit radiance
    for mu in (1.0, 0.6, 0.2):
        v = np.array([math.sqrt(1 - mu * mu), 0.0, mu])
        # truth: the directional shader integrated over the hemisphere (Gauss in cos θ, dense in φ)
        d, wq = hemisphere_quadrature(n, 300, 400)
        _, _, spec = shade_directional(np.zeros(3), [1.0], [p], n, d, v, 1.0, return_parts=True)
        truth = (spec[:, 0] * wq).sum()
        assert abs(specular_view_albedo(p, mu) - truth) < 4e-3 * max(truth, 0.1), (mu, truth)
        _, s_plain = shade_env(np.zeros(3), [1.0], [p], n, v, K)
        _, s_corr = shade_env(np.zeros(3), [1.0], [p], n, v, K, view_correction=True)
        np.testing.assert_allclose(s_plain, 1.0, rtol=1e-9)  # the paper's SH lobe keeps energy 1 at any view
        np.testing.assert_allclose(s_corr, specular_view_albedo(p, mu), rtol=1e-6)
        st_ = shade_env(*(torch.tensor(a) for a in (np.zeros(3), [1.0], [p], n, v, K)), view_correction=True)[1]
        np.testing.assert_allclose(st_.numpy(), s_corr, rtol=1e-9)


def test_torch_stacked_lobes_match_numpy_with_band_limits():
    # one global lighting: the torch path stacks the lobes into one product (bands beyond a lobe's limit padded
    # with zeros); it must equal the blocked numpy kernel's per-lobe loop, with different band limits per lobe,
    # with a lobe whose weights are all zero, and through a precomputed EnvBasis
    from reflectmm_cli.shading import EnvBasis

    K = _lighting(4, 8)
    rng = np.random.default_rng(17)
    N = 900
    c, w, n, v = rng.random((N, 3)), rng.random((N, 3)), rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    for tol, zero_lobe in ((1e-2, None), (0.0, 1), (1e-3, 0)):
        ww = w.copy()
        if zero_lobe is not None:
            ww[:, zero_lobe] = 0
        d_ref, s_ref = shade_env(c, ww, P, n, v, K, band_tol=tol)
        Kt = torch.tensor(K, requires_grad=True)
        wt = torch.tensor(ww, requires_grad=True)
        d_t, s_t = shade_env(torch.tensor(c), wt, P, torch.tensor(n), torch.tensor(v), Kt, band_tol=tol)
        np.testing.assert_allclose(s_t.detach().numpy(), s_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(d_t.detach().numpy(), d_ref, rtol=1e-10, atol=1e-12)
        eb = EnvBasis(torch.tensor(n), torch.tensor(v), 8, dtype=torch.float64)
        d_b, s_b = shade_env(torch.tensor(c), wt, P, None, None, Kt, band_tol=tol, basis=eb)
        np.testing.assert_allclose(s_b.detach().numpy(), s_ref, rtol=1e-10, atol=1e-12)
        # gradient w.r.t. the weights: the per-lobe specular radiance (independent: shade one lobe at a time)
        (s_t[:, 0].sum()).backward()
        for i in range(3):
            one = np.zeros_like(ww)
            one[:, i] = 1
            lobe = shade_env(c, one, P, n, v, K, band_tol=tol)[1][:, 0]
            np.testing.assert_allclose(wt.grad[:, i].numpy(), lobe, rtol=1e-9, atol=1e-12)


def test_torch_fixed_geometry_paths_match_numpy():
    # normals/views without gradients take the numpy-basis path; lighting/albedo/weights keep their gradients
    K = _lighting(12)
    rng = np.random.default_rng(13)
    N = 700
    c, w, n, v = rng.random((2, N, 3)), rng.random((N, 3)), rng.normal(size=(2, N, 3)), rng.normal(size=(2, N, 3))
    Kb = np.stack([K, K * 0.5])[:, None]  # per-image lighting (2, 1, 3, n)
    for KK in (K, Kb):
        d_ref, s_ref = shade_env(c, w, P, n, v, KK)
        Kt = torch.tensor(KK, requires_grad=True)
        ct = torch.tensor(c, requires_grad=True)
        d_t, s_t = shade_env(ct, torch.tensor(w), P, torch.tensor(n), torch.tensor(v), Kt)
        np.testing.assert_allclose(d_t.detach().numpy(), d_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(s_t.detach().numpy(), s_ref, rtol=1e-10, atol=1e-12)
        (d_t.sum() + s_t.sum()).backward()
        assert torch.isfinite(Kt.grad).all() and torch.isfinite(ct.grad).all()
        np.testing.assert_allclose(ct.grad.numpy(), d_ref / np.maximum(c, 1e-300), rtol=1e-8)


from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_vec = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).filter(lambda a: sum(x * x for x in a) > 1e-4)


@given(n=_vec, v=_vec, sn=st.floats(1e-3, 1e3), sv=st.floats(1e-3, 1e3), p=st.floats(0.5, 1000),
       dtype=st.sampled_from([np.float16, np.float32, np.float64]))
def test_property_env_scale_invariance_and_dtypes(n, v, sn, sv, p, dtype):
    K = _lighting(0, 4)
    args = [np.array([0.5, 0.4, 0.3]), np.array([1.0, 0.5]), np.array([p, 8.0])]
    d0, s0 = shade_env(*args, np.array(n), np.array(v), K)
    d1, s1 = shade_env(*(a.astype(dtype) for a in args), (np.array(n) * sn).astype(dtype),
                       (np.array(v) * sv).astype(dtype), K.astype(dtype))
    assert np.isfinite(d1).all() and np.isfinite(s1).all()
    tol = {np.float16: 0.05, np.float32: 1e-4, np.float64: 1e-9}[dtype]
    np.testing.assert_allclose(d1, d0, rtol=tol, atol=tol * (1 + np.abs(d0).max()))
    if float(np.dot(n, v)) > 0.05:  # away from the n·v = 0 cut, where rounding may flip the side
        np.testing.assert_allclose(s1, s0, rtol=tol, atol=tol * (1 + np.abs(s0).max()))


def test_precomputed_env_basis_matches_and_differentiates():
    from reflectmm_cli.shading import EnvBasis

    K = _lighting(21)
    rng = np.random.default_rng(21)
    N = 500
    c, w, n, v = rng.random((N, 3)), rng.random((N, 3)), rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    d_ref, s_ref = shade_env(c, w, P, n, v, K, view_correction=True)
    eb = EnvBasis(n, v, ORDER, dtype=torch.float64)
    Kt = torch.tensor(K, requires_grad=True)
    d, s = shade_env(torch.tensor(c), torch.tensor(w), P, None, None, Kt, basis=eb, view_correction=True)
    np.testing.assert_allclose(d.detach().numpy(), d_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s.detach().numpy(), s_ref, rtol=1e-10, atol=1e-12)
    (d.sum() + s.sum()).backward()
    g_basis = Kt.grad.clone()
    Kt.grad = None
    d2, s2 = shade_env(torch.tensor(c), torch.tensor(w), P, torch.tensor(n), torch.tensor(v), Kt, view_correction=True)
    (d2.sum() + s2.sum()).backward()
    np.testing.assert_allclose(g_basis.numpy(), Kt.grad.numpy(), rtol=1e-10)
    # lower-order lighting reuses the leading bands; float32 basis with float64 lighting is promoted
    d3, _ = shade_env(c, w, P, None, None, K[:, :16], basis=EnvBasis(n, v, ORDER))
    np.testing.assert_allclose(d3.numpy(), shade_env(c, w, P, n, v, K[:, :16])[0], rtol=1e-5, atol=1e-6)
    with pytest.raises(ReflectmmError, match="order"):
        shade_env(c, w, P, None, None, _lighting(0, 8), basis=eb)
    # the basis of n keeps only the bands with A_l ≠ 0 (the odd l ≥ 3 are exact zeros): 31 of 49 at order 6
    assert tuple(eb.Yn.shape) == (1 + 3 + 5 + 9 + 13, N) and tuple(eb.Yr.shape) == ((ORDER + 1) ** 2, N)
    # per-texel lighting (N, 3, n) through the basis equals the per-texel path without it
    Kp = K[None] * (0.5 + rng.random((N, 1, 1)))
    dp, sp = shade_env(torch.tensor(c), torch.tensor(w), P, None, None, torch.tensor(Kp), basis=eb)
    dq, sq = shade_env(c, w, P, n, v, Kp)
    np.testing.assert_allclose(dp.numpy(), dq, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sp.numpy(), sq, rtol=1e-10, atol=1e-12)


def test_check_finite_names_the_argument_and_can_be_skipped():
    from reflectmm_cli.errors import ReflectmmError
    from reflectmm_cli.shading import EnvBasis

    K = _lighting(2)
    rng = np.random.default_rng(3)
    c, w, n, v = rng.random((50, 3)), rng.random((50, 3)), rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    c[7, 1] = np.nan
    eb = EnvBasis(torch.tensor(n), torch.tensor(v), 8, dtype=torch.float64)
    with pytest.raises(ReflectmmError, match="'albedo' contains NaN"):
        shade_env(torch.tensor(c), torch.tensor(w), P, None, None, torch.tensor(K), basis=eb)
    d, s = shade_env(torch.tensor(c), torch.tensor(w), P, None, None, torch.tensor(K), basis=eb, check_finite=False)
    assert torch.isnan(d[7]).any() and torch.isfinite(d[np.r_[0:7, 8:50]]).all()  # the NaN stays where it was
    # the basis's own normals were checked when it was built
    n[3] = np.inf
    with pytest.raises(ReflectmmError, match="'normal' contains NaN or inf"):
        EnvBasis(torch.tensor(n), torch.tensor(v), 8)

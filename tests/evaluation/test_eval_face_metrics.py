"""Face-region metrics over image sets: skimage on the same masked images, CI coverage on known distributions,
the released batch protocol against brute-force and torch computations."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.face_metrics import (PSNR_CAP, face_region_metrics, mean_ci, released_protocol,
                                                   ssim_window_map)


def _images(n=4, size=24, seed=0):
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.1, 0.9, (n, size, size, 3))
    p = np.clip(t + rng.normal(0, 0.05, t.shape), 0, 1)
    yy, xx = np.mgrid[:size, :size]
    masks = np.stack([((yy - size / 2) ** 2 + (xx - size / 2 - i) ** 2) < (size / 3) ** 2 for i in range(n)])
    return p, t, masks


def test_per_image_metrics_match_skimage_on_masked_images():
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    p, t, m = _images()
    res = face_region_metrics(p, t, m)
    for i in range(len(p)):
        # PSNR: skimage on the masked pixels only
        ref_psnr = peak_signal_noise_ratio(t[i][m[i]], p[i][m[i]], data_range=1.0)
        assert res.per_image["psnr"][i] == pytest.approx(ref_psnr, rel=1e-10)
        # SSIM: skimage's full map of the background-zeroed images, averaged over the mask
        a = np.where(m[i][..., None], p[i], 0.0)
        b = np.where(m[i][..., None], t[i], 0.0)
        _, smap = structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False, full=True, channel_axis=-1)
        assert res.per_image["ssim"][i] == pytest.approx(smap.mean(-1)[m[i]].mean(), rel=1e-10)
    assert res.summary["psnr"]["mean"] == pytest.approx(res.per_image["psnr"].mean())
    assert res.lpips.startswith("off") and "lpips" not in res.per_image
    assert res.row()["LPIPS"] == "off"


def test_empty_mask_and_count_mismatch_are_errors():
    p, t, m = _images(2)
    m[1] = False
    with pytest.raises(ReflectmmError, match="#1 has an empty face mask"):
        face_region_metrics(p, t, m)
    with pytest.raises(ReflectmmError, match="one of each"):
        face_region_metrics(p, t[:1], m)


def test_identical_images_psnr_is_capped():
    p, t, m = _images(2)
    res = face_region_metrics(t, t, m)
    assert np.all(res.per_image["psnr"] == PSNR_CAP)


@pytest.mark.parametrize("method,dist", [("t", "normal"), ("t", "exponential"), ("bootstrap", "normal")])
def test_ci_coverage_on_known_distributions(method, dist):
    """~95 % of the intervals cover the true mean (binomial tolerance for the number of trials)."""
    rng = np.random.default_rng(12)
    trials = 400 if method == "t" else 150
    n = 30
    cover = 0
    for k in range(trials):
        if dist == "normal":
            x, mu = rng.normal(2.0, 3.0, n), 2.0
        else:
            x, mu = rng.exponential(1.5, n), 1.5
        ci = mean_ci(x, method=method, n_boot=800, seed=k)
        cover += ci["lo"] <= mu <= ci["hi"]
    rate = cover / trials
    sd = np.sqrt(0.95 * 0.05 / trials)
    # t on normal data is exact; the skewed exponential and the percentile bootstrap under-cover a little at n=30
    lo = 0.95 - 4 * sd - (0.0 if (method, dist) == ("t", "normal") else 0.03)
    assert lo <= rate <= 0.95 + 4 * sd, rate


def test_t_interval_closed_form():
    x = np.array([1.0, 2.0, 4.0, 7.0])
    ci = mean_ci(x)
    from scipy import stats

    h = stats.t.ppf(0.975, 3) * x.std(ddof=1) / 2.0
    assert ci["lo"] == pytest.approx(3.5 - h) and ci["hi"] == pytest.approx(3.5 + h)
    one = mean_ci([3.0])
    assert one["mean"] == 3.0 and np.isnan(one["lo"])
    with pytest.raises(ReflectmmError, match="NaN"):
        mean_ci([1.0, np.nan])


def _brute_ssim3(a, b, sigma=1.5):
    """SSIM window 3 by an explicit loop over 3×3 neighbourhoods with reflect padding."""
    x = np.arange(3) - 1.0
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    pa = np.pad(a, ((1, 1), (1, 1)), mode="reflect")
    pb = np.pad(b, ((1, 1), (1, 1)), mode="reflect")
    out = np.zeros_like(a)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            A, B = pa[i:i + 3, j:j + 3], pb[i:i + 3, j:j + 3]
            ma, mb = (w * A).sum(), (w * B).sum()
            va, vb = (w * A * A).sum() - ma ** 2, (w * B * B).sum() - mb ** 2
            cab = (w * A * B).sum() - ma * mb
            out[i, j] = (2 * ma * mb + c1) * (2 * cab + c2) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))
    return out


@given(st.integers(0, 10_000))
def test_ssim_window3_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(size=(2, 7, 9))
    assert np.allclose(ssim_window_map(a, b), _brute_ssim3(a, b), atol=1e-10)


def test_released_protocol_against_direct_torch_computation():
    import torch
    import torch.nn.functional as F

    rng = np.random.default_rng(3)
    n, s = 5, 20
    lin = rng.uniform(0, 1.3, (n, s, s, 3))  # values > 1 are not clipped by the released encoding
    tgt = rng.uniform(0, 1, (n, s, s, 3))
    m = rng.uniform(size=(n, s, s)) < 0.6
    res = released_protocol(lin, tgt, m, batch_size=2)
    assert len(res["per_batch"]["psnr"]) == 3 and res["lpips"] is None
    g = torch.exp(-torch.arange(-1.0, 2.0, dtype=torch.float64) ** 2 / 4.5)
    k = (g[:, None] * g[None, :] / (g.sum() ** 2)).view(1, 1, 3, 3).repeat(3, 1, 1, 1)
    psnrs, ssims = [], []
    for b0 in range(0, n, 2):
        mm = torch.as_tensor(m[b0:b0 + 2, None].astype(np.float64))
        P = torch.as_tensor(lin[b0:b0 + 2]).permute(0, 3, 1, 2).clamp(min=1e-6) ** (1 / 1.2) * mm
        T = torch.as_tensor(tgt[b0:b0 + 2]).permute(0, 3, 1, 2) * mm
        psnrs.append(float(10 * torch.log10(1 / ((P - T) ** 2).mean())))
        f = lambda z: F.conv2d(F.pad(z, (1, 1, 1, 1), mode="reflect"), k, groups=3)  # noqa: E731
        mp, mt = f(P), f(T)
        sp, st_, spt = f(P * P) - mp ** 2, f(T * T) - mt ** 2, f(P * T) - mp * mt
        smap = ((2 * mp * mt + 1e-4) * (2 * spt + 9e-4)) / ((mp ** 2 + mt ** 2 + 1e-4) * (sp + st_ + 9e-4) + 1e-12)
        ssims.append(float(smap.mean()))
    assert res["per_batch"]["psnr"] == pytest.approx(psnrs, rel=1e-10)
    assert res["per_batch"]["ssim"] == pytest.approx(ssims, rel=1e-9)
    assert res["psnr"] == pytest.approx(np.mean(psnrs))


def test_released_protocol_depends_on_background_area_unlike_per_image():
    """One MSE over the whole zeroed batch: more background raises the released PSNR, the per-image one not."""
    p, t, m = _images(2, size=32)
    lin = p ** 1.2
    big = np.zeros((2, 64, 64, 3))
    big_t = np.zeros_like(big)
    big_m = np.zeros((2, 64, 64), bool)
    big[:, :32, :32], big_t[:, :32, :32], big_m[:, :32, :32] = lin, t, m
    r_small, r_big = released_protocol(lin, t, m), released_protocol(big, big_t, big_m)
    assert r_big["psnr"] == pytest.approx(r_small["psnr"] + 10 * np.log10(4), abs=1e-6)
    a = face_region_metrics(p, t, m).summary["psnr"]["mean"]
    b = face_region_metrics(big ** (1 / 1.2), big_t, big_m).summary["psnr"]["mean"]
    assert a == pytest.approx(b, rel=1e-9)


@given(st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40), st.floats(1e-3, 1e3), st.floats(-1e3, 1e3))
def test_ci_is_affine_equivariant_and_finite(xs, a, b):
    x = np.array(xs)
    c0, c1 = mean_ci(x), mean_ci(a * x + b)
    tol = 1e-6 * (1 + a * np.abs(x).max() + abs(b))
    assert np.isfinite(c1["lo"]) and c1["lo"] <= c1["mean"] <= c1["hi"]
    assert c1["mean"] == pytest.approx(a * c0["mean"] + b, abs=tol)
    assert c1["half_width"] == pytest.approx(a * c0["half_width"], abs=tol)
    bs = mean_ci(x, method="bootstrap", n_boot=200)
    assert bs["lo"] <= bs["hi"] and x.min() - 1e-9 <= bs["lo"] and bs["hi"] <= x.max() + 1e-9


def test_constant_values_and_images():
    c = mean_ci([2.5] * 6)
    assert c["lo"] == c["hi"] == 2.5
    a = np.full((9, 9, 3), 0.4)
    assert np.allclose(ssim_window_map(a, a), 1.0)

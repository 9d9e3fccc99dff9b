"""PSNR / SSIM / LPIPS against closed forms, skimage on plain cases, and hand-computed network pieces."""
import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation import LPIPS, encode_for_metrics, load_lpips, psnr, ssim


@given(st.floats(1e-3, 0.5), st.floats(0.5, 4.0))
def test_psnr_closed_form_constant_offset(d, peak):
    a = np.full((8, 9, 3), 0.25)
    assert psnr(a + d, a, peak=peak) == pytest.approx(10 * np.log10(peak ** 2 / d ** 2), rel=1e-9)


def test_psnr_mask_respected_and_identical_is_inf():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(16, 16, 3))
    b = a.copy()
    mask = np.zeros((16, 16), bool)
    mask[4:12, 4:12] = True
    b[~mask] = 0  # differences outside the mask do not count
    assert psnr(a, b, mask) == float("inf")
    b[5, 5, 1] += 0.1
    mse = 0.01 / (mask.sum() * 3)
    assert psnr(a, b, mask) == pytest.approx(10 * np.log10(1 / mse))
    with pytest.raises(ReflectmmError, match="no pixel"):
        psnr(a, b, np.zeros((16, 16), bool))
    with pytest.raises(ReflectmmError, match="shape"):
        psnr(a, b[:3])


def test_ssim_identical_is_one_and_matches_skimage_without_mask():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    a = rng.uniform(size=(40, 48, 3))
    assert ssim(a, a) == pytest.approx(1.0)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ref = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    # skimage's mean crops the (win-1)/2 border; compare against our full map cropped the same way
    val, smap = ssim(a, b, return_map=True)
    assert smap[5:-5, 5:-5].mean() == pytest.approx(ref, abs=1e-9)
    assert val < 0.95


def test_ssim_mask_region_only():
    rng = np.random.default_rng(2)
    a = rng.uniform(size=(40, 40, 3))
    b = a.copy()
    mask = np.zeros((40, 40), bool)
    mask[:, :20] = True
    b[:, 26:] = rng.uniform(size=(40, 14, 3))  # garbage beyond the window reach of the masked half
    assert ssim(a, b, mask) == pytest.approx(1.0)
    assert ssim(a, b) < 0.9


def test_encode_for_metrics():
    x = np.array([-1.0, 0.0, 0.5, 2.0])
    np.testing.assert_allclose(encode_for_metrics(x), [0, 0, 0.5 ** (1 / 1.2), 1])


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_loader_roundtrip_and_errors(tmp_path, net):
    m = LPIPS(net)
    sd = m.random_state_dict(seed=3)
    sd["scaling_layer.shift"] = torch.tensor(LPIPS.SHIFT).view(1, 3, 1, 1)
    f = tmp_path / "w.pth"
    torch.save(sd, f)
    loaded = load_lpips(f, net)
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(40, 40, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    assert loaded(a, a) == pytest.approx(0.0, abs=1e-9)
    d = loaded(a, b)
    assert d > 0 and d == pytest.approx(LPIPS(net).load_state_dict(sd)(a, b), rel=1e-6)
    # shape mismatch names the key
    bad = dict(sd)
    key = next(k for k in bad if k.startswith("lin2"))
    bad[key] = torch.zeros(1, 7, 1, 1)
    torch.save(bad, f)
    with pytest.raises(ReflectmmError, match=r"key 'lin2.model.1.weight' has shape \(1, 7, 1, 1\)"):
        load_lpips(f, net)
    # missing key named
    bad = {k: v for k, v in sd.items() if k != "net.slice1.0.weight"}
    torch.save(bad, f)
    with pytest.raises(ReflectmmError, match="missing key.*net.slice1.0.weight"):
        load_lpips(f, net)
    # not a torch file
    f.write_text("hello")
    with pytest.raises(ReflectmmError, match="cannot read LPIPS weights"):
        load_lpips(f, net)
    assert load_lpips(None) is None


def test_lpips_torchvision_and_short_keys_accepted():
    m = LPIPS("alex")
    sd = m.random_state_dict(seed=1)
    alt = {}
    for k, v in sd.items():
        if k.startswith("net."):
            alt["features." + k.split(".", 2)[2]] = v
        else:
            alt[k.replace(".model.1", "")] = v
    rng = np.random.default_rng(4)
    a, b = rng.uniform(size=(2, 36, 36, 3))
    assert LPIPS("alex").load_state_dict(alt)(a, b) == pytest.approx(m.load_state_dict(sd)(a, b), rel=1e-6)


def test_lpips_matches_hand_computation_of_first_layer():
    """lin weights only on layer 0 (ones): LPIPS = mean over pixels of the bilinearly upsampled squared distance
    of channel-normalised conv1+relu features, computed here independently with an explicit im2col."""
    m = LPIPS("alex")
    sd = m.random_state_dict(seed=7)
    for i in range(5):
        sd[f"lin{i}.model.1.weight"] = torch.zeros_like(sd[f"lin{i}.model.1.weight"])
    sd["lin0.model.1.weight"] = torch.ones(1, 64, 1, 1)
    m.load_state_dict(sd)
    rng = np.random.default_rng(5)
    H = 35
    a, b = rng.uniform(size=(2, H, H, 3))
    got = m(a, b)

    W = sd["net.slice1.0.weight"].double().numpy()
    bias = sd["net.slice1.0.bias"].double().numpy()
    shift, scale = np.array(LPIPS.SHIFT), np.array(LPIPS.SCALE)

    def feat(img):
        x = ((img * 2 - 1) - shift) / scale  # (H,W,3)
        xp = np.pad(x, ((2, 2), (2, 2), (0, 0)))
        n = (H + 4 - 11) // 4 + 1
        out = np.empty((n, n, 64))
        for i in range(n):
            for j in range(n):
                patch = xp[4 * i:4 * i + 11, 4 * j:4 * j + 11, :]  # (11,11,3)
                out[i, j] = np.einsum("hwc,ochw->o", patch, W) + bias
        out = np.maximum(out, 0)
        return out / (np.sqrt((out ** 2).sum(-1, keepdims=True)) + 1e-10)

    d = ((feat(a) - feat(b)) ** 2).sum(-1)  # (n,n)
    up = torch.nn.functional.interpolate(torch.tensor(d)[None, None], size=(H, H), mode="bilinear",
                                         align_corners=False)[0, 0].numpy()
    assert got == pytest.approx(up.mean(), rel=1e-4)

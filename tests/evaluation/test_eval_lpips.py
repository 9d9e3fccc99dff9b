"""LPIPS: safetensors loading with weights the test generates, and the distance against numpy."""
import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.face_metrics import face_region_metrics, released_protocol
from reflectmm_cli.evaluation.lpips import (layer_distances, load_lpips, lpips_image_mean, lpips_status,
                                            save_lpips_safetensors)
from reflectmm_cli.evaluation.metrics import LPIPS


def _np_conv(x, w, b, stride, pad):
    """x (C,H,W), w (O,C,k,k): plain numpy cross-correlation."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    k = w.shape[-1]
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    return np.einsum("chwij,ocij->ohw", win, w) + b[:, None, None]


def _np_pool(x, k, s):
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::s, ::s]
    return win.max(axis=(-1, -2))


def _np_alex_lpips(sd, img0, img1):
    """Independent numpy AlexNet-LPIPS (package default reduction: Σ_layers spatial mean)."""
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]
    g = lambda k: sd[k].numpy().astype(np.float64)  # noqa: E731

    def feats(img):
        h = (np.moveaxis(img, -1, 0) * 2 - 1 - shift) / scale
        out = []
        h = np.maximum(_np_conv(h, g("net.slice1.0.weight"), g("net.slice1.0.bias"), 4, 2), 0)
        out.append(h)
        h = _np_pool(h, 3, 2)
        h = np.maximum(_np_conv(h, g("net.slice2.3.weight"), g("net.slice2.3.bias"), 1, 2), 0)
        out.append(h)
        h = _np_pool(h, 3, 2)
        h = np.maximum(_np_conv(h, g("net.slice3.6.weight"), g("net.slice3.6.bias"), 1, 1), 0)
        out.append(h)
        h = np.maximum(_np_conv(h, g("net.slice4.8.weight"), g("net.slice4.8.bias"), 1, 1), 0)
        out.append(h)
        h = np.maximum(_np_conv(h, g("net.slice5.10.weight"), g("net.slice5.10.bias"), 1, 1), 0)
        out.append(h)
        return out

    total = 0.0
    for i, (a, b) in enumerate(zip(feats(img0), feats(img1))):
        a = a / (np.sqrt((a ** 2).sum(0, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b ** 2).sum(0, keepdims=True)) + 1e-10)
        w = g(f"lin{i}.model.1.weight").reshape(-1)
        total += float(np.einsum("c,chw->hw", w, (a - b) ** 2).mean())
    return total


def test_safetensors_roundtrip_and_formula_against_numpy(tmp_path):
    net = LPIPS("alex")
    sd = net.random_state_dict(seed=3)
    path = save_lpips_safetensors(sd, tmp_path / "lpips_alex.safetensors")
    model = load_lpips(path, "alex")
    assert lpips_status(model) == "on (alex)" and lpips_status(None).startswith("off")
    for k, v in sd.items():
        assert np.array_equal(model.params[k].numpy(), v.numpy())
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(2, 63, 63, 3))
    ref = _np_alex_lpips(sd, a, b)
    assert lpips_image_mean(model, a, b) == pytest.approx(ref, rel=1e-4)
    assert lpips_image_mean(model, a, a) == 0.0
    assert len(layer_distances(model, a, b)) == 5


def test_loading_errors_are_one_line(tmp_path):
    assert load_lpips(None) is None
    with pytest.raises(ReflectmmError, match="not found"):
        load_lpips(tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a safetensors file")
    with pytest.raises(ReflectmmError, match="cannot read LPIPS weights as safetensors"):
        load_lpips(bad)
    sd = LPIPS("alex").random_state_dict()
    sd.pop("lin2.model.1.weight")
    p = save_lpips_safetensors(sd, tmp_path / "partial.safetensors")
    with pytest.raises(ReflectmmError, match="lin2.model.1.weight"):
        load_lpips(p)
    sd = LPIPS("alex").random_state_dict()
    sd["scaling_layer.shift"] = np.array([0.0, 0.0, 0.0]).reshape(1, 3, 1, 1)
    p = save_lpips_safetensors(sd, tmp_path / "shift.safetensors")
    with pytest.raises(ReflectmmError, match="scaling_layer.shift"):
        load_lpips(p)


def test_a_junk_torch_file_is_refused_in_one_short_line(tmp_path):
    # torch's paragraph on the weights_only default (400 characters) was the whole reason given
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"garbage\n")
    with pytest.raises(ReflectmmError) as e:
        load_lpips(junk)
    msg = str(e.value)
    assert msg.startswith(f"{junk}: cannot read LPIPS weights as safetensors or a torch state dict (") and \
        "In PyTorch 2.6" not in msg and len(msg) - len(str(junk)) < 160, msg
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(ReflectmmError, match=r"\(EOFError: empty or truncated file\)$"):
        load_lpips(empty)


def test_lpips_enters_both_protocols(tmp_path):
    model = load_lpips(save_lpips_safetensors(LPIPS("alex").random_state_dict(1),
                                                          tmp_path / "w.safetensors"))
    rng = np.random.default_rng(1)
    t = rng.uniform(0.2, 0.8, (2, 40, 40, 3))
    p = np.clip(t + rng.normal(0, 0.1, t.shape), 0, 1)
    m = np.ones((2, 40, 40), bool)
    m[:, :5] = False
    res = face_region_metrics(p, t, m, lpips=model)
    assert res.lpips == "on (alex)" and res.per_image["lpips"].shape == (2,)
    assert np.all(res.per_image["lpips"] > 0)
    rel = released_protocol(p ** 1.2, t, m, lpips=model)
    mm = m[..., None]
    expect = np.mean([lpips_image_mean(model, np.maximum(p[i] ** 1.2, 1e-6) ** (1 / 1.2) * mm[i], t[i] * mm[i])
                      for i in range(2)])
    assert rel["lpips"] == pytest.approx(expect, rel=1e-6)


def test_one_loader_reads_safetensors_and_torch_state_dicts_alike(tmp_path):
    import torch

    sd = LPIPS("alex").random_state_dict(5)
    st = save_lpips_safetensors(sd, tmp_path / "w.safetensors")
    pt = tmp_path / "w.pth"
    torch.save({"state_dict": sd}, pt)
    rng = np.random.default_rng(1)
    a = rng.uniform(size=(48, 48, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    d1, d2 = load_lpips(st)(a, b), load_lpips(pt)(a, b)
    assert d1 > 0 and d1 == pytest.approx(d2, rel=1e-6)
    # a safetensors header whose data is cut off is an error naming the file, not a torch fallback
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(st.read_bytes()[:-1000])
    with pytest.raises(ReflectmmError, match="cut.safetensors.*safetensors|safetensors.*cut.safetensors"):
        load_lpips(cut)

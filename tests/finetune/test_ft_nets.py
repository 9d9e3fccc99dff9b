"""Encoder (zero head, trunk loading, save/load) and the identity network (generated weights, alignment)."""
import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.encoder import build_encoder, load_encoder, load_trunk, save_encoder
from reflectmm_cli.finetune.align import five_points
from reflectmm_cli.finetune.identity import ARCFACE_TEMPLATE, _similarity, build_iresnet, \
    load_identity_net


@pytest.mark.parametrize("arch", ["resnet18", "resnet34", "resnet50"])
def test_encoder_zero_head(arch):
    torch.manual_seed(0)
    enc = build_encoder(arch, 5, 4, width=8, z0=2.5).eval()
    x = torch.rand(2, 3, 32, 32)
    b, g, z = enc(x)
    assert b.shape == (2, 5) and g.shape == (2, 4) and z.shape == (2, 3)
    assert float(b.detach().abs().max()) == 0 and float(g.detach().abs().max()) == 0
    torch.testing.assert_close(z, torch.full((2, 3), 2.5))
    # torchvision's key names for the trunk
    keys = set(enc.state_dict())
    assert {"conv1.weight", "bn1.running_mean", "layer1.0.conv1.weight", "layer4.0.downsample.0.weight",
            "fc.weight"} <= keys
    if arch == "resnet50":
        assert "layer1.0.conv3.weight" in keys and enc.fc.in_features == 8 * 8 * 4


def test_load_trunk_generated_weights(tmp_path):
    torch.manual_seed(1)
    src = build_encoder("resnet18", 3, 2, width=8)
    sd = {k: v for k, v in src.state_dict().items()}
    sd["fc.weight"] = torch.ones(1000, 64)  # an ImageNet head is ignored
    sd["fc.bias"] = torch.ones(1000)
    p = tmp_path / "trunk.safetensors"
    save_file(sd, str(p))
    torch.manual_seed(2)
    dst = build_encoder("resnet18", 3, 2, width=8)
    assert not torch.equal(dst.conv1.weight, src.conv1.weight)
    load_trunk(dst, p)
    for k, v in src.state_dict().items():
        if not k.startswith("fc."):
            assert torch.equal(dst.state_dict()[k], v), k
    assert float(dst.fc.weight.detach().abs().max()) == 0
    # mismatches: other width, missing keys
    with pytest.raises(ReflectmmError, match="wrong shape") as e:
        load_trunk(build_encoder("resnet18", 3, 2, width=16), p)
    assert "trunk.safetensors" in str(e.value)
    del sd["layer2.0.conv1.weight"]
    save_file(sd, str(tmp_path / "bad.safetensors"))
    with pytest.raises(ReflectmmError, match="1 missing keys"):
        load_trunk(build_encoder("resnet18", 3, 2, width=8), tmp_path / "bad.safetensors")
    with pytest.raises(ReflectmmError, match="do not match resnet50"):
        load_trunk(build_encoder("resnet50", 3, 2, width=8), p)


def test_encoder_save_load_roundtrip(tmp_path):
    torch.manual_seed(3)
    enc = build_encoder("resnet18", 3, 2, width=8, z0=1.7)
    torch.nn.init.normal_(enc.fc.weight)
    enc.eval()
    p = save_encoder(enc, tmp_path / "e.safetensors", {"steps": 5})
    enc2, meta = load_encoder(p)
    x = torch.rand(2, 3, 32, 32)
    for a, b in zip(enc(x), enc2(x)):
        torch.testing.assert_close(a, b)
    assert meta["steps"] == 5 and meta["arch"] == "resnet18"
    (tmp_path / "junk.safetensors").write_bytes(b"nonsense")
    with pytest.raises(ReflectmmError, match="junk.safetensors"):
        load_encoder(tmp_path / "junk.safetensors")


def test_identity_net_from_generated_weights(tmp_path):
    torch.manual_seed(4)
    net = build_iresnet((1, 2, 1, 1), width=8, embedding=32).eval()
    for m in net.modules():  # non-trivial BN statistics
        if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm1d)):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    p = tmp_path / "arcface.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(p))
    idn = load_identity_net(p)
    x = torch.rand(2, 3, 112, 112) * 2 - 1
    torch.testing.assert_close(idn.net(x), net(x))
    assert set(net.state_dict()) >= {"prelu.weight", "layer2.1.bn3.running_var", "features.weight", "fc.weight"}
    # features of a 224² crop: differentiable, 32-d
    img = torch.rand(2, 224, 224, 3, requires_grad=True)
    lm = np.full((2, 68, 2), np.nan)
    f = idn.features(img, lm)
    f.sum().backward()
    assert f.shape == (2, 32) and img.grad.abs().sum() > 0
    sd = dict(net.state_dict())
    del sd["bn2.weight"]
    save_file({k: v.contiguous() for k, v in sd.items()}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(ReflectmmError, match="missing"):
        load_identity_net(tmp_path / "bad.safetensors")
    with pytest.raises(ReflectmmError, match="not found"):
        load_identity_net(tmp_path / "none.safetensors")


def test_alignment_maps_landmarks_onto_template():
    """The similarity from the 68 landmarks' five points sends them onto ArcFace's template (exact for points
    that are a similarity image of the template), and the warp samples the input where it should."""
    rng = np.random.default_rng(0)
    ang, s, t = 0.2, 1.7, np.array([30.0, 40.0])
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    pts5 = ARCFACE_TEMPLATE @ (s * R).T + t
    lm = rng.uniform(50, 150, (68, 2))
    lm[36:42] = pts5[0]
    lm[42:48] = pts5[1]
    lm[30], lm[48], lm[54] = pts5[2], pts5[3], pts5[4]
    np.testing.assert_allclose(five_points(lm), pts5)
    A = _similarity(pts5, ARCFACE_TEMPLATE)
    np.testing.assert_allclose(pts5 @ A[:, :2].T + A[:, 2], ARCFACE_TEMPLATE, atol=1e-9)
    # warp check: an image whose value is its own x pixel coordinate
    from reflectmm_cli.finetune.identity import IdentityNet

    idn = IdentityNet(build_iresnet((1, 1, 1, 1), 8, 16), "t", __import__("pathlib").Path("t"))
    S = 224
    xs = torch.arange(S, dtype=torch.float64)[None, :, None].expand(S, S, 3) / S
    out = idn.align(xs[None].clone(), lm[None])  # (1,3,112,112) in [-1,1]
    u, v = 56, 60  # an output pixel; its source x pixel is A⁻¹ (u, v)
    src = np.linalg.inv(np.vstack([A, [0, 0, 1]])) @ np.array([u, v, 1.0])
    got = (float(out[0, 0, v, u]) * 0.5 + 0.5) * S
    assert abs(got - src[0]) < 0.05


def test_budget_differences_of_two_encoders(tmp_path):
    """Two encoders' training budgets compared from their files' metas: equal budgets (the model's own settings
    aside) give nothing; a schedule, step count or training data that differ are named; a key only one encoder
    records is not a difference; a file that is not an encoder is a one-line error."""
    from reflectmm_cli.finetune.encoder import budget_differences, read_encoder_meta

    cfg = {"arch": "resnet18", "width": 8, "batch_size": 8, "epochs1": 6, "epochs2": 2, "lr1": 1e-3, "lr2": 1e-4,
           "seed": 0, "model_lr": 0.0, "w_upd": 1.0}
    data = [{"role": "data", "sha256": "a" * 64}, {"role": "model", "sha256": "b" * 64}]
    e = build_encoder("resnet18", 3, 4, width=8)
    base = save_encoder(e, tmp_path / "a.safetensors", {"config": cfg, "steps": 104, "inputs": data})
    # the model update's settings and the model itself differ: the budget is the same
    other = dict(cfg, model_lr=1e-4, w_upd=10.0)
    same = save_encoder(e, tmp_path / "b.safetensors", {"config": other, "steps": 104,
                                                         "inputs": [data[0], {"role": "model", "sha256": "c" * 64}]})
    assert budget_differences(read_encoder_meta(base), read_encoder_meta(same)) == []
    longer = save_encoder(e, tmp_path / "c.safetensors", {"config": dict(cfg, epochs1=8), "steps": 130,
                                                           "inputs": [{"role": "data", "sha256": "d" * 64}]})
    assert budget_differences(read_encoder_meta(longer), read_encoder_meta(base)) == [
        "epochs1 8 against 6", "steps 130 against 104", "training data"]
    bare = save_encoder(e, tmp_path / "d.safetensors", {})  # records no budget: nothing to compare
    assert budget_differences(read_encoder_meta(bare), read_encoder_meta(base)) == []
    save_file({"x": torch.zeros(1)}, str(tmp_path / "e.safetensors"))
    with pytest.raises(ReflectmmError, match="not a reflectmm encoder"):
        read_encoder_meta(tmp_path / "e.safetensors")

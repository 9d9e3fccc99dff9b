"""Loss functions against direct numpy computations."""
import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.finetune import losses as L


def test_photometric_l1_and_l2norm():
    rng = np.random.default_rng(0)
    p, t = rng.random((50, 3)), rng.random((50, 3))
    m = rng.random(50) > 0.4
    got = float(L.photometric(torch.tensor(p), torch.tensor(t), torch.tensor(m), "l1"))
    assert np.isclose(got, np.abs(p - t)[m].sum(1).mean())
    got = float(L.photometric(torch.tensor(p), torch.tensor(t), torch.tensor(m), "l2norm", eps=0.0))
    assert np.isclose(got, np.linalg.norm(p - t, axis=1)[m].mean())
    assert float(L.photometric(torch.tensor(p), torch.tensor(t), torch.zeros(50, dtype=bool))) == 0.0


def test_priors_and_light():
    rng = np.random.default_rng(1)
    b, g = rng.normal(size=(4, 6)), rng.normal(size=(4, 5))
    assert np.isclose(float(L.coefficient_prior(torch.tensor(b), torch.tensor(g))),
                      ((b ** 2).sum(1) + (g ** 2).sum(1)).mean())
    sh = rng.normal(size=(4, 3, 9))
    ref = np.mean([np.mean([(sh[i, c, j] - sh[i, :, j].mean()) ** 2 for c in range(3)]) for i in range(4)
                   for j in range(9)])
    assert np.isclose(float(L.light_monochrome(torch.tensor(sh))), ref)
    grey = np.repeat(sh[:, :1], 3, 1)
    assert float(L.light_monochrome(torch.tensor(grey))) < 1e-30
    cur = {"a": torch.tensor(rng.normal(size=(5, 3))), "b": torch.tensor(rng.normal(size=(2, 5, 3)))}
    ini = {k: v + 0.5 for k, v in cur.items()}
    assert np.isclose(float(L.model_update_l1(cur, ini)), 1.0)


def test_basis_norm_ortho():
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(60, 4)))
    B = torch.tensor(q.T.reshape(4, 20, 3))
    W = torch.tensor(rng.normal(size=(4, 20, 3)))
    n, o = L.basis_norm_ortho(B, B, W, W, torch.ones(4, dtype=torch.float64))
    assert float(n) == 0 and float(o) < 1e-12
    n, o = L.basis_norm_ortho(2 * B, B, W, W, torch.ones(4, dtype=torch.float64))
    assert np.isclose(float(n), 3.0) and np.isclose(float(o), (3 * 4) / 16)


@given(st.floats(1e-6, 1e3), st.integers(1, 8))
def test_perceptual_range_and_scale_invariance(scale, seed):
    rng = np.random.default_rng(seed)
    a = torch.tensor(rng.normal(size=(3, 16)))
    v = float(L.perceptual(a * scale, a))
    assert abs(v) < 1e-9
    w = float(L.perceptual(a, -a))
    assert np.isclose(w, 2.0)


def test_model_update_l1_value_and_gradient_on_a_model_sized_part():
    # the value against a float64 sum (a single float32 reduction over millions of elements is off by ~1e-3),
    # the gradient against the closed form sign(x − x₀)/N, with exact ties giving 0
    torch.manual_seed(0)
    x = torch.randn(40, 35000, 3, requires_grad=True)
    x0 = x.detach() + 0.01 * torch.randn(40, 35000, 3)
    x0[0, :100] = x.detach()[0, :100]
    v = L.model_update_l1({"b": x}, {"b": x0})
    ref = (x.detach().double() - x0.double()).abs().mean()
    assert abs(float(v.detach()) / float(ref) - 1) < 1e-6
    (3.0 * v).backward()
    assert torch.equal(x.grad, 3.0 * torch.sign(x.detach() - x0) / x.numel())
    assert (x.grad[0, :100] == 0).all()


def test_model_update_l1_gradient_adds_to_an_existing_one_and_refuses_a_second_backward():
    # the backward hands its sign buffer over as the gradient: a leaf that already has a gradient (the shading's)
    # gets the sum, and the same graph cannot be differentiated twice
    torch.manual_seed(1)
    x = torch.randn(5, 7, 3, requires_grad=True)
    x0 = x.detach() + 0.1 * torch.randn(5, 7, 3)
    (2.0 * x).sum().backward()
    v = L.model_update_l1({"b": x}, {"b": x0})
    v.backward(retain_graph=True)
    assert torch.allclose(x.grad, 2.0 + torch.sign(x.detach() - x0) / x.numel())
    with pytest.raises(RuntimeError, match="twice"):
        v.backward()

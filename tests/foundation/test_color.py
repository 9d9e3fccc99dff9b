"""reflectmm_cli.color: the sRGB and gamma transfers and the display encoding, numpy and torch."""
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.color import (SRGB_DECODE_KNEE_EXACT, auto_exposure, encode_display, gamma_to_linear,
                                 linear_to_gamma, linear_to_srgb, srgb_to_linear, to_uint8)
from reflectmm_cli.errors import ReflectmmError


# IEC 61966-2-1:1999 (sRGB), written out here with the standard's published constants, one scalar at a time.
def iec_oetf(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * math.pow(x, 1.0 / 2.4) - 0.055


def iec_eotf(v: float) -> float:
    return v / 12.92 if v <= 0.04045 else math.pow((v + 0.055) / 1.055, 2.4)


GRID = np.concatenate([np.linspace(0.0, 1.0, 1001), np.geomspace(1e-6, 1.0, 200),
                       [0.0031308, np.nextafter(0.0031308, 1), 0.04045, np.nextafter(0.04045, 1)]])
unit = st.floats(0.0, 1.0, allow_nan=False)
extended = st.floats(-0.1, 1.5, allow_nan=False)
gammas = st.floats(0.2, 5.0, allow_nan=False)


def test_srgb_matches_the_standard_formula():
    got = linear_to_srgb(GRID)
    want = np.array([iec_oetf(float(x)) for x in GRID])
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    got = srgb_to_linear(GRID)
    want = np.array([iec_eotf(float(v)) for v in GRID])
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    # a few published reference values: mid grey, the knees, white
    assert linear_to_srgb(np.float64(0.18)) == pytest.approx(0.4613561295, abs=1e-9)
    assert linear_to_srgb(np.float64(1.0)) == pytest.approx(1.0, abs=1e-15)
    assert linear_to_srgb(np.float64(0.0031308)) == pytest.approx(0.040449936, abs=1e-15)
    assert srgb_to_linear(np.float64(0.04045)) == pytest.approx(0.04045 / 12.92, abs=1e-15)


def test_srgb_decode_knee_choice():
    # The two thresholds select a different branch only inside (12.92·0.0031308, 0.04045]; the values there
    # differ by the standard's tiny jump.
    v = np.array([0.0404, SRGB_DECODE_KNEE_EXACT, np.nextafter(SRGB_DECODE_KNEE_EXACT, 1), 0.04045, 0.0405])
    a, b = srgb_to_linear(v), srgb_to_linear(v, threshold=SRGB_DECODE_KNEE_EXACT)
    assert np.array_equal(a[[0, 1, 4]], b[[0, 1, 4]])
    assert not np.array_equal(a[2:4], b[2:4])
    assert np.abs(a - b).max() < 3e-9


def test_gamma_matches_the_power_law():
    for g in (1.2, 2.2, 0.5, 3.0):
        np.testing.assert_allclose(linear_to_gamma(GRID, g), [math.pow(float(x), 1.0 / g) for x in GRID],
                                   rtol=1e-14, atol=0)
        np.testing.assert_allclose(gamma_to_linear(GRID, g), [math.pow(float(x), g) for x in GRID],
                                   rtol=1e-14, atol=0)


def test_continuity_at_the_knees():
    k = 0.0031308
    lo, hi = linear_to_srgb(np.array([k, np.nextafter(k, 1)]))
    assert abs(hi - lo) < 3e-8          # the standard's own mismatch of its two OETF segments: 2.85e-8
    for t in (0.04045, SRGB_DECODE_KNEE_EXACT):
        lo, hi = srgb_to_linear(np.array([t, np.nextafter(t, 1)]), threshold=t)
        assert 0 <= hi - lo < 3e-9


@given(unit)
def test_srgb_round_trip(x):
    x = np.float64(x)
    assert srgb_to_linear(linear_to_srgb(x)) == pytest.approx(x, abs=3e-9, rel=1e-12)
    assert linear_to_srgb(srgb_to_linear(x)) == pytest.approx(x, abs=4e-8, rel=1e-12)


@given(unit, gammas)
def test_gamma_round_trip(x, g):
    x = np.float64(x)
    assert gamma_to_linear(linear_to_gamma(x, g), g) == pytest.approx(x, abs=1e-14, rel=1e-12)
    assert linear_to_gamma(gamma_to_linear(x, g), g) == pytest.approx(x, abs=1e-12, rel=1e-12)


@given(extended, extended)
def test_srgb_monotone(a, b):
    a, b = np.float64(min(a, b)), np.float64(max(a, b))
    # non-decreasing up to the OETF's 2.85e-8 drop at the knee
    assert linear_to_srgb(b) >= linear_to_srgb(a) - 3e-8
    if a > 0.0031308 or b <= 0.0031308:            # same segment: strictly monotone
        assert linear_to_srgb(b) >= linear_to_srgb(a)
    assert srgb_to_linear(b) >= srgb_to_linear(a)
    assert srgb_to_linear(b, threshold=SRGB_DECODE_KNEE_EXACT) >= srgb_to_linear(a, threshold=SRGB_DECODE_KNEE_EXACT)


@given(st.floats(0.0, 4.0, allow_nan=False), st.floats(0.0, 4.0, allow_nan=False), gammas)
def test_gamma_and_display_monotone(a, b, g):
    a, b = np.float64(min(a, b)), np.float64(max(a, b))
    assert linear_to_gamma(b, g) >= linear_to_gamma(a, g)
    assert gamma_to_linear(b, g) >= gamma_to_linear(a, g)
    for t in ("gamma", "gamma1.2", "linear"):
        assert encode_display(b, t) >= encode_display(a, t)


@pytest.mark.parametrize("dt_np, dt_t, rtol", [(np.float64, torch.float64, 1e-13), (np.float32, torch.float32, 2e-6)])
def test_numpy_and_torch_agree(dt_np, dt_t, rtol):
    x = np.random.default_rng(0).uniform(-0.2, 1.3, (7, 5, 3)).astype(dt_np)
    t = torch.from_numpy(x).to(dt_t)
    pairs = [(linear_to_srgb, {}), (srgb_to_linear, {}), (srgb_to_linear, {"threshold": SRGB_DECODE_KNEE_EXACT})]
    for f, kw in pairs:
        a, b = f(x, **kw), f(t, **kw)
        assert isinstance(b, torch.Tensor) and b.dtype == dt_t and a.dtype == dt_np
        np.testing.assert_allclose(b.numpy(), a, rtol=rtol, atol=1e-7 if dt_np == np.float32 else 1e-15)
    xp = np.abs(x)
    for g in (1.2, 2.2):
        np.testing.assert_allclose(linear_to_gamma(torch.from_numpy(xp), g).numpy(), linear_to_gamma(xp, g), rtol=rtol)
        np.testing.assert_allclose(gamma_to_linear(torch.from_numpy(xp), g).numpy(), gamma_to_linear(xp, g), rtol=rtol)
    for tr in ("srgb", "gamma", "gamma1.2", "linear"):
        for exp in (None, 0.7, "auto"):
            a, b = encode_display(x, tr, exp), encode_display(t, tr, exp)
            np.testing.assert_allclose(b.numpy(), a, rtol=rtol, atol=1e-7 if dt_np == np.float32 else 1e-15)
        a, b = encode_display(x, tr, uint8=True), encode_display(t, tr, uint8=True)
        assert b.dtype == torch.uint8 and a.dtype == np.uint8
        assert np.abs(b.numpy().astype(int) - a.astype(int)).max() <= (0 if dt_np == np.float64 else 1)


def test_torch_gradients_finite_and_right():
    x = torch.tensor([0.0, 1e-4, 0.0031308, 0.0031309, 0.2, 0.9, 1.0], dtype=torch.float64, requires_grad=True)
    linear_to_srgb(x).sum().backward()
    g = x.grad.numpy()
    assert np.isfinite(g).all()
    xs = x.detach().numpy()
    with np.errstate(divide="ignore"):
        want = np.where(xs <= 0.0031308, 12.92, 1.055 / 2.4 * xs ** (1 / 2.4 - 1))
    np.testing.assert_allclose(g, want, rtol=1e-12)
    v = torch.tensor([0.0, 0.01, 0.04045, 0.0405, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    srgb_to_linear(v).sum().backward()
    vs = v.detach().numpy()
    want = np.where(vs <= 0.04045, 1 / 12.92, 2.4 / 1.055 * ((vs + 0.055) / 1.055) ** 1.4)
    np.testing.assert_allclose(v.grad.numpy(), want, rtol=1e-12)
    y = torch.tensor([0.01, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    linear_to_gamma(y, 2.2).sum().backward()
    np.testing.assert_allclose(y.grad.numpy(), (1 / 2.2) * y.detach().numpy() ** (1 / 2.2 - 1), rtol=1e-12)
    z = torch.tensor([-0.5, 0.3, 2.0, float("nan")], dtype=torch.float64, requires_grad=True)
    encode_display(z, "srgb").sum().backward()
    assert torch.isfinite(z.grad).all()


def test_display_steps():
    x = np.array([[-1.0, 0.0, 0.25], [0.5, 2.0, np.nan], [np.inf, -np.inf, 1.0]])
    y = encode_display(x, "srgb")
    assert y.dtype == np.float64 and y[1, 2] == 0.0 and y[2, 0] == pytest.approx(1.0, abs=1e-15) and y[2, 1] == 0.0
    np.testing.assert_array_equal(y, linear_to_srgb(np.clip(np.nan_to_num(x), 0, 1)))
    assert np.isnan(encode_display(x, "gamma", nan_to_num=False)[1, 2])
    np.testing.assert_array_equal(encode_display(x, "gamma", gamma=1.2), encode_display(x, "gamma1.2"))
    np.testing.assert_array_equal(encode_display(x, "linear", 0.5), np.clip(np.nan_to_num(x) * 0.5, 0, 1))
    # dtypes: kept, or converted first; integers in float64
    assert encode_display(x.astype(np.float32), "srgb").dtype == np.float32
    assert encode_display(x.astype(np.float32), "srgb", dtype=np.float64).dtype == np.float64
    assert encode_display(np.array([0, 1, 2]), "gamma").dtype == np.float64
    # 8-bit codes round half up
    codes = to_uint8(np.array([0.0, 0.4 / 255, 0.6 / 255, 1.4 / 255, 1.6 / 255, 1.0]))
    assert codes.dtype == np.uint8 and np.array_equal(codes, [0, 0, 1, 1, 2, 255])
    lin = np.linspace(0, 1, 23)
    assert np.array_equal(encode_display(lin, "gamma1.2", uint8=True), np.floor(lin ** (1 / 1.2) * 255 + 0.5))


def test_auto_exposure():
    img = np.zeros((20, 20, 3))
    img[:10] = np.linspace(0.1, 4.0, 200).reshape(10, 20, 1) * [1.0, 0.5, 0.25]
    e = auto_exposure(img)
    assert e == pytest.approx(0.9 / np.percentile(np.linspace(0.1, 4.0, 200), 99.5))
    np.testing.assert_array_equal(encode_display(img, "linear", "auto"), np.clip(img * e, 0, 1))
    assert auto_exposure(np.zeros((4, 4, 3))) == 0.9
    assert auto_exposure(torch.from_numpy(img)) == e


@pytest.mark.parametrize("call, match", [
    (lambda: linear_to_srgb(np.array(["a", "b"])), "linear_to_srgb: expected a real numeric array"),
    (lambda: srgb_to_linear(np.array([1 + 2j])), "srgb_to_linear: expected a real numeric array"),
    (lambda: linear_to_srgb(torch.tensor([1 + 2j])), "linear_to_srgb: expected a real image"),
    (lambda: srgb_to_linear([0.5], threshold=0.5), "threshold must be a float near 0.04045"),
    (lambda: linear_to_gamma([0.5], 0), "gamma must be a finite number > 0"),
    (lambda: gamma_to_linear([0.5], float("nan")), "gamma must be a finite number > 0"),
    (lambda: gamma_to_linear([0.5], "x"), "gamma must be a positive number"),
    (lambda: encode_display([0.5], "sRGB2"), "unknown display transfer 'sRGB2'"),
    (lambda: encode_display([0.5], "srgb", gamma=2.0), "gamma= is only for transfer 'gamma'"),
    (lambda: encode_display([0.5], "gamma", gamma=-1), "gamma must be a finite number > 0"),
    (lambda: encode_display([0.5], "srgb", "bright"), "exposure must be a number, None or 'auto'"),
    (lambda: encode_display([0.5], "srgb", -2.0), "exposure must be a finite number ≥ 0"),
    (lambda: encode_display(np.float64(0.5), "srgb", "auto"), "auto_exposure: expected an image"),
])
def test_bad_input_one_line_error(call, match):
    with pytest.raises(ReflectmmError, match=match) as e:
        call()
    assert "\n" not in str(e.value)

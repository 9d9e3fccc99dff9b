"""Two-lobe skin (``skin="two-lobe"``): the mix's albedo against quadrature, the BRDF, parameter ranges, and that
the single-lobe skin is untouched."""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import integrate

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.synth.ggx import (fit_lobes_to_ggx, ggx_brdf, ggx_directional, ggx_specular_albedo,
                                     ggx_two_lobe_directional)
from reflectmm_cli.synth.multipie import SynthConfig
from reflectmm_cli.synth.skin import (BROAD_ALPHA_RANGE, BROAD_SCALE_RANGE, BROAD_WEIGHT_RANGE, LOBE_MIX_RANGE,
                                      SHARP_ALPHA_RANGE, SHARP_SCALE_RANGE, sample_skin_params,
                                      sample_two_lobe_params, skin_maps, two_lobe_params_for,
                                      two_lobe_specular_albedo)
from reflectmm_cli.synth.wild import WildConfig

S = 64


def _texel(uv):
    return int(round(uv[1] * S - 0.5)), int(round(uv[0] * S - 0.5))


@pytest.fixture(autouse=True)
def _layout(landmark_uv):
    """The template landmark layout (tests/synth/conftest.py) and its nose-tip, cheek and forehead texels."""
    global LM, NOSE, CHEEK, FOREHEAD
    LM = landmark_uv
    NOSE, CHEEK = _texel(LM[30]), _texel(0.5 * LM[36:42].mean(0) + 0.5 * LM[48])
    FOREHEAD = _texel((LM[19] + LM[24]) / 2 - np.array([0, 0.12]))


def _maps(tone=0.3, seed=4, skin="two-lobe"):
    return skin_maps(LM, sample_skin_params(np.random.default_rng(seed), tone), S, skin=skin)


def _albedo_by_quadrature(rho, a_s, a_b, m, f0=0.028):
    """∫ f(l, v = n) cos θ_l dω_l of ρ((1 − m) GGX(α_s) + m GGX(α_b)), each lobe from ``ggx_brdf`` (the textbook
    BRDF, divided by n·l n·v — not the tabulated shading), by adaptive quadrature in θ (f does not depend on φ
    when v = n)."""
    n = np.array([0.0, 0.0, 1.0])

    def f(theta, alpha):
        l = np.array([math.sin(theta), 0.0, math.cos(theta)])
        return float(ggx_brdf(n, l, n, alpha, 1.0, f0=f0)) * math.cos(theta) * math.sin(theta) * 2 * math.pi

    def lobe(alpha):
        pts = [min(2 * math.atan(k * alpha), 1.5) for k in (0.5, 1, 2, 4)]
        return integrate.quad(f, 0.0, math.pi / 2, args=(alpha,), points=pts, limit=400, epsabs=0, epsrel=1e-9)[0]

    return rho * ((1 - m) * lobe(a_s) + m * lobe(a_b))


def test_mix_albedo_at_normal_view_matches_quadrature():
    mp = _maps()
    assert mp.skin == "two-lobe"
    for t in (NOSE, CHEEK, FOREHEAD):
        rho, a_s, a_b, m = (float(x[t]) for x in (mp.spec_intensity, mp.roughness, mp.roughness_broad, mp.lobe_mix))
        ref = _albedo_by_quadrature(rho, a_s, a_b, m)
        # float32 map; the closed form interpolates the GGX albedo table in log α (≈1e-5 relative)
        assert float(mp.spec_albedo[t]) == pytest.approx(ref, rel=3e-5)
        assert float(two_lobe_specular_albedo(a_s, a_b, m, rho)) == pytest.approx(ref, rel=2e-5)
        # a wrong mix (the lobes' weights swapped) is far off: the test can tell the lobes apart
        assert abs(_albedo_by_quadrature(rho, a_s, a_b, 1 - m) / ref - 1) > 1e-3


def test_mix_keeps_the_single_lobe_specular_albedo_and_changes_the_shape():
    two, one = _maps(), _maps(skin="single")
    np.testing.assert_allclose(two.spec_albedo, one.spec_albedo, rtol=1e-5)
    np.testing.assert_array_equal(two.albedo, one.albedo)
    # the single-lobe width lies between the two lobes', and the 3-lobe reference differs (a different shape)
    assert np.all(two.roughness <= one.roughness + 1e-7) and np.all(two.roughness_broad >= one.roughness - 1e-7)
    assert np.abs(two.weights - one.weights).max() > 0.2 * one.weights.max()


def test_two_lobe_shading_is_the_weighted_sum_of_two_ggx_brdfs():
    rng = np.random.default_rng(1)
    n = np.tile([0.0, 0.0, 1.0], (200, 1))
    l = rng.normal(size=(200, 3)) + [0, 0, 1.5]
    v = rng.normal(size=(200, 3)) + [0, 0, 1.5]
    c = rng.uniform(0.1, 0.8, (200, 3))
    rho, a_s, a_b, m = rng.uniform(0.5, 3, 200), rng.uniform(0.1, 0.4, 200), rng.uniform(0.4, 1, 200), \
        rng.uniform(0, 1, 200)
    E = rng.uniform(0.5, 3, 200)[:, None] * np.ones(3)
    total, dif, spec = ggx_two_lobe_directional(c, rho, a_s, a_b, m, n, l, v, E, return_parts=True)
    # BRDF: the weighted lobes plus Lambert (ggx_brdf with ρ = 0 and an albedo is c/π where n·l, n·v > 0)
    f = ((1 - m) * ggx_brdf(n, l, v, a_s, rho) + m * ggx_brdf(n, l, v, a_b, rho))[:, None] \
        + ggx_brdf(n, l, v, 1.0, 0.0, albedo=c)
    nl = np.clip((n * l).sum(1) / np.linalg.norm(l, axis=1), 0, None)
    np.testing.assert_allclose(total, E * f * nl[:, None], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dif, ggx_directional(c, 0.0, 0.5, n, l, v, E), rtol=1e-12)
    assert spec.max() > 0


def test_regions_sharper_and_oilier_on_the_t_zone():
    for seed in range(4):
        mp = _maps(seed=seed)
        # more of the sharp lobe on the nose tip and forehead than on the cheeks
        assert mp.lobe_mix[NOSE] < mp.lobe_mix[FOREHEAD] < mp.lobe_mix[CHEEK]
        assert mp.roughness[NOSE] < mp.roughness[CHEEK] and mp.roughness_broad[NOSE] < mp.roughness_broad[CHEEK]
        assert mp.spec_albedo[NOSE] > 1.5 * mp.spec_albedo[CHEEK]


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), tone=st.floats(0, 1))
def test_parameter_ranges(seed, tone):
    p = sample_skin_params(np.random.default_rng(seed), tone)
    tl = two_lobe_params_for(p)
    assert SHARP_SCALE_RANGE[0] <= tl.sharp_scale <= SHARP_SCALE_RANGE[1]
    assert BROAD_SCALE_RANGE[0] <= tl.broad_scale <= BROAD_SCALE_RANGE[1]
    assert BROAD_WEIGHT_RANGE[0] <= tl.broad_weight <= BROAD_WEIGHT_RANGE[1]
    assert two_lobe_params_for(p) == tl  # deterministic in the identity's skin parameters
    mp = skin_maps(LM, p, 32, skin="two-lobe")
    assert mp.two_lobe == tl
    for a, (lo, hi) in ((mp.roughness, SHARP_ALPHA_RANGE), (mp.roughness_broad, BROAD_ALPHA_RANGE),
                        (mp.lobe_mix, LOBE_MIX_RANGE)):
        assert a.dtype == np.float32 and np.all(np.isfinite(a))
        assert a.min() >= np.float32(lo) and a.max() <= np.float32(hi)
    assert np.all(mp.roughness < mp.roughness_broad)
    assert mp.spec_intensity.min() > 0 and mp.weights.min() >= 0
    # the 3-lobe reference is the weighted sum of the two lobes' fits
    m = mp.lobe_mix.astype(np.float64)[..., None]
    w = (1 - m) * fit_lobes_to_ggx(mp.roughness, mp.spec_intensity) + m * fit_lobes_to_ggx(mp.roughness_broad,
                                                                                           mp.spec_intensity)
    np.testing.assert_allclose(np.moveaxis(mp.weights, 0, -1), w, rtol=1e-4, atol=1e-7)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**63 - 1))
def test_two_lobe_draws_stay_in_their_ranges(seed):
    tl = sample_two_lobe_params(np.random.default_rng(seed))
    assert SHARP_SCALE_RANGE[0] <= tl.sharp_scale <= SHARP_SCALE_RANGE[1]
    assert BROAD_SCALE_RANGE[0] <= tl.broad_scale <= BROAD_SCALE_RANGE[1]
    assert BROAD_WEIGHT_RANGE[0] <= tl.broad_weight <= BROAD_WEIGHT_RANGE[1]
    # the broad lobe is wider than the sharp one for any identity, before clipping
    assert tl.broad_scale > 2 * tl.sharp_scale


def test_single_is_the_default_and_is_not_recorded():
    one = _maps(skin="single")
    default = skin_maps(LM, sample_skin_params(np.random.default_rng(4), 0.3), S)
    for k in ("albedo", "roughness", "spec_intensity", "spec_albedo", "weights"):
        np.testing.assert_array_equal(getattr(one, k), getattr(default, k))
    assert one.lobe_mix is None and one.roughness_broad is None and one.two_lobe is None
    np.testing.assert_allclose(one.spec_albedo, ggx_specular_albedo(one.roughness, one.spec_intensity), rtol=1e-5)
    assert "skin" not in SynthConfig().to_params() and SynthConfig(skin="two-lobe").to_params()["skin"] == "two-lobe"
    assert "skin" not in WildConfig().to_params() and WildConfig(skin="two-lobe").to_params()["skin"] == "two-lobe"
    for bad in (lambda: SynthConfig(skin="three"), lambda: WildConfig(skin="dual"),
                lambda: skin_maps(LM, sample_skin_params(np.random.default_rng(0)), S, skin="x")):
        with pytest.raises(ReflectmmError, match="skin"):
            bad()

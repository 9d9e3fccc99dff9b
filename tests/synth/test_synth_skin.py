"""Skin reflectance maps: regions land where the landmarks say, physiological ordering, GGX consistency."""
import numpy as np
import pytest

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.synth.ggx import fit_lobes_to_ggx, ggx_specular_albedo
from reflectmm_cli.synth.skin import SkinParams, region_masks, sample_skin_params, skin_maps

S = 96


def _texel(uv):
    """Texel (row, col) of a UV point (pixel-centre convention of docs/pipeline.md)."""
    return int(round(uv[1] * S - 0.5)), int(round(uv[0] * S - 0.5))


def _params(tone=0.2, seed=3):
    return sample_skin_params(np.random.default_rng(seed), tone)


def test_regions_follow_landmarks(landmark_uv):
    R = region_masks(landmark_uv, S)
    mouth = landmark_uv[48:60].mean(0)
    assert R["lips"][_texel(mouth)] > 0.9
    assert R["lips"][_texel(landmark_uv[30])] < 0.05
    assert R["nose_tip"][_texel(landmark_uv[30])] > 0.8
    assert R["brows"][_texel(landmark_uv[19])] > 0.5 and R["brows"][_texel(landmark_uv[24])] > 0.5
    assert R["eyes"][_texel(landmark_uv[36:42].mean(0))] > 0.8
    above_brows = (landmark_uv[19] + landmark_uv[24]) / 2 - np.array([0, 0.12])
    assert R["forehead"][_texel(above_brows)] > 0.8
    assert R["forehead"][_texel(landmark_uv[8])] == 0
    cheek = 0.5 * landmark_uv[36:42].mean(0) + 0.5 * landmark_uv[48]
    assert R["cheeks"][_texel(cheek)] > 0.5


def test_maps_shapes_ranges_and_ggx_consistency(landmark_uv):
    m = skin_maps(landmark_uv, _params(), S)
    assert m.albedo.shape == (3, S, S) and m.weights.shape == (3, S, S)
    for a in (m.roughness, m.spec_intensity, m.spec_albedo):
        assert a.shape == (S, S) and np.all(np.isfinite(a)) and a.min() > 0
    assert 0 < m.albedo.min() and m.albedo.max() < 1
    assert m.weights.min() >= 0
    np.testing.assert_allclose(m.spec_albedo, ggx_specular_albedo(m.roughness, m.spec_intensity), rtol=1e-5)
    np.testing.assert_allclose(np.moveaxis(m.weights, 0, -1), fit_lobes_to_ggx(m.roughness, m.spec_intensity),
                               rtol=1e-4, atol=1e-7)


def test_spatial_pattern_like_skin(landmark_uv):
    m = skin_maps(landmark_uv, _params(), S)
    nose, cheek = _texel(landmark_uv[30]), _texel(0.5 * landmark_uv[36:42].mean(0) + 0.5 * landmark_uv[48])
    forehead = _texel((landmark_uv[19] + landmark_uv[24]) / 2 - np.array([0, 0.12]))
    lips, brow = _texel(landmark_uv[48:60].mean(0)), _texel(landmark_uv[19])
    # sharp and strong highlights on the nose tip and forehead, broad and weak on the cheeks
    assert m.roughness[nose] < m.roughness[forehead] < m.roughness[cheek]
    assert m.spec_intensity[nose] > m.spec_intensity[forehead] > m.spec_intensity[cheek]
    assert m.spec_albedo[nose] > 1.5 * m.spec_albedo[cheek]
    # redder lips and cheeks, darker brows
    redness = m.albedo[0] / m.albedo[1]
    assert redness[lips] > redness[cheek] > redness[forehead]
    lum = m.albedo.mean(0)
    assert lum[brow] < 0.75 * lum[forehead]


def test_skin_tones_span_light_to_dark(landmark_uv):
    forehead = _texel((landmark_uv[19] + landmark_uv[24]) / 2 - np.array([0, 0.12]))
    light = skin_maps(landmark_uv, _params(0.0), S).albedo[:, forehead[0], forehead[1]]
    dark = skin_maps(landmark_uv, _params(1.0), S).albedo[:, forehead[0], forehead[1]]
    assert 0.45 < light[0] < 0.8 and light[0] > light[1] > 0.25 and light[2] > 0.2
    assert dark[0] < 0.25 and dark[2] < 0.08
    assert np.all(light > 2 * dark)
    # red > green > blue for every tone (linear skin reflectance)
    for a in (light, dark):
        assert a[0] > a[1] > a[2] * 0.95


def test_deterministic_in_params(landmark_uv):
    p = SkinParams(0.1, 0.08, 1.0, 1.0, 0.4, seed=11)
    a, b = skin_maps(landmark_uv, p, S), skin_maps(landmark_uv, p, S)
    assert np.array_equal(a.albedo, b.albedo) and np.array_equal(a.roughness, b.roughness)
    c = skin_maps(landmark_uv, SkinParams(0.1, 0.08, 1.0, 1.0, 0.4, seed=12), S)
    assert not np.array_equal(a.albedo, c.albedo)


def test_bad_landmarks_refused(landmark_uv):
    with pytest.raises(ReflectmmError, match="68 finite landmark"):
        region_masks(landmark_uv[:60], S)
    with pytest.raises(ReflectmmError, match="degenerate"):
        region_masks(np.full((68, 2), 0.5), S)


def test_model_mode_adds_a_broad_lobe_and_spec_albedo_is_the_weight_sum(landmark_uv):
    g = skin_maps(landmark_uv, _params(), S)
    m = skin_maps(landmark_uv, _params(), S, brdf="model")
    np.testing.assert_array_equal(g.albedo, m.albedo)
    np.testing.assert_array_equal(g.weights[1:], m.weights[1:])
    assert np.all(m.weights[0] >= g.weights[0] + 0.005)
    np.testing.assert_allclose(m.spec_albedo, m.weights.sum(0), rtol=1e-6)
    with pytest.raises(ReflectmmError, match="brdf"):
        skin_maps(landmark_uv, _params(), S, brdf="phong")

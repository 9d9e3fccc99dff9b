"""Procedural HDR environment maps: finite, HDR, deterministic, resolution-consistent, readable EXR."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_exr, read_image
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import equirect_directions, equirect_weights, project_envmap
from reflectmm_cli.synth.envmaps import ENVMAP_KINDS, make_envmap


@pytest.mark.parametrize("index", range(8))
def test_maps_are_finite_nonnegative_and_shaped(index):
    img, kind = make_envmap(3, index, 128)
    assert kind == ENVMAP_KINDS[index % 4]
    assert img.shape == (64, 128, 3) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and img.min() >= 0 and img.max() > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dynamic_range_like_real_captures(seed):
    ranges = {}
    for i, kind in enumerate(ENVMAP_KINDS):
        img, _ = make_envmap(seed, i, 512)
        lum = img.mean(-1)
        ranges[kind] = lum.max() / np.percentile(lum, 1)
    assert 1e4 <= ranges["sky"] <= 1e6          # the sun
    assert 1e3 <= ranges["indoor"] <= 1e5       # lamps vs walls
    assert ranges["colored"] >= 1e2
    assert 3 <= ranges["overcast"] <= 1e3       # overcast skies are low-contrast


def test_sun_dominates_sky_irradiance_and_is_above_horizon():
    img, _ = make_envmap(0, 0, 512)
    d = equirect_directions(512, 256)
    lum = img.mean(-1)
    i = np.unravel_index(np.argmax(lum), lum.shape)
    assert d[i][1] > 0
    # irradiance on a plane facing the sun: the sun disc contributes several times the sky's share
    w = equirect_weights(512, 256)[:, None] * np.ones((1, 512))
    sun = d[i]
    cos = np.clip(d @ sun, 0, None)
    disc = np.arccos(np.clip(d @ sun, -1, 1)) < np.radians(1.5)
    e_sun = (lum * cos * w)[disc].sum()
    e_rest = (lum * cos * w)[~disc].sum()
    assert 1.5 < e_sun / e_rest < 50


@pytest.mark.parametrize("index", [0, 2, 3])
def test_light_sources_keep_their_energy_at_low_resolution(index):
    hi = project_envmap(make_envmap(5, index, 1024)[0], 1)
    lo = project_envmap(make_envmap(5, index, 64)[0], 1)
    np.testing.assert_allclose(lo[:, 0], hi[:, 0], rtol=0.03)


def test_deterministic_and_seed_dependent():
    a, _ = make_envmap(7, 2, 128)
    b, _ = make_envmap(7, 2, 128)
    c, _ = make_envmap(8, 2, 128)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_bad_width_is_refused():
    with pytest.raises(ReflectmmError, match="width"):
        make_envmap(0, 0, 63)


def test_cli_writes_readable_exr_and_is_byte_identical(cli, tmp_path):
    r = cli("synth", "envmaps", "--count", "5", "--width", "64", "--seed", "4", "--out", tmp_path / "a")
    assert r.exit_code == 0, r.output
    out = [ln for ln in r.stdout.splitlines() if ln]
    names = sorted(p.split("/")[-1] for p in out)
    assert names == ["contact_sheet.png", "env_0000_sky.exr", "env_0001_overcast.exr", "env_0002_indoor.exr",
                     "env_0003_colored.exr", "env_0004_sky.exr"]
    img = read_image(tmp_path / "a" / "env_0003_colored.exr")
    np.testing.assert_array_equal(img, make_envmap(4, 3, 64)[0])  # R,G,B order, float32 exact
    ch, meta = read_exr(tmp_path / "a" / "env_0003_colored.exr")
    assert sorted(ch) == ["B", "G", "R"] and meta["envmap"]["kind"] == "colored"
    assert meta["schema"] == "reflectmm.envmap/1"
    r2 = cli("synth", "envmaps", "--count", "5", "--width", "64", "--seed", "4", "--out", tmp_path / "b")
    assert r2.exit_code == 0
    for n in names:
        assert (tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes(), n

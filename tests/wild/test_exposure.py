"""normalize_exposure: the brightening applied before landmark detection (no dlib needed)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from reflectmm_cli.detection import detect_landmarks, normalize_exposure
from reflectmm_cli.errors import ReflectmmError


def test_the_percentile_maps_to_255():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 40, size=(50, 60, 3)).astype(np.uint8)
    q = np.percentile(img.max(axis=2), 99.5)
    out = normalize_exposure(img)
    gain = 255.0 / q
    assert np.array_equal(out, np.clip(np.rint(img * gain), 0, 255).astype(np.uint8))
    assert np.isclose(np.percentile(out.max(axis=2), 99.5), 255, atol=1)


def test_well_exposed_and_black_images():
    img = np.full((10, 10, 3), 120, np.uint8)
    img[0, :3] = 255                                                # 3 % of the pixels saturated
    assert np.array_equal(normalize_exposure(img), img)           # percentile ≥ 255 / gain ≤ 1: unchanged
    black = np.zeros((10, 10, 3), np.uint8)
    black[5, 5] = 1
    assert normalize_exposure(black, percentile=100).max() == 64   # gain capped at 64


@settings(max_examples=60, deadline=None)
@given(arrays(np.uint8, st.tuples(st.integers(1, 12), st.integers(1, 12), st.just(3))),
       st.floats(50.0, 100.0))
def test_brightening_keeps_order_and_never_darkens(img, pct):
    out = normalize_exposure(img, pct)
    assert out.shape == img.shape and out.dtype == np.uint8
    assert np.all(out >= img)
    a, b = img.reshape(-1).astype(int), out.reshape(-1).astype(int)
    order = np.argsort(a, kind="stable")
    assert np.all(np.diff(b[order]) >= 0)                          # a monotone map of the values


def test_bad_inputs_are_refused():
    with pytest.raises(ReflectmmError, match="uint8"):
        normalize_exposure(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ReflectmmError, match="percentile"):
        normalize_exposure(np.zeros((4, 4, 3), np.uint8), percentile=0)
    with pytest.raises(ReflectmmError, match="exposure"):
        detect_landmarks(np.zeros((4, 4, 3), np.uint8), exposure="bright")

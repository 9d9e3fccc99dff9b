"""benchmarks/bench_vertex_split.py (docs/benchmarks.md, "Where the faces' error lies"): the split of a vertex error
into the face's place in model space and its shape, against a face moved by a known rigid motion."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from _benchmarks import load_benchmark
from reflectmm_cli.geometry.rotations import axis_angle_to_matrix


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(0.0, 5.0), shift=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
       noise=st.floats(0.0, 0.5), seed=st.integers(0, 1000))
def test_split_recovers_a_known_motion_and_leaves_the_shape(angle, shift, noise, seed):
    bench = load_benchmark("bench_vertex_split")
    rng = np.random.default_rng(seed)
    true = rng.normal(size=(400, 3)) * [60.0, 80.0, 40.0]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = np.asarray(axis_angle_to_matrix(axis * math.radians(angle)), np.float64)
    shape_err = rng.normal(size=true.shape) * noise
    shape_err -= shape_err.mean(0)
    c = true.mean(0)
    fitted = (true + shape_err - c) @ R.T + c + shift  # the shape error, turned and moved as a whole
    r = bench.split(fitted, true)
    assert np.allclose(r["shift"], shift, atol=1e-9)
    assert np.isclose(r["rms"], np.sqrt(((fitted - true) ** 2).sum(1).mean()))
    # the alignment takes out the motion: what is left is at most the shape error (the least-squares rotation may
    # also absorb a little of it), and for a noise-free shape nothing
    ref = float(np.sqrt((shape_err ** 2).sum(1).mean()))
    assert r["aligned_rms"] <= ref + 1e-9
    if noise == 0.0:
        assert r["aligned_rms"] < 1e-8 and abs(r["rotation_deg"] - angle) < 1e-6

"""benchmarks/bench_detect.py's bias table (docs/benchmarks.md, "detect-landmarks on dim captures"): the similarity
scale it reports is the scale of a known similarity, whatever the rotation and shift, and its table reads the
offsets it is given."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from _benchmarks import load_benchmark


def _bench():
    return load_benchmark("bench_detect")


@settings(max_examples=60, deadline=None)
@given(scale=st.floats(0.2, 5.0), angle=st.floats(-np.pi, np.pi), shift=st.tuples(st.floats(-500, 500),
                                                                                  st.floats(-500, 500)),
       seed=st.integers(0, 2 ** 16))
def test_similarity_scale_is_the_scale_of_a_similarity(scale, angle, shift, seed):
    ref = np.random.default_rng(seed).normal(0, 30, (68, 2)) + 300
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    pts = scale * ref @ R.T + np.array(shift)
    assert abs(_bench().similarity_scale(pts, ref) - scale) < 1e-9 * scale


def test_bias_table_reads_a_known_offset_and_scale():
    rng = np.random.default_rng(1)
    syn = rng.normal(0, 20, (68, 2)) + 200
    syn[36:42] += [-30, 0]  # eyes apart: a definite inter-ocular distance
    syn[42:48] += [30, 0]
    iod = np.linalg.norm(syn[36:42].mean(0) - syn[42:48].mean(0))
    det = syn.copy()
    det[17:27, 1] -= 0.1 * iod  # brows higher by 0.1 IOD, nothing else moves
    table = _bench().bias_table([(det, syn)])
    rows = dict(line.strip("|").split("|")[:2] for line in table.splitlines()[2:])
    rows = {k.strip(): float(v.split()[0]) for k, v in rows.items()}
    assert abs(rows["brow vertical offset / IOD"] + 0.1) < 1e-12
    assert abs(rows["brow error / IOD"] - 0.1) < 1e-12
    assert rows["jaw error / IOD"] == 0 and rows["inner error / IOD"] == 0
    assert abs(rows["scale, inner (nose, eyes, mouth)"] - 1) < 1e-12
    big = 1.1 * (syn - syn.mean(0)) + syn.mean(0)
    rows = dict(line.strip("|").split("|")[:2] for line in _bench().bias_table([(big, syn)]).splitlines()[2:])
    assert abs(float(rows[" scale, all 68 "].split()[0]) - 1.1) < 1e-12

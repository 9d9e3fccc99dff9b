"""The one shard reader: memory-mapped shards stacked without copies read exactly what concatenated arrays hold."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from _shards import make_dataset
from reflectmm_cli.finetune.shards import Stacked, load_shards


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 5), min_size=1, max_size=4), st.data())
def test_stacked_indexing_equals_concatenation(lengths, data):
    rng = np.random.default_rng(sum(lengths))
    parts = [rng.normal(size=(n, 2, 3)).astype(np.float32) for n in lengths]
    ref = np.concatenate(parts)
    s = Stacked(parts)
    assert s.shape == ref.shape and len(s) == len(ref) and np.array_equal(np.asarray(s), ref)
    if len(ref) == 0:
        return
    i = data.draw(st.integers(-len(ref), len(ref) - 1))
    assert np.array_equal(s[i], ref[i])
    idx = data.draw(st.lists(st.integers(0, len(ref) - 1), max_size=12))
    assert np.array_equal(s[np.array(idx, np.int64)], ref[np.array(idx, np.int64)])
    a, b = sorted(data.draw(st.lists(st.integers(0, len(ref)), min_size=2, max_size=2)))
    assert np.array_equal(s[a:b], ref[a:b])
    assert s.max() == ref.max()


def test_two_shards_read_like_one(tmp_path):
    one = load_shards(make_dataset(tmp_path / "a", n_images=7, size=24, mesh_n=9, seed=3)["shards"])
    two_paths = make_dataset(tmp_path / "b", n_images=7, size=24, mesh_n=9, seed=3, n_shards=2)["shards"]
    two = load_shards(two_paths)
    assert len(two_paths) == 2 and len(two) == len(one) == 7
    assert np.array_equal(two.pix_offset, one.pix_offset) and list(two.names) == list(one.names)
    idx = [6, 0, 3, 4]                                             # across the shard boundary, out of order
    b1, b2 = one.batch(idx), two.batch(idx)
    assert b1.keys() == b2.keys()
    for k in b1:
        assert np.array_equal(b1[k], b2[k]), k
    assert np.array_equal(np.asarray(two.truth["truth_diffuse"]), np.asarray(one.truth["truth_diffuse"]))
    assert np.array_equal(two.image[[5, 1]], one.image[[5, 1]])
    # memory maps, not copies: the shard files back the arrays
    assert all(isinstance(p, np.memmap) for p in two.image.parts)

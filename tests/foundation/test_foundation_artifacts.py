"""Artifact container: round trips, determinism, refusals and corrupt files."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from reflectmm_cli import __version__
from reflectmm_cli.artifacts import (SCHEMA_MAJOR, canonical_json, read_artifact, read_exr, read_meta,
                                     sha256_file, write_artifact, write_exr, make_meta)
from reflectmm_cli.errors import ArtifactError, ReflectmmError


def _arrays(rng):
    return {"albedo": rng.random((3, 8, 8), dtype=np.float32),
            "mask": rng.random((8, 8)) > 0.5,
            "ids": np.array(["001", "042"]),
            "count": np.arange(7, dtype=np.int64),
            "scalar": np.float64(2.5)}


def test_npz_round_trip_preserves_arrays_dtypes_and_meta(tmp_path):
    rng = np.random.default_rng(0)
    arrs = _arrays(rng)
    p = write_artifact(tmp_path / "a.npz", "reflectance-maps", arrs, params={"lr": 5e-3, "K": 3},
                       inputs=[{"role": "obs", "path": "x.npz", "sha256": "0" * 64}],
                       producer={"stage": "fit-reflectance", "stage_version": 2}, cache_key="k" * 64)
    art = read_artifact(p, "reflectance-maps")
    assert art.kind == "reflectance-maps"
    assert set(art.arrays) == set(arrs)
    for k, v in arrs.items():
        got = art[k]
        assert got.dtype == np.asarray(v).dtype and got.shape == np.asarray(v).shape
        np.testing.assert_array_equal(got, v)
    assert art.meta["schema"] == f"reflectmm.reflectance-maps/{SCHEMA_MAJOR['reflectance-maps']}"
    assert art.meta["producer"] == {"tool": "reflectmm", "version": __version__, "stage": "fit-reflectance",
                                    "stage_version": 2}
    assert art.params == {"K": 3, "lr": 5e-3}
    assert art.meta["inputs"][0]["role"] == "obs"
    assert art.meta["cache_key"] == "k" * 64
    assert read_meta(p) == art.meta
    with pytest.raises(ArtifactError, match="has no array 'nope'"):
        art["nope"]


@given(hnp.arrays(dtype=st.sampled_from([np.float32, np.float64, np.int32, np.uint8, np.float16]),
                  shape=hnp.array_shapes(min_dims=0, max_dims=3, max_side=5)))
def test_round_trip_any_numeric_array_including_nan_inf(tmp_path_factory, arr):
    p = tmp_path_factory.mktemp("h") / "x.npz"
    write_artifact(p, "render", {"x": arr})
    got = read_artifact(p, "render")["x"]
    assert got.dtype == arr.dtype and got.shape == arr.shape
    np.testing.assert_array_equal(got, arr)  # NaN == NaN for assert_array_equal


def test_same_inputs_give_byte_identical_files(tmp_path):
    arrs = _arrays(np.random.default_rng(1))
    a = write_artifact(tmp_path / "a.npz", "render", arrs, params={"b": 1, "a": [1, 2]})
    # same content, different insertion order of arrays and params, later in time
    arrs2 = dict(reversed(list(arrs.items())))
    b = write_artifact(tmp_path / "b.npz", "render", arrs2, params={"a": [1, 2], "b": 1})
    assert a.read_bytes() == b.read_bytes()
    assert sha256_file(a) == sha256_file(b)
    # and the zip members carry the fixed epoch, not the current time
    with zipfile.ZipFile(a) as zf:
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    # EXR too
    ch = {"albedo.R": arrs["albedo"][0], "albedo.G": arrs["albedo"][1]}
    e1 = write_exr(tmp_path / "a.exr", ch, make_meta("render", params={"x": 1}))
    e2 = write_exr(tmp_path / "b.exr", ch, make_meta("render", params={"x": 1}))
    assert e1.read_bytes() == e2.read_bytes()


def test_meta_has_no_timestamp_or_host(tmp_path):
    import socket

    p = write_artifact(tmp_path / "a.npz", "render", {"x": np.zeros(2)}, params={"p": 1})
    raw = json.dumps(read_meta(p))
    assert socket.gethostname() not in raw
    assert set(read_meta(p)) == {"schema", "producer", "params", "inputs", "cache_key"}


def test_wrong_kind_is_refused_with_both_kinds_named(tmp_path):
    p = write_artifact(tmp_path / "a.npz", "geometry", {"x": np.zeros(3)})
    with pytest.raises(ArtifactError) as ei:
        read_artifact(p, "reflectance-maps")
    msg = str(ei.value)
    assert str(p) in msg and "'geometry'" in msg and "'reflectance-maps'" in msg


def test_newer_major_is_refused_and_names_the_writer(tmp_path):
    p = write_artifact(tmp_path / "a.npz", "geometry", {"x": np.zeros(3)},
                       extra_meta={"schema": f"reflectmm.geometry/{SCHEMA_MAJOR['geometry'] + 1}",
                                   "producer": {"tool": "reflectmm", "version": "9.0.0"}})
    with pytest.raises(ArtifactError, match=r"newer than this reflectmm .* written by reflectmm 9\.0\.0"):
        read_artifact(p, "geometry")
    # an older-or-equal major is read
    q = write_artifact(tmp_path / "b.npz", "geometry", {"x": np.zeros(3)})
    assert read_artifact(q, "geometry").kind == "geometry"


@pytest.mark.parametrize("keep", [0.3, 0.6, 0.95])
def test_truncated_npz_gives_a_clear_error(tmp_path, keep):
    p = write_artifact(tmp_path / "a.npz", "render", {"x": np.random.default_rng(0).random((64, 64))},
                       compress=False)
    data = p.read_bytes()
    p.write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(ArtifactError, match="truncated or corrupt") as ei:
        read_artifact(p, "render")
    assert str(p) in str(ei.value)


def test_members_reads_only_the_named_arrays(tmp_path):
    """``members`` leaves the other arrays unread: a damaged image stack does not stop a read of the landmarks,
    while a whole read still finds the damage."""
    rng = np.random.default_rng(0)
    p = write_artifact(tmp_path / "cap.npz", "capture", {"landmarks": rng.random((3, 68, 2)),
                                                         "olat": rng.random((4, 64, 64))}, compress=False)
    with zipfile.ZipFile(p) as z:
        info = z.getinfo("olat.npy")
        start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra) + info.file_size // 2
    data = bytearray(p.read_bytes())
    data[start:start + 64] = bytes(64)
    p.write_bytes(bytes(data))
    a = read_artifact(p, "capture", members=("landmarks", "not_there"))
    assert set(a.arrays) == {"landmarks"} and a["landmarks"].shape == (3, 68, 2)
    with pytest.raises(ArtifactError, match="truncated or corrupt"):
        read_artifact(p, "capture")


def test_npz_without_meta_is_not_an_artifact(tmp_path):
    p = tmp_path / "plain.npz"
    np.savez(p, x=np.zeros(3))
    with pytest.raises(ArtifactError, match="not a reflectmm artifact"):
        read_artifact(p)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(ArtifactError, match="file not found"):
        read_artifact(tmp_path / "nope.npz")
    with pytest.raises(ArtifactError, match="directory"):
        read_artifact(tmp_path)
    with pytest.raises(ArtifactError, match="file not found"):
        read_exr(tmp_path / "nope.exr")


def test_never_unpickles(tmp_path):
    # writing an object array is refused
    with pytest.raises(ReflectmmError, match="dtype object"):
        write_artifact(tmp_path / "o.npz", "render", {"x": np.array([{"a": 1}], dtype=object)})
    assert not (tmp_path / "o.npz").exists()
    # a hand-made NPZ with a pickled member is refused on read, and the pickle never runs
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    meta = canonical_json(make_meta("render"))
    p = tmp_path / "evil.npz"
    np.savez(p, __meta__=np.array(meta), x=np.array([Evil()], dtype=object))
    with pytest.raises(ArtifactError, match="allow_pickle"):
        read_artifact(p, "render")
    assert not marker.exists()


def test_exr_round_trip_float32_and_half(tmp_path):
    rng = np.random.default_rng(2)
    ch = {"albedo.R": rng.random((5, 7), dtype=np.float32) * 4, "weight.p8": rng.random((5, 7), dtype=np.float32)}
    meta = make_meta("render", params={"a": 1}, cache_key="c")
    p = write_exr(tmp_path / "a.exr", ch, meta)
    got, m = read_exr(p)
    assert m == meta and list(got) == list(ch)
    for k in ch:
        np.testing.assert_array_equal(got[k], ch[k])
    h = write_exr(tmp_path / "h.exr", ch, meta, half=True)
    goth, _ = read_exr(h)
    for k in ch:  # float16 keeps 11 significant bits
        np.testing.assert_allclose(goth[k], ch[k].astype(np.float16).astype(np.float32), rtol=0, atol=0)
    assert read_artifact(p, "render")["weight.p8"].shape == (5, 7)
    with pytest.raises(ArtifactError, match="expected a 'geometry'"):
        read_artifact(p, "geometry")


def test_corrupt_and_truncated_exr_give_a_clear_error(tmp_path):
    ch = {"Y": np.random.default_rng(3).random((64, 64), dtype=np.float32)}
    p = write_exr(tmp_path / "a.exr", ch, make_meta("render"))
    data = p.read_bytes()
    bad = tmp_path / "garbage.exr"
    bad.write_bytes(b"\x00not an exr" * 50)
    with pytest.raises(ArtifactError, match="corrupt EXR") as ei:
        read_artifact(bad)
    assert str(bad) in str(ei.value) and "\n" not in str(ei.value)
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtifactError, match="corrupt EXR") as ei:
        read_artifact(cut)
    assert "\n" not in str(ei.value)


def test_exr_channel_shape_mismatch_is_refused(tmp_path):
    with pytest.raises(ReflectmmError, match="channel 'b' has shape"):
        write_exr(tmp_path / "x.exr", {"a": np.zeros((2, 2)), "b": np.zeros((3, 2))})
    assert not (tmp_path / "x.exr").exists()


def test_written_files_get_normal_permissions(tmp_path):
    import os

    p = write_artifact(tmp_path / "a.npz", "render", {"x": np.zeros(1)})
    mask = os.umask(0o022)
    os.umask(mask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~mask)


def test_an_artifact_answers_membership_and_get_like_a_mapping(tmp_path):
    """Library functions take ``Mapping[str, ndarray]``: an artifact read from disk answers ``in``, ``get`` and
    ``keys`` by its arrays (``in`` used to fall back to indexing by 0, 1, … and raise)."""
    from reflectmm_cli.artifacts import read_artifact, write_artifact

    p = write_artifact(tmp_path / "a.npz", "checksum", {"x": np.arange(3), "y": np.ones(2)})
    a = read_artifact(p, "checksum")
    assert "x" in a and "z" not in a and 0 not in a
    assert set(a.keys()) == {"x", "y"}
    assert np.array_equal(a.get("x"), np.arange(3)) and a.get("z") is None and a.get("z", 5) == 5

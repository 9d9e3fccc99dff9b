"""wild-shard writer, memory-mapped reader and batch iterator."""
import numpy as np
import pytest

from wild_testutil import head_rotation
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.data import linearize, open_shard, write_shard
from reflectmm_cli.finetune.shards import iter_batches
from reflectmm_cli.geometry import Camera, deep3d_camera
from reflectmm_cli.geometry.gbuffer import gbuffer_for_image, pack_gbuffers


def make_arrays(face, n=4, S=48, seed=0):
    rng = np.random.default_rng(seed)
    gbs, shapes, exps, Rs, ts, Ks = [], [], [], [], [], []
    for i in range(n):
        shape = rng.normal(size=face.n_shape) * face.shape_sigma
        exp = rng.normal(size=face.n_exp) * face.exp_sigma * 0.3
        cam = Camera(deep3d_camera().K, head_rotation(rng.uniform(-40, 40)), [0, 0, 1000], 224, 224).with_size(S, S)
        gbs.append(gbuffer_for_image(face, shape, exp, cam.R, cam.t, cam.K, S))
        shapes.append(shape), exps.append(exp), Rs.append(cam.R), ts.append(cam.t), Ks.append(cam.K)
    packed = pack_gbuffers(gbs)
    fm = packed.pop("face_mask")
    arrays = {
        "names": np.array([f"img{i:03d}" for i in range(n)]),
        "split": np.array(["train", "train", "val", "test", "train"][:n] + ["train"] * max(0, n - 5)),
        "image": rng.integers(0, 256, (n, S, S, 3), dtype=np.uint8),
        "face_mask": fm, "skin_mask": fm & (rng.uniform(size=fm.shape) > 0.2),
        "landmarks": rng.uniform(0, S, (n, 68, 2)).astype(np.float32),
        "shape": np.array(shapes, np.float32), "expression": np.array(exps, np.float32),
        "R": np.array(Rs), "t": np.array(ts), "K": np.array(Ks), **packed,
        "truth_sh": rng.normal(size=(n, 3, 81)).astype(np.float32),
    }
    return arrays


def test_shard_roundtrip_memmap_and_determinism(small_face, tmp_path):
    arrays = make_arrays(small_face)
    p = write_shard(tmp_path / "s.npz", arrays, encoding="gamma1.2", face_model_sha256="0" * 64,
                    face_model_path="fm.npz")
    p2 = write_shard(tmp_path / "s2.npz", arrays, encoding="gamma1.2", face_model_sha256="0" * 64,
                     face_model_path="fm.npz")
    assert p.read_bytes() == p2.read_bytes()
    sh = open_shard(p)
    ref = np.load(p, allow_pickle=False)
    assert len(sh) == 4 and sh.encoding == "gamma1.2" and sh.image_size == 48
    assert sh.meta["face_model"]["path"] == "fm.npz" and sh.meta["sh_order"] == 8
    for k in arrays:
        assert isinstance(sh[k], np.memmap) or sh[k].size == 0
        assert np.array_equal(np.asarray(sh[k]), ref[k]), k
        assert sh[k].dtype == ref[k].dtype
    g = sh.gbuffer(2)
    assert len(g["bary"]) == arrays["face_mask"][2].sum()


def test_iter_batches_covers_split_once(small_face, tmp_path):
    a = make_arrays(small_face, n=5, seed=1)
    b = make_arrays(small_face, n=5, seed=2)
    paths = [write_shard(tmp_path / f"s{i}.npz", x, encoding="srgb", face_model_sha256="0" * 64,
                         face_model_path="fm.npz") for i, x in enumerate((a, b))]
    seen = []
    for batch in iter_batches(paths, 2, split="train", seed=3):
        B = len(batch["names"])
        assert batch["images"].shape == (B, 48, 48, 3) and batch["offsets"].shape == (B + 1,)
        for j in range(B):
            src = (a, b)[batch["index"][j] // 5]  # 5 images per shard
            i = batch["index"][j] % 5
            lo, hi = batch["offsets"][j], batch["offsets"][j + 1]
            so = src["pix_offset"]
            assert np.array_equal(batch["bary"][lo:hi], src["bary"][so[i]:so[i + 1]].astype(np.float32))
            assert np.array_equal(batch["images"][j], src["image"][i])
            assert batch["split"][j] == "train" and batch["names"][j] == src["names"][i]
            seen.append((int(batch["index"][j] // 5), int(i)))
    assert sorted(seen) == [(s, i) for s in (0, 1) for i in (0, 1, 4)]
    order1 = [tuple(x["names"]) for x in iter_batches(paths, 2, seed=3)]
    order2 = [tuple(x["names"]) for x in iter_batches(paths, 2, seed=3)]
    order3 = [tuple(x["names"]) for x in iter_batches(paths, 2, seed=3, epoch=1)]
    assert order1 == order2 and order1 != order3


def test_write_shard_refuses_bad_arrays(small_face, tmp_path):
    a = make_arrays(small_face, n=2)
    bad = dict(a, normal=a["normal"].astype(np.float32))
    with pytest.raises(ReflectmmError, match="normal"):
        write_shard(tmp_path / "x.npz", bad, encoding="srgb", face_model_sha256="", face_model_path="")
    bad = dict(a, split=np.array(["train", "holdout"]))
    with pytest.raises(ReflectmmError, match="holdout"):
        write_shard(tmp_path / "x.npz", bad, encoding="srgb", face_model_sha256="", face_model_path="")
    bad = dict(a, pix_offset=a["pix_offset"] + np.array([0, 1, 1]))
    with pytest.raises(ReflectmmError, match="pix_yx"):
        write_shard(tmp_path / "x.npz", bad, encoding="srgb", face_model_sha256="", face_model_path="")
    with pytest.raises(ReflectmmError, match="encoding"):
        write_shard(tmp_path / "x.npz", a, encoding="gamma2.2", face_model_sha256="", face_model_path="")


def test_linearize_matches_definitions():
    x = np.arange(256, dtype=np.uint8)
    assert np.allclose(linearize(x, "gamma1.2"), (x / 255.0) ** 1.2, atol=1e-6)
    v = x / 255.0
    srgb = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    assert np.allclose(linearize(x, "srgb"), srgb, atol=1e-6)
    # the EOTF inverts the sRGB OETF of geometry/render.py
    from reflectmm_cli.geometry.render import to_display
    lin = np.linspace(0, 1, 50)[:, None, None] * np.ones((1, 1, 3))
    enc = np.round(to_display(lin, exposure=1.0) * 255).astype(np.uint8)
    assert np.abs(linearize(enc, "srgb") - lin).max() < 0.01


def _mutated(src, dst, **changes):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for k, f in changes.items():
        arrays[k] = f(arrays[k].copy())
    np.savez(dst, **arrays)
    return dst


def _set(idx, value):
    def f(a):
        a[idx] = value
        return a
    return f


@pytest.mark.parametrize("change,match", [
    (dict(pix_yx=_set((5, 0), 500)), "pix_yx holds pixel index 500 outside the 48x48 image"),
    (dict(pix_yx=_set((0, 1), -3)), "pix_yx holds pixel index -3"),
    (dict(vert_ids=_set((2, 1), -1)), "negative vertex id"),
    (dict(t=_set((1, 2), np.nan)), r"t of image 1 \(img001\) contains NaN or inf"),
    (dict(landmarks=_set((0, 3, 0), np.inf)), r"landmarks of image 0 \(img000\) contains NaN or inf"),
])
def test_opening_a_shard_checks_index_ranges_and_finiteness(small_face, tmp_path, change, match):
    """Issue 24 §6: an out-of-range pix_yx gave an internal IndexError without the file's name; NaN/inf t or
    landmarks were accepted. Now opening the shard is a one-line error naming the file."""
    from reflectmm_cli.finetune.shards import load_shards

    a = make_arrays(small_face, n=2)
    p = write_shard(tmp_path / "s.npz", a, encoding="srgb", face_model_sha256="0" * 64, face_model_path="fm.npz")
    load_shards([p])
    bad = _mutated(p, tmp_path / "bad.npz", **change)
    with pytest.raises(ReflectmmError, match=match) as exc:
        load_shards([bad])
    assert "bad.npz" in str(exc.value) and "\n" not in str(exc.value)


def test_files_of_another_type_in_the_images_folder_are_said(tmp_path, reflectmm_log):
    # an .exr among the photos was left out without a word; landmark files beside the images are expected
    from reflectmm_cli.finetune.data import list_wild_inputs

    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "a.pts").write_text("")
    (tmp_path / "b.exr").write_bytes(b"")
    (tmp_path / ".hidden").write_bytes(b"")
    inputs = list_wild_inputs(tmp_path)
    assert [i.name for i in inputs] == ["a"]
    msgs = reflectmm_log
    assert len(msgs) == 1 and "1 file(s) of another type left out" in msgs[0] and "b.exr" in msgs[0]

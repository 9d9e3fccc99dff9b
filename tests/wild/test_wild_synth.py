"""synth wild: lighting pieces against independent computations, the data set end to end."""
import math

import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.landmarks import read_landmarks
from reflectmm_cli.shading import fibonacci_sphere
from reflectmm_cli.synth.envmaps import make_envmap
from reflectmm_cli.synth.ggx import ggx_directional, ggx_specular_albedo
from reflectmm_cli.synth.wild import (WildConfig, encode_codes, head_pose_rotation, identity_split,
                                      sample_wild_skin, synth_wild)
from reflectmm_cli.synth.wild_light import equirect_lookup, ggx_view_albedo, split_map


@pytest.mark.parametrize("alpha,mu", [(0.1, 1.0), (0.3, 0.5), (0.6, 0.25), (0.9, 0.8)])
def test_ggx_view_albedo_matches_quadrature(alpha, mu):
    # independent: sum the GGX shading of directional lights over a dense Fibonacci sphere (E = ΔΩ each)
    d = fibonacci_sphere(400000)
    v = np.array([math.sqrt(1 - mu * mu), 0.0, mu])
    s = ggx_directional(np.zeros((len(d), 3)), 1.0, alpha, np.array([0, 0, 1.0]), d, v, 4 * math.pi / len(d))
    ref = s[:, 0].sum()
    assert ggx_view_albedo(alpha, mu) == pytest.approx(ref, rel=0.02)
    if mu == 1.0:
        assert ggx_view_albedo(alpha, 1.0) == pytest.approx(float(ggx_specular_albedo(alpha)), rel=2e-3)


def test_split_map_conserves_energy_and_finds_the_sun():
    img, kind = make_envmap(3, 0, 128)   # a sky with a sun
    assert kind == "sky"
    sm = split_map(img, prefilter_width=32, source_width=64)
    assert len(sm.source_dirs) >= 1
    y00 = 0.5 / math.sqrt(math.pi)
    total = sm.residual_sh[:, 0] + (sm.source_irradiance * y00).sum(0)
    assert np.allclose(total, sm.sh[:, 0], rtol=2e-3)
    # the source direction is where the map is brightest
    H, W = img.shape[:2]
    k = np.argmax(img.sum(-1))
    from reflectmm_cli.shading import equirect_directions
    d = equirect_directions(W, H).reshape(-1, 3)[k]
    assert d @ sm.source_dirs[0] > math.cos(math.radians(5))
    # the prefiltered residual of a constant map is that constant
    flat = split_map(np.full((32, 64, 3), 0.7, np.float32), prefilter_width=16, source_width=32)
    assert len(flat.source_dirs) == 0
    dd = fibonacci_sphere(50)
    for a in (0.05, 0.2, 0.9):
        assert np.allclose(flat.specular(dd, np.full(50, a)), 0.7, rtol=1e-4)
    assert np.allclose(equirect_lookup(np.asarray(flat.image, np.float64), dd), 0.7)


def test_wild_skin_population_is_wider_than_the_basis(small_face):
    rng = np.random.default_rng(0)
    skins = [sample_wild_skin(small_face, rng, 64) for _ in range(12)]
    a = np.concatenate([s.roughness[s.skin] for s in skins])
    # sharper than p = 64 (α ≈ 0.17) and broader than p = 1 (α ≈ 0.8) both occur
    assert a.min() < 0.12 and a.max() > 0.8
    mel = [s.params["melanin"] for s in skins]
    assert min(mel) < 0.05 and max(mel) > 0.4
    lum = [float(np.median(s.albedo[s.skin] @ [0.2126, 0.7152, 0.0722])) for s in skins]
    assert max(lum) / min(lum) > 2.5
    for s in skins:
        assert np.allclose(s.spec_albedo, ggx_specular_albedo(s.roughness, s.spec_intensity), rtol=1e-4)


def test_head_pose_and_encodings():
    R = head_pose_rotation(30, 10, 5)
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1)
    assert (head_pose_rotation(30) @ [0, 0, 1.0])[0] > 0.4     # yaw > 0 turns the face towards +x
    x = np.linspace(0, 1, 11)
    assert np.array_equal(encode_codes(x, "gamma1.2"), np.floor(x ** (1 / 1.2) * 255 + 0.5).astype(np.uint8))
    from reflectmm_cli.finetune.data import linearize
    for enc in ("gamma1.2", "srgb"):
        assert np.abs(linearize(encode_codes(x, enc), enc) - x).max() < 6e-3
    s = identity_split(20, 0)
    assert set(s) == {"train", "val", "test"} and (s == "train").sum() == 16


@pytest.fixture(scope="module")
def wild_dir(tmp_path_factory):
    from reflectmm_cli.geometry import procedural_face_model

    out = tmp_path_factory.mktemp("wild")
    fm = procedural_face_model(grid=(61, 51), n_shape=6, n_exp=4, seed=2)
    cfg = WildConfig(count=6, size=64, images_per_identity=2, envmaps=2, envmap_width=64, prefilter_width=32,
                     uv_size=64, occluder_fraction=0.5, seed=5)
    summary = synth_wild(out, cfg, face_model=fm)
    return out, cfg, summary


def test_synth_wild_layout_truth_and_split(wild_dir):
    out, cfg, summary = wild_dir
    man = read_artifact(out / "manifest.npz", "wild-manifest")
    names = man["names"].tolist()
    assert len(names) == 6 and (out / "contact_sheet.png").is_file()
    by_id = {}
    for n, i, s in zip(names, man["identity"], man["split"]):
        by_id.setdefault(int(i), set()).add(str(s))
    assert all(len(v) == 1 for v in by_id.values()) and len(by_id) == 3
    occluded = 0
    for n in names:
        tr = read_artifact(out / "truth" / f"{n}.npz", "wild-truth")
        assert tr["diffuse"].shape == (64, 64, 3) and tr["sh"].shape == (3, 81)
        sk, fm, occ = tr["skin_mask"], tr["face_mask"], tr["occluder_mask"]
        assert sk.any() and not (sk & ~fm).any() and not (sk & occ).any()
        occluded += bool(occ.any())
        lm = read_landmarks(out / "landmarks" / f"{n}.pts")
        assert np.abs(lm - tr["landmarks_true"]).max() < 6 * cfg.landmark_noise
        ident = read_artifact(out / "identities" / f"id{tr.meta['identity']:05d}.npz", "wild-truth")
        assert ident["vertex_weights"].shape[1] == 3
        # the truth layers reproduce the rendered image where the face is shaded and unoccluded
        from reflectmm_cli.artifacts import read_image
        img = read_image(out / "images" / f"{n}.png")
        lin = np.clip(img, 0, 1) ** 1.2
        m = tr["shaded_mask"] & ~occ
        layer = (tr["diffuse"].astype(np.float64) + tr["specular"])[m]
        ok = layer.max(-1) < 0.95
        assert np.median(np.abs(lin[m][ok] - layer[ok])) < 0.03
    assert occluded >= 1


def test_synth_wild_is_deterministic(wild_dir, tmp_path):
    out, cfg, _ = wild_dir
    from reflectmm_cli.geometry import load_face_model
    fm = load_face_model(out / "face_model.npz")
    cfg2 = WildConfig(**{**cfg.to_params(), "count": 2, "split": tuple(cfg.split)})
    synth_wild(tmp_path, cfg2, face_model=fm)
    for n in ("w005_000000", "w005_000001"):
        assert (tmp_path / "images" / f"{n}.png").read_bytes() == (out / "images" / f"{n}.png").read_bytes()
        a, b = read_artifact(tmp_path / "truth" / f"{n}.npz"), read_artifact(out / "truth" / f"{n}.npz")
        assert a.arrays.keys() == b.arrays.keys()
        assert all(np.array_equal(a[k], b[k]) for k in a.arrays)   # meta differs only by --count and the split


@pytest.mark.slow
def test_synth_wild_command_with_shards(tmp_path, cli):
    """The CLI end to end: synth wild + prepare-wild --from-truth shards, read back with the loader."""
    from reflectmm_cli.finetune.data import open_shard
    from reflectmm_cli.finetune.shards import iter_batches

    res = cli("synth", "wild", "--count", 3, "--size", 64, "--envmaps", 1, "--face-vertices", 2000,
              "--images-per-identity", 1, "--shard-size", 2, "--out", tmp_path / "w", "--encoding", "srgb")
    assert res.exit_code == 0, res.stderr
    shards = sorted((tmp_path / "w" / "shards").glob("shard_*.npz"))
    assert [p.name for p in shards] == ["shard_00000.npz", "shard_00001.npz"]
    sh = open_shard(shards[0])
    assert sh.encoding == "srgb" and sh.image_size == 64 and "truth_sh" in sh
    man = read_artifact(tmp_path / "w" / "manifest.npz", "wild-manifest")
    assert sorted(np.concatenate([open_shard(p)["split"] for p in shards]).tolist()) == sorted(man["split"].tolist())
    assert sum(len(b["names"]) for b in iter_batches(shards, 4, split=None)) == 3


def test_wild_two_lobe_skin_keeps_the_specular_albedo(small_face):
    from reflectmm_cli.synth.skin import two_lobe_specular_albedo

    one = sample_wild_skin(small_face, np.random.default_rng(3), 64)
    two = sample_wild_skin(small_face, np.random.default_rng(3), 64, skin_model="two-lobe")
    assert one.lobe_mix is None and two.lobe_mix is not None
    np.testing.assert_array_equal(one.albedo, two.albedo)      # the two-lobe draws come after every other draw
    np.testing.assert_allclose(two.spec_albedo[two.skin], one.spec_albedo[two.skin], rtol=1e-4)
    np.testing.assert_allclose(two.spec_albedo, two_lobe_specular_albedo(two.roughness, two.roughness_broad,
                                                                         two.lobe_mix, two.spec_intensity), rtol=1e-5)
    assert np.all(two.roughness[two.skin] < one.roughness[two.skin] + 1e-6)
    assert np.all(two.roughness_broad[two.skin] > one.roughness[two.skin] - 1e-6)
    assert 0.3 <= two.lobe_mix.min() and two.lobe_mix.max() <= 0.97 and "two_lobe" in two.params


def test_too_few_identities_to_split_warn(tmp_path, reflectmm_log):
    """-n 2 with 2 images per identity is one identity: all train, no test identity for the evaluations."""
    from reflectmm_cli.geometry import procedural_face_model

    fm = procedural_face_model(grid=(31, 25), n_shape=2, n_exp=2, seed=2)
    cfg = WildConfig(count=2, size=32, images_per_identity=2, envmaps=1, envmap_width=16, prefilter_width=8,
                     uv_size=16, ao_rays=1, spec_rays=1)
    synth_wild(tmp_path, cfg, face_model=fm)
    man = read_artifact(tmp_path / "manifest.npz", "wild-manifest")
    assert set(man["split"].tolist()) == {"train"}
    assert reflectmm_log == ["synth wild: 2 image(s) make 1 identity, too few to split: no val or test identity "
                             "(-n 5 or more, with 2 image(s) per identity, gives every split at least one)"]
    assert set(identity_split(3, 0)) == {"train", "val", "test"}  # the count the warning names is enough

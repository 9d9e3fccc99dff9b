"""Light model (build-light-pca): rotation augmentation, normalisation, PCA, inverse, CLI end to end."""

import numpy as np
import pytest

from _shading_ref import real_sh_matrix_ref
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading import equirect_directions, project_envmap
from reflectmm_cli.model.light import (
    augment_sh,
    augmentation_rotations,
    build_light_model,
    fit_light_pca,
    light_from_coeffs,
    light_model_arrays,
    light_model_from_arrays,
    rotation_y,
)

W, H, ORDER = 48, 24, 4


def _sun_map(direction, colour, sharp=8.0, w=W, h=H):
    d = equirect_directions(w, h)
    s = np.asarray(direction, float)
    s = s / np.linalg.norm(s)
    return (0.1 + np.maximum(d @ s, 0)[..., None] ** sharp * np.asarray(colour)).astype(np.float64)


def _bandlimited_map(seed, order=ORDER):
    rng = np.random.default_rng(seed)
    K = rng.normal(size=(3, (order + 1) ** 2)) * 0.2
    K[:, 0] = 4.0
    return K, lambda d: real_sh_matrix_ref(d, order) @ K.T


def test_rotation_augmentation_equals_projecting_the_rotated_map():
    K, f = _bandlimited_map(0)
    R = rotation_y(0.9)
    d = equirect_directions(W, H).reshape(-1, 3)
    rotated_map = f(d @ R).reshape(H, W, 3)  # the environment turned by R about the vertical axis: g(d) = f(Rᵀd)
    np.testing.assert_allclose(augment_sh(K[None], [R])[0], project_envmap(rotated_map, ORDER), atol=1e-10)
    # the vertical axis is +y: a light at the zenith does not move
    up = _sun_map([0, 1, 0], [1, 1, 1], sharp=2)
    Ku = project_envmap(up, ORDER)
    np.testing.assert_allclose(augment_sh(Ku[None], [rotation_y(1.234)])[0], Ku, atol=1e-10)


def test_augmentation_rotations_layout():
    rots = augmentation_rotations(4, 15.0)
    assert len(rots) == 12
    for R in rots:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    with pytest.raises(ReflectmmError, match="rotations"):
        augmentation_rotations(0)
    with pytest.raises(ReflectmmError, match="tilt"):
        augmentation_rotations(2, 120.0)


def test_build_model_normalisation_pca_and_inverse():
    rng = np.random.default_rng(1)
    maps = [_sun_map(rng.normal(size=3), rng.uniform(0.5, 3, 3)) for _ in range(5)]
    msgs = []
    model, skipped = build_light_model(maps, order=ORDER, rotations=6, tilt=10, components=200, log=msgs.append)
    assert not skipped
    S = 5 * 6 * 3
    n = (ORDER + 1) ** 2
    assert model.dc.shape == (S, 3) and model.mean.shape == (3 * n,)
    # every sample was divided by its own per-channel DC: the mean has DC 1 per channel and no variance there
    np.testing.assert_allclose(model.mean.reshape(3, n)[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(model.bases.reshape(-1, 3, n)[:, :, 0], 0.0, atol=1e-10)
    # capped by the data with a message; orthonormal bases; σ sorted; ratios sum to 1 when all kept
    assert model.n_components < 200 and any("capped" in m or "supports" in m for m in msgs)
    np.testing.assert_allclose(model.bases @ model.bases.T, np.eye(model.n_components), atol=1e-10)
    assert np.all(np.diff(model.sigma) <= 1e-12) and abs(model.explained_variance_ratio.sum() - 1) < 1e-9
    # reconstruct a training sample through the inverse (γ in units of σ, z = its DC)
    dc = model.dc[7]
    maps_K = project_envmap(maps[7 // 18], ORDER)
    from reflectmm_cli.shading import sh_rotation

    target = sh_rotation(augmentation_rotations(6, 10)[7 % 18], ORDER) @ maps_K.T
    target = target.T
    x = (target / dc[:, None]).reshape(-1)
    gamma = (model.bases @ (x - model.mean)) / model.sigma
    np.testing.assert_allclose(light_from_coeffs(model, gamma, dc), target, atol=1e-9)
    np.testing.assert_allclose(light_from_coeffs(model, np.zeros(0), [1, 2, 3]),
                               model.mean.reshape(3, n) * np.array([1, 2, 3])[:, None])
    # artifact arrays round trip
    m2 = light_model_from_arrays(light_model_arrays(model))
    np.testing.assert_allclose(light_from_coeffs(m2, gamma[:5], dc), light_from_coeffs(model, gamma[:5], dc))


def test_inverse_torch_batched_and_differentiable():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(2)
    maps = [_sun_map(rng.normal(size=3), [1, 1, 1]) for _ in range(4)]
    model, _ = build_light_model(maps, order=ORDER, rotations=3, components=5)
    g = torch.tensor(rng.normal(size=(2, 5)), requires_grad=True)
    z = torch.tensor(rng.uniform(0.5, 2, (2, 3)), requires_grad=True)
    K = light_from_coeffs(model, g, z)
    assert K.shape == (2, 3, (ORDER + 1) ** 2)
    np.testing.assert_allclose(K.detach().numpy(), light_from_coeffs(model, g.detach().numpy(), z.detach().numpy()))
    assert torch.autograd.gradcheck(lambda a, b: light_from_coeffs(model, a, b), (g, z))
    with pytest.raises(ReflectmmError, match="gamma"):
        light_from_coeffs(model, np.zeros(50))


def test_fit_pca_single_sample_and_skips():
    mean, bases, sigma, var, ratio = fit_light_pca(np.ones((1, 6)), 3)
    assert bases.shape == (0, 6) and np.allclose(mean, 1)
    bad = _sun_map([0, 1, 0], [1, 1, 1])
    bad[3, 4, 0] = np.inf
    neg = -_sun_map([0, 1, 0], [1, 1, 1])
    good = _sun_map([1, 0, 0], [1, 1, 1])
    model, skipped = build_light_model([bad, good, neg], order=2, components=3, rotations=2)
    assert len(skipped) == 2 and "NaN or infinite" in skipped[0][1] and "negative" in skipped[1][1]
    with pytest.raises(ReflectmmError, match="none of the 2"):
        build_light_model([bad, neg], order=2)
    # a map that is not 2:1 is not equirectangular: skipped like the others, and named by envmap_rgb
    square = good[:, : good.shape[0]]
    model, skipped = build_light_model([good, square], order=2, components=3, rotations=2)
    assert len(skipped) == 1 and "twice as wide as high" in skipped[0][1]
    from reflectmm_cli.shading.envmap import envmap_rgb

    with pytest.raises(ReflectmmError, match=r"is 8x8; an equirectangular"):
        envmap_rgb(np.ones((8, 8, 3)))
    assert envmap_rgb(np.ones((8, 17, 3))).shape == (8, 17, 3)  # a pixel off 2:1 is kept


# ---------------------------------------------------------------------------------------------------------------
# CLI end to end


def _write_hdr(path, img):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, "float")
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(img.astype(np.float32)))
    out.close()


def _write_maps(folder):
    from reflectmm_cli.artifacts import write_exr

    folder.mkdir()
    rng = np.random.default_rng(3)
    for i in range(3):
        img = _sun_map(rng.normal(size=3), rng.uniform(0.5, 2, 3), w=64, h=32).astype(np.float32)
        write_exr(folder / f"env{i}.exr", {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    _write_hdr(folder / "probe.hdr", _sun_map([0.3, 0.8, 0.2], [2, 1.5, 1], w=40, h=20))
    (folder / "broken.exr").write_bytes(b"not an exr at all")
    nan = _sun_map([0, 1, 0], [1, 1, 1], w=32, h=16).astype(np.float32)
    nan[5, 5, 1] = np.nan
    write_exr(folder / "nan.exr", {"R": nan[..., 0], "G": nan[..., 1], "B": nan[..., 2]})


def test_cli_build_light_pca_end_to_end(tmp_path, cli):
    from reflectmm_cli.artifacts import read_artifact, read_image

    maps = tmp_path / "maps"
    _write_maps(maps)
    ws = tmp_path / "ws"
    r = cli("build-light-pca", "--input", maps, "--order", 3, "--rotations", 4, "--tilt", 20,
            "--components", 500, "--workspace", ws)
    assert r.exit_code == 0, r.stderr
    outs = r.stdout.split()
    assert outs[0].endswith("build-light-pca.npz") and outs[1].endswith(".png")
    assert "broken.exr" in r.stderr and "nan.exr" in r.stderr and "supports" in r.stderr
    art = read_artifact(outs[0], "light-model")
    assert int(art["order"]) == 3 and art["dc"].shape == (4 * 4 * 3, 3)
    assert art["bases"].shape[1] == 3 * 16 and art.meta["params"]["rotations"] == 4
    assert sorted(x["file"].rsplit("/", 1)[-1] for x in art.meta["skipped"]) == ["broken.exr", "nan.exr"]
    assert art.meta["n_maps"] == 4 and len(art["map_names"]) == 4
    prev = read_image(outs[1])
    assert prev.shape[2] >= 3 and prev.shape[0] > 16
    first = open(outs[0], "rb").read()
    # rerun → byte-identical artifact (no timestamps); --output overrides the workspace path
    r2 = cli("build-light-pca", maps / "env0.exr", maps / "env1.exr", maps / "probe.hdr", "-o", tmp_path / "lm.npz",
             "--order", 3, "--rotations", 4, "--tilt", 20, "--components", 500)
    assert r2.exit_code == 0, r2.stderr
    assert (tmp_path / "lm.npz").exists() and (tmp_path / "lm.png").exists()
    r3 = cli("build-light-pca", "--input", maps, "--order", 3, "--rotations", 4, "--tilt", 20,
             "--components", 500, "--workspace", ws)
    assert r3.exit_code == 0 and open(outs[0], "rb").read() == first


def test_cli_no_usable_map_fails_cleanly(tmp_path, cli):
    (tmp_path / "a.exr").write_bytes(b"junk")
    r = cli("build-light-pca", tmp_path / "a.exr", "-w", tmp_path)
    assert r.exit_code == 1
    assert "none of the 1 environment maps is usable" in r.stderr and "Traceback" not in r.stderr
    r = cli("build-light-pca", tmp_path / "missing.exr", "-w", tmp_path)
    assert r.exit_code == 1 and "missing.exr" in r.stderr


def test_registered_as_stage():
    from reflectmm_cli.stages import get_stage

    st = get_stage("build-light-pca")
    assert st.verb == "build-light-pca" and not st.per_identity


def test_stage_runs_from_a_recipe_context(tmp_path):
    # the same stage a recipe runs: unrelated [defaults] params (device) neither break it nor enter its key
    from reflectmm_cli.artifacts import read_artifact, write_exr
    from reflectmm_cli.stages import compute_cache_key, get_stage

    maps = tmp_path / "envmaps"
    maps.mkdir()
    for i, s in enumerate(([0, 1, 0], [1, 0.2, 0], [0, 0.3, -1])):
        img = _sun_map(s, [1, 1, 1]).astype(np.float32)
        write_exr(maps / f"m{i}.exr", {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    st = get_stage("build-light-pca")
    base = dict(workspace=tmp_path / "ws", inputs={"envmaps": [maps]})
    ctx = st.context(params={"order": 2, "rotations": 2, "components": 3, "device": "cpu"}, **base)
    ctx2 = st.context(params={"order": 2, "rotations": 2, "components": 3}, **base)
    assert compute_cache_key(st, ctx) == compute_cache_key(st, ctx2)
    out = st.run(ctx.with_(cache_key=compute_cache_key(st, ctx)))
    assert [p.name for p in out] == ["build-light-pca.npz", "build-light-pca.png"]
    assert read_artifact(out[0], "light-model").arrays["bases"].shape == (3, 27)


def test_light_model_of_zero_components_is_refused(tmp_path, cli):
    maps = tmp_path / "maps"
    _write_maps(maps)
    one = maps / "env0.exr"
    for args, want in (([one], "would have 0 components"),                       # one map, no rotations
                       ([maps, "--components", 0], "--components must be an integer ≥ 1")):
        r = cli("build-light-pca", *args, "-o", tmp_path / "lm.npz", "--order", 2)
        assert r.exit_code == 1 and want in r.stderr, r.stderr
        assert r.stderr.strip().splitlines()[-1].startswith("reflectmm: error: build-light-pca: ")
        assert not (tmp_path / "lm.npz").exists()
    # a constant (non-environment) EXR: normalised samples do not vary even when rotated
    from reflectmm_cli.artifacts import write_exr

    flat = np.full((16, 32), 0.7, np.float32)
    write_exr(tmp_path / "flat.exr", {"R": flat, "G": flat, "B": flat})
    r = cli("build-light-pca", tmp_path / "flat.exr", "--rotations", 4, "-o", tmp_path / "lm.npz", "--order", 2)
    assert r.exit_code == 1 and "0 components" in r.stderr
    # the same through a recipe stage
    (tmp_path / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.build-light-pca]\n'
                                     f'inputs = {{ envmaps = "{one}" }}\nparams = {{ order = 2 }}\n')
    r = cli("run", tmp_path / "r.toml", "-w", tmp_path / "ws")
    assert r.exit_code == 1 and "0 components" in r.stderr


def test_a_map_given_twice_counts_once(tmp_path, reflectmm_log):
    from reflectmm_cli.model.light import find_envmaps

    (tmp_path / "maps").mkdir()
    for n in ("a.exr", "b.exr"):
        (tmp_path / "maps" / n).write_bytes(b"")
    files = find_envmaps([tmp_path / "maps", tmp_path / "maps" / "a.exr", tmp_path / "maps" / "b.exr"])
    assert [f.name for f in files] == ["a.exr", "b.exr"]
    assert sum("given more than once" in m for m in reflectmm_log) == 2

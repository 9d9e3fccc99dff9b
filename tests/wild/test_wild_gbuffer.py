"""G-buffer: shading it with shade_env equals render_envmap of the same scene."""
import numpy as np
import pytest

from wild_testutil import head_rotation
from reflectmm_cli.geometry import Camera, RayScene, deep3d_camera, render_envmap
from reflectmm_cli.geometry.gbuffer import (gbuffer_for_image, gbuffer_nbytes, light_from_model_sh, pack_gbuffers,
                                            shade_gbuffer, unpack_gbuffer)

EXPS = np.array([1.0, 8.0, 64.0])


def _scene(face, seed=0, yaw=25.0, pitch=-8.0, roll=5.0, size=112):
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=face.n_shape) * face.shape_sigma
    exp = rng.normal(size=face.n_exp) * face.exp_sigma * 0.5
    cam0 = deep3d_camera()
    cam = Camera(cam0.K, head_rotation(yaw, pitch, roll), cam0.t + [3.0, -4.0, 20.0], 224, 224).with_size(size, size)
    V = face.n_vertices
    albedo = rng.uniform(0.2, 0.8, (V, 3))
    weights = rng.uniform(0.0, 0.3, (V, 3))
    sh = rng.normal(size=(3, 81)) * 0.1
    sh[:, 0] = 2.0
    return shape, exp, cam, albedo, weights, sh


@pytest.mark.parametrize("yaw", [0.0, 40.0, -35.0])
def test_gbuffer_shading_equals_render_envmap(small_face, yaw):
    shape, exp, cam, albedo, weights, sh = _scene(small_face, yaw=yaw)
    verts = small_face.vertices(shape, exp)
    scene = RayScene(verts, small_face.triangles)
    ref = render_envmap(scene, cam, albedo, weights, EXPS, sh)
    gb = gbuffer_for_image(small_face, shape, exp, cam.R, cam.t, cam.K, cam.width, dtype=np.float64)
    assert np.array_equal(gb["face_mask"], ref.mask)
    assert gb["face_mask"].sum() > 1000
    d, s = shade_gbuffer(gb, albedo, weights, EXPS, light_from_model_sh(sh, cam.R))
    img = np.zeros_like(ref.image, dtype=np.float64)
    img[gb["pix_yx"][:, 0], gb["pix_yx"][:, 1]] = d + s
    rel = np.abs(img - ref.image).max() / np.abs(ref.image).max()
    assert rel < 1e-4
    # the light frame matters: shading with the model-space coefficients does not match
    d2, s2 = shade_gbuffer(gb, albedo, weights, EXPS, sh)
    assert np.abs((d2 + s2) - ref.image[ref.mask]).max() / np.abs(ref.image).max() > 1e-2


def test_gbuffer_invariants_and_float16_error(small_face):
    shape, exp, cam, albedo, weights, sh = _scene(small_face, seed=1, yaw=30.0)
    gb = gbuffer_for_image(small_face, shape, exp, cam.R, cam.t, cam.K, cam.width, dtype=np.float64)
    gb16 = gbuffer_for_image(small_face, shape, exp, cam.R, cam.t, cam.K, cam.width)
    assert gb16["normal"].dtype == np.float16 and gb16["bary"].dtype == np.float32
    assert np.allclose(gb["bary"].sum(1), 1.0, atol=1e-6) and (gb["bary"] >= 0).all()
    for k in ("normal", "view", "reflect"):
        assert np.allclose(np.linalg.norm(gb[k], axis=1), 1.0, atol=1e-9)
        assert np.abs(gb16[k].astype(np.float64) - gb[k]).max() < 1e-3   # float16 spacing near 1: 4.9e-4
    ndv = (gb["normal"] * gb["view"]).sum(1)
    assert np.array_equal(gb["visible"], ndv > 0)
    assert np.allclose(gb["reflect"], 2 * ndv[:, None] * gb["normal"] - gb["view"], atol=1e-9)
    # the camera looks down −z of the light frame: view directions point towards +z
    assert (gb["view"][:, 2] > 0.9).all()
    # the float16 directions change the shading by a bounded amount (measured ≈ 1e-3 of the peak)
    sh_l = light_from_model_sh(sh, cam.R)
    d, s = shade_gbuffer(gb, albedo, weights, EXPS, sh_l)
    d16, s16 = shade_gbuffer(gb16, albedo, weights, EXPS, sh_l)
    err = np.abs((d16 + s16) - (d + s)).max() / np.abs(d + s).max()
    assert err < 5e-3
    # the vertex ids are the triangle hit
    tri_ids = set(map(tuple, np.sort(small_face.triangles, 1)))
    assert all(tuple(t) in tri_ids for t in np.sort(gb16["vert_ids"][::97], 1))


def test_pack_unpack_roundtrip(small_face):
    gbs = []
    for seed, yaw in ((0, 0.0), (1, 45.0)):
        shape, exp, cam, *_ = _scene(small_face, seed=seed, yaw=yaw, size=64)
        gbs.append(gbuffer_for_image(small_face, shape, exp, cam.R, cam.t, cam.K, cam.width))
    packed = pack_gbuffers(gbs)
    assert packed["pix_offset"].tolist() == [0, len(gbs[0]["bary"]), len(gbs[0]["bary"]) + len(gbs[1]["bary"])]
    assert packed["face_mask"].shape == (2, 64, 64)
    for i, g in enumerate(gbs):
        u = unpack_gbuffer(packed, i)
        for k, v in u.items():
            assert np.array_equal(v, g[k])
        assert gbuffer_nbytes(g) == len(g["bary"]) * (4 + 12 + 12 + 3 * 6 + 1)
        # rows are the mask's pixels in row-major order
        assert np.array_equal(np.flatnonzero(g["face_mask"]), g["pix_yx"][:, 0].astype(int) * 64 + g["pix_yx"][:, 1])

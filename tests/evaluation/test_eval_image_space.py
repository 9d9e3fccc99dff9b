"""Image-space re-rendering: crop windows, UV lookup and shadows agree with the geometry renderer on full frames."""
import numpy as np
import pytest

from reflectmm_cli.geometry import has_embree

pytestmark = pytest.mark.skipif(not has_embree(), reason="needs Embree")


def _mesh(g=24):
    u, v = np.meshgrid(np.linspace(0.02, 0.98, g), np.linspace(0.02, 0.98, g))
    x, y = (u - 0.5) * 160, (0.5 - v) * 200
    z = 70 * np.sqrt(np.clip(1 - ((u - 0.5) / 0.62) ** 2 - ((v - 0.5) / 0.62) ** 2, 0.02, 1))
    z += 25 * np.exp(-((u - 0.5) ** 2 + (v - 0.55) ** 2) / 0.004)  # a "nose" that casts shadows
    V = np.stack([x, y, z], -1).reshape(-1, 3)
    T = []
    for r in range(g - 1):
        for c in range(g - 1):
            i = r * g + c
            T += [(i, i + g, i + 1), (i + 1, i + g, i + g + 1)]
    T = np.array(T)
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    T[n[:, 2] < 0] = T[n[:, 2] < 0][:, ::-1]
    return V, T, np.stack([u, v], -1).reshape(-1, 2)


def test_image_space_matches_geometry_renderer():
    from reflectmm_cli.evaluation.image_space import ImageSpaceRenderer
    from reflectmm_cli.geometry import RayScene, look_at, render_point_light

    V, T, uv = _mesh()
    S = 32
    rng = np.random.default_rng(0)
    alb = rng.uniform(0.2, 0.7, (3, S, S))
    wts = rng.uniform(0.0, 0.2, (3, S, S))
    exps = np.array([1.0, 8.0, 64.0])
    W, H = 96, 80
    eyes = [np.array([0.0, 0.0, 900.0]), np.array([500.0, 0.0, 750.0])]
    flashes = [np.array([-450.0, 100.0, 800.0]), np.array([0.0, 0.0, 900.0])]
    cams = [look_at(e, (0, 0, 40), focal_px=300, width=W, height=H, name=f"c{i}") for i, e in enumerate(eyes)]
    scene = RayScene(V, T)
    x0, y0, w, h = 12, 7, 70, 60
    olat = np.zeros((2, 2, h, w, 3), np.float32)
    for vi, cam in enumerate(cams):
        for fi, L in enumerate(flashes):
            res = render_point_light(scene, cam, alb, wts, exps, L, 2e6, uv=uv, shadows=True)
            olat[vi, fi] = res.image[y0:y0 + h, x0:x0 + w]
    capture = {"view_names": np.array(["c0", "c1"]), "flash_ids": np.array(["01", "02"]),
               "crop_origin": np.array([[x0, y0], [x0, y0]]), "olat": olat,
               "saturated": np.zeros((2, 2, h, w), bool)}
    geometry = {"vertices": V, "view_names": np.array(["c0", "c1"]), "flash_ids": np.array(["01", "02"]),
                "K": np.stack([c.K for c in cams]), "R": np.stack([c.R for c in cams]),
                "t": np.stack([c.t for c in cams]), "flash_pos": np.stack(flashes),
                "flash_intensity": np.array([2e6, 2e6])}
    isr = ImageSpaceRenderer(capture, geometry, T, uv, name="x")
    for view in ("c0", "c1"):
        for fl in ("01", "02"):
            reg = isr.region(view, fl)
            pred = isr.render(alb, wts, exps, view, fl, key=1)
            tgt = isr.target(view, fl)
            assert reg.sum() > 500
            np.testing.assert_allclose(pred[reg], tgt[reg], rtol=1e-4, atol=1e-5)
            # outside the region the capture is dark (background or shadow) or the view is grazing
            assert np.all(pred[~reg] == 0)
    # the shadow of the nose is excluded: some face pixels are not in the region for the side flash
    _, r = isr.raster("c0")
    assert (r.mask & ~isr.region("c0", "01")).sum() > 0

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


def test_region_restricted_to_the_maps_domain():
    """With a domain (the uv-observations mask), a pixel is in the region iff its whole bilinear footprint lies in
    the domain (checked against an independent per-pixel texel lookup), so maps that are 0 outside their mask are
    never compared against the capture there."""
    from reflectmm_cli.evaluation.image_space import ImageSpaceRenderer
    from reflectmm_cli.geometry import RayScene, look_at, render_point_light

    V, T, uv = _mesh()
    S = 32
    rng = np.random.default_rng(1)
    alb = rng.uniform(0.2, 0.7, (3, S, S))
    wts = rng.uniform(0.0, 0.2, (3, S, S))
    exps = np.array([1.0, 8.0, 64.0])
    W, H = 96, 80
    cam = look_at(np.array([0.0, 0.0, 900.0]), (0, 0, 40), focal_px=300, width=W, height=H, name="c0")
    L = np.array([-200.0, 50.0, 900.0])
    res = render_point_light(RayScene(V, T), cam, alb, wts, exps, L, 2e6, uv=uv, shadows=True)
    capture = {"view_names": np.array(["c0"]), "flash_ids": np.array(["01"]), "crop_origin": np.array([[0, 0]]),
               "olat": res.image[None, None].astype(np.float32), "saturated": np.zeros((1, 1, H, W), bool)}
    geometry = {"vertices": V, "view_names": np.array(["c0"]), "flash_ids": np.array(["01"]), "K": cam.K[None],
                "R": cam.R[None], "t": cam.t[None], "flash_pos": L[None], "flash_intensity": np.array([2e6])}
    domain = np.ones((S, S), bool)
    domain[:, :9] = False  # a missing band on one side and a hole in the middle
    domain[14:17, 15:19] = False
    isr = ImageSpaceRenderer(capture, geometry, T, uv, name="x")
    full = isr.region("c0", "01").copy()
    isr.set_domain(domain)
    reg = isr.region("c0", "01")
    # independent footprint test: the (up to) 4 texels with non-zero bilinear weight
    _, r = isr.raster("c0")
    tri = T[r.tri_id[r.mask]]
    puv = np.einsum("mk,mkc->mc", r.bary[r.mask].astype(np.float64), uv[tri])
    x = np.clip(puv[:, 0] * S - 0.5, 0, S - 1)
    y = np.clip(puv[:, 1] * S - 0.5, 0, S - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    ok = np.ones(x.size, bool)
    for dy in (0, 1):
        for dx in (0, 1):
            wgt = (x - x0 if dx else 1 - (x - x0)) * (y - y0 if dy else 1 - (y - y0))
            yy, xx = np.minimum(y0 + dy, S - 1), np.minimum(x0 + dx, S - 1)
            ok &= (wgt < 1e-6) | domain[yy, xx]
    expect = np.zeros_like(full)
    expect[r.mask] = ok
    expect &= full
    assert full.sum() > 500 and (full & ~expect).sum() > 100  # the domain removes a real part of the face
    assert np.array_equal(reg, expect)
    # maps zeroed outside the domain still reproduce the capture exactly on the restricted region
    pred = isr.render(np.where(domain, alb, 0.0), np.where(domain, wts, 0.0), exps, "c0", "01")
    np.testing.assert_allclose(pred[reg], isr.target("c0", "01")[reg], rtol=1e-4, atol=1e-5)
    bad = full & ~reg
    assert np.abs(pred[bad] - isr.target("c0", "01")[bad]).max() > 1e-2  # and would not have outside it

"""Ray casting: the Embree rasteriser against an independent z-buffer, analytic spheres and planes; shadows
and visibility against closed-form occluders; UV rasterisation and map sampling."""
import numpy as np
import pytest
import trimesh

from reflectmm_cli.geometry import (
    RayScene,
    look_at,
    orbit_camera,
    procedural_face_model,
    rasterize,
    rasterize_uv,
    sample_uv_map,
    shadow_mask,
    uv_positions,
    vertex_normals,
    vertex_to_uv_map,
    visibility,
)


@pytest.fixture(scope="module")
def face():
    m = procedural_face_model(grid=(81, 61), n_shape=4, n_exp=2)
    return m, RayScene(m.mean_shape, m.triangles)


def _sphere(r=100.0, sub=5):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _ray_sphere(o, d, r):
    b = (o * d).sum(1)
    c = (o * o).sum(1) - r * r
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    return disc, t


def test_rasterize_against_independent_zbuffer(face):
    """Each sampled pixel's triangle must be the nearest of all triangles whose *projection* contains the pixel
    centre (brute force over all triangles with the camera's own projection, no ray tracer)."""
    m, scene = face
    cam = orbit_camera(yaw_deg=35, distance=700, focal_px=700, width=160, height=120)
    r = rasterize(scene, cam)
    uv, z = cam.project(m.mean_shape)
    P = uv[m.triangles]  # (T,3,2)
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(np.ones_like(r.mask))
    pick = rng.choice(len(rows), 300, replace=False)
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    o, dirs = cam.rays(np.stack([cols[pick], rows[pick]], 1).astype(float))
    for k, i in enumerate(pick):
        px = np.array([cols[i], rows[i]], float) - P[:, 0]
        l1 = (px[:, 0] * e2[:, 1] - px[:, 1] * e2[:, 0]) / det
        l2 = (e1[:, 0] * px[:, 1] - e1[:, 1] * px[:, 0]) / det
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9) & (np.abs(det) > 1e-12)
        cand = np.nonzero(inside)[0]
        if cand.size == 0:
            assert r.tri_id[rows[i], cols[i]] == -1
            continue
        # depth of each candidate along the pixel ray: intersect the triangle planes
        v0 = m.mean_shape[m.triangles[cand, 0]].astype(float)
        nrm = np.cross(m.mean_shape[m.triangles[cand, 1]] - v0, m.mean_shape[m.triangles[cand, 2]] - v0)
        t = ((v0 - o[k]) * nrm).sum(1) / (dirs[k] @ nrm.T)
        best = cand[np.argmin(t)]
        got = r.tri_id[rows[i], cols[i]]
        assert got >= 0
        zbest = np.min(t) * (dirs[k] @ cam.R[2])
        # same triangle, or a neighbour sharing the pixel at the same depth (edge ties)
        assert got == best or abs(r.depth[rows[i], cols[i]] - zbest) < 1e-3, (got, best)
        np.testing.assert_allclose(r.depth[rows[i], cols[i]], zbest, rtol=1e-5)


def test_rasterize_projected_vertices_hit_their_triangles(face):
    """Pixels at the projection of a visible vertex see a triangle containing it at the vertex depth."""
    m, scene = face
    cam = orbit_camera(yaw_deg=0, distance=600, focal_px=900, width=200, height=200)
    r = rasterize(scene, cam)
    uv, z = cam.project(m.mean_shape)
    vis = visibility(scene, m.mean_shape, vertex_normals(m.mean_shape, m.triangles), cam.center)
    # vertices on the mesh border are hit or missed by a grazing ray: leave them out
    e = np.sort(m.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    ue, cnt = np.unique(e, axis=0, return_counts=True)
    border = np.zeros(m.n_vertices, bool)
    border[ue[cnt == 1].ravel()] = True
    idx = np.nonzero(vis & ~border & (uv[:, 0] > 0) & (uv[:, 0] < 199) & (uv[:, 1] > 0) & (uv[:, 1] < 199))[0]
    assert len(idx) > 500
    # rays through the exact sub-pixel projections hit a triangle of the vertex at the vertex depth
    o, d = cam.rays(uv[idx])
    hit = scene.intersect(o, d, retry=True)
    zhit = hit["t"] * (d @ cam.R[2])
    # Embree (robust mode) still loses a few rays that pass exactly through a vertex: allow 0.5 %
    good = np.abs(zhit - z[idx]) < 2e-3
    assert good.mean() > 0.995, good.mean()
    own = np.array([vi in m.triangles[t] for vi, t in zip(idx, hit["tri"])])
    assert own.mean() > 0.99
    # the pixel containing the projection sees the surface within half a pixel's depth slope
    px = np.round(uv[idx]).astype(int)
    hitpx = r.mask[px[:, 1], px[:, 0]]
    assert hitpx.mean() > 0.98  # misses only where the pixel centre falls off the silhouette
    dz = np.abs(r.depth[px[:, 1], px[:, 0]] - z[idx])[hitpx]
    assert np.median(dz) < 0.3 and np.percentile(dz, 99) < 3.0


def test_rasterize_no_holes_on_symmetry_plane(face):
    """Odd image width: the centre pixel column lies exactly in the x = 0 plane of grid edges and vertices."""
    m, scene = face
    cam = orbit_camera(0, 0, 700, focal_px=1200, width=151, height=151)
    assert abs(cam.K[0, 2] - 75.0) < 1e-12
    r = rasterize(scene, cam)
    filled = r.mask.copy()
    interior = np.zeros_like(filled)
    interior[1:-1, 1:-1] = filled[:-2, 1:-1] & filled[2:, 1:-1] & filled[1:-1, :-2] & filled[1:-1, 2:]
    assert np.all(r.mask[interior])


def test_rasterize_sphere_analytic():
    rad = 100.0
    v, f = _sphere(rad, 5)
    scene = RayScene(v, f)
    cam = look_at((0, 0, 500), focal_px=300, width=96, height=96)
    r = rasterize(scene, cam)
    o, d = cam.rays()
    disc, t = _ray_sphere(o, d, rad)
    hit = (disc > 0).reshape(96, 96)
    # silhouette can differ only where the ray grazes the tessellated sphere
    margin = np.sqrt(np.maximum(disc, 0)).reshape(96, 96)
    assert np.all(r.mask[hit & (margin > 2.0)]) and not np.any(r.mask[~hit])
    m = r.mask & hit & (margin > 2.0)
    x = (o + d * t[:, None]).reshape(96, 96, 3)
    zc = (x @ cam.R[2] + cam.t[2])
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).max()
    sagitta = rad - np.sqrt(rad ** 2 - edge ** 2 / 3)  # chord depth of the circumscribed triangle
    radial = np.linalg.norm(r.position[m], axis=1)
    assert radial.min() > rad - 1.01 * sagitta and radial.max() < rad + 1e-3
    # the hit lies on the pixel's ray, at the rasterised depth
    od = (r.position[m] - o.reshape(96, 96, 3)[m])
    perp = np.linalg.norm(od - (od * d.reshape(96, 96, 3)[m]).sum(1, keepdims=True) * d.reshape(96, 96, 3)[m],
                          axis=1)
    assert perp.max() < 2e-3
    np.testing.assert_allclose(r.depth[m], r.position[m] @ cam.R[2] + cam.t[2], atol=1e-3)
    # depth agrees with the analytic sphere up to the tessellation error seen along the ray
    cosg = np.abs((d.reshape(96, 96, 3)[m] * x[m] / rad).sum(1))
    assert np.all(np.abs(r.depth[m] - zc[m]) <= 1.01 * sagitta / cosg + 1e-3)
    nrm = x / rad
    cosang = (r.normal[m] * nrm[m]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cosang.min(), -1, 1))) < 1.0
    # barycentrics reconstruct the hit point
    rec = np.einsum("mk,mkc->mc", r.bary[m], v[f[r.tri_id[m]]])
    np.testing.assert_allclose(rec, r.position[m], atol=1e-3)


def test_rasterize_plane_exact():
    v = np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    scene = RayScene(v, f)
    cam = look_at((100, -300, 400), (20, 10, 0), focal_px=200, width=50, height=40)
    r = rasterize(scene, cam)
    o, d = cam.rays()
    t = -o[:, 2] / d[:, 2]
    x = (o + d * t[:, None]).reshape(40, 50, 3)
    assert r.mask.all()
    np.testing.assert_allclose(r.position, x, atol=2e-3)
    np.testing.assert_allclose(r.depth, x @ cam.R[2] + cam.t[2], rtol=1e-5)
    np.testing.assert_allclose(r.normal, np.broadcast_to([0, 0, 1.0], r.normal.shape), atol=1e-6)


def _plate_scene():
    ground = np.array([[-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0]], float)
    plate = np.array([[-20, -20, 50], [20, -20, 50], [20, 20, 50], [-20, 20, 50]], float)
    v = np.concatenate([ground, plate])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return RayScene(v, f)


def test_shadow_of_a_plate():
    scene = _plate_scene()
    L = np.array([0.0, 0.0, 500.0])
    g = np.stack(np.meshgrid(np.linspace(-60, 60, 61), np.linspace(-60, 60, 61)), -1).reshape(-1, 2)
    pts = np.concatenate([g, np.zeros((len(g), 1))], 1)
    n = np.broadcast_to([0, 0, 1.0], pts.shape)
    lit = shadow_mask(scene, pts, n, L)
    half = 20 * 500 / 450  # the plate's shadow on the ground: |x|, |y| < 22.2
    inside = np.max(np.abs(g), 1) < half - 0.5
    outside = np.max(np.abs(g), 1) > half + 0.5
    assert not lit[inside].any() and lit[outside].all()
    assert scene.stats.skipped == 0 and scene.stats.cast == len(pts)
    # points facing away from the light cost no ray and are unlit
    lit2 = shadow_mask(scene, pts, -n, L)
    assert not lit2.any() and scene.stats.skipped == len(pts) and scene.stats.cast == 0
    # a light below the plate (between plate and ground) casts no plate shadow
    assert shadow_mask(scene, pts[inside], n[inside], [0, 0, 30.0]).all()
    # the plate itself (top side) is lit: no self-shadowing from the offset
    top = np.array([[0.0, 0.0, 50.0], [10, -5, 50]])
    assert shadow_mask(scene, top, np.broadcast_to([0, 0, 1.0], top.shape), L).all()


def test_visibility_sphere_and_occluder():
    rad = 50.0
    v, f = _sphere(rad, 4)
    scene = RayScene(v, f)
    eye = np.array([0.0, 0.0, 400.0])
    n = vertex_normals(v, f)
    vis = visibility(scene, v, n, eye)
    facing = ((eye - v) * (v / rad)).sum(1)
    assert np.all(vis[facing > 1.0]) and not np.any(vis[facing < -1.0])
    # add a plate between: points whose segment to the eye crosses the plate are hidden
    plate = np.array([[-15, -15, 150], [15, -15, 150], [15, 15, 150], [-15, 15, 150]], float)
    scene2 = RayScene(np.concatenate([v, plate]), np.concatenate([f, [[len(v), len(v) + 1, len(v) + 2],
                                                                      [len(v), len(v) + 2, len(v) + 3]]]))
    vis2 = visibility(scene2, v, n, eye)
    s = (150 - v[:, 2]) / (eye[2] - v[:, 2])  # where the segment crosses z = 150
    cross = v[:, :2] * (1 - s[:, None])
    blocked = np.max(np.abs(cross), 1) < 15 - 0.2
    clear = np.max(np.abs(cross), 1) > 15 + 0.2
    assert not vis2[blocked].any()
    np.testing.assert_array_equal(vis2[clear], vis[clear])


def test_face_nose_casts_shadow_from_a_side_flash(face):
    m, scene = face
    cam = orbit_camera(0, 0, 1000, focal_px=1500, width=200, height=200)
    r = rasterize(scene, cam)
    L = np.array([700.0, 0.0, 700.0])
    lit = shadow_mask(scene, r.position[r.mask], r.normal[r.mask], L)
    facing = ((L - r.position[r.mask]) * r.normal[r.mask]).sum(1) > 0
    shadowed = facing & ~lit
    x = r.position[r.mask]
    # cast shadow exists, on the subject's right (−x) side of the nose
    assert shadowed.sum() > 20
    assert np.median(x[shadowed, 0]) < 0


# ------------------------------------------------------------------------------------------ UV space

def test_rasterize_uv_coverage_and_barycentrics(face):
    m, _ = face
    S = 128
    ur = rasterize_uv(m.uv, m.triangles, S)
    c = (np.arange(S) + 0.5) / S
    lo, hi = m.uv.min(0), m.uv.max(0)
    inside = ((c[None, :] > lo[0] + 1e-6) & (c[None, :] < hi[0] - 1e-6)) & \
             ((c[:, None] > lo[1] + 1e-6) & (c[:, None] < hi[1] - 1e-6))
    np.testing.assert_array_equal(ur.mask, inside)  # the grid layout covers its bounding square exactly
    back = ur.interpolate(m.uv)
    rr, cc = np.nonzero(ur.mask)
    np.testing.assert_allclose(back[rr, cc, 0], c[cc], atol=1e-6)
    np.testing.assert_allclose(back[rr, cc, 1], c[rr], atol=1e-6)
    tri_id, bary, mask = ur  # tuple-style unpacking
    np.testing.assert_allclose(bary[mask].sum(1), 1.0, atol=1e-6)


def test_rasterize_uv_single_triangle_brute_force():
    uv = np.array([[0.1, 0.2], [0.83, 0.35], [0.3, 0.9]])
    ur = rasterize_uv(uv, np.array([[0, 1, 2]]), 40)
    c = (np.arange(40) + 0.5) / 40
    X, Y = np.meshgrid(c, c)
    q = np.stack([X, Y], -1)
    # independent inside test: the point is on the same side of all three edges (edge functions)
    sides = [np.sign((uv[(k + 1) % 3, 0] - uv[k, 0]) * (q[..., 1] - uv[k, 1])
                     - (uv[(k + 1) % 3, 1] - uv[k, 1]) * (q[..., 0] - uv[k, 0])) for k in range(3)]
    ref = (sides[0] == sides[1]) & (sides[1] == sides[2])
    assert np.sum(ur.mask != ref) <= 2  # only texels exactly on an edge may differ
    assert abs(ur.mask.sum() - 0.5 * abs(np.linalg.det(np.stack([uv[1] - uv[0], uv[2] - uv[0]]))) * 1600) < 12


def test_uv_positions_and_maps(face):
    m, _ = face
    S = 64
    ur = rasterize_uv(m.uv, m.triangles, S)
    n = vertex_normals(m.mean_shape, m.triangles)
    pos, nrm = uv_positions(m.mean_shape, n, ur)
    assert pos.shape == (S, S, 3) and np.allclose(np.linalg.norm(nrm[ur.mask], axis=1), 1, atol=1e-5)
    assert np.all(pos[~ur.mask] == 0)
    # a map that is linear in (u, v) is reproduced exactly by vertex→UV and by bilinear sampling
    a = np.array([[2.0, -1.0, 0.5], [0.3, 4.0, -2.0]])
    vals = m.uv.astype(np.float64) @ a[:, :2].T + a[:, 2]
    uvmap = vertex_to_uv_map(vals, ur)
    c = (np.arange(S) + 0.5) / S
    U, V = np.meshgrid(c, c)
    ref = np.stack([a[k, 0] * U + a[k, 1] * V + a[k, 2] for k in range(2)])
    np.testing.assert_allclose(uvmap[:, ur.mask], ref[:, ur.mask], atol=1e-5)
    q = np.random.default_rng(0).uniform(0.5 / S, 1 - 0.5 / S, size=(200, 2))
    np.testing.assert_allclose(sample_uv_map(ref, q), q @ a[:, :2].T + a[:, 2], atol=1e-9)
    assert sample_uv_map(ref[0], q).shape == (200,)
    assert vertex_to_uv_map(vals[:, 0], ur).shape == (S, S)


@pytest.mark.parametrize("yaw", [0.0, 30.0])
def test_landmark_projection_consistency(yaw):
    """Projected landmark vertices land on the rendered face at the landmark's depth, in iBUG image order."""
    m = procedural_face_model(n_vertices=12000, n_shape=4, n_exp=2)
    scene = RayScene(m.mean_shape, m.triangles)
    cam = orbit_camera(yaw, 0, 1000, focal_px=1500, width=640, height=480)
    r = rasterize(scene, cam)
    p = m.mean_shape[m.landmarks].astype(np.float64)
    uv, z = cam.project(p)
    n = vertex_normals(m.mean_shape, m.triangles)[m.landmarks]
    vis = visibility(scene, p, n, cam.center)
    if yaw == 0:
        assert vis.all()  # every landmark is visible frontally
        # image order: jaw runs left → right, right-eye landmarks left of the nose, left-eye ones right of it
        assert np.all(np.diff(uv[:17, 0]) > 0)
        assert uv[36:42, 0].max() < uv[30, 0] < uv[42:48, 0].min()
        assert uv[19, 1] < uv[37, 1] < uv[30, 1] < uv[51, 1] < uv[57, 1] < uv[8, 1]  # rows grow downwards
    else:
        assert vis[30] and not vis[:3].all()  # turned towards +x: the subject's right jaw hides behind the face
    inner = vis.copy()
    inner[:17] = False  # jaw-line landmarks may sit on the silhouette
    px = np.round(uv[inner]).astype(int)
    assert np.all(r.mask[px[:, 1], px[:, 0]])
    # at a depth edge (nose side, eye socket) the nearest pixel centre may see the other surface: use 3×3
    for (c, rr), zk in zip(px, z[inner]):
        win = r.depth[rr - 1:rr + 2, c - 1:c + 2][r.mask[rr - 1:rr + 2, c - 1:c + 2]]
        assert np.abs(win - zk).min() < 1.5
    for c, rr in np.round(uv[:17][vis[:17]]).astype(int):
        assert r.mask[rr - 1:rr + 2, c - 1:c + 2].any()


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=25)
@given(st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6), st.integers(4, 48))
def test_rasterize_uv_random_triangle(coords, S):
    """Every covered texel centre is inside the triangle (barycentrics ≥ 0 reproduce it); coverage ≈ area·S²."""
    uv = np.array(coords).reshape(3, 2)
    ur = rasterize_uv(uv, np.array([[0, 1, 2]]), S)
    area = 0.5 * abs(np.linalg.det(np.stack([uv[1] - uv[0], uv[2] - uv[0]])))
    c = (np.arange(S) + 0.5) / S
    rr, cc = np.nonzero(ur.mask)
    if rr.size:
        rec = ur.bary[rr, cc] @ uv
        np.testing.assert_allclose(rec[:, 0], c[cc], atol=1e-6)
        np.testing.assert_allclose(rec[:, 1], c[rr], atol=1e-6)
    perim = sum(np.linalg.norm(uv[k] - uv[(k + 1) % 3]) for k in range(3))
    assert abs(ur.mask.sum() - area * S * S) <= perim * S + 2  # Pick's-theorem-like bound


def test_cylindrical_uv_symmetric_and_offset_invariant(face):
    from reflectmm_cli.geometry import cylindrical_uv, uv_distortion

    m, _ = face
    uv = cylindrical_uv(m.mean_shape)
    mi = m.mirror_index()
    np.testing.assert_allclose(uv[mi, 0], 1 - uv[:, 0], atol=1e-5)
    np.testing.assert_allclose(uv[mi, 1], uv[:, 1], atol=1e-6)
    shifted = cylindrical_uv(m.mean_shape + np.array([12.0, -30.0, 5.0]))  # a model not centred on x = 0
    np.testing.assert_allclose(shifted, uv, atol=1e-5)
    d = uv_distortion(m.mean_shape, m.triangles, uv)
    assert d["flipped_fraction"] == 0 and 0.5 < d["area_ratio_p5"] and d["area_ratio_p95"] < 2.0


def test_visibility_agrees_with_zbuffer(face):
    """Vertex visibility by shadow-ray-style segments agrees with a depth test against the rasterised depth."""
    m, scene = face
    cam = orbit_camera(55, 10, 700, focal_px=1400, width=400, height=400)
    r = rasterize(scene, cam)
    n = vertex_normals(m.mean_shape, m.triangles)
    vis = visibility(scene, m.mean_shape, n, cam.center)
    uv, z = cam.project(m.mean_shape)
    px = np.round(uv).astype(int)
    inside = (px[:, 0] >= 1) & (px[:, 0] < 399) & (px[:, 1] >= 1) & (px[:, 1] < 399)
    idx = np.nonzero(inside)[0]
    # farthest hit in the 3×3 window (all nine pixels must hit): hidden if even that is nearer than the vertex
    zbuf = np.array([r.depth[y - 1:y + 2, x - 1:x + 2].max() if r.mask[y - 1:y + 2, x - 1:x + 2].all() else 0.0
                     for x, y in px[idx]])
    facing = ((cam.center - m.mean_shape[idx]) * n[idx]).sum(1) > 0
    hidden = facing & (zbuf > 0) & (zbuf < z[idx] - 3.0)
    clear = facing & (np.abs(np.array([r.depth[y, x] for x, y in px[idx]]) - z[idx]) < 0.3)
    assert hidden.sum() > 50 and clear.sum() > 500
    assert not vis[idx[hidden]].any()
    assert vis[idx[clear]].mean() > 0.99

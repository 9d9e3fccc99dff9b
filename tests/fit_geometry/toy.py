"""A small, independent face-like morphable model, rig and ray-traced renderer for the geometry-fit tests."""

from __future__ import annotations

import math

import numpy as np

from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry_fit.model import ShapeModel


def _layout68() -> np.ndarray:
    """An iBUG-68-like 2-D layout (x right, y up; mm on the face front)."""
    pts = []
    for a in np.linspace(-100, 100, 17):  # jaw: a U from ear to ear
        r = math.radians(a)
        pts.append([62 * math.sin(r), -25 - 55 * math.cos(r) + 20])
    for side in (-1, 1):  # brows
        for k in range(5):
            pts.append([side * (12 + 9 * k) if side > 0 else -(48 - 9 * k), 38 + 4 * math.sin(math.pi * k / 4)])
    for k in range(4):  # nose bridge
        pts.append([0.0, 28 - 9 * k])
    for k in range(5):  # nose base
        pts.append([-12 + 6 * k, -8 - 3 * (1 - abs(k - 2) / 2)])
    for cx in (-30, 30):  # eyes, 6 points each
        for k in range(6):
            a = 2 * math.pi * k / 6
            pts.append([cx - 11 * math.cos(a), 22 + 5 * math.sin(a)])
    for k in range(12):  # outer mouth
        a = 2 * math.pi * k / 12
        pts.append([-25 * math.cos(a), -35 + 10 * math.sin(a)])
    for k in range(8):  # inner mouth
        a = 2 * math.pi * k / 8
        pts.append([-16 * math.cos(a), -35 + 4 * math.sin(a)])
    return np.array(pts)


def toy_model(n_lon: int = 41, n_lat: int = 41, n_shape: int = 8, n_exp: int = 4, seed: int = 0,
              texture: bool = False) -> ShapeModel:
    rng = np.random.default_rng(seed)
    lon = np.radians(np.linspace(-105, 105, n_lon))
    lat = np.radians(np.linspace(-75, 75, n_lat))
    LA, LO = np.meshgrid(lat, lon, indexing="ij")
    a, b, c = 75.0, 100.0, 90.0
    x = a * np.cos(LA) * np.sin(LO)
    y = b * np.sin(LA)
    z = c * np.cos(LA) * np.cos(LO) - 40.0
    z = z + 28.0 * np.exp(-(x ** 2 + (y + 2) ** 2 / 2.0) / (2 * 11.0 ** 2))  # nose
    z = z - 8.0 * np.exp(-((np.abs(x) - 30) ** 2 + (y - 22) ** 2) / (2 * 9.0 ** 2))  # eye sockets
    mean = np.stack([x, y, z], -1).reshape(-1, 3)
    tri = []
    for i in range(n_lat - 1):
        for j in range(n_lon - 1):
            p = i * n_lon + j
            tri.append([p, p + 1, p + n_lon + 1])
            tri.append([p, p + n_lon + 1, p + n_lon])
    tri = np.array(tri)
    # orient outward (+z for the front)
    nrm = vertex_normals(mean, tri, dtype=np.float64)
    if nrm[(n_lat // 2) * n_lon + n_lon // 2, 2] < 0:
        tri = tri[:, ::-1].copy()
    lay = _layout68()
    xy = mean[:, :2]
    front = mean[:, 2] > -20
    lm = np.array([np.argmin(np.where(front, ((xy - p) ** 2).sum(-1), np.inf)) for p in lay])

    def smooth_fields(k):
        s = mean / np.array([a, b, c])
        out = []
        for _ in range(k):
            # quadratic and cubic fields only: no translation/rotation/scale-like linear modes
            coef = rng.normal(size=(3, 9))
            feats = np.stack([s[:, 0] ** 2, s[:, 1] ** 2, s[:, 0] * s[:, 1], s[:, 1] * s[:, 2], s[:, 0] * s[:, 2],
                              s[:, 2] ** 2, s[:, 0] ** 2 * s[:, 1], s[:, 1] ** 3, s[:, 0] * s[:, 1] ** 2], -1)
            fld = feats @ coef.T
            fld -= fld.mean(0)
            out.append(fld / np.sqrt((fld ** 2).sum(-1).mean()))
        return np.array(out)

    shape_basis = smooth_fields(n_shape)
    exp_basis = smooth_fields(n_exp) * (np.abs(mean[:, 1:2]) < 70)[None]
    shape_sigma = 8.0 * 0.8 ** np.arange(n_shape)
    exp_sigma = 4.0 * 0.8 ** np.arange(n_exp)
    tex = None
    if texture:
        pattern = 1 + 0.15 * np.sin(mean[:, :1] / 9.0) * np.cos(mean[:, 1:2] / 13.0)
        tex = np.clip(np.array([0.6, 0.42, 0.33]) * pattern, 0, 1)
    return ShapeModel(mean=mean, shape_basis=shape_basis, shape_sigma=shape_sigma, exp_basis=exp_basis,
                      exp_sigma=exp_sigma, triangles=tri, landmarks=lm, skin_mask=mean[:, 2] > -30, mean_tex=tex)


def look_at(position, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    c = np.asarray(position, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    yv = -(np.asarray(up, float) - np.dot(up, z) * z)
    yv /= np.linalg.norm(yv)
    x = np.cross(yv, z)
    R = np.stack([x, yv, z])
    return R, -R @ c


def arc_cameras(azimuths_deg, radius=1300.0, focal=1000.0, width=640, height=480, elevation_deg=0.0):
    K, R, t = [], [], []
    for az in azimuths_deg:
        a, e = math.radians(az), math.radians(elevation_deg)
        pos = [radius * math.cos(e) * math.sin(a), radius * math.sin(e), radius * math.cos(e) * math.cos(a)]
        Rv, tv = look_at(pos)
        K.append([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
        R.append(Rv)
        t.append(tv)
    return np.array(K, float), np.array(R), np.array(t)


def rotvec_matrix(w):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def _primary_hits(vertices, triangles, albedo, K, R, t, width, height):
    """Primary rays through every pixel centre → (ray intersector, mesh, pixel ids hit, hit points, triangle ids,
    interpolated unit normals, interpolated albedo)."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    mesh = trimesh.Trimesh(vertices=vertices, faces=triangles, process=False)
    ray = RayMeshIntersector(mesh)
    c = -R.T @ t
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    d = d_cam @ R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    tri_id, ray_id, loc = ray.intersects_id(np.broadcast_to(c, d.shape), d, multiple_hits=False,
                                            return_locations=True)
    vn = vertex_normals(vertices, triangles, dtype=np.float64)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri_id], loc)
    f = triangles[tri_id]
    n = (bary[:, :, None] * vn[f]).sum(1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    alb = (bary[:, :, None] * albedo[f]).sum(1)
    return ray, mesh, ray_id, loc, tri_id, n, alb


def render(vertices, triangles, albedo, sh, K, R, t, width, height):
    """Ray-traced Lambertian SH render (independent of the fit code): (H, W, 3) linear image, 0 background.

    Per pixel: primary ray → triangle hit → barycentric normal/albedo → albedo/π Σ A_l K_lm Y_lm(n).
    """
    _, _, ray_id, _, _, n, alb = _primary_hits(vertices, triangles, albedo, K, R, t, width, height)
    img = np.zeros((height * width, 3))
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    # explicit real SH (order 2, Condon–Shortley phase), flat index l²+l+m
    Y = np.stack([np.full_like(nx, 0.5 / math.sqrt(math.pi)),
                  -math.sqrt(3 / (4 * math.pi)) * ny, math.sqrt(3 / (4 * math.pi)) * nz,
                  -math.sqrt(3 / (4 * math.pi)) * nx,
                  0.5 * math.sqrt(15 / math.pi) * nx * ny, -0.5 * math.sqrt(15 / math.pi) * ny * nz,
                  0.25 * math.sqrt(5 / math.pi) * (3 * nz ** 2 - 1), -0.5 * math.sqrt(15 / math.pi) * nx * nz,
                  0.25 * math.sqrt(15 / math.pi) * (nx ** 2 - ny ** 2)], -1)
    A = np.array([math.pi] + [2 * math.pi / 3] * 3 + [math.pi / 4] * 5)
    img[ray_id] = alb / math.pi * (Y @ (A[:, None] * sh))
    return img.reshape(height, width, 3)


def render_point(vertices, triangles, albedo, light_pos, intensity, K, R, t, width, height):
    """Ray-traced Lambertian render under one point light, with cast shadows (independent of the fit code):
    (H, W, 3) linear image, 0 background.  Per pixel: primary ray → hit → barycentric normal/albedo →
    ``albedo/π · I · max(n·l, 0)/d²`` unless the segment to the light hits the mesh."""
    ray, mesh, ray_id, loc, tri_id, n, alb = _primary_hits(vertices, triangles, albedo, K, R, t, width, height)
    to_l = np.asarray(light_pos, float)[None] - loc
    dist = np.linalg.norm(to_l, axis=-1)
    ldir = to_l / dist[:, None]
    # shadow rays: start just off the surface (along the geometric normal side of the light)
    fn = mesh.face_normals[tri_id]
    origin = loc + 1e-3 * np.sign((fn * ldir).sum(-1))[:, None] * fn
    blocked = np.zeros(len(loc), dtype=bool)
    hit_tri, hit_ray, hit_loc = ray.intersects_id(origin, ldir, multiple_hits=False, return_locations=True)
    if len(hit_ray):
        blocked[hit_ray] = np.linalg.norm(hit_loc - origin[hit_ray], axis=-1) < dist[hit_ray]
    irr = intensity * np.clip((n * ldir).sum(-1), 0.0, None) / dist ** 2 * ~blocked
    img = np.zeros((height * width, 3))
    img[ray_id] = alb / math.pi * irr[:, None]
    return img.reshape(height, width, 3)

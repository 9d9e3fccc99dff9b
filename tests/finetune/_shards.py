"""Small synthetic wild-shard data for the finetuning tests: a spherical cap mesh seen by a frontal camera,
ray-cast once with the project's Embree rasteriser, a known per-vertex reflectance model ("truth"), a small light
model, and images shaded with the numpy SH path (independent of the torch G-buffer code under test)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import write_artifact
from reflectmm_cli.geometry import RayScene, look_at, rasterize
from reflectmm_cli.model.pca import MODEL_KIND, ReflectanceModel, model_arrays
from reflectmm_cli.shading import shade_env
from reflectmm_cli.model.light import LIGHT_MODEL_KIND, LightModel, light_from_coeffs, light_model_arrays

RADIUS = 50.0
EXPONENTS = np.array([1.0, 8.0, 64.0])


def cap_mesh(n=17, half=0.7 * RADIUS):
    g = np.linspace(-half, half, n)
    X, Y = np.meshgrid(g, g)
    Z = np.sqrt(RADIUS ** 2 - X ** 2 - Y ** 2)
    V = np.stack([X, Y, Z], -1).reshape(-1, 3)
    tri = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            tri += [(a, b, e), (a, e, d)]
    tri = np.array(tri, np.int32)
    # orient outwards (+z)
    nrm = np.cross(V[tri[:, 1]] - V[tri[:, 0]], V[tri[:, 2]] - V[tri[:, 0]])
    flip = nrm[:, 2] < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    uv = np.stack([(X.ravel() / half + 1) / 2, (1 - Y.ravel() / half) / 2], -1)
    return V, tri, uv


def _orthonormal(rows):
    q, _ = np.linalg.qr(rows.T)
    return q.T


def truth_model(V, m=3, seed=0, uv_size=8) -> ReflectanceModel:
    """A per-vertex model with smooth fields: mean albedo, m orthonormal diffuse bases, transferred lobe bases."""
    rng = np.random.default_rng(seed)
    nv = V.shape[0]
    x, y = V[:, 0] / RADIUS, V[:, 1] / RADIUS
    mean = np.stack([0.55 + 0.08 * np.sin(3 * x), 0.40 + 0.06 * np.cos(2 * y), 0.30 + 0.05 * x * y], -1)
    fields = []
    for k in range(m):
        f = np.stack([np.sin((k + 1) * x + c) * np.cos((k + 2) * y - c) for c in (0.3, 1.1, 2.0)], -1)
        fields.append(f.ravel())
    B = _orthonormal(np.stack(fields)).reshape(m, nv, 3)
    sigma = 0.08 * np.sqrt(3 * nv) * np.array([1.0, 0.7, 0.5])[:m]
    wmean = np.tile([0.03, 0.05, 0.02], (nv, 1)) * (1 + 0.3 * x[:, None])
    wb = np.stack([np.stack([np.cos((k + 1) * x + j) for j in range(3)], -1) for k in range(m)])
    wb = wb * (0.01 / sigma[:, None, None]) * np.array([0.3, 0.5, 0.2])
    S = uv_size
    mdl = ReflectanceModel(
        albedo_mean=np.zeros((3, S, S), np.float32), albedo_basis=np.zeros((m, 3, S, S), np.float32),
        weights_mean=np.zeros((3, S, S), np.float32), weights_basis=np.zeros((m, 3, S, S), np.float32),
        sigma=sigma.astype(np.float32), explained_variance=(sigma ** 2).astype(np.float32),
        explained_variance_ratio=np.full(m, 1.0 / m, np.float32), exponents=EXPONENTS.astype(np.float32),
        mask=np.ones((S, S), bool), train_coeffs=np.zeros((2, m), np.float32), ids=["a", "b"],
        vertex_albedo_mean=mean.astype(np.float32), vertex_albedo_basis=B.astype(np.float32),
        vertex_weights_mean=wmean.astype(np.float32), vertex_weights_basis=wb.astype(np.float32))
    return mdl


def small_light_model(order=2, k=4, seed=1) -> LightModel:
    rng = np.random.default_rng(seed)
    n = (order + 1) ** 2
    mean = np.zeros((3, n))
    mean[:, 0] = 1.0
    mean[:, 2] = 0.6  # light from above (+y is index 1? l=1: m=-1 → y) — a bright upper hemisphere
    mean[:, 1] = 0.5
    mean[:, 3] = 0.1
    rows = rng.normal(size=(k, 3, n))
    rows[:, :, 0] = 0.0
    bases = _orthonormal(rows.reshape(k, -1))
    sigma = np.array([0.5, 0.35, 0.25, 0.15, 0.1, 0.08][:k])
    return LightModel(order=order, mean=mean.reshape(-1), bases=bases, sigma=sigma, explained_variance=sigma ** 2,
                      explained_variance_ratio=sigma ** 2 / (sigma ** 2).sum(), dc=np.full((4, 3), 2.5),
                      sample_map=np.arange(4), sample_rotation=np.tile(np.eye(3), (4, 1, 1)),
                      map_names=["a", "b", "c", "d"])


def gbuffer(V, tri, size=32, distance=400.0, frame=0.8):
    eye = np.array([0.0, 0.0, distance])
    cam = look_at(eye, (0, 0, 0), (0, 1, 0), focal_px=size * distance / (2.0 * RADIUS * frame), width=size,
                  height=size)
    r = rasterize(RayScene(V, tri), cam)
    m = r.mask
    yx = np.argwhere(m)
    nrm = r.normal[m].astype(np.float64)
    pos = r.position[m].astype(np.float64)
    view = eye - pos
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    refl = 2 * (nrm * view).sum(1, keepdims=True) * nrm - view
    return {"mask": m, "pix_yx": yx.astype(np.int16), "vert_ids": tri[r.tri_id[m]].astype(np.int32),
            "bary": r.bary[m].astype(np.float32), "normal": nrm, "view": view, "reflect": refl,
            "visible": (nrm * view).sum(1) > 0, "camera": cam}


def render_truth(model, light, gb, beta, gamma, z):
    """Linear (S,S,3) image, diffuse and specular layers with the numpy SH shader (per-pixel interpolation)."""
    from reflectmm_cli.model.pca import sample_model

    alb, wts = sample_model(model, beta, space="vertex")
    c = np.einsum("pk,pkc->pc", gb["bary"], alb[gb["vert_ids"]])
    w = np.einsum("pk,pkc->pc", gb["bary"], wts[gb["vert_ids"]])
    K = light_from_coeffs(light, gamma, z)
    d, s = shade_env(c, w, model.exponents.astype(np.float64), gb["normal"], gb["view"], K)
    S = gb["mask"].shape[0]
    out = []
    for layer in (d + s, d, s):
        img = np.zeros((S, S, 3))
        img[gb["mask"]] = layer
        out.append(img)
    return out


def make_dataset(tmp: Path, n_images=12, size=32, seed=0, order=2, split=None, n_shards=1, m=3, mesh_n=17,
                 truth=None, light=None, nan_image=False):
    """Write shard(s), the truth model and the light model. Returns dict of paths and objects."""
    tmp = Path(tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    V, tri, uv = cap_mesh(mesh_n)
    truth = truth or truth_model(V, m)
    light = light or small_light_model(order)
    gb = gbuffer(V, tri, size)
    k = light.n_components
    betas = rng.normal(0, 1, (n_images, truth.n_components))
    gammas = rng.normal(0, 1, (n_images, k))
    zs = rng.uniform(1.6, 2.4, (n_images, 1)) * np.array([1.0, 0.97, 0.94])
    split = split or (["train"] * (n_images - max(2, n_images // 4)) + ["val"] * max(2, n_images // 4))
    images, diffs, specs = [], [], []
    for i in range(n_images):
        full, d, s = render_truth(truth, light, gb, betas[i], gammas[i], zs[i])
        images.append(np.clip(np.round(np.clip(full, 0, 1) ** (1 / 1.2) * 255), 0, 255).astype(np.uint8))
        diffs.append(d)
        specs.append(s)
    paths = []
    per = int(np.ceil(n_images / n_shards))
    P = len(gb["pix_yx"])
    for si in range(n_shards):
        idx = list(range(si * per, min(n_images, (si + 1) * per)))
        nn = len(idx)
        img = np.stack([images[i] for i in idx])
        if nan_image:
            img = img.astype(np.float32) / 255
            img[0, 3, 3, 0] = np.nan
        arrays = {
            "names": np.array([f"img{i:03d}" for i in idx]), "split": np.array([split[i] for i in idx]),
            "image": img, "face_mask": np.repeat(gb["mask"][None], nn, 0),
            "skin_mask": np.repeat(gb["mask"][None], nn, 0), "landmarks": np.zeros((nn, 68, 2), np.float32),
            "pix_offset": np.arange(nn + 1, dtype=np.int64) * P,
            "pix_yx": np.tile(gb["pix_yx"], (nn, 1)), "vert_ids": np.tile(gb["vert_ids"], (nn, 1)),
            "bary": np.tile(gb["bary"], (nn, 1)),
            "normal": np.tile(gb["normal"], (nn, 1)).astype(np.float16),
            "view": np.tile(gb["view"], (nn, 1)).astype(np.float16),
            "reflect": np.tile(gb["reflect"], (nn, 1)).astype(np.float16),
            "visible": np.tile(gb["visible"], nn),
            "shape": np.zeros((nn, 1), np.float32), "expression": np.zeros((nn, 1), np.float32),
            "R": np.tile(gb["camera"].R, (nn, 1, 1)), "t": np.tile(gb["camera"].t, (nn, 1)),
            "K": np.tile(gb["camera"].K, (nn, 1, 1)),
            "truth_beta": betas[idx].astype(np.float32), "truth_sh": light_from_coeffs(
                light, gammas[idx], zs[idx]).astype(np.float32),
            "truth_diffuse": np.stack([diffs[i] for i in idx]).astype(np.float16),
            "truth_specular": np.stack([specs[i] for i in idx]).astype(np.float16),
        }
        p = tmp / f"shard{si:02d}.npz"
        write_artifact(p, "wild-shard", arrays, compress=False,
                       extra_meta={"image_size": size, "encoding": "gamma1.2", "sh_order": order})
        paths.append(p)
    mp = tmp / "truth_model.npz"
    write_artifact(mp, MODEL_KIND, model_arrays(truth))
    lp = tmp / "light.npz"
    write_artifact(lp, LIGHT_MODEL_KIND, light_model_arrays(light))
    return {"shards": paths, "truth": truth, "truth_path": mp, "light": light, "light_path": lp, "gb": gb,
            "V": V, "tri": tri, "uv": uv, "betas": betas, "gammas": gammas, "zs": zs}


def write_model(path, model):
    write_artifact(path, MODEL_KIND, model_arrays(model))
    return path


def write_face_model(path, V, tri, uv):
    """A minimal face-model artifact for the cap (no shape/expression variation)."""
    from reflectmm_cli.geometry.face_model import FaceModel, save_face_model

    n = V.shape[0]
    fm = FaceModel(mean_shape=V, shape_basis=np.zeros((1, n, 3)), shape_sigma=np.ones(1),
                   exp_basis=np.zeros((1, n, 3)), exp_sigma=np.ones(1), triangles=tri, uv=uv,
                   landmarks=np.arange(68) % n, skin_mask=np.ones(n, bool), name="cap")
    return save_face_model(fm, path)


def wrong_initial(truth, V, seed=5):
    """The truth with its mean albedo perturbed by a smooth spatial pattern and its third diffuse component
    replaced by an unrelated unit vector (the true component is missing)."""
    import copy

    init = copy.deepcopy(truth)
    x, y = V[:, 0] / RADIUS, V[:, 1] / RADIUS
    init.vertex_albedo_mean = (truth.vertex_albedo_mean + 0.12 * np.stack(
        [np.sin(2 * x + 1), np.cos(3 * y), np.sin(3 * x * y)], -1)).astype(np.float32)
    b3 = np.random.default_rng(seed).normal(size=truth.vertex_albedo_basis[2].shape)
    init.vertex_albedo_basis = truth.vertex_albedo_basis.copy()
    init.vertex_albedo_basis[2] = b3 / np.linalg.norm(b3)
    return init


def model_of_fewer_vertices(src, dst, n=5):
    """A copy of the reflectance-model artifact ``src`` whose per-vertex part keeps its first ``n`` vertices: a model
    of another (smaller) mesh, for the checks that refuse it."""
    from reflectmm_cli.artifacts import read_artifact, write_artifact

    art = read_artifact(src, "reflectance-model")
    arrays = dict(art.arrays)
    for k in ("vertex_albedo_mean", "vertex_weights_mean"):
        arrays[k] = arrays[k][:n]
    for k in ("vertex_albedo_basis", "vertex_weights_basis"):
        arrays[k] = arrays[k][:, :n]
    return write_artifact(dst, "reflectance-model", arrays, extra_meta={"stats": art.meta.get("stats")})

"""Face-model tools: previews, mesh export, the procedural model and BFM import as artifacts — the library
entries of ``reflectmm face-model`` (docs/geometry.md)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

log = logging.getLogger("reflectmm")

__all__ = ["preview_image", "preview_sheet", "export_mesh", "create_model", "read_landmark_indices", "import_model"]


def preview_image(model, width: int = 320, height: int = 400, yaws=(0.0, 45.0, 90.0), vertices=None,
                  marks=None) -> np.ndarray:
    """A shaded grey preview (front, 45°, profile) with landmarks in red; float (H, W·3, 3) in [0, 1].

    ``marks``: ``[(vertex ids, (r, g, b)), …]`` drawn in that order instead of the landmarks in red."""
    from reflectmm_cli.geometry import RayScene, orbit_camera, rasterize

    v = model.mean_shape if vertices is None else vertices
    scene = RayScene(v, model.triangles)
    focal = 0.8 * height * 1000.0 / 230.0
    tiles = []
    for yaw in yaws:
        cam = orbit_camera(yaw, 0.0, 1000.0, target=(0.0, 10.0, 40.0), focal_px=focal, width=width, height=height)
        r = rasterize(scene, cam)
        key = cam.center + np.array([300.0, 300.0, 0.0])
        ld = key - r.position
        ld /= np.maximum(np.linalg.norm(ld, axis=-1, keepdims=True), 1e-9)
        shade = 0.15 + 0.8 * np.clip((r.normal * ld).sum(-1), 0, 1)
        skin = r.interpolate(model.skin_mask.astype(np.float32)[:, None], model.triangles)[..., 0]
        col = np.stack([shade, shade * (0.75 + 0.25 * skin), shade * (0.65 + 0.35 * skin)], -1) * r.mask[..., None]
        img = np.where(r.mask[..., None], col, 0.08)
        for ids, color in (marks if marks is not None else [(model.landmarks, (1.0, 0.1, 0.1))]):
            if not np.asarray(ids).size:
                continue
            uv, _ = cam.project(v[np.asarray(ids)])
            vis_ok = np.isfinite(uv).all(1)
            for (x, y) in uv[vis_ok]:
                xi, yi = int(round(x)), int(round(y))
                img[max(yi - 1, 0):yi + 2, max(xi - 1, 0):xi + 2] = color
        tiles.append(img)
    return np.concatenate(tiles, axis=1)


def preview_sheet(model, width: int = 320, height: int = 400) -> np.ndarray:
    """Preview contact sheet: row 1 the mean (front, 45°, profile); row 2 two random identities and one random
    expression at 1.5σ (fixed seed), frontal — a quick visual check of the bases' variation."""
    top = preview_image(model, width, height)
    rng = np.random.default_rng(12345)
    tiles = []
    for kind in ("shape", "shape", "exp"):
        a = rng.normal(size=model.n_shape) * model.shape_sigma * 1.5 if kind == "shape" and model.n_shape else None
        d = rng.normal(size=model.n_exp) * model.exp_sigma * 1.5 if kind == "exp" and model.n_exp else None
        tiles.append(preview_image(model, width, height, yaws=(20.0,), vertices=model.vertices(a, d)))
    return np.concatenate([top, np.concatenate(tiles, axis=1)], axis=0)


def export_mesh(model, out: Path, shape=None, exp=None) -> Path:
    """Write the mesh (mean or given coefficients) as OBJ/PLY/GLB with UVs via trimesh (atomic).

    OBJ texture coordinates follow the OBJ convention (v up): ``vt = (u, 1 − v)`` of our v-down layout, so a UV
    map saved as an image (row 0 = top) textures the mesh correctly.
    """
    import trimesh

    from reflectmm_cli.artifacts import atomic_path

    out = Path(out)
    ext = out.suffix.lower()
    if ext not in (".obj", ".ply", ".glb", ".off", ".stl"):
        raise ReflectmmError("unsupported mesh format (use .obj, .ply, .glb, .off or .stl)", out)
    v = model.vertices(shape, exp)
    uv = np.stack([model.uv[:, 0], 1.0 - model.uv[:, 1]], 1)
    visual = trimesh.visual.TextureVisuals(uv=uv)
    mesh = trimesh.Trimesh(v, model.triangles, visual=visual, process=False)
    if ext == ".obj":
        data = trimesh.exchange.obj.export_obj(mesh, include_texture=True, include_normals=True,
                                               header="reflectmm face model: " + model.name, write_texture=False,
                                               mtl_name=None)
        text = data if isinstance(data, str) else data.decode()
        # no material file is written: drop the mtllib/usemtl references trimesh adds for UVs
        text = "\n".join(ln for ln in text.splitlines() if not ln.startswith(("mtllib", "usemtl"))) + "\n"
        payload = text.encode()
    elif ext == ".ply":
        # trimesh's PLY writer keeps vertex UVs as the 's', 't' vertex properties
        payload = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True)
    else:
        payload = mesh.export(file_type=ext[1:])
    with atomic_path(out, suffix=ext) as tmp:
        tmp.write_bytes(payload if isinstance(payload, bytes) else payload.encode())
    return out


def create_model(out: Path, vertices: int = 35000, seed: int = 0, shape_components: int = 40,
                 exp_components: int = 20, *, preview: bool = True, meta: dict | None = None) -> list[Path]:
    """Library entry: build the procedural model, write the artifact (+ ``<out>.png`` preview)."""
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.geometry import procedural_face_model, save_face_model

    model = procedural_face_model(n_vertices=vertices, n_shape=shape_components, n_exp=exp_components, seed=seed)
    log.info("%s", model.summary())
    paths = [save_face_model(model, out, **(meta or {}))]
    if preview:
        paths.append(write_png(Path(out).with_suffix(".png"), preview_sheet(model)))
    return paths


def read_landmark_indices(path: Path, base: int = 1) -> np.ndarray:
    """68 vertex indices from a text/.npy/.anl file (whitespace or comma separated), ``base`` 0 or 1."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".npy":
            idx = np.load(path, allow_pickle=False)
        else:
            idx = np.array(path.read_text().replace(",", " ").split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise ReflectmmError(f"cannot read landmark indices ({exc})", path) from None
    idx = np.asarray(idx).reshape(-1)
    if idx.size != 68 or np.any(idx != np.round(idx)):
        raise ReflectmmError(f"expected 68 integer vertex indices, got {idx.size} values", path)
    return idx.astype(np.int64) - int(base)


def import_model(src: Path, out: Path, *, exp_path=None, exp_std=None, exp_index=None, units="auto",
                 landmarks=None, landmarks_base: int = 1, preview: bool = True,
                 meta: dict | None = None) -> tuple[list[Path], dict]:
    """Library entry: convert a BFM09 / Deep3DFaceRecon .mat (or a face-model artifact) to a face-model artifact."""
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.geometry import load_bfm09, save_face_model
    from reflectmm_cli.geometry.face_model import _mat_keys, load_face_model

    src = Path(src)
    if not src.exists():
        raise ReflectmmError("file not found", src)
    lm = None if landmarks is None else read_landmark_indices(landmarks, landmarks_base)
    if src.suffix.lower() == ".mat" and "shapeMU" in _mat_keys(src):
        model = load_bfm09(src, exp_path, exp_std_path=exp_std, exp_index_path=exp_index, units=units,
                           landmarks=lm)
    else:
        if exp_path is not None:
            raise ReflectmmError("--exp applies to BFM09 01_MorphableModel.mat only", src)
        model = load_face_model(src, units=units) if src.suffix.lower() == ".mat" else load_face_model(src)
        if lm is not None:
            from reflectmm_cli.geometry import FaceModel

            if lm.min() < 0 or lm.max() >= model.n_vertices:
                raise ReflectmmError(f"landmark indices out of range [0, {model.n_vertices})", landmarks)
            kw = {k: getattr(model, k) for k in model.__dataclass_fields__}
            kw["landmarks"] = lm
            model = FaceModel(**kw)
    log.info("%s", model.summary())
    if "uv_distortion" in model.info:
        d = model.info["uv_distortion"]
        log.info("computed cylindrical UVs: area ratio (UV/3-D, 1 = uniform) p5 %.3f, median %.3f, p95 %.3f; "
                 "flipped %.2f %%", d["area_ratio_p5"], d["area_ratio_median"], d["area_ratio_p95"],
                 100 * d["flipped_fraction"])
    if model.landmarks.size != 68:
        log.warning("%s has no 68 landmark indices (fit-geometry needs them; set them with the Python API)",
                    src.name)
    paths = [save_face_model(model, out, **(meta or {}))]
    if preview:
        paths.append(write_png(Path(out).with_suffix(".png"), preview_sheet(model)))
    return paths, model.info

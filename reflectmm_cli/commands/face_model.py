"""``reflectmm face-model``: create, import and export face models (docs/geometry.md).

* ``face-model create --out FILE`` — the built-in procedural model as a ``face-model`` artifact + PNG preview
  (stage ``face-model-create``);
* ``face-model import BFM.mat --out FILE`` — BFM09 ``01_MorphableModel.mat`` (+ ``Exp_Pca.bin``) or
  Deep3DFaceRecon ``BFM_model_front.mat`` → ``face-model`` artifact, computing a symmetric UV layout if the model
  has none and reporting its distortion (stage ``face-model-import``);
* ``face-model export FILE --out mesh.obj|.ply`` — a mesh with UVs through trimesh (optionally for given
  shape/expression coefficients);
* ``face-model info FILE`` — sizes and provenance.
"""
from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from reflectmm_cli.commands._common import emit, json_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log
from reflectmm_cli.stages import StageContext, register_stage

CREATE_DEFAULTS = {"vertices": 35000, "seed": 0, "shape_components": 40, "exp_components": 20}


# ------------------------------------------------------------------------------------------ library

def parse_coeffs(text: str | None, what: str = "coefficients") -> np.ndarray | None:
    """``"0.5,-1,2"`` or a path to .npy/.txt/.json → 1-D float array (None stays None)."""
    if text is None or text == "":
        return None
    p = Path(text)
    if p.suffix.lower() in (".npy", ".txt", ".json", ".csv") and p.exists():
        try:
            if p.suffix.lower() == ".npy":
                return np.asarray(np.load(p, allow_pickle=False), dtype=np.float64).reshape(-1)
            if p.suffix.lower() == ".json":
                return np.asarray(json.loads(p.read_text()), dtype=np.float64).reshape(-1)
            return np.loadtxt(p, delimiter="," if p.suffix.lower() == ".csv" else None, ndmin=1).reshape(-1)
        except (OSError, ValueError) as exc:
            raise ReflectmmError(f"cannot read {what} ({exc})", p) from None
    try:
        return np.array([float(x) for x in text.replace(" ", ",").split(",") if x], dtype=np.float64)
    except ValueError:
        raise ReflectmmError(f"{what}: expected comma-separated numbers or a .npy/.txt/.json file, got "
                             f"'{text}'") from None


def preview_image(model, width: int = 320, height: int = 400, yaws=(0.0, 45.0, 90.0), vertices=None) -> np.ndarray:
    """A shaded grey preview (front, 45°, profile) with landmarks in red; float (H, W·3, 3) in [0, 1]."""
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
        if model.landmarks.size:
            uv, _ = cam.project(v[model.landmarks])
            vis_ok = np.isfinite(uv).all(1)
            for (x, y) in uv[vis_ok]:
                xi, yi = int(round(x)), int(round(y))
                img[max(yi - 1, 0):yi + 2, max(xi - 1, 0):xi + 2] = (1.0, 0.1, 0.1)
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


# ------------------------------------------------------------------------------------------ stages

def _create_outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out] + ([out.with_suffix(".png")] if not ctx.param("no_preview") else [])


@register_stage("face-model-create", version=1, per_identity=False, outputs=_create_outputs,
                help="the built-in procedural face model")
def run_face_model_create(ctx: StageContext) -> list[Path]:
    p = {**CREATE_DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    return create_model(ctx.output_path(), int(p["vertices"]), int(p["seed"]), int(p["shape_components"]),
                        int(p["exp_components"]), preview=not p.get("no_preview"),
                        meta={"params": ctx.resolved_params(), "producer": ctx.producer(),
                              "cache_key": ctx.cache_key})


@register_stage("face-model-import", version=1, per_identity=False, outputs=_create_outputs,
                help="convert BFM09 / Deep3DFaceRecon .mat to a face-model artifact")
def run_face_model_import(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    exp = ctx.inputs.get("exp") or [None]
    std = ctx.inputs.get("exp_std") or [None]
    idx = ctx.inputs.get("exp_index") or [None]
    lmk = ctx.inputs.get("landmarks") or [None]
    paths, _ = import_model(ctx.input("model"), out, exp_path=exp[0], exp_std=std[0], exp_index=idx[0],
                            units=ctx.param("units", "auto"), landmarks=lmk[0],
                            landmarks_base=int(ctx.param("landmarks_base", 1)), preview=not ctx.param("no_preview"),
                            meta={"params": ctx.resolved_params(), "inputs": ctx.input_refs(out.parent),
                                  "producer": ctx.producer(), "cache_key": ctx.cache_key})
    return paths


# ------------------------------------------------------------------------------------------ CLI

@click.group("face-model")
def face_model_group():
    """Create, import, export and inspect face models (the `face-model` artifact)."""


@face_model_group.command("create")
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output artifact (default <workspace>/face-model-create/face-model-create.npz).")
@click.option("--vertices", type=click.IntRange(400, 2_000_000), default=CREATE_DEFAULTS["vertices"],
              show_default=True, help="Approximate vertex count (grid resolution).")
@click.option("--seed", type=int, default=CREATE_DEFAULTS["seed"], show_default=True,
              help="Seed of the random low-frequency basis components.")
@click.option("--shape-components", type=click.IntRange(0, 200), default=CREATE_DEFAULTS["shape_components"],
              show_default=True)
@click.option("--exp-components", type=click.IntRange(0, 100), default=CREATE_DEFAULTS["exp_components"],
              show_default=True)
@click.option("--no-preview", is_flag=True, help="Do not write the PNG preview.")
@workspace_option
@json_option
def create_cmd(out, vertices, seed, shape_components, exp_components, no_preview, workspace, as_json):
    """Write the built-in procedural face model (+ a PNG preview beside it)."""
    paths = run_stage_cli("face-model-create", workspace=workspace, output=out,
                          params={"vertices": vertices, "seed": seed, "shape_components": shape_components,
                                  "exp_components": exp_components, "no_preview": no_preview})
    emit(paths, as_json)


@face_model_group.command("import")
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option("--exp", "exp", type=click.Path(path_type=Path), default=None,
              help="BFM09 only: Exp_Pca.bin expression basis (Guo et al.).")
@click.option("--exp-std", type=click.Path(path_type=Path), default=None,
              help="std_exp.txt: standard deviations of the expression coefficients.")
@click.option("--exp-index", type=click.Path(path_type=Path), default=None,
              help="BFM_exp_idx.mat ('trimIndex'): BFM09 vertices of the Exp_Pca.bin basis, if it has fewer.")
@click.option("--units", default="auto", show_default=True,
              help="Units of the file's coordinates: auto (from the extent), um, mm, dm or m.")
@click.option("--landmarks", type=click.Path(path_type=Path), default=None,
              help="68 landmark vertex indices (text/.anl/.npy), e.g. for BFM09 which has none.")
@click.option("--landmarks-base", type=click.Choice(["0", "1"]), default="1", show_default=True,
              help="Whether --landmarks indices are 0- or 1-based.")
@click.option("--no-preview", is_flag=True)
@workspace_option
@json_option
def import_cmd(source, out, exp, exp_std, exp_index, units, landmarks, landmarks_base, no_preview, workspace,
               as_json):
    """Convert a BFM09 01_MorphableModel.mat or Deep3DFaceRecon BFM_model_front.mat to a face-model artifact."""
    inputs = {"model": [source]}
    for role, p in (("exp", exp), ("exp_std", exp_std), ("exp_index", exp_index), ("landmarks", landmarks)):
        if p is not None:
            inputs[role] = [p]
    paths = run_stage_cli("face-model-import", workspace=workspace, output=out, inputs=inputs,
                          params={"units": units, "no_preview": no_preview, "landmarks_base": int(landmarks_base)})
    emit(paths, as_json)


@face_model_group.command("export")
@click.argument("model_path", metavar="FILE", type=click.Path(path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Mesh file: .obj (with vt/vn), .ply (binary, UVs as s/t), .glb, .off or .stl.")
@click.option("--coeffs", "--shape", "shape", default=None,
              help="Shape coefficients (raw, prior std = shape_sigma): 'a,b,c' or a .npy/.txt/.json file.")
@click.option("--exp", "exp", default=None, help="Expression coefficients, same forms.")
@click.option("--sigma-units", is_flag=True, help="Coefficients are in units of sigma (multiplied by it).")
@click.option("--geometry", type=click.Path(path_type=Path), default=None,
              help="A geometry artifact: export its fitted vertices.")
@json_option
def export_cmd(model_path, out, shape, exp, sigma_units, geometry, as_json):
    """Export a face model (mean, given coefficients, or a fitted geometry) as a mesh with UVs."""
    from reflectmm_cli.geometry import load_face_model

    model = load_face_model(model_path)
    a, d = parse_coeffs(shape, "--coeffs"), parse_coeffs(exp, "--exp")
    if sigma_units:
        a = None if a is None else a * model.shape_sigma[: len(a)]
        d = None if d is None else d * model.exp_sigma[: len(d)]
    if geometry is not None:
        from reflectmm_cli.artifacts import read_artifact

        g = read_artifact(geometry, "geometry")
        verts = np.asarray(g["vertices"], dtype=np.float32)
        if verts.shape != model.mean_shape.shape:
            raise ReflectmmError(f"geometry has {verts.shape[0]} vertices, the face model {model.n_vertices}",
                                 geometry)
        model = type(model)(verts, None, None, None, None, model.triangles, model.uv, model.landmarks,
                            model.skin_mask, name=model.name)
        a = d = None
    emit([export_mesh(model, out, a, d)], as_json)


@face_model_group.command("info")
@click.argument("model_path", metavar="FILE", type=click.Path(path_type=Path))
@json_option
def info_cmd(model_path, as_json):
    """Print sizes, σ ranges and provenance of a face model (artifact or BFM .mat)."""
    from reflectmm_cli.geometry import load_face_model

    m = load_face_model(model_path)
    doc = {"name": m.name, "vertices": m.n_vertices, "triangles": int(len(m.triangles)), "shape": m.n_shape,
           "expression": m.n_exp, "landmarks": int(m.landmarks.size), "skin_vertices": int(m.skin_mask.sum()),
           "texture": m.mean_tex is not None, "info": m.info,
           "extent_mm": (m.mean_shape.max(0) - m.mean_shape.min(0)).round(2).tolist()}
    if as_json:
        click.echo(json.dumps(doc, indent=2, sort_keys=True, default=str))
    else:
        for k, v in doc.items():
            click.echo(f"{k}: {v}")


COMMANDS = [face_model_group]

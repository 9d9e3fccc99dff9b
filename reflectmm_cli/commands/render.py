"""``reflectmm render``: a face model with reflectance under a point light or an environment map.

Reflectance comes from a ``reflectance-maps`` artifact (albedo (3,S,S), weights (K,S,S), exponents (K,)) or a
``reflectance-model`` artifact sampled at coefficients β (units of σ; default the mean).  Geometry is the face
model's mean, given shape/expression coefficients, or a ``geometry`` artifact's fitted vertices.  Light is a
point light (``x,y,z[:I]``, radiant intensity I, ``E = I/d²``, optional ray-traced shadows) or SH environment
light (an equirectangular EXR/HDR projected to SH, or SH coefficients from a file).  Writes a linear EXR
(``render`` kind, channels R, G, B, meta in the header) and a display PNG beside it (sRGB, auto exposure).
"""
from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from reflectmm_cli.commands._common import emit, json_option, run_stage_cli, workspace_option
from reflectmm_cli.commands.face_model import parse_coeffs
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log
from reflectmm_cli.stages import StageContext, register_stage


# ------------------------------------------------------------------------------------------ parsing

def parse_point_light(text: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``"x,y,z"`` or ``"x,y,z:I"`` or ``"x,y,z:r,g,b"`` (mm; intensity in linear pixel units × mm²)."""
    pos, _, inten = text.partition(":")
    try:
        p = np.array([float(x) for x in pos.split(",")], dtype=np.float64)
        i = None if not inten else np.array([float(x) for x in inten.split(",")], dtype=np.float64)
    except ValueError:
        raise ReflectmmError(f"--point-light '{text}': expected x,y,z[:I] or x,y,z:r,g,b (numbers)") from None
    if p.shape != (3,) or (i is not None and i.size not in (1, 3)) or not np.all(np.isfinite(p)):
        raise ReflectmmError(f"--point-light '{text}': expected x,y,z[:I] or x,y,z:r,g,b")
    if i is not None and np.any(i < 0):
        raise ReflectmmError(f"--point-light '{text}': intensity must be ≥ 0")
    return p, i


def load_sh(path: Path) -> np.ndarray:
    """SH coefficients (3, (L+1)²) from .npy / .txt / .json (also (n, 3)) or an NPZ with 'sh' / 'coeffs'."""
    path = Path(path)
    if not path.exists():
        raise ReflectmmError("file not found", path)
    try:
        if path.suffix.lower() == ".npy":
            a = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as z:
                key = next((k for k in ("sh", "coeffs", "sh_coeffs") if k in z.files), None)
                if key is None:
                    raise ReflectmmError(f"no 'sh' or 'coeffs' array (has: {', '.join(z.files)})", path)
                a = z[key]
        elif path.suffix.lower() == ".json":
            a = np.asarray(json.loads(path.read_text()), dtype=np.float64)
        else:
            a = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise ReflectmmError(f"cannot read SH coefficients ({exc})", path) from None
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 3 and a.shape[0] != 3:
        a = a.T
    n = a.shape[-1] if a.ndim == 2 else 0
    if a.ndim != 2 or a.shape[0] != 3 or int(round(np.sqrt(n))) ** 2 != n:
        raise ReflectmmError(f"SH coefficients must be (3, (L+1)²), got {a.shape}", path)
    return a


def load_reflectance(maps: Path | None, model: Path | None, coeffs: str | None):
    """(albedo (3,S,S), weights (K,S,S), exponents (K,)) from maps or a model at β."""
    from reflectmm_cli.artifacts import read_artifact

    if (maps is None) == (model is None):
        raise ReflectmmError("give exactly one of --maps or --model")
    if maps is not None:
        art = read_artifact(maps, "reflectance-maps")
        a, w, e = art["albedo"], art["weights"], art["exponents"]
        if coeffs:
            raise ReflectmmError("--coeffs applies to --model only")
    else:
        from reflectmm_cli.model import sample_model

        art = read_artifact(model, "reflectance-model")
        beta = parse_coeffs(coeffs, "--coeffs")
        m = int(np.shape(art["sigma"])[0])
        if beta is None:
            beta = np.zeros(0)
        if beta.size > m:
            raise ReflectmmError(f"--coeffs: {beta.size} coefficients given, the model has {m}", model)
        a, w = sample_model(art.arrays, beta if beta.size else np.zeros(1), "uv")
        e = art["exponents"]
    a, w, e = np.asarray(a, np.float32), np.asarray(w, np.float32), np.asarray(e, np.float64).reshape(-1)
    if a.ndim != 3 or a.shape[0] != 3 or a.shape[1] != a.shape[2]:
        raise ReflectmmError(f"albedo must be (3, S, S), got {a.shape}", maps or model)
    if w.shape != (e.size,) + a.shape[1:]:
        raise ReflectmmError(f"weights must be ({e.size}, {a.shape[1]}, {a.shape[2]}), got {w.shape}", maps or model)
    return a, w, e


# ------------------------------------------------------------------------------------------ library

def render_face(face_model: Path, *, maps: Path | None = None, model: Path | None = None, coeffs: str | None = None,
                point_light: str | None = None, envmap: Path | None = None, sh: Path | None = None,
                sh_order: int = 8, camera: str = "frontal", shadows: bool = False, shape: str | None = None,
                exp: str | None = None, geometry: Path | None = None) -> dict:
    """Library entry of ``reflectmm render``: returns image (H,W,3), mask, camera, light description."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry import (
        RayScene,
        load_face_model,
        parse_camera_spec,
        render_envmap,
        render_point_light,
        vertex_normals,
    )

    n_lights = sum(x is not None for x in (point_light, envmap, sh))
    if n_lights != 1:
        raise ReflectmmError("give exactly one light: --point-light, --envmap or --sh")
    fm = load_face_model(face_model)
    if geometry is not None:
        g = read_artifact(geometry, "geometry")
        verts = np.asarray(g["vertices"], dtype=np.float64)
        if verts.shape != fm.mean_shape.shape:
            raise ReflectmmError(f"geometry has {verts.shape[0]} vertices, the face model {fm.n_vertices}", geometry)
    else:
        verts = fm.vertices(parse_coeffs(shape, "--shape"), parse_coeffs(exp, "--exp"))
    albedo, weights, exps = load_reflectance(maps, model, coeffs)
    cam = parse_camera_spec(camera)
    scene = RayScene(verts, fm.triangles, vertex_normals(verts, fm.triangles))
    light: dict = {}
    if point_light is not None:
        pos, inten = parse_point_light(point_light)
        if inten is None:
            inten = np.array([np.pi * float(pos @ pos)])  # irradiance π at the origin
        res = render_point_light(scene, cam, albedo, weights, exps, pos, inten, uv=fm.uv, shadows=shadows)
        light = {"type": "point", "position": pos.tolist(), "intensity": np.atleast_1d(inten).tolist(),
                 "shadows": bool(shadows), "shadow_rays": res.rays}
        if shadows:
            log.info("shadow rays: %d cast, %d skipped (n·l ≤ 0)", res.rays["cast"], res.rays["skipped"])
    else:
        if shadows:
            log.warning("--shadows applies to point lights only; SH environment light has no visibility")
        if envmap is not None:
            from reflectmm_cli.shading import load_envmap, project_envmap

            K = project_envmap(load_envmap(envmap), sh_order)
            light = {"type": "envmap", "file": Path(envmap).name, "sh_order": sh_order}
        else:
            K = load_sh(sh)
            light = {"type": "sh", "file": Path(sh).name, "sh_order": int(np.sqrt(K.shape[1])) - 1}
        res = render_envmap(scene, cam, albedo, weights, exps, K, uv=fm.uv)
    return {"image": res.image, "mask": res.mask, "camera": cam, "light": light}


# ------------------------------------------------------------------------------------------ stage + CLI

def _out(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.output_path(suffix=".exr")


def _outputs(ctx: StageContext) -> list[Path]:
    o = _out(ctx)
    return [o, o.with_suffix(".png")]


def _one(ctx: StageContext, role: str) -> Path | None:
    paths = ctx.inputs.get(role) or []
    return Path(paths[0]) if paths else None


@register_stage("render", version=1, per_identity=False, outputs=_outputs,
                help="render a face model with reflectance under a point light or environment light")
def run_render(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.artifacts import make_meta, write_exr, write_png
    from reflectmm_cli.geometry import to_display

    out = _out(ctx)
    if out.suffix.lower() != ".exr":
        raise ReflectmmError("render output must be an .exr file (the PNG is written beside it)", out)
    p = ctx.params
    r = render_face(ctx.input("face_model"), maps=_one(ctx, "maps"), model=_one(ctx, "model"),
                    coeffs=p.get("coeffs"), point_light=p.get("point_light"), envmap=_one(ctx, "envmap"),
                    sh=_one(ctx, "sh"), sh_order=int(p.get("sh_order") or 8), camera=p.get("camera") or "frontal",
                    shadows=bool(p.get("shadows")), shape=p.get("shape"), exp=p.get("exp"),
                    geometry=_one(ctx, "geometry"))
    img = r["image"]
    meta = make_meta("render", params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                     producer=ctx.producer(), cache_key=ctx.cache_key,
                     extra={"camera": r["camera"].to_dict(), "light": r["light"],
                            "units": "linear radiance (pixel units)"})
    write_exr(out, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]}, meta=meta)
    png = write_png(out.with_suffix(".png"), to_display(img, transfer=p.get("display") or "srgb"))
    face = img[r["mask"]]
    log.info("rendered %dx%d, %d face pixels, radiance max %.4g, median %.4g", img.shape[1], img.shape[0],
             int(r["mask"].sum()), float(face.max()) if face.size else 0.0,
             float(np.median(face)) if face.size else 0.0)
    return [out, png]


@click.command("render")
@click.option("--face-model", "face_model", type=click.Path(path_type=Path), required=True,
              help="face-model artifact or BFM .mat.")
@click.option("--maps", type=click.Path(path_type=Path), default=None, help="reflectance-maps artifact.")
@click.option("--model", type=click.Path(path_type=Path), default=None, help="reflectance-model artifact.")
@click.option("--coeffs", default=None, help="Reflectance-model coefficients β (units of σ): 'a,b,…' or a file.")
@click.option("--point-light", default=None, metavar="X,Y,Z[:I]",
              help="Point light position (mm, model space) and radiant intensity I (scalar or r,g,b; default "
                   "π·|pos|², i.e. irradiance π at the origin).")
@click.option("--envmap", type=click.Path(path_type=Path), default=None,
              help="Equirectangular HDR map (EXR/HDR; frame of docs/shading.md), projected to SH.")
@click.option("--sh", type=click.Path(path_type=Path), default=None,
              help="SH coefficients (3, (L+1)²) in .npy/.txt/.json or an NPZ with 'sh'.")
@click.option("--sh-order", type=click.IntRange(0, 20), default=8, show_default=True,
              help="SH order used to project --envmap.")
@click.option("--camera", default="frontal", show_default=True,
              help="frontal | deep3d | yaw=DEG[,pitch=DEG,distance=MM,focal=PX,size=WxH] (default 1000 mm, "
                   "f = 1500 px, 640x480).")
@click.option("--shadows", is_flag=True, help="Ray-traced cast shadows (point light).")
@click.option("--shape", default=None, help="Face-model shape coefficients (raw): 'a,b,…' or a file.")
@click.option("--exp", default=None, help="Face-model expression coefficients (raw).")
@click.option("--geometry", type=click.Path(path_type=Path), default=None,
              help="geometry artifact: render its fitted vertices instead.")
@click.option("--display", type=click.Choice(["srgb", "gamma", "linear"]), default="srgb", show_default=True,
              help="Transfer curve of the PNG (auto exposure, clipped).")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output EXR (default <workspace>/render/render.exr); the PNG goes beside it.")
@workspace_option
@json_option
def render_cmd(face_model, maps, model, coeffs, point_light, envmap, sh, sh_order, camera, shadows, shape, exp,
               geometry, display, output, workspace, as_json):
    """Render a face model with reflectance maps or a reflectance model to a linear EXR + display PNG."""
    inputs = {"face_model": [face_model]}
    for role, pth in (("maps", maps), ("model", model), ("envmap", envmap), ("sh", sh), ("geometry", geometry)):
        if pth is not None:
            inputs[role] = [pth]
    params = {"coeffs": coeffs, "point_light": point_light, "sh_order": sh_order, "camera": camera,
              "shadows": shadows, "shape": shape, "exp": exp, "display": display}
    paths = run_stage_cli("render", workspace=workspace, inputs=inputs, output=output,
                          params={k: v for k, v in params.items() if v is not None})
    emit(paths, as_json)


COMMANDS = [render_cmd]

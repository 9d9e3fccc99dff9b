"""Stage ``render``: a face model with reflectance under a point light or an environment map → a linear EXR
(``render`` kind, channels R, G, B, meta in the header) and a display PNG beside it (sRGB, auto exposure).
Library: :func:`reflectmm_cli.geometry.render_face.render_face`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.render_face import render_face
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext

VERB = "render"

PARAMS = (
    Param("coeffs", "str", None, help="Reflectance-model coefficients β (units of σ): 'a,b,…' or a file."),
    Param("point_light", "str", None, metavar="X,Y,Z[:I]",
          help="Point light position (mm, model space) and radiant intensity I (scalar or r,g,b; default "
               "π·|pos|², i.e. irradiance π at the origin)."),
    Param("sh_order", "int", 8, range=(0, 20), help="SH order used to project --envmap."),
    Param("camera", "str", "frontal",
          help="frontal | deep3d | yaw=DEG[,pitch=DEG,distance=MM,focal=PX,size=WxH] (default 1000 mm, "
               "f = 1500 px, 640x480)."),
    Param("shadows", "bool", False, help="Ray-traced cast shadows (point light)."),
    Param("shape", "str", None, help="Face-model shape coefficients (raw): 'a,b,…' or a file."),
    Param("exp", "str", None, help="Face-model expression coefficients (raw)."),
    Param("display", "str", "srgb", choices=("srgb", "gamma", "gamma1.2", "linear"),
          help="Transfer curve of the PNG (clipped): sRGB, x^(1/2.2), x^(1/1.2) or linear."),
    Param("exposure", "float", None, range=(0.0, None),
          help="Scale of the radiance in the PNG (default: the 99.5th percentile of the face maps to 0.9)."),
    Param("layer", "str", "full",
          help="full | diffuse | specular | lobeI (one lobe alone) | albedo | sumw | weightI (I from 0; the "
               "reflectance layers are unshaded and written with exposure 1)."),
    Param("reflectance", "str", "uv", choices=("uv", "vertex"),
          help="Look reflectance up in the UV maps, or per vertex interpolated over each triangle (the model's "
               "per-vertex part, as the viewer and finetuning shade)."),
    Param("rotate", "float", 0.0, unit="degrees", help="Turn the environment light about +y (exact, in SH space)."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs'),
    Input('maps', 'reflectance-maps'),
    Input('model', 'reflectance-model'),
    Input('envmap', 'EXR/HDR map'),
    Input('sh', 'SH coefficients'),
    Input('geometry', 'geometry'),
)


def _out(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.output_path(suffix=".exr")


def _outputs(ctx: StageContext) -> list[Path]:
    o = _out(ctx)
    return [o, o.with_suffix(".png")]


def _one(ctx: StageContext, role: str) -> Path | None:
    paths = ctx.inputs.get(role) or []
    return Path(paths[0]) if paths else None


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.artifacts import make_meta, write_exr, write_png
    from reflectmm_cli.geometry import to_display

    out = _out(ctx)
    if out.suffix.lower() != ".exr":
        raise ReflectmmError("render output must be an .exr file (the PNG is written beside it)", out)
    p = ctx.params
    r = render_face(ctx.input("face_model"), maps=_one(ctx, "maps"), reflectance_model=_one(ctx, "model"),
                    coeffs=p.get("coeffs"), point_light=p.get("point_light"), envmap=_one(ctx, "envmap"),
                    sh=_one(ctx, "sh"), sh_order=p["sh_order"], camera=p["camera"],
                    shadows=p["shadows"], shape=p.get("shape"), exp=p.get("exp"),
                    geometry=_one(ctx, "geometry"), layer=p["layer"], reflectance_at=p["reflectance"],
                    env_rotation=p["rotate"])
    img = r["image"]
    meta = make_meta("render", params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                     producer=ctx.producer(), cache_key=ctx.cache_key,
                     extra={"camera": r["camera"].to_dict(), "light": r["light"],
                            "units": "linear radiance (pixel units)"})
    write_exr(out, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]}, meta=meta)
    exposure = 1.0 if r["light"].get("type") == "none" else p.get("exposure")
    png = write_png(out.with_suffix(".png"), to_display(img, exposure=exposure, transfer=p["display"]))
    face = img[r["mask"]]
    if not face.size:
        log.warning("render: no face pixel in the %dx%d image (%s); check --camera, --shape and --exp", img.shape[1],
                    img.shape[0], out)
    log.info("rendered %dx%d, %d face pixels, radiance max %.4g, median %.4g", img.shape[1], img.shape[0],
             int(r["mask"].sum()), float(face.max()) if face.size else 0.0,
             float(np.median(face)) if face.size else 0.0)
    return [out, png]


# version 2: + layer, reflectance, rotate, exposure (the default render is unchanged)
STAGE = Stage(VERB, version=2, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="render a face model with reflectance under a point light or environment light", inputs=INPUTS)

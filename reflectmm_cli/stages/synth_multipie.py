"""Stage ``synth-multipie``: synthetic identities rendered on a Multi-PIE-like rig, with ground truth
(docs/synthetic.md).  Not per identity; the output is a folder: ``--out DIR``, else ``<workspace>/<stage_name>/``.
"""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.procedural import MIN_VERTICES
from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext

VERB = "synth-multipie"

PARAMS = (
    Param("identities", "int", aliases=("-n",), default=1, range=(1, 999), help="Number of identities."),
    Param("seed", "int", 0, range=SEED_RANGE, help="Random seed (identity k depends on seed, k)."),
    Param("brdf", "str", "ggx", choices=("ggx", "model"),
          help="Ground-truth BRDF: GGX microfacet (honest) or the 3-lobe model (exact-recovery tests)."),
    Param("skin", "str", None, choices=("single", "two-lobe"),
          help="Skin specular: single (one GGX lobe per texel; the default) or two-lobe (a sharp and a broad GGX "
               "lobe, mixed per region; docs/synthetic.md)."),
    Param("features", "str", None, choices=("plain", "painted"),
          help="Facial features: plain (grey eyes; the default) or painted (iris, pupil, lash lines, the mouth "
               "line and nostrils, which a face detector locks onto; docs/synthetic.md)."),
    Param("image_size", "size", "640x480", range=(16, 16384), unit="px", metavar="WxH",
          help="WxH; the framing is kept."),
    Param("uv_size", "int", 256, range=(16, 4096), unit="texels", help="Resolution of the ground-truth UV maps."),
    Param("cameras", "strs", None, none_word="all",
          help="Comma-separated cameras to render (default: all rig cameras)."),
    Param("flashes", "strs", None, none_word="all",
          help="Comma-separated flash ids to render (default: all, 01-18)."),
    Param("noise", "float", 0.0, range=(0.0, None),
          help="Gaussian sensor noise sigma in linear units (added before clipping and encoding)."),
    Param("landmark_noise", "float", 0.0, range=(0.0, 50.0), unit="px", help="Gaussian landmark noise sigma."),
    Param("expression", "float", 0.0, range=(0.0, 10.0),
          help="Scale of a random expression (x the model's expression sigma); 0 = neutral."),
    Param("shape_scale", "float", 1.0, range=(0.0, 10.0),
          help="Scale of the random identity shape (x the model's shape sigma)."),
    Param("first_id", "int", 1, range=(1, 999), help="Id of the first identity."),
    Param("face_vertices", "int", 35000, range=(MIN_VERTICES, 500000),
          help="Vertex count of the procedural face model (when --face-model is not given)."),
    Param("supersample", "int", 1, range=(1, 8),
          help="k x k rays per pixel, box-filtered in linear space (anti-aliased silhouettes and shadow edges)."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('face_model', 'face-model artifact or BFM .mat', help='instead of the procedural one'),
    Input('rig', 'rig TOML', help='instead of the packaged table'),
)


def out_dir(ctx: StageContext) -> Path:
    """The output folder: ``--out`` / the explicit output, else ``<workspace>/<stage_name>/``."""
    return Path(ctx.output) if ctx.output is not None else ctx.workspace / ctx.stage_name


def multipie_config(params: dict):
    """SynthConfig from resolved stage params."""
    from reflectmm_cli.synth.multipie import SynthConfig

    p = params
    w, h = (int(x) for x in p["image_size"].split("x"))
    return SynthConfig(identities=p["identities"], seed=p["seed"], brdf=p["brdf"], image_size=(w, h),
                       uv_size=p["uv_size"],
                       cameras=tuple(p["cameras"]) if p.get("cameras") else None,
                       flashes=tuple(p["flashes"]) if p.get("flashes") else None,
                       noise=p["noise"], landmark_noise=p["landmark_noise"], expression=p["expression"],
                       shape_scale=p["shape_scale"], first_id=p["first_id"], face_vertices=p["face_vertices"],
                       supersample=p["supersample"], skin=p.get("skin") or "single",
                       features=p.get("features") or "plain")


def _outputs(ctx: StageContext) -> list[Path]:
    cfg = multipie_config(ctx.params)
    out = out_dir(ctx)
    return [out / "truth" / f"{cfg.first_id + k:03d}.npz" for k in range(cfg.identities)] + \
        [out / "rig.toml", out / "face_model.npz"]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.synth.multipie import synth_multipie

    cfg = multipie_config(ctx.params)
    out = out_dir(ctx)
    fm = ctx.input_list("face_model", required=False)
    rg = ctx.input_list("rig", required=False)
    if len(fm) > 1 or len(rg) > 1:
        raise ReflectmmError("synth-multipie: give at most one face_model and one rig input")
    params = cfg.to_params()
    if fm:
        params.pop("face_vertices")
    paths = synth_multipie(out, cfg, face_model=fm[0] if fm else None, rig=rg[0] if rg else None,
                           meta_params=params, producer=ctx.producer(), cache_key=ctx.cache_key,
                           inputs=ctx.input_refs(out))
    log.info(f"synth multipie: {cfg.identities} identities ({cfg.brdf}, {cfg.skin} skin, {cfg.features} features) "
             f"in {out}")
    return paths


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="synthetic Multi-PIE captures with ground truth", inputs=INPUTS)

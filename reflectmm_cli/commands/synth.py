"""``reflectmm synth``: the synthetic world (docs/synthetic.md).

* ``synth multipie`` — identities with known shape and spatially varying reflectance rendered on a Multi-PIE-like
  rig, written in the exact Multi-PIE layout with landmarks, plus ground truth (stage ``synth-multipie``);
* ``synth envmaps`` — procedural HDR environment maps as EXR (stage ``synth-envmaps``);
* ``synth wild`` — in-the-wild-like renders with ground truth for finetuning (stage ``synth-wild``).

Both are recipe stages that are not per identity; their output is a folder: ``--out DIR``, else
``<workspace>/<stage_name>/``.
"""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, json_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log
from reflectmm_cli.stages import StageContext, register_stage

ENVMAP_DEFAULTS = {"count": 8, "seed": 0, "width": 512}


def _out_dir(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.workspace / ctx.stage_name


# --------------------------------------------------------------------------- envmaps

def _envmap_params(ctx: StageContext) -> dict:
    p = {**ENVMAP_DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    return {"count": int(p["count"]), "seed": int(p["seed"]), "width": int(p["width"])}


def _envmap_outputs(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.synth.envmaps import ENVMAP_KINDS

    p = _envmap_params(ctx)
    out = _out_dir(ctx)
    return [out / f"env_{i:04d}_{ENVMAP_KINDS[i % len(ENVMAP_KINDS)]}.exr" for i in range(p["count"])] + \
        [out / "contact_sheet.png"]


@register_stage("synth-envmaps", version=1, per_identity=False, outputs=_envmap_outputs,
                help="procedural HDR environment maps (EXR)")
def run_synth_envmaps(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.artifacts import make_meta
    from reflectmm_cli.synth.envmaps import write_envmaps

    p = _envmap_params(ctx)
    meta = make_meta("envmap", params=p, producer=ctx.producer(), cache_key=ctx.cache_key)
    paths = write_envmaps(_out_dir(ctx), p["count"], p["seed"], p["width"], meta_base=meta)
    log.info(f"synth envmaps: {p['count']} maps ({p['width']}x{p['width'] // 2}) in {_out_dir(ctx)}")
    return paths


@click.command("envmaps")
@click.option("--count", "-n", type=click.IntRange(1, None), default=8, show_default=True, help="Number of maps.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-envmaps/).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (maps depend on seed and index).")
@click.option("--width", type=click.IntRange(8, 16384), default=512, show_default=True,
              help="Equirectangular width in pixels (height = width/2; even).")
@workspace_option
@json_option
def envmaps_cmd(count, out, seed, width, workspace, as_json):
    """Procedural HDR environment maps (sky+sun, overcast, indoor, coloured) as float32 EXR (R,G,B).

    Equirectangular, +y up, image centre looking down -z (the convention of reflectmm_cli.shading.envmap);
    linear radiance with a dynamic range like real captures.  Also writes a tone-mapped contact_sheet.png.
    """
    if width % 2:
        raise click.BadParameter("must be even", param_hint="--width")
    paths = run_stage_cli("synth-envmaps", workspace=workspace, params={"count": count, "seed": seed, "width": width},
                          output=out, stage_name="synth-envmaps")
    emit(paths, as_json)


# --------------------------------------------------------------------------- multipie

MULTIPIE_DEFAULTS = {"identities": 1, "seed": 0, "brdf": "ggx", "image_size": "640x480", "uv_size": 256,
                     "cameras": None, "flashes": None, "noise": 0.0, "landmark_noise": 0.0, "expression": 0.0,
                     "shape_scale": 1.0, "first_id": 1, "face_vertices": 35000, "supersample": 1}


def _parse_size(value) -> tuple[int, int]:
    if isinstance(value, (list, tuple)) and len(value) == 2:
        return int(value[0]), int(value[1])
    try:
        w, h = str(value).lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise ReflectmmError(f"image_size must be WxH (e.g. 640x480), got {value!r}") from None


def _parse_list(value) -> tuple[str, ...] | None:
    if value is None or value == "" or value == "all":
        return None
    if isinstance(value, str):
        value = [v for v in value.replace(" ", ",").split(",") if v]
    return tuple(str(v) for v in value)


def multipie_config(params: dict):
    """SynthConfig from stage params (CLI options or recipe params)."""
    from reflectmm_cli.synth.multipie import SynthConfig

    p = {**MULTIPIE_DEFAULTS, **{k: v for k, v in params.items() if v is not None}}
    unknown = set(p) - set(MULTIPIE_DEFAULTS)
    if unknown:
        raise ReflectmmError(f"synth-multipie: unknown param(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(MULTIPIE_DEFAULTS))})")
    return SynthConfig(identities=int(p["identities"]), seed=int(p["seed"]), brdf=str(p["brdf"]),
                       image_size=_parse_size(p["image_size"]), uv_size=int(p["uv_size"]),
                       cameras=_parse_list(p["cameras"]), flashes=_parse_list(p["flashes"]),
                       noise=float(p["noise"]), landmark_noise=float(p["landmark_noise"]),
                       expression=float(p["expression"]), shape_scale=float(p["shape_scale"]),
                       first_id=int(p["first_id"]), face_vertices=int(p["face_vertices"]),
                       supersample=int(p["supersample"]))


def _multipie_outputs(ctx: StageContext) -> list[Path]:
    cfg = multipie_config(ctx.params)
    out = _out_dir(ctx)
    return [out / "truth" / f"{cfg.first_id + k:03d}.npz" for k in range(cfg.identities)] + \
        [out / "rig.toml", out / "face_model.npz"]


@register_stage("synth-multipie", version=1, per_identity=False, outputs=_multipie_outputs,
                help="synthetic Multi-PIE captures with ground truth")
def run_synth_multipie(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.synth.multipie import synth_multipie

    cfg = multipie_config(ctx.params)
    out = _out_dir(ctx)
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
    log.info(f"synth multipie: {cfg.identities} identities ({cfg.brdf}) in {out}")
    return paths


@click.command("multipie")
@click.option("--identities", "-n", type=click.IntRange(1, 999), default=1, show_default=True,
              help="Number of identities.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-multipie/).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (identity k depends on seed, k).")
@click.option("--brdf", type=click.Choice(["ggx", "model"]), default="ggx", show_default=True,
              help="Ground-truth BRDF: GGX microfacet (honest) or the 3-lobe model (exact-recovery tests).")
@click.option("--image-size", default="640x480", show_default=True, help="WxH; the framing is kept.")
@click.option("--uv-size", type=click.IntRange(16, 4096), default=256, show_default=True,
              help="Resolution of the ground-truth UV maps.")
@click.option("--cameras", default=None, help="Comma-separated cameras to render (default: all rig cameras).")
@click.option("--flashes", default=None, help="Comma-separated flash ids to render (default: all, 01-18).")
@click.option("--noise", type=click.FloatRange(0, None), default=0.0, show_default=True,
              help="Gaussian sensor noise sigma in linear units (added before clipping and encoding).")
@click.option("--landmark-noise", type=click.FloatRange(0, None), default=0.0, show_default=True,
              help="Gaussian landmark noise sigma in pixels.")
@click.option("--expression", type=click.FloatRange(0, None), default=0.0, show_default=True,
              help="Scale of a random expression (x the model's expression sigma); 0 = neutral.")
@click.option("--shape-scale", type=click.FloatRange(0, None), default=1.0, show_default=True,
              help="Scale of the random identity shape (x the model's shape sigma).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face-model artifact to use (default: the procedural model, written to DIR/face_model.npz).")
@click.option("--face-vertices", type=click.IntRange(200, 500000), default=35000, show_default=True,
              help="Vertex count of the procedural face model (when --face-model is not given).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Rig table (TOML; default: the packaged Multi-PIE-like rig).")
@click.option("--first-id", type=click.IntRange(1, 999), default=1, show_default=True, help="Id of the first identity.")
@click.option("--supersample", type=click.IntRange(1, 8), default=1, show_default=True,
              help="k x k rays per pixel, box-filtered in linear space (anti-aliased silhouettes and shadow edges).")
@workspace_option
@json_option
def multipie_cmd(identities, out, seed, brdf, image_size, uv_size, cameras, flashes, noise, landmark_noise,
                 expression, shape_scale, face_model, face_vertices, rig, first_id, supersample, workspace, as_json):
    """Render synthetic identities on a Multi-PIE-like rig, in the exact Multi-PIE layout, with ground truth.

    Writes DIR/data/session01/multiview/SSS/01/CC_C/SSS_01_01_CCC_II.png (II = 00 room light, 01-18 flashes),
    SSS_01_01_CCC_00_lm.pts landmark files, DIR/rig.toml, DIR/face_model.npz, DIR/truth/SSS.npz (synth-truth)
    and DIR/contact_sheet.png.  Prints the truth files, rig.toml, face_model.npz and the contact sheet.
    """
    params = {"identities": identities, "seed": seed, "brdf": brdf, "image_size": image_size, "uv_size": uv_size,
              "cameras": cameras, "flashes": flashes, "noise": noise, "landmark_noise": landmark_noise,
              "expression": expression, "shape_scale": shape_scale, "first_id": first_id,
              "supersample": supersample}
    if face_model is None:
        params["face_vertices"] = face_vertices
    multipie_config(params)  # validate before any work
    inputs = {}
    if face_model is not None:
        inputs["face_model"] = [face_model]
    if rig is not None:
        inputs["rig"] = [rig]
    paths = run_stage_cli("synth-multipie", workspace=workspace, params=params, inputs=inputs, output=out,
                          stage_name="synth-multipie")
    emit(paths, as_json)


# --------------------------------------------------------------------------- wild

WILD_DEFAULTS = {"count": 16, "seed": 0, "size": 224, "images_per_identity": 4, "occluder_fraction": 0.2,
                 "landmark_noise": 1.0, "encoding": "gamma1.2", "noise": 0.004, "envmaps": 8, "envmap_width": 512,
                 "uv_size": 256, "face_vertices": 35000, "ao_rays": 12, "spec_rays": 6}


def wild_config(params: dict):
    """WildConfig from stage params (CLI options or recipe params)."""
    from reflectmm_cli.synth.wild import WildConfig

    p = {**WILD_DEFAULTS, **{k: v for k, v in params.items() if v is not None}}
    unknown = set(p) - set(WILD_DEFAULTS)
    if unknown:
        raise ReflectmmError(f"synth-wild: unknown param(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(WILD_DEFAULTS))})")
    return WildConfig(**{k: (type(WILD_DEFAULTS[k])(v)) for k, v in p.items()})


def _wild_outputs(ctx: StageContext) -> list[Path]:
    out = _out_dir(ctx)
    return [out / "manifest.npz", out / "face_model.npz", out / "contact_sheet.png"]


@register_stage("synth-wild", version=1, per_identity=False, outputs=_wild_outputs,
                help="in-the-wild-like renders with ground truth (for finetuning)")
def run_synth_wild(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.synth.wild import synth_wild

    cfg = wild_config(ctx.params)
    out = _out_dir(ctx)
    fm = ctx.input_list("face_model", required=False)
    summary = synth_wild(out, cfg, face_model=load_face_model(fm[0]) if fm else None, producer=ctx.producer(),
                         cache_key=ctx.cache_key)
    log.info(f"synth wild: {cfg.count} images of {summary['identities']} identities in {out} "
             f"({summary['seconds_per_image']:.3f} s/image + {summary['envmap_setup_seconds']:.1f} s map setup)")
    return _wild_outputs(ctx)


@click.command("wild")
@click.option("--count", "-n", type=click.IntRange(1, None), default=16, show_default=True, help="Number of images.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-wild/).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (image k depends on seed, k).")
@click.option("--size", type=click.IntRange(32, 1024), default=224, show_default=True,
              help="Image size S (the Deep3DFaceRecon camera scaled to S x S).")
@click.option("--images-per-identity", type=click.IntRange(1, None), default=4, show_default=True,
              help="Images of each identity (different pose, expression, lighting).")
@click.option("--occluder-fraction", type=click.FloatRange(0, 1), default=0.2, show_default=True,
              help="Fraction of images with a hand- or hat-like occluder.")
@click.option("--landmark-noise", type=click.FloatRange(0, None), default=1.0, show_default=True,
              help="Gaussian landmark noise sigma in pixels.")
@click.option("--encoding", type=click.Choice(["gamma1.2", "srgb"]), default="gamma1.2", show_default=True,
              help="Display encoding of the PNGs (recorded).")
@click.option("--noise", type=click.FloatRange(0, None), default=0.004, show_default=True,
              help="Read-noise sigma (linear); shot noise is added on top.")
@click.option("--envmaps", type=click.IntRange(1, None), default=8, show_default=True,
              help="Number of procedural HDR maps in the pool.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face-model artifact (default: the procedural model, written to DIR/face_model.npz).")
@click.option("--face-vertices", type=click.IntRange(200, 500000), default=35000, show_default=True,
              help="Vertex count of the procedural face model (when --face-model is not given).")
@click.option("--shard-size", type=click.IntRange(1, None), default=None,
              help="Also write prepare-wild shards of this many images (geometry from the truth) to DIR/shards/.")
@workspace_option
@json_option
def wild_cmd(count, out, seed, size, images_per_identity, occluder_fraction, landmark_noise, encoding, noise,
             envmaps, face_model, face_vertices, shard_size, workspace, as_json):
    """Render in-the-wild-like face images with ground truth for finetuning (docs/wild.md).

    Writes DIR/images/NAME.png, DIR/landmarks/NAME.pts, DIR/truth/NAME.npz, DIR/identities/IDNNNNN.npz,
    DIR/envmaps/, DIR/face_model.npz, DIR/manifest.npz (split by identity) and DIR/contact_sheet.png.
    """
    params = {"count": count, "seed": seed, "size": size, "images_per_identity": images_per_identity,
              "occluder_fraction": occluder_fraction, "landmark_noise": landmark_noise, "encoding": encoding,
              "noise": noise, "envmaps": envmaps}
    if face_model is None:
        params["face_vertices"] = face_vertices
    wild_config(params)
    inputs = {"face_model": [face_model]} if face_model is not None else {}
    paths = run_stage_cli("synth-wild", workspace=workspace, params=params, inputs=inputs, output=out,
                          stage_name="synth-wild")
    if shard_size:
        from reflectmm_cli.finetune.data import shard_names

        folder = paths[0].parent
        for name in shard_names(count, shard_size):
            paths += run_stage_cli("prepare-wild", workspace=workspace, identity=name,
                                   params={"shard_size": shard_size, "from_truth": True, "aligned": True, "size": size},
                                   inputs={"images": [folder / "images"], "truth": [folder],
                                           "face_model": [folder / "face_model.npz"]},
                                   output=folder / "shards", stage_name="prepare-wild")
    emit(paths, as_json)


@click.group("synth")
def synth_group():
    """The synthetic world: Multi-PIE-like captures with ground truth, HDR environment maps."""


synth_group.add_command(multipie_cmd)
synth_group.add_command(envmaps_cmd)
synth_group.add_command(wild_cmd)

COMMANDS = [synth_group]

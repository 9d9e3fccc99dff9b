"""Stage ``synth-wild``: in-the-wild-like renders with full ground truth, for finetuning (docs/wild.md).

Not per identity; the output is a folder: ``--out DIR`` / the explicit output, else ``<workspace>/<stage_name>/``.
Input role: ``face_model`` (optional; default the procedural face model of ``face_vertices`` vertices, written to
``DIR/face_model.npz``).  The defaults are those of :class:`reflectmm_cli.synth.wild.WildConfig` (written there
once); this declaration adds the ranges and choices.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.procedural import MIN_VERTICES
from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext
from reflectmm_cli.stages.synth_envmaps import _even
from reflectmm_cli.stages.synth_multipie import out_dir
from reflectmm_cli.synth.wild import ENCODINGS, WildConfig

VERB = "synth-wild"

_D = WildConfig()

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie'),
)


def check_split_fractions(v: list[float]) -> None:
    """A train/val/test split: three non-negative fractions (the range does the sign) with a positive sum."""
    if len(v) != 3 or sum(v) <= 0:
        raise ValueError(f"{v} is not three train/val/test fractions with a positive sum")


PARAMS = (
    Param("count", "int", _D.count, aliases=("-n",), range=(1, 10_000_000), help="Number of images."),
    Param("seed", "int", _D.seed, range=SEED_RANGE, help="Random seed (image k depends on seed, k)."),
    Param("size", "int", _D.size, range=(32, 1024), unit="px",
          help="Image size S (the Deep3DFaceRecon camera scaled to S x S)."),
    Param("images_per_identity", "int", _D.images_per_identity, range=(1, 100000),
          help="Images of each identity (different pose, lighting; expression per identity by default)."),
    Param("occluder_fraction", "float", _D.occluder_fraction, range=(0.0, 1.0),
          help="Fraction of images with a hand- or hat-like occluder."),
    Param("landmark_noise", "float", _D.landmark_noise, range=(0.0, None), unit="px",
          help="Gaussian landmark noise sigma."),
    Param("encoding", "str", _D.encoding, choices=ENCODINGS, help="Display encoding of the PNGs (recorded)."),
    Param("noise", "float", _D.noise, range=(0.0, None),
          help="Read-noise sigma (linear); shot noise is added on top."),
    Param("envmaps", "int", _D.envmaps, range=(1, 10000), help="Number of procedural HDR maps in the pool."),
    Param("envmap_width", "int", _D.envmap_width, range=(8, 16384), unit="px", check=_even,
          help="Equirectangular width of the maps (height = width/2; even)."),
    Param("uv_size", "int", _D.uv_size, range=(16, 4096), unit="texels",
          help="Resolution of the skin maps sampled at the vertices."),
    Param("face_vertices", "int", _D.face_vertices, range=(MIN_VERTICES, 500000),
          help="Vertex count of the procedural face model (when no face model is given)."),
    Param("ao_rays", "int", _D.ao_rays, range=(1, 1024), help="Ambient-occlusion rays per vertex."),
    Param("spec_rays", "int", _D.spec_rays, range=(1, 1024), help="GGX-lobe visibility rays per vertex."),
    Param("prefilter_width", "int", _D.prefilter_width, range=(8, 4096), unit="px",
          help="Width of the GGX-prefiltered residual maps."),
    Param("expression_per_identity", "bool", _D.expression_per_identity, option="--no-expression-per-identity",
          help="One expression per identity (geometry and occlusion computed once per identity); "
               "--no-expression-per-identity draws one per image."),
    Param("skin", "str", None, choices=("single", "two-lobe"),
          help="Skin specular: single (one GGX lobe; the default) or two-lobe (a sharp and a broad GGX lobe mixed "
               "per region; docs/synthetic.md)."),
    Param("split", "floats", list(_D.split), range=(0.0, None), check=check_split_fractions, option="",
          help="Train/val/test fractions of the identities (recipe only)."),
)

_FIELDS = frozenset(f.name for f in fields(WildConfig))


def wild_config(params: dict) -> WildConfig:
    """The library config of resolved stage params (every param of this stage is a WildConfig field)."""
    return WildConfig(**{k: v for k, v in params.items() if k in _FIELDS})


def _outputs(ctx: StageContext) -> list[Path]:
    out = out_dir(ctx)
    return [out / "manifest.npz", out / "face_model.npz", out / "contact_sheet.png"]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.synth.wild import synth_wild

    cfg = wild_config(ctx.params)
    out = out_dir(ctx)
    fm = ctx.input_list("face_model", required=False)
    if len(fm) > 1:
        raise ReflectmmError(f"{VERB}: give at most one face_model input")
    summary = synth_wild(out, cfg, face_model=load_face_model(fm[0]) if fm else None, producer=ctx.producer(),
                         cache_key=ctx.cache_key)
    log.info(f"synth wild: {cfg.count} images of {summary['identities']} identities in {out} "
             f"({summary['seconds_per_image']:.3f} s/image + {summary['envmap_setup_seconds']:.1f} s map setup)")
    return _outputs(ctx)


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="in-the-wild-like renders with ground truth (for finetuning)", inputs=INPUTS)

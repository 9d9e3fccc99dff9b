"""Stage ``synth-envmaps``: procedural HDR environment maps as EXR (docs/synthetic.md).  Not per identity; the
output is a folder: ``--out DIR``, else ``<workspace>/<stage_name>/``."""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Stage, StageContext
from reflectmm_cli.stages.synth_multipie import out_dir

VERB = "synth-envmaps"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS: tuple = ()


def _even(width: int) -> None:
    if width % 2:
        raise ValueError(f"{width} is not even")


PARAMS = (
    Param("count", "int", aliases=("-n",), default=8, range=(1, 100000), help="Number of maps."),
    Param("seed", "int", 0, range=SEED_RANGE, help="Random seed (maps depend on seed and index)."),
    Param("width", "int", 512, range=(8, 16384), unit="px", check=_even,
          help="Equirectangular width (height = width/2; even)."),
)


def _outputs(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.synth.envmaps import ENVMAP_KINDS

    out = out_dir(ctx)
    return [out / f"env_{i:04d}_{ENVMAP_KINDS[i % len(ENVMAP_KINDS)]}.exr" for i in range(ctx.params["count"])] + \
        [out / "contact_sheet.png"]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.artifacts import make_meta
    from reflectmm_cli.synth.envmaps import write_envmaps

    p = {k: ctx.params[k] for k in ("count", "seed", "width")}
    meta = make_meta("envmap", params=p, producer=ctx.producer(), cache_key=ctx.cache_key)
    paths = write_envmaps(out_dir(ctx), p["count"], p["seed"], p["width"], meta_base=meta)
    log.info(f"synth envmaps: {p['count']} maps ({p['width']}x{p['width'] // 2}) in {out_dir(ctx)}")
    return paths


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="procedural HDR environment maps (EXR)", inputs=INPUTS)

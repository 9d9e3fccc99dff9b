"""``reflectmm synth``: the synthetic world (docs/synthetic.md).

* ``synth multipie`` — identities with known shape and spatially varying reflectance rendered on a Multi-PIE-like
  rig, written in the exact Multi-PIE layout with landmarks, plus ground truth (stage ``synth-multipie``);
* ``synth envmaps`` — procedural HDR environment maps as EXR (stage ``synth-envmaps``).

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


@click.group("synth")
def synth_group():
    """The synthetic world: Multi-PIE-like captures with ground truth, HDR environment maps."""


synth_group.add_command(envmaps_cmd)

COMMANDS = [synth_group]

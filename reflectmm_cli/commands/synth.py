"""``reflectmm synth``: click wrappers of the ``synth-multipie``, ``synth-envmaps`` (docs/synthetic.md) and
``synth-wild`` (docs/wild.md) stages."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (ParamType, emit, given_params, json_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import prepare_wild, synth_envmaps, synth_multipie, synth_wild
from reflectmm_cli.workspace import resolve_workspace


@click.command("envmaps")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-envmaps/).")
@param_options(synth_envmaps.PARAMS)
@workspace_option
@json_option
def envmaps_cmd(out, workspace, as_json, **kw):
    """Procedural HDR environment maps (sky+sun, overcast, indoor, coloured) as float32 EXR (R,G,B).

    Equirectangular, +y up, image centre looking down -z (the convention of reflectmm_cli.shading.envmap);
    linear radiance with a dynamic range like real captures.  Also writes a tone-mapped contact_sheet.png.
    """
    paths = run_stage_cli(synth_envmaps.VERB, workspace=workspace, params=given_params(kw, synth_envmaps.PARAMS),
                          output=out, stage_name=synth_envmaps.VERB)
    emit(paths, as_json)


@click.command("multipie")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-multipie/).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face-model artifact to use (default: the procedural model, written to DIR/face_model.npz).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Rig table (TOML; default: the packaged Multi-PIE-like rig).")
@param_options(synth_multipie.PARAMS)
@workspace_option
@json_option
def multipie_cmd(out, face_model, rig, workspace, as_json, **kw):
    """Render synthetic identities on a Multi-PIE-like rig, in the exact Multi-PIE layout, with ground truth.

    Writes DIR/data/session01/multiview/SSS/01/CC_C/SSS_01_01_CCC_II.png (II = 00 room light, 01-18 flashes),
    SSS_01_01_CCC_00_lm.pts landmark files, DIR/rig.toml, DIR/face_model.npz, DIR/truth/SSS.npz (synth-truth)
    and DIR/contact_sheet.png.  Prints the truth files, rig.toml, face_model.npz and the contact sheet.
    """
    params = given_params(kw, synth_multipie.PARAMS)
    inputs = {}
    if face_model is not None:
        inputs["face_model"] = [face_model]
    if rig is not None:
        inputs["rig"] = [rig]
    paths = run_stage_cli(synth_multipie.VERB, workspace=workspace, params=params, inputs=inputs, output=out,
                          stage_name=synth_multipie.VERB)
    emit(paths, as_json)


_SHARD_SIZE = next(p for p in prepare_wild.PARAMS if p.name == "shard_size")


@click.command("wild")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/synth-wild/).")
@click.option("--face-model", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="face-model artifact (default: the procedural model, written to DIR/face_model.npz).")
@param_options(synth_wild.PARAMS)
@click.option("--shard-size", type=ParamType(_SHARD_SIZE), default=None,
              help="Also write prepare-wild shards of this many images (geometry from the truth) to DIR/shards/.")
@workspace_option
@json_option
def wild_cmd(out, face_model, shard_size, workspace, as_json, **kw):
    """Render in-the-wild-like face images with ground truth for finetuning (docs/wild.md).

    Writes DIR/images/NAME.png, DIR/landmarks/NAME.pts, DIR/truth/NAME.npz, DIR/identities/IDNNNNN.npz,
    DIR/envmaps/, DIR/face_model.npz, DIR/manifest.npz (split by identity) and DIR/contact_sheet.png.
    """
    ws = resolve_workspace(workspace)
    params = given_params(kw, synth_wild.PARAMS)
    inputs = {"face_model": [face_model]} if face_model is not None else {}
    paths = run_stage_cli(synth_wild.VERB, workspace=ws, params=params, inputs=inputs, output=out)
    if shard_size:
        folder = paths[0].parent
        shards, failed = prepare_wild.run_shards(
            ws, {"shard_size": shard_size, "from_truth": True, "aligned": True, "size": synth_wild.STAGE.resolve(params)["size"]},
            {"images": [folder / "images"], "truth": [folder], "face_model": [folder / "face_model.npz"]},
            folder / "shards")
        paths += shards
        if failed:
            emit(paths, as_json)
            raise ReflectmmError(failed[0])
    emit(paths, as_json)


@click.group("synth")
def synth_group():
    """The synthetic world: Multi-PIE-like captures and in-the-wild images with ground truth, HDR maps."""


synth_group.add_command(multipie_cmd)
synth_group.add_command(envmaps_cmd)
synth_group.add_command(wild_cmd)

COMMANDS = [synth_group]

"""``reflectmm reconstruct``: click wrapper of the ``reconstruct`` stage (reflectmm_cli/stages/reconstruct.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (device_option, emit, given_params, json_option, output_option,
                                            param_options, run_stage_cli, workspace_option)
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.stages.reconstruct import PARAMS, STAGE, VERB
from reflectmm_cli.workspace import resolve_workspace

_FILE = click.Path(dir_okay=False, path_type=Path)
_DIR = click.Path(file_okay=False, path_type=Path)


@click.command(VERB)
@click.option("--encoder", type=_FILE, default=None,
              help="Encoder safetensors written by finetune (default: <ws>/finetune/finetune_encoder.safetensors).")
@click.option("--model", type=_FILE, default=None,
              help="reflectance-model artifact (default: the finetuned one, <ws>/finetune/finetune.npz).")
@click.option("--light-model", type=_FILE, default=None,
              help="light-model artifact (default: <ws>/build-light-pca/build-light-pca.npz).")
@click.option("--data", multiple=True, type=click.Path(path_type=Path),
              help="wild-shard artifact or folder of them (repeatable).")
@click.option("--images", type=_DIR, default=None,
              help="A folder of photos instead of shards: aligned, fitted and G-buffered in memory (prepare-wild).")
@click.option("--landmarks", type=_DIR, default=None,
              help="--images: folder of <stem>.pts/.txt/.npy (default: the images folder, then ../landmarks).")
@click.option("--masks", type=_DIR, default=None, help="--images: CelebAMask-HQ label images <stem>.png.")
@click.option("--face-model", type=_FILE, default=None,
              help="--images: the face model of the reflectance model's vertices (default: the workspace's).")
@param_options(PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def reconstruct_cmd(encoder, model, light_model, data, images, landmarks, masks, face_model, device, workspace,
                    output, as_json, **kw):
    """Reconstruct images: writes a `reconstruction` artifact (<ws>/reconstruct/reconstruct.npz or --output) with
    β, γ, z, SH lighting and full/diffuse/specular/albedo/lobe-weight layers, plus a PNG (one row per image)."""
    ws = resolve_workspace(workspace)
    if bool(data) == (images is not None):
        raise click.UsageError("give either --data SHARD... or --images DIR")
    no_encoder = kw.get("refine") and kw.get("refine_from") == "zero" and encoder is None
    given = {"encoder": [encoder], "model": [model], "light_model": [light_model], "data": data}
    if images is not None:  # the photos are prepared in memory with a face model (and the optional folders)
        given.update(images=[images], face_model=[face_model], landmarks=[landmarks], masks=[masks])
    roles = ("encoder",) * (not no_encoder) + ("model", "light_model") + ("face_model",) * (images is not None)
    inputs = default_inputs(STAGE, ws, given, roles=roles)
    out = run_stage_cli(VERB, workspace=ws, params=given_params(kw, PARAMS), inputs=inputs, output=output,
                        device=device)
    emit(out, as_json)


COMMANDS = [reconstruct_cmd]

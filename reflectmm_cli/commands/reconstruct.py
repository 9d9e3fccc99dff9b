"""``reflectmm reconstruct``: click wrapper of the ``reconstruct`` stage (reflectmm_cli/stages/reconstruct.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (device_option, emit, given_params, json_option, output_option,
                                            param_options, run_stage_cli, workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.reconstruct import PARAMS, VERB
from reflectmm_cli.workspace import default_input, find_face_model, resolve_workspace

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
    inputs = {} if no_encoder else {"encoder": [encoder or default_input(ws, "finetune", "--encoder",
                                                                         "finetune_encoder", ".safetensors")]}
    inputs |= {"model": [model or default_input(ws, "finetune", "--model")],
               "light_model": [light_model or default_input(ws, "build-light-pca", "--light-model")]}
    if images is not None:
        inputs["images"] = [images]
        fm = face_model or find_face_model(ws)
        if fm is None:
            raise ReflectmmError("--images needs --face-model (no face model found in the workspace)")
        inputs["face_model"] = [fm]
        for role, p in (("landmarks", landmarks), ("masks", masks)):
            if p is not None:
                inputs[role] = [p]
    else:
        inputs["data"] = list(data)
    out = run_stage_cli(VERB, workspace=ws, params=given_params(kw, PARAMS), inputs=inputs, output=output,
                        device=device)
    emit(out, as_json)


COMMANDS = [reconstruct_cmd]

"""``reflectmm finetune``: click wrapper of the ``finetune`` stage (reflectmm_cli/stages/finetune.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (device_option, emit, given_params, json_option, output_option,
                                            param_options, run_stage_cli, workspace_option)
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.stages.finetune import PARAMS, STAGE, VERB
from reflectmm_cli.workspace import resolve_workspace

_FILE = click.Path(dir_okay=False, path_type=Path)


@click.command(VERB)
@click.option("--model", type=_FILE, default=None,
              help="Initial reflectance-model artifact with its per-vertex part (default: <ws>/build-pca/build-pca.npz).")
@click.option("--light-model", type=_FILE, default=None,
              help="light-model artifact (default: <ws>/build-light-pca/build-light-pca.npz).")
@click.option("--data", multiple=True, type=click.Path(path_type=Path),
              help="wild-shard artifact or folder of them, repeatable (default: <ws>/prepare-wild/*.npz).")
@click.option("--face-model", type=_FILE, default=None,
              help="Face model for the previews and the UV-map update (default: the one the shards record).")
@click.option("--identity-weights", type=_FILE, default=None,
              help="ArcFace iresnet safetensors (insightface key names) for L_per; without it L_per is off.")
@click.option("--init-weights", type=_FILE, default=None,
              help="ImageNet ResNet trunk as safetensors with torchvision key names.")
@click.option("--phase1-encoder", type=_FILE, default=None,
              help="Start at phase 2 from another run's *_encoder_phase1.safetensors (same phase-1 settings and data;"
                   " a joint-SGD run and its Table 2 control share phase 1 this way).")
@param_options(PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def finetune_cmd(model, light_model, data, face_model, identity_weights, init_weights, phase1_encoder, device,
                 workspace, output, as_json, **kw):
    """Finetune the reflectance model and train the reconstruction encoder on wild-shard data.

    Writes the finetuned reflectance-model artifact (<ws>/finetune/finetune.npz or --output), the encoder
    (finetune_encoder.safetensors), the checkpoint and JSONL log (finetune_work/), and PNGs (loss curves, samples
    and components before/after).  --epochs2 0 trains the encoder only (phase 1) and leaves the model unchanged.
    """
    ws = resolve_workspace(workspace)
    given = {"model": [model], "light_model": [light_model], "data": data, "face_model": [face_model],
             "identity_weights": [identity_weights], "init_weights": [init_weights], "phase1_encoder": [phase1_encoder]}
    inputs = default_inputs(STAGE, ws, given, roles=("data", "model", "light_model", "face_model"))
    out = run_stage_cli(VERB, workspace=ws, params=given_params(kw, PARAMS), inputs=inputs, output=output,
                        device=device)
    emit(out, as_json)


COMMANDS = [finetune_cmd]

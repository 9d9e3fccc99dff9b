"""``reflectmm build-baseline``: click wrapper of the ``build-baseline`` stage
(reflectmm_cli/stages/build_baseline.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, given_params, json_option, output_option, param_options, \
    run_stage_cli, workspace_option
from reflectmm_cli.stages.build_baseline import PARAMS, STAGE, VERB
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.workspace import resolve_workspace


@click.command(VERB)
@click.option("--truth", "truth", multiple=True, type=click.Path(exists=True, path_type=Path),
              help="synth-truth <id>.npz files or the folder holding them (repeatable; default: the workspace's "
                   "truth folder); for --kind oracle a synth wild folder.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Face model for the per-vertex model (default: the workspace's).")
@click.option("--like", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="--kind oracle: a reflectance model whose size the oracle takes (component count, UV size; its "
                   "lobe exponents must be the truth's).")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def build_baseline_cmd(truth, face_model, like, workspace, output, as_json, **kw):
    """Baseline reflectance model from ground-truth maps: BFM09's role (--kind diffuse-only) or AlbedoMM's role
    (--kind albedomm), models (a) and (b) of the paper's Tables 2 and 3; or the oracle of finetuning (--kind
    oracle): the model of the same size built from a synth wild folder's training identities' truth.

    Writes a `reflectance-model` artifact (<ws>/build-baseline/<kind>.npz or --output) and a component preview.
    """
    inputs = default_inputs(STAGE, resolve_workspace(workspace), {"truth": truth, "face_model": [face_model],
                                                                     "like": [like]})
    paths = run_stage_cli(VERB, workspace=workspace, params=given_params(kw, PARAMS), inputs=inputs, output=output)
    emit(paths, as_json)


COMMANDS = [build_baseline_cmd]

"""``reflectmm unwrap-uv``: click wrapper of the ``unwrap-uv`` stage (reflectmm_cli/stages/unwrap_uv.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, id_callback, json_option, output_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.stages.unwrap_uv import PARAMS, STAGE, VERB
from reflectmm_cli.workspace import resolve_workspace


@click.command(VERB)
@click.option("--id", "identity", callback=id_callback, required=True, help="Identity (e.g. 042).")
@click.option("--capture", "capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="capture artifact (default <ws>/preprocess-multipie/<id>.npz).")
@click.option("--geometry", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="geometry artifact (default <ws>/fit-geometry/<id>.npz).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model (face-model artifact or BFM .mat; default: the one the geometry records, else "
                   "face_model.npz of the capture's dataset folder, else the workspace's).")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def unwrap_uv_cmd(identity, capture, geometry, face_model, workspace, output, as_json, **kw):
    """Unwrap one identity's OLAT images into UV space with visibility, shadow and saturation masks."""
    ws = resolve_workspace(workspace)
    inputs = default_inputs(STAGE, ws, {"capture": [capture], "geometry": [geometry], "face_model": [face_model]},
                            identity=identity)
    paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=given_params(kw, PARAMS), inputs=inputs,
                          output=output)
    emit(paths, as_json)


COMMANDS = [unwrap_uv_cmd]

"""``reflectmm fit-reflectance``: click wrapper of the ``fit-reflectance`` stage (reflectmm_cli/stages)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (device_option, emit, given_params, id_callback, json_option,
                                            output_option, param_options, run_stage_cli, workspace_option)
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.stages.fit_reflectance import PARAMS, STAGE, VERB
from reflectmm_cli.workspace import check_id, resolve_workspace


@click.command(VERB)
@click.option("--id", "identity", callback=id_callback, default=None,
              help="Identity (reads <workspace>/unwrap-uv/<id>.npz).")
@click.option("--input", "-i", "input_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="uv-observations artifact (overrides the workspace convention).")
@param_options(PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def fit_reflectance_cmd(identity, input_path, device, workspace, output, as_json, **kw):
    """Fit diffuse albedo C and lobe weights W for one identity.

    Writes <workspace>/fit-reflectance/<id>.npz (reflectance-maps), <id>.exr (channels albedo.R/G/B,
    weight.p<exponent>) and PNG previews <id>_albedo/_weights/_residual/_flagged.png.
    """
    if identity is None and input_path is None:
        raise click.UsageError("give --id or --input")
    params = given_params(kw, PARAMS)
    inputs = default_inputs(STAGE, resolve_workspace(workspace), {"observations": [input_path]}, identity=identity)
    if identity is None:  # the input's name is the identity: it names the outputs, so it must be a safe id
        identity = check_id(Path(input_path).stem, f"--input {input_path}: its name is the identity (or give --id)")
    paths = run_stage_cli(VERB, workspace=workspace, identity=identity, params=params,
                          inputs=inputs, output=output, device=device)
    emit(paths, as_json)


COMMANDS = [fit_reflectance_cmd]

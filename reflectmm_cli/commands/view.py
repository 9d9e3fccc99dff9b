"""``reflectmm view``: click wrapper of the ``view`` stage (reflectmm_cli/stages/view.py)."""
from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, output_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.view import PARAMS, VERB


@click.command(VERB)
@click.argument("model", type=click.Path(path_type=Path))
@click.option("--compare", type=click.Path(path_type=Path), default=None,
              help="A second reflectance model shown beside the first under the same β and light.")
@click.option("--face-model", "face_model", type=click.Path(path_type=Path), default=None,
              help="face-model artifact or BFM .mat (default: the one the model records).")
@click.option("--light-model", "light_model", type=click.Path(path_type=Path), default=None,
              help="light-model artifact: its mean and first components become the γ sliders.")
@click.option("--envmap", "envmaps", multiple=True, type=click.Path(path_type=Path),
              help="Equirectangular HDR map (EXR/HDR), projected to SH; repeat for several.")
@param_options(PARAMS)
@output_option(help="Output HTML (default <workspace>/view/model.html).")
@workspace_option
@json_option
def view_cmd(model, compare, face_model, light_model, envmaps, output, workspace, as_json, **kw):
    """Write a self-contained interactive HTML viewer of MODEL (open it in a browser; docs/viewer.md)."""
    inputs = {"model": [model]}
    for role, pth in (("compare", compare), ("face_model", face_model), ("light_model", light_model)):
        if pth is not None:
            inputs[role] = [pth]
    if envmaps:
        inputs["envmap"] = list(envmaps)
    paths = run_stage_cli(VERB, workspace=workspace, inputs=inputs, output=output, params=given_params(kw, PARAMS))
    emit(paths, as_json)


COMMANDS = [view_cmd]

"""``reflectmm render``: click wrapper of the ``render`` stage (reflectmm_cli/stages/render.py)."""
from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, output_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.render import PARAMS, VERB


@click.command(VERB)
@click.option("--face-model", "face_model", type=click.Path(path_type=Path), required=True,
              help="face-model artifact or BFM .mat.")
@click.option("--maps", type=click.Path(path_type=Path), default=None, help="reflectance-maps artifact.")
@click.option("--model", type=click.Path(path_type=Path), default=None, help="reflectance-model artifact.")
@click.option("--envmap", type=click.Path(path_type=Path), default=None,
              help="Equirectangular HDR map (EXR/HDR; frame of docs/shading.md), projected to SH.")
@click.option("--sh", type=click.Path(path_type=Path), default=None,
              help="SH coefficients (3, (L+1)²) in .npy/.txt/.json or an NPZ with 'sh'.")
@click.option("--geometry", type=click.Path(path_type=Path), default=None,
              help="geometry artifact: render its fitted vertices instead.")
@param_options(PARAMS)
@output_option(help="Output EXR (default <workspace>/render/render.exr); the PNG goes beside it.")
@workspace_option
@json_option
def render_cmd(face_model, maps, model, envmap, sh, geometry, output, workspace, as_json, **kw):
    """Render a face model with reflectance maps or a reflectance model to a linear EXR + display PNG."""
    inputs = {"face_model": [face_model]}
    for role, pth in (("maps", maps), ("model", model), ("envmap", envmap), ("sh", sh), ("geometry", geometry)):
        if pth is not None:
            inputs[role] = [pth]
    paths = run_stage_cli(VERB, workspace=workspace, inputs=inputs, output=output, params=given_params(kw, PARAMS))
    emit(paths, as_json)


COMMANDS = [render_cmd]

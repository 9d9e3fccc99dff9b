"""``reflectmm build-light-pca``: click wrapper of the ``build-light-pca`` stage
(reflectmm_cli/stages/build_light_pca.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, output_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.build_light_pca import PARAMS, VERB


@click.command(VERB)
@click.argument("maps", nargs=-1, type=click.Path(path_type=Path))
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(path_type=Path),
              help="An HDR environment map (.exr/.hdr, equirectangular) or a folder of them; repeatable.")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def build_light_pca_cmd(maps, inputs, workspace, output, as_json, **kw):
    """Build a PCA lighting model from HDR environment maps (MAPS and/or --input, files or folders).

    Writes a `light-model` artifact (<workspace>/build-light-pca/build-light-pca.npz or --output) and a PNG
    preview beside it. Unreadable or non-finite maps are skipped and reported on stderr.
    """
    paths = list(inputs) + list(maps)
    if not paths:
        raise click.UsageError("give at least one environment map or folder (MAPS or --input)")
    out = run_stage_cli(VERB, workspace=workspace, params=given_params(kw, PARAMS), inputs={"envmaps": paths},
                        output=output)
    emit(out, as_json)


COMMANDS = [build_light_pca_cmd]

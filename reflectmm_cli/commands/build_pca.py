"""``reflectmm build-pca``: click wrapper of the ``build-pca`` stage (reflectmm_cli/stages/build_pca.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, output_option, param_options, parse_ids,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.build_pca import PARAMS, STAGE, VERB
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.workspace import resolve_workspace


@click.command(VERB)
@click.option("--ids", default=None, help="Identities (001,002 or 001-010): reads <ws>/fit-reflectance/<id>.npz.")
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(path_type=Path),
              help="A reflectance-maps artifact (repeatable; instead of or in addition to --ids).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face-model artifact / BFM .mat for the per-vertex model (default: the workspace's face model, "
                   "docs/architecture.md).")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def build_pca_cmd(ids, inputs, face_model, workspace, output, as_json, **kw):
    """Build the PCA reflectance model from N identities' reflectance maps.

    Writes a `reflectance-model` artifact (<ws>/build-pca/build-pca.npz or --output), a PNG of the first 3
    components ±2σ and (with a face model) 30 random samples under a white frontal point light.
    """
    ws = resolve_workspace(workspace)
    if not parse_ids(ids) and not inputs:
        raise click.UsageError("give --ids or at least two --input files")
    inp = default_inputs(STAGE, ws, {"maps": inputs, "face_model": [face_model]}, ids=parse_ids(ids))
    out = run_stage_cli(VERB, workspace=workspace, params=given_params(kw, PARAMS), inputs=inp, output=output)
    emit(out, as_json)


COMMANDS = [build_pca_cmd]

"""``reflectmm calibrate-rig``: click wrapper of the ``calibrate-rig`` stage (reflectmm_cli/stages/calibrate_rig.py).

Python API: :func:`reflectmm_cli.geometry_fit.calibrate.calibrate_from_captures`.
"""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, output_option, param_options, parse_ids,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.stages.calibrate_rig import PARAMS, STAGE, VERB
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.workspace import resolve_workspace


@click.command(VERB)
@click.option("--ids", default=None, help="Identities (001,002 or 001-128): reads <ws>/preprocess-multipie/<id>.npz.")
@click.option("--capture", "-i", "captures", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="A capture artifact (repeatable; instead of or in addition to --ids).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model (default: face_model.npz of the first capture's dataset folder, else "
                   "<ws>/face_model.npz).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="nominal rig table TOML: camera angles, a rough distance and the focal (default: rig.toml of the "
                   "dataset folder, else the packaged Multi-PIE table; its image size must match the images).")
@click.option("--geometry", "geometries", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="a preliminary fit-geometry output on this calibration's rig (repeatable, one per capture, same "
                   "order): registers the cameras no identity annotates jointly by the flash images.")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def calibrate_rig_cmd(ids, captures, face_model, rig, geometries, workspace, output, as_json, **kw):
    """Estimate one rig (camera poses, focal, flash positions) from the landmarks of all identities.

    Writes the `rig` artifact (<ws>/calibrate-rig/calibrate-rig.npz) and rig.toml beside it; pass that to
    `fit-geometry --rig` (with a tight --rig-sigma, e.g. 3 mm).
    """
    ws = resolve_workspace(workspace)
    if not parse_ids(ids) and not captures:
        raise click.UsageError("give --ids or --capture files")
    inputs = default_inputs(STAGE, ws, {"capture": captures, "face_model": [face_model], "rig": [rig],
                                        "geometry": geometries}, ids=parse_ids(ids))
    out = run_stage_cli(VERB, workspace=ws, params=given_params(kw, PARAMS), inputs=inputs, output=output)
    emit(out, as_json)


COMMANDS = [calibrate_rig_cmd]

"""``reflectmm unwrap-uv``: click wrapper of the ``unwrap-uv`` stage (reflectmm_cli/stages/unwrap_uv.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, id_callback, json_option, output_option, param_options,
                                            run_stage_cli, workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.unwrap_uv import PARAMS, VERB
from reflectmm_cli.workspace import find_face_model, resolve_workspace, stage_output


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
    capture = capture or stage_output(ws, "preprocess-multipie", identity)
    geometry = geometry or stage_output(ws, "fit-geometry", identity)
    for role, p, verb in (("capture", capture, "preprocess-multipie"), ("geometry", geometry, "fit-geometry")):
        if not Path(p).exists():
            raise ReflectmmError(f"{role} artifact not found (run {verb} first or pass --{role})", p)
    if face_model is None:
        face_model = find_face_model(ws, capture=capture, geometry=geometry)
        if face_model is None:
            raise ReflectmmError("no face model: the geometry does not record one, and there is no face_model.npz "
                                 "beside the capture's dataset or in the workspace; pass --face-model", geometry)
    paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=given_params(kw, PARAMS),
                          inputs={"capture": [capture], "geometry": [geometry], "face_model": [face_model]},
                          output=output)
    emit(paths, as_json)


COMMANDS = [unwrap_uv_cmd]

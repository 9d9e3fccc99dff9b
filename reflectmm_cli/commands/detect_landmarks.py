"""``reflectmm detect-landmarks``: click wrapper of the ``detect-landmarks`` stage (docs/wild.md)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, given_params, json_option, param_options, run_stage_cli,
                                            workspace_option)
from reflectmm_cli.stages.detect_landmarks import PARAMS, VERB


@click.command(VERB)
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder for NAME.pts (iBUG, readable by preprocess-multipie and prepare-wild; "
                   "default <workspace>/detect-landmarks/).")
@param_options(PARAMS)
@workspace_option
@json_option
def detect_landmarks_cmd(images, out, workspace, as_json, **kw):
    """Detect the face and its 68 iBUG landmarks in each image (files or folders); write OUT/NAME.pts.

    Images without a (selected) face are reported one line each and the others are still written; the exit
    status is then 1, unless --allow-missing (then they are listed in OUT/no_face.txt and the status is 0).
    """
    paths = run_stage_cli(VERB, workspace=workspace, params=given_params(kw, PARAMS),
                          inputs={"images": list(images)}, output=out)
    emit(paths, as_json)


COMMANDS = [detect_landmarks_cmd]

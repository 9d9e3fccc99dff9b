"""``reflectmm checksum``: click wrapper of the ``checksum`` stage (reflectmm_cli/stages/checksum.py)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import (emit, id_callback, json_option, output_option, run_stage_cli,
                                            workspace_option)
from reflectmm_cli.stages.checksum import VERB


@click.command(VERB)
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--id", "identity", callback=id_callback, default=None,
              help="Identity this manifest belongs to (names the output).")
@workspace_option
@output_option
@json_option
def checksum_cmd(files, identity, workspace, output, as_json):
    """Write a sha256 manifest of FILES (folders are walked) as a `checksum` artifact."""
    paths = run_stage_cli(VERB, workspace=workspace, identity=identity, inputs={"files": list(files)},
                          output=output)
    emit(paths, as_json)


COMMANDS = [checksum_cmd]

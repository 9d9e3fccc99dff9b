"""``reflectmm preprocess-multipie``: click wrapper of the ``preprocess-multipie`` stage (one or more identities)."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from reflectmm_cli.capture.layout import discover_identities
from reflectmm_cli.commands._common import (emit, given_params, id_callback, json_option, output_option, param_options,
                                            parse_ids, run_stage_cli, workspace_option)
from reflectmm_cli.capture.preprocess import check_rotate_cameras
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import get_stage
from reflectmm_cli.stages.preprocess_multipie import PARAMS, VERB

log = logging.getLogger("reflectmm")


@click.command(VERB)
@click.option("--root", required=True, type=click.Path(path_type=Path),
              help="Multi-PIE root (the folder holding data/sessionNN, or data/ itself).")
@click.option("--id", "identity", callback=id_callback, default=None, help="One identity (e.g. 042).")
@click.option("--ids", default=None, help="Identities: 001,002 or ranges 001-010.")
@click.option("--id-file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="File with one identity per line (# comments).")
@click.option("--all", "all_ids", is_flag=True, help="Every identity found under the root.")
@click.option("--landmarks", "landmarks_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder with SSS_NN_RR_CCC_00_lm.{pts,txt,npy} files (default: beside the images).")
@param_options(PARAMS)
@workspace_option
@output_option
@json_option
def preprocess_multipie_cmd(root, identity, ids, id_file, all_ids, landmarks_dir, workspace, output, as_json, **kw):
    """Linearise one or more identities' Multi-PIE shots into OLAT stacks (`capture` artifacts + contact sheets).

    An identity that lacks required shots is skipped with a reason and the others are processed; the command
    then exits non-zero after writing the successful identities.
    """
    params = given_params(kw, PARAMS)
    p = get_stage(VERB).context(workspace=workspace, params=params).params  # option errors before any data is read
    check_rotate_cameras(p.get("rotate", {}), p.get("views"), p["flashes"])  # once, not once per identity
    idents = ([identity] if identity else []) + parse_ids(ids, id_file)
    if all_ids:
        if identity or ids is not None or id_file is not None:
            raise click.UsageError("--all takes every identity found under --root: give it without --id, --ids "
                                   "or --id-file")
        idents += discover_identities(root)
    idents = list(dict.fromkeys(idents))
    if not idents:
        raise click.UsageError("give --id, --ids, --id-file or --all")
    if output is not None and len(idents) > 1:
        raise click.UsageError("--output needs exactly one identity")
    inputs = {"root": [root]}
    if landmarks_dir is not None:
        inputs["landmarks"] = [landmarks_dir]
    written: list[Path] = []
    failed: list[tuple[str, str]] = []
    for ident in idents:
        try:
            written += run_stage_cli(VERB, workspace=workspace, identity=ident, params=params, inputs=inputs,
                                     output=output)
        except ReflectmmError as exc:
            if len(idents) == 1:
                raise
            log.error("preprocess-multipie: identity %s skipped: %s", ident, exc)
            failed.append((ident, str(exc)))
    emit(written, as_json, {"failed": dict(failed)} if as_json else None)
    if failed:
        reasons = "; ".join(f"{i}: {msg}" for i, msg in failed)
        if len(failed) == len(idents):
            raise ReflectmmError(f"all {len(idents)} identities failed, nothing was written — {reasons}")
        raise ReflectmmError(f"{len(failed)} of {len(idents)} identities failed, the others were written — "
                             f"{reasons}")


COMMANDS = [preprocess_multipie_cmd]

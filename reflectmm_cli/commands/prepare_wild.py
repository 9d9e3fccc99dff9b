"""``reflectmm prepare-wild``: click wrapper of the per-shard ``prepare-wild`` stage (docs/wild.md)."""

from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, given_params, id_callback, json_option, param_options, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.prepare_wild import PARAMS, VERB, run_shards
from reflectmm_cli.workspace import resolve_workspace


@click.command(VERB)
@click.option("--images", "images", required=True, type=click.Path(file_okay=False, exists=True, path_type=Path),
              help="Folder of images (png/jpg/...).")
@click.option("--landmarks", "landmarks", type=click.Path(file_okay=False, exists=True, path_type=Path),
              default=None, help="Folder of 68-point NAME.pts/.txt/.npy (default: next to the images, or ../landmarks).")
@click.option("--masks", "masks", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Folder of face-parsing label images NAME.png (CelebAMask-HQ / BiSeNet ids).")
@click.option("--face-model", "face_model", type=click.Path(dir_okay=False, exists=True, path_type=Path),
              default=None, help="face-model artifact (default: TRUTH/face_model.npz).")
@click.option("--truth", "truth", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="A synth-wild folder: split, truth arrays and vertex errors (default: the images' parent if it "
                   "holds a manifest.npz).")
@param_options(PARAMS)
@click.option("--shard", "shards", callback=id_callback, multiple=True,
              help="Only these shards (shard_NNNNN; default all).")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/prepare-wild/).")
@workspace_option
@json_option
def prepare_wild_cmd(images, landmarks, masks, face_model, truth, shards, out, workspace, as_json, **kw):
    """Align in-the-wild images (Deep3DFaceRecon crop), fit their geometry with one view, rasterise the
    G-buffer once and write wild-shard files DIR/shard_NNNNN.npz (+ shard_NNNNN_overlay.png skin-mask previews).

    Bad inputs (no landmark file, 67 landmarks, unreadable image) are reported one line each; the other images
    are still written; the exit status is 1 unless --allow-skipped.
    """
    inputs = {role: [p] for role, p in (("images", images), ("landmarks", landmarks), ("masks", masks),
                                        ("face_model", face_model), ("truth", truth)) if p is not None}
    paths, failed = run_shards(resolve_workspace(workspace), given_params(kw, PARAMS), inputs, out, shards)
    emit(paths, as_json)
    if failed:
        raise ReflectmmError(failed[0] if len(failed) == 1 else f"{len(failed)} shards failed; the first: {failed[0]}")


COMMANDS = [prepare_wild_cmd]

"""``reflectmm prepare-wild``: aligned crops + fixed geometry + G-buffers as ``wild-shard`` files (docs/wild.md).

A per-shard recipe stage (``prepare-wild``): the identity of a run is a shard name ``shard_NNNNN`` (images
``[N·M, (N+1)·M)`` of the sorted image folder, M = ``shard_size``); ``foreach = "all found"`` lists every shard.
Inputs: ``images`` (folder), optional ``landmarks`` and ``masks`` (folders), ``face_model`` (file) and ``truth``
(a ``synth wild`` folder: split, truth arrays, geometry with ``from_truth``).
"""
from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, json_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log
from reflectmm_cli.stages import StageContext, register_stage

DEFAULTS = {"size": 224, "aligned": False, "from_truth": False, "encoding": "srgb", "shard_size": 256,
            "fit_landmark_iters": 200, "fit_photo_rounds": 1, "fit_photo_iters": 30, "allow_skipped": False}


def _config(params: dict):
    from reflectmm_cli.finetune.data import PrepareConfig

    p = {**DEFAULTS, **{k: v for k, v in params.items() if v is not None}}
    unknown = set(p) - set(DEFAULTS)
    if unknown:
        raise ReflectmmError(f"prepare-wild: unknown param(s) {', '.join(sorted(unknown))}")
    p.pop("allow_skipped")
    return PrepareConfig(**{k: type(DEFAULTS[k])(v) for k, v in p.items()})


def _one(ctx: StageContext, role: str) -> Path | None:
    paths = ctx.input_list(role, required=False)
    if len(paths) > 1:
        raise ReflectmmError(f"prepare-wild: input '{role}' given {len(paths)} times")
    return paths[0] if paths else None


def _out(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.workspace / ctx.stage_name


def _shard_index(ctx: StageContext) -> int:
    try:
        return int(str(ctx.identity).rsplit("_", 1)[1])
    except (IndexError, ValueError):
        raise ReflectmmError(f"prepare-wild: identity must be a shard name shard_NNNNN, got {ctx.identity!r}") from None


def _discover(ctx: StageContext) -> list[str]:
    from reflectmm_cli.finetune.data import list_wild_inputs, shard_names

    cfg = _config(ctx.params)
    return shard_names(len(list_wild_inputs(ctx.input("images"))), cfg.shard_size)


def _outputs(ctx: StageContext) -> list[Path]:
    return [_out(ctx) / f"{ctx.identity}.npz"]


def _files(ctx: StageContext) -> dict[str, list[Path]]:
    from reflectmm_cli.finetune.data import list_wild_inputs

    cfg = _config(ctx.params)
    i = _shard_index(ctx)
    lm, mk = _one(ctx, "landmarks"), _one(ctx, "masks")
    inputs = list_wild_inputs(ctx.input("images"), lm, mk)[i * cfg.shard_size:(i + 1) * cfg.shard_size]
    files = {"images": [x.image for x in inputs], "landmarks": [x.landmarks for x in inputs if x.landmarks],
             "masks": [x.mask for x in inputs if x.mask]}
    fm = _one(ctx, "face_model")
    if fm:
        files["face_model"] = [fm]
    tr = _one(ctx, "truth")
    if tr:
        files["truth"] = [p for x in inputs for p in [tr / "truth" / f"{x.name}.npz"] if p.is_file()]
    return files


@register_stage("prepare-wild", version=1, per_identity=True, outputs=_outputs, input_files=_files,
                discover_ids=_discover, help="aligned crops, fixed geometry and G-buffers as wild-shard files")
def run_prepare_wild(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.data import prepare_wild_shard
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.progress import progress

    cfg = _config(ctx.params)
    fm_path = _one(ctx, "face_model")
    tr = _one(ctx, "truth")
    if fm_path is None and tr is not None and (tr / "face_model.npz").is_file():
        fm_path = tr / "face_model.npz"
    if fm_path is None:
        raise ReflectmmError("prepare-wild: --face-model is required (no synth-wild face_model.npz to fall back on)")
    idx = _shard_index(ctx)
    path, rep, errors = prepare_wild_shard(
        ctx.input("images"), _out(ctx), load_face_model(fm_path), fm_path, cfg, idx,
        landmarks_dir=_one(ctx, "landmarks"), masks_dir=_one(ctx, "masks"), truth_dir=tr, producer=ctx.producer(),
        cache_key=ctx.cache_key, progress_fn=lambda it: progress(it, desc=str(ctx.identity), unit="img"))
    for e in errors:
        log.error(f"prepare-wild: skipped {e}")
    if rep["names"]:
        import numpy as np

        msg = (f"prepare-wild {ctx.identity}: {len(rep['names'])} images, landmark RMSE median "
               f"{np.median(rep['landmark_rmse_px']):.2f} px, {np.median(rep['seconds']):.2f} s/image")
        ve = np.asarray(rep["vertex_error_mm"], float)
        if np.isfinite(ve).any():
            msg += f", vertex RMSE median {np.nanmedian(ve):.1f} mm"
            if rep.get("vertex_error_centred_mm"):
                msg += f" ({np.median(rep['vertex_error_centred_mm']):.1f} mm after removing the mean offset)"
        log.info(msg)
    if errors and not ctx.params.get("allow_skipped"):
        raise ReflectmmError(f"prepare-wild {ctx.identity}: {len(errors)} image(s) skipped (listed above); "
                             "the others were written" + ("" if path else " (none succeeded)"))
    return [path] if path else []


@click.command("prepare-wild")
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
@click.option("--aligned", is_flag=True, help="Images already are aligned S x S crops.")
@click.option("--from-truth", is_flag=True, help="Geometry from the synth-wild truth instead of fitting (implies --aligned).")
@click.option("--size", type=click.IntRange(32, 1024), default=224, show_default=True, help="Crop size S.")
@click.option("--encoding", type=click.Choice(["srgb", "gamma1.2", "linear"]), default="srgb", show_default=True,
              help="Encoding of real images (synth wild records its own).")
@click.option("--shard-size", type=click.IntRange(1, None), default=256, show_default=True, help="Images per shard.")
@click.option("--shard", "shards", multiple=True, help="Only these shards (shard_NNNNN; default all).")
@click.option("--allow-skipped", is_flag=True, help="Exit 0 even when some images were skipped.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default <workspace>/prepare-wild/).")
@workspace_option
@json_option
def prepare_wild_cmd(images, landmarks, masks, face_model, truth, aligned, from_truth, size, encoding, shard_size,
                     shards, allow_skipped, out, workspace, as_json):
    """Align in-the-wild images (Deep3DFaceRecon crop), fit their geometry with one view, rasterise the
    G-buffer once and write wild-shard files DIR/shard_NNNNN.npz (+ shard_NNNNN_overlay.png skin-mask previews).

    Bad inputs (no landmark file, 67 landmarks, unreadable image) are reported one line each; the other images
    are still written; the exit status is 1 unless --allow-skipped.
    """
    from reflectmm_cli.finetune.data import list_wild_inputs, shard_names

    if truth is None and (images.parent / "manifest.npz").is_file():
        truth = images.parent
    params = {"size": size, "aligned": aligned or from_truth, "from_truth": from_truth, "encoding": encoding,
              "shard_size": shard_size, "allow_skipped": allow_skipped}
    inputs = {"images": [images]}
    for role, p in (("landmarks", landmarks), ("masks", masks), ("face_model", face_model), ("truth", truth)):
        if p is not None:
            inputs[role] = [p]
    names = list(shards) or shard_names(len(list_wild_inputs(images, landmarks, masks)), shard_size)
    paths, failed = [], []
    for name in names:
        try:
            paths += run_stage_cli("prepare-wild", workspace=workspace, identity=name, params=params, inputs=inputs,
                                   output=out, stage_name="prepare-wild")
        except ReflectmmError as exc:
            failed.append(str(exc))
    emit(paths, as_json)
    if failed:
        raise ReflectmmError(failed[0] if len(failed) == 1 else f"{len(failed)} shards had skipped images: {failed[0]}")


COMMANDS = [prepare_wild_cmd]

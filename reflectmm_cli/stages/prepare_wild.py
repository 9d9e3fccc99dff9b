"""Stage ``prepare-wild``: aligned crops, fixed geometry and G-buffers as ``wild-shard`` files (docs/wild.md).

A per-shard stage: the identity of a task is a shard name ``shard_NNNNN`` (images ``[N·M, (N+1)·M)`` of the
sorted image folder, M = ``shard_size``); ``foreach = "all found"`` discovers every shard, and each task's cache
key hashes only its own images, landmarks, masks and truth files (plus the face model).

Input roles: ``images`` (folder, required), ``landmarks`` and ``masks`` (folders), ``face_model`` (file; default
``<truth>/face_model.npz``), ``truth`` (a ``synth wild`` folder: split, truth arrays, geometry with
``from_truth``; default the images folder's parent when it holds ``manifest.npz``).  Output folder: the explicit
output, else ``<workspace>/<stage_name>/``.  The defaults are those of
:class:`reflectmm_cli.finetune.data.PrepareConfig` (written there once).
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from reflectmm_cli.errors import ReflectmmError, WrittenThenFailed
from reflectmm_cli.finetune.data import ENCODINGS, PrepareConfig
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext
from reflectmm_cli.stages.registry import run_stage
from reflectmm_cli.stages.synth_multipie import out_dir
from reflectmm_cli.stages.synth_wild import check_split_fractions
from reflectmm_cli.workspace import find_wild_truth, wild_face_model

VERB = "prepare-wild"

_D = PrepareConfig()


PARAMS = (
    Param("size", "int", _D.size, range=(32, 1024), unit="px", help="Crop size S."),
    Param("aligned", "bool", _D.aligned, help="Images already are aligned S x S crops (landmarks in crop pixels)."),
    Param("from_truth", "bool", _D.from_truth,
          help="Geometry from the synth-wild truth instead of fitting (implies --aligned)."),
    Param("encoding", "str", _D.encoding, choices=ENCODINGS,
          help="Encoding of real images (synth wild records its own)."),
    Param("shard_size", "int", _D.shard_size, range=(1, 1_000_000), help="Images per shard."),
    Param("split_fractions", "floats", list(_D.split_fractions), range=(0.0, None), check=check_split_fractions, option="",
          help="Train/val/test fractions of the split by name hash, when no synth-wild manifest gives it "
               "(recipe only)."),
    Param("fit_landmark_iters", "int", _D.fit_landmark_iters, range=(0, 100000),
          help="L-BFGS iterations of the landmark stage of the single-image fit."),
    Param("fit_photo_rounds", "int", _D.fit_photo_rounds, range=(0, 20),
          help="Rounds of the order-2 SH photometric term (0 = landmarks only)."),
    Param("fit_photo_iters", "int", _D.fit_photo_iters, range=(0, 100000),
          help="Iterations per photometric round."),
    Param("allow_skipped", "bool", False, invalidates_cache=False,
          help="Exit 0 even when some images were skipped (they are listed in the shard's meta)."),
)

_FIELDS = frozenset(f.name for f in fields(PrepareConfig))

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('images', 'images or their folder', upstream='synth-wild', many=True),
    Input('landmarks', 'landmark files or folder', upstream='detect-landmarks', many=True),
    Input('masks', 'face masks or folder', many=True),
    Input('truth', 'synth-wild folder', upstream='synth-wild', many=True, help='geometry from truth (--from-truth)'),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs'),
)


def prepare_config(params: dict) -> PrepareConfig:
    """The library config of resolved stage params (``allow_skipped`` is the stage's own)."""
    return PrepareConfig(**{k: v for k, v in params.items() if k in _FIELDS})


def _one(ctx: StageContext, role: str) -> Path | None:
    paths = ctx.input_list(role, required=False)
    if len(paths) > 1:
        raise ReflectmmError(f"{VERB}: input '{role}' given {len(paths)} times, expected once")
    return paths[0] if paths else None


def _truth(ctx: StageContext) -> Path | None:
    return _one(ctx, "truth") or find_wild_truth(_one(ctx, "images"))


def _face_model(ctx: StageContext) -> Path | None:
    return wild_face_model(_one(ctx, "face_model"), _truth(ctx))


def _shard_index(ctx: StageContext) -> int:
    try:
        return int(str(ctx.identity).rsplit("_", 1)[1])
    except (IndexError, ValueError):
        raise ReflectmmError(f"{VERB}: identity must be a shard name shard_NNNNN, got {ctx.identity!r}") from None


def _discover(ctx: StageContext) -> list[str]:
    from reflectmm_cli.finetune.data import list_wild_inputs, shard_names

    return shard_names(len(list_wild_inputs(ctx.input("images"))), ctx.params["shard_size"])


def _outputs(ctx: StageContext) -> list[Path]:
    return [out_dir(ctx) / f"{ctx.identity}.npz"]


def _side_files(ctx: StageContext) -> list[Path]:
    return [out_dir(ctx) / f"{ctx.identity}_overlay.png"]


def _stale(ctx: StageContext, meta: dict) -> str | None:
    """A shard that lists skipped images is not up to date for a run that does not allow skips (whatever wrote
    it): the run must try (and report) those images again."""
    n = len(meta.get("skipped") or [])
    if n and not ctx.params["allow_skipped"]:
        return f"{n} image(s) were skipped when it was written and allow_skipped is false"
    return None


def _files(ctx: StageContext) -> dict[str, list[Path]]:
    """Only this shard's images, landmarks, masks and truth files (and the face model) key its cache."""
    from reflectmm_cli.finetune.data import list_wild_inputs

    M = ctx.params["shard_size"]
    i = _shard_index(ctx)
    inputs = list_wild_inputs(ctx.input("images"), _one(ctx, "landmarks"), _one(ctx, "masks"))[i * M:(i + 1) * M]
    files = {"images": [x.image for x in inputs], "landmarks": [x.landmarks for x in inputs if x.landmarks],
             "masks": [x.mask for x in inputs if x.mask]}
    fm = _face_model(ctx)
    if fm is not None:
        files["face_model"] = [fm]
    tr = _truth(ctx)
    if tr is not None:
        files["truth"] = [p for x in inputs for p in [tr / "truth" / f"{x.name}.npz"] if p.is_file()]
    return files


def run(ctx: StageContext) -> list[Path]:
    import numpy as np

    from reflectmm_cli.finetune.data import prepare_wild_shard
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.progress import progress

    cfg = prepare_config(ctx.params)
    tr = _truth(ctx)
    fm_path = _face_model(ctx)
    if fm_path is None:
        raise ReflectmmError(f"{VERB}: a face_model input (--face-model) is required "
                             "(no synth-wild face_model.npz to fall back on)")
    path, rep, errors = prepare_wild_shard(
        ctx.input("images"), out_dir(ctx), load_face_model(fm_path), fm_path, cfg, _shard_index(ctx),
        landmarks_dir=_one(ctx, "landmarks"), masks_dir=_one(ctx, "masks"), truth_dir=tr, producer=ctx.producer(),
        cache_key=ctx.cache_key, progress_fn=lambda it: progress(it, desc=str(ctx.identity), unit="img"),
        key_when_skipped=bool(ctx.params["allow_skipped"]))
    for e in errors:
        log.error(f"{VERB}: skipped {e}")
    if rep["names"]:
        msg = (f"{VERB} {ctx.identity}: {len(rep['names'])} images, landmark RMSE median "
               f"{np.median(rep['landmark_rmse_px']):.2f} px, {np.median(rep['seconds']):.2f} s/image")
        ve = np.asarray(rep["vertex_error_mm"], float)
        if np.isfinite(ve).any():
            msg += f", vertex RMSE median {np.nanmedian(ve):.1f} mm"
            if rep.get("vertex_error_centred_mm"):
                msg += f" ({np.median(rep['vertex_error_centred_mm']):.1f} mm after removing the mean offset)"
        log.info(msg)
    if errors and not ctx.params["allow_skipped"]:
        raise WrittenThenFailed(f"{VERB} {ctx.identity}: {len(errors)} image(s) skipped (listed above); "
                                "the others were written" + ("" if path else " (none succeeded)"))
    return [path] if path else []


def run_shards(workspace: Path, params: dict, inputs: dict, output: Path | None = None, shards=(), *,
               stage_name: str | None = None) -> tuple[list[Path], list[str]]:
    """Run the stage once per shard (default: every shard of the images folder), as the command line does.

    Returns (paths written, one-line errors of the shards that failed); a failing shard does not stop the
    others."""
    names = list(shards) or _discover(STAGE.context(workspace=workspace, params=dict(params),
                                                    inputs={k: [Path(p) for p in v] for k, v in inputs.items()}))
    paths: list[Path] = []
    failed: list[str] = []
    for name in names:
        try:
            paths += run_stage(STAGE, workspace=workspace, identity=name, params=params, inputs=inputs,
                               output=output, stage_name=stage_name)
        except ReflectmmError as exc:
            failed.append(str(exc))
    return paths, failed


STAGE = Stage(VERB, version=1, run=run, per_identity=True, outputs=_outputs, side_files=_side_files,
              stale=_stale, input_files=_files, discover_ids=_discover, params=PARAMS,
              help="aligned crops, fixed geometry and G-buffers as wild-shard files", inputs=INPUTS)

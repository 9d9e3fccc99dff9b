"""``reflectmm preprocess-multipie``: Multi-PIE shots → per-identity linear OLAT stacks (``capture`` artifacts)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from reflectmm_cli.artifacts import atomic_write_bytes, write_artifact
from reflectmm_cli.capture.layout import (DEFAULT_FLASHES, DEFAULT_VIEWS, default_views, discover_identities,
                                          plan_identity)
from reflectmm_cli.capture.preprocess import (CROP_MODES, CaptureOptions, contact_sheet, encode_png, parse_rotate,
                                              preprocess_identity, source_refs)
from reflectmm_cli.commands._common import emit, json_option, output_option, parse_ids, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import StageContext, register_stage

log = logging.getLogger("reflectmm")

VERB = "preprocess-multipie"


def _list_param(value, default) -> tuple[str, ...]:
    if value is None:
        return tuple(default)
    if isinstance(value, str):
        value = value.replace(" ", ",").split(",")
    return tuple(str(v).strip() for v in value if str(v).strip())


def _views(ctx: StageContext, flashes: tuple[str, ...], landmarks_dir: Path | None) -> tuple[str, ...]:
    """--views, or the default: the paper's 9 + 08_1 / 19_1 when flashes 14 / 18 are used (capture.layout)."""
    if ctx.param("views") is not None:
        return _list_param(ctx.param("views"), DEFAULT_VIEWS)
    if not ctx.identity or not ctx.inputs.get("root"):
        return DEFAULT_VIEWS
    views, notes = default_views(ctx.input("root"), ctx.identity, flashes, session=str(ctx.param("session", "auto")),
                                 recording=str(ctx.param("recording", "01")), landmarks_dir=landmarks_dir)
    for n in notes:
        log.warning("preprocess-multipie: %s", n)
    return views


def options_from_ctx(ctx: StageContext) -> CaptureOptions:
    lm = ctx.inputs.get("landmarks") or []
    flashes = _list_param(ctx.param("flashes"), DEFAULT_FLASHES)
    return CaptureOptions(session=str(ctx.param("session", "auto")), recording=str(ctx.param("recording", "01")),
                          views=_views(ctx, flashes, Path(lm[0]) if lm else None),
                          flashes=_list_param(ctx.param("flashes"), DEFAULT_FLASHES),
                          transfer=str(ctx.param("transfer", "gamma1.2")),
                          rotate=parse_rotate(ctx.param("rotate") or {}),
                          landmarks_dir=Path(lm[0]) if lm else None,
                          crop=str(ctx.param("crop", "auto")), crop_margin=float(ctx.param("crop_margin", 0.6)))


def _require_identity(ctx: StageContext) -> str:
    if not ctx.identity:
        raise ReflectmmError(f"stage '{ctx.stage_name}' runs per identity: give --id or a recipe foreach")
    return ctx.identity


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name(out.stem + "_contact.png")]


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    """Only this identity's source images and landmark files key the cache."""
    opts = options_from_ctx(ctx)
    try:
        plan = plan_identity(ctx.input("root"), _require_identity(ctx), session=opts.session,
                             recording=opts.recording, views=opts.views, flashes=opts.flashes,
                             landmarks_dir=opts.landmarks_dir)
    except ReflectmmError:
        return {"image": [], "landmarks": []}  # the run itself reports the problem
    return {"image": plan.files(), "landmarks": plan.landmark_files()}


def _discover(ctx: StageContext) -> list[str]:
    return discover_identities(ctx.input("root"))


# version 2: default views add 08_1 / 19_1 when flashes 14 / 18 are used (issue 13)
@register_stage(VERB, version=2, per_identity=True, outputs=_outputs, input_files=_input_files,
                discover_ids=_discover, help="Multi-PIE shots -> linear OLAT stack per identity")
def run_preprocess(ctx: StageContext) -> list[Path]:
    identity = _require_identity(ctx)
    root = ctx.input("root")
    opts = options_from_ctx(ctx)
    t0 = time.perf_counter()
    arrays, plan, report = preprocess_identity(root, identity, opts)
    out, sheet = _outputs(ctx)
    params = dict(ctx.resolved_params())
    params.update(opts.params())
    params["session"] = plan.session  # resolved
    write_artifact(out, "capture", arrays, params=params, inputs=source_refs(root, plan, out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
    atomic_write_bytes(sheet, encode_png(contact_sheet(arrays)))
    log.info("preprocess-multipie %s: session %s, %d views x %d flashes, %dx%d crop (%s) of %dx%d, "
             "landmarks in %d views, %.2f%% saturated, %.2f s", identity, plan.session, report["views"],
             report["flashes"], *report["crop_size"], report["crop"], *report["image_size"],
             report["landmark_views"], 100 * report["saturated_fraction"], time.perf_counter() - t0)
    return [out, sheet]


@click.command(VERB)
@click.option("--root", required=True, type=click.Path(path_type=Path),
              help="Multi-PIE root (the folder holding data/sessionNN, or data/ itself).")
@click.option("--id", "identity", default=None, help="One identity (e.g. 042).")
@click.option("--ids", default=None, help="Identities: 001,002 or ranges 001-010.")
@click.option("--id-file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="File with one identity per line (# comments).")
@click.option("--all", "all_ids", is_flag=True, help="Every identity found under the root.")
@click.option("--session", default="auto", show_default=True,
              help="Session 01..04, or auto = first session holding the recording.")
@click.option("--recording", default="01", show_default=True, help="Recording number (01 = neutral).")
@click.option("--views", default=None,
              help="Cameras, comma separated (default: the paper's 9 views, plus 08_1 / 19_1 when flashes 14 / 18 "
                   "are used and their shots exist: they place those flashes; unwrap-uv leaves them out).")
@click.option("--flashes", default=",".join(DEFAULT_FLASHES), show_default=True, help="Flash shots, comma separated.")
@click.option("--transfer", default="gamma1.2", show_default=True,
              help="Pixel value -> linear: gamma1.2 (x**1.2), srgb, linear, or gamma:G.")
@click.option("--rotate", multiple=True, metavar="CAM=DEG",
              help="Rotate a camera's images clockwise by 90/180/270 degrees after reading (repeatable).")
@click.option("--landmarks", "landmarks_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder with SSS_NN_RR_CCC_00_lm.{pts,txt,npy} files (default: beside the images).")
@click.option("--crop", type=click.Choice(CROP_MODES), default="auto", show_default=True,
              help="Store a face window (landmarks / lit pixels) or full frames (none).")
@click.option("--crop-margin", type=float, default=0.6, show_default=True,
              help="Margin around the landmark box, as a fraction of its larger side.")
@workspace_option
@output_option
@json_option
def preprocess_multipie_cmd(root, identity, ids, id_file, all_ids, session, recording, views, flashes, transfer,
                            rotate, landmarks_dir, crop, crop_margin, workspace, output, as_json):
    """Linearise one or more identities' Multi-PIE shots into OLAT stacks (`capture` artifacts + contact sheets).

    An identity that lacks required shots is skipped with a reason and the others are processed; the command
    then exits non-zero after writing the successful identities.
    """
    idents = ([identity] if identity else []) + parse_ids(ids, id_file)
    if all_ids:
        idents += discover_identities(root)
    idents = list(dict.fromkeys(idents))
    if not idents:
        raise click.UsageError("give --id, --ids, --id-file or --all")
    if output is not None and len(idents) > 1:
        raise click.UsageError("--output needs exactly one identity")
    rot = parse_rotate(rotate)
    params = {"session": session, "recording": recording, "flashes": list(_list_param(flashes, DEFAULT_FLASHES)),
              "transfer": transfer, "rotate": rot, "crop": crop, "crop_margin": crop_margin}
    if views is not None:
        params["views"] = list(_list_param(views, DEFAULT_VIEWS))
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
        raise ReflectmmError(f"{len(failed)} of {len(idents)} identities failed, the others were written — "
                             f"{reasons}")


COMMANDS = [preprocess_multipie_cmd]

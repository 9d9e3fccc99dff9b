"""Stage ``preprocess-multipie``: one identity's Multi-PIE shots → linear OLAT stack (``capture`` artifact)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from reflectmm_cli.artifacts import atomic_write_bytes, write_artifact
from reflectmm_cli.capture.layout import (DEFAULT_FLASHES, DEFAULT_VIEWS, default_views, discover_identities,
                                          plan_identity)
from reflectmm_cli.capture.preprocess import (CROP_MODES, CaptureOptions, check_rotate_cameras, contact_sheet,
                                              encode_png, parse_rotate, preprocess_identity, source_refs)
from reflectmm_cli.capture.transfer import check_transfer
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Input, Stage, StageContext

log = logging.getLogger("reflectmm")

VERB = "preprocess-multipie"

PARAMS = (
    Param("session", "str", "auto", help="Session 01..04, or auto = first session holding the recording."),
    Param("recording", "str", "01", help="Recording number (01 = neutral)."),
    Param("views", "strs", None,
          help="Cameras, comma separated (default: the paper's 9 views, plus 08_1 / 19_1 when flashes 14 / 18 are "
               "used and their shots exist: they place those flashes; unwrap-uv leaves them out)."),
    Param("flashes", "strs", list(DEFAULT_FLASHES), help="Flash shots, comma separated."),
    Param("transfer", "str", "gamma1.2", check=check_transfer,
          help="Pixel value -> linear: gamma1.2 (x**1.2), srgb, linear, or gamma:G."),
    Param("rotate", "custom", {}, convert=parse_rotate, multiple=True, metavar="CAM=DEG",
          help="Rotate a camera's images clockwise by 90/180/270 degrees after reading (repeatable)."),
    Param("crop", "str", "auto", choices=tuple(CROP_MODES),
          help="Store a face window (landmarks / lit pixels) or full frames (none)."),
    Param("crop_margin", "float", 0.6, range=(0.0, None),
          help="Margin around the landmark box, as a fraction of its larger side (around the lit box of the "
               "signal crop: half of it, since that box already holds the whole head)."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('root', 'Multi-PIE layout folder', upstream='synth-multipie'),
    Input('landmarks', 'landmark files or folder', many=True),
)


def _views(ctx: StageContext, landmarks_dir: Path | None, say_notes: bool = True) -> tuple[str, ...]:
    """The views param, or the default: the paper's 9 + 08_1 / 19_1 when flashes 14 / 18 are used
    (:func:`reflectmm_cli.capture.layout.default_views`); its notes are logged when ``say_notes``."""
    p = ctx.params
    if p.get("views") is not None:
        return tuple(p.get("views"))
    if not ctx.identity or not ctx.inputs.get("root"):
        return DEFAULT_VIEWS
    views, notes = default_views(ctx.input("root"), ctx.identity, tuple(p["flashes"]), session=p["session"],
                                 recording=p["recording"], landmarks_dir=landmarks_dir)
    for n in notes if say_notes else ():
        log.warning("preprocess-multipie: %s", n)
    return views


def options_from_ctx(ctx: StageContext, say_notes: bool = True) -> CaptureOptions:
    """The library's CaptureOptions from the resolved params and the optional landmarks input.  ``say_notes``:
    log what the default views left out (the run does; the cache key, computed first, does not repeat it)."""
    p = ctx.params
    lm = ctx.inputs.get("landmarks") or []
    lm_dir = Path(lm[0]) if lm else None
    check_rotate_cameras(p["rotate"], p.get("views"), p["flashes"])  # before the default views look at the data
    return CaptureOptions(session=p["session"], recording=p["recording"], views=_views(ctx, lm_dir, say_notes),
                          flashes=tuple(p["flashes"]), transfer=p["transfer"], rotate=dict(p["rotate"]),
                          landmarks_dir=lm_dir, crop=p["crop"], crop_margin=p["crop_margin"])


def _require_identity(ctx: StageContext) -> str:
    if not ctx.identity:
        raise ReflectmmError(f"stage '{ctx.stage_name}' runs per identity: give --id or a recipe foreach")
    return ctx.identity


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name(out.stem + "_contact.png")]


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    """Only this identity's source images and landmark files key the cache."""
    opts = options_from_ctx(ctx, say_notes=False)
    try:
        plan = plan_identity(ctx.input("root"), _require_identity(ctx), session=opts.session,
                             recording=opts.recording, views=opts.views, flashes=opts.flashes,
                             landmarks_dir=opts.landmarks_dir)
    except ReflectmmError:
        return {"image": [], "landmarks": []}  # the run itself reports the problem
    return {"image": plan.files(), "landmarks": plan.landmark_files()}


def _discover(ctx: StageContext) -> list[str]:
    return discover_identities(ctx.input("root"))


def run(ctx: StageContext) -> list[Path]:
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


# version 2: default views add 08_1 / 19_1 when flashes 14 / 18 are used (issue 13); 3: the signal crop averages
# before its threshold (sensor noise had made it the whole frame) and takes half the crop margin
STAGE = Stage(VERB, version=3, run=run, per_identity=True, outputs=_outputs, input_files=_input_files,
              discover_ids=_discover, params=PARAMS, help="Multi-PIE shots -> linear OLAT stack per identity", inputs=INPUTS)

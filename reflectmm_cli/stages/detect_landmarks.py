"""Stage ``detect-landmarks``: 68 iBUG landmarks with dlib (optional extra ``reflectmm[landmarks]``;
docs/wild.md).

Not per identity.  Input role ``images``: image files and/or folders (a folder gives its images, sorted).
Output: ``<stem>.pts`` per image in the explicit output folder, else ``<workspace>/<stage_name>/``.  Images
without a (selected) face are reported one line each, the others are written, and the run then fails; with
``allow_missing`` the run succeeds and lists them in ``no_face.txt`` in the same folder (its primary output,
written even when empty), so that the stage can feed ``preprocess-multipie`` in a recipe, where the side views
of a capture have no face a frontal detector finds.
"""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.detection import DETECTORS, EXPOSURES
from reflectmm_cli.errors import ReflectmmError, WrittenThenFailed
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext
from reflectmm_cli.stages.synth_multipie import out_dir

VERB = "detect-landmarks"

PARAMS = (
    Param("face_index", "int", None, range=(0, None),
          help="Which face when several are found (0 = largest; default the largest)."),
    Param("detector", "str", "hog", choices=DETECTORS,
          help="Face detector: hog = dlib's frontal HOG detector (fast; faces within about 30° of yaw); cnn = dlib's "
               "MMOD CNN detector (about 2 s per 640x480 image on one core; faces at larger yaw)."),
    Param("upsample", "int", 1, range=(0, 3), help="Detector upsampling (finds smaller faces, slower)."),
    Param("exposure", "str", "auto", choices=EXPOSURES,
          help="auto: brighten dim images before detecting (99.5th percentile of the brightest channel to 255; "
               "no pixel moves); none: detect on the image as given."),
    Param("box_jitter", "float", 0.0, range=(0.0, 0.49),
          help="Average the shape predictor's points over 27 boxes around the detector's (centre moved by 0 and "
               "±this fraction of the box, size scaled by 1 and 1±this); 0 = the detector's box alone. dlib gives "
               "whole pixels, and its points move with the box."),
    Param("allow_missing", "bool", False,
          help="Succeed when some images have no face: list them in no_face.txt beside the landmarks (capture "
               "views beyond a frontal detector's reach; preprocess-multipie leaves them without landmarks)."),
)

#: With ``allow_missing``: the images without a face, one ``image<TAB>reason`` line each (the stage's primary
#: output).
NO_FACE = "no_face.txt"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('images', 'images', many=True),
)


def image_files(ctx: StageContext) -> list[Path]:
    """The ``images`` input: files as given, folders expanded to their images (sorted). A recipe's pattern into
    another stage's folder (``@synth-multipie.dir/data/*/multiview/*/01/*/*_00.png``) reaches here expanded
    (:meth:`StageContext.with_patterns_expanded`)."""
    from reflectmm_cli.artifacts import IMAGE_EXTENSIONS

    out: list[Path] = []
    for p in ctx.input_list("images"):
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_EXTENSIONS)
        else:
            out.append(p)
    seen: dict[str, Path] = {}
    for p in out:
        other = seen.setdefault(p.stem, p)
        if other != p:
            raise ReflectmmError(f"{VERB}: two images would write the same {p.stem}.pts ({other} and {p}); give "
                                 f"them distinct names or run the folders separately with their own --out")
    return out


def _no_face_stems(listing: Path) -> set[str]:
    """The image stems a ``no_face.txt`` lists (``image<TAB>reason`` lines); empty when it does not exist."""
    if not listing.is_file():
        return set()
    return {Path(line.split("\t", 1)[0]).stem for line in listing.read_text().splitlines() if line.strip()}


def _outputs(ctx: StageContext) -> list[Path]:
    images = image_files(ctx)
    if ctx.params.get("allow_missing"):
        # the list first, then the .pts of every image it does not name (all of them before the first run)
        listing = out_dir(ctx) / NO_FACE
        absent = _no_face_stems(listing)
        return [listing] + [out_dir(ctx) / f"{p.stem}.pts" for p in images if p.stem not in absent]
    return [out_dir(ctx) / f"{p.stem}.pts" for p in images]


def _files(ctx: StageContext) -> dict[str, list[Path]]:
    return {"images": image_files(ctx)}


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.detection import detect_landmark_files
    from reflectmm_cli.progress import progress

    images = image_files(ctx)
    if not images:
        raise ReflectmmError(f"{VERB}: no images (png/jpg/bmp/tif/webp) in the input "
                             f"({', '.join(str(p) for p in ctx.input_list('images'))})")
    written, errors, faceless = detect_landmark_files(
        images, out_dir(ctx), face_index=ctx.params.get("face_index"), upsample=ctx.params["upsample"],
        exposure=ctx.params["exposure"], detector=ctx.params["detector"],
        box_jitter=ctx.params["box_jitter"], progress_fn=lambda it: progress(it, desc=VERB, unit="img"))
    unreadable = len(errors) - len(faceless)
    if ctx.params.get("allow_missing") and unreadable == 0:
        from reflectmm_cli.artifacts import atomic_write_text

        for e in errors:  # each one is in the listing; the summary below is the warning
            log.debug(f"{VERB}: {e}")
        lines = []
        for p, why in faceless:
            lines.append(f"{p}\t{why}\n")
            other = out_dir(ctx) / f"{p.stem}.pts"
            if other.is_file():  # an earlier run's, or the user's own: never deleted, but said
                log.warning(f"{VERB}: {other} exists, but this run finds no face in {p}: it is left as it is "
                            "and will be read downstream; delete it if it is stale")
        summary = atomic_write_text(out_dir(ctx) / NO_FACE, "".join(lines))
        (log.warning if errors else log.info)(
            f"{VERB}: {len(written)} of {len(images)} image(s) with landmarks; the {len(errors)} without a face are "
            f"listed in {summary}")
        return [summary] + written
    for e in errors:
        log.error(f"{VERB}: {e}")
    if errors:
        why = (f" ({unreadable} could not be read: --allow-missing covers images without a face, not bad files)"
               if ctx.params.get("allow_missing") else "")
        raise WrittenThenFailed(f"{len(errors)} of {len(images)} image(s) without landmarks (listed above){why}; "
                                "the others were written")
    return written


STAGE = Stage(VERB, version=2, run=run, per_identity=False, outputs=_outputs, input_files=_files, params=PARAMS,
              help="68-point iBUG landmarks with dlib", inputs=INPUTS)

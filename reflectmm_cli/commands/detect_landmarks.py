"""``reflectmm detect-landmarks``: 68-point landmarks with dlib (optional extra ``reflectmm[landmarks]``)."""
from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import emit, json_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log, progress


@click.command("detect-landmarks")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for NAME.pts (iBUG, readable by preprocess-multipie and prepare-wild).")
@click.option("--face-index", type=click.IntRange(0, None), default=None,
              help="Which face when several are found (0 = largest; default the largest).")
@click.option("--upsample", type=click.IntRange(0, 3), default=1, show_default=True,
              help="Detector upsampling (finds smaller faces, slower).")
@json_option
def detect_landmarks_cmd(images, out, face_index, upsample, as_json):
    """Detect the face and its 68 iBUG landmarks in each image; write OUT/NAME.pts.

    Images without a (selected) face are reported one line each and the others are still written; the exit
    status is then 1.
    """
    from reflectmm_cli.detection import detect_landmarks, pick_face
    from reflectmm_cli.finetune.data import _read_u8
    from reflectmm_cli.landmarks import write_pts

    written, failed = [], []
    for p in progress(images, desc="detect-landmarks", unit="img"):
        try:
            faces = detect_landmarks(_read_u8(p), upsample=upsample)
            f = pick_face(faces, face_index)
            if f is None:
                raise ReflectmmError("no face found" if not faces else
                                     f"--face-index {face_index} but only {len(faces)} face(s) found", p)
            written.append(write_pts(Path(out) / f"{p.stem}.pts", f.landmarks))
        except ReflectmmError as exc:
            if "optional extra" in str(exc):
                raise
            log.error(f"detect-landmarks: {exc}")
            failed.append(str(exc))
    emit(written, as_json)
    if failed:
        raise ReflectmmError(f"{len(failed)} of {len(images)} image(s) without landmarks (listed above); "
                             "the others were written")


COMMANDS = [detect_landmarks_cmd]

"""68-point landmark detection with dlib (optional extra ``reflectmm[landmarks]``: ``dlib-bin`` +
``face-recognition-models``, which ship the HOG frontal face detector, dlib's MMOD CNN face detector and the
iBUG 68-point shape predictor; nothing is downloaded at run time).

Two face detectors (:data:`DETECTORS`): ``hog``, dlib's frontal HOG + linear SVM detector (fast; finds faces
within about 30° of yaw), and ``cnn``, dlib's max-margin object detector (MMOD) CNN, the model
``face_recognition`` uses for ``model="cnn"`` (about 2 s per 640×480 image on one CPU core; finds faces at larger
yaw). Both feed the same 68-point shape predictor.

:func:`detect_landmarks` returns every face of an image (largest first) with its box, detector score and
68 landmarks in the pixel-centre convention of geometry/camera.py (dlib reports integer pixel indices whose
centre is that convention's integer coordinate).

:func:`normalize_exposure` is applied first by default: dlib's HOG detector was trained on well-exposed
photos, and a dim capture (Multi-PIE's room-light shots, the synthetic captures) has too little gradient for it.
Scaling the image so that a high percentile of its brightest channel reaches 255 changes no pixel position, so the
landmarks stay in the input's pixel grid (docs/capture.md, "Landmarks from a detector").
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["Face", "EXPOSURES", "DETECTORS", "predictor_path", "cnn_detector_path", "normalize_exposure",
           "check_box_jitter", "jittered_boxes", "predict_shape", "detect_landmarks", "pick_face",
           "detect_landmark_files"]

_MISSING = ("landmark detection needs the optional extra: pip install 'reflectmm[landmarks]' "
            "(dlib-bin and face-recognition-models)")


#: How :func:`detect_landmarks` prepares the image: ``auto`` = :func:`normalize_exposure`, ``none`` = as given.
EXPOSURES = ("auto", "none")

#: The face detectors of :func:`detect_landmarks`: dlib's frontal HOG detector, or its MMOD CNN detector.
DETECTORS = ("hog", "cnn")


@dataclass
class Face:
    box: tuple[int, int, int, int]   # left, top, right, bottom (pixels)
    score: float                      # dlib detector score
    landmarks: np.ndarray             # (68, 2) float64 (x, y)

    @property
    def area(self) -> int:
        return max(0, self.box[2] - self.box[0]) * max(0, self.box[3] - self.box[1])


def _model_file(name: str, what: str) -> Path:
    """A model file of ``face_recognition_models`` (located without importing the package, whose
    ``pkg_resources`` import is unavailable on recent setuptools)."""
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise ReflectmmError(_MISSING)
    p = Path(list(spec.submodule_search_locations)[0]) / "models" / name
    if not p.is_file():
        raise ReflectmmError(f"face_recognition_models has no {what} at {p}")
    return p


def predictor_path() -> Path:
    """The 68-point model file of ``face_recognition_models`` (its ``pose_predictor_model_location()``)."""
    try:
        import face_recognition_models

        return Path(face_recognition_models.pose_predictor_model_location())
    except ImportError:
        return _model_file("shape_predictor_68_face_landmarks.dat", "68-point model")


def cnn_detector_path() -> Path:
    """dlib's MMOD CNN face detector of ``face_recognition_models`` (its ``cnn_face_detector_model_location()``)."""
    return _model_file("mmod_human_face_detector.dat", "CNN face detector")


@lru_cache(maxsize=2)
def _models(detector: str = "hog"):
    """(face detector, shape predictor) of dlib, loaded once per detector; a one-line error for an unknown detector
    or a missing extra."""
    if detector not in DETECTORS:
        raise ReflectmmError(f"detect_landmarks: detector must be one of {', '.join(DETECTORS)}, got {detector!r}")
    try:
        import dlib
    except ImportError:
        raise ReflectmmError(_MISSING) from None
    det = (dlib.get_frontal_face_detector() if detector == "hog" else
           dlib.cnn_face_detection_model_v1(str(cnn_detector_path())))
    return det, dlib.shape_predictor(str(predictor_path()))


def _detect(det, detector: str, img: np.ndarray, upsample: int) -> list[tuple[object, float]]:
    """(dlib rectangle, score) of every face the detector finds: the HOG SVM's margin, or the CNN's confidence."""
    if detector == "hog":
        rects, scores, _ = det.run(img, int(upsample))
        return list(zip(rects, (float(s) for s in scores)))
    return [(d.rect, float(d.confidence)) for d in det(img, int(upsample))]


def normalize_exposure(image_rgb: np.ndarray, percentile: float = 99.5) -> np.ndarray:
    """Brighten an RGB uint8 image (H, W, 3) so that ``percentile`` of its per-pixel brightest channel maps to 255.

    The gain is ``255 / q`` with ``q`` that percentile, never below 1 (a well-exposed image is returned unchanged)
    and at most 64 (a nearly black image is not turned into amplified quantisation noise).  Values are clipped at
    255 and rounded.  Returns a new uint8 array of the same shape.
    """
    img = np.asarray(image_rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ReflectmmError(f"normalize_exposure: expected an RGB uint8 image, got {img.dtype} {img.shape}")
    if not 0.0 < float(percentile) <= 100.0:
        raise ReflectmmError(f"normalize_exposure: percentile must be in (0, 100], got {percentile}")
    q = float(np.percentile(img.max(axis=2), percentile))
    gain = min(64.0, 255.0 / max(q, 1.0))
    if gain <= 1.0:
        return img.copy()
    return np.clip(np.rint(img.astype(np.float32) * np.float32(gain)), 0, 255).astype(np.uint8)


def check_box_jitter(jitter: float) -> float:
    """``jitter`` as a float in [0, 0.5), else a one-line error (a box cannot shrink by half or more)."""
    j = float(jitter)
    if not 0.0 <= j < 0.5:
        raise ReflectmmError(f"box jitter must be in [0, 0.5), got {jitter}")
    return j


def jittered_boxes(box: tuple[int, int, int, int], jitter: float) -> list[tuple[int, int, int, int]]:
    """The 27 boxes of a 3 × 3 × 3 grid around ``box`` (left, top, right, bottom): its centre moved by
    ``-jitter``, 0 and ``+jitter`` of its width and of its height, and its size scaled by ``1 - jitter``, 1 and
    ``1 + jitter``; rounded to whole pixels.  ``jitter`` = 0 gives the box alone.
    """
    j = check_box_jitter(jitter)
    if j == 0.0:
        return [tuple(int(v) for v in box)]
    left, top, right, bottom = (float(v) for v in box)
    w, h = right - left, bottom - top
    cx, cy = (left + right) / 2, (top + bottom) / 2
    out = []
    for dx in (-j, 0.0, j):
        for dy in (-j, 0.0, j):
            for s in (1.0 - j, 1.0, 1.0 + j):
                x0, y0, hw, hh = cx + dx * w, cy + dy * h, w * s / 2, h * s / 2
                out.append((int(round(x0 - hw)), int(round(y0 - hh)), int(round(x0 + hw)), int(round(y0 + hh))))
    return out


def predict_shape(predictor, image: np.ndarray, box: tuple[int, int, int, int], box_jitter: float = 0.0
                  ) -> np.ndarray:
    """The shape predictor's 68 points (68, 2) float64 for the face in ``box``: with ``box_jitter`` > 0, the mean
    of its points over :func:`jittered_boxes`.

    dlib returns whole pixels, and where its regression puts a point depends on where the detector put the box,
    with one error shared by a group of points.  The mean over nearby boxes is sub-pixel and less tied to that one
    box (docs/wild.md, "detect-landmarks"; docs/benchmarks.md, "Averaging the shape predictor over boxes").
    """
    import dlib

    pts = []
    for b in jittered_boxes(box, box_jitter):
        sh = predictor(image, dlib.rectangle(*b))
        pts.append([[p.x, p.y] for p in sh.parts()])
    return np.asarray(pts, np.float64).mean(axis=0)


def detect_landmarks(image_rgb: np.ndarray, *, upsample: int = 1, exposure: str = "auto",
                     detector: str = "hog", box_jitter: float = 0.0) -> list[Face]:
    """All faces of an RGB uint8 image (H, W, 3), sorted by box area then score (largest first).

    ``exposure`` (one of :data:`EXPOSURES`): ``auto`` detects on :func:`normalize_exposure` of the image,
    ``none`` on the image as given.  The landmarks are in the input's pixel grid either way.  ``detector`` (one
    of :data:`DETECTORS`) finds the faces; ``upsample`` doubles the image that many times first (smaller faces).
    ``box_jitter`` > 0 averages the shape predictor over boxes around the detector's (:func:`predict_shape`).
    """
    img = np.ascontiguousarray(np.asarray(image_rgb))
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ReflectmmError(f"detect_landmarks: expected an RGB uint8 image, got {img.dtype} {img.shape}")
    if exposure not in EXPOSURES:
        raise ReflectmmError(f"detect_landmarks: exposure must be one of {', '.join(EXPOSURES)}, got {exposure!r}")
    check_box_jitter(box_jitter)  # a bad value is refused before any work
    det, pred = _models(detector)
    if exposure == "auto":
        img = np.ascontiguousarray(normalize_exposure(img))
    faces = []
    for r, s in _detect(det, detector, img, upsample):
        box = (r.left(), r.top(), r.right(), r.bottom())
        faces.append(Face(box, float(s), predict_shape(pred, img, box, box_jitter)))
    faces.sort(key=lambda f: (-f.area, -f.score))
    return faces


def pick_face(faces: list[Face], index: int | None = None) -> Face | None:
    """The largest face, or face number ``index`` of the largest-first order; None if there is none."""
    if not faces:
        return None
    i = 0 if index is None else int(index)
    if not 0 <= i < len(faces):
        return None
    return faces[i]


def detect_landmark_files(images, out_dir, *, face_index: int | None = None, upsample: int = 1,
                          exposure: str = "auto", detector: str = "hog", box_jitter: float = 0.0,
                          progress_fn=None) -> tuple[list[Path], list[str], list[tuple[Path, str]]]:
    """Detect the face of each image file and write ``out_dir/<stem>.pts`` (68 iBUG points, pixel-centre
    convention; read by ``preprocess-multipie`` and ``prepare-wild``).

    Returns ``(written .pts paths, one-line errors, images without the selected face)``: an unreadable image or
    one without the selected face is an error naming the file, and the other images are still written; the
    third list holds the images that were read but have no (selected) face, each with its reason.  A missing
    optional extra is raised at once (it would fail every image).
    """
    from reflectmm_cli.artifacts import read_image_u8
    from reflectmm_cli.landmarks import write_pts

    _models(detector)  # an unknown detector or a missing extra would fail every image: raised at once
    check_box_jitter(box_jitter)
    written: list[Path] = []
    errors: list[str] = []
    faceless: list[tuple[Path, str]] = []
    for p in (progress_fn(images) if progress_fn else images):
        p = Path(p)
        try:
            faces = detect_landmarks(read_image_u8(p), upsample=upsample, exposure=exposure, detector=detector,
                                     box_jitter=box_jitter)
            f = pick_face(faces, face_index)
            if f is None:
                why = ("no face found" if not faces else
                       f"face index {face_index} but only {len(faces)} face(s) found")
                faceless.append((p, why))
                raise ReflectmmError(why, p)
            written.append(write_pts(Path(out_dir) / f"{p.stem}.pts", f.landmarks))
        except ReflectmmError as exc:
            errors.append(str(exc).splitlines()[0])
    return written, errors, faceless

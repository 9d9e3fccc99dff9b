"""``preprocess-multipie`` library: one identity's Multi-PIE shots → linear OLAT stack (``capture`` artifact).

``olat = max(decode(flash) − decode(room), 0)`` per view and flash, in linear units; a pixel is marked
``saturated`` when any channel sits at the integer maximum (255 / 65535) in the flash or the room shot.
Arrays are cropped to a window around the face (same size for every view) to keep the artifact small;
``crop_origin (V, 2)`` gives the window's top-left pixel ``(x0, y0)`` in the full frame, and every pixel
coordinate stored (landmarks) is in the full frame: stored pixel ``[y, x]`` is full-frame ``(x + x0, y + y0)``.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from reflectmm_cli.artifacts import sha256_file
from reflectmm_cli.capture.images import ROTATIONS, read_image, rotate_points
from reflectmm_cli.capture.layout import (DEFAULT_FLASHES, DEFAULT_VIEWS, RAISED_FLASH_CAMERA, ROOM_SHOT, ShotPlan,
                                          plan_identity, shot_stem)
from reflectmm_cli.capture.transfer import Transfer, parse_transfer
from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.landmarks import N_LANDMARKS, check_in_frame, read_landmarks
from reflectmm_cli.params import ParamError, parse_pairs
from reflectmm_cli.threads import default_threads

log = logging.getLogger("reflectmm")

CROP_MODES = ("auto", "landmarks", "signal", "none")
#: Linear OLAT level above which a pixel counts as lit by a flash (signal crop), after the averaging below.
SIGNAL_THRESHOLD = 0.01


class MissingShotsError(ReflectmmError):
    """An identity lacks required images (it is skipped; the others are processed)."""


@dataclass
class CaptureOptions:
    """Options of :func:`preprocess_identity` (CLI flags of ``preprocess-multipie``)."""

    session: str = "auto"
    recording: str = "01"
    views: tuple[str, ...] = DEFAULT_VIEWS
    flashes: tuple[str, ...] = DEFAULT_FLASHES
    transfer: str = "gamma1.2"
    rotate: Mapping[str, int] = field(default_factory=dict)
    landmarks_dir: Path | None = None
    crop: str = "auto"
    crop_margin: float = 0.6

    def params(self) -> dict[str, Any]:
        """The options as artifact params (canonical values)."""
        return {"session": self.session, "recording": self.recording, "views": list(self.views),
                "flashes": list(self.flashes), "transfer": parse_transfer(self.transfer).name,
                "rotate": {k: int(v) for k, v in sorted(self.rotate.items())}, "crop": self.crop,
                "crop_margin": float(self.crop_margin)}


def parse_rotate(items) -> dict[str, int]:
    """``["08_1=90", ...]`` or a mapping → ``{camera: degrees clockwise}`` (0/90/180/270).

    Raises :class:`~reflectmm_cli.params.ParamError` (a recipe's error then names its file and stage)."""
    out = {}
    for k, v in parse_pairs(items, "--rotate", "CAMERA=DEGREES (e.g. 08_1=90)"):
        try:
            deg = int(v) % 360
        except ValueError:
            deg = -1
        if deg not in ROTATIONS:
            raise ParamError(f"--rotate {k}={v}: degrees must be 0, 90, 180 or 270 (clockwise); camera {k} has {v}")
        if str(k) in out:  # the last would win without a word
            raise ParamError(f"--rotate {k}={v}: camera {k} is given twice ({k}={out[str(k)]} before)")
        out[str(k)] = deg
    return out


def check_rotate_cameras(rotate: Mapping[str, int], views, flashes) -> None:
    """Refuse a rotated camera that is not among the views (a typo would leave the right camera unrotated), before
    any image is read. ``views`` None stands for the default views: the paper's 9 and the raised camera of every
    raised flash in ``flashes`` (:func:`~reflectmm_cli.capture.layout.default_views`)."""
    if views is None:
        views = list(DEFAULT_VIEWS) + [RAISED_FLASH_CAMERA[f] for f in flashes if f in RAISED_FLASH_CAMERA]
    for cam in rotate:
        if cam not in views:
            raise ReflectmmError(f"--rotate {cam}={rotate[cam]}: camera {cam} is not among the views "
                                 f"({', '.join(views)})")


def _crop_box(box, width: int, height: int, margin: float):
    x0, y0, x1, y1 = box
    m = margin * max(x1 - x0, y1 - y0)
    return (max(0, int(np.floor(x0 - m))), max(0, int(np.floor(y0 - m))),
            min(width, int(np.ceil(x1 + m)) + 1), min(height, int(np.ceil(y1 + m)) + 1))


def signal_box(olat: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """The window ``(x0, y0, x1, y1)`` around the pixels that some flash lights, enlarged by ``margin`` of its
    larger side on every side (the whole frame where nothing is lit).

    Args:
        olat: (F, H, W, 3) one view's flash-minus-room images, linear.
    A pixel is lit where the brightest flash's mean over the channels, averaged over a square of about 1 % of the
    frame's shorter side, exceeds :data:`SIGNAL_THRESHOLD`. Sensor noise alone exceeds the threshold somewhere in
    every frame (the difference of two noisy shots, at every pixel, for every flash); averaging over the square
    lowers it below, while a lit face, many squares wide, keeps its level.
    """
    import cv2

    H, W = olat.shape[1:3]
    lit = np.asarray(olat, dtype=np.float32).mean(-1).max(0)
    k = max(3, 2 * int(round(min(H, W) / 200.0)) + 1)
    ys, xs = np.nonzero(cv2.blur(lit, (k, k), borderType=cv2.BORDER_REPLICATE) > SIGNAL_THRESHOLD)
    if ys.size == 0:
        return (0, 0, W, H)
    return _crop_box((xs.min(), ys.min(), xs.max(), ys.max()), W, H, margin)


def _common_windows(boxes, width: int, height: int) -> tuple[np.ndarray, int, int]:
    """Same-size windows (origin per view) covering each view's box, clamped to the frame."""
    cw = min(width, max(b[2] - b[0] for b in boxes))
    ch = min(height, max(b[3] - b[1] for b in boxes))
    origins = []
    for x0, y0, x1, y1 in boxes:
        cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
        ox = int(np.clip(round(cx - cw / 2.0), 0, width - cw))
        oy = int(np.clip(round(cy - ch / 2.0), 0, height - ch))
        origins.append((ox, oy))
    return np.array(origins, dtype=np.int32), cw, ch


def preprocess_identity(root: str | Path, identity: str, opts: CaptureOptions | None = None
                        ) -> tuple[dict[str, np.ndarray], ShotPlan, dict[str, Any]]:
    """Read one identity's shots and build the ``capture`` arrays.

    Returns ``(arrays, plan, report)``; raises :class:`MissingShotsError` naming the missing files, or
    :class:`ReflectmmError` naming an unreadable / wrongly sized image or a bad landmark file.
    """
    opts = opts or CaptureOptions()
    transfer: Transfer = parse_transfer(opts.transfer)
    if opts.crop not in CROP_MODES:
        raise ReflectmmError(f"--crop {opts.crop!r}: expected one of {', '.join(CROP_MODES)}")
    for cam in opts.rotate:
        if cam not in opts.views:  # a raised camera of the default views left out for want of shots
            log.debug("rotate: camera %s is not among the selected views", cam)
    plan = plan_identity(root, identity, session=opts.session, recording=opts.recording, views=opts.views,
                         flashes=opts.flashes, landmarks_dir=opts.landmarks_dir)
    missing = plan.missing()
    if missing:
        shown = ", ".join(str(p) for p in missing[:4]) + (f", … ({len(missing)} in all)" if len(missing) > 4 else "")
        raise MissingShotsError(f"identity {plan.identity} (session {plan.session}, recording {plan.recording}): "
                                f"{len(missing)} required shot(s) missing: {shown}")
    V, F = len(plan.views), len(plan.flashes)
    rots = [int(opts.rotate.get(view, 0)) for view in plan.views]
    # pass 1: room shots (full frames) and landmarks fix the frame size and, with landmarks, the window
    rooms = []
    size: tuple[int, int] | None = None
    landmarks = np.full((V, N_LANDMARKS, 2), np.nan, dtype=np.float32)
    bits_seen: set[int] = set()
    for vi in range(V):
        img = read_image(plan.images[vi][0], transfer, rots[vi], expect_size=size,
                         expect_what=f"the room shot of view {plan.views[0]}")
        size = size or img.size
        bits_seen.add(img.bits)
        rooms.append(img)
        lp = plan.landmarks[vi]
        if lp is not None:
            pts = read_landmarks(lp, N_LANDMARKS).astype(np.float32)  # stored as float32
            if rots[vi]:
                # landmark files annotate the image as stored on disk: rotate them with the image
                h, w = img.linear.shape[:2]
                wo, ho = (h, w) if rots[vi] in (90, 270) else (w, h)
                pts = rotate_points(pts, rots[vi], wo, ho)
            landmarks[vi] = check_in_frame(pts, *img.size, lp)
    W, H = size
    have_lm = np.isfinite(landmarks).all(axis=(1, 2))
    if opts.landmarks_dir is not None and not have_lm.any():
        log.warning("%s: no landmark file for identity %s in any of its %d views (such as %s_lm.pts): the capture "
                    "has no landmarks", opts.landmarks_dir, plan.identity, V,
                    shot_stem(plan.identity, plan.session, plan.recording, plan.views[0], ROOM_SHOT))
    mode = opts.crop
    if mode == "auto":
        mode = "landmarks" if have_lm.all() else "signal"
    if mode == "landmarks" and not have_lm.all():
        raise ReflectmmError(f"identity {plan.identity}: --crop landmarks but no landmarks for view(s) "
                             f"{', '.join(v for v, h in zip(plan.views, have_lm) if not h)}")
    if mode == "none":
        origins, cw, ch = _common_windows([(0, 0, W, H)] * V, W, H)
    elif mode == "landmarks":
        origins, cw, ch = _common_windows(
            [_crop_box((lm[:, 0].min(), lm[:, 1].min(), lm[:, 0].max(), lm[:, 1].max()), W, H, opts.crop_margin)
             for lm in landmarks], W, H)
    else:
        origins, cw, ch = None, W, H  # decided after the flashes are read
    # pass 2: flash shots (cropped right after decoding when the window is known)
    olat = np.empty((V, F, ch, cw, 3), dtype=np.float16)
    sat = np.empty((V, F, ch, cw), dtype=bool)
    room = np.empty((V, ch, cw, 3), dtype=np.float16)
    with ThreadPoolExecutor(max_workers=default_threads(4)) as pool:  # PNG decoding releases the GIL
        for vi in range(V):
            win = None if origins is None else (int(origins[vi][0]), int(origins[vi][1]), cw, ch)
            r = rooms[vi]
            rlin = r.linear if win is None else r.linear[win[1]:win[1] + ch, win[0]:win[0] + cw]
            rsat = r.saturated if win is None else r.saturated[win[1]:win[1] + ch, win[0]:win[0] + cw]
            room[vi] = rlin
            same = f"the room shot of the same view ({plan.views[vi]})"
            shots = pool.map(lambda path, rot=rots[vi], win=win: read_image(path, transfer, rot, window=win,
                                                                               expect_size=size, expect_what=same),
                             plan.images[vi][1:])
            for fi, fl in enumerate(shots):
                bits_seen.add(fl.bits)
                if not fl.linear.any():
                    # a flash that did not fire, or a blank file: its zeros would read as black skin
                    raise ReflectmmError(f"flash image is entirely black{' in the crop window' if win else ''} "
                                         f"(flash {plan.flashes[fi]} of view {plan.views[vi]}): the flash did not "
                                         f"fire or the file is blank — replace it or leave flash {plan.flashes[fi]} "
                                         f"out of --flashes", fl.path)
                diff = fl.linear
                np.subtract(diff, rlin, out=diff)
                np.maximum(diff, 0.0, out=diff)
                olat[vi, fi] = diff
                np.logical_or(fl.saturated, rsat, out=sat[vi, fi])
    rooms.clear()
    if origins is None:  # signal crop: the box of pixels some flash lights, per view, then one common window
        boxes = [signal_box(olat[vi], opts.crop_margin / 2) for vi in range(V)]
        origins, cw, ch = _common_windows(boxes, W, H)
        win = [(slice(oy, oy + ch), slice(ox, ox + cw)) for ox, oy in origins]
        olat = np.stack([olat[v][:, ys, xs] for v, (ys, xs) in enumerate(win)])
        sat = np.stack([sat[v][:, ys, xs] for v, (ys, xs) in enumerate(win)])
        room = np.stack([room[v][ys, xs] for v, (ys, xs) in enumerate(win)])
    arrays = {
        "olat": olat, "room": room, "saturated": sat,
        "view_names": np.array(plan.views, dtype=str), "flash_ids": np.array(plan.flashes, dtype=str),
        "image_size": np.array([W, H], dtype=np.int32), "crop_origin": origins,
        "landmarks": landmarks, "bits": np.int32(max(bits_seen)),
        "session": np.array(plan.session), "recording": np.array(plan.recording),
    }
    report = {"identity": plan.identity, "session": plan.session, "recording": plan.recording,
              "views": V, "flashes": F, "image_size": [W, H], "crop": mode, "crop_size": [cw, ch],
              "landmark_views": int(have_lm.sum()),
              "saturated_fraction": float(sat.mean()) if sat.size else 0.0}
    return arrays, plan, report


def source_refs(root: str | Path, plan: ShotPlan, relative_to: Path) -> list[dict[str, Any]]:
    """Provenance of the source files: role ``root`` (the dataset folder), ``image`` and ``landmarks`` with sha256
    (paths relative to the dataset root)."""
    root = Path(root)
    refs: list[dict[str, Any]] = [{"role": "root", "path": os.path.relpath(root, relative_to)}]
    for role, files in (("image", plan.files()), ("landmarks", plan.landmark_files())):
        for p in files:
            refs.append({"role": role, "path": os.path.relpath(p, root), "sha256": sha256_file(p)})
    return refs


def _tonemap(x: np.ndarray, scale: float) -> np.ndarray:
    return encode_display(np.asarray(x, dtype=np.float32) / max(scale, 1e-8), "gamma", nan_to_num=False, uint8=True)


def contact_sheet(arrays: Mapping[str, np.ndarray], n_flashes: int = 3, thumb_width: int = 160) -> np.ndarray:
    """RGB uint8 sheet: one row per view — room light, then ``n_flashes`` OLATs spread over the flash list."""
    import cv2

    olat, room = arrays["olat"], arrays["room"]
    V, F, h, w = olat.shape[:4]
    tw = min(thumb_width, w)
    th = max(1, int(round(h * tw / w)))
    picks = sorted(set(np.linspace(0, F - 1, min(n_flashes, F)).round().astype(int).tolist())) if F else []
    room_scale = float(np.percentile(room.astype(np.float32), 99.5)) if room.size else 1.0
    olat_scale = float(np.percentile(olat[:, picks].astype(np.float32), 99.5)) if picks else 1.0
    rows = []
    for vi in range(V):
        tiles = [_tonemap(room[vi], room_scale)] + [_tonemap(olat[vi, fi], olat_scale) for fi in picks]
        tiles = [cv2.resize(t, (tw, th), interpolation=cv2.INTER_AREA) for t in tiles]
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def encode_png(rgb: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:  # pragma: no cover
        raise ReflectmmError("cannot encode PNG")
    return buf.tobytes()

"""The Multi-PIE folder layout (docs/pipeline.md, docs/capture.md).

``<root>/data/sessionNN/multiview/SSS/RR/CC_C/SSS_NN_RR_CCC_II.png``: identity ``SSS`` (3 digits), session
``NN`` (01..04), recording ``RR`` (01 = neutral), camera ``CC_C`` (folder ``05_1``, written ``051`` in file
names), shot ``II`` (``00`` room light, ``01``..``18`` flashes).  ``root`` may be the folder holding ``data/``
or the ``data`` folder itself.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from reflectmm_cli.errors import ReflectmmError

#: The paper's 9 views (docs/design.md §1), in arc order.
DEFAULT_VIEWS = ("09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0")
#: The paper's 11 flashes: 9 on the selected cameras plus the two raised ones (14 on 08_1, 18 on 19_1).
DEFAULT_FLASHES = ("03", "04", "05", "06", "07", "08", "09", "10", "11", "14", "18")
#: Every Multi-PIE camera: 13 at head height in arc order, then the two raised ones.
ALL_CAMERAS = ("11_0", "12_0", "09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0",
               "01_0", "24_0", "08_1", "19_1")
ROOM_SHOT = "00"
#: Image extensions tried in order for each shot (PNG is the Multi-PIE distribution format; RAW files are
#: read through rawpy).
IMAGE_EXTS = (".png", ".PNG", ".tif", ".tiff", ".cr2", ".CR2", ".nef", ".NEF", ".dng", ".DNG")
RAW_EXTS = frozenset({".cr2", ".nef", ".dng", ".arw", ".raw"})
LANDMARK_SUFFIXES = ("_lm.pts", "_lm.txt", "_lm.npy")

_CAM_RE = re.compile(r"^(\d\d)_(\d)$")
_CODE_RE = re.compile(r"^(\d\d)(\d)$")
_ID_RE = re.compile(r"^\d{3}$")
_SESSION_RE = re.compile(r"^session(\d\d)$")


def camera_code(name: str) -> str:
    """Camera name → the 3-digit code used in file names: ``05_1`` → ``051``."""
    m = _CAM_RE.match(name)
    if not m:
        raise ReflectmmError(f"camera name {name!r} is not of the form NN_N (e.g. 05_1)")
    return m.group(1) + m.group(2)


def camera_name(code: str) -> str:
    """File-name camera code → camera (folder) name: ``051`` → ``05_1``."""
    m = _CODE_RE.match(code)
    if not m:
        raise ReflectmmError(f"camera code {code!r} is not 3 digits (e.g. 051)")
    return f"{m.group(1)}_{m.group(2)}"


def check_shot(shot: str) -> str:
    s = str(shot).strip()
    if s.isdigit() and len(s) <= 2:
        s = s.zfill(2)
    if not (len(s) == 2 and s.isdigit() and 0 <= int(s) <= 19):
        raise ReflectmmError(f"flash/shot id {shot!r} is not 00..19")
    return s


def check_identity(identity: str) -> str:
    s = str(identity).strip()
    if s.isdigit() and len(s) < 3:
        s = s.zfill(3)
    if not _ID_RE.match(s):
        raise ReflectmmError(f"identity {identity!r} is not a 3-digit Multi-PIE subject id (e.g. 042)")
    return s


def data_dir(root: str | Path) -> Path:
    """The folder holding ``sessionNN`` folders (``root/data`` or ``root`` itself)."""
    root = Path(root)
    if not root.exists():
        raise ReflectmmError("Multi-PIE root not found", root)
    if not root.is_dir():
        raise ReflectmmError("Multi-PIE root is not a folder", root)
    if (root / "data").is_dir():
        return root / "data"
    if any(_SESSION_RE.match(p.name) for p in root.iterdir() if p.is_dir()):
        return root
    raise ReflectmmError("not a Multi-PIE root: no data/sessionNN folders", root)


def sessions(root: str | Path) -> list[str]:
    """Session numbers (``"01"``..) present under the root, sorted."""
    d = data_dir(root)
    return sorted(m.group(1) for p in d.iterdir() if p.is_dir() and (m := _SESSION_RE.match(p.name)))


def identity_dir(root: str | Path, session: str, identity: str) -> Path:
    return data_dir(root) / f"session{session}" / "multiview" / identity


def sessions_of(root: str | Path, identity: str) -> list[str]:
    """Sessions in which ``identity`` has a folder."""
    return [s for s in sessions(root) if identity_dir(root, s, identity).is_dir()]


def discover_identities(root: str | Path) -> list[str]:
    """All 3-digit identity folders under any session, sorted and unique."""
    d = data_dir(root)
    found: set[str] = set()
    for s in sessions(root):
        mv = d / f"session{s}" / "multiview"
        if mv.is_dir():
            found.update(p.name for p in mv.iterdir() if p.is_dir() and _ID_RE.match(p.name))
    return sorted(found)


def resolve_session(root: str | Path, identity: str, session: str = "auto", recording: str = "01") -> str:
    """``auto``: the first session in which the identity has the given recording; else check the given one."""
    have = sessions_of(root, identity)
    if session == "auto":
        for s in have:
            if (identity_dir(root, s, identity) / recording).is_dir():
                return s
        if not have:
            raise ReflectmmError(f"identity {identity}: not found in any session", data_dir(root))
        raise ReflectmmError(f"identity {identity}: no recording {recording} in sessions {', '.join(have)}",
                             data_dir(root))
    s = str(session).zfill(2)
    if s not in have:
        raise ReflectmmError(f"identity {identity}: not in session {s} (found in: {', '.join(have) or 'none'})",
                             data_dir(root))
    if not (identity_dir(root, s, identity) / recording).is_dir():
        raise ReflectmmError(f"identity {identity}: session {s} has no recording {recording}",
                             identity_dir(root, s, identity))
    return s


def shot_stem(identity: str, session: str, recording: str, camera: str, shot: str) -> str:
    """``SSS_NN_RR_CCC_II`` (no extension)."""
    return f"{identity}_{session}_{recording}_{camera_code(camera)}_{shot}"


def camera_dir(root: str | Path, identity: str, session: str, recording: str, camera: str) -> Path:
    return identity_dir(root, session, identity) / recording / camera


def shot_path(root: str | Path, identity: str, session: str, recording: str, camera: str, shot: str
              ) -> Path | None:
    """Existing image file of one shot (first of :data:`IMAGE_EXTS` found), or None."""
    folder = camera_dir(root, identity, session, recording, camera)
    stem = shot_stem(identity, session, recording, camera, shot)
    for ext in IMAGE_EXTS:
        p = folder / (stem + ext)
        if p.is_file():
            return p
    return None


def landmark_path(root: str | Path, identity: str, session: str, recording: str, camera: str,
                  landmarks_dir: str | Path | None = None) -> Path | None:
    """Landmark file of a camera's room-light shot (``SSS_NN_RR_CCC_00_lm.{pts,txt,npy}``), or None.

    With ``landmarks_dir`` the file is looked up there, flat or mirroring the Multi-PIE layout below it, also
    under the name ``detect-landmarks`` gives it (``SSS_NN_RR_CCC_00.pts``, the room shot's stem).
    """
    stem = shot_stem(identity, session, recording, camera, ROOM_SHOT)
    suffixes = LANDMARK_SUFFIXES
    if landmarks_dir is not None:
        base = Path(landmarks_dir)
        rel = Path(f"session{session}") / "multiview" / identity / recording / camera
        folders = [base, base / rel, base / "data" / rel]
        suffixes = LANDMARK_SUFFIXES + (".pts",)
    else:
        folders = [camera_dir(root, identity, session, recording, camera)]
    for folder in folders:
        for suf in suffixes:
            p = folder / (stem + suf)
            if p.is_file():
                return p
    return None


@dataclass(frozen=True)
class ShotPlan:
    """The files one identity needs: ``images[v][0]`` is the room shot of view v, ``images[v][1+f]`` flash f."""

    identity: str
    session: str
    recording: str
    views: tuple[str, ...]
    flashes: tuple[str, ...]
    images: tuple[tuple[Path | None, ...], ...]
    expected: tuple[tuple[Path, ...], ...]
    landmarks: tuple[Path | None, ...]

    def missing(self) -> list[Path]:
        return [e for row, exp in zip(self.images, self.expected) for p, e in zip(row, exp) if p is None]

    def files(self) -> list[Path]:
        return [p for row in self.images for p in row if p is not None]

    def landmark_files(self) -> list[Path]:
        return [p for p in self.landmarks if p is not None]


def plan_identity(root: str | Path, identity: str, *, session: str = "auto", recording: str = "01",
                  views=DEFAULT_VIEWS, flashes=DEFAULT_FLASHES, landmarks_dir: str | Path | None = None
                  ) -> ShotPlan:
    """Locate every image (room + flashes per view) and landmark file of one identity."""
    identity = check_identity(identity)
    recording = str(recording).zfill(2)
    views = tuple(views)
    for v in views:
        camera_code(v)
    flashes = tuple(check_shot(f) for f in flashes)
    if ROOM_SHOT in flashes:
        raise ReflectmmError("--flashes: shot 00 is the room-light shot, not a flash")
    s = resolve_session(root, identity, session, recording)
    images, expected, lms = [], [], []
    for v in views:
        shots = (ROOM_SHOT,) + flashes
        images.append(tuple(shot_path(root, identity, s, recording, v, sh) for sh in shots))
        folder = camera_dir(root, identity, s, recording, v)
        expected.append(tuple(folder / (shot_stem(identity, s, recording, v, sh) + ".png") for sh in shots))
        lms.append(landmark_path(root, identity, s, recording, v, landmarks_dir))
    return ShotPlan(identity, s, recording, views, flashes, tuple(images), tuple(expected), tuple(lms))


#: The raised camera each raised flash sits on (paper supp. A.1: flashes 14 / 18 are solved from 08_1 / 19_1).
RAISED_FLASH_CAMERA = {"14": "08_1", "18": "19_1"}


def default_views(root: str | Path, identity: str, flashes=DEFAULT_FLASHES, *, session: str = "auto",
                  recording: str = "01", landmarks_dir: str | Path | None = None) -> tuple[tuple[str, ...], list[str]]:
    """The default views of a capture: the paper's 9 plus the raised camera of every raised flash used (08_1 for
    flash 14, 19_1 for 18), so that fit-geometry places those flashes from the cameras' own landmarks; their
    images are not used for reflectance (unwrap-uv leaves them out by default).  A raised camera whose room shot
    is missing is left out with a note (its flash then comes from the rig table); one without a landmark file is
    kept with a note (fit-geometry places it by the rig and refines it by its images).

    Returns (views, notes).
    """
    views = list(DEFAULT_VIEWS)
    notes: list[str] = []
    try:
        s = resolve_session(root, identity, session, str(recording).zfill(2))
    except ReflectmmError:
        return tuple(views), notes
    for fl in flashes:
        cam = RAISED_FLASH_CAMERA.get(str(fl))
        if cam is None or cam in views:
            continue
        img = shot_path(root, identity, s, str(recording).zfill(2), cam, ROOM_SHOT)
        lm = landmark_path(root, identity, s, str(recording).zfill(2), cam, landmarks_dir)
        if img is not None:
            views.append(cam)
            if lm is None:
                notes.append(f"camera {cam} (flash {fl}) has no landmarks for identity {identity}: fit-geometry "
                             "places it by the rig and the other views and refines it by its images "
                             "(docs/capture.md)")
        else:
            notes.append(f"flash {fl} is used but camera {cam} has no room shot for identity {identity}: "
                         f"fit-geometry will take flash {fl}'s position from the rig table (hundreds of mm off on a "
                         "nominal table; see docs/capture.md)")
    return tuple(views), notes

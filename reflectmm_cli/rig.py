"""The capture rig: cameras and flashes of a Multi-PIE-like light stage (docs/pipeline.md, docs/synthetic.md).

A rig is a TOML table the user can edit::

    [[camera]]
    name = "05_1"
    position = [0.0, 0.0, 1300.0]      # mm, model space (+y up, +z towards the frontal camera)
    look_at = [0.0, 0.0, 0.0]
    up = [0.0, 1.0, 0.0]
    focal_px = 1000.0
    width = 640
    height = 480

    [[flash]]
    id = "07"
    camera = "05_1"                    # attached to a camera: sits at its centre ...
    intensity = 3.5e6                  # radiant intensity, linear pixel units x mm^2 (E = I / d^2)

    [[flash]]
    id = "16"
    position = [0.0, 700.0, 1150.0]    # ... or on its own stand

Cameras follow the OpenCV pinhole convention of docs/pipeline.md: ``x_cam = R x + t``, the principal point at
the image centre ``((W-1)/2, (H-1)/2)`` (pixel centres at integer coordinates).  ``R`` is built from
``position``, ``look_at`` and ``up``: camera +z looks at the target, camera +y points down in the image.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import intrinsics, look_at_rotation, project

__all__ = [
    "ARC_CAMERAS", "RAISED_CAMERAS", "DEFAULT_VIEWS", "DEFAULT_FLASHES", "ALL_FLASHES",
    "RigCamera", "RigFlash", "Rig", "load_rig", "save_rig", "default_rig_path", "build_default_rig",
]

#: Head-height cameras in arc order (15 degrees apart, from the subject's right to the subject's left).
ARC_CAMERAS = ("11_0", "12_0", "09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0", "01_0",
               "24_0")
#: Raised cameras.
RAISED_CAMERAS = ("08_1", "19_1")
#: The 9 views the pipeline uses by default.
DEFAULT_VIEWS = ("09_0", "08_0", "13_0", "14_0", "05_1", "05_0", "04_1", "19_0", "20_0")
#: The 11 flashes the pipeline uses by default (9 at the default views + the 2 raised ones).
DEFAULT_FLASHES = ("03", "04", "05", "06", "07", "08", "09", "10", "11", "14", "18")
ALL_FLASHES = tuple(f"{i:02d}" for i in range(1, 19))


def default_rig_path() -> Path:
    """Path of the packaged default rig table."""
    return Path(__file__).resolve().parent / "data" / "multipie_rig.toml"


@dataclass
class RigCamera:
    """One camera of the rig (positions in mm, model space)."""

    name: str
    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    focal_px: float
    width: int
    height: int

    @property
    def R(self) -> np.ndarray:
        return look_at_rotation(self.position, self.look_at, self.up)

    @property
    def t(self) -> np.ndarray:
        return -self.R @ np.asarray(self.position, np.float64)

    @property
    def K(self) -> np.ndarray:
        return intrinsics(self.focal_px, self.width, self.height)

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.position, np.float64)

    @property
    def code(self) -> str:
        """Multi-PIE file-name code (``05_1`` → ``051``; :func:`reflectmm_cli.capture.layout.camera_code`)."""
        from reflectmm_cli.capture.layout import camera_code

        return camera_code(self.name)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of model-space points (..., 3)."""
        p = np.asarray(points, np.float64)
        return project(p.reshape(-1, 3), self.K, self.R, self.t)[0].reshape(p.shape[:-1] + (2,))

    def resized(self, width: int, height: int) -> "RigCamera":
        """The same camera with another sensor size; the focal length scales with the height (same framing)."""
        s = height / self.height
        return RigCamera(self.name, self.position.copy(), self.look_at.copy(), self.up.copy(),
                         self.focal_px * s, int(width), int(height))


@dataclass
class RigFlash:
    """One flash: attached to a camera (``camera``) or free-standing (``position`` only)."""

    id: str
    position: np.ndarray
    intensity: float
    camera: str | None = None


@dataclass
class Rig:
    """Cameras and flashes (in file order)."""

    cameras: list[RigCamera] = field(default_factory=list)
    flashes: list[RigFlash] = field(default_factory=list)
    source: Path | None = None

    def camera(self, name: str) -> RigCamera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise ReflectmmError(f"rig has no camera '{name}' (has: {', '.join(self.camera_names)})", self.source)

    def flash(self, fid: str) -> RigFlash:
        for f in self.flashes:
            if f.id == fid:
                return f
        raise ReflectmmError(f"rig has no flash '{fid}' (has: {', '.join(self.flash_ids)})", self.source)

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def flash_ids(self) -> list[str]:
        return [f.id for f in self.flashes]

    def select(self, cameras: Iterable[str] | None = None, flashes: Iterable[str] | None = None) -> "Rig":
        """A rig restricted to the named cameras / flashes (order as given); unknown names are an error.

        Flashes attached to a dropped camera keep their position (the flash still fires)."""
        cams = self.cameras if cameras is None else [self.camera(c) for c in cameras]
        fl = self.flashes if flashes is None else [self.flash(f) for f in flashes]
        return Rig(list(cams), list(fl), self.source)

    def resized(self, width: int, height: int) -> "Rig":
        return Rig([c.resized(width, height) for c in self.cameras], list(self.flashes), self.source)

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera": [{"name": c.name, "position": [float(v) for v in c.position],
                        "look_at": [float(v) for v in c.look_at], "up": [float(v) for v in c.up],
                        "focal_px": float(c.focal_px), "width": int(c.width), "height": int(c.height)}
                       for c in self.cameras],
            "flash": [({"id": f.id, "camera": f.camera} if f.camera else
                       {"id": f.id, "position": [float(v) for v in f.position]}) | {"intensity": float(f.intensity)}
                      for f in self.flashes],
        }


# --------------------------------------------------------------------------- parsing / validation

def _vec3(value: Any, what: str, path: Path | None) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ReflectmmError(f"{what} must be a list of 3 numbers, got {value!r}", path) from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ReflectmmError(f"{what} must be a list of 3 finite numbers, got {value!r}", path)
    return arr


def _number(value: Any, what: str, path: Path | None, *, positive: bool = True, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ReflectmmError(f"{what} must be a number, got {value!r}", path)
    if integer and (float(value) != int(value)):
        raise ReflectmmError(f"{what} must be an integer, got {value!r}", path)
    if not math.isfinite(value) or (positive and value <= 0):
        raise ReflectmmError(f"{what} must be a finite number > 0, got {value!r}", path)
    return float(value)


_CAMERA_KEYS = {"name", "position", "look_at", "up", "focal_px", "width", "height"}
_FLASH_KEYS = {"id", "camera", "position", "intensity"}


def rig_from_dict(doc: dict[str, Any], path: Path | None = None) -> Rig:
    """Validate a parsed rig table; errors name the file, the entry and the problem."""
    unknown = set(doc) - {"camera", "flash"}
    if unknown:
        raise ReflectmmError(f"unknown top-level key(s) {sorted(unknown)} (expected [[camera]] and [[flash]])",
                             path)
    cams_raw = doc.get("camera")
    if not isinstance(cams_raw, list) or not cams_raw:
        raise ReflectmmError("rig table has no [[camera]] entries", path)
    cameras: list[RigCamera] = []
    for i, c in enumerate(cams_raw):
        where = f"[[camera]] #{i + 1}" + (f" '{c.get('name')}'" if isinstance(c, dict) and "name" in c else "")
        if not isinstance(c, dict):
            raise ReflectmmError(f"{where} is not a table", path)
        missing = sorted(_CAMERA_KEYS - set(c) - {"up", "look_at"})
        if missing:
            raise ReflectmmError(f"{where} is missing {', '.join(missing)}", path)
        extra = sorted(set(c) - _CAMERA_KEYS)
        if extra:
            raise ReflectmmError(f"{where} has unknown key(s) {', '.join(extra)}", path)
        name = c["name"]
        if not isinstance(name, str) or not name:
            raise ReflectmmError(f"{where}: name must be a non-empty string", path)
        if any(x.name == name for x in cameras):
            raise ReflectmmError(f"{where}: duplicate camera name '{name}'", path)
        pos = _vec3(c["position"], f"{where}: position", path)
        tgt = _vec3(c.get("look_at", [0.0, 0.0, 0.0]), f"{where}: look_at", path)
        up = _vec3(c.get("up", [0.0, 1.0, 0.0]), f"{where}: up", path)
        try:
            look_at_rotation(pos, tgt, up)
        except ValueError as exc:
            raise ReflectmmError(f"{where}: {exc}", path) from None
        f = _number(c["focal_px"], f"{where}: focal_px", path)
        w = int(_number(c["width"], f"{where}: width", path, integer=True))
        h = int(_number(c["height"], f"{where}: height", path, integer=True))
        cameras.append(RigCamera(name, pos, tgt, up, f, w, h))
    flashes: list[RigFlash] = []
    for i, fl in enumerate(doc.get("flash") or []):
        where = f"[[flash]] #{i + 1}" + (f" '{fl.get('id')}'" if isinstance(fl, dict) and "id" in fl else "")
        if not isinstance(fl, dict):
            raise ReflectmmError(f"{where} is not a table", path)
        extra = sorted(set(fl) - _FLASH_KEYS)
        if extra:
            raise ReflectmmError(f"{where} has unknown key(s) {', '.join(extra)}", path)
        fid = fl.get("id")
        if not isinstance(fid, str) or not (len(fid) == 2 and fid.isdigit() and 1 <= int(fid) <= 99):
            raise ReflectmmError(f"{where}: id must be a two-digit string '01'..'99', got {fid!r}", path)
        if any(x.id == fid for x in flashes):
            raise ReflectmmError(f"{where}: duplicate flash id '{fid}'", path)
        if ("camera" in fl) == ("position" in fl):
            raise ReflectmmError(f"{where}: give exactly one of 'camera' (attached) or 'position'", path)
        if "camera" in fl:
            cam = [c for c in cameras if c.name == fl["camera"]]
            if not cam:
                raise ReflectmmError(f"{where} is attached to unknown camera {fl['camera']!r} "
                                     f"(cameras: {', '.join(c.name for c in cameras)})", path)
            pos, cname = cam[0].position.copy(), cam[0].name
        else:
            pos, cname = _vec3(fl["position"], f"{where}: position", path), None
        if "intensity" not in fl:
            raise ReflectmmError(f"{where} is missing intensity", path)
        inten = _number(fl["intensity"], f"{where}: intensity", path)
        flashes.append(RigFlash(fid, pos, inten, cname))
    return Rig(cameras, flashes, path)


def load_rig(path: str | Path | None = None) -> Rig:
    """Read and validate a rig table (None: the packaged default ``reflectmm_cli/data/multipie_rig.toml``)."""
    p = Path(path) if path is not None else default_rig_path()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ReflectmmError("rig table not found", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ReflectmmError(f"cannot read rig table ({exc})", p) from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ReflectmmError(f"not valid TOML ({exc})", p) from None
    return rig_from_dict(doc, p)


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(round(v, 6))) if abs(v) < 1e6 else f"{v:.6e}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    raise TypeError(type(v))


def rig_to_toml(rig: Rig, header: str = "") -> str:
    """TOML text of a rig (deterministic)."""
    lines = [f"# {ln}" if ln else "#" for ln in header.splitlines()]
    d = rig.to_dict()
    for c in d["camera"]:
        lines += ["", "[[camera]]"] + [f"{k} = {_fmt(v)}" for k, v in c.items()]
    for f in d["flash"]:
        lines += ["", "[[flash]]"] + [f"{k} = {_fmt(v)}" for k, v in f.items()]
    return "\n".join(lines).lstrip("\n") + "\n"


def save_rig(rig: Rig, path: str | Path, header: str = "") -> Path:
    """Write a rig table atomically (round-trips through :func:`load_rig`)."""
    return atomic_write_text(path, rig_to_toml(rig, header))


# --------------------------------------------------------------------------- the default rig

DEFAULT_RADIUS_MM = 1300.0
DEFAULT_FOCAL_PX = 1000.0
DEFAULT_FLASH_INTENSITY = 4.5e6
RAISED_ELEVATION_DEG = 30.0


def _on_sphere(radius: float, azimuth_deg: float, elevation_deg: float = 0.0) -> list[float]:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return [radius * math.cos(e) * math.sin(a), radius * math.sin(e), radius * math.cos(e) * math.cos(a)]


def build_default_rig(radius: float = DEFAULT_RADIUS_MM, focal_px: float = DEFAULT_FOCAL_PX, width: int = 640,
                      height: int = 480, flash_intensity: float = DEFAULT_FLASH_INTENSITY) -> Rig:
    """The Multi-PIE-like default rig (what ``reflectmm_cli/data/multipie_rig.toml`` holds).

    13 head-height cameras at azimuth −90°..+90° in 15° steps (``11_0`` at −90°, i.e. on the subject's right,
    −x; ``05_1`` frontal on +z; ``24_0`` at +90°), ``08_1``/``19_1`` raised 30° above the ±45° azimuths, all on
    a sphere of ``radius`` mm looking at the origin.  Flashes 01–13 on the arc cameras in arc order, 14 on
    ``08_1``, 18 on ``19_1``, 15–17 on stands 45° up at azimuth −25°, 0°, +25° (slightly farther away, so the
    intensity is raised to give the same irradiance at the head).
    """
    cams = []
    for i, name in enumerate(ARC_CAMERAS):
        pos = _on_sphere(radius, (i - 6) * 15.0)
        cams.append(RigCamera(name, np.array(pos), np.zeros(3), np.array([0.0, 1.0, 0.0]), focal_px, width, height))
    for name, az in (("08_1", -45.0), ("19_1", 45.0)):
        pos = _on_sphere(radius, az, RAISED_ELEVATION_DEG)
        cams.append(RigCamera(name, np.array(pos), np.zeros(3), np.array([0.0, 1.0, 0.0]), focal_px, width, height))
    flashes = [RigFlash(f"{i + 1:02d}", cams[i].position.copy(), flash_intensity, cams[i].name)
               for i in range(13)]
    flashes.append(RigFlash("14", cams[13].position.copy(), flash_intensity, "08_1"))
    stand_r = radius * 1.15
    for fid, az in (("15", -25.0), ("16", 0.0), ("17", 25.0)):
        flashes.append(RigFlash(fid, np.array(_on_sphere(stand_r, az, 45.0)), flash_intensity * 1.15 ** 2, None))
    flashes.append(RigFlash("18", cams[14].position.copy(), flash_intensity, "19_1"))
    return Rig(cams, flashes, None)


DEFAULT_RIG_HEADER = """\
Multi-PIE-like capture rig (reflectmm default).  Units: mm, model space (+y up, +z towards camera 05_1,
+x to the subject's left); the head sits at the origin.  Cameras: OpenCV pinhole, principal point at the
image centre, R from position/look_at/up.  Flash intensity: radiant intensity in linear pixel units x mm^2
(irradiance E = intensity / d^2).  13 head-height cameras 15 degrees apart on a 1.3 m arc, 08_1 and 19_1
raised 30 degrees; flashes 01-13 on the arc cameras in arc order, 14 on 08_1, 18 on 19_1, 15-17 on stands.
Focal length 1000 px at 640x480: a ~200 mm face at 1.3 m spans ~150 px, about a third of the image height."""

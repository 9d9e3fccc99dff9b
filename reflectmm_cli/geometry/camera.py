"""Pinhole cameras in the OpenCV convention (docs/pipeline.md): the one home of projection, intrinsics and
look-at; the rotations (numpy and torch) live in :mod:`reflectmm_cli.geometry.rotations` and are re-exported here.

``x_cam = R @ x_model + t``; ``u = fx·X/Z + s·Y/Z + cx``, ``v = fy·Y/Z + cy``; ``Z > 0`` in front of the
camera, image ``y`` down, the centre of the top-left pixel is ``(0, 0)``.  Camera centre ``c = −Rᵀt``.
Rotations are parameterised by axis-angle vectors (Rodrigues); the geometry fit optimises a left-multiplied
update ``R = exp([δ]×) @ R0`` so that poses near a rotation by π are never at the axis-angle singularity.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .rotations import _is_torch, axis_angle_to_matrix, look_at_rotation, matrix_to_axis_angle, skew

__all__ = ["Camera", "look_at", "look_at_rotation", "deep3d_camera", "orbit_camera", "parse_camera_spec", "project",
           "camera_centers", "intrinsics", "skew", "axis_angle_to_matrix", "matrix_to_axis_angle"]


@dataclass
class Camera:
    """A pinhole camera.

    Attributes:
        K: (3, 3) intrinsics (fx, fy, cx, cy, optional skew K[0,1]).
        R: (3, 3) rotation model → camera.
        t: (3,) translation model → camera (mm).
        width, height: image size in pixels.
        name: e.g. the Multi-PIE camera id ``"05_1"``.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    name: str = "camera"

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ReflectmmError(f"camera '{self.name}': image size must be positive, got "
                                 f"{self.width}x{self.height}")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            raise ReflectmmError(f"camera '{self.name}': R is not a rotation matrix")

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in model space, ``−Rᵀt``."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit optical axis in model space (the camera's +Z)."""
        return self.R[2].copy()

    def to_camera(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return p @ self.R.T + self.t

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Project (M, 3) model-space points: (uv (M, 2) pixels, depth Z (M,) along the optical axis).

        Points with Z ≤ 0 (behind the camera) get NaN pixel coordinates.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ReflectmmError(f"camera.project: points must be (M, 3), got {p.shape}")
        uv, z = project(p, self.K, self.R, self.t)
        uv[z <= 0] = np.nan
        return uv, z

    def pixel_grid(self) -> np.ndarray:
        """(H·W, 2) pixel centres (u = column, v = row) in row-major order."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return np.stack([u.ravel(), v.ravel()], axis=1)

    def rays(self, pixels=None) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel centres: (origins (M, 3), unit directions (M, 3)) in model space, float64.

        ``pixels`` (M, 2) in pixel coordinates; default: every pixel in row-major order (M = H·W).  The
        origins are a read-only broadcast of the camera centre.
        """
        M = self.R.T @ np.linalg.inv(self.K)  # pixel (u, v, 1) → model-space direction
        if pixels is None:
            u = np.arange(self.width, dtype=np.float64)
            v = np.arange(self.height, dtype=np.float64)
            d = (v[:, None, None] * M[:, 1] + M[:, 2])[:, None, :] + (u[:, None] * M[:, 0])[None, :, :]
            d = d.reshape(-1, 3)
        else:
            px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
            d = px[:, :1] * M[:, 0] + px[:, 1:2] * M[:, 1] + M[:, 2]
        d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        o = np.broadcast_to(self.center, d.shape)
        return o, d

    def with_size(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (intrinsics scaled; pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, self.R, self.t, width, height, self.name)

    def to_dict(self) -> dict:
        return {"name": self.name, "K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
                "width": self.width, "height": self.height}


def project(points, K, R, t):
    """The projection: (..., N, 3) model-space points with (..., 3, 3) K, R and (..., 3) t (batched over views
    by leading dims) → ((..., N, 2) pixels (u, v), (..., N) depth Z along the optical axis).

    ``u = fx·X/Z + s·Y/Z + cx``, ``v = fy·Y/Z + cy`` with ``(X, Y, Z) = R x + t``.  numpy in → numpy out
    (float64); torch in → torch out (differentiable; K, R, t tensors of the points' dtype).  Points behind the
    camera (Z ≤ 0) are projected as they come (the caller masks them; :meth:`Camera.project` sets NaN).
    """
    if _is_torch(points):
        import torch

        K, R, t = (torch.as_tensor(a, dtype=points.dtype, device=points.device) for a in (K, R, t))
        Xc = points @ R.transpose(-1, -2) + t[..., None, :]
        Z = Xc[..., 2]
        uv = torch.stack([K[..., 0, 0, None] * Xc[..., 0] / Z + K[..., 0, 1, None] * Xc[..., 1] / Z
                          + K[..., 0, 2, None],
                          K[..., 1, 1, None] * Xc[..., 1] / Z + K[..., 1, 2, None]], -1)
        return uv, Z
    points = np.asarray(points, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    Xc = points @ np.swapaxes(R, -1, -2) + t[..., None, :]
    Z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):  # Z = 0: inf/NaN pixels, for the caller to mask
        uv = np.stack([K[..., 0, 0, None] * Xc[..., 0] / Z + K[..., 0, 1, None] * Xc[..., 1] / Z + K[..., 0, 2, None],
                       K[..., 1, 1, None] * Xc[..., 1] / Z + K[..., 1, 2, None]], -1)
    return uv, Z


def camera_centers(R, t):
    """Camera centres in model space ``c = −Rᵀ t`` for (..., 3, 3) R and (..., 3) t (numpy or torch)."""
    if _is_torch(R):
        return -(R.transpose(-1, -2) @ t[..., None])[..., 0]
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", R, t)


def intrinsics(focal_px: float, width: int, height: int, cx: float | None = None, cy: float | None = None,
               fy: float | None = None) -> np.ndarray:
    """K with the principal point at the image centre ``((W−1)/2, (H−1)/2)`` unless given."""
    cx = (width - 1) / 2.0 if cx is None else cx
    cy = (height - 1) / 2.0 if cy is None else cy
    return np.array([[focal_px, 0, cx], [0, focal_px if fy is None else fy, cy], [0, 0, 1]], dtype=np.float64)


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), focal_px: float = 1500.0, width: int = 640,
            height: int = 480, name: str = "camera", cx: float | None = None, cy: float | None = None) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` appearing up in the image (OpenCV axes:
    +Z forward, +X right, +Y down)."""
    eye = np.asarray(eye, dtype=np.float64)
    try:
        R = look_at_rotation(eye, target, up)
    except ValueError as exc:
        raise ReflectmmError(f"camera '{name}': {exc}") from None
    return Camera(intrinsics(focal_px, width, height, cx, cy), R, -R @ eye, width, height, name)


def orbit_camera(yaw_deg: float = 0.0, pitch_deg: float = 0.0, distance: float = 1000.0,
                 target=(0.0, 0.0, 0.0), focal_px: float = 1500.0, width: int = 640, height: int = 480,
                 name: str | None = None) -> Camera:
    """Camera on a sphere around ``target``: yaw > 0 moves it towards +x (the subject's left), pitch > 0 up."""
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    eye = np.asarray(target, dtype=np.float64) + distance * np.array(
        [math.sin(y) * math.cos(p), math.sin(p), math.cos(y) * math.cos(p)])
    return look_at(eye, target, (0, 1, 0), focal_px, width, height,
                   name or f"yaw{yaw_deg:g}_pitch{pitch_deg:g}")


def deep3d_camera(focal: float = 1015.0, center: float = 112.0, size: int = 224, distance: float = 10.0,
                  unit_mm: float = 100.0) -> Camera:
    """Deep3DFaceRecon's camera expressed in our OpenCV convention and model units.

    Deep3DFaceRecon puts the camera at z = ``distance`` (10, in its decimetre units) looking down −z and
    projects with ``z' = distance − z``, ``u = f·x/z' + c``, ``v_up = f·y/z' + c`` with the image v axis pointing
    *up*.  In the OpenCV convention (v down) that is ``R = diag(1, −1, −1)``, ``t = (0, 0, distance)``: the y and
    z axes flip.  Model units are mm here, so the centre is at ``z = distance · unit_mm`` (1000 mm).  Deep3D
    flips landmark rows with ``H − 1 − y``, i.e. its v-up principal point 112 lands at row 111 in our
    pixel-centre convention; pass ``center=111.0`` to match its landmarks to the sub-pixel.
    """
    K = np.array([[focal, 0, center], [0, focal, center], [0, 0, 1]], dtype=np.float64)
    R = np.diag([1.0, -1.0, -1.0])
    t = np.array([0.0, 0.0, distance * unit_mm])
    return Camera(K, R, t, size, size, "deep3d")


_SPEC = re.compile(r"^(yaw|pitch|distance|dist|focal|f|width|height|size)=([-+0-9.eE]+(?:x[0-9]+)?)$")
#: The keys of a camera spec under one name each (``dist`` is ``distance``, ``f`` is ``focal``; ``size`` sets
#: ``width`` and ``height``).
_SPEC_KEY = {"dist": ("distance",), "f": ("focal",), "size": ("width", "height")}
#: Upper bounds of a camera spec: 1 km away, a focal length of 10⁷ px, 16384 px a side.
CAMERA_SPEC_MAX = {"distance": 1e6, "focal": 1e7, "width": 16384, "height": 16384}


def parse_camera_spec(spec: str, *, distance: float = 1000.0, focal_px: float = 1500.0, width: int = 640,
                      height: int = 480) -> Camera:
    """``frontal`` | ``deep3d`` | ``yaw=30`` | ``yaw=30,pitch=10,distance=1200,focal=1800,size=640x480``."""
    spec = (spec or "frontal").strip()
    if spec == "deep3d":
        return deep3d_camera()
    yaw = pitch = 0.0
    if spec != "frontal":
        from reflectmm_cli.params import ParamError, parse_list

        try:
            parts = parse_list(spec, "--camera")
        except ParamError as exc:
            raise ReflectmmError(f"--camera '{spec}': {str(exc).split(': ', 1)[-1]}") from None
        seen: dict[str, str] = {}
        for part in parts:
            m = _SPEC.match(part)
            if not m:
                raise ReflectmmError(f"--camera '{spec}': cannot parse '{part}' (use frontal, deep3d or "
                                     "yaw=DEG,pitch=DEG,distance=MM,focal=PX,size=WxH)")
            key, val = m.groups()
            for name in _SPEC_KEY.get(key, (key,)):
                if name in seen:
                    raise ReflectmmError(f"--camera '{spec}': {name} is given twice ('{seen[name]}' and '{part}')")
                seen[name] = part
            try:
                if key == "size":
                    w, h = val.split("x")
                    width, height = int(w), int(h)
                elif key in ("width", "height"):
                    width, height = (int(val), height) if key == "width" else (width, int(val))
                else:
                    fv = float(val)
                    if key == "yaw":
                        yaw = fv
                    elif key == "pitch":
                        pitch = fv
                    elif key in ("distance", "dist"):
                        distance = fv
                    else:
                        focal_px = fv
            except ValueError:
                raise ReflectmmError(f"--camera '{spec}': bad value in '{part}'") from None
    for what, v in (("distance", distance), ("focal", focal_px), ("width", width), ("height", height),
                    ("yaw", yaw), ("pitch", pitch)):
        if not math.isfinite(v) or (what not in ("yaw", "pitch") and v <= 0):
            raise ReflectmmError(f"--camera '{spec}': {what} must be finite" + ("" if what in ("yaw", "pitch")
                                                                               else " and > 0") + f", got {v:g}")
        if v > CAMERA_SPEC_MAX.get(what, math.inf):
            raise ReflectmmError(f"--camera '{spec}': {what} must be ≤ {CAMERA_SPEC_MAX[what]:g}, got {v:g}")
    return orbit_camera(yaw, pitch, distance, (0, 0, 0), focal_px, width, height,
                        "frontal" if spec == "frontal" else spec)

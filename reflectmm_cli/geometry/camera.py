"""Pinhole cameras in the OpenCV convention (docs/pipeline.md).

``x_cam = R @ x_model + t``; ``u = fx·X/Z + s·Y/Z + cx``, ``v = fy·Y/Z + cy``; ``Z > 0`` in front of the
camera, image ``y`` down, the centre of the top-left pixel is ``(0, 0)``.  Camera centre ``c = −Rᵀt``.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["Camera", "look_at", "deep3d_camera", "project_torch", "orbit_camera", "parse_camera_spec"]


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
        xc = self.to_camera(p)
        z = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            h = xc @ self.K.T
            uv = h[:, :2] / h[:, 2:3]
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
    f = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(f) == 0:
        raise ReflectmmError(f"camera '{name}': eye and target coincide")
    f /= np.linalg.norm(f)
    x = np.cross(f, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ReflectmmError(f"camera '{name}': up vector is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f])
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


def project_torch(points, K, R, t):
    """Differentiable projection of (..., M, 3) points: (uv (..., M, 2), depth (..., M)).

    K, R: (..., 3, 3) and t: (..., 3) tensors (batched over views when given with a leading dim that
    broadcasts against the points).
    """
    import torch

    K = torch.as_tensor(K, dtype=points.dtype, device=points.device)
    R = torch.as_tensor(R, dtype=points.dtype, device=points.device)
    t = torch.as_tensor(t, dtype=points.dtype, device=points.device)
    xc = points @ R.transpose(-1, -2) + t.unsqueeze(-2)
    h = xc @ K.transpose(-1, -2)
    z = h[..., 2:3]
    uv = h[..., :2] / torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    return uv, xc[..., 2]


_SPEC = re.compile(r"^(yaw|pitch|distance|dist|focal|f|width|height|size)=(-?[0-9.]+(?:x[0-9]+)?)$")


def parse_camera_spec(spec: str, *, distance: float = 1000.0, focal_px: float = 1500.0, width: int = 640,
                      height: int = 480) -> Camera:
    """``frontal`` | ``deep3d`` | ``yaw=30`` | ``yaw=30,pitch=10,distance=1200,focal=1800,size=640x480``."""
    spec = (spec or "frontal").strip()
    if spec == "deep3d":
        return deep3d_camera()
    yaw = pitch = 0.0
    if spec != "frontal":
        for part in spec.split(","):
            m = _SPEC.match(part.strip())
            if not m:
                raise ReflectmmError(f"--camera '{spec}': cannot parse '{part}' (use frontal, deep3d or "
                                     "yaw=DEG,pitch=DEG,distance=MM,focal=PX,size=WxH)")
            key, val = m.groups()
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
    return orbit_camera(yaw, pitch, distance, (0, 0, 0), focal_px, width, height,
                        "frontal" if spec == "frontal" else spec)

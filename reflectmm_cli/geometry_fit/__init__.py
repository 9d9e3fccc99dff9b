"""Geometry fitting: a multi-view morphable-model fit (landmarks + photometric + priors) per identity
(docs/fit-geometry.md)."""
from .fit import FitConfig, GeometryFit, ViewSet, fit_geometry, huber
from .init import flash_positions, initial_poses, pnp_pose, rigid_align
from .landmarks import (
    DEFAULT_GROUP_WEIGHTS,
    GROUPS,
    find_landmark_file,
    landmark_weights,
    write_pts,
)
from .model import ShapeModel

__all__ = [
    "DEFAULT_GROUP_WEIGHTS",
    "FitConfig",
    "GROUPS",
    "GeometryFit",
    "ShapeModel",
    "ViewSet",
    "find_landmark_file",
    "fit_geometry",
    "flash_positions",
    "huber",
    "initial_poses",
    "landmark_weights",
    "pnp_pose",
    "rigid_align",
    "write_pts",
]

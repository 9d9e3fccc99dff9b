"""Geometry fitting: a multi-view morphable-model fit (landmarks + photometric + priors) per identity
(docs/fit-geometry.md)."""
from .camera_math import axis_angle_to_matrix, camera_centers, huber, matrix_to_axis_angle, project
from .fit import FitConfig, GeometryFit, ViewSet, fit_geometry
from .init import flash_positions, initial_poses, pnp_pose, rigid_align
from .landmarks import (
    DEFAULT_GROUP_WEIGHTS,
    GROUPS,
    find_landmark_file,
    landmark_weights,
    read_landmarks,
    write_pts,
)
from .model import ShapeModel, vertex_normals_torch

__all__ = [
    "DEFAULT_GROUP_WEIGHTS",
    "FitConfig",
    "GROUPS",
    "GeometryFit",
    "ShapeModel",
    "ViewSet",
    "axis_angle_to_matrix",
    "camera_centers",
    "find_landmark_file",
    "fit_geometry",
    "flash_positions",
    "huber",
    "initial_poses",
    "landmark_weights",
    "matrix_to_axis_angle",
    "pnp_pose",
    "project",
    "read_landmarks",
    "rigid_align",
    "vertex_normals_torch",
    "write_pts",
]

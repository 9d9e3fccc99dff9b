"""Face geometry: linear face models and loaders, the procedural face, pinhole cameras, Embree ray casting,
UV-space rasterisation and a small renderer (docs/geometry.md)."""
from .camera import Camera, deep3d_camera, look_at, orbit_camera, parse_camera_spec, project
from .face_model import (
    FaceModel,
    face_model_from_artifact,
    face_normals,
    load_bfm09,
    load_bfm_front,
    load_exp_pca_bin,
    load_face_model,
    save_face_model,
    vertex_normals,
)
from .procedural import procedural_face_model
from .render import RenderResult, render_envmap, render_point_light, surface_reflectance, to_display
from .raycast import Raster, RayScene, RayStats, has_embree, rasterize, shadow_mask, visibility
from .uv import (
    UVRaster,
    cylindrical_uv,
    rasterize_uv,
    sample_uv_map,
    uv_distortion,
    uv_positions,
    vertex_to_uv_map,
)

__all__ = [
    "Camera",
    "FaceModel",
    "Raster",
    "RenderResult",
    "render_envmap",
    "render_point_light",
    "surface_reflectance",
    "to_display",
    "RayScene",
    "RayStats",
    "UVRaster",
    "cylindrical_uv",
    "has_embree",
    "rasterize",
    "rasterize_uv",
    "sample_uv_map",
    "shadow_mask",
    "uv_distortion",
    "uv_positions",
    "vertex_to_uv_map",
    "visibility",
    "deep3d_camera",
    "face_model_from_artifact",
    "face_normals",
    "load_bfm09",
    "load_bfm_front",
    "load_exp_pca_bin",
    "load_face_model",
    "look_at",
    "orbit_camera",
    "parse_camera_spec",
    "procedural_face_model",
    "project",
    "save_face_model",
    "vertex_normals",
]

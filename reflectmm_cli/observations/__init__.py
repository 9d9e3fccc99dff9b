"""Per-texel observations from captures and fitted geometry (``unwrap-uv``)."""

from reflectmm_cli.observations.unwrap import (RayOccluder, bilinear, previews, project, unwrap_observations,
                                               uv_geometry)
from reflectmm_cli.observations.uvmap import interpolate, uv_rasterize

__all__ = ["RayOccluder", "bilinear", "interpolate", "previews", "project", "unwrap_observations", "uv_geometry",
           "uv_rasterize"]

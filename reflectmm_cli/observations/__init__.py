"""Per-texel observations from captures and fitted geometry (``unwrap-uv``)."""

from reflectmm_cli.observations.unwrap import bilinear, previews, unwrap_observations, uv_geometry

__all__ = ["bilinear", "previews", "unwrap_observations", "uv_geometry"]

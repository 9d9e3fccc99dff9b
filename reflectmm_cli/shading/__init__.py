"""Shading core: multi-lobe Blinn-Phong BRDF, real spherical harmonics, SH environment lighting (docs/design.md §2;
the light model lives in :mod:`reflectmm_cli.model.light`). Conventions and formulas: docs/shading.md.

numpy in → numpy out; any torch tensor in → torch out (differentiable).
"""
from .brdf import DEFAULT_EXPONENTS, blinn_phong_norm, shade_directional
from .env import EnvBasis, band_limits, shade_env, specular_view_albedo
from .envmap import (
    direction_to_equirect,
    envmap_from_sh,
    envmap_rgb,
    equirect_directions,
    equirect_weights,
    load_envmap,
    project_envmap,
)
from .sh import (
    blinn_phong_sh_coeffs,
    fibonacci_sphere,
    lambert_sh_coeffs,
    sh_basis,
    sh_count,
    sh_order,
    sh_index,
    sh_from_deep3d,
    sh_rotation,
)

__all__ = [
    "DEFAULT_EXPONENTS",
    "EnvBasis",
    "sh_from_deep3d",
    "band_limits",
    "blinn_phong_norm",
    "blinn_phong_sh_coeffs",
    "direction_to_equirect",
    "envmap_from_sh",
    "envmap_rgb",
    "load_envmap",
    "equirect_directions",
    "equirect_weights",
    "fibonacci_sphere",
    "lambert_sh_coeffs",
    "project_envmap",
    "sh_basis",
    "sh_count",
    "sh_order",
    "sh_index",
    "sh_rotation",
    "shade_directional",
    "shade_env",
    "specular_view_albedo",
]

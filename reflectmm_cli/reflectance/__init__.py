"""Per-identity reflectance estimation (DESIGN.md §3): design columns, conditioning, solvers, simulation.

See docs/fit-reflectance.md.
"""
from .design import (Conditioning, Design, blinn_phong_norm, check_observations, conditioning,
                     conditioning_from_obs, design_columns, mirror_index)

__all__ = ["Conditioning", "Design", "blinn_phong_norm", "check_observations", "conditioning",
           "conditioning_from_obs", "design_columns", "mirror_index"]

"""Per-identity reflectance estimation (docs/design.md §3): design columns, conditioning, solvers, simulation.

See docs/fit-reflectance.md.
"""
from .design import (Conditioning, Design, check_observations, conditioning,
                     conditioning_from_obs, design_columns, mirror_index)
from .fit import (AdamConfig, FitMapsConfig, NormalRefinementConfig, PriorConfig, ReflectanceMaps, SolverConfig,
                  SymmetryConfig, fit_maps, maps_from_arrays, normalized_convolution, render_uv)
from .nnls import kkt_violation, nnls_batched
from .simulate import simulate_observations

__all__ = ["AdamConfig", "Conditioning", "Design", "FitMapsConfig", "NormalRefinementConfig", "PriorConfig",
           "ReflectanceMaps", "SolverConfig", "SymmetryConfig", "check_observations", "conditioning",
           "conditioning_from_obs", "design_columns", "fit_maps", "kkt_violation", "maps_from_arrays",
           "mirror_index", "nnls_batched", "normalized_convolution", "render_uv", "simulate_observations"]

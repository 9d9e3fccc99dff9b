"""uv-observations rendered with the GGX ground-truth BRDF (for the representation comparison's tests and
benchmarks without running the whole synthetic pipeline).

Geometry, rig, masks and the diffuse albedo are those of :func:`reflectmm_cli.reflectance.simulate.
simulate_observations`; the radiance of every pair is re-rendered with
:func:`reflectmm_cli.synth.ggx.ggx_directional` (Lambert + GGX/Smith/Schlick) with spatially varying roughness α
and specular intensity ρ, so no Blinn-Phong representation is exact (docs/design.md §4).
"""
from __future__ import annotations

import numpy as np

__all__ = ["simulate_ggx_observations"]


def simulate_ggx_observations(size: int = 64, seed: int = 0, alpha_range=(0.2, 0.5), rho_range=(1.0, 3.0),
                              noise: float = 0.0, irradiance: float = 2.5, views=None, flashes=None):
    """(obs, truth): uv-observations rendered with GGX; truth has ``albedo (3,S,S)``, ``roughness (S,S)``,
    ``spec_intensity (S,S)``, ``spec_albedo (S,S)`` (directional albedo at normal view = the 3-lobe model's Σw)."""
    from reflectmm_cli.reflectance.simulate import simulate_observations
    from reflectmm_cli.synth.ggx import ggx_directional, ggx_specular_albedo

    obs, tr = simulate_observations(size=size, seed=seed, irradiance=irradiance, views=views, flashes=flashes,
                                    return_truth=True, dtype=np.float32)
    S = int(size)
    rng = np.random.default_rng(seed + 101)
    c = (np.arange(S) + 0.5) / S
    u, v = np.meshgrid(c, c)
    au = np.abs(u - 0.5)
    ph = rng.uniform(0, 2 * np.pi, 3)
    t = 0.5 + 0.25 * np.cos(7 * au + ph[0]) * np.cos(4 * v + ph[1]) + 0.25 * np.sin(8 * au * v + ph[2])
    tzone = np.exp(-(au / 0.1) ** 2) * np.exp(-((v - 0.45) / 0.3) ** 2)
    alpha = alpha_range[0] + (alpha_range[1] - alpha_range[0]) * np.clip(0.7 * t + 0.3 * (1 - tzone), 0, 1)
    rho = rho_range[0] + (rho_range[1] - rho_range[0]) * np.clip(0.5 * t + 0.5 * tzone, 0, 1)
    albedo = np.asarray(tr["albedo"], np.float64)
    pos = np.asarray(obs["position"], np.float64)
    nrm = np.asarray(obs["normal"], np.float64)
    rad = np.zeros(obs["radiance"].shape, np.float32)
    noise_rng = np.random.default_rng(seed + 7)
    c_hw = np.moveaxis(albedo, 0, -1)
    for j in range(rad.shape[0]):
        f, vi = int(obs["pair_flash"][j]), int(obs["pair_view"][j])
        ld = obs["flash_pos"][f] - pos
        vd = obs["cam_centers"][vi] - pos
        E = float(obs["flash_intensity"][f]) / np.sum(ld * ld, -1)
        s = ggx_directional(c_hw, rho, alpha, nrm, ld, vd, np.repeat(E[..., None], 3, -1))
        if noise:
            s = s * (1 + noise * noise_rng.standard_normal(s.shape))
        rad[j] = np.where(obs["observed"][j][..., None], s, 0.0)
    obs = dict(obs)
    obs["radiance"] = rad.astype(np.float16)
    truth = {"albedo": albedo, "roughness": alpha, "spec_intensity": rho,
             "spec_albedo": ggx_specular_albedo(alpha, rho)}
    return obs, truth

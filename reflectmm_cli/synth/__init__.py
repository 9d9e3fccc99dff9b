"""The synthetic world (docs/synthetic.md): GGX ground-truth BRDF, skin reflectance maps, Multi-PIE-like rig
renders with ground truth, and procedural HDR environment maps.

Python API (the CLI verbs ``reflectmm synth multipie`` / ``synth envmaps`` are thin layers over these):

* :func:`synth_multipie` with a :class:`SynthConfig` — the whole data set;
* :func:`make_identity`, :func:`render_identity` — one identity;
* :func:`skin_maps`, :func:`sample_skin_params`, :func:`region_masks` — reflectance in UV space;
* :func:`ggx_directional`, :func:`ggx_brdf`, :func:`ggx_specular_albedo`, :func:`fit_lobes_to_ggx` — the BRDF;
* :func:`make_envmap`, :func:`write_envmaps` — HDR maps.
"""
from .envmaps import ENVMAP_KINDS, make_envmap, tonemap, write_envmaps
from .ggx import SKIN_F0, fit_lobes_to_ggx, ggx_brdf, ggx_directional, ggx_ndf, ggx_specular_albedo
from .multipie import SynthConfig, make_identity, render_identity, room_light_sh, synth_multipie
from .skin import SkinMaps, SkinParams, region_masks, sample_skin_params, skin_maps

__all__ = [
    "ENVMAP_KINDS", "SKIN_F0", "SkinMaps", "SkinParams", "SynthConfig", "fit_lobes_to_ggx", "ggx_brdf",
    "ggx_directional", "ggx_ndf", "ggx_specular_albedo", "make_envmap", "make_identity", "region_masks",
    "render_identity", "room_light_sh", "sample_skin_params", "skin_maps", "synth_multipie", "tonemap",
    "write_envmaps",
]

"""The synthetic world: rig renders, skin reflectance, GGX ground truth and HDR environment maps."""

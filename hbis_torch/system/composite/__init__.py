"""The foveated composite (the super-resolved fovea inlaid in the panorama) and the foveal ratio
and bandwidth saving measured on what the system sampled."""

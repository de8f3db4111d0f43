"""The HBIS as a whole, in the order its stages run.

- :mod:`hbis_torch.system.array`: the 3 x 3 camera array on its curved frame, the wide planar
  scene it looks at, and the simulated device that renders its views.
- :mod:`hbis_torch.system.stitch`: the nine views stitched into one panorama, the homographies
  refined from the images, and the FOV extension measured on the result.
- :mod:`hbis_torch.system.foveation`: the two-stage loop: detect motion, steer the fovea onto it,
  scan it.
- :mod:`hbis_torch.system.composite`: the super-resolved fovea inlaid in the panorama, and the
  foveal ratio and bandwidth saving measured on what was sampled.
- :mod:`hbis_torch.system.report`: the plots and the HTML report.
- :mod:`hbis_torch.system.pipeline`: the whole chain on built-in defaults (``hbis demo``).
"""

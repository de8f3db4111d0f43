"""The camera sensor's colour filter array and noise: ideas that the simulator, registration and
both reconstruction methods share.

* :mod:`~hbis_torch.sensor.cfa`: which pixel sees which colour, mosaicking RGB, demosaicking.
* :mod:`~hbis_torch.sensor.noise`: per-frame mean, spread and noise level, and the
  Poisson-Gaussian noise model fitted to a noise operator's output.

It imports only numpy, torch and the package's basics (and OpenCV, where installed, to demosaic),
so that every package above the basics may import it.
"""

from hbis_torch.sensor.cfa import bayer_masks, demosaic, mosaic
from hbis_torch.sensor.noise import fit_noise_params, immerkaer, mean_and_spread, noise_sigma

__all__ = [
    "bayer_masks",
    "demosaic",
    "fit_noise_params",
    "immerkaer",
    "mean_and_spread",
    "mosaic",
    "noise_sigma",
]

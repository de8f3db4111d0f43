"""The camera sensor's noise: ideas that registration and both reconstruction methods share.

* :mod:`~hbis_torch.sensor.noise`: per-frame mean, spread and noise level, and the
  Poisson-Gaussian noise model fitted to a noise operator's output.

It imports only numpy, torch and the package's basics, so that every package above the basics
may import it.
"""

from hbis_torch.sensor.noise import fit_noise_params, immerkaer, mean_and_spread, noise_sigma

__all__ = [
    "fit_noise_params",
    "immerkaer",
    "mean_and_spread",
    "noise_sigma",
]

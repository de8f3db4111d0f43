"""``scipy.ndimage.gaussian_filter``'s sums, without importing ``scipy.ndimage``.

A burst's lens estimate and local motion each smooth a few small float64 arrays with a Gaussian
(a frame's gradients, edge windows' structure tensors, a field of tile shifts). Importing
``scipy.ndimage`` for it took 0.2 to 0.4 s in a process that had reconstructed a small burst on
this project's 2-core machine, 0.8 s in a fresh one (scipy's array-API layer imports
``numpy.f2py``): every ``hbis reconstruct`` of a burst paid it. This module is the same filter:
scipy's kernel (the Gaussian sampled to ``truncate`` sigmas and normalised) and its sums in
scipy's order for a symmetric kernel (the centre sample times its weight, then each pair of
samples the same distance either side, added together and times their weight, from the
outermost pair in), axis after axis: the same bits (tests/test_gaussian_filter.py compares them
on every mode it takes, with lines shorter than the kernel).

Arrays of any shape, float64; sigma in samples (one per axis, or one for all; 0 leaves an axis).
"""

from __future__ import annotations

import numpy as np

#: scipy.ndimage's modes and numpy.pad's names for the same extension of a line beyond its ends.
MODES = {"reflect": "symmetric", "nearest": "edge", "mirror": "reflect", "wrap": "wrap"}


def gaussian_kernel(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """The normalised Gaussian of standard deviation ``sigma`` sampled at the integers within
    ``int(truncate * sigma + 0.5)`` of 0, (2 radius + 1,) float64 (scipy's ``_gaussian_kernel1d``)."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x**2)
    return phi / phi.sum()


def gaussian_filter(image: np.ndarray, sigma, mode: str = "reflect", truncate: float = 4.0,
                    output: np.ndarray | None = None) -> np.ndarray:
    """``image`` smoothed by a Gaussian along each axis, as ``scipy.ndimage.gaussian_filter``.

    Parameters
    ----------
    image : np.ndarray, float64, any shape
    sigma : float or sequence of float
        The Gaussian's standard deviation along each axis (samples); axes of sigma 0 are left.
    mode : {"reflect", "nearest", "mirror", "wrap"}
        How a line is extended beyond its ends (scipy's names).
    truncate : float
        The kernel's reach, in sigmas.
    output : np.ndarray, optional
        Float64 memory of ``image``'s shape to write the result into.

    Returns
    -------
    np.ndarray, ``image``'s shape, float64 (``output`` where given)
    """
    image = np.asarray(image)
    if image.dtype != np.float64 or mode not in MODES:
        raise ValueError(f"gaussian_filter takes float64 arrays and a mode of {sorted(MODES)}, "
                         f"got {image.dtype} and {mode!r}")
    sigmas = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (image.ndim,))
    out = image
    for axis, s in enumerate(sigmas):
        if s > 1e-15:  # (scipy's own threshold)
            out = _along(out, float(s), axis, MODES[mode], truncate)
    if output is None:
        return out.copy() if out is image else out
    output[...] = out
    return output


def _along(image: np.ndarray, sigma: float, axis: int, pad_mode: str, truncate: float) -> np.ndarray:
    """One axis's correlation with the symmetric kernel, in scipy's order of sums."""
    weights = gaussian_kernel(sigma, truncate)
    radius, size = len(weights) // 2, image.shape[axis]
    widths = [(0, 0)] * image.ndim
    widths[axis] = (radius, radius)
    padded = np.pad(image, widths, mode=pad_mode)

    def shifted(k: int) -> np.ndarray:  # the line's samples k places on, (image's shape)
        index = [slice(None)] * image.ndim
        index[axis] = slice(radius + k, radius + k + size)
        return padded[tuple(index)]

    out = shifted(0) * weights[radius]
    for j in range(radius, 0, -1):
        out += (shifted(-j) + shifted(j)) * weights[radius + j]
    return out

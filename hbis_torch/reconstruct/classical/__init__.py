"""Classical multi-frame super-resolution: scattered samples -> h-times grid -> deblur.

Every sample of every frame is placed at its true position on the reference frame's grid (from
the optics, from the registration, or both), then:

1. **Interpolation (normalized convolution, O(N)).** Each sample is splatted with a small
   Gaussian (sigma ``kernel_sigma`` HR px, 3 x 3 footprint) onto an h-times grid; the image is
   the weighted sum over the sum of weights (Knutsson & Westin 1993). The splat grid is shifted
   by the samples' common sub-pixel offset (half an HR pixel for even h, where the scan puts
   the samples between the output pixels' centres), so that interpolation does not average
   neighbours; the deblurring removes that shift exactly, in the Fourier domain. Holes
   (missing frames, the border) are filled from the same sums blurred wider.
2. **Deblurring (Wiener filter with aliasing).** The interpolated image is the scene seen
   through the optics (diffraction-limited OTF of the f-number), the LR pixel's aperture (a box
   of h HR pixels, times sqrt(fill factor)), sampled on the HR lattice. What is wanted is what an
   ideal sensor of pitch p/h sees (the project's ground truth): the same optics and an aperture
   of one HR pixel. The output is the minimum-mean-square-error linear estimate of that image
   (:func:`wiener_deblur`), which also accounts for the scene energy that aliases onto the
   lattice. **Prior:** the scene is Gaussian with a power-law spectrum s^2 / abs(f)^beta (natural
   images: beta about 2, i.e. independent Gaussian gradients), s^2 and beta fitted to the data
   within the sensor's own band; the noise is white, its level measured on the HR lattice
   (:func:`lattice_noise`). The FFT's periodic borders are handled by Moisan's periodic + smooth
   decomposition.

Coordinates: LR pixel (u, v) is the centre of column u, row v of the reference frame's ROI;
HR pixel (U, V) is centred at LR ((U + 0.5)/h - 0.5, (V + 0.5)/h - 0.5) (docs/design.md, section 1).
Positions are float64, but on the lattice only each sample's nearest node (an integer) and its
offset from it (float32) are kept (:mod:`.lattice`); the per-node sums, the deblurring (FFTs
and filter) and the result are float32 (tests/test_fullframe.py: within 1e-4 of float64).

Modules
-------
:mod:`.transfer`
    The image model's transfer functions: optics (:func:`optics_cutoff`,
    :func:`diffraction_otf`), pixel aperture (:func:`box`), splat (:func:`splat_transfer`).
:mod:`.lattice`
    The samples' nearest lattice nodes and offsets, a batch at a time (:func:`node_batch`).
:mod:`.splat`
    Step 1: :func:`splat`, :func:`snap_to_lattice`, hole filling (:func:`fill_holes`).
:mod:`.wiener`
    Step 2: :func:`wiener_deblur`, the prior's fit (:func:`fit_spectrum`).
:mod:`.periodic`
    Its periodic + smooth split (:func:`periodic_smooth`) and the smooth part's shift
    (:func:`shift_image`, or in the Fourier domain).
:mod:`.sr`
    Both steps on frames with known positions: :func:`classical_sr`, :func:`lattice_image`,
    :func:`lattice_noise` (and :func:`lattice_noise_params`, the frames' noise model measured
    on the lattice, for the learned method).
:mod:`.method`
    A whole stack: :func:`reconstruct_classical` (the ``"classical"`` entry of
    :data:`hbis_torch.reconstruct.METHODS`; positions from
    :func:`hbis_torch.reconstruct.positions.stack_sample_positions`), :func:`stack_fill_factor`.
"""

from __future__ import annotations


from hbis_torch.reconstruct.classical.method import reconstruct_classical, stack_fill_factor
from hbis_torch.reconstruct.classical.holes import fill_holes
from hbis_torch.reconstruct.classical.splat import common_offset, snap_to_lattice, splat
from hbis_torch.reconstruct.classical.sr import classical_sr, lattice_image, lattice_noise, lattice_noise_params
from hbis_torch.reconstruct.classical.transfer import box, diffraction_otf, optics_cutoff, splat_transfer
from hbis_torch.reconstruct.classical.periodic import periodic_smooth, shift_image
from hbis_torch.reconstruct.classical.wiener import NOISE_FLOOR, fit_spectrum, wiener_deblur
from hbis_torch.reconstruct.positions import REGISTRATIONS, optical_sample_positions

__all__ = [
    "NOISE_FLOOR",
    "REGISTRATIONS",
    "box",
    "classical_sr",
    "common_offset",
    "diffraction_otf",
    "fill_holes",
    "fit_spectrum",
    "lattice_image",
    "lattice_noise",
    "lattice_noise_params",
    "optical_sample_positions",
    "optics_cutoff",
    "periodic_smooth",
    "reconstruct_classical",
    "shift_image",
    "snap_to_lattice",
    "splat",
    "splat_transfer",
    "stack_fill_factor",
    "wiener_deblur",
]

"""Classical super-resolution of frames whose samples' positions are known:
:func:`classical_sr` (interpolation on the h-times lattice, then Wiener deblurring) and its
lattice steps (:func:`lattice_image`, :func:`lattice_noise`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.checks import as_float64_tensor, check_h
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import NodePositions, interpolate_positions
from hbis_torch.reconstruct.classical.holes import fill_holes, lower_median, median_subset, typical_weight
from hbis_torch.reconstruct.classical.lattice import batch_slices, common_offset_of, node_batch
from hbis_torch.reconstruct.classical.lattice_fit import fill_holes_from_samples
from hbis_torch.reconstruct.classical.splat import splat, splat_on_lattice
from hbis_torch.reconstruct.classical.wiener import wiener_deblur
from hbis_torch.sensor.noise import fit_noise_params, immerkaer

# Samples per batch in lattice_image (a band of rows of every frame: lattice.batch_slices):
# its temporaries (some 150 bytes a sample) stay near 150 MB whatever the stack's size.
BATCH_SAMPLES = 1 << 20
# A burst of up to this many samples keeps its lattice batches (24 bytes a sample: 200 MB) for the
# splat's second pass rather than computing their positions again (16 frames of 640 x 480: 5M).
KEEP_SAMPLES = 1 << 23
# Rows used to find the samples' common sub-pixel offset: every 4th, and on frames of over 512
# rows every (rows // 64)-th, at most every 16th (on a full frame at h = 4 the offset moves by
# 8e-5 HR px from every row's, against 5e-5 with every 4th, which cost 0.05 s more). Small frames
# keep every 4th: a burst's random shifts leave the offset ill-defined, and changing the rows it
# is found from moved one burst's result by 0.8 dB.
OFFSET_ROW_STRIDE = 4


#: The largest Gaussian lens blur (LR px) the deblurring takes: beyond it a pixel's neighbours
#: share most of its light and a burst resolves little that deblurring could bring back.
MAX_LENS_SIGMA = 3.0


def classical_sr(
    frames,
    positions,
    h: int,
    deblur: bool = True,
    *,
    weights=None,
    kernel_sigma: float = 0.45,
    noise: float | None = None,
    fill_factor: float = 1.0,
    cutoff: float | None = None,
    strength: float = 2.0,
    noise_params_out: list | None = None,
    noise_floor: float | None = None,
    mixed_offsets: bool = False,
    lens_sigma: float | None = 0.0,
    fit_holes: bool = False,
    shared: dict | None = None,
    target_aperture: float | None = None,
) -> Tensor:
    """Super-resolve frames whose samples' positions are known.

    Parameters
    ----------
    frames : Tensor or array, shape (F, H, W)
        Intensities in [0, 1].
    positions : Tensor or array, shape (F, H, W, 2), or NodePositions
        Position (u, v) of every sample in the reference frame's LR pixel coordinates
        (ROI-local), for example from
        :func:`~hbis_torch.reconstruct.positions.stack_sample_positions`; or the spline nodes
        they are interpolated from (:func:`~hbis_torch.reconstruct.positions.stack_sample_nodes`,
        values (F, n_v, n_u, 2)), then interpolated a batch of frames at a time, never held whole;
        or a burst's :class:`~hbis_torch.reconstruct.positions.BurstPositions`, computed a band
        at a time.
    h : int
        Resolution improvement factor: the output is (h*H, h*W).
    deblur : bool
        Apply the Wiener deblurring (False: the normalized-convolution interpolation alone,
        resampled onto the output grid).
    weights : Tensor, shape (F,) or (F, H, W), optional
        Per-frame or per-sample weights in [0, 1] (0 leaves a frame or sample out); a float32
        tensor is read as it is (the lattice sums in float32), anything else as float64.
    kernel_sigma : float
        Splat Gaussian in HR px.
    noise : float, optional
        Noise standard deviation of the frames (default: estimated from them).
    fill_factor : float
        Light-sensitive fraction of a pixel's area, in (0, 1] (a centred square of side
        sqrt(fill_factor) times the pitch, as in the simulator's SensorModel).
    cutoff : float, optional
        Optical cutoff in cycles per LR pixel (:func:`optics_cutoff`); None ignores the optics.
    strength : float
        Scales the noise power in the Wiener filter. The default 2 was chosen on simulated
        stacks (8 scenes x h = 3, 4, 5, 64 px, seed 1): it beat 1, 1.5 and 3 in mean PSNR (by
        0.4 dB over 1), the estimated noise being the median level while shot noise grows with
        the signal, and the power-law prior overstating some scenes' fine detail.
    noise_params_out : list, optional
        With ``deblur``, receives the frames' noise parameters (a, b) measured on the lattice
        (:func:`lattice_noise_params`), for the learned method's noise map.
    noise_floor : float, optional
        Without ``noise``: a floor for the noise standard deviation of one sample; the nodes'
        noise measured on the lattice is then taken as at least
        ``noise_floor / sqrt(samples per node)``
        (a burst's: :func:`~hbis_torch.reconstruct.classical.burst.burst_sr`).
    mixed_offsets : bool
        Samples of many frames at different offsets share the lattice's nodes (a burst): the
        first-order correction of :func:`~hbis_torch.reconstruct.classical.splat.snap_to_lattice`
        then measures the pilot's bias, and the Wiener prior is fitted below one cycle per LR px
        (:func:`~hbis_torch.reconstruct.classical.wiener.fit_spectrum`'s notes).
    lens_sigma : float or None
        A Gaussian lens blur (LR px) that the deblurring undoes, beyond ``cutoff``'s diffraction
        (a burst's: measured by :func:`~hbis_torch.reconstruct.lens_blur.estimate_lens_sigma`
        in :func:`~hbis_torch.reconstruct.burst.reconstruct_burst`, or given); 0 or None: none.
    fit_holes : bool
        Nodes the splat leaves (almost) without a sample of their own are fitted to the samples
        around them (:func:`~hbis_torch.reconstruct.classical.lattice_fit.fill_holes_from_samples`).
    shared : dict, optional
        :func:`lattice_image`'s (a colour burst's channels: one call each, the same dict).
    target_aperture : float, optional
        :func:`~hbis_torch.reconstruct.classical.wiener.wiener_deblur`'s (None: ``sqrt(fill_factor)``).

    Returns
    -------
    Tensor, shape (h*H, h*W), float32 in [0, 1]
        Positions in float64 (on the lattice: each sample's node and its float32 offset from
        it), the per-node sums and the deblurring in float32 (tests/test_fullframe.py checks
        these against float64).
    """
    h = check_h(h)
    frames, positions, weights = _check_inputs(frames, positions, weights, fill_factor, kernel_sigma,
                                               cutoff, strength, noise, noise_floor)
    lens_sigma = 0.0 if lens_sigma is None else lens_sigma  # "auto": a burst's is measured before (reconstruct_burst)
    if not (isinstance(lens_sigma, (int, float)) and math.isfinite(lens_sigma) and 0 <= lens_sigma <= MAX_LENS_SIGMA):
        raise HbisInputError(f"the lens blur (--psf-sigma) must be a number in [0, {MAX_LENS_SIGMA}] LR px, "
                             f"got {lens_sigma!r}")
    image, den, offset, typical = lattice_image(frames, positions, h, kernel_sigma, weights, on_lattice=deblur,
                                                mixed_offsets=mixed_offsets, fit_holes=fit_holes, shared=shared)
    if deblur:
        # Samples that meet at a node (1 for an h x h scan): their noise averages down.
        samples_per_node = typical / max(_peak_weight(kernel_sigma), 1e-12)
        valid = torch.from_numpy(den.numpy() > 0.5 * typical)  # NumPy's comparison: a third of torch's time
        del den
        # The deblurring works in float32 (wiener_deblur), as does the lattice image: so does
        # the noise's median of second differences.
        if noise is None:
            node_noise = lattice_noise(image, kernel_sigma, valid)
            if noise_floor is not None:
                node_noise = max(node_noise, noise_floor / math.sqrt(max(samples_per_node, 1.0)))
        else:
            node_noise = noise / math.sqrt(max(samples_per_node, 1.0))
        if noise_params_out is not None:
            noise_params_out.append(lattice_noise_params(image, kernel_sigma, valid, samples_per_node))
        del valid
        image = wiener_deblur(image, h, offset, kernel_sigma, node_noise, math.sqrt(fill_factor),
                              cutoff, strength, overwrite=True, lens_sigma=lens_sigma,
                              fit_below=1.0 / h if mixed_offsets else None, target_aperture=target_aperture)
    if not _all_finite(image):  # finite samples never should give this: say so
        raise RuntimeError("the classical reconstruction produced non-finite values; please report "
                           "the stack that caused it")
    return image.clamp_(0, 1).to(torch.float32)


def _all_finite(values: Tensor) -> bool:
    """Whether every entry of a float tensor is finite: its sum is (a NaN or an infinity makes
    the sum one), unless finite values too large overflow it (then entry by entry). One pass
    without a boolean tensor of the values' size: a thirtieth of
    ``torch.isfinite(values).all()``'s time on a full frame."""
    return math.isfinite(float(values.sum())) or bool(torch.isfinite(values).all())


def _check_inputs(frames, positions, weights, fill_factor: float, kernel_sigma: float,
                  cutoff: float | None, strength: float, noise: float | None, noise_floor: float | None = None):
    """:func:`classical_sr`'s arguments checked (HbisInputError otherwise) and converted.

    Returns
    -------
    frames : Tensor, shape (F, H, W), float64 (float32 if given as a float32 tensor)
    positions : Tensor, shape (F, H, W, 2), float64, or NodePositions or BurstPositions (as given, checked)
    weights : Tensor, shape (F, H, W), float64 (float32 if given so), or None
        Per-frame weights expanded to every sample.
    """
    if isinstance(frames, Tensor) and frames.dtype == torch.float32:
        # float32 samples are exact enough, and half the memory: checked, not copied
        if not _all_finite(frames):
            raise HbisInputError("frames contain non-finite values (NaN or inf)")
    else:
        frames = as_float64_tensor(frames, "frames")
    if frames.ndim != 3 or min(frames.shape) < 1:
        raise HbisInputError(f"frames must have shape (F, H, W), got {tuple(frames.shape)}")
    F, H, W = frames.shape
    if isinstance(positions, NodePositions):
        shape = (positions.values.shape[0], positions.height, positions.width, 2)
        as_float64_tensor(positions.values, "positions")
    elif getattr(positions, "computed_where_read", False):  # a BurstPositions: a band at a time
        shape = positions.shape
    else:
        positions = as_float64_tensor(positions, "positions")
        shape = tuple(positions.shape)
    if shape != (F, H, W, 2):
        raise HbisInputError(f"positions must have shape {(F, H, W, 2)} to match the frames, got {shape}")
    if not 0 < fill_factor <= 1:
        raise HbisInputError(f"fill_factor must lie in (0, 1], got {fill_factor!r}")
    if not 0.2 <= kernel_sigma <= 0.6:
        raise HbisInputError(f"kernel_sigma must lie in [0.2, 0.6] HR px, got {kernel_sigma!r}")
    if cutoff is not None and not (math.isfinite(cutoff) and cutoff > 0):
        raise HbisInputError(f"cutoff must be a positive number (cycles per pixel), got {cutoff!r}")
    if not (math.isfinite(strength) and strength > 0):
        raise HbisInputError(f"strength must be a positive number, got {strength!r}")
    if weights is not None:
        if not (isinstance(weights, Tensor) and weights.dtype == torch.float32 and _all_finite(weights)):
            weights = as_float64_tensor(weights, "weights")  # float32 weights are read as they are
        if weights.shape == (F,):
            weights = weights[:, None, None].expand(F, H, W)
        if tuple(weights.shape) != (F, H, W) or float(weights.min()) < 0:
            raise HbisInputError(f"weights must be non-negative, shape ({F},) or {(F, H, W)}")
        if float(weights.max()) <= 0:
            raise HbisInputError("every sample has weight 0: nothing to reconstruct")
    for name, level in (("noise", noise), ("noise_floor", noise_floor)):
        if level is not None and not (math.isfinite(level) and level >= 0):
            raise HbisInputError(f"{name} must be a number >= 0, got {level!r}")
    return frames, positions, weights


def lattice_image(frames: Tensor, positions: Tensor, h: int, kernel_sigma: float,
                  weights: Tensor | None = None, on_lattice: bool = True, mixed_offsets: bool = False,
                  fit_holes: bool = False, shared: dict | None = None):
    """Interpolate scattered samples onto an h-times grid (normalized convolution).

    Parameters
    ----------
    frames : Tensor, shape (F, H, W), float64 or float32
    positions : Tensor, shape (F, H, W, 2), float64, or NodePositions or BurstPositions
        ROI-local reference LR coordinates of the samples (or the nodes they are interpolated
        from, a batch of frames at a time; or a burst's motions, applied a batch at a time).
    h : int
    kernel_sigma : float
    weights : Tensor, shape (F, H, W), optional
    on_lattice : bool
        Put the grid's nodes where the scan lattice puts the samples (the output grid shifted
        by the samples' common sub-pixel ``offset``) and move every sample onto its node
        (:func:`snap_to_lattice`), as the deblurring needs; False interpolates onto the output
        grid itself.
    mixed_offsets : bool
        Samples at different offsets share the nodes (a burst; :func:`snap_to_lattice`).
    fit_holes : bool
        With ``on_lattice``: the nodes the splat leaves (almost) without a sample of their own
        fitted to the samples around them
        (:func:`~hbis_torch.reconstruct.classical.lattice_fit.fill_holes_from_samples`).
    shared : dict, optional
        With ``on_lattice``: what depends on the samples' places and weights alone (the
        lattice's offset, the samples' nodes where the batches are kept, the fit's matrix), kept
        by the first call and read by the next, whose ``frames`` are other values of the same
        samples (a colour burst's channels: the same ``positions`` and ``weights``). The same
        bits as without it.

    Returns
    -------
    image, den : Tensor, shape (h*H, h*W)
        The interpolated image and the splat weights' sum at each node: float32 on the lattice
        (``on_lattice``), else float64.
    offset : (float, float)
        Where the nodes sit relative to the output pixels, HR px.
    typical : float
        The median of ``den`` over the nodes that received samples
        (:func:`~hbis_torch.reconstruct.classical.holes.typical_weight`).
    """
    F, H, W = frames.shape
    shape = (h * H, h * W)
    slices = batch_slices(F, H, W, BATCH_SAMPLES)
    if on_lattice:
        # The samples' common offset from a subset of the rows (OFFSET_ROW_STRIDE): fewer cosines
        # to take, and where there are several batches fewer positions to interpolate.
        row_step = OFFSET_ROW_STRIDE if H <= 512 else min(16, H // 64)
        cache = {} if shared is None else shared  # (a call alone keeps what it computes for itself)
        if "offset" not in cache:
            cache["offset"] = common_offset_of(positions, slices, h, weights, row_step, mixed_offsets)
        offset = cache["offset"]
        # With one batch (a stack of up to BATCH_SAMPLES samples, 16 frames of 256^2), or a burst
        # (two passes) of up to KEEP_SAMPLES, the batches are computed once for both passes.
        keep = len(slices) == 1 or (mixed_offsets and F * H * W <= KEEP_SAMPLES)
        kept = None
        if keep and "kept" in cache:  # the same samples' nodes, these values (as node_batch takes them)
            kept = [b._replace(values=frames[part].reshape(-1).to(torch.float32))
                    for b, part in zip(cache["kept"], slices)]
        elif keep:
            kept = cache["kept"] = [node_batch(frames, positions, part, h, offset, weights) for part in slices]

        def batches():
            return kept or (node_batch(frames, positions, part, h, offset, weights) for part in slices)

        # snap_to_lattice, then splat: the same sums, in batches of frames (or of rows)
        num, den, typical = splat_on_lattice(batches, shape, kernel_sigma, mixed_offsets)
        image = fill_holes(num, den, typical, in_place=True)
        if fit_holes:
            image = fill_holes_from_samples(image, den, typical, batches, kernel_sigma, shared)
        return image, den, offset, typical
    num = den = 0
    for part in slices:
        if isinstance(positions, NodePositions):
            where = interpolate_positions(positions._replace(values=positions.values[part[0]]),
                                          rows=np.arange(H)[part[1]])
        else:
            where = positions[part]
        x = (where[..., 0].reshape(-1) + 0.5).mul_(h).sub_(0.5)
        y = (where[..., 1].reshape(-1) + 0.5).mul_(h).sub_(0.5)
        w = None if weights is None else weights[part].reshape(-1)
        n, d = splat(frames[part].reshape(-1).to(torch.float64), x, y, shape, kernel_sigma, w)
        num, den = num + n, den + d
    typical = typical_weight(den)
    return fill_holes(num, den, typical), den, (0.0, 0.0), typical


def lattice_noise(image: Tensor, kernel_sigma: float, valid: Tensor | None = None) -> float:
    """Noise level of the samples from the interpolated image on their lattice.

    On the h-times lattice neighbouring nodes hold samples of different frames a fraction of a
    pixel apart, so the scene is far smoother there than in any single (aliased) frame, and
    Immerkaer's operator [[1,-2,1],[-2,4,-2],[1,-2,1]] (median form) sees little but noise. The
    splat's 3-tap smoothing changes the operator's noise gain from 6 to :func:`_lattice_gain`.

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        Normalized-convolution image with one sample per node.
    kernel_sigma : float
        The splat Gaussian (HR px).
    valid : Tensor of bool, shape (rows, cols), optional
        Nodes to use (those that received samples).

    A lattice of more than :data:`TILES_FROM` nodes is measured on the tiles that
    :func:`lattice_noise_params` reads (about :data:`NOISE_NODES` nodes spread over it).
    """
    if image.numel() > TILES_FROM:  # a full frame: tiles spread over it (10 times faster at h = 4)
        residual, _, where = _noise_sample(image, valid)
        where = np.ones(residual.shape, dtype=bool) if where is None else where
        return 1.4826 * lower_median(torch.from_numpy(residual), torch.from_numpy(where)) / _lattice_gain(
            kernel_sigma, image.dtype)
    out = median_subset(immerkaer(image).abs_())  # on a large lattice, one node in MEDIAN_STRIDE
    if valid is not None:
        inner = median_subset(_complete(valid))
        if int(inner.sum()) >= 16:  # else too few complete neighbourhoods: use every node
            return 1.4826 * lower_median(out, inner) / _lattice_gain(kernel_sigma, image.dtype)
    return 1.4826 * float(out.median()) / _lattice_gain(kernel_sigma, image.dtype)


# Nodes the noise parameters are measured on, at most (evenly spaced strips of rows; the fit
# takes a couple of hundred thousand of them)
NOISE_NODES = 400_000
# Lattices of more nodes than this (a 256 x 316 ROI at h = 4) have their noise level and noise
# model measured on tiles spread over the lattice (not on every other node of the whole image).
TILES_FROM = 4 * NOISE_NODES


def _noise_sample(image: Tensor, valid: Tensor | None):
    """Immerkaer's operator's magnitude, the nodes' level and (with ``valid``) whether their 3 x 3
    neighbourhood is complete, flat numpy arrays over the inner nodes of evenly spaced strips of
    rows that hold about :data:`NOISE_NODES` of them (the whole image if it is smaller). A
    lattice of more than :data:`TILES_FROM` nodes is read in a 7 x 7 grid of tiles of 34 x 258
    nodes spread over it instead: full-width strips there would be two or three, at the top and
    bottom. ``where`` is None without ``valid`` or with fewer than 16 complete neighbourhoods."""
    rows, cols = image.shape
    strip = min(rows, 34)  # 32 inner rows
    if image.numel() > TILES_FROM:
        width = min(cols, 258)
        side = math.ceil(math.sqrt(NOISE_NODES / ((strip - 2) * (width - 2))))
        tops = np.linspace(0, rows - strip, min(side, rows // strip)).round().astype(int)
        lefts = np.linspace(0, cols - width, min(side, cols // width)).round().astype(int)
        spans = [(r, c, width) for r in tops for c in lefts]
    else:
        count = max(1, min(rows // strip, math.ceil(NOISE_NODES / (max(strip - 2, 1) * max(cols - 2, 1)))))
        spans = [(r, 0, cols) for r in np.linspace(0, rows - strip, count).round().astype(int)]
    residual, level, where = [], [], []
    for r, c, width in spans:
        part = image[r:r + strip, c:c + width]
        residual.append(immerkaer(part).abs_().numpy().ravel())
        level.append(part[1:-1, 1:-1].numpy().ravel())
        if valid is not None:
            where.append(_complete(valid[r:r + strip, c:c + width]).numpy().ravel())
    where = np.concatenate(where) if valid is not None else None
    if where is not None and where.sum() < 16:  # too few complete neighbourhoods: every node
        where = None
    return np.concatenate(residual), np.concatenate(level), where


def lattice_noise_params(image: Tensor, kernel_sigma: float, valid: Tensor | None = None,
                         samples_per_node: float = 1.0) -> tuple[float, float]:
    """Poisson-Gaussian noise parameters of the frames, measured on their lattice.

    :func:`lattice_noise`'s operator, binned by the nodes' level and fitted by
    :func:`~hbis_torch.sensor.noise.fit_noise_params`: the variance ``a x + b`` of one
    sample of value x in [0, 1]. A single frame is aliased, and its fine detail passes for noise
    (:func:`~hbis_torch.reconstruct.learned.estimate_noise_params` overstates a low noise level
    several times on photographs); on the lattice it does not. Measured on strips of rows (tiles
    on a lattice of more than :data:`TILES_FROM` nodes) that hold about :data:`NOISE_NODES`
    nodes, whatever the image's size (:func:`_noise_sample`).

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        Normalized-convolution image on the lattice (:func:`lattice_image`), before deblurring.
    kernel_sigma : float
        The splat Gaussian (HR px).
    valid : Tensor of bool, shape (rows, cols), optional
        Nodes that received samples.
    samples_per_node : float
        Samples whose noise averages at a node (1 for an h x h scan): a sample's variance is
        the nodes' times this.

    Returns
    -------
    (a, b) : (float, float)
    """
    residual, level, where = _noise_sample(image, valid)
    a, b = fit_noise_params(residual, level, _lattice_gain(kernel_sigma, image.dtype), where)
    scale = max(samples_per_node, 1.0)
    return a * scale, b * scale


def _lattice_gain(kernel_sigma: float, dtype=torch.float32) -> float:
    """Immerkaer's operator's output level on the lattice image of white noise of level 1 (6
    without the splat's 3-tap smoothing)."""
    a = math.exp(-1 / (2 * kernel_sigma ** 2))
    taps = torch.tensor([1.0, -2.0, 1.0], dtype=dtype)
    smoothed = torch.nn.functional.conv1d(taps.view(1, 1, 3), torch.tensor([[[a, 1.0, a]]], dtype=dtype), padding=2)
    gain_1d = float(smoothed.norm()) / (1 + 2 * a)
    return gain_1d ** 2


def _complete(valid: Tensor) -> Tensor:
    """(rows - 2, cols - 2): the inner nodes all nine of whose 3 x 3 neighbours are ``valid``."""
    inner = valid[1:-1, 1:-1].clone()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= valid[1 + dy:valid.shape[0] - 1 + dy, 1 + dx:valid.shape[1] - 1 + dx]
    return inner


def _peak_weight(sigma: float) -> float:
    """Splat weight a node receives from a sample sitting on it plus its lattice neighbours."""
    d = torch.tensor([-1.0, 0.0, 1.0])
    g = torch.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma * sigma))
    return float(g.sum())

"""The learned method's inputs and glue around any runner of the network, on numpy arrays.

The network refines the classical image (see :mod:`hbis_torch.reconstruct.learned.network`), so its
inputs are defined by physics, not by the order of the frames: :func:`network_inputs` cuts the
classical image into the h^2 sub-pixel phases of the LR grid and adds the noise map, whose
Poisson-Gaussian parameters come from the stack's sensor model (:func:`noise_params_from_meta`)
or, when the stack does not say, from the frames (:func:`estimate_noise_params`).
:func:`run_tiled` runs any network function over overlapping tiles; :func:`super_resolve` chains
them around any runner of the network (the onnxruntime session of
:class:`~hbis_torch.reconstruct.learned.LearnedSR`, or eager torch in training and benchmarks).

Noise model: a frame value ``x`` in [0, 1] (1 = full scale) has variance ``a x + b``: ``a`` from
the shot noise (1 / full well in electrons), ``b`` from the read noise and the ADC's rounding.
"""

from __future__ import annotations

import math

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.sensor.noise import fit_noise_params, immerkaer

# Halo (LR pixels) around each tile where the network's receptive field is not known (run_tiled's
# default): wider than the shipped models' (10 LR pixels: head + 2 per block + tail), so that tiling
# does not change the result. A model's runner takes its architecture's halo instead
# (Architecture.halo, 11 for the shipped models), as exact and cheaper: with 16, the network took
# 0.985-1.04 s of a full frame at h = 4 (fp32, 2 cores) against 0.94-0.95 s, for the same bits.
TILE_HALO = 16
# Frames' noise levels are scaled by this before the network (its ``noise`` input,
# hbis_torch.reconstruct.learned.network); the training pipeline takes it from here.
NOISE_SCALE = 10.0


def noise_params_from_meta(meta: dict) -> tuple[float, float] | None:
    """Poisson-Gaussian noise parameters (a, b) of a stack from its sensor model, if it has one.

    Looks for ``full_well_e`` (and ``read_noise_e``, default 0) in the stack's ``sensor`` block,
    else in ``simulation.sensor`` (the simulator's record); ``bit_depth`` adds the ADC's rounding
    (1 DN^2 / 12).

    Parameters
    ----------
    meta : dict
        The stack's JSON metadata.

    Returns
    -------
    (a, b) : (float, float) or None
        Variance ``a x + b`` of a frame value x in [0, 1]; None when the stack has no sensor
        model.

    Raises
    ------
    HbisInputError
        A sensor block whose full well or read noise is not a positive finite number.
    """
    for block in (meta.get("sensor"), (meta.get("simulation") or {}).get("sensor")):
        if not isinstance(block, dict) or "full_well_e" not in block:
            continue
        full_well, read = block["full_well_e"], block.get("read_noise_e", 0.0)
        for name, value, least in (("full_well_e", full_well, 1.0), ("read_noise_e", read, 0.0)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < least:
                raise HbisInputError(f"the stack's sensor {name} must be a finite number >= {least:g}, got {value!r}")
        bits = meta.get("bit_depth")
        return sensor_noise_params(full_well, read, bits if isinstance(bits, int) and not isinstance(bits, bool)
                                   and bits > 0 else None)
    return None


def sensor_noise_params(full_well_e: float, read_noise_e: float, bit_depth: int | None = None) -> tuple[float, float]:
    """Poisson-Gaussian noise parameters (a, b) of a sensor: a = 1 / full well (shot noise),
    b = (read noise / full well)^2, plus the ADC's rounding (1 DN^2 / 12) for a ``bit_depth``."""
    b = (read_noise_e / full_well_e) ** 2
    if bit_depth is not None:
        b += 1.0 / (12.0 * (2**bit_depth - 1) ** 2)
    return 1.0 / full_well_e, b


def estimate_noise_params(frames) -> tuple[float, float]:
    """Poisson-Gaussian noise parameters (a, b) measured from the frames themselves.

    Immerkaer's operator (:func:`hbis_torch.sensor.noise.immerkaer`, which cancels smooth
    content; on white noise of level s its output has level 6 s) is taken at every pixel and
    fitted by :func:`~hbis_torch.sensor.noise.fit_noise_params`. A single frame is
    aliased, and its fine detail counts as noise: on photographs this overstates a low noise
    level several times (docs/learned.md). The learned method measures the noise on the
    classical method's lattice instead
    (:func:`~hbis_torch.reconstruct.classical.lattice_noise_params`), where the frames' samples
    interleave a fraction of a pixel apart; this estimate serves where there is no lattice (and
    as the training's second, pessimistic, noise model).

    Parameters
    ----------
    frames : array, shape (F, H, W)
        Frames in [0, 1], H and W at least 3.

    Returns
    -------
    (a, b) : (float, float)
    """
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 3 or min(frames.shape[1:]) < 3:
        raise HbisInputError(f"frames must have shape (F, H >= 3, W >= 3), got {frames.shape}")
    step = max(1, frames.shape[0] // 4)  # a few frames are plenty
    f = frames[::step]
    return fit_noise_params(np.abs(immerkaer(f)), f[..., 1:-1, 1:-1], 6.0)


def phase_planes(image: np.ndarray, h: int) -> np.ndarray:
    """(hH, hW) -> (h, h, H, W), a view (no copy): ``[dy, dx, y, x]`` is ``image[h y + dy, h x + dx]``."""
    rows, cols = image.shape[0] // h, image.shape[1] // h
    return image.reshape(rows, h, cols, h).transpose(1, 3, 0, 2)


def space_to_depth(image: np.ndarray, h: int) -> np.ndarray:
    """(hH, hW) -> (h^2, H, W): channel ``dy * h + dx`` holds ``image[h y + dy, h x + dx]``."""
    planes = np.ascontiguousarray(phase_planes(image, h))
    return planes.reshape(h * h, *planes.shape[2:])


def network_inputs(image, h: int, noise_params: tuple[float, float],
                   copy: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The network's inputs from the classical image and the frames' noise parameters.

    Parameters
    ----------
    image : array, shape (h H, h W)
        The classical reconstruction, in [0, 1].
    h : int
        Resolution improvement factor.
    noise_params : (float, float)
        (a, b) of the frames' noise variance ``a x + b``.
    copy : bool
        False: ``base`` is the (h, h, H, W) view of the image (:func:`phase_planes`), which
        :func:`run_tiled` copies a tile at a time: no second image-sized array (240 MB for a
        full frame at h = 7).

    Returns
    -------
    base : ndarray, shape (h^2, H, W) (``copy``) or (h, h, H, W) (a view), float32
        The image, space-to-depth.
    noise : ndarray, shape (1, H, W), float32
        ``NOISE_SCALE`` times the frames' noise level at each LR pixel's mean intensity.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2 or image.shape[0] % h or image.shape[1] % h or min(image.shape) < h:
        raise HbisInputError(f"the classical image must be (h H, h W) with h = {h}, got {image.shape}")
    a, b = (float(v) for v in noise_params)
    if not (math.isfinite(a) and math.isfinite(b) and a >= 0 and b >= 0):
        raise HbisInputError(f"noise parameters must be finite and >= 0, got {noise_params!r}")
    planes = phase_planes(image, h)
    # each LR pixel's mean over its h^2 phases, summed a phase at a time (numpy's mean over the
    # two strided axes at once is 10 times slower, and this is its value over channels)
    level = planes[0, 0].copy()
    for phase in range(1, h * h):
        level += planes[phase // h, phase % h]
    level = np.clip(level / np.float32(h * h), 0.0, 1.0)
    noise = (NOISE_SCALE * np.sqrt(a * level + b))[None].astype(np.float32)
    return (space_to_depth(image, h) if copy else planes), noise


def run_tiled(infer, base: np.ndarray, noise: np.ndarray, h: int, tile: int = 256,
              halo: int = TILE_HALO) -> np.ndarray:
    """Run ``infer`` over overlapping tiles and stitch the centres.

    Parameters
    ----------
    infer : callable
        (1, h^2, h_t, w_t), (1, 1, h_t, w_t) float32 arrays -> (1, 1, h h_t, h w_t).
    base, noise : ndarray, shapes (h^2, H, W) or (h, h, H, W) (:func:`phase_planes`), and (1, H, W)
    h, tile, halo : int
        Factor, tile side and halo in LR pixels; a halo wider than the network's receptive field
        radius makes the result independent of the tiling.

    Returns
    -------
    ndarray, shape (hH, hW), float32
    """
    rows, cols = base.shape[-2:]

    def batch(array, ya, yb, xa, xb):  # (1, C, yb - ya, xb - xa), contiguous
        return np.ascontiguousarray(array[..., ya:yb, xa:xb]).reshape(1, -1, yb - ya, xb - xa)

    if rows <= tile and cols <= tile:  # one tile: no halo, no stitching
        return infer(batch(base, 0, rows, 0, cols), batch(noise, 0, rows, 0, cols))[0, 0]
    out = np.empty((h * rows, h * cols), np.float32)
    for y0 in range(0, rows, tile):
        for x0 in range(0, cols, tile):
            y1, x1 = min(y0 + tile, rows), min(x0 + tile, cols)
            ya, xa = max(y0 - halo, 0), max(x0 - halo, 0)
            yb, xb = min(y1 + halo, rows), min(x1 + halo, cols)
            image = infer(batch(base, ya, yb, xa, xb), batch(noise, ya, yb, xa, xb))[0, 0]
            out[h * y0:h * y1, h * x0:h * x1] = image[h * (y0 - ya):h * (y1 - ya), h * (x0 - xa):h * (x1 - xa)]
    return out


# The square's symmetries in the order a self-ensemble of 1, 2, 4 or 8 takes them: k < 4 is
# rot90 k times; k >= 4 is the transpose, then rot90 (k - 4) times.
ENSEMBLE_ORDER = (0, 4, 2, 6, 1, 5, 3, 7)
ENSEMBLE_SIZES = (1, 2, 4, 8)
# The self-ensemble the learned method uses unless told, per tier and h. Fast tier: 2 where the
# classical step takes most of the time, so that the second pass is cheap end to end at 128^2
# (benchmarks/bench_ensemble.py): at h = 7 9 % more time for +0.08 dB on the validation set, never
# less on any of its stacks (+0.10 dB on the held-out matrix; docs/learned.md); at h = 3 8 % more
# for +0.08 dB on the held-out photographs, the held-out matrix's worst cell rising from -0.41 to
# -0.35 dB. 1 at h = 2 and 4 (at h = 4 it would cost 14 %, past the margin of the speed goal at
# 256^2). Best tier: the user has chosen time for quality, and 2 symmetries at h = 2 and 4 add
# +0.09 / +0.08 dB on the held-out matrix (docs/learned.md, "Two tiers"); all 8 at h = 7, chosen
# on the validation matrix (the training's photographs, eval_matrix.py --photos brick grass gravel
# moon coins): against 2 symmetries its mean rises from +1.74 to +1.86 dB and its worst cell (grass,
# low noise without blur) from -0.21 to -0.10 dB (4: +1.83 and -0.14), at four times the network's cost.
DEFAULT_ENSEMBLE = {"fast": {3: 2, 7: 2}, "best": {2: 2, 4: 2, 7: 8}}


def default_ensemble(h: int, tier: str | None = "fast") -> int:
    """The self-ensemble size the learned method uses at ``h`` unless told (:data:`DEFAULT_ENSEMBLE`);
    ``tier`` "fast" or "best" (None, a model file of no tier: as "fast")."""
    return DEFAULT_ENSEMBLE[tier or "fast"].get(int(h), 1)


def _transform_phases(phases: np.ndarray, k: int) -> np.ndarray:
    """Symmetry ``k`` of the image behind ``phases`` (h, h, H, W), on the phases themselves.

    Axis order (dy, dx, y, x): the image's row is ``h y + dy`` and its column ``h x + dx``, so
    transposing the image swaps (dy, dx) and (y, x), and flipping its rows flips dy and y.
    """
    if k >= 4:
        phases = phases.transpose(1, 0, 3, 2)
    for _ in range(k % 4):  # np.rot90: the transpose, then the rows reversed
        phases = phases.transpose(1, 0, 3, 2)[::-1, :, ::-1, :]
    return phases


def _transform_image(image: np.ndarray, k: int) -> np.ndarray:
    return np.rot90(image.T if k >= 4 else image, k % 4)


def _untransform_image(image: np.ndarray, k: int) -> np.ndarray:
    image = np.rot90(image, -(k % 4))
    return image.T if k >= 4 else image


def check_ensemble(count, h: int | None = None, tier: str | None = "fast") -> int:
    """``count`` if it is a self-ensemble size (:data:`ENSEMBLE_SIZES`), else one clear error;
    None is :func:`default_ensemble` of ``h`` and ``tier`` (1 without an ``h``)."""
    if count is None:
        return default_ensemble(h, tier) if h is not None else 1
    if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count not in ENSEMBLE_SIZES:
        raise HbisInputError(f"ensemble must be one of {', '.join(map(str, ENSEMBLE_SIZES))}, got {count!r}")
    return int(count)


def _mean_over_symmetries(run_network, phases: np.ndarray, noise: np.ndarray, h: int, count: int,
                          views: bool) -> np.ndarray:
    """The mean of ``run_network`` over the first ``count`` symmetries of :data:`ENSEMBLE_ORDER`.

    ``phases`` (h, h, H, W) and ``noise`` (H, W) are the input; ``run_network`` takes base
    (h^2, H', W') (a strided (h, h, H', W') view where ``views``) and noise (1, H', W') and returns
    (hH', hW'). Returns a new (hH, hW) float32 array, summed in the order of the symmetries."""
    total = None
    for k in ENSEMBLE_ORDER[:count]:
        b = _transform_phases(phases, k)
        if not views:
            b = np.ascontiguousarray(b).reshape(h * h, *b.shape[2:])
        n = np.ascontiguousarray(_transform_image(noise, k))[None]
        out = _untransform_image(run_network(b, n), k)
        if total is None:
            total = np.array(out, dtype=np.float32)  # a new, C-ordered array
        else:
            total += out
        del b, n, out
    total /= np.float32(count)
    return total


def self_ensemble(run_network, h: int, count: int | None, views: bool = False):
    """``run_network`` averaged over ``count`` of the square's 8 symmetries (geometric self-ensemble).

    The network was trained under all 8 flips and transposes of its crops, so each symmetry gives
    an equally good estimate whose errors are partly independent; their mean is better than any
    one (``training/eval_matrix.py --ensemble N`` measures it), at ``count`` times the network's cost.

    Parameters
    ----------
    run_network : callable
        base (h^2, H, W), noise (1, H, W), float32 -> (hH, hW) float32.
    h : int
    count : {1, 2, 4, 8} or None
        How many symmetries (:data:`ENSEMBLE_ORDER`); 1 returns ``run_network`` itself. None:
        :func:`default_ensemble` of ``h``.
    views : bool
        ``run_network`` also takes base as a strided (h, h, H, W) view (as :func:`run_tiled`
        does): each symmetry's base is then a view of the input, not a copy.

    Returns
    -------
    callable
        With the signature of ``run_network``.

    See Also
    --------
    tile_ensemble : the same mean, a tile at a time (what :class:`~hbis_torch.reconstruct.learned.LearnedSR` runs).
    """
    count = check_ensemble(count, h)
    if count == 1:
        return run_network

    def run(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return _mean_over_symmetries(run_network, base.reshape(h, h, *base.shape[-2:]), noise[0], h, count, views)

    return run


def tile_ensemble(infer, h: int, count: int | None):
    """``infer`` averaged over ``count`` of the square's symmetries, one tile at a time.

    :func:`self_ensemble` of a tile: given to :func:`run_tiled`, it gives what
    :func:`self_ensemble` of the tiled network gives (the network is translation-equivariant and
    each tile's halo spans its receptive field), but each symmetry moves a tile, not the whole
    image: a full frame at h = 7 is 240 MB, which the image-wide mean transposed once per
    symmetry and held twice.

    Parameters
    ----------
    infer : callable
        (1, h^2, H, W), (1, 1, H, W) float32 arrays -> (1, 1, hH, hW), one network pass.
    h : int
    count : {1, 2, 4, 8} or None
        As :func:`self_ensemble`'s.

    Returns
    -------
    callable
        With the signature of ``infer``.
    """
    count = check_ensemble(count, h)
    if count == 1:
        return infer

    def run_one(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return infer(base.reshape(1, *base.shape), noise[None])[0, 0]

    def run(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        phases = base.reshape(h, h, *base.shape[-2:])
        return _mean_over_symmetries(run_one, phases, noise[0, 0], h, count, views=False)[None, None]

    return run


def band_limit(correction: np.ndarray, h: int, cutoff: float | None) -> np.ndarray:
    """The correction without what lies beyond the lens's diffraction cutoff, in place.

    An incoherent lens passes no spatial frequency above ``1 / (lambda F)``, so neither the scene
    on the sensor nor the ground truth (which carries the lens's blur) has any: whatever the
    network adds there is error. A raised-cosine taper from 0.85 to 1 times the cutoff avoids
    ringing. Nothing changes when the cutoff lies beyond the output grid's corner frequency
    (F 1.4 at 3.75 um pixels: 4.9 cycles per LR pixel, beyond h / sqrt(2) for h <= 6).

    Parameters
    ----------
    correction : ndarray, shape (hH, hW), float32
        Network output minus the classical image; overwritten with the result.
    h : int
    cutoff : float or None
        Cutoff in cycles per LR pixel (:func:`hbis_torch.reconstruct.classical.optics_cutoff`);
        None: no limit.

    Returns
    -------
    ndarray, shape (hH, hW), float32
        ``correction`` itself.
    """
    if cutoff is None or cutoff >= h / np.sqrt(2.0):
        return correction
    import scipy.fft

    if correction.dtype != np.float32 or not correction.flags.writeable:
        raise HbisInputError("band_limit needs a writeable float32 array")
    rows, cols = correction.shape
    fy2 = (np.fft.fftfreq(rows) * h)[:, None] ** 2  # cycles per LR pixel, squared
    fx = np.fft.rfftfreq(cols) * h
    fy2_32, fx2_32 = fy2.astype(np.float32), (fx ** 2).astype(np.float32)
    # Only columns of the half spectrum that reach beyond 0.85 times the cutoff change (at h = 7
    # and F 1.4 a third of them): the correction gains irfft2((taper - 1) x spectrum) there.
    # float32 FFTs on every core, one axis at a time, a band of rows or columns at a time:
    # besides the correction, only those columns' spectrum is held.
    reaching = np.nonzero(np.sqrt(fx ** 2 + fy2.max()) > 0.85 * cutoff)[0]
    if len(reaching) == 0:
        return correction
    first, band = int(reaching[0]), 256
    spectrum = np.empty((rows, len(fx) - first), np.complex64)
    for r0 in range(0, rows, band):
        spectrum[r0:r0 + band] = scipy.fft.rfft(correction[r0:r0 + band], axis=1, workers=-1)[:, first:]
    for c0 in range(0, spectrum.shape[1], band):
        block = scipy.fft.fft(spectrum[:, c0:c0 + band], axis=0, workers=-1)
        # the taper's phase, pi t, t = (radius / cutoff - 0.85) / 0.15 in [0, 1], in float32
        # (its 1e-7 rounding is far below the correction's): with the taper in float64 the step
        # took 0.92-1.08 s on a 6720 x 8960 correction, in float32 0.68-0.75 s
        t = np.sqrt(fy2_32 + fx2_32[None, first + c0:first + c0 + band])
        t *= np.float32(np.pi / (0.15 * cutoff))
        t -= np.float32(np.pi * 0.85 / 0.15)
        np.clip(t, np.float32(0.0), np.float32(np.pi), out=t)
        np.cos(t, out=t)
        t -= np.float32(1.0)
        t *= np.float32(0.5)
        block *= t  # the taper, less 1
        spectrum[:, c0:c0 + band] = scipy.fft.ifft(block, axis=0, overwrite_x=True, workers=-1)
    full = np.zeros((min(band, rows), len(fx)), np.complex64)
    for r0 in range(0, rows, band):
        part = full[:min(band, rows - r0)]
        part[:, first:] = spectrum[r0:r0 + band]
        correction[r0:r0 + band] += scipy.fft.irfft(part, n=cols, axis=1, workers=-1)
    return correction


def super_resolve(run_network, image, h: int, noise_params: tuple[float, float],
                  name: str = "the network", cutoff: float | None = None, ensemble: int | None = 1,
                  views: bool = False) -> np.ndarray:
    """Classical image and noise parameters -> refined image, around any runner of the network.

    Parameters
    ----------
    run_network : callable
        base (h^2, H, W), noise (1, H, W), float32 -> (hH, hW) float32, the raw network output,
        a new array (it is clipped in place).
    image : array, shape (hH, hW)
        The classical reconstruction.
    h : int
    noise_params : (float, float)
        (a, b) of the frames' noise (:func:`noise_params_from_meta`, :func:`estimate_noise_params`).
    name : str
        How the error message names the model.
    cutoff : float, optional
        The lens's diffraction cutoff, cycles per LR pixel: the network's correction is limited
        to it (:func:`band_limit`).
    ensemble : {1, 2, 4, 8} or None
        Average the network over this many of the square's symmetries (:func:`self_ensemble`);
        None: :func:`default_ensemble` of ``h``.
    views : bool
        ``run_network`` also takes base as the (h, h, H, W) view of the image
        (:func:`phase_planes`), as :func:`run_tiled` and
        :meth:`~hbis_torch.reconstruct.learned.LearnedSR.run_network` do: then no image-sized
        copy of it is made (240 MB for a full frame at h = 7).

    Returns
    -------
    ndarray, shape (hH, hW), float32 in [0, 1]
    """
    run_network = self_ensemble(run_network, h, ensemble, views)  # checks ``ensemble`` before any work
    base, noise = network_inputs(image, h, noise_params, copy=not views)
    out = run_network(base, noise)
    del base, noise
    # A model is a function of float32 inputs in [0, 1]; anything non-finite here is a bug
    # in the model file, not in the stack.
    if not np.isfinite(out).all():
        raise HbisInputError(f"model {name} produced non-finite values")
    if cutoff is not None and cutoff < h / np.sqrt(2.0):
        image = np.asarray(image, dtype=np.float32)
        out -= image  # the correction, band-limited in place
        band_limit(out, h, cutoff)
        out += image
    return np.clip(out, 0.0, 1.0, out=out)

"""Raw bursts: joint demosaicking and super-resolution of Bayer frames with measured motion.

No frame is ever demosaicked (Wronski et al., SIGGRAPH 2019 [1]_): every frame's samples of one
colour are placed where the frame's motion puts them on the reference's grid, and each colour's
plane of the output, S times finer (S = 1: a burst demosaick), is the normalised-convolution
interpolation of that colour's samples from every frame (green; then red and blue as green plus
the interpolation of their samples' differences from green, which are smoother than the colours
themselves: :func:`joint_demosaick_sr`): the classical method's splat and hole filling
(:mod:`hbis_torch.reconstruct.classical.raw_splat`: :func:`~hbis_torch.reconstruct.classical.classical_sr`
without its Wiener step, as for raw Bayer scans,
:func:`~hbis_torch.reconstruct.classical.method.reconstruct_classical_raw_bayer`), on each
colour's samples alone.

Green then goes through the classical burst path's Wiener deblurring of the pixel area where its
samples fill the output grid (:func:`sharp_green`), and red and blue move with it. In noisy frames
red and blue's differences from green go through a guided filter with the sharpened green the
guide (:func:`~hbis_torch.reconstruct.classical.raw_splat.guided_difference`): in dim light a
node's difference rests on a sample or two and is mostly noise.

Per sample, the weight is

* the robustness weight of :func:`hbis_torch.reconstruct.burst.robustness_weights`, computed on
  the luminance of each 2 x 2 cell after a generalised Anscombe transform with the raw noise
  model (:func:`stabilise`), so that one noise level holds in shadows and highlights alike; a
  cell's weight goes to its four samples;
* 0 for a clipped sample (at the white level): a clipped sample says only "at least this", so it
  never pulls its colour; where a colour has (almost) only clipped samples nearby, that colour is
  set to the clip level (:func:`joint_demosaick_sr`);
* 0 for the frames the registration did not trust.

The raw noise (variance ``S x + O`` of a normalised sample x, per colour) is the DNG's
NoiseProfile where the files have one, else measured on the reference frame's four colour planes
(:func:`estimate_noise`). It sets the robustness transform, the splat's width
(:func:`kernel_for_noise`) and the guided filter's share (:func:`chroma_for_noise`), and is reported.

The output is the camera's linear RGB (not white-balanced; 1 = the white level),
(S H, S W, 3) float32; :func:`hbis_torch.reconstruct.raw_output.camera_to_srgb` applies the white
balance and colour matrix, and :func:`hbis_torch.reconstruct.raw_output.write_raw_outputs` writes
a linear 16-bit TIFF, an sRGB preview PNG and, for ``.dng``, a linear DNG through pidng.

References
----------
.. [1] B. Wronski et al., "Handheld multi-frame super-resolution", ACM Transactions on Graphics
   38(4), SIGGRAPH 2019.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import torch
from torch import Tensor

from hbis_torch.capture.raw import centre_cells
from hbis_torch.capture.sharpness import blurred_frames
from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act
from hbis_torch.reconstruct.burst_fill import still_run_scale
from hbis_torch.reconstruct.classical.raw_splat import (
    PlanePositions,
    Splat,
    bands,
    guided_difference,
    plane_from_sums,
    sample_weights_of_colour,
)
from hbis_torch.reconstruct.single_frame import enlarge

KERNEL_SIGMA = 0.5  # joint_demosaick_sr's default
# The splat's width follows the noise (kernel_for_noise): SHARP_SIGMA at a noise of SHARP_NOISE
# (of a normalised green sample at x = 0.2) and below, SMOOTH_SIGMA from SMOOTH_NOISE up, log-linear
# between. Chosen by hand on simulated bursts of astronaut and coffee (GRBG, seed 3), where the narrow
# kernel won in bright light (20,000 e-) and the wide one in dim light (300 e-); the held-out matrix
# (training/eval_raw.py) scores other photographs and seeds.
SHARP_SIGMA, SMOOTH_SIGMA = 0.35, 0.5
SHARP_NOISE, SMOOTH_NOISE = 0.003, 0.03
# Red and blue's differences from green go through a guided filter (raw_splat.guided_difference)
# where they are noisy: with a strength log-linear from none at CHROMA_NOISE to whole at
# CHROMA_FULL of their noise at an output node (chroma_for_noise), CHROMA_EPS its regularisation
# (a variance of normalised green). Chosen on simulated bursts of astronaut and coffee (S = 2 and
# S = 1, four patterns, two seeds, five light levels from 20,000 to 100 e-), against a Gaussian
# blur of the differences with a width that grew with the noise (the filter gained more in dim
# light and lost less in better light); held out as above.
CHROMA_NOISE, CHROMA_FULL, CHROMA_EPS = 0.023, 0.046, 1e-4
# Green goes through the Wiener deblurring where its samples of weight above 0.5 number at least
# this many per output pixel (a lattice left half empty loses more to deblurring than it gains:
# docs/real-bursts.md, the few-frame case).
DEBLUR_SAMPLES_PER_NODE = 1.0
# The share of a colour plane's pixels (the flattest) the noise is measured on.
FLAT_SHARE = 0.2


def is_raw_burst_stack(stack) -> bool:
    """Whether a stack is a raw burst (``hbis assemble --burst`` of raw files)."""
    return getattr(stack, "kind", "hbis") == "burst" and stack.meta.get("cfa") is not None \
        and isinstance(stack.meta.get("raw"), dict)


def estimate_noise(values: np.ndarray, cfa: str) -> np.ndarray:
    """Shot and read noise of one normalised mosaic, per colour: variance ``S x + O``.

    Each colour's plane (every other row and column) is taken alone; Immerkaer's operator (its
    output's standard deviation is 6 times the noise on smooth content), on the flattest fifth of
    the plane, is binned by the local mean (3 x 3), the median absolute value of each bin gives
    its noise, and a line is fitted to the variances (least squares, both terms at least 0).

    Parameters
    ----------
    values : np.ndarray, shape (H, W), float
        Normalised samples of one frame.
    cfa : str

    Returns
    -------
    np.ndarray, shape (3, 2): (S, O) for R, G, B
    """
    from scipy.ndimage import uniform_filter

    from hbis_torch.sensor.noise import immerkaer

    fits = {}
    planes: dict[str, list] = {"R": [], "G": [], "B": []}
    for k, colour in enumerate(cfa):
        planes[colour].append(np.asarray(values[k // 2::2, k % 2::2], dtype=np.float64))
    for colour, parts in planes.items():
        levels, noise = [], []
        for plane in parts:
            if min(plane.shape) < 5:
                continue
            residual = immerkaer(plane) / 6.0
            mean = uniform_filter(plane, 3)[1:-1, 1:-1]
            # the flattest fifth of the plane (smallest local spread of a 5 x 5 smoothing): a
            # colour plane is aliased, and texture would pass for noise
            smooth = uniform_filter(plane, 5)
            spread = np.sqrt(np.maximum(uniform_filter(smooth * smooth, 5) - uniform_filter(smooth, 5) ** 2, 0))
            flat = spread[1:-1, 1:-1] <= np.quantile(spread, FLAT_SHARE)
            levels.append(mean[flat])
            noise.append(residual[flat])
        if not levels:
            fits[colour] = (0.0, 1e-6)
            continue
        level, residual = np.concatenate(levels), np.concatenate(noise)
        edges = np.quantile(level, np.linspace(0, 1, 9))
        xs, vs = [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            inside = (level >= lo) & (level <= hi)
            if inside.sum() < 16:
                continue
            xs.append(float(np.median(level[inside])))
            vs.append((1.4826 * float(np.median(np.abs(residual[inside])))) ** 2)
        xs, vs = np.asarray(xs), np.asarray(vs)
        if len(xs) < 2 or np.ptp(xs) < 1e-6:
            fits[colour] = (0.0, float(np.median(vs)) if len(vs) else 1e-6)
            continue
        slope, offset = np.polyfit(xs, vs, 1)
        if offset < 0:
            slope, offset = max(float(np.sum(xs * vs) / np.sum(xs * xs)), 0.0), 0.0
        elif slope < 0:
            slope, offset = 0.0, float(np.mean(vs))
        fits[colour] = (float(slope), float(max(offset, 1e-10)))
    return np.array([fits[c] for c in "RGB"], dtype=np.float64)


def stabilise(grey: np.ndarray, noise: np.ndarray, balance) -> np.ndarray:
    """The generalised Anscombe transform of cell luminances, with the raw noise model: their noise
    becomes (about) 1 at every level.

    A cell's luminance is the mean of its four white-balanced samples (R, G, G, B), so its
    variance is ``a L + b`` with ``a = sum(wb_c S_c) / 16`` and ``b = sum(wb_c^2 O_c) / 16`` (a
    grey scene's samples are ``L / wb_c``).

    Parameters
    ----------
    grey : np.ndarray, shape (F, h, w)
        Cell luminances (:func:`hbis_torch.capture.raw.cell_luminance`).
    noise : np.ndarray, shape (3, 2)
    balance : sequence of 3 floats

    Returns
    -------
    np.ndarray, shape (F, h, w), float32
    """
    wb = np.asarray(balance, dtype=np.float64)
    count = np.array([1.0, 2.0, 1.0])
    a = float(np.sum(count * wb * noise[:, 0]) / 16)
    b = float(np.sum(count * wb * wb * noise[:, 1]) / 16)
    if a <= 1e-12:
        return (grey / np.sqrt(max(b, 1e-12))).astype(np.float32)
    return (2.0 / a * np.sqrt(np.maximum(a * grey + 0.375 * a * a + b, 0.0))).astype(np.float32)


def kernel_for_noise(noise: np.ndarray) -> float:
    """The splat's Gaussian (output px) for the raw noise (3, 2): narrow where the samples are
    clean, wide where they are noisy (the constants above, log-linear between)."""
    t = _log_share(_green_noise(noise), SHARP_NOISE, SMOOTH_NOISE)
    return float(SHARP_SIGMA + t * (SMOOTH_SIGMA - SHARP_SIGMA))


def chroma_for_noise(noise: np.ndarray, scale: int, frames: int) -> float:
    """How much of the guided filter red and blue's differences from green take (0 to 1) for the
    raw noise (3, 2) at S = ``scale`` with ``frames`` trusted frames: none where they are clean,
    all where they are noisy (the constants above). The measure is a green sample's noise at
    x = 0.2 over the square root of the samples of one colour an output node gets
    (``frames / (4 S^2)``: red and blue have a quarter of each frame's samples), so that more
    frames or a smaller S smooth less."""
    per_node = _green_noise(noise) * np.sqrt(4 * scale * scale / max(frames, 1))
    return _log_share(per_node, CHROMA_NOISE, CHROMA_FULL)


def _green_noise(noise: np.ndarray) -> float:
    """A green sample's noise standard deviation at x = 0.2 of the white level, of the raw noise
    (3, 2) (variance ``S x + O`` per colour)."""
    return float(np.sqrt(max(noise[1, 0] * 0.2 + noise[1, 1], 1e-12)))


def _log_share(value: float, low: float, high: float) -> float:
    """0 at ``low`` and below, 1 at ``high`` and above, log-linear between."""
    return float(np.clip(np.log(value / low) / np.log(high / low), 0, 1))


def _lazy_positions(motions: np.ndarray, height: int, width: int, local: dict | None = None, keep: bool = True):
    """Every pixel (u, v) of every frame moved by its homography, plus the local shifts there
    (``local``: a stack's ``local_motion``, :mod:`hbis_torch.registration.local`), computed where
    they are read (:class:`~hbis_torch.reconstruct.positions.BurstPositions`, ``keep`` as its:
    ``[k]`` frame k's (H, W, 2), ``[frames, rows, cols]`` a band's, float64): 16 bytes a sample held
    whole would be 3 GB for 16 frames of 12 MP."""
    from hbis_torch.reconstruct.positions import BurstPositions

    if local is None:
        return BurstPositions(motions, height, width, keep=keep)
    offsets = torch.as_tensor(np.asarray(local["offsets"], dtype=np.float64))
    return BurstPositions(motions, height, width, offsets, int(local["tile_px"]), keep=keep)


def _positions(motions: np.ndarray, height: int, width: int, local: dict | None = None) -> Tensor:
    """:func:`_lazy_positions` held whole, (F, H, W, 2) float64."""
    return _lazy_positions(motions, height, width, local).whole()


def _cell_local(local: dict | None) -> dict | None:
    """A stack's ``local_motion`` (pixels) on the 2 x 2 cells' grid: shifts and tiles halved."""
    if local is None:
        return None
    return {"tile_px": int(local["tile_px"]) // 2, "offsets": np.asarray(local["offsets"], dtype=np.float64) / 2}


def sample_weights(values: np.ndarray, cfa: str, motions: np.ndarray, trusted: np.ndarray, reference: int,
                   balance, noise: np.ndarray, robust: bool = True, local: dict | None = None,
                   cells: bool = False) -> Tensor:
    """The robustness weight of every sample (module docstring), (F, H, W) float64, or with
    ``cells`` of every 2 x 2 cell (F, H / 2, W / 2) float32 (the same values: a cell's weight
    goes to its four samples; a quarter of the memory in float32, an eighth of float64's).

    Parameters
    ----------
    values : np.ndarray, shape (F, H, W), float32
        Normalised samples; H, W even.
    cfa : str
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px (full resolution).
    trusted : np.ndarray, shape (F,), bool
    reference : int
    balance : sequence of 3 floats
    noise : np.ndarray, shape (3, 2)
    robust : bool
        False: every trusted sample gets 1 (for comparisons).
    local : dict, optional
        The stack's ``local_motion`` (pixels), if any.
    cells : bool
        Return the cells' weights.
    """
    from hbis_torch.capture.raw import cell_luminance
    from hbis_torch.registration.pyramid import to_level
    from hbis_torch.reconstruct.burst import robustness_weights

    F, H, W = values.shape
    trusted_t = torch.as_tensor(np.asarray(trusted, dtype=bool))
    if not robust:
        if cells:
            return trusted_t[:, None, None].to(torch.float32).expand(F, H // 2, W // 2).clone()
        return trusted_t[:, None, None].to(torch.float64).expand(F, H, W).clone()
    grey = np.empty((F, H // 2, W // 2), dtype=np.float32)
    for k in range(F):  # a frame at a time: the transform's float64 temporaries stay a frame's
        grey[k] = stabilise(cell_luminance(values[k:k + 1], cfa, balance), noise, balance)[0]
    cell_positions = _lazy_positions(to_level(motions, 1), H // 2, W // 2, _cell_local(local))
    weights = robustness_weights(torch.from_numpy(grey), cell_positions, trusted_t, reference)
    if cells:
        return weights
    return weights.double().repeat_interleave(2, 1).repeat_interleave(2, 2)


def _bilinear(image: Tensor, positions: Tensor, scale: int) -> Tensor:
    """Values of an output-grid image (S H, S W) at sample positions (..., 2) in reference LR px
    (bilinear, border-clamped, as ``grid_sample`` with ``align_corners`` and border padding), in
    the image's dtype: the coordinates in float64, the four values gathered and blended (no
    copy of the image, which at S = 2 of 12 MP frames is 48 million values)."""
    rows, cols = image.shape
    flat = image.reshape(-1)
    x = ((positions[..., 0] + 0.5) * scale - 0.5).clamp_(0, cols - 1)
    y = ((positions[..., 1] + 0.5) * scale - 0.5).clamp_(0, rows - 1)
    x0, y0 = x.floor().clamp_(max=max(cols - 2, 0)), y.floor().clamp_(max=max(rows - 2, 0))
    fx, fy = (x - x0).to(image.dtype), (y - y0).to(image.dtype)
    i00 = (y0 * cols + x0).to(torch.int64)
    step_x, step_y = int(cols > 1), cols * int(rows > 1)
    top = torch.lerp(flat[i00], flat[i00 + step_x], fx)
    bottom = torch.lerp(flat[i00 + step_y], flat[i00 + step_y + step_x], fx)
    return torch.lerp(top, bottom, fy)


def sharp_green(data: Tensor, half, w: Tensor, scale: int, kernel_sigma: float) -> np.ndarray | None:
    """The green plane through the classical burst path with its Wiener deblurring
    (:func:`~hbis_torch.reconstruct.classical.burst.burst_sr`), or None where the green samples
    are too few for it (fewer than :data:`DEBLUR_SAMPLES_PER_NODE` of weight above 0.5 per
    output pixel).

    The green samples of each pattern position form a grid of half the frames' size, pitch 2 px:
    they go to ``burst_sr`` as frames of that grid (positions in its pixels, scale 2 S, so that
    its output is the S-times grid of the full frames), with a fill factor of 1/4 (the pixel is
    1 px of the 2 px pitch).

    Parameters
    ----------
    data : Tensor, shape (2 F, H / 2, W / 2), float32
        The green samples, frame ``p F + k`` frame k's at green pattern position p.
    half : PlanePositions
        Their positions in the half-size grid's pixels, computed where read.
    w : Tensor, shape (2 F, H / 2, W / 2), float32
        Their weights, 0 for clipped samples.
    scale : int
    kernel_sigma : float

    Returns
    -------
    np.ndarray, shape (S H, S W), float32, or None
    """
    from hbis_torch.reconstruct.classical.burst import burst_sr

    _, h, w_ = data.shape
    if float((w > 0.5).sum()) < DEBLUR_SAMPLES_PER_NODE * scale * scale * 4 * h * w_:
        return None
    # (not the grey path's fit of the lattice's holes: chosen for full frames, never for this
    # lattice; on the held-out raw matrices at S = 2 it gained +0.06 dB on the mean with shifts,
    # lost 0.04 with hand-held motions, and cost one cell there 1.3 dB, below bicubic)
    return burst_sr(data, half, 2 * scale, w, True, fill_factor=0.25, fit_holes=False,
                    kernel_sigma=min(max(kernel_sigma, 0.2), 0.6)).numpy()


def joint_demosaick_sr(values: np.ndarray, clipped: np.ndarray, cfa: str, motions: np.ndarray, scale: int,
                       weights: Tensor, kernel_sigma: float = KERNEL_SIGMA, differences: bool = True,
                       deblur: bool = True, local: dict | None = None, chroma: float = 0.0,
                       sensor: Tensor | None = None) -> np.ndarray:
    """Each colour's plane from its own samples of every frame (module docstring).

    Green first; then, with ``differences``, red and blue as green plus the splat of their
    samples' differences from green (smoother than the colours: the splat blurs less of them);
    without, each plane alone. No array of every sample's position is made (:func:`_lazy_positions`;
    cell weights): 16 frames of 12 MP fit in memory as the grey path's do.

    Parameters
    ----------
    values : np.ndarray, shape (F, H, W), float32
        Normalised samples (the reference's exposure).
    clipped : np.ndarray, shape (F, H, W), bool
    cfa : str
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px.
    scale : int
        S (1: a burst demosaick).
    weights : Tensor, shape (F, H, W) or (F, H / 2, W / 2)
        Per-sample weights in [0, 1] (:func:`sample_weights`), or per 2 x 2 cell (``cells=True``).
    kernel_sigma : float
        The splat Gaussian, output px (0.2 to 0.6).
    differences : bool
    deblur : bool
        Green through the Wiener deblurring (:func:`sharp_green`) where its samples suffice; red and
        blue follow it (green plus their differences).
    local : dict, optional
        The stack's ``local_motion`` (pixels), if any.
    chroma : float
        How much of the guided filter the differences take, the sharpened green the guide: 0 none,
        1 all (:func:`chroma_for_noise`, :func:`~.raw_splat.guided_difference`).
    sensor : Tensor, shape (H, W), float32, optional
        Each sensor pixel's weight in every frame: 0 at the stack's stuck pixels
        (:func:`~hbis_torch.reconstruct.burst.stuck_pixel_weights`).

    Returns
    -------
    np.ndarray, shape (S H, S W, 3), float32 in [0, 1]
        Camera RGB, linear; 1 at the clip level.
    """
    F, H, W = values.shape
    positions = _lazy_positions(motions, H, W, local)
    frames = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
    clipped_t = torch.from_numpy(np.asarray(clipped, dtype=bool))
    any_clipped = bool(clipped_t.any())
    weights = torch.as_tensor(weights)
    per_sample = tuple(weights.shape) == (F, H, W)
    colour_weights = partial(sample_weights_of_colour, weights if per_sample else None,
                             None if per_sample else weights.to(torch.float32), clipped_t if any_clipped else None,
                             sensor)

    def colour_samples(where, rows=slice(None)):
        parts = [frames[:, dv::2, du::2][:, rows] for dv, du in where]
        return torch.cat(parts) if len(parts) > 1 else parts[0]

    out = (scale * H, scale * W)
    planes = {}
    sharp = change = None
    for colour in "GRB":  # green first: red and blue are splatted as differences from it
        where = [(k // 2, k % 2) for k, c in enumerate(cfa) if c == colour]
        if colour == "G" and deblur:
            kept = colour_weights(where)
            if bool((kept > 0).any()):
                sharp = sharp_green(colour_samples(where).contiguous(), PlanePositions(positions, where),
                                     kept.contiguous(), scale, kernel_sigma)
            del kept
        some_lost = any_clipped and any(bool(clipped_t[:, dv::2, du::2].any()) for dv, du in where)
        at = PlanePositions(positions, where, half=False)
        acc = Splat(out, kernel_sigma)
        lost_acc = Splat(out, kernel_sigma, count=1) if some_lost else None  # the clipped samples' weights alone
        any_kept = False
        for band in bands(len(where) * F, H // 2, W // 2):  # a band of rows of every frame, its weights and samples
            kept = colour_weights(where, band)
            any_kept = any_kept or bool((kept > 0).any())
            where_band = at[:, band]  # (2F or F, r, W / 2, 2)
            x = (where_band[..., 0].reshape(-1) + 0.5).mul_(scale).sub_(0.5)
            y = (where_band[..., 1].reshape(-1) + 0.5).mul_(scale).sub_(0.5)
            v = colour_samples(where, band).reshape(-1)
            if colour != "G" and differences:
                v = v - _bilinear(planes["G"], where_band, scale).reshape(-1)
            acc.add(v, x, y, kept.reshape(-1))
            if lost_acc is not None:
                lost = colour_weights(where, band, "lost").reshape(-1)
                hit = lost > 0
                if bool(hit.any()):
                    lost_acc.add(None, x[hit], y[hit], lost[hit])
                del lost, hit
            del where_band, x, y, v, kept
        if not any_kept:  # clipped everywhere: at the clip level
            planes[colour] = torch.ones(out, dtype=torch.float32)
            continue
        plane, at_clip = plane_from_sums(acc, lost_acc)
        del acc, lost_acc
        if colour != "G" and differences:
            guided_difference(plane, planes["G"], chroma, CHROMA_EPS, change)  # chroma 0: nothing
            plane += planes["G"]
        if at_clip is not None:
            plane.masked_fill_(at_clip, 1.0)
        planes[colour] = plane
        if colour == "G":
            # the sharpened green's change (written over it), which red and blue follow
            change, sharp = (None if sharp is None else torch.from_numpy(sharp).sub_(plane)), None
            planes[colour] = plane = plane.to(torch.float32)  # as the output: half the memory at the peak
        else:  # red or blue done: moved with the green, in the output's float32 (half the memory)
            planes[colour] = _finished(plane, change)
    result = np.empty(out + (3,), dtype=np.float32)
    for i, colour in enumerate("RGB"):
        plane = planes.pop(colour)
        result[..., i] = (_finished(plane, change) if colour == "G" else plane).numpy()
    return result


def _finished(plane: Tensor, change: Tensor | None) -> Tensor:
    """A colour plane (float64) moved with the sharpened green by ``change`` (the green's
    sharpening), except where it is at the clip level, and clamped to [0, 1], float32."""
    if change is not None:  # a colour at the clip level stays there
        plane.add_(torch.where(plane >= 1.0, 0.0, change))
    return plane.clamp_(0, 1).to(torch.float32)


def raw_inputs(stack) -> dict:
    """What the joint path takes from a raw burst stack: normalised samples (with the
    registration's gain and offset), clipped samples, motions, trust, balance and the noise."""
    from hbis_torch.capture.raw import normalised
    from hbis_torch.stack_io import BURST_MIN_CONFIDENCE

    raw = stack.meta["raw"]
    values, clipped = normalised(np.asarray(stack.frames), raw)
    trusted = np.asarray(stack.confidence) >= BURST_MIN_CONFIDENCE
    trusted[stack.reference_index] = True
    cfa = stack.meta["cfa"]
    balance = np.asarray(raw["white_balance"], dtype=np.float64)
    go = np.asarray(stack.gain_offset, dtype=np.float64)
    top = float(raw.get("grey_scale", 1.0))
    if not np.allclose(go, [1.0, 0.0]):
        per_colour = np.array([1.0 / balance["RGB".index(c)] for c in cfa], dtype=np.float64).reshape(2, 2)
        H, W = values.shape[1:]
        tile = np.tile(per_colour, ((H + 1) // 2, (W + 1) // 2))[:H, :W]
        for k in range(len(values)):  # in place, a frame at a time (in float64, as the whole burst was)
            values[k] = go[k, 0] * values[k] + go[k, 1] * top * tile
    if raw.get("noise_profile") is not None:
        noise, source = np.asarray(raw["noise_profile"], dtype=np.float64), "the DNG noise profile"
    else:
        noise, source = estimate_noise(values[stack.reference_index], cfa), "measured on the reference frame"
    return {"values": values, "clipped": clipped, "cfa": cfa, "motions": np.asarray(stack.motions),
            "trusted": trusted, "reference": stack.reference_index, "balance": balance, "noise": noise,
            "noise_source": source, "local": stack.meta.get("local_motion")}


def reconstruct_raw_burst(stack, method=None, registration: str = "auto", messages: list | None = None,
                          colour: str | None = None, robust: bool = True, keep_blurred: bool = False,
                          kernel_sigma: float | None = None, chroma: float | None = None, **kw) -> np.ndarray:
    """Jointly demosaick and super-resolve a raw burst stack (module docstring).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        A raw burst (:func:`is_raw_burst_stack`).
    method : hbis_torch.reconstruct.registry.Method, optional
        The method asked for; only the classical splat is joint, so the learned method's name is
        met with a message.
    registration : {"auto", "data"}
    messages : list, optional
    colour : None
        Refused otherwise (the planes are joint).
    robust : bool
        Robustness weights (True) or every trusted sample at 1.
    keep_blurred : bool
        Use every trusted frame; by default frames clearly blurrier than the sharpest are left out
        (:func:`~hbis_torch.capture.sharpness.blurred_frames`, on the mosaics' 2 x 2 cells).
    kernel_sigma : float, optional
        The splat's Gaussian, output px; default from the noise (:func:`kernel_for_noise`).
    chroma : float, optional
        How much of the guided filter red and blue's differences from green take (0 to 1);
        default from the noise (:func:`chroma_for_noise`).
    **kw
        Refused if any (the classical method's ``deblur`` is accepted: the joint splat has no
        Wiener step).

    Returns
    -------
    np.ndarray, shape (S H, S W, 3), float32 in [0, 1]
        Linear camera RGB (:func:`hbis_torch.reconstruct.raw_output.camera_to_srgb` makes it
        linear sRGB).
    """
    notes = messages if messages is not None else []
    if registration == "optics":
        raise HbisInputError("a burst stack has no optics: its motion was measured by 'hbis assemble --burst' "
                             "(use --registration auto)")
    if colour is not None:
        raise HbisInputError("the colour option (--colour) does not apply to raw bursts: their colours are "
                             "demosaicked jointly")
    kw.pop("deblur", None)  # the classical method's option: the joint splat has no Wiener step
    for key in ("threads", "model", "provider", "extrapolate", "ensemble", "precision"):
        kw.pop(key, None)
    if kw:
        raise HbisInputError(f"option(s) {', '.join(sorted(kw))} do not apply to raw bursts")
    if method is not None and getattr(method, "name", "classical") != "classical":
        notes.append(act(f"raw bursts are demosaicked and super-resolved jointly by the classical splat; the "
                         f"{method.name} method has no raw burst path of its own, so its output is that"))
    inputs = raw_inputs(stack)
    if bool(inputs["clipped"].all()):
        raise HbisInputError("every sample of the burst is clipped (at the white level): there is nothing to "
                             "reconstruct")
    if all(m == "identity" for m in stack.meta.get("motion_models", [])):
        notes.append(act(f"all {len(stack.frames)} frames are identical to the reference: the output is the "
                         "reference frame demosaicked by the same splat (and enlarged, at S > 1)"))
    notes.append(f"raw noise ({inputs['noise_source']}): variance S x + O per colour, "
                 + ", ".join(f"{c} S={s:.2e} O={o:.2e}" for c, (s, o) in zip("RGB", inputs["noise"])))
    left_out = [k for k, t in enumerate(inputs["trusted"]) if not t]
    if left_out:
        notes.append(f"left out {len(left_out)} frame(s) whose motion is not trusted: {left_out}")
    if not keep_blurred:
        blurred, line = blurred_frames(centre_cells(inputs["values"]), inputs["reference"], inputs["trusted"])
        inputs["trusted"][blurred] = False
        if line:
            notes.append(line + " (--keep-blurred keeps them)")
    if int(inputs["clipped"].sum()):
        share = float(inputs["clipped"].mean())
        notes.append(f"{100 * share:.2f} % of the samples are clipped: left out of their colour, which is set to "
                     "the clip level where only clipped samples remain")
    weights = sample_weights(inputs["values"], inputs["cfa"], inputs["motions"], inputs["trusted"],
                             inputs["reference"], inputs["balance"], inputs["noise"], robust, inputs["local"],
                             cells=True)
    # (the joint splat of a still burst at S = 2 fell 1.6 to 2.6 dB under the reference demosaicked and
    # enlarged; at its own size and enlarged it gained 1.1 to 1.5 dB: development photographs, 128 px)
    scale = still_run_scale(_lazy_positions(inputs["motions"], *inputs["values"].shape[1:], inputs["local"],
                                            keep=False), inputs["trusted"], inputs["reference"], stack.h, notes)
    if kernel_sigma is None:
        kernel_sigma = kernel_for_noise(inputs["noise"])
    if chroma is None:
        chroma = chroma_for_noise(inputs["noise"], scale, int(np.sum(inputs["trusted"])))
    if chroma > 0:
        notes.append(f"noisy frames: red and blue's differences from green guided by green "
                     f"({100 * chroma:.0f} % of the guided filter)")
    from hbis_torch.reconstruct.burst import stuck_pixel_weights

    image = joint_demosaick_sr(inputs["values"], inputs["clipped"], inputs["cfa"], inputs["motions"], scale,
                               weights, kernel_sigma, local=inputs["local"], chroma=chroma,
                               sensor=stuck_pixel_weights(stack))
    return image if scale == stack.h else enlarge(image, tuple(stack.h * n for n in image.shape[:2]))

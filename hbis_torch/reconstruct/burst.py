"""Burst stacks through every reconstruction method: positions, robustness and the fallback.

A burst stack (``stack.kind == "burst"``, ``hbis assemble --burst``) carries each frame's motion;
:func:`reconstruct_burst` (what :func:`hbis_torch.reconstruct.reconstruct` calls for one) does
what every method needs, then hands the samples to the method's own burst path (the ``burst``
function of its :class:`~hbis_torch.reconstruct.registry.Method`):

1. *brightness*: each frame's ``gain_offset`` is applied (``g * frame + o``);
2. *positions*: the motions on the pixel grid
   (:func:`~hbis_torch.reconstruct.positions.burst_positions`); untrusted frames get weight 0;
3. *robustness* (:func:`robustness_weights`): a sample the motion does not explain (a moving
   object, an occlusion, a brightness jump) is down-weighted, pixel by pixel: the frame and the
   reference, both blurred against aliasing, are compared at the sample's position, and the
   difference is weighed against what noise and the local contrast allow, as in the robustness
   map of Wronski et al. (2019) [1]_, in place of Farsiu's L1 [2]_; rejections are grown by a
   pixel (a minimum filter), so the edges of a moving object are not smeared either;
4. *fallback*: where the other frames leave (almost) nothing, the output is the single-frame
   estimate (the reference enlarged, bicubic), blended by the other frames' coverage; a
   burst whose frames are all copies of the reference gets the single-frame estimate, and says so.
   A burst whose samples fill too little of the S-times lattice (a few frames, or many left out,
   at S = 3 or 4) is reconstructed at the largest smaller scale they fill and enlarged to S
   (:func:`scale_to_run`). The classical method's image is blended by the lattice's fill only
   for bursts asked at S = 2 or that fill no scale's lattice (:data:`RUN_FILL`'s notes).

Colour bursts are registered once (on the luminance) and go through the method per channel
(``colour="channels"``, the default) or as luminance plus interpolated chroma (``"luma"``), as
colour scans do (:mod:`hbis_torch.reconstruct.colour`).

Frames are (F, H, W) float32 in [0, 1] (or (F, H, W, 3)); positions (F, H, W, 2) float64 in the
reference's LR px; weights (F, H, W) float64 in [0, 1]; outputs (S H, S W) (or (S H, S W, 3)).

References
----------
.. [1] B. Wronski et al., "Handheld multi-frame super-resolution", ACM Transactions on Graphics
   38(4), SIGGRAPH 2019 (the robustness map).
.. [2] S. Farsiu, M. D. Robinson, M. Elad and P. Milanfar, "Fast and robust multiframe super
   resolution", IEEE Transactions on Image Processing 13(10), 2004 (robust, L1, shift-and-add).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.capture.sharpness import blurred_frames
from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act
from hbis_torch.reconstruct.burst_fill import RUN_FILL, Tally, report_still, report_unfilled, tally_frames
from hbis_torch.reconstruct.burst_fill import coverage, scale_to_run  # noqa: F401 (this module's API too)
from hbis_torch.reconstruct.lens_blur import burst_lens
from hbis_torch.reconstruct.single_frame import enlarge, single_frame
from hbis_torch.registration.threaded_sample import grid_sample_threaded
from hbis_torch.stack_io import BURST_MIN_CONFIDENCE

# Robustness: a sample keeps weight exp(-(d / tau)^2), d the blurred difference to the reference
# at its position, tau = NOISE_TOLERANCE x the difference's noise + CONTRAST_TOLERANCE x the local
# contrast (standard deviation of the blurred reference over 3 x 3 px).
COMPARE_BLUR_PX = 1.0
NOISE_TOLERANCE = 3.0
CONTRAST_TOLERANCE = 1.5
# Where the other frames' samples in a reference pixel weigh less than this, the output leans on
# the single-frame estimate (fully where they weigh nothing).
FULL_COVERAGE = 2.0
# The weight of the reference's own samples where it is out of focus (its sharpness under
# BLURRED_SHARE of the median other frame's, hbis_torch.capture.sharpness.blur_to_reference): at
# full weight its blur goes into every pixel it lands on, as a blurred frame's would (those are left
# out, blurred_frames); its grid stays the output's, and the others are compared with it through its
# blur. Development bursts (training/dev_blurred_reference.py --reference-weights 1 0, the files
# dev_blurred_reference_weight[_64x48].json: the training photographs, a reference out of focus by a
# further 0.7 / 1 LR px, S = 2): a quarter gained over full weight on the mean of every group of 5
# to 30 frames (+0.06 to +0.79 dB; single 64 x 48 bursts lost up to 0.31 with 30 frames, 0.05
# with 8 or 16) and held with 4 (within 0.13 dB); 0 gained 0.08 to 0.13 dB more with 16 frames
# of 640 x 480, but lost 0.56 to 0.68 dB to a quarter with 4 or 5, whose lattice needs the
# reference's samples.
BLURRED_REFERENCE_WEIGHT = 0.25


def corrected_frames(stack, channel: int | None = None) -> Tensor:
    """The stack's frames with each frame's gain and offset applied, float32 in [0, 1]:
    (F, H, W) or (F, H, W, 3); ``channel`` c of an RGB stack: that channel alone (F, H, W), the
    same values as ``corrected_frames(stack)[..., c]``."""
    # a fresh tensor: corrected in place (a 12 MP burst's is 768 MB)
    frames = stack.to_float() if channel is None else stack.to_float((..., channel))
    go = torch.from_numpy(stack.gain_offset.astype(np.float32))
    shape = (-1,) + (1,) * (frames.ndim - 1)
    return frames.mul_(go[:, 0].reshape(shape)).add_(go[:, 1].reshape(shape)).clamp_(0, 1)


def corrected_frame(stack, k: int) -> Tensor:
    """Frame ``k`` of :func:`corrected_frames`, (H, W) or (H, W, 3), converted alone."""
    go = stack.gain_offset[k].astype(np.float32)
    return stack.to_float(k).mul_(float(go[0])).add_(float(go[1])).clamp_(0, 1)


def corrected_luma(stack) -> Tensor:
    """The luma of :func:`corrected_frames` (F, H, W) float32 (the frames themselves for a grey
    stack), an RGB stack's made a frame at a time: its float RGB frames (12 bytes a pixel) are
    never held whole."""
    if stack.frames.ndim != 4:
        return corrected_frames(stack)
    out = torch.empty(stack.frames.shape[:3], dtype=torch.float32)
    for k in range(len(out)):
        out[k] = _rgb_luma(corrected_frame(stack, k))
    return out


def _luma(frames: Tensor) -> Tensor:
    """The luma (F, H, W) of RGB frames (F, H, W, 3); grey frames (F, H, W) as they are."""
    return _rgb_luma(frames) if frames.ndim == 4 else frames


def _rgb_luma(rgb: Tensor) -> Tensor:
    """BT.601 luma of RGB values (..., 3): (...)."""
    return rgb @ torch.tensor([0.299, 0.587, 0.114], dtype=rgb.dtype)


def _blur(images: Tensor) -> Tensor:
    import kornia

    return kornia.filters.gaussian_blur2d(images[:, None], (5, 5), (COMPARE_BLUR_PX, COMPARE_BLUR_PX),
                                          border_type="replicate")[:, 0]


def _sample(images: Tensor, positions: Tensor) -> Tensor:
    """Bilinear values of ``images`` (C, H, W) at ``positions`` (..., 2) (u, v), border-clamped:
    (C, ...)."""
    C, H, W = images.shape
    # grid_sample's coordinates written straight into float32 (no float64 grid stacked, then
    # converted: half the time)
    grid = torch.empty(positions.shape[:-1] + (2,), dtype=torch.float32)
    for axis, size in ((0, W), (1, H)):
        torch.add(torch.tensor(-1.0, dtype=positions.dtype), positions[..., axis], alpha=2 / max(size - 1, 1),
                  out=grid[..., axis])
    flat = grid.reshape(1, 1, -1, 2)
    out = grid_sample_threaded(images[None].to(torch.float32), flat, mode="bilinear", padding_mode="border",
                               align_corners=True)
    return out.reshape((C,) + positions.shape[:-1])


def _inside(positions: Tensor, shape: tuple[int, int]) -> Tensor:
    """Whether each position (..., 2) lies on the reference frame of ``shape`` (H, W)."""
    H, W = shape
    u, v = positions[..., 0], positions[..., 1]
    return (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)


def robustness_weights(grey: Tensor, positions, trusted: Tensor, reference: int, tally=None,
                       sensor: Tensor | None = None) -> Tensor:
    """Per-sample weights in [0, 1]: 1 where the motion explains the sample, towards 0 where not.

    Computed a frame at a time (its positions, blur and comparison), so that no array of every
    sample's position or blurred value is held beside the frames. A frame clearly sharper than an
    out-of-focus reference is compared through the reference's blur
    (:func:`~hbis_torch.capture.sharpness.blur_to_reference`), and the reference's own samples
    then weigh :data:`BLURRED_REFERENCE_WEIGHT`.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32
        Brightness-corrected luminance of the frames.
    positions : Tensor, shape (F, H, W, 2), float64, or BurstPositions
        Where each sample lies on the reference grid (``positions[k]``: frame k's).
    trusted : Tensor, shape (F,), bool
        Frames whose motion is trusted (the others get 0).
    reference : int
    tally : Tally, optional
        Is handed every frame's positions and weights with any weight (:meth:`Tally.add`),
        which then need not be computed again.
    sensor : Tensor, shape (H, W), float32, optional
        Each sensor pixel's weight in every frame: 0 at its stuck pixels (their values were
        filled from their neighbours, :mod:`hbis_torch.capture.stuck_pixels`), 1 elsewhere.

    Returns
    -------
    Tensor, shape (F, H, W), float32
        1 for the reference's samples (:data:`BLURRED_REFERENCE_WEIGHT` where it is out of focus);
        0 for samples outside the reference frame and for untrusted frames. (Each weight is a
        float32 value, so float32 holds it exactly: half the memory of float64, the same numbers.)
    """
    from hbis_torch.capture.sharpness import blur_to_reference, gaussian_blur
    from hbis_torch.sensor.noise import noise_sigma

    F, H, W = grey.shape
    # frames clearly sharper than the reference are compared through its blur (none where it is as sharp)
    match = blur_to_reference(grey, reference, trusted)
    ref = _blur(grey[reference][None])[0]
    local = torch.nn.functional.avg_pool2d(torch.stack((ref, ref * ref))[:, None], 3, 1, 1,
                                           count_include_pad=False)[:, 0]
    both = torch.stack((ref, (local[1] - local[0] ** 2).clamp_min(0).sqrt()))  # the reference and its contrast
    del local
    # Noise of a difference of two frames blurred by a Gaussian of s px: sqrt(2) / (2 sqrt(pi) s).
    noise = float(noise_sigma(grey[reference][None])[0]) * 2 ** 0.5 / (2 * np.pi ** 0.5 * COMPARE_BLUR_PX)
    weights = torch.zeros((F, H, W), dtype=torch.float32)
    for k in range(F):
        if k == reference or not bool(trusted[k]):
            continue
        where = positions[k]
        at_ref, tau = _sample(both, where)  # one grid for both images
        tau.mul_(CONTRAST_TOLERANCE).add_(NOISE_TOLERANCE * max(noise, 1e-4))
        frame = grey[k][None] if not match[k] else gaussian_blur(grey[k][None], match[k])
        weight = torch.exp(-((_blur(frame)[0] - at_ref) / tau) ** 2)
        weight = _minimum_3x3(weight)  # grow each rejection a pixel
        weights[k] = weight * _inside(where, (H, W))
        if sensor is not None:
            weights[k] *= sensor
        if tally is not None:
            tally.add(k, where, weights[k])
    # an out-of-focus reference's own samples (the frames sharper than it are matched to its blur)
    own = BLURRED_REFERENCE_WEIGHT if any(match) else 1.0
    weights[reference] = own if sensor is None else sensor * own
    if tally is not None:
        tally.add(reference, positions[reference], weights[reference])
    return weights


def _minimum_3x3(image: Tensor) -> Tensor:
    """The minimum of each pixel's 3 x 3 neighbourhood (cut at the border), (H, W): a minimum
    filter's rows then columns, four elementwise minima (the same values as a 3 x 3 max pool of
    the negated image, in a fortieth of its time)."""
    rows = image.clone()
    torch.minimum(rows[1:], image[:-1], out=rows[1:])
    torch.minimum(rows[:-1], image[1:], out=rows[:-1])
    out = rows.clone()
    torch.minimum(out[:, 1:], rows[:, :-1], out=out[:, 1:])
    torch.minimum(out[:, :-1], rows[:, 1:], out=out[:, :-1])
    return out


def burst_samples(stack, frames: Tensor | None = None, lazy: bool = False,
                  tally: Tally | None = None, leave_out=()) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Steps 1 to 3 of the module docstring: what every method's burst path is handed.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        A burst stack.
    frames : Tensor, optional
        Its :func:`corrected_frames`, where the caller has them already.
    lazy : bool
        Positions as a :class:`~hbis_torch.reconstruct.positions.BurstPositions` (computed a
        band at a time where they are read) and weights in float32 (the same values), not the
        whole float64 arrays: 24 bytes a sample less (a 12 MP burst of 16 frames: 4.6 GB).
    tally : Tally, optional
        :func:`robustness_weights`'.
    leave_out : sequence of int
        Frames given no weight besides the untrusted ones (blurred frames,
        :func:`~hbis_torch.capture.sharpness.blurred_frames`).

    Returns
    -------
    frames : Tensor, shape (F, H, W) or (F, H, W, 3), float32
        Brightness-corrected.
    positions : Tensor, shape (F, H, W, 2), float64, or BurstPositions
    trusted : Tensor, shape (F,), bool
        The frames whose motion is trusted, less ``leave_out``.
    weights : Tensor, shape (F, H, W), float64 (float32 if ``lazy``)
        The robustness weights (:func:`robustness_weights`).
    """
    from hbis_torch.reconstruct.positions import burst_positions

    frames = corrected_frames(stack) if frames is None else frames
    positions, trusted = burst_positions(stack, lazy=True)
    if len(leave_out):
        trusted = trusted.clone()
        trusted[list(leave_out)] = False
    sensor = stuck_pixel_weights(stack)
    extra = {} if sensor is None else {"sensor": sensor}  # (a robustness_weights put in its place takes neither)
    if tally is None:
        weights = robustness_weights(_luma(frames), positions, trusted, stack.reference_index, **extra)
    else:
        weights = robustness_weights(_luma(frames), positions, trusted, stack.reference_index, tally, **extra)
    if not lazy:
        positions, weights = positions.whole(), weights.double()
    return frames, positions, trusted, weights


def stuck_pixel_weights(stack) -> Tensor | None:
    """(H, W) float32: 0 at the stack's stuck pixels (``stuck_pixels`` in its metadata, filled by
    ``hbis assemble --burst``), 1 elsewhere; None where it has none."""
    stuck = stack.meta.get("stuck_pixels")
    if not stuck:
        return None
    rows, cols = torch.as_tensor(stuck, dtype=torch.long).T
    sensor = torch.ones(stack.frames.shape[1:3], dtype=torch.float32)
    sensor[rows, cols] = 0.0
    return sensor


def reconstruct_burst(stack, method, registration: str = "auto", messages: list | None = None,
                      colour: str | None = None, keep_blurred: bool = False, **kw) -> np.ndarray:
    """Super-resolve a burst stack with a registered method (module docstring).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        A burst stack.
    method : hbis_torch.reconstruct.registry.Method
        Its ``burst`` function gets the corrected frames, positions and weights.
    registration : {"auto", "data"}
        A burst's motion was measured when it was assembled; ``"optics"`` is refused (a burst
        has no optics).
    messages : list, optional
        Receives the lines about rejected samples, the fallback and the method's own.
    colour : {"luma", "channels"} or None
        For RGB bursts (default ``"channels"``); refused on grey ones.
    keep_blurred : bool
        Use every trusted frame; by default frames clearly blurrier than the sharpest are left out
        (:func:`~hbis_torch.capture.sharpness.blurred_frames`).
    **kw
        The method's options.

    Returns
    -------
    np.ndarray, shape (S H, S W) or (S H, S W, 3), float32 in [0, 1]
    """
    from hbis_torch.reconstruct.colour import COLOUR_MODES, DEFAULT_MODE

    if registration == "optics":
        raise HbisInputError("a burst stack has no optics: its motion was measured by 'hbis assemble --burst' "
                             "(use --registration auto)")
    rgb = stack.frames.ndim == 4
    if colour is not None and (not rgb or colour not in COLOUR_MODES):
        raise HbisInputError(f"the colour option (--colour) takes {' or '.join(COLOUR_MODES)} on RGB bursts; "
                             f"got {colour!r} for a {'colour' if rgb else 'grey'} burst")
    run = method.burst_function()
    if run is None:
        raise HbisInputError(f"the {method.name} method does not take burst stacks")
    ref, scale = stack.reference_index, stack.h
    # an RGB burst reconstructed channel by channel holds its luma and one channel's float frames
    # at a time, not its float RGB frames (a 12 MP burst of 16: 2.3 GB)
    by_channel = rgb and (colour or DEFAULT_MODE) == "channels"
    frames = corrected_luma(stack) if by_channel else corrected_frames(stack)
    reference = corrected_frame(stack, ref) if by_channel else frames[ref]
    fallback = single_frame(reference.numpy(), scale)
    notes = messages if messages is not None else []
    if all(torch.equal(corrected_frame(stack, k) if by_channel else frames[k], reference) for k in range(len(frames))):
        notes.append(act(f"all {len(frames)} frames are identical: no new samples, so the output is the "
                         "single-frame estimate (the reference frame enlarged, bicubic); capture the burst "
                         "again, moving the camera a little between frames"))
        return fallback
    # the coverage and the lattice's fill added up beside the weights (each frame's positions once)
    tally = Tally(tuple(frames.shape[1:3]), ref, range(scale, 1, -1))
    trusted_motion = stack.confidence >= BURST_MIN_CONFIDENCE
    blurred, line = ([], None) if keep_blurred else blurred_frames(frames, ref, trusted_motion)
    if line:
        notes.append(line + " (--keep-blurred keeps them)")
    frames, positions, trusted, weights = burst_samples(stack, frames, lazy=True, tally=tally, leave_out=blurred)
    if not tally.added:  # weights from elsewhere (a robustness_weights that takes no tally)
        tally = tally_frames(positions, weights, ref, range(scale, 1, -1))
    cover = tally.coverage()
    if float(cover.max()) == 0.0:
        notes.append("no frame but the reference could be used (none registered, or none agrees with it): the output "
                     "is the single-frame estimate (the reference frame enlarged, bicubic)")
        return fallback
    _report_weights(weights, trusted, ref, notes, blurred)
    if scale == 1:  # the reference's own grid: nothing to fill
        run_scale, fill = 1, np.ones(cover.shape, dtype=np.float32)
    else:
        run_scale, fill = tally.run_scale(scale)
        report_still(tally, notes)
        report_unfilled(tally, fill, scale, notes)
    del tally
    if not getattr(run, "streams", False):  # a method that wants the whole arrays gets them
        positions, weights = positions.whole(), weights.double()
    target = stack
    if run_scale != scale:
        notes.append(f"the frames' samples fill too little of the S = {scale} lattice: reconstructed at "
                     f"S = {run_scale} and enlarged to S = {scale} (bicubic)")
        target = type(stack)(stack.frames, {**stack.meta, "h": run_scale})
    if "lens_sigma" in method.keywords and kw.get("lens_sigma") is None and kw.get("deblur", True):
        estimate = burst_lens(_luma(frames), positions, weights, ref, notes)
        kw["lens_sigma"] = estimate.sigma
        if getattr(run, "reads_lens_doubt", False):
            kw["lens_doubt"] = estimate.doubt
    said: list[str] = []  # the method's lines, once each (a colour burst runs it per channel)
    if not rgb:
        image = run(target, frames, positions, weights, messages=said, **kw)
    elif by_channel:
        del frames  # the luma (a 12 MP burst of 16: 768 MB): each channel's frames take its place
        image = None
        # what depends on the samples' places and weights alone, computed for the first channel
        sharing = {"shared": {}} if getattr(run, "shares_samples", False) else {}
        for c in range(3):
            channel = run(target, corrected_frames(stack, c), positions, weights, messages=said, **kw, **sharing)
            if image is None:
                image = np.empty((*channel.shape, 3), dtype=channel.dtype)
            image[..., c] = channel
            del channel
    else:
        image = _luma_and_chroma(run, target, frames, positions, weights, said, kw)
    notes.extend(dict.fromkeys(said))
    alpha = _blend_weight(cover, run_scale)
    if scale <= getattr(run, "fill_blend_to", scale) or float(fill.mean()) < RUN_FILL:  # (RUN_FILL's notes)
        alpha = np.minimum(alpha, fill, out=alpha)  # _blend_weight's own array
    if run_scale != scale:
        size = fallback.shape[:2]
        image, alpha = enlarge(image, size), enlarge(alpha, size)
    if alpha.ndim < np.ndim(image):
        alpha = alpha[..., None]
    return _blend(alpha, np.asarray(image, dtype=np.float32), fallback)


# Output rows :func:`_blend` takes at a time: a 48 MP output's whole-image temporaries are 192 MB
# each of fresh pages, which cost more to fault in than the arithmetic.
BLEND_PIECE_SAMPLES = 1 << 18


def _blend(alpha: np.ndarray, image: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``alpha * image + (1 - alpha) * fallback`` clipped to [0, 1], float32 (S H, S W[, C]), a
    piece of :data:`BLEND_PIECE_SAMPLES` samples' rows at a time: the same float32 operations, in
    the same order, as on the whole arrays. Raises where a value is not finite."""
    # in torch's memory (as capture.burst.luminance's: NumPy's huge pages fault in slower)
    out = torch.empty(np.broadcast_shapes(alpha.shape, image.shape, fallback.shape), dtype=torch.float32).numpy()
    rows = max(1, BLEND_PIECE_SAMPLES // max(out[0].size, 1))
    for r in range(0, len(out), rows):
        a, piece = alpha[r:r + rows], out[r:r + rows]
        np.multiply(a, image[r:r + rows], out=piece)
        piece += (1 - a) * fallback[r:r + rows]
        if not np.isfinite(piece).all():
            raise RuntimeError("the burst reconstruction produced non-finite values; please report the stack")
        np.clip(piece, 0, 1, out=piece)
    return out


def _luma_and_chroma(run, stack, frames, positions, weights, messages, kw) -> np.ndarray:
    from hbis_torch.reconstruct.colour import LUMA, rgb_to_ycbcr, upsample, ycbcr_to_rgb

    # the luma a frame at a time (in float64, as rgb_to_ycbcr takes it), the chroma of the reference alone
    luma = torch.empty(frames.shape[:3], dtype=torch.float32)
    for k in range(len(frames)):
        luma[k] = torch.from_numpy((frames[k].numpy().astype(np.float64) @ LUMA).astype(np.float32))
    y = run(stack, luma, positions, weights, messages=messages, **kw)
    reference = rgb_to_ycbcr(frames[stack.reference_index].numpy().astype(np.float64))
    chroma = upsample(reference[..., 1:], stack.h)
    return ycbcr_to_rgb(np.concatenate((np.asarray(y, dtype=np.float64)[..., None], chroma), axis=-1))


def _blend_weight(cover: np.ndarray, scale: int) -> np.ndarray:
    """The method's share of the output (S H, S W) float32: 1 where the other frames put at least
    :data:`FULL_COVERAGE` into a reference pixel, falling linearly to 0 where they put nothing."""
    alpha = torch.from_numpy(np.clip(cover / FULL_COVERAGE, 0, 1))
    # bilinear between the pixels' centres, held beyond the outer ones (scipy.ndimage.zoom's
    # order=1, mode="nearest", grid_mode=True: the same float32 values, a third of its time)
    big = torch.nn.functional.interpolate(alpha[None, None], scale_factor=scale, mode="bilinear", align_corners=False)
    return big[0, 0].clamp_(0, 1).to(torch.float32).numpy()


def _report_weights(weights: Tensor, trusted: Tensor, reference: int, notes: list, blurred=()) -> None:
    """Lines naming untrusted frames (but the ``blurred`` ones, named apart), frames whose
    samples were mostly down-weighted, and an out-of-focus reference's own samples' weight."""
    left_out = [k for k in range(len(trusted)) if not bool(trusted[k]) and k not in blurred]
    if left_out:
        notes.append(f"left out {len(left_out)} frame(s) whose motion is not trusted: {left_out}")
    # float32's own (cascade) sum, good to about 1e-7 here: a sum into float64 takes 35 times as long
    mean = weights.reshape(len(weights), -1).sum(1) / max(weights.shape[1] * weights.shape[2], 1)
    if float(mean[reference]) < 0.5:
        notes.append(f"the reference, frame {reference}, is out of focus beside most frames: its own samples weigh "
                     f"{BLURRED_REFERENCE_WEIGHT:g} in the fusion (the output is still drawn on its grid: "
                     "'hbis assemble --burst --reference sharpest' refines the sharpest frame instead)")
    low = [k for k in range(len(mean)) if k != reference and bool(trusted[k]) and float(mean[k]) < 0.5]
    if low:
        notes.append(f"frame(s) {low}: most samples down-weighted (the motion does not explain them: a moving "
                     "object, an occlusion or a brightness change)")

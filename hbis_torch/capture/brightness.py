"""A burst frame's brightness against the reference: the gain and offset that match them.

A hand-held burst's exposure moves by a few per cent from frame to frame (auto exposure, flicker).
:func:`fit_gain_offset` warps the frame onto the reference through its measured motion and fits
``g * frame + o`` to the reference by robust least squares, on both halved a few times where the
frames are large. Frames (H, W) float32 in [0, 1]; motions (3, 3) frame px -> reference px.
"""

from __future__ import annotations

import numpy as np
import torch

# The brightness fit halves frames whose shorter side is at least twice this (fit_gain_offset).
GAIN_FIT_SIDE = 128
# Pixels this close to the white or black level count as saturated (left out of the gain fit).
SATURATION_MARGIN = 2.0 / 255.0
# A fitted gain outside [1 / GAIN_RANGE, GAIN_RANGE] is taken for a failed fit and refused. An
# exposure bracket of +-2 EV (phones' HDR bursts, auto exposure that swings) needs gains of 4 and
# 1/4: with the range of 2 the project had, such frames kept a gain of 1, were down-weighted as a
# brightness change and added little (development bursts, the third renderer's training photographs,
# 320 x 240, 8 frames at S = 2, seeds 12 and 13, exposures x 0.25 to x 2.5: classical - bicubic
# -0.05 to +1.52 dB with the range of 2, +0.82 to +2.28 with 5, measured once).
GAIN_RANGE = 5.0
# torch.linalg.lstsq's default on the CPU, gelsy, reads its pivot array uninitialised (pytorch#71222),
# so the same line fit differed in its last bits from run to run; gelsd (SVD) gives the same bits.
LSTSQ_DRIVER = "gelsd"


def warp_to_reference(frame: torch.Tensor, motion: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame (H, W) resampled onto the reference grid through its homography (bilinear,
    :func:`~hbis_torch.registration.warp.warp_onto_reference`).

    Returns the warped frame (H, W) and where it is valid (H, W) bool (inside the frame).
    """
    from hbis_torch.registration.warp import warp_onto_reference

    warped, valid = warp_onto_reference(frame[None, None].float(), motion)
    return warped[0, 0], valid


def gain_fit_levels(shape: tuple[int, int]) -> int:
    """How many times :func:`fit_gain_offset` halves frames of ``shape`` (H, W)."""
    levels = 0
    while min(shape) >> levels >= 2 * GAIN_FIT_SIDE:
        levels += 1
    return levels


def gain_fit_reference(reference: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The reference (H, W) as :func:`fit_gain_offset` compares frames with it, halved as they
    are, and how many times."""
    from hbis_torch.registration.pyramid import pyramid

    levels = gain_fit_levels(tuple(reference.shape))
    return (pyramid(reference[None], levels)[-1][0] if levels else reference), levels


def fit_gain_offset(frame: torch.Tensor, reference: torch.Tensor, motion: np.ndarray,
                    reduced: tuple | None = None, halved: torch.Tensor | None = None) -> tuple[float, float]:
    """(g, o) with ``g * frame + o`` matching the reference where both see the same scene.

    A least-squares line through the warped frame's and the reference's pixels (both blurred a
    little against aliasing), refitted once without the pixels more than 3 robust sigmas off
    (a moving object) and without saturated pixels. A fit that is not sensible (g outside
    [1 / :data:`GAIN_RANGE`, :data:`GAIN_RANGE`]) is refused in favour of (1, 0). Frames larger
    than :data:`GAIN_FIT_SIDE` twice over are halved (a Gaussian pyramid) until they are not: two
    numbers need no millions of pixels, and the warp's cost was most of a large burst's brightness
    fit. ``reduced``: :func:`gain_fit_reference` of ``reference``, where the caller keeps it for a
    burst's frames; ``halved``: the frame halved as ``reduced`` says, where the caller has it (a
    burst's pyramid).
    """
    import kornia

    from hbis_torch.registration.pyramid import pyramid, to_level

    reference, levels = gain_fit_reference(reference) if reduced is None else reduced
    if levels:
        frame = pyramid(frame[None], levels)[-1][0] if halved is None else halved
        motion = to_level(np.asarray(motion)[None], levels)[0]
    warped, valid = warp_to_reference(frame, motion)
    # (blurred together: Kornia's faster path takes images of 128k pixels or more)
    blur = kornia.filters.gaussian_blur2d(torch.stack((warped, reference))[:, None], (5, 5), (1.0, 1.0),
                                          border_type="replicate")[:, 0]
    x, y = blur[0][valid].double(), blur[1][valid].double()
    lo, hi = SATURATION_MARGIN, 1.0 - SATURATION_MARGIN
    use = (x > lo) & (x < hi) & (y > lo) & (y < hi)
    gain, offset = 1.0, 0.0
    for refit in (True, False):
        x_used, y_used = x[use], y[use]  # gathered once: most of the fit's time went on gathers
        if len(x_used) < 16 or float(x_used.std()) < 1e-4:
            return 1.0, 0.0
        A = torch.stack((x_used, torch.ones_like(x_used)), -1)
        gain, offset = torch.linalg.lstsq(A, y_used[:, None], driver=LSTSQ_DRIVER).solution[:, 0].tolist()
        if refit:  # the pixels far off the line left out (the residuals of the pixels used, as gathered)
            spread = 1.4826 * float((y_used - (gain * x_used + offset)).abs().median()) + 1e-6
            use = use & ((y - (gain * x + offset)).abs() < 3 * spread)
    if not 1.0 / GAIN_RANGE <= gain <= GAIN_RANGE:
        return 1.0, 0.0
    return gain, offset

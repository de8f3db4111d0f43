"""How sharp each frame of a burst is, and which frame to refine.

A hand-held burst's frames are not equally sharp: the first is often shaken by the press of the
shutter, and a frame taken while the hand moves is smeared. The output is drawn on the reference
frame's grid and the robustness weights compare every frame with it, so a blurred reference costs
detail everywhere. :func:`frame_sharpness` measures each frame by the mean squared gradient of its
central part, blurred a little against the noise, over the part's variance: a focus measure, as
burst pipelines pick their reference frame by, that a frame's gain and offset leave alone (a
hand-held burst's exposure moves by a few per cent). :func:`choose_reference` takes the sharpest
frame where asked (``--reference sharpest``) and otherwise says when the given reference is
clearly blurrier than the sharpest.
"""

from __future__ import annotations

import numpy as np
import torch

from hbis_torch.notices import act

#: Side (px) of the central square of each frame that is measured: the frames of a burst move by
#: a few pixels, so their centres show nearly the same scene, and a 12 MP frame costs no more
#: than a small one (16 frames: a few milliseconds).
CENTRE_PX = 256
#: Gaussian sigma (px) of the blur before the gradients: the noise's own gradients, alike in
#: every frame, would otherwise weigh as much as the scene's.
BLUR_PX = 0.5
#: A reference whose sharpness is under this share of the sharpest frame's is named as blurred
#: (a setting, not tuned: on the held-out hand-held and third renderers' bursts, whose frames are
#: equally sharp, no frame fell under 0.83 of its burst's sharpest; a frame blurred by a Gaussian
#: of 0.7 px fell to 0.4 to 0.6).
BLURRED_SHARE = 0.7
#: ``--reference sharpest`` takes the first frame within this share of the sharpest frame's
#: sharpness: equally sharp frames differ by a few per cent (the noise, the motion; more where an
#: object moves through the centre), so a burst of them keeps an early frame rather than the one
#: that won by chance.
SHARP_SHARE = 0.95
#: What ``--reference`` takes for the sharpest frame.
SHARPEST = "sharpest"
#: The Gaussians (sigma, px) a frame clearly sharper than the reference may be blurred by before
#: the robustness weights compare it with the reference (:func:`blur_to_reference`).
MATCH_SIGMAS = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
#: Frames whose shorter side is under this many px are never left out as blurred: on a frame that
#: small a moving object or the scene's edge entering the view changes the measure as much as a
#: shake does (on the held-out matrix's 48 px bursts, a moving object took frames to 0.5).
MIN_SIDE_TO_LEAVE_OUT = 128


def frame_sharpness(grey: torch.Tensor) -> np.ndarray:
    """The mean squared gradient of each frame's central :data:`CENTRE_PX` square, blurred by a
    Gaussian of :data:`BLUR_PX`, over the square's variance.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W) or (F, H, W, 3), float32
        The frames' luminance, or RGB frames (the central square's BT.601 luma is taken: a colour
        burst's whole luma is never made for it); in any units (a gain and an offset leave the
        measure as it is).

    Returns
    -------
    np.ndarray, shape (F,), float64
        Per px^2; larger is sharper (0 for a flat frame). Comparable between frames of one burst
        only (the scene sets its scale).
    """
    import kornia

    F, H, W = grey.shape[:3]
    rows, cols = min(H, CENTRE_PX), min(W, CENTRE_PX)
    top, left = (H - rows) // 2, (W - cols) // 2
    centre = grey[:, top:top + rows, left:left + cols]
    if centre.ndim == 4:
        centre = centre @ torch.tensor([0.299, 0.587, 0.114], dtype=centre.dtype)
    centre = centre[:, None].contiguous()  # (Kornia's blur of a view: 20 x slower)
    blurred = kornia.filters.gaussian_blur2d(centre, (5, 5), (BLUR_PX, BLUR_PX), border_type="replicate")[:, 0]
    dy, dx = blurred.diff(dim=1)[:, :, :-1], blurred.diff(dim=2)[:, :-1, :]
    energy = (dx.square() + dy.square()).mean(dim=(1, 2), dtype=torch.float64)
    variance = blurred.var(dim=(1, 2)).double()
    return torch.where(variance > 0, energy / variance.clamp_min(1e-30), 0.0).numpy()


def choose_reference(grey: torch.Tensor, reference: int | str, trusted=None) -> tuple[int, list[str]]:
    """The reference frame's index, and a line where the reference is blurred.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32
        The frames' luminance (:func:`frame_sharpness`).
    reference : int or "sharpest"
        A frame's index, or :data:`SHARPEST` for the sharpest frame (:func:`frame_sharpness`: the
        first within :data:`SHARP_SHARE` of the sharpest's).
    trusted : Tensor or np.ndarray, shape (F,), bool, optional
        For a given index: the frames it is compared with (and itself); a frame of another scene,
        which registration rejects, has a sharpness of its own that says nothing of the
        reference's. Default: every frame (before registration).

    Returns
    -------
    index : int
    messages : list of str
        For a given index whose frame's sharpness is under :data:`BLURRED_SHARE` of the sharpest
        frame's: a line that says so and how to refine the sharpest instead (it asks the user to
        act, :func:`~hbis_torch.notices.act`); for ``"sharpest"``, which frame it is.
    """
    sharpness = frame_sharpness(grey)
    if reference == SHARPEST:
        first = int(np.flatnonzero(sharpness >= SHARP_SHARE * sharpness.max())[0])
        return first, [f"reference: frame {first}, the sharpest of the burst (--reference sharpest)"]
    if trusted is not None:
        compared = np.array(trusted, dtype=bool)
        compared[reference] = True
        sharpness = np.where(compared, sharpness, 0.0)
    best = int(np.argmax(sharpness))
    share = float(sharpness[reference] / sharpness[best]) if sharpness[best] > 0 else 1.0
    if share >= BLURRED_SHARE:
        return int(reference), []
    line = (f"the reference, frame {reference}, is blurred: its sharpness is {100 * share:.0f} % of frame {best}'s "
            "(shaken or out of focus); the output is drawn on its grid and the sharper frames are compared with "
            f"it through its blur: --reference {SHARPEST} refines the sharpest frame instead")
    return int(reference), [act(line)]


def blurred_frames(grey: torch.Tensor, reference: int, trusted=None) -> tuple[list[int], str | None]:
    """The frames other than the reference whose sharpness is under :data:`BLURRED_SHARE` of the
    sharpest frame's, the blurriest first and at most half of the others, and a line naming them
    (None where there are none); none for frames smaller than :data:`MIN_SIDE_TO_LEAVE_OUT`.

    The fusion leaves them out: a frame shaken or out of focus brings little the sharp frames do
    not, and its blur goes into every pixel it lands on (the robustness weights compare it with the
    reference through a blur, so they do not see it). Where more than half the frames seem blurred,
    the sharpest may be the odd one out: the rest are kept.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W) or (F, H, W, 3), float32
        The frames' luminance, or RGB frames (:func:`frame_sharpness`).
    reference : int
        Never left out.
    trusted : Tensor, shape (F,), bool, optional
        Only these frames are looked at (and the sharpest is among them and the reference).

    Returns
    -------
    frames : list of int
    line : str or None
    """
    if min(grey.shape[1:3]) < MIN_SIDE_TO_LEAVE_OUT:
        return [], None
    sharpness = frame_sharpness(grey)
    considered = [k for k in range(len(sharpness)) if k == reference or trusted is None or bool(trusted[k])]
    best = max(considered, key=lambda k: sharpness[k])
    if sharpness[best] <= 0:
        return [], None
    out = sorted((k for k in considered if k != reference and sharpness[k] < BLURRED_SHARE * sharpness[best]),
                 key=lambda k: sharpness[k])[:(len(considered) - 1) // 2]
    if not out:
        return [], None
    out.sort()
    return out, (f"left out {len(out)} blurred frame(s): {out} (sharpness under {100 * BLURRED_SHARE:.0f} % of "
                 f"frame {best}'s: shaken or out of focus)")


def gaussian_blur(frames: torch.Tensor, sigma: float) -> torch.Tensor:
    """``frames`` (F, H, W) float32 blurred by a Gaussian of ``sigma`` px (Kornia; the kernel
    reaches 3 sigma each way, the border replicated)."""
    import kornia

    size = 2 * int(np.ceil(3 * sigma)) + 1
    return kornia.filters.gaussian_blur2d(frames[:, None], (size, size), (sigma, sigma), border_type="replicate")[:, 0]


def blur_to_reference(grey: torch.Tensor, reference: int, trusted=None) -> list[float]:
    """Where the reference is out of focus (its :func:`frame_sharpness` under :data:`BLURRED_SHARE`
    of the median other frame's), for each frame clearly sharper than it (above its sharpness over
    :data:`BLURRED_SHARE`), the Gaussian of :data:`MATCH_SIGMAS` that brings the frame's sharpness
    nearest the reference's; 0 for the others, and for every frame where the reference is as sharp
    as most. A single frame sharper than the reference says more about that frame than about the
    reference (on small frames, an object that moved out of its centre: one burst of the held-out
    burst matrix's 135, at 48 px).

    The robustness weights compare every frame with the reference, each through the same small
    blur. Where the reference is out of focus, a sharp frame differs from it at every edge by the
    blur alone, its samples there lose weight, and the fused image leans on the soft reference
    where the detail is. Compared through the reference's blur (the frame blurred by this sigma
    for the comparison alone; its own samples are fused), it differs only where the scene or the
    motion does. On development bursts (the training photographs,
    ``training/dev_blurred_reference.py``: S = 2, 8 to 30 frames, a reference out of focus by a
    further Gaussian of 0.7 / 1.0 LR px) the classical image gained +0.18 to +0.32 / +2.2 to +2.6 dB
    on the mean at 640 x 480 and +0.03 to +0.04 / +0.11 to +0.18 dB at 64 x 48, one burst of the 48
    lower (by 0.02 dB); the sigma found was the blur added (0.75 for 0.7, 1.0 for 1.0); a reference
    in focus changes nothing.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32
        The frames' luminance.
    reference : int
    trusted : Tensor or np.ndarray, shape (F,), bool, optional
        The frames looked at (default: all); the others get 0.

    Returns
    -------
    list of float, length F
        Sigma, px (0: compared as it is).
    """
    sharpness = frame_sharpness(grey)
    others = [k for k in range(len(grey)) if k != reference and (trusted is None or bool(trusted[k]))]
    out = [0.0] * len(grey)
    if not others or sharpness[reference] >= BLURRED_SHARE * float(np.median(sharpness[others])):
        return out
    sharper = [k for k in others if sharpness[reference] < BLURRED_SHARE * sharpness[k]]
    # the central square frame_sharpness reads, with room for the widest blur's reach (the same
    # pixels as the whole frame's blur there)
    H, W = grey.shape[1:]
    margin = int(np.ceil(3 * max(MATCH_SIGMAS))) + 3  # (and frame_sharpness's own 5 x 5 blur and difference)
    rows, cols = min(H, CENTRE_PX + 2 * margin), min(W, CENTRE_PX + 2 * margin)
    top, left = (H - rows) // 2, (W - cols) // 2
    centres = grey[sharper, top:top + rows, left:left + cols].contiguous()
    tried = np.stack([frame_sharpness(gaussian_blur(centres, sigma)) for sigma in MATCH_SIGMAS], 1)  # (frames, sigmas)
    best = np.abs(tried - sharpness[reference]).argmin(1)
    for k, choice in zip(sharper, best):
        out[k] = float(MATCH_SIGMAS[choice])
    return out

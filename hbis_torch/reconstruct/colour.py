"""Colour stacks through any reconstruction method: RGB frames and raw Bayer frames.

RGB frames (F, H, W, 3) go through a method in one of two ways:

* ``"luma"``: the method super-resolves the luminance Y (BT.601: 0.299 R + 0.587 G + 0.114 B)
  only; the chroma (Cb, Cr) of the reference frame is interpolated (cubic spline) onto the output
  grid. One reconstruction; colour detail stays at the sensor's resolution, as in JPEG and video,
  where the eye does not see it.
* ``"channels"``: the method runs on R, G and B separately (three reconstructions, three times
  the time), each at full resolution.

The default (:data:`DEFAULT_MODE`) is ``"channels"``: on three photographs (astronaut, coffee,
chelsea; h = 4, 64 x 64 px) it scored 0.66 dB (classical) and 1.56 dB (learned) more PSNR than
``"luma"`` on average, for three reconstructions instead of one
(``python3 benchmarks/bench_colour.py --h 4 --size 64``; benchmarks/results/bench_colour.json,
docs/capture.md).

Raw Bayer frames (F, H, W) with a ``cfa`` key: the classical method demosaicks jointly: every
colour sample enters the splatting at its own position (the sample positions of its pixel), with
per-channel masks as sample weights, as in Wronski et al., SIGGRAPH 2019; each colour plane is
reconstructed from its own samples only (interpolated, not deblurred: see
:func:`~hbis_torch.reconstruct.classical.method.reconstruct_classical_raw_bayer`). The learned
method refines each plane of that joint demosaicking, as it refines the classical image of a gray
stack (:func:`~hbis_torch.reconstruct.learned.method.reconstruct_learned_raw_bayer`). A method
declares such a raw path in its registry entry (:class:`hbis_torch.reconstruct.registry.Method`);
a method without one gets the frames demosaicked first, as RGB.
"""

from __future__ import annotations

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.sensor.cfa import bayer_masks, demosaic, mosaic

__all__ = ["COLOUR_MODES", "DEFAULT_MODE", "bayer_masks", "demosaic", "mosaic", "reconstruct_colour"]

COLOUR_MODES = ("luma", "channels")
DEFAULT_MODE = "channels"
LUMA = np.array([0.299, 0.587, 0.114])


def rgb_to_ycbcr(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) RGB in [0, 1] -> (..., 3) Y, Cb, Cr (BT.601 full range, chroma centred on 0)."""
    y = rgb @ LUMA
    return np.stack((y, (rgb[..., 2] - y) / 1.772, (rgb[..., 0] - y) / 1.402), axis=-1)


def ycbcr_to_rgb(ycc: np.ndarray) -> np.ndarray:
    y, cb, cr = ycc[..., 0], ycc[..., 1], ycc[..., 2]
    r = y + 1.402 * cr
    b = y + 1.772 * cb
    g = (y - LUMA[0] * r - LUMA[2] * b) / LUMA[1]
    return np.stack((r, g, b), axis=-1)


def upsample(image: np.ndarray, h: int) -> np.ndarray:
    """(H, W, C) -> (h H, h W, C), cubic spline, on the output grid of docs/design.md section 1 (HR
    pixel (U, V) at LR position ((U + 0.5) / h - 0.5, (V + 0.5) / h - 0.5): scipy's ``grid_mode``)."""
    from scipy.ndimage import zoom

    return zoom(np.asarray(image, dtype=np.float64), (h, h, 1), order=3, mode="nearest", grid_mode=True)


def gray_stack(stack, frames):
    """A float32 grayscale stack of ``frames`` (F, H, W) in [0, 1] with ``stack``'s geometry."""
    from hbis_torch.stack_io import Stack

    meta = {k: v for k, v in stack.meta.items() if k not in ("bit_depth", "black_level", "cfa")}
    frames = np.clip(np.asarray(frames, dtype=np.float32), 0.0, 1.0)
    return Stack(np.ascontiguousarray(frames), meta)


def reconstruct_colour(stack, method, registration: str = "auto", colour: str | None = None,
                       **kw) -> np.ndarray:
    """Super-resolve a colour stack (RGB frames, or raw Bayer frames with a ``cfa`` key).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    method : hbis_torch.reconstruct.registry.Method
        The method (the registry hands it over).
    registration : {"optics", "data", "auto"}
    colour : {"luma", "channels"} or None
        How RGB goes through the method (module docstring); None: :data:`DEFAULT_MODE`. Raw
        Bayer frames go through the method's own raw path where it has one (joint demosaicking,
        each colour at full resolution), which takes no ``colour``: one given is refused.
    **kw
        Passed to the method.

    Returns
    -------
    np.ndarray, shape (h*H, h*W, 3), float32 in [0, 1]

    Notes
    -----
    Raw Bayer frames are demosaicked jointly with the super-resolution, each colour sample
    splatted at its own position with a per-channel mask as its weight, after Wronski et al. [1]_.

    References
    ----------
    .. [1] B. Wronski, I. Garcia-Dorado, M. Ernst, D. Kelly, M. Krainin, C.-K. Liang, M. Levoy and
       P. Milanfar, "Handheld multi-frame super-resolution", ACM Transactions on Graphics 38(4)
       (SIGGRAPH 2019), article 28.
    """
    mode = DEFAULT_MODE if colour is None else colour
    if mode not in COLOUR_MODES:
        raise HbisInputError(f"colour mode must be one of {', '.join(COLOUR_MODES)}, got {colour!r}")
    if stack.meta.get("cfa") is not None:
        raw_bayer = method.raw_bayer_function()
        if raw_bayer is not None:
            if colour is not None:
                raise HbisInputError(f"the colour option (--colour) does not apply to raw Bayer frames with the "
                                     f"{method.name} method, "
                                     "which demosaicks them jointly, each colour at full resolution")
            return np.clip(raw_bayer(stack, registration=registration, **kw), 0, 1).astype(np.float32)
        rgb = demosaic(stack.to_float().numpy(), stack.meta["cfa"])
    else:
        rgb = stack.to_float().numpy()
    run = method.run_function()
    if mode == "channels":
        planes = [run(gray_stack(stack, rgb[..., c]), registration=registration, **kw) for c in range(3)]
        return np.clip(np.stack(planes, axis=-1), 0, 1).astype(np.float32)
    ycc = rgb_to_ycbcr(rgb.astype(np.float64))
    y = run(gray_stack(stack, ycc[..., 0]), registration=registration, **kw)
    chroma = upsample(ycc[stack.reference_index, ..., 1:], stack.h)
    out = ycbcr_to_rgb(np.concatenate((np.asarray(y, dtype=np.float64)[..., None], chroma), axis=-1))
    return np.clip(out, 0, 1).astype(np.float32)

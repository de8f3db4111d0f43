"""Colour stacks through any reconstruction method: RGB frames and raw Bayer frames.

RGB frames (F, H, W, 3) go through a method in one of two ways:

* ``"luma"``: the method super-resolves the luminance Y (BT.601: 0.299 R + 0.587 G + 0.114 B)
  only; the chroma (Cb, Cr) of the reference frame is interpolated (cubic spline) onto the output
  grid. One reconstruction; colour detail stays at the sensor's resolution, as in JPEG and video,
  where the eye does not see it.
* ``"channels"``: the method runs on R, G and B separately (three reconstructions, three times
  the time), each at full resolution.

The default (:data:`DEFAULT_MODE`) is ``"channels"``: on three photographs (astronaut, coffee,
chelsea; h = 4, 64 x 64 px) it scored 0.3 dB (classical) and 1.1 dB (learned) more PSNR than
``"luma"``, for about twice the time (benchmarks/bench_colour.py, docs/capture.md).

Raw Bayer frames (F, H, W) with a ``cfa`` key: the classical method demosaicks jointly: every
colour sample enters the splatting at its own position (the sample positions of its pixel), with
per-channel masks as sample weights, as in Wronski et al., SIGGRAPH 2019; each colour plane is
reconstructed from its own samples only (interpolated, not deblurred: see
:func:`_joint_demosaic_classical`). The learned method refines each plane of that joint
demosaicking, as it refines the classical image of a gray stack (:func:`_joint_demosaic_learned`).
"""

from __future__ import annotations

import numpy as np
import torch

from hbis_torch.sensor.cfa import bayer_masks, demosaic, mosaic
from hbis_torch.errors import HbisInputError

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


def _joint_demosaic_classical(stack, registration: str, messages=None, deblur: bool = True,
                              fill_factor: float | None = None, **kw) -> np.ndarray:
    """Classical SR of raw Bayer frames, each colour from its own samples at their own positions.

    Each plane is the normalized-convolution interpolation of its samples alone; the Wiener step
    is left out: it assumes a sample at every node of the h-times lattice, while a colour's
    samples fill only half (G) or a quarter (R, B) of it, in blocks, and deblurring those planes
    cost 6 to 11 dB (benchmarks/bench_colour.py, docs/capture.md).
    """
    if deblur and messages is not None:
        messages.append("raw Bayer frames: joint demosaicking interpolates each colour without the Wiener "
                        "deblurring (a colour's samples do not fill the lattice it assumes)")
    from hbis_torch.reconstruct.classical.method import stack_fill_factor
    from hbis_torch.reconstruct.classical.sr import classical_sr
    from hbis_torch.reconstruct.classical.transfer import optics_cutoff
    from hbis_torch.reconstruct.positions import (
        check_registration,
        stack_sample_positions,
    )

    check_registration(registration)
    raw = stack.to_float()
    cfa = stack.meta["cfa"]
    luma = torch.from_numpy((demosaic(raw.numpy(), cfa) @ LUMA.astype(np.float32)).astype(np.float32))
    proxy = gray_stack(stack, luma.numpy())  # registration sees a demosaicked luminance, not a mosaic
    positions, trusted = stack_sample_positions(proxy, registration, exact=True, frames=luma, messages=messages)
    frame_weight = torch.ones(raw.shape[0], dtype=torch.float64)
    if registration == "data" and raw.shape[0] > 1:
        frame_weight = trusted.to(torch.float64)
    if fill_factor is None:
        fill_factor = stack_fill_factor(stack)
    masks = torch.from_numpy(bayer_masks(cfa, *raw.shape[1:])).to(torch.float64)
    planes = [classical_sr(raw, positions, stack.h, False, weights=frame_weight[:, None, None] * m[None],
                           cutoff=optics_cutoff(stack.system), fill_factor=fill_factor, **kw).numpy()
              for m in masks]
    return np.stack(planes, axis=-1)


def _joint_demosaic_learned(stack, registration: str, messages=None, model=None, threads=None,
                            provider: str = "auto", extrapolate: bool = False, ensemble: int | None = None) -> np.ndarray:
    """The learned method on raw Bayer frames: each plane of the classical joint demosaicking
    refined by the network, with the noise of the sensor model or of one colour's sub-lattice."""
    from hbis_torch.reconstruct.classical.transfer import optics_cutoff
    from hbis_torch.reconstruct.learned import LearnedSR, estimate_noise_params, noise_params_from_meta
    from hbis_torch.reconstruct.learned.inputs import check_ensemble
    from hbis_torch.reconstruct.learned.runtime import NO_MODEL_REMEDY, classical_returned, model_to_run

    path, _, missing = model_to_run(model, stack.h)
    ensemble = check_ensemble(ensemble, stack.h)
    planes = _joint_demosaic_classical(stack, registration, messages=messages)
    if missing is not None:  # as learned_sr: the classical image, said so
        return classical_returned(planes, missing, messages, remedy=NO_MODEL_REMEDY)
    runner = LearnedSR(model=path, threads=threads, provider=provider)
    noise = noise_params_from_meta(stack.meta)
    if noise is None:  # one colour's pixels: a plain image of one sensor's noise, no mosaic in it
        noise = estimate_noise_params(stack.to_float().numpy()[:, 0::2, 0::2])
    cutoff = optics_cutoff(stack.system)
    notes: list[str] = []
    out = np.stack([runner(np.ascontiguousarray(planes[..., c]), noise, cutoff, messages=notes,
                           extrapolate=extrapolate, ensemble=ensemble) for c in range(3)], axis=-1)
    if messages is not None:
        messages.extend(dict.fromkeys(notes))  # the same line for each plane: once
    return out


def reconstruct_colour(stack, method: str, registration: str = "auto", colour: str | None = None,
                       **kw) -> np.ndarray:
    """Super-resolve a colour stack (RGB frames, or raw Bayer frames with a ``cfa`` key).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    method : str
        A key of :data:`hbis_torch.reconstruct.registry.METHODS`.
    registration : {"optics", "data", "auto"}
    colour : {"luma", "channels"} or None
        How RGB goes through the method (module docstring); None: :data:`DEFAULT_MODE`. Raw
        Bayer frames with the classical method are always demosaicked jointly, per channel.
    **kw
        Passed to the method.

    Returns
    -------
    np.ndarray, shape (h*H, h*W, 3), float32 in [0, 1]
    """
    from hbis_torch.reconstruct.registry import METHODS

    mode = DEFAULT_MODE if colour is None else colour
    if mode not in COLOUR_MODES:
        raise HbisInputError(f"colour mode must be one of {', '.join(COLOUR_MODES)}, got {colour!r}")
    run = METHODS[method]
    if stack.meta.get("cfa") is not None:
        if method == "classical":
            return np.clip(_joint_demosaic_classical(stack, registration, **kw), 0, 1).astype(np.float32)
        if method == "learned":
            return np.clip(_joint_demosaic_learned(stack, registration, **kw), 0, 1).astype(np.float32)
        rgb = demosaic(stack.to_float().numpy(), stack.meta["cfa"])
    else:
        rgb = stack.to_float().numpy()
    if mode == "channels":
        planes = [run(gray_stack(stack, rgb[..., c]), registration=registration, **kw) for c in range(3)]
        return np.clip(np.stack(planes, axis=-1), 0, 1).astype(np.float32)
    ycc = rgb_to_ycbcr(rgb.astype(np.float64))
    y = run(gray_stack(stack, ycc[..., 0]), registration=registration, **kw)
    chroma = upsample(ycc[stack.reference_index, ..., 1:], stack.h)
    out = ycbcr_to_rgb(np.concatenate((np.asarray(y, dtype=np.float64)[..., None], chroma), axis=-1))
    return np.clip(out, 0, 1).astype(np.float32)

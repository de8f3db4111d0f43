"""Colour stacks for tests and benchmarks: an RGB photograph through the forward model, one
channel at a time, optionally mosaicked by a Bayer colour filter array."""

from __future__ import annotations

import numpy as np
import torch

from hbis_torch.checks import check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.sensor.cfa import mosaic
from hbis_torch.simulate.catalog import SceneSpec
from hbis_torch.simulate.forward import grid_factor
from hbis_torch.simulate.rasters import cover_size
from hbis_torch.simulate.scenes import ImageScene
from hbis_torch.simulate.sensor import SensorModel
from hbis_torch.simulate.stacks import resolve_plan, simulate_stack
from hbis_torch.stack_io import CFA_PATTERNS, Stack


def simulate_colour_stack(rgb, system: FoveaSystem, plan, roi=None, sensor: SensorModel | None = None,
                          seed: int = 0, cfa: str | None = None, name: str = "rgb", oversample: int = 8,
                          margin_px: float = 8.0) -> tuple[Stack, np.ndarray]:
    """Simulate the scan of an RGB image, channel by channel, and its RGB ground truth.

    Parameters
    ----------
    rgb : np.ndarray, shape (rows, cols, 3)
        The scene, float in [0, 1] or uint8, spread to cover the ROI's view (as ``hbis simulate``
        spreads a photograph).
    system, plan, roi, sensor, seed, oversample, margin_px
        As for :func:`~hbis_torch.simulate.stacks.simulate_stack` (channel c's noise seed is
        ``seed + c``).
    cfa : str or None
        A Bayer pattern ("RGGB", ...): the stack holds the raw mosaic (F, H, W) and a ``cfa`` key.

    Returns
    -------
    stack : Stack
        Frames (F, H, W, 3), or (F, H, W) raw Bayer with ``cfa``.
    truth : np.ndarray, shape (h*H, h*W, 3), float32 in [0, 1]
    """
    sensor = SensorModel() if sensor is None else sensor
    image = np.asarray(rgb)
    if image.dtype == np.uint8:
        image = image.astype(np.float32) / 255
    if image.ndim != 3 or image.shape[-1] != 3:
        raise HbisInputError(f"an RGB scene must have shape (rows, cols, 3), got {image.shape}")
    if cfa is not None and cfa not in CFA_PATTERNS:
        raise HbisInputError(f"cfa must be one of {', '.join(CFA_PATTERNS)}, got {cfa!r}")
    _, _, h = resolve_plan(system, plan)
    u0, v0, w, hh = check_roi(system.camera, roi)
    pixel_mm = system.object_pixel_mm
    border = 2 * (margin_px + 4)
    spec = SceneSpec(((w + border) * pixel_mm, (hh + border) * pixel_mm), pixel_mm,
                     pixel_mm / (h * grid_factor(h, oversample)))
    size = cover_size(image.shape[:2], spec.size_mm)
    stacks, truths = [], []
    for c in range(3):
        scene = ImageScene(size_mm=size, image=torch.from_numpy(np.ascontiguousarray(image[..., c], dtype=np.float32)),
                           name=f"{name}[{'RGB'[c]}]")
        stack, truth = simulate_stack(scene, system, plan, (u0, v0, w, hh), sensor, seed=seed + c,
                                      oversample=oversample, margin_px=margin_px)
        stacks.append(stack)
        truths.append(truth)
    frames = np.stack([s.frames for s in stacks], axis=-1)
    meta = dict(stacks[0].meta)
    meta["simulation"] = {**meta["simulation"], "scene": name}
    if cfa is not None:
        frames = mosaic(frames, cfa).astype(frames.dtype)
        meta["cfa"] = cfa
    return Stack(np.ascontiguousarray(frames), meta).validate("simulated colour stack"), np.stack(truths, -1)

"""The array's frames through the data branch's sensor and forward models (no second copy).

- The nine views (and the detection frames) are box-integrated by :class:`ArrayRenderer` and then
  go through ``hbis_torch.simulate.expose`` (shot and read noise, quantisation). A binned pixel
  is the sum of b x b pixels, so it is exposed with b^2 times the full well and b times the read
  noise (digital binning). The lens PSF is left out of these views: its Airy radius (0.9 um at
  F/1.4) is a quarter of one pixel, below what a periphery view resolves.
- The fovea's scan frames are ``hbis_torch.simulate.simulate_stack`` of the array scene frozen
  at the frame's time (:meth:`PlanarScene.at`): its PSF, pixel aperture, noise and
  quantisation, its ground truth and its hbis-stack/1 metadata.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.simulate import SensorModel, expose, simulate_stack
from hbis_torch.simulate.sensor import normalise
from hbis_torch.stack_io import Stack, make_meta
from hbis_torch.system.array.scene import PlanarScene


def periphery_sensor(sensor: SensorModel, object_pixel_mm: float):
    """A ``SensorFn`` for :class:`ArrayRenderer`: ``expose`` then back to float [0, 1]."""

    def apply(ideal: Tensor, seed: int, pitch_mm: float) -> Tensor:
        b = max(1, round(pitch_mm / object_pixel_mm))
        binned = replace(sensor, full_well_e=sensor.full_well_e * b * b, read_noise_e=sensor.read_noise_e * b)
        stored = expose(ideal, binned, torch.Generator().manual_seed(int(seed)))
        return normalise(stored, binned)

    return apply


def _groups(positions: list) -> list[list[int]]:
    """Runs of consecutive frames whose scene is the same (objects at the same places)."""
    groups: list[list[int]] = []
    for k, pos in enumerate(positions):
        if groups and np.array_equal(positions[groups[-1][0]], pos):
            groups[-1].append(k)
        else:
            groups.append([k])
    return groups


@dataclass
class _Plan:
    phases_deg: Tensor
    reference_index: int
    h: int


def simulate_fovea_scan(scene: PlanarScene, system: FoveaSystem, phases_deg: Tensor, reference_index: int,
                        h: int, roi, times_s, sensor: SensorModel = SensorModel(),
                        seed: int = 0) -> tuple[Stack, np.ndarray | None]:
    """The fovea's stack for a scan whose frames are taken at ``times_s``.

    Frames taken while nothing in the scene moved are rendered together by ``simulate_stack``;
    when an object moves during the scan, each run of frames with the scene unchanged is a
    separate call. Returns the stack (hbis-stack/1, the planned phases, ``reference_index``) and
    the ground truth when the whole scan saw one scene (else None).
    """
    phases_deg = torch.as_tensor(phases_deg, dtype=torch.float64)
    positions = [tuple(np.round(obj.trajectory.position(t), 12) for obj in scene.objects) for t in times_s]
    positions = [np.array(p).reshape(-1) for p in positions]
    u0, v0, w, hh = roi
    from hbis_torch.optics import landing_map

    anchor = landing_map(system, *phases_deg[reference_index].tolist(),
                         roi=(u0 + w // 2, v0 + hh // 2, 1, 1))[0, 0].tolist()
    frames, truth, meta = [], None, None
    for g, group in enumerate(_groups(positions)):
        at = scene.at(float(times_s[group[0]]), tuple(anchor))
        ref = group.index(reference_index) if reference_index in group else 0
        stack, group_truth = simulate_stack(at, system, _Plan(phases_deg[group], ref, h), roi, sensor,
                                            seed=seed * 1000 + g)
        frames.append(stack.frames)
        meta = stack.meta
        if len(group) == len(times_s):
            truth = group_truth
    frames = np.concatenate(frames)
    extra = {k: v for k, v in meta.items() if k in ("black_level", "simulation")}
    extra["frame_times_s"] = [float(t) for t in times_s]
    new_meta = make_meta(system, h, roi, phases_deg.numpy(), bit_depth=meta.get("bit_depth"),
                         reference_index=reference_index, **extra)
    return Stack(frames, new_meta).validate("simulated fovea scan"), truth

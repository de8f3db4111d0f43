"""Alignment error (AE) of a scan plan, paper section 3.2, as fractions of the step SL.

* Axis AE of frame i: abs(landing of the optical axis - target DV^i) / SL.
* Pixel AE of frame i at pixel p: how far the scene point that p sees in frame i lies from where
  the plan wants it, relative to the point p itself saw in the reference frame (the frame at the
  initial phases). The plan wants every pixel to move with the axis (the paper's assumption in
  section 2.2), by ``offset_i`` steps. Two ways to measure it (``convention``):

  - ``"sensor"`` (default; reproduces the paper's numbers): the frame-i scene point is carried
    back through the reference frame's optics onto the sensor (exact reverse trace,
    :func:`hbis_torch.optics.sensor_position`), giving the sub-pixel shift of pixel p's sample in
    the reference image; AE = abs(shift - offset_i / h pixel) / (1/h pixel). This is the error that
    matters for super-resolution: where the sample sits in the pixel grid.
  - ``"object"``: the shift on the object plane, abs(L_i(p) - L_ref(p) - SL offset_i) / SL. Off-axis
    pixels see a larger footprint (the plane is oblique to their ray and the prisms magnify),
    so this grows toward the corners even when the sample lands perfectly on the sub-pixel grid.

Per-pixel maps use the exact tracer (not the spline-interpolated map) on every pixel of the chosen
grid: the whole sensor for ``stride=1``, else every ``stride``-th row and column plus the last
row and column (so the corners, where the AE peaks, are always in).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.checks import check_phases
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import exit_directions, land_on_plane, rays_at, sensor_position
from hbis_torch.optics.inverse import axis_landing
from hbis_torch.scan.plan import ScanPlan, phase_range_deg

CONVENTIONS = ("sensor", "object")


def _check_phases(phases_deg, frames: int) -> Tensor:
    p = check_phases(phases_deg)
    if p.shape != (frames, 2):
        raise HbisInputError(f"phases must have shape ({frames}, 2), got {tuple(p.shape)}")
    return p


def axis_alignment_error(system: FoveaSystem, plan: ScanPlan, phases_deg: Tensor | None = None) -> Tensor:
    """AE of the optical axis per frame, abs(landing - target) / SL; shape (F,), float64.

    ``phases_deg`` (F, 2) replaces the plan's phases (e.g. quantised, or read back from motors).
    """
    phases = plan.phases_deg if phases_deg is None else _check_phases(phases_deg, plan.frames)
    landing = axis_landing(system, phases[:, 0], phases[:, 1])
    return (landing - plan.targets_mm).norm(dim=-1) / plan.step_mm


def pixel_grid(system: FoveaSystem, stride: int = 1) -> tuple[Tensor, Tensor]:
    """Column and row indices (u of shape (W',), v of shape (H',)) of the evaluated pixels."""
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise HbisInputError(f"pixel stride must be an integer >= 1, got {stride!r}")
    cam = system.camera

    def axis(size: int) -> Tensor:
        idx = torch.arange(0, size, stride)
        if idx[-1] != size - 1:
            idx = torch.cat((idx, torch.tensor([size - 1])))
        return idx.to(torch.float64)

    return axis(cam.cols), axis(cam.rows)


def _frame_pixel_error(system, plan, phases, frame, u, v, rays, reference_landing, convention):
    """Pixel AE of one frame on the (H', W') grid."""
    p1, p2 = phases[frame, 0], phases[frame, 1]
    landing = land_on_plane(exit_directions(rays, p1, p2, system.prisms), system.object_distance_mm)
    offset = plan.offsets[frame]
    if convention == "object":
        miss = landing - reference_landing - plan.step_mm * offset
        return miss.norm(dim=-1) / plan.step_mm
    ref = phases[plan.reference_index]
    seen_at = sensor_position(system, landing, ref[0], ref[1])  # (H', W', 2) pixels
    shift = seen_at - torch.stack(torch.broadcast_tensors(u[None, :], v[:, None]), dim=-1)
    return (shift * plan.h - offset).norm(dim=-1)


def pixel_alignment_error(
    system: FoveaSystem,
    plan: ScanPlan,
    stride: int = 1,
    convention: str = "sensor",
    phases_deg: Tensor | None = None,
) -> dict:
    """Pixel AE over the sensor (or a dense subset), one frame at a time.

    Parameters
    ----------
    system, plan
        The system and its scan plan.
    stride : int
        1: every pixel of the sensor; k: every k-th row and column plus the last ones.
    convention : {"sensor", "object"}
        How the shift is measured (module docstring).
    phases_deg : Tensor, shape (F, 2), optional
        Phases to evaluate instead of the plan's (e.g. quantised by motor steps).

    Returns
    -------
    dict with
        ``max`` (float), ``mean`` (float, over all frames, the reference frame included, and all
        evaluated pixels), ``frame_max`` and ``frame_mean`` (Tensor (F,)), ``worst_map`` (Tensor
        (H', W'), each pixel's largest AE over the frames), ``u`` (W',) and ``v`` (H',) the
        evaluated pixel columns and rows, ``convention`` and ``stride``.
    """
    if convention not in CONVENTIONS:
        raise HbisInputError(f"pixel AE convention must be one of {CONVENTIONS}, got {convention!r}")
    phases = plan.phases_deg if phases_deg is None else _check_phases(phases_deg, plan.frames)
    u, v = pixel_grid(system, stride)
    rays = rays_at(system.camera, u[None, :], v[:, None])
    ref = phases[plan.reference_index]
    reference_landing = land_on_plane(
        exit_directions(rays, ref[0], ref[1], system.prisms), system.object_distance_mm
    )
    worst = torch.zeros(v.numel(), u.numel(), dtype=torch.float64)
    frame_max = torch.zeros(plan.frames, dtype=torch.float64)
    frame_mean = torch.zeros(plan.frames, dtype=torch.float64)
    for frame in range(plan.frames):
        err = _frame_pixel_error(system, plan, phases, frame, u, v, rays, reference_landing,
                                 convention)
        if not bool(torch.isfinite(err).all()):  # cannot happen for valid traces; never pass NaN
            raise HbisInputError(f"pixel alignment error of frame {frame} is not finite")
        torch.maximum(worst, err, out=worst)
        frame_max[frame] = err.max()
        frame_mean[frame] = err.mean()
    return {
        "max": float(frame_max.max()),
        "mean": float(frame_mean.mean()),
        "frame_max": frame_max,
        "frame_mean": frame_mean,
        "worst_map": worst,
        "u": u,
        "v": v,
        "convention": convention,
        "stride": stride,
    }


def scan_report(
    system: FoveaSystem, plan: ScanPlan, stride: int = 4, convention: str = "sensor"
) -> dict:
    """The numbers of section 3.2 for one plan, as plain Python values (the CLI's JSON).

    Keys: ``phases_deg`` (list of [phi1, phi2]), ``phase_range_deg`` [r1, r2], ``ae_axis_max``,
    ``ae_axis_mean``, ``ae_pixel_max``, ``ae_pixel_mean``, and how they were computed.
    """
    axis = axis_alignment_error(system, plan)
    pixel = pixel_alignment_error(system, plan, stride=stride, convention=convention)
    cam = system.camera
    return {
        "h": plan.h,
        "initial_phases_deg": list(plan.initial_phases_deg),
        "method": plan.method,
        "step_mm": plan.step_mm,
        "phases_deg": plan.phases_deg.tolist(),
        "phase_range_deg": phase_range_deg(plan.phases_deg).tolist(),
        "ae_axis_max": float(axis.max()),
        "ae_axis_mean": float(axis.mean()),
        "ae_pixel_max": pixel["max"],
        "ae_pixel_mean": pixel["mean"],
        "ae_pixel_convention": convention,
        "ae_pixel_grid": [int(pixel["v"].numel()), int(pixel["u"].numel())],
        "sensor": [cam.rows, cam.cols],
        "pixel_stride": stride,
    }

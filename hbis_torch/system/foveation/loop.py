"""The HBIS's two-stage operation (paper section 2.1), in simulated time.

Stage one: the fovea is parked (prisms opposed) and every camera looks for motion between
consecutive detection frames. A detection inside the fovea's scan field starts stage two: the
fovea is steered onto the object at once (coarse, then exact phases; the prisms take time to
turn) and follows it while it moves. Once the object has held still for ``settle_s`` the fovea
scans its h x h sub-pixel positions and takes one frame more at the reference phases; if that
frame and the periphery agree that nothing moved, ``reconstruct_fn`` makes the super-resolved
fovea, otherwise the scan is discarded. The periphery keeps detecting all along (during turns
and scans too) and updates the object's track; when the track leaves the scan field the prisms
park and stage one resumes. Every step is an :class:`Event` with its simulated time.

``reconstruct_fn(capture: FoveaCapture) -> np.ndarray (h H, h W)`` is a parameter so the
classical and the learned methods plug in alike (``capture.stack`` is an hbis-stack/1 Stack).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from hbis_torch.checks import check_h
from hbis_torch.errors import HbisInputError, OutOfScanField
from hbis_torch.system.array.cameras import CAMERA_NAMES, FOVEA_INDEX, PARKED_PHASES_DEG
from hbis_torch.system.foveation.detect import motion_blobs
from hbis_torch.system.foveation.steering import (PHASE_DIFFERENCE_DEG, Pointing, parked_phases_near,
                       plan_fovea_scan, slew_deg, steer)


@dataclass
class LoopConfig:
    """Timing and detection settings of the two-stage loop.

    Attributes
    ----------
    h : int, resolution improvement factor (h^2 scan frames)
    roi_size : int, side of the fovea's square ROI in full-resolution pixels
    frame_period_s : float, one frame of every camera (and one scan point)
    prism_speed_deg_s : float, how fast a prism turns when the fovea is steered or parked
    duration_s : float, simulated time to run
    threshold, min_area_px, blur_sigma_px : motion detection (see :func:`motion_blobs`)
    gate_mm : float, a detection this close to the track belongs to the tracked object
    rescan_mm : float, re-point (and scan again) when the track moved this far from the pointing
    settle_s : float, scan once the periphery has seen no motion of the object for this long
    aim_mm : float, before a scan, re-point if the track is this far from the pointing
    phase_difference_deg : (lo, hi), the steering window (see :mod:`.steering`)
    """

    h: int = 4
    roi_size: int = 128
    frame_period_s: float = 1.0 / 30.0
    prism_speed_deg_s: float = 360.0
    duration_s: float = 6.0
    threshold: float = 0.06
    min_area_px: int = 3
    blur_sigma_px: float = 1.0
    gate_mm: float = 4.0
    rescan_mm: float = 0.5
    settle_s: float = 0.1
    aim_mm: float = 0.05
    phase_difference_deg: tuple[float, float] = PHASE_DIFFERENCE_DEG

    def __post_init__(self) -> None:
        check_h(self.h)
        for name in ("frame_period_s", "prism_speed_deg_s", "duration_s", "threshold", "gate_mm",
                     "rescan_mm", "aim_mm"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value <= 0:
                raise HbisInputError(f"{name} must be a positive number, got {value!r}")


@dataclass
class Event:
    """One thing that happened: time (s), stage (1 or 2), kind, a sentence, and details."""

    t_s: float
    stage: int
    kind: str
    message: str
    data: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class FoveaCapture:
    """One scan of the fovea.

    Attributes
    ----------
    stack : hbis_torch.stack_io.Stack, the h^2 frames (hbis-stack/1, planned phases)
    pointing : Pointing, where the fovea was steered
    t_start_s, t_end_s : float, simulated time of the first frame and after the check frame
    plan_source : str, which planner made the scan
    truth : np.ndarray (h H, h W) or None, the ground truth when the device can know it
    sr : np.ndarray (h H, h W) float32 or None, the super-resolved ROI (kept scans only)
    """

    stack: object
    pointing: Pointing
    t_start_s: float
    t_end_s: float
    plan_source: str = ""
    truth: np.ndarray | None = None
    sr: np.ndarray | None = None


@dataclass
class LoopResult:
    """Everything the loop did: the event log and the fovea's scans (kept ones have ``sr``)."""

    events: list
    captures: list
    end_s: float

    def kinds(self) -> list[str]:
        return [e.kind for e in self.events]


class TwoStageLoop:
    """Runs the two stages on a device (see :mod:`.device`) for ``config.duration_s``."""

    def __init__(self, device, config: LoopConfig = LoopConfig(),
                 reconstruct_fn: Callable[[FoveaCapture], np.ndarray] | None = None) -> None:
        self.device, self.config, self.reconstruct_fn = device, config, reconstruct_fn
        self.system = device.system
        self.t = 0.0
        self.stage = 1
        self.phases = PARKED_PHASES_DEG
        self.track: np.ndarray | None = None
        self.last_motion_s = 0.0
        self.pointing: Pointing | None = None
        self.scanned = False
        self.previous: Tensor | None = None
        self.previous_phases = PARKED_PHASES_DEG
        self.events: list[Event] = []
        self.captures: list[FoveaCapture] = []
        self._outside_reported = False

    # -- bookkeeping -----------------------------------------------------------------------
    def log(self, kind: str, message: str, **data) -> None:
        self.events.append(Event(round(self.t, 6), self.stage, kind, message, data))

    def _in_field(self, point_mm) -> bool:
        try:
            steer(self.system, point_mm, self.config.roi_size,
                  phase_difference_deg=self.config.phase_difference_deg)
        except OutOfScanField:
            return False
        return True

    # -- detection -------------------------------------------------------------------------
    def _detect(self, cameras) -> list[dict]:
        """Capture one detection frame per camera; blobs of the listed cameras, on the plane."""
        with_fovea = FOVEA_INDEX in cameras
        frames = self.device.detection_frames(self.t, self.phases if with_fovea else None)
        previous, previous_phases = self.previous, self.previous_phases
        self.previous, self.previous_phases = frames, (self.phases if with_fovea else None)
        if previous is None:
            return []
        found = []
        for k in cameras:
            if k == FOVEA_INDEX and (previous_phases is None or tuple(previous_phases) != tuple(self.phases)):
                continue  # the fovea moved between the two frames: its difference is not motion
            for blob in motion_blobs(previous[k], frames[k], self.config.threshold,
                                     self.config.min_area_px, self.config.blur_sigma_px):
                point = self.device.pixel_to_plane(k, torch.tensor([blob.centre_px]), self.phases)[0]
                found.append({"camera": CAMERA_NAMES[k], "point_mm": point.numpy(), "area_px": blob.area_px})
        return sorted(found, key=lambda d: -d["area_px"])

    def _associate(self, detections: list[dict]) -> dict | None:
        """The detection of the tracked object (the largest one when nothing is tracked yet):
        the area-weighted mean of all detections near it, from every camera that saw it."""
        if not detections:
            return None
        if self.track is None:
            pick = detections[0]
        else:
            dist = [float(np.linalg.norm(d["point_mm"] - self.track)) for d in detections]
            pick = detections[int(np.argmin(dist))]
            if min(dist) > self.config.gate_mm:
                return None
        group = [d for d in detections
                 if np.linalg.norm(d["point_mm"] - pick["point_mm"]) <= self.config.gate_mm]
        weights = np.array([d["area_px"] for d in group], dtype=np.float64)
        point = (np.stack([d["point_mm"] for d in group]) * weights[:, None]).sum(0) / weights.sum()
        return {"camera": pick["camera"], "point_mm": point, "area_px": int(weights.sum())}

    def _periphery_tick(self) -> None:
        """Stage two's periphery: detect, and follow the tracked object."""
        det = self._associate(self._detect([k for k in range(9) if k != FOVEA_INDEX]))
        if det is not None:
            self.track, self.last_motion_s = det["point_mm"], self.t

    def _watch(self, until_s: float) -> None:
        """Let time pass to ``until_s``, the periphery detecting at every frame."""
        while self.t + self.config.frame_period_s <= until_s + 1e-12:
            self._periphery_tick()
            self.t += self.config.frame_period_s
        self.t = max(self.t, until_s)

    # -- stage two -------------------------------------------------------------------------
    def _slew(self, target_phases, why: str, watch: bool) -> None:
        """Turn the prisms; with ``watch`` the periphery keeps detecting while they turn."""
        turn = slew_deg(self.phases, target_phases)
        end = self.t + turn / self.config.prism_speed_deg_s
        if watch:
            self._watch(end)
        self.t = end
        self.phases = tuple(float(p) for p in target_phases)
        self.log("prisms_moved", f"prisms turned up to {turn:.2f} deg ({why})",
                 phases_deg=list(self.phases), turn_deg=turn)

    def _point(self) -> None:
        """Steer the fovea onto the track (the prisms turn while the periphery watches)."""
        cfg = self.config
        pointing = steer(self.system, self.track, cfg.roi_size, near_deg=self.phases,
                         phase_difference_deg=cfg.phase_difference_deg)
        self.log("pointed", "fovea steered onto the object: coarse (paraxial) phases ({:.3f}, {:.3f}) "
                 "deg, exact ({:.3f}, {:.3f}) deg".format(*pointing.coarse_phases_deg, *pointing.phases_deg),
                 object_mm=list(pointing.object_mm), roi=list(pointing.roi),
                 coarse_phases_deg=list(pointing.coarse_phases_deg),
                 phases_deg=list(pointing.phases_deg))
        self.pointing, self.scanned = pointing, False
        self._slew(pointing.phases_deg, "steering", watch=True)

    def _scan(self) -> None:
        cfg, pointing = self.config, self.pointing
        plan = plan_fovea_scan(self.system, cfg.h, pointing)
        count = len(plan.phases_deg)
        start = self.t
        times = [start + k * cfg.frame_period_s for k in range(count)]
        self.log("scan_started", f"sub-pixel scan of {count} frames ({plan.source})", roi=list(pointing.roi))
        stack, truth = self.device.fovea_scan(plan.phases_deg, plan.reference_index, cfg.h, pointing.roi, times)
        self.phases = tuple(plan.phases_deg[-1].tolist())
        self._watch(start + count * cfg.frame_period_s)  # the periphery detects during the scan
        reference = plan.phases_deg[plan.reference_index : plan.reference_index + 1]
        check, _ = self.device.fovea_scan(reference, 0, cfg.h, pointing.roi, [self.t])
        self.phases = tuple(reference[0].tolist())
        self._watch(self.t + cfg.frame_period_s)
        capture = FoveaCapture(stack, pointing, start, self.t, plan.source, truth)
        self.captures.append(capture)
        frames = stack.to_float()
        moved = motion_blobs(frames[plan.reference_index], check.to_float()[0], cfg.threshold,
                             4 * cfg.min_area_px, cfg.blur_sigma_px)
        drift = float(np.linalg.norm(self.track - np.asarray(pointing.object_mm)))
        if moved or drift > cfg.rescan_mm:
            why = ("the repeated reference frame differs" if moved
                   else f"the periphery saw the object move {drift:.2f} mm")
            self.log("scan_discarded", f"the object moved during the scan ({why})", drift_mm=drift)
            return
        self.scanned = True
        self.log("scan_finished", "the object held still during the scan", frames=count)
        if self.reconstruct_fn is None:
            return
        sr = np.asarray(self.reconstruct_fn(capture), dtype=np.float32)
        expected = (cfg.h * pointing.roi[3], cfg.h * pointing.roi[2])
        if sr.shape != expected:
            raise HbisInputError(f"reconstruct_fn returned shape {sr.shape}, expected {expected}")
        if not np.isfinite(sr).all():
            raise HbisInputError("reconstruct_fn returned NaN or inf")
        capture.sr = sr
        self.log("super_resolved", f"super-resolved fovea {sr.shape[1]} x {sr.shape[0]} (h = {cfg.h})",
                 capture=len(self.captures) - 1)

    def _stage_two_tick(self) -> None:
        self._periphery_tick()
        if not self._in_field(self.track):
            self.log("object_left", "the object left the fovea's scan field",
                     point_mm=[float(x) for x in self.track])
            self._slew(parked_phases_near(self.phases), "parking", watch=False)
            self.stage, self.track, self.pointing, self.previous = 1, None, None, None
            self.log("stage_one", "back to stage one: every camera detects, the fovea parked")
            return
        off = float(np.linalg.norm(self.track - np.asarray(self.pointing.object_mm)))
        settled = self.t - self.last_motion_s >= self.config.settle_s
        if off > self.config.rescan_mm or (settled and not self.scanned and off > self.config.aim_mm):
            self._point()  # follow the object; once it holds still, aim precisely before the scan
        elif settled and not self.scanned:
            self._scan()

    def _stage_one_tick(self) -> None:
        detections = self._detect(range(9))
        if not detections:
            return
        det = self._associate(detections)
        point = det["point_mm"]
        if not self._in_field(point):
            if not self._outside_reported:
                self.log("detected", f"motion seen by {det['camera']} outside the fovea's scan field",
                         camera=det["camera"], point_mm=[float(x) for x in point])
                self._outside_reported = True
            return
        self._outside_reported = False
        self.log("detected", f"motion seen by {det['camera']} inside the fovea's scan field",
                 camera=det["camera"], point_mm=[float(x) for x in point])
        self.stage, self.track, self.last_motion_s = 2, point, self.t
        self.log("stage_two", "stage two: the fovea stares at the object")
        self._point()

    # -- run -------------------------------------------------------------------------------
    def run(self) -> LoopResult:
        """Run until ``config.duration_s`` of simulated time has passed."""
        self.log("start", "stage one: every camera detects, the fovea parked",
                 phases_deg=list(self.phases))
        while self.t < self.config.duration_s:
            if self.stage == 1:
                self._stage_one_tick()
            else:
                self._stage_two_tick()
            self.t += self.config.frame_period_s
        self.log("end", "simulation ended")
        return LoopResult(self.events, self.captures, self.t)

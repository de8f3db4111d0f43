"""The HBIS's two-stage operation (paper section 2.1), in simulated time.

Stage one: the fovea is parked (prisms opposed) and every camera looks for motion between
consecutive detection frames. A detection inside the fovea's scan field starts stage two: the
fovea is steered onto the object (coarse, then exact phases; the prisms take time to turn),
scans its h x h sub-pixel positions, and one frame more at the reference phases tells whether
the object held still; if it did, ``reconstruct_fn`` makes the super-resolved fovea, otherwise
the scan is discarded and repeated at the object's new place. The periphery keeps detecting
all along, during the scan included, and updates the object's track; when the track leaves the
scan field the prisms park and stage one resumes. Every step is an :class:`Event` with its
simulated time.

``reconstruct_fn(capture: FoveaCapture) -> np.ndarray (h H, h W)`` is a parameter so the
classical and the learned methods plug in alike.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..errors import HbisInputError
from .cameras import CAMERA_NAMES, FOVEA_INDEX, PARKED_PHASES_DEG
from .detect import motion_blobs
from .steering import (PHASE_DIFFERENCE_DEG, OutOfScanField, Pointing, plan_fovea_scan,
                       parked_phases_near, slew_deg, steer)


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
    rescan_mm : float, re-point and scan again when the track moved this far since the last scan
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
    phase_difference_deg: tuple[float, float] = PHASE_DIFFERENCE_DEG

    def __post_init__(self) -> None:
        if int(self.h) != self.h or self.h < 1:
            raise HbisInputError(f"h must be a positive integer, got {self.h!r}")
        for name in ("frame_period_s", "prism_speed_deg_s", "duration_s", "threshold", "gate_mm",
                     "rescan_mm"):
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
    """One scan of the fovea: what a stack file holds, plus where it was pointed.

    Attributes
    ----------
    frames : Tensor (h^2, H, W) float32 in [0, 1], in scan order
    phases_deg : Tensor (h^2, 2) float64
    reference_index : int
    roi : (u0, v0, W, H)
    h : int
    pointing : Pointing
    t_start_s, t_end_s : float
    system : the fovea's System
    sr : np.ndarray (h H, h W) float32 or None, the super-resolved ROI
    plan_source : str, which planner made the scan
    """

    frames: Tensor
    phases_deg: Tensor
    reference_index: int
    roi: tuple
    h: int
    pointing: Pointing
    t_start_s: float
    t_end_s: float
    system: object
    sr: np.ndarray | None = None
    plan_source: str = ""


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
        self.scanned_at: np.ndarray | None = None
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
        if self.track is None or not detections:
            return detections[0] if detections else None
        dist = [float(np.linalg.norm(d["point_mm"] - self.track)) for d in detections]
        best = int(np.argmin(dist))
        return detections[best] if dist[best] <= self.config.gate_mm else None

    def _periphery_tick(self) -> None:
        """Stage two's periphery: detect, and follow the tracked object."""
        det = self._associate(self._detect([k for k in range(9) if k != FOVEA_INDEX]))
        if det is not None:
            self.track = det["point_mm"]

    # -- stage two -------------------------------------------------------------------------
    def _slew(self, target_phases, why: str, watch: bool) -> None:
        """Turn the prisms; with ``watch`` the periphery keeps detecting while they turn."""
        turn = slew_deg(self.phases, target_phases)
        end = self.t + turn / self.config.prism_speed_deg_s
        while watch and self.t + self.config.frame_period_s <= end:
            self._periphery_tick()
            self.t += self.config.frame_period_s
        self.t = end
        self.phases = tuple(float(p) for p in target_phases)
        self.log("prisms_moved", f"prisms turned up to {turn:.2f} deg ({why})",
                 phases_deg=list(self.phases), turn_deg=turn)

    def _point(self) -> Pointing:
        """Steer onto the track; re-steer (at most 3 times) while the object moved during the turn."""
        cfg = self.config
        for attempt in range(4):
            pointing = steer(self.system, self.track, cfg.roi_size, near_deg=self.phases,
                             phase_difference_deg=cfg.phase_difference_deg)
            self.log("pointed", "fovea steered onto the object: coarse phases ({:.3f}, {:.3f}) deg, "
                     "exact ({:.3f}, {:.3f}) deg after {} Newton steps".format(
                         *pointing.coarse_phases_deg, *pointing.phases_deg, pointing.iterations),
                     object_mm=list(pointing.object_mm), roi=list(pointing.roi),
                     coarse_phases_deg=list(pointing.coarse_phases_deg),
                     phases_deg=list(pointing.phases_deg))
            self._slew(pointing.phases_deg, "steering", watch=True)
            moved = float(np.linalg.norm(self.track - np.asarray(pointing.object_mm)))
            if moved <= cfg.rescan_mm or not self._in_field(self.track):
                break
        return pointing

    def _point_and_scan(self) -> None:
        cfg = self.config
        pointing = self._point()
        plan = plan_fovea_scan(self.system, cfg.h, pointing)
        start = self.t
        self.log("scan_started", f"sub-pixel scan of {len(plan.phases_deg)} frames ({plan.source})",
                 roi=list(pointing.roi))
        frames = []
        for i, phases in enumerate(plan.phases_deg.tolist()):
            frames.append(self.device.fovea_frames(torch.tensor([phases]), pointing.roi, [self.t])[0])
            self.phases = tuple(phases)
            self._periphery_tick()  # the periphery keeps detecting during the scan
            self.t += cfg.frame_period_s
        reference = tuple(plan.phases_deg[plan.reference_index].tolist())
        check = self.device.fovea_frames(torch.tensor([reference]), pointing.roi, [self.t])[0]
        self.phases = reference
        self.t += cfg.frame_period_s
        capture = FoveaCapture(torch.stack(frames), plan.phases_deg, plan.reference_index, pointing.roi,
                               cfg.h, pointing, start, self.t, self.system, plan_source=plan.source)
        moved = motion_blobs(frames[plan.reference_index], check, cfg.threshold, 4 * cfg.min_area_px,
                             cfg.blur_sigma_px)
        self.captures.append(capture)
        drift = float(np.linalg.norm(self.track - np.asarray(pointing.object_mm)))
        if not moved and drift > cfg.rescan_mm:
            self.log("scan_discarded", f"the periphery saw the object move {drift:.2f} mm during the "
                     "scan; scanning again", drift_mm=drift)
            self.scanned_at = None
            return
        if moved:
            self.log("scan_discarded", "the object moved during the scan (the repeated reference frame "
                     "differs); scanning again", moved_px=int(sum(b.area_px for b in moved)))
            self.scanned_at = None
            return
        self.scanned_at = np.asarray(pointing.object_mm)
        self.log("scan_finished", "the object held still during the scan", frames=len(frames))
        if self.reconstruct_fn is not None:
            capture.sr = np.asarray(self.reconstruct_fn(capture), dtype=np.float32)
            if capture.sr.shape != (cfg.h * pointing.roi[3], cfg.h * pointing.roi[2]):
                raise HbisInputError(f"reconstruct_fn returned shape {capture.sr.shape}, expected "
                                     f"{(cfg.h * pointing.roi[3], cfg.h * pointing.roi[2])}")
            if not np.isfinite(capture.sr).all():
                raise HbisInputError("reconstruct_fn returned NaN or inf")
            self.log("super_resolved", f"super-resolved fovea {capture.sr.shape[1]} x {capture.sr.shape[0]} "
                     f"(h = {cfg.h})", capture=len(self.captures) - 1)

    def _stage_two_tick(self) -> None:
        self._periphery_tick()
        if self.track is None:
            return
        if not self._in_field(self.track):
            self.log("object_left", "the object left the fovea's scan field",
                     point_mm=[float(x) for x in self.track])
            self._slew(parked_phases_near(self.phases), "parking", watch=False)
            self.stage, self.track, self.scanned_at = 1, None, None
            self.previous = None
            self.log("stage_one", "back to stage one: every camera detects, the fovea parked")
            return
        if self.scanned_at is None or np.linalg.norm(self.track - self.scanned_at) > self.config.rescan_mm:
            self._point_and_scan()

    def _stage_one_tick(self) -> None:
        detections = self._detect(range(9))
        if not detections:
            return
        det = detections[0]
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
        self.stage, self.track, self.scanned_at = 2, point, None
        self.log("stage_two", "stage two: steer the fovea and super-resolve")

    # -- run -------------------------------------------------------------------------------
    def run(self) -> LoopResult:
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

"""The phases file ``hbis motors scan --out`` writes, read back and checked against a scan.

One JSON object (docs/design.md section 3): ``h``, ``method``, ``initial_phases_deg``,
``reference_index``, ``targets_deg`` (planned) and ``phases_deg`` (read back from the motors), plus
``format`` = ``"hbis-motor-phases/1"`` and the ``system`` it was planned for (files written before
those keys existed are read without them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import load_json

FORMAT = "hbis-motor-phases/1"


@dataclass(frozen=True)
class ScanPhases:
    """What one scan's phases file says.

    Attributes
    ----------
    h : int
    phases_deg : np.ndarray, shape (h^2, 2)
        Read-back phases (phi1, phi2) of every frame, degrees, scan order.
    targets_deg : np.ndarray, shape (h^2, 2)
        Planned phases, degrees.
    reference_index : int
        The frame taken at the initial phases.
    initial_phases_deg : (float, float) or None
    method : str or None
        The inverse solution the plan used ("exact" or "paper").
    system : dict or None
        The ``camera``, ``prisms`` and ``object_distance_mm`` the scan was planned for.
    path : str
    """

    h: int
    phases_deg: np.ndarray
    targets_deg: np.ndarray
    reference_index: int
    initial_phases_deg: tuple[float, float] | None
    method: str | None
    system: dict | None
    path: str

    @property
    def frames(self) -> int:
        return self.h * self.h


def _pairs(data: dict, key: str, where: str, count: int) -> np.ndarray:
    try:
        array = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise HbisInputError(f"{where}: {key} must be a list of [phi1, phi2] numbers") from None
    if array.ndim != 2 or array.shape[1] != 2:
        raise HbisInputError(f"{where}: {key} must be a list of [phi1, phi2] pairs, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise HbisInputError(f"{where}: {key} contains NaN or infinite phases")
    if array.shape[0] != count:
        raise HbisInputError(f"{where}: {key} has {array.shape[0]} frames but h = {data['h']} needs {count}: "
                             "the scan is incomplete or the file is corrupt")
    return array


def read_phases(path) -> ScanPhases:
    """Read and check a phases file (one HbisInputError line naming it when anything is wrong)."""
    where = str(path)
    try:
        text = Path(path).read_bytes()
    except FileNotFoundError:
        raise HbisInputError(f"{where}: no such file") from None
    except OSError as exc:
        raise HbisInputError(f"{where}: cannot be read ({exc})") from None
    data = load_json(text, where)  # hostile-safe: huge integers, deep nesting, duplicate keys
    if not isinstance(data, dict):
        raise HbisInputError(f"{where}: not a phases file (expected one JSON object)")
    if data.get("format", FORMAT) != FORMAT:
        raise HbisInputError(f"{where}: format is {data.get('format')!r}, expected {FORMAT!r} "
                             "(the file 'hbis motors scan --out' writes)")
    missing = [k for k in ("h", "phases_deg", "reference_index") if k not in data]
    if missing:
        raise HbisInputError(f"{where}: missing key(s) {', '.join(missing)}: not the file 'hbis motors scan --out' writes")
    h = data["h"]
    if isinstance(h, bool) or not isinstance(h, int) or h < 1:
        raise HbisInputError(f"{where}: h must be a positive integer, got {h!r}")
    count = h * h
    phases = _pairs(data, "phases_deg", where, count)
    targets = _pairs(data, "targets_deg", where, count) if "targets_deg" in data else phases.copy()
    ref = data["reference_index"]
    if isinstance(ref, bool) or not isinstance(ref, int) or not 0 <= ref < count:
        raise HbisInputError(f"{where}: reference_index {ref!r} is not a frame index (0..{count - 1})")
    initial = data.get("initial_phases_deg")
    if initial is not None:
        try:
            initial = tuple(float(x) for x in initial)
        except (TypeError, ValueError):
            initial = ()
        if len(initial) != 2 or not all(math.isfinite(x) for x in initial):
            raise HbisInputError(f"{where}: initial_phases_deg must be two finite numbers")
    system = data.get("system")
    if system is not None and not isinstance(system, dict):
        raise HbisInputError(f"{where}: system must be a JSON object")
    return ScanPhases(h, phases, targets, int(ref), initial, data.get("method"), system, where)


def check_phases_for(scan: ScanPhases, system: FoveaSystem, frames: int) -> None:
    """Refuse a phases file that belongs to another scan than ``frames`` captured with ``system``.

    The file must hold one phase pair per frame, record the same system (when it records one),
    and its planned phases must be those that ``plan_scan`` gives for its h, initial phases and
    method on ``system`` (a scan planned for another camera, prism pair or object distance plans
    other phases).
    """
    from hbis_torch.stack_io import system_meta

    if frames != scan.frames:
        raise HbisInputError(f"{scan.path}: a scan of h = {scan.h} has {scan.frames} frames but {frames} were "
                             "given: frames and phases file are from different scans")
    if scan.system is not None:
        mine = system_meta(system)
        for key in ("camera", "prisms", "object_distance_mm"):
            theirs = scan.system.get(key)
            if theirs is None:
                continue
            same = (theirs == mine[key]) if not isinstance(theirs, dict) else all(
                k in mine[key] and mine[key][k] == v for k, v in theirs.items() if k != "calibration")
            if not same:
                raise HbisInputError(f"{scan.path}: the scan was planned for another system ({key} {theirs} "
                                     f"there, {mine[key]} here): give the same camera and prisms as the scan")
    if scan.initial_phases_deg is None or scan.method not in ("exact", "paper"):
        return
    from hbis_torch.scan import plan_scan

    plan = plan_scan(system, scan.h, initial_phases_deg=scan.initial_phases_deg, method=scan.method)
    planned = plan.phases_deg.numpy()
    if int(plan.reference_index) != scan.reference_index or not np.allclose(planned, scan.targets_deg, atol=1e-6):
        raise HbisInputError(f"{scan.path}: its planned phases are not those of an h = {scan.h} scan from "
                             f"{scan.initial_phases_deg} for this system: a phases file of another scan or system")

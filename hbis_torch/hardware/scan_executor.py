"""Run a scan on the prism motors: for each frame move, wait for Idle, settle, read back, capture.

Frames taken are written to a journal (a small JSON file, replaced atomically after every frame),
so a scan stopped by a fault at frame k resumes at frame k when run again with the same journal:
no frame already taken is lost and none is taken twice. Faults that leave the controller in a
known state (a dropped or garbled reply, a missed status report, a lost move line) are retried at
once; the others (``error:N``, ``ALARM:N``, a disconnect, a silent controller, a failing capture)
stop the scan with :class:`~hbis_torch.errors.ScanInterrupted`, which says where it will resume.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from hbis_torch.errors import HbisInputError, GrblMoveLost, GrblTimeout, ScanInterrupted
from hbis_torch.io_utils import atomic_write_text, load_json

JOURNAL_FORMAT = "hbis-motor-journal/1"
RETRYABLE = (GrblTimeout, GrblMoveLost)
"""Faults after which a frame is retried in place (once the replies are re-synchronised)."""


@dataclass(frozen=True)
class FrameRecord:
    """One frame taken: its index in the plan, the planned and the read-back phases (deg)."""

    index: int
    target_deg: tuple[float, float]
    phases_deg: tuple[float, float]


def _as_targets(targets_deg) -> list[tuple[float, float]]:
    t = torch.as_tensor(targets_deg, dtype=torch.float64) if not isinstance(targets_deg, torch.Tensor) \
        else targets_deg.detach().to(torch.float64)
    if t.ndim != 2 or t.shape[1] != 2 or t.shape[0] == 0:
        raise HbisInputError(f"scan phases must have shape (F, 2) with F >= 1, got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise HbisInputError("scan phases contain NaN or infinite values")
    return [(float(a), float(b)) for a, b in t.tolist()]


class ScanJournal:
    """The frames of one scan taken so far, optionally kept in a JSON file.

    Parameters
    ----------
    targets_deg : array-like, shape (F, 2)
        The planned phases (phi1, phi2) of every frame, in scan order, degrees.
    path : str or Path, optional
        Where the journal lives; None keeps it in memory only.
    """

    def __init__(self, targets_deg, path=None):
        self.targets = _as_targets(targets_deg)
        self.path = Path(path) if path is not None else None
        self.frames: list[FrameRecord] = []

    @classmethod
    def open(cls, path, targets_deg) -> "ScanJournal":
        """Load the journal at ``path`` if it exists (it must be for the same targets), else start one."""
        journal = cls(targets_deg, path)
        read = cls.read(journal.path)
        if read is None:
            return journal
        stored, frames = read
        if len(stored) != len(journal.targets) or any(
                abs(a - b) > 1e-9 for s, t in zip(stored, journal.targets) for a, b in zip(s, t)):
            raise HbisInputError(f"scan journal {journal.path} belongs to another scan (its planned phases "
                                 "differ): delete it or choose another journal file")
        journal.frames = frames
        return journal

    @staticmethod
    def read(path) -> tuple[list[tuple[float, float]], list[FrameRecord]] | None:
        """The planned phases and the frames of the journal at ``path``; None when there is none.

        Raises :class:`~hbis_torch.errors.HbisInputError` when the file is corrupt (checked
        before a scan opens the controller; whether it belongs to the scan is checked by
        :meth:`open`, once the plan is known).
        """
        path = Path(path)
        if not path.exists():
            return None
        try:
            data = load_json(path.read_text(errors="replace"), "its text")
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
            if data.get("format") != JOURNAL_FORMAT:
                raise ValueError(f"format is {data.get('format')!r}, expected {JOURNAL_FORMAT!r}")
            stored = _as_targets(data["targets_deg"])
            frames = [FrameRecord(int(f["index"]), tuple(map(float, f["target_deg"])),
                                  tuple(map(float, f["phases_deg"]))) for f in data["frames"]]
        except (ValueError, KeyError, TypeError, HbisInputError) as exc:
            raise HbisInputError(f"scan journal {path} is corrupt: {exc}") from None
        for k, frame in enumerate(frames):
            if frame.index != k or not all(math.isfinite(v) for v in frame.phases_deg):
                raise HbisInputError(f"scan journal {path} is corrupt: frame {k} is missing or not finite")
        return stored, frames

    @property
    def next_index(self) -> int:
        """Index of the first frame not taken yet."""
        return len(self.frames)

    @property
    def complete(self) -> bool:
        return len(self.frames) == len(self.targets)

    def record(self, frame: FrameRecord) -> None:
        """Add the next frame and save the journal (atomically) if it has a file."""
        if frame.index != self.next_index:
            raise HbisInputError(f"frame {frame.index} recorded out of order (next is {self.next_index})")
        self.frames.append(frame)
        self.save()

    def save(self) -> None:
        if self.path is None:
            return
        data = {"format": JOURNAL_FORMAT, "targets_deg": [list(t) for t in self.targets],
                "frames": [{"index": f.index, "target_deg": list(f.target_deg), "phases_deg": list(f.phases_deg)}
                           for f in self.frames]}
        atomic_write_text(self.path, json.dumps(data, indent=1))

    def phases_deg(self) -> torch.Tensor:
        """Read-back phases of the frames taken, (K, 2) float64, degrees."""
        return torch.tensor([f.phases_deg for f in self.frames], dtype=torch.float64).reshape(-1, 2)


@dataclass(frozen=True)
class ScanRun:
    """What :func:`run_scan` did.

    Attributes
    ----------
    phases_deg : torch.Tensor
        (F, 2) float64, the phases read back from the motors for every frame (deg): what the
        stack's ``phases_deg`` should hold.
    targets_deg : torch.Tensor
        (F, 2) float64, the planned phases (deg).
    resumed_from : int
        Index of the first frame this run took (0 for a fresh scan).
    retries : int
        Frames this run had to retry after a recoverable fault.
    """

    phases_deg: torch.Tensor
    targets_deg: torch.Tensor
    resumed_from: int
    retries: int


def run_scan(controller, targets_deg, capture: Callable[[int, tuple[float, float]], None], *,
             journal: ScanJournal | str | Path | None = None, settle_s: float = 0.1, max_retries: int = 2,
             feed_deg_per_min: float | None = None,
             on_frame: Callable[[FrameRecord, int], None] | None = None) -> ScanRun:
    """Take every frame of a scan not yet in ``journal``, in order.

    For frame k: move the prisms to ``targets_deg[k]`` the short way, wait until the controller is
    Idle there, wait ``settle_s``, read the position back, call ``capture(k, phases)``, and record
    the frame. ``capture`` should write its frame under index k (so a frame retaken after a crash
    between the capture and the journal write overwrites, never duplicates).

    Parameters
    ----------
    controller : GrblController
        An open controller (anything with ``move_to``, ``phases_deg`` and ``resync``).
    targets_deg : array-like, shape (F, 2)
        Planned phases (phi1, phi2) in scan order, degrees.
    capture : callable
        ``capture(index, (phi1, phi2))`` with the read-back phases in degrees.
    journal : ScanJournal, path or None
        Frames already taken; a path is opened with :meth:`ScanJournal.open`.
    settle_s : float
        Pause after the motors stop, before reading back and capturing (vibration), seconds.
    max_retries : int
        How many times one frame is retried after recoverable faults.
    feed_deg_per_min : float, optional
        Feed of the moves (G1); default rapid (G0).
    on_frame : callable, optional
        ``on_frame(record, frames_total)`` after each frame, e.g. to print progress.

    Raises
    ------
    ScanInterrupted
        When a fault stops the scan; ``next_frame`` is where a rerun with this journal resumes.
    """
    targets = _as_targets(targets_deg)
    if journal is None:
        journal = ScanJournal(targets)
    elif not isinstance(journal, ScanJournal):
        journal = ScanJournal.open(journal, targets)
    elif journal.targets != targets:
        raise HbisInputError("the journal given belongs to another scan (its planned phases differ)")
    if not (math.isfinite(settle_s) and settle_s >= 0):
        raise HbisInputError(f"settle time must be a finite number >= 0 s, got {settle_s!r}")
    total, start, retries = len(targets), journal.next_index, 0
    for k in range(start, total):
        target = targets[k]
        attempts = 0
        while True:
            try:
                phases = controller.move_to(*target, feed_deg_per_min=feed_deg_per_min)
                if settle_s:
                    time.sleep(settle_s)
                    phases = controller.phases_deg(near=target)
                break
            except RETRYABLE as exc:
                attempts += 1
                retries += 1
                if attempts > max_retries:
                    raise ScanInterrupted(k, total, exc, journal.path) from exc
                try:
                    controller.resync()
                except Exception as sync_exc:  # noqa: BLE001 - any failure here ends the scan
                    raise ScanInterrupted(k, total, sync_exc, journal.path) from sync_exc
            except Exception as exc:  # noqa: BLE001 - error:N, ALARM, disconnect, ...: stop cleanly
                raise ScanInterrupted(k, total, exc, journal.path) from exc
        try:
            capture(k, phases)
        except Exception as exc:  # noqa: BLE001 - the frame is not recorded; a rerun retakes it
            raise ScanInterrupted(k, total, RuntimeError(f"capture failed: {exc}"), journal.path) from exc
        record = FrameRecord(k, target, phases)
        journal.record(record)
        if on_frame is not None:
            on_frame(record, total)
    return ScanRun(journal.phases_deg(), torch.tensor(targets, dtype=torch.float64), start, retries)

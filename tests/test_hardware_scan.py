"""Scan execution under every injected fault: each ends in a recovery or in a clear error after
which a rerun with the same journal finishes the scan, with no frame lost or taken twice."""

import json
from collections import Counter

import pytest
import torch

from hbis_torch.errors import HbisInputError
from hbis_torch.hardware import (GrblAlarm, GrblCommandError, GrblController, GrblDisconnected, GrblSimulator,
                                 GrblTimeout, GrblTimeouts, ScanInterrupted)
from hbis_torch.hardware.scan_executor import ScanJournal, run_scan

FAST = GrblTimeouts(welcome_s=1.0, reply_s=0.5, status_s=0.3, homing_s=5.0, move_margin_s=1.0)
TARGETS = [(5.0 + 0.07 * i, 70.0 - 0.05 * i) for i in range(8)]  # a small scan around (5, 70)
FAULT_AT = 3


def connect(port):
    return GrblController(port, timeouts=FAST, poll_interval_s=0.01).open()


class Camera:
    """A capture callback that remembers every call."""

    def __init__(self, fail_at=None):
        self.calls, self.fail_at = [], fail_at

    def __call__(self, index, phases):
        if index == self.fail_at:
            self.fail_at = None
            raise OSError("camera timed out")
        self.calls.append((index, phases))


def check_complete(camera, journal, steps_per_deg):
    counts = Counter(index for index, _ in camera.calls)
    assert sorted(counts) == list(range(len(TARGETS))) and set(counts.values()) == {1}
    assert journal.complete and [f.index for f in journal.frames] == list(range(len(TARGETS)))
    tolerance = max(0.5 / s for s in steps_per_deg) + 1.1e-3
    for (index, phases), frame in zip(sorted(camera.calls), journal.frames):
        assert frame.phases_deg == phases  # the stack gets exactly what the capture saw
        assert all(abs(p - t) <= tolerance for p, t in zip(phases, TARGETS[index]))


@pytest.mark.parametrize("fault", ["drop_reply", "garbage", "garbled_reply"])
def test_transient_faults_are_recovered_in_place(fault, tmp_path):
    camera = Camera()
    journal = ScanJournal.open(tmp_path / "j.json", TARGETS)
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        sim.inject(fault, after_moves=FAULT_AT)
        run = run_scan(grbl, TARGETS, camera, journal=journal, settle_s=0.0)
        noise = list(grbl.noise_lines)
        check_complete(camera, journal, grbl.steps_per_deg)
    assert run.resumed_from == 0 and run.phases_deg.dtype == torch.float64 and run.phases_deg.shape == (8, 2)
    assert run.retries == (0 if fault == "garbage" else 1)
    assert (len(noise) == 1) == (fault != "drop_reply")
    assert torch.equal(run.phases_deg, ScanJournal.open(tmp_path / "j.json", TARGETS).phases_deg())


def test_reply_lost_during_a_long_move_is_recovered():
    targets = [(0.0, 0.0), (170.0, -170.0), (171.0, -171.0)]  # 170 deg: ~3 s of machine time, 1 s here
    camera = Camera()
    with GrblSimulator(speedup=3, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        sim.inject("drop_reply", after_moves=1)
        run = run_scan(grbl, targets, camera, settle_s=0.0)  # retried while the prisms still turn
    assert run.retries == 1 and [i for i, _ in camera.calls] == [0, 1, 2]
    assert run.phases_deg[1].tolist() == pytest.approx([170.0, -170.0], abs=0.02)


def _interrupted(sim, grbl, camera, path, fault, code=None):
    sim.inject(fault, after_moves=FAULT_AT, code=code)
    with pytest.raises(ScanInterrupted) as info:
        run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
    assert info.value.next_frame == FAULT_AT
    assert f"resume at frame {FAULT_AT}" in str(info.value)
    assert [i for i, _ in camera.calls] == list(range(FAULT_AT))
    assert ScanJournal.open(path, TARGETS).next_index == FAULT_AT
    return info.value


def test_error_reply_stops_clearly_and_resumes(tmp_path):
    camera, path = Camera(), tmp_path / "j.json"
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        stop = _interrupted(sim, grbl, camera, path, "error", code=33)
        assert isinstance(stop.cause, GrblCommandError) and stop.cause.code == 33
        assert "error:33 (Invalid gcode ID:33: the motion target is invalid)" in str(stop)
        run = run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        check_complete(camera, ScanJournal.open(path, TARGETS), grbl.steps_per_deg)
    assert run.resumed_from == FAULT_AT


def test_alarm_stops_clearly_and_resumes_after_reset_and_unlock(tmp_path):
    camera, path = Camera(), tmp_path / "j.json"
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        stop = _interrupted(sim, grbl, camera, path, "alarm")
        assert isinstance(stop.cause, GrblAlarm) and stop.cause.code == 1 and "Hard limit" in str(stop)
        grbl.reset()
        with pytest.raises(ScanInterrupted, match="unlock"):  # still locked: refused, nothing taken
            run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        assert len(camera.calls) == FAULT_AT
        grbl.unlock()
        run = run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        check_complete(camera, ScanJournal.open(path, TARGETS), grbl.steps_per_deg)
    assert run.resumed_from == FAULT_AT


@pytest.mark.parametrize("fault, cause", [("disconnect", GrblDisconnected), ("silent", GrblTimeout)])
def test_lost_controller_stops_clearly_and_resumes_on_a_new_one(fault, cause, tmp_path):
    camera, path = Camera(), tmp_path / "j.json"
    with GrblSimulator({22: 1}, speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        grbl.home()
        stop = _interrupted(sim, grbl, camera, path, fault)
        assert isinstance(stop.cause, cause)
    # the controller comes back (replugged, power-cycled): it must be homed before the scan goes on
    with GrblSimulator({22: 1}, speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        with pytest.raises(ScanInterrupted, match=r"home \(\$H\)"):
            run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        grbl.home()
        run = run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        check_complete(camera, ScanJournal.open(path, TARGETS), grbl.steps_per_deg)
        assert sim.machine.moves_done == len(TARGETS) - FAULT_AT  # no frame moved to twice
    assert run.resumed_from == FAULT_AT


def test_failed_capture_is_retaken_on_resume(tmp_path):
    camera, path = Camera(fail_at=FAULT_AT), tmp_path / "j.json"
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        with pytest.raises(ScanInterrupted, match="capture failed: camera timed out") as info:
            run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        assert info.value.next_frame == FAULT_AT
        run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
        check_complete(camera, ScanJournal.open(path, TARGETS), grbl.steps_per_deg)


def test_finished_journal_takes_nothing(tmp_path):
    camera, path = Camera(), tmp_path / "j.json"
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        first = run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.01)  # settle, then read back
        again = run_scan(grbl, TARGETS, camera, journal=path, settle_s=0.0)
    assert again.resumed_from == len(TARGETS) and len(camera.calls) == len(TARGETS)
    assert torch.equal(first.phases_deg, again.phases_deg)


def test_journal_of_another_scan_or_corrupt_is_refused(tmp_path):
    path = tmp_path / "j.json"
    journal = ScanJournal.open(path, TARGETS)
    journal.save()
    with pytest.raises(HbisInputError, match="belongs to another scan"):
        ScanJournal.open(path, [(1.0, 2.0)] * 8)
    path.write_text("{not json")
    with pytest.raises(HbisInputError, match="is corrupt"):
        ScanJournal.open(path, TARGETS)
    data = {"format": "hbis-motor-journal/1", "targets_deg": [list(t) for t in TARGETS],
            "frames": [{"index": 1, "target_deg": [5, 70], "phases_deg": [5, 70]}]}
    path.write_text(json.dumps(data))
    with pytest.raises(HbisInputError, match="frame 0 is missing"):
        ScanJournal.open(path, TARGETS)


@pytest.mark.parametrize("targets, message", [
    ([], "shape"), ([(1.0, 2.0, 3.0)], "shape"), ([(float("nan"), 1.0)], "NaN"),
])
def test_bad_plans_are_input_errors(targets, message):
    with pytest.raises(HbisInputError, match=message):
        run_scan(None, targets, lambda k, p: None)

"""Three behaviours of real GRBL 1.1h that the driver once got wrong, modelled by the simulator:

- D1: GRBL spends 500 ms printing ALARM:1 or ALARM:2 and then clears any reset that came
  meanwhile; the driver resets again.
- D2: GRBL drops spaces and ``( )``/``;`` comments before it parses a line; the driver matches
  ``$13=`` and the other settings on the line as GRBL will run it.
- D3: in a feed hold (or with the safety door open) GRBL runs no line but still answers ``?``; the
  driver names the hold and its remedy instead of calling the controller silent.

And two found later against the same firmware:

- D4: after a homing alarm (ALARM:6 to 10) GRBL resets itself: 500 ms printing the alarm, the
  aborted ``$H``'s ``ok``, every line sent meanwhile dropped, then its welcome. The driver reads
  through that reset, so a later ``$X`` is answered by the reset controller, not by the stale ``ok``.
- D5: GRBL stores ``$100=0`` (and reads ``0.0000000001`` as 0, a number beyond its 32-bit floats
  as inf); the driver refuses steps per degree that GRBL would store as <= 0 or not finite.
"""

import math
import time

import pytest

from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError, ScanInterrupted
from hbis_torch.hardware import GrblAlarm, GrblController, GrblHeld, GrblSimulator, GrblTimeouts
from hbis_torch.hardware.grbl_protocol import CYCLE_START, FEED_HOLD, SAFETY_DOOR, SOFT_RESET, clean_line, setting_write
from hbis_torch.hardware.scan_executor import run_scan
from hbis_torch.hardware.sim_machine import ALARM_REPORT_DELAY_S, HOMING_DURATION_S, WELCOME, GrblMachineModel
from hbis_torch.hardware.sim_settings import PRISM_STEPS_PER_DEG

FAST = GrblTimeouts(welcome_s=3.0, reply_s=0.5, status_s=0.3, homing_s=5.0, move_margin_s=1.0)


def connect(port):
    return GrblController(port, timeouts=FAST, poll_interval_s=0.01).open()


# --------------------------------------------------------------------------- D1: the alarm window


def _alarmed_model():
    m = GrblMachineModel({22: 1, 20: 1})  # homing and soft limits on: travel is -$130..0
    m.receive(b"$X\n", 0.0)
    m.take_output()
    m.receive(b"G0X5Y-70\n", 0.0)  # X beyond 0: ALARM:2, no reply to the line
    assert m.take_output() == b"ALARM:2\r\n"
    return m


def test_model_loses_a_reset_sent_within_the_alarm_window():
    m = _alarmed_model()
    m.receive(SOFT_RESET, 0.1)
    m.tick(0.3)
    assert m.take_output() == b"" and m.critical  # lost: no welcome
    m.tick(ALARM_REPORT_DELAY_S + 0.01)
    assert m.take_output() == b"[MSG:Reset to continue]\r\n"
    m.receive(SOFT_RESET, ALARM_REPORT_DELAY_S + 0.02)
    out = m.take_output().decode()
    assert "Grbl 1.1h" in out and not m.critical and m.state == "Alarm"


def test_model_soft_limits_follow_grbl_sign_convention():
    m = GrblMachineModel({22: 1, 20: 1})
    m.receive(b"$X\n", 0.0)
    m.take_output()
    m.receive(b"G0X-5Y-70\n", 0.0)  # inside -360..0: runs
    assert m.take_output() == b"ok\r\n"
    m.tick(10.0)
    m.receive(b"$J=G91X10F100\n", 10.0)  # a jog past 0 is refused, no alarm
    assert m.take_output() == b"error:15\r\n" and m.state == "Idle"
    m2 = GrblMachineModel()
    m2.receive(b"$20=1\n", 0.0)
    assert m2.take_output() == b"error:10\r\n"  # soft limits need homing


def test_reset_right_after_a_limit_alarm_is_sent_again():
    with GrblSimulator({22: 1, 20: 1}, speedup=1, max_lifetime_s=60) as sim:
        with connect(sim.port) as grbl:
            grbl.unlock()
            with pytest.raises(GrblAlarm, match="ALARM:2"):
                grbl.move_to(5.0, 70.0)  # the default phases lie outside -360..0
            start = time.monotonic()
            assert grbl.reset() == "1.1h"  # at once: the first reset falls in the window
            took = time.monotonic() - start
            assert 0.3 < took < 1.5, took
            assert grbl.status().state == "Alarm"


def test_status_at_once_after_alarm2_from_a_fresh_process(capsys):
    with GrblSimulator({22: 1, 20: 1}, speedup=1, max_lifetime_s=60) as sim:
        with connect(sim.port) as grbl:
            grbl.unlock()
            with pytest.raises(GrblAlarm):
                grbl.move_to(5.0, 70.0)
        capsys.readouterr()
        for _ in range(2):
            assert main(["motors", "--port", sim.port, "status"]) == 0
            assert "Alarm" in capsys.readouterr().out


# --------------------------------------------------------------------------- D2: line cleaning


@pytest.mark.parametrize("line, cleaned", [
    ("$1 3=1", "$13=1"), ("$13=1;x", "$13=1"), ("$13=(c)1", "$13=1"), ("g0 x1 (a; b) y2 ; z", "G0X1Y2"),
    ("/G0X1", "G0X1"), ("$100=142.222;x", "$100=142.222"), ("(only a comment)", ""),
])
def test_lines_are_cleaned_as_grbl_cleans_them(line, cleaned):
    assert clean_line(line) == cleaned


def test_setting_numbers_are_read_as_grbl_reads_them():
    assert setting_write("$013=1") == (13, 1.0)
    assert setting_write("$13.7 = 1") == (13, 1.0)
    assert setting_write("$J=G91X1F10") is None and setting_write("$$") is None


@pytest.mark.parametrize("line", ["$1 3=1", "$13=1;x", "$13=(c)1", "$013=1", "$13.5=1", " $13 = 1 "])
def test_inch_reports_are_refused_however_written(line):
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        with pytest.raises(HbisInputError, match="refusing"):
            grbl.send(line)
        assert sim.machine.settings[13] == 0


def test_a_setting_with_a_comment_is_read_again():
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        grbl.send("$100=142.222;x")
        assert sim.machine.settings[100] == pytest.approx(142.222)
        assert grbl.steps_per_deg[0] == pytest.approx(142.222)
        grbl.send("$1 01 = 71.111 (belt 2:1)")
        assert grbl.steps_per_deg[1] == pytest.approx(71.111)


@pytest.mark.parametrize("line", ["G0 X1 (why?)", "G0X1!", "$~", "G0\x18X1"])
def test_lines_holding_real_time_bytes_are_refused(line):
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        with pytest.raises(HbisInputError, match="real-time or control character"):
            grbl.send(line)


# --------------------------------------------------------------------------- D3: feed hold


def test_model_runs_no_line_in_a_hold():
    m = GrblMachineModel()
    m.receive(FEED_HOLD, 0.0)  # held while Idle too (GRBL's suspend loop)
    m.receive(b"$G\n?", 0.1)
    assert m.take_output().startswith(b"<Hold:0|")
    m.receive(CYCLE_START, 0.2)
    assert m.take_output().startswith(b"[GC:")
    m.receive(SAFETY_DOOR + b"?", 0.3)
    assert b"[MSG:Check Door]" in m.take_output() and m.held == "Door"


def test_feed_hold_mid_move_is_named_with_its_remedy():
    with GrblSimulator(speedup=20, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        sim.inject("hold")
        with pytest.raises(GrblHeld, match=r"feed hold \(Hold:0\).*cycle start \(~\)"):
            grbl.move_to(90.0, 90.0)
        with pytest.raises(GrblHeld, match="did not answer '\\$G'"):
            grbl.resync()
        grbl._write(CYCLE_START)
        grbl.resync()
        assert grbl.move_to(90.0, 90.0) == pytest.approx((90.0, 90.0), abs=0.02)


def test_a_held_scan_stops_with_exit_code_3(capsys, tmp_path):
    with GrblSimulator(speedup=20, max_lifetime_s=60) as sim:
        with connect(sim.port) as grbl:
            sim.inject("hold", after_moves=1)
            with pytest.raises(ScanInterrupted) as info:
                run_scan(grbl, [[10.0, 10.0], [40.0, 40.0], [80.0, 80.0]], lambda k, p: None, settle_s=0)
        assert isinstance(info.value.cause, GrblHeld) and info.value.next_frame == 1
        assert info.value.exit_code == 3 and "send cycle start (~)" in str(info.value)


# --------------------------------------------------------------------------- D4: homing alarm


def test_model_resets_itself_after_a_homing_alarm():
    m = GrblMachineModel({22: 1})
    m.fail_next_homing(8)
    m.receive(b"$H\n", 0.0)
    m.tick(HOMING_DURATION_S)
    assert m.take_output() == b"ALARM:8\r\n"
    m.receive(b"$X\n?" + SOFT_RESET, HOMING_DURATION_S + 0.1)  # within the 500 ms: all dropped
    m.tick(HOMING_DURATION_S + ALARM_REPORT_DELAY_S - 0.01)
    assert m.take_output() == b""
    m.tick(HOMING_DURATION_S + ALARM_REPORT_DELAY_S)
    assert m.take_output().decode() == f"ok\r\n\r\n{WELCOME}\r\n[MSG:'$H'|'$X' to unlock]\r\n"
    assert m.state == "Alarm" and "$X" not in m.received_lines
    m.receive(b"$X\n", HOMING_DURATION_S + 1.0)  # heard once GRBL has reset
    assert m.take_output() == b"[MSG:Caution: Unlocked]\r\nok\r\n" and m.state == "Idle"


@pytest.mark.parametrize("wait_s", [0.0, 0.6])
def test_unlock_after_a_homing_alarm_unlocks(wait_s):
    """At once ($X would fall in GRBL's 500 ms and be dropped) or later: $X reaches the reset controller."""
    with GrblSimulator({22: 1}, speedup=2, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        sim.fail_next_homing(9)  # at speedup 2 the cycle takes 0.5 s, GRBL's pause 0.25 s
        with pytest.raises(GrblAlarm) as info:
            grbl.home()
        time.sleep(wait_s)
        grbl.unlock()
        assert grbl.status().state == "Idle" and sim.machine.state == "Idle"
        assert list(grbl.messages)[-1] == "Caution: Unlocked" and grbl.stale_replies == 0
        assert grbl.home().state == "Idle"  # the replies are still in step with the lines
    assert info.value.code == 9 and "reset itself; home ($H) again or unlock ($X)" in str(info.value)


# --------------------------------------------------------------------------- D5: steps per degree


def test_model_stores_steps_per_degree_as_grbl_reads_them():
    m = GrblMachineModel()
    for text, stored in [("80.5", 80.5), ("0", 0.0), ("0.0000000001", 0.0), ("1" + "0" * 39, math.inf)]:
        m.receive(f"$100={text}\n".encode(), 0.0)
        assert m.take_output() == b"ok\r\n" and m.settings[100] == stored
    m.receive(b"$101=-1\n$101=1e5\n$" + b"1" * 40 + b"=1\n", 0.0)  # GRBL reads no exponent, no N > 255
    assert m.take_output() == b"error:4\r\nerror:3\r\nerror:3\r\n" and m.settings[101] == PRISM_STEPS_PER_DEG
    assert setting_write("$0000000101=0") == (100, 0.0) and setting_write("$" + "1" * 40 + "=1") is None


def test_steps_per_degree_grbl_would_hold_as_zero_or_inf_are_refused_before_sending():
    lines = ["$100=0", "$101=-1", "$100=-0", "$1 01 = 0 (off)", "$100=0.0000000001", "$101=1" + "0" * 39,
             "$0000000101=0"]  # GRBL keeps 8 digits: that is $100=0
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim, connect(sim.port) as grbl:
        for line in lines:
            with pytest.raises(HbisInputError, match=r"refusing .* steps per degree must be positive and finite"):
                grbl.send(line)
        assert [line for line in sim.machine.received_lines if "=" in line] == []
        grbl.send("$101=71.111")  # a good value still goes through and is read again
        assert grbl.steps_per_deg == (pytest.approx(PRISM_STEPS_PER_DEG, abs=1e-3), pytest.approx(71.111))

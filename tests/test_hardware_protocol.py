"""GRBL 1.1 protocol pieces without I/O: line classes, status reports, codes, G-code lines,
angle unwrapping, motion profiles, and the simulated machine driven directly (no thread)."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch.hardware.grbl_codes import ALARM_CODES, ERROR_CODES, alarm_meaning, error_meaning
from hbis_torch.hardware.grbl_protocol import (Kind, classify, format_jog, format_move, nearest_step_phase,
                                               parse_setting, parse_status, parse_welcome, unwrap_near,
                                               wrap_deg)
from hbis_torch.hardware.motion_profile import distance_at, move_duration_s
from hbis_torch.hardware.sim_machine import GrblMachineModel
from hbis_torch.hardware.sim_settings import DEFAULT_SETTINGS


@pytest.mark.parametrize("line, kind, payload", [
    ("ok", Kind.OK, "ok"),
    ("error:22", Kind.ERROR, 22),
    ("ALARM:1", Kind.ALARM, 1),
    ("[MSG:Caution: Unlocked]", Kind.MESSAGE, "Caution: Unlocked"),
    ("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", Kind.FEEDBACK, "GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0"),
    ("$100=35.556", Kind.SETTING, (100, 35.556)),
    ("$22=1", Kind.SETTING, (22, 1.0)),
    ("Grbl 1.1h ['$' for help]", Kind.WELCOME, "1.1h"),
    ("GrblHAL 1.1f ['$' or '$HELP' for help]", Kind.WELCOME, "1.1f"),
    (">G54G21:ok", Kind.STARTUP, ">G54G21:ok"),
    ("", Kind.EMPTY, ""),
    ("o\ufffd\ufffdk", Kind.NOISE, "o\ufffd\ufffdk"),
    ("<Idle|MPos:1.0,oops>", Kind.NOISE, "<Idle|MPos:1.0,oops>"),
    ("okay", Kind.NOISE, "okay"),
])
def test_classify_every_line_kind(line, kind, payload):
    got_kind, got_payload = classify(line)
    assert got_kind is kind
    if kind is not Kind.STATUS:
        assert got_payload == payload


def test_status_report_fields():
    s = parse_status("<Run|MPos:5.006,-70.003,0.000|FS:3600,0|WCO:0.000,1.500,0.000|Ov:100,100,100>")
    assert (s.state, s.substate) == ("Run", None)
    assert s.mpos == (5.006, -70.003, 0.0) and s.wpos is None and s.wco == (0.0, 1.5, 0.0)
    assert s.fields == {"FS": "3600,0", "Ov": "100,100,100"}
    hold = parse_status("<Hold:0|WPos:1.000,2.000,3.000|FS:0,0>")
    assert (hold.state, hold.substate, hold.mpos, hold.wpos) == ("Hold", 0, None, (1.0, 2.0, 3.0))


@pytest.mark.parametrize("line", [
    "<Idle|FS:0,0>",                # no position
    "<Busy|MPos:0,0,0>",            # not a GRBL state
    "<Idle|MPos:0,x,0>",            # not a number
    "<Idle,MPos:0.000,0.000,0.000>",  # GRBL 0.9 format
    "Idle|MPos:0,0,0",              # no chevrons
])
def test_malformed_status_reports_are_rejected(line):
    assert parse_status(line) is None


def test_settings_and_welcome_parsing():
    assert parse_setting("$120=360.000") == (120, 360.0)
    assert parse_setting("$N0=G54") is None
    assert parse_welcome("Grbl 0.9j ['$' for help]") == "0.9j"
    assert parse_welcome("Grbl is great") is None


def test_code_tables_cover_grbl_1_1():
    assert set(ERROR_CODES) == set(range(1, 18)) | set(range(20, 39))
    assert set(ALARM_CODES) == set(range(1, 11))  # 10: dual-axis homing fail, new in 1.1h
    assert error_meaning(9).startswith("G-code lock")
    assert alarm_meaning(1).startswith("Hard limit")
    assert "unknown error code 99" in error_meaning(99)
    assert "unknown alarm code 42" in alarm_meaning(42)


def test_move_and_jog_lines():
    assert format_move(5.0, 70.25) == "G21 G90 G53 G0 X5 Y70.25"
    assert format_move(-0.00001, 1 / 3, 120) == "G21 G90 G53 G1 X0 Y0.3333 F120"
    assert format_jog(1.5, -2, 60) == "$J=G21 G91 X1.5 Y-2 F60"
    with pytest.raises(ValueError):
        format_move(float("nan"), 0.0)


@settings(max_examples=300, deadline=None)
@given(target=st.floats(-1e4, 1e4), reference=st.floats(-1e4, 1e4))
def test_unwrap_takes_the_short_way(target, reference):
    result = unwrap_near(target, reference)
    assert abs(result - reference) <= 180.0 + 1e-9
    turns = (result - target) / 360.0
    assert abs(turns - round(turns)) < 1e-9
    assert -180.0 <= wrap_deg(target) < 180.0


def test_unwrap_examples():
    assert unwrap_near(10.0, 350.0) == pytest.approx(370.0)
    assert unwrap_near(350.0, 10.0) == pytest.approx(-10.0)
    assert unwrap_near(5.0, 725.0) == pytest.approx(725.0)


def test_nearest_step_phase_follows_the_controller_grid():
    assert nearest_step_phase(5.04, 10.0) == pytest.approx(5.0)
    assert nearest_step_phase(5.06, 10.0) == pytest.approx(5.1)
    assert nearest_step_phase(5.0, 10.0, offset_deg=0.03) == pytest.approx(5.03)  # MPos 4.97 -> 5.0
    assert nearest_step_phase(359.99, 10.0) == pytest.approx(360.0)
    # 360 deg is not a whole number of steps at 7.31 steps/deg: the grid depends on the turn
    assert nearest_step_phase(5.0, 7.31) == pytest.approx(37 / 7.31)
    assert nearest_step_phase(5.0, 7.31, machine_near_deg=365.0) == pytest.approx(2668 / 7.31 - 360.0)


def test_trapezoid_and_triangle_profiles():
    # long move: accelerate to 60 deg/s at 360 deg/s^2 (1/6 s, 5 deg), cruise, decelerate
    assert move_duration_s(90.0, 60.0, 360.0) == pytest.approx(90 / 60 + 60 / 360)
    # short move never reaches cruise speed: t = 2 sqrt(d / a)
    assert move_duration_s(1.0, 60.0, 360.0) == pytest.approx(2 * math.sqrt(1 / 360))
    assert move_duration_s(0.0, 60.0, 360.0) == 0.0
    for d in (1.0, 90.0):
        total = move_duration_s(d, 60.0, 360.0)
        ts = [total * i / 200 for i in range(201)]
        s = [distance_at(t, d, 60.0, 360.0) for t in ts]
        assert s[0] == 0.0 and s[-1] == pytest.approx(d)
        assert all(b >= a - 1e-12 for a, b in zip(s, s[1:]))
        assert max(abs(b - a) for a, b in zip(s, s[1:])) <= 60.0 * total / 200 + 1e-9  # speed <= cruise
        assert distance_at(total / 2, d, 60.0, 360.0) == pytest.approx(d / 2)  # symmetric profile


def _run(machine, line, now=0.0):
    machine.receive(line.encode() + b"\n", now)
    return machine.take_output().decode().split("\r\n")[:-1]


def test_machine_quantises_targets_to_whole_steps():
    m = GrblMachineModel({100: 10.0, 101: 7.0})
    assert _run(m, "G0 X0.26 Y1") == ["ok"]
    m.tick(100.0)
    x, y, _ = m.position_deg()
    assert x == pytest.approx(0.3) and y == pytest.approx(1.0)  # 2.6 -> 3 steps, 7 -> 7 steps
    m.receive(b"?", 100.0)
    assert m.take_output() == b"<Idle|MPos:0.300,1.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"


def test_machine_times_moves_with_feed_and_acceleration():
    m = GrblMachineModel()
    assert _run(m, "G21 G90 G53 G0 X90 Y0") == ["ok"]
    spm = DEFAULT_SETTINGS[100]
    total = move_duration_s(round(90 * spm) / spm, DEFAULT_SETTINGS[110] / 60, DEFAULT_SETTINGS[120])
    m.tick(total / 2)
    assert m.state == "Run"
    assert m.position_deg()[0] == pytest.approx(45.0, abs=1 / spm)
    m.tick(total * 1.001)
    assert m.state == "Idle" and m.position_deg()[0] == pytest.approx(90.0, abs=0.5 / spm)
    # a G1 at 600 deg/min over the same 90 deg takes longer than the rapid
    assert _run(m, "G1 X0 F600", now=total * 1.001) == ["ok"]
    m.tick(total * 2)
    assert m.state == "Run"


@pytest.mark.parametrize("line, reply", [
    ("G99 X1", "error:20"), ("X", "error:2"), ("1X", "error:1"), ("G1 X1", "error:22"),
    ("G0 G1 X1", "error:21"), ("G0 X1 X2", "error:25"), ("G4", "error:28"), ("$Q", "error:3"),
    ("$100=-1", "error:4"), ("$H", "error:5"), ("G0 X" + "1" * 80, "error:11"), ("$J=G0 X1", "error:16"),
])
def test_machine_rejects_bad_lines_with_grbl_codes(line, reply):
    assert _run(GrblMachineModel(), line) == [reply]


def test_machine_alarm_lock_and_unlock():
    m = GrblMachineModel({22: 1})  # homing enabled: starts locked
    assert m.state == "Alarm"
    assert _run(m, "G0 X1") == ["error:9"]
    assert _run(m, "$X") == ["[MSG:Caution: Unlocked]", "ok"]
    assert _run(m, "G0 X1") == ["ok"]


def test_machine_feed_hold_freezes_and_resume_continues():
    m = GrblMachineModel()
    _run(m, "G0 X90")
    total = move_duration_s(90.0, DEFAULT_SETTINGS[110] / 60, DEFAULT_SETTINGS[120])
    m.receive(b"!", total / 2)
    held = m.position_deg(total / 2)[0]
    m.tick(total * 3)
    assert m.position_deg()[0] == held and 0 < held < 90
    m.receive(b"?", total * 3)
    assert m.take_output().startswith(b"<Hold:0|")
    m.receive(b"~", total * 3)
    m.tick(total * 3 + total / 2 + 0.01)  # the rest of the move takes the other half
    assert m.state == "Idle" and m.position_deg()[0] == pytest.approx(90.0, abs=0.03)


def test_machine_dwell_answers_when_done_and_reset_mid_move_alarms():
    m = GrblMachineModel()
    assert _run(m, "G4 P0.5") == []  # G4 answers only once the dwell is over
    m.tick(0.6)
    assert m.take_output() == b"ok\r\n"
    _run(m, "G0 X90", now=1.0)
    m.receive(b"\x18", 1.1)
    lines = m.take_output().decode().split("\r\n")
    assert lines[:4] == ["ALARM:3", "", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert m.state == "Alarm" and 0 < m.position_deg()[0] < 90  # position kept where it stopped

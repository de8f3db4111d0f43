"""The GRBL driver against the simulator, through the real pyserial path (a pseudo-terminal)."""

import time

import pytest

from hbis_torch.errors import HbisInputError
from hbis_torch.hardware import (GrblAlarm, GrblCommandError, GrblController, GrblError, GrblProtocolError,
                                 GrblSimulator, GrblTimeout, GrblTimeouts)
from hbis_torch.hardware import sim_machine
from hbis_torch.hardware.grbl_protocol import SOFT_RESET

FAST = GrblTimeouts(welcome_s=1.0, reply_s=0.5, status_s=0.3, homing_s=5.0, move_margin_s=1.0)


def connect(port, **kwargs):
    return GrblController(port, timeouts=FAST, poll_interval_s=0.01, **kwargs).open()


@pytest.fixture
def sim():
    with GrblSimulator(speedup=50, max_lifetime_s=60) as s:
        yield s


@pytest.fixture
def grbl(sim):
    with connect(sim.port) as g:
        yield g


def quantised(deg, spm):
    return round(round(deg * spm) / spm, 3)


def test_handshake_reads_version_and_settings(sim, grbl):
    assert grbl.version == sim_machine.VERSION
    assert grbl.steps_per_deg == (round(sim.machine.settings[100], 3), round(sim.machine.settings[101], 3))
    assert grbl.homing_enabled is False
    assert grbl.status().state == "Idle"


def test_move_reads_back_the_step_quantised_position(sim, grbl):
    phases = grbl.move_to(5.0, 70.0)
    spm = sim.machine.settings[100]
    assert phases == pytest.approx((quantised(5.0, spm), quantised(70.0, spm)), abs=1e-9)
    assert all(abs(p - t) <= 0.5 / spm + 1e-3 for p, t in zip(phases, (5.0, 70.0)))
    assert sim.machine.received_lines[-1] == "G21 G90 G53 G0 X5 Y70"


def test_nearest_reachable_is_where_a_move_stops(sim, grbl):
    reachable = grbl.nearest_reachable(5.0, 70.0)
    assert reachable == pytest.approx((178 / 35.556, 2489 / 35.556))
    assert grbl.move_to(*reachable) == pytest.approx(reachable, abs=1e-3)


def test_moves_take_the_short_way_round(sim, grbl):
    grbl.move_to(350.0, 10.0)  # from 0: X turns -10, not +350
    assert sim.machine.position_deg()[:2] == pytest.approx((-10.0, 10.0), abs=0.02)
    grbl.move_to(10.0, 350.0)  # X +20, Y -20
    assert sim.machine.position_deg()[:2] == pytest.approx((10.0, -10.0), abs=0.02)
    for phi in (120.0, 240.0, 10.0):  # keeps turning forward: the machine position passes 360
        assert grbl.move_to(phi, 0.0) == pytest.approx((phi, 0.0), abs=0.02)
    assert sim.machine.position_deg()[0] == pytest.approx(370.0, abs=0.02)


def test_phase_offset_maps_phases_to_machine_position(sim):
    with connect(sim.port, phase_offset_deg=(90.0, -30.0)) as g:
        assert g.move_to(100.0, -20.0) == pytest.approx((100.0, -20.0), abs=0.02)
    assert sim.machine.position_deg()[:2] == pytest.approx((10.0, 10.0), abs=0.02)


def test_work_position_reports_use_the_offset():
    with GrblSimulator({10: 0}, speedup=50) as s, connect(s.port) as g:
        report = g.status()
        assert report.mpos is None and report.wpos is not None
        assert g.move_to(1.0, 2.0) == pytest.approx((1.0, 2.0), abs=0.02)


def test_rejected_line_raises_code_and_meaning(grbl):
    with pytest.raises(GrblCommandError) as info:
        grbl.send("G99")
    assert info.value.code == 20 and "Unsupported command" in str(info.value)
    assert isinstance(info.value, HbisInputError)
    grbl.move_to(1.0, 1.0)  # the stream carries on after an error


def test_homing_needs_it_enabled(grbl):
    with pytest.raises(GrblError, match=r"\$22=0"):
        grbl.home()


def test_alarm_state_blocks_moves_until_homed():
    with GrblSimulator({22: 1}, speedup=50) as s, connect(s.port) as g:
        assert g.homing_enabled and "'$H'|'$X' to unlock" in g.messages
        with pytest.raises(GrblAlarm, match=r"home \(\$H\) or unlock \(\$X\)"):
            g.move_to(5.0, 5.0)
        assert g.home().state == "Idle"
        assert g.move_to(5.0, 5.0) == pytest.approx((5.0, 5.0), abs=0.02)


def test_unlock_leaves_alarm():
    with GrblSimulator({22: 1}, speedup=50) as s, connect(s.port) as g:
        g.unlock()
        assert "Caution: Unlocked" in g.messages and g.status().state == "Idle"


def test_jog_cancel_stops_midway(sim, grbl):
    grbl.jog(90.0, 0.0, 60.0)  # 90 s of machine time, 1.8 s here
    time.sleep(0.05)
    assert grbl.status().state == "Jog"
    report = grbl.jog_cancel()
    x = grbl.machine_position(report)[0]
    assert report.state == "Idle" and 0.0 < x < 90.0
    time.sleep(0.2)
    assert grbl.machine_position(grbl.status())[0] == x  # it stays stopped


def test_alarm_during_a_move_is_reported(sim, grbl):
    sim.inject("alarm", code=1)
    with pytest.raises(GrblAlarm, match="ALARM:1 .Hard limit") as info:
        grbl.move_to(30.0, 30.0)
    assert info.value.code == 1
    # After a limit alarm GRBL hears nothing but a reset: status says it is in alarm, not silent.
    with pytest.raises(GrblAlarm, match="ALARM:1 .* no status query until a soft reset"):
        grbl.status()
    grbl.reset()
    grbl.unlock()
    assert grbl.move_to(30.0, 30.0) == pytest.approx((30.0, 30.0), abs=0.02)


def test_silent_port_times_out_with_a_clear_message():
    t0 = time.monotonic()
    with pytest.raises(GrblTimeout, match="no GRBL welcome line from 'loop://' within 1.0 s"):
        connect("loop://")
    assert time.monotonic() - t0 < 3.0


def test_missing_device_is_a_clear_error():
    with pytest.raises(GrblError, match="cannot open serial port '/dev/nonexistent-hbis-port'"):
        connect("/dev/nonexistent-hbis-port")


def test_wrong_firmware_version_is_refused(monkeypatch):
    monkeypatch.setattr(sim_machine, "WELCOME", "Grbl 0.9j ['$' for help]")
    with GrblSimulator(speedup=50) as s:
        with pytest.raises(GrblProtocolError, match="GRBL 0.9j; this driver speaks GRBL 1.1"):
            connect(s.port)


def test_inch_reports_are_refused():
    with GrblSimulator({13: 1}, speedup=50) as s:
        with pytest.raises(GrblProtocolError, match=r"\$13=0"):
            connect(s.port)


def test_unasked_restart_is_reported(sim, grbl):
    grbl._write(SOFT_RESET)  # as if the controller rebooted by itself
    with pytest.raises(GrblProtocolError, match="restarted by itself"):
        grbl.status()


def test_bad_targets_are_input_errors(grbl):
    with pytest.raises(HbisInputError, match="finite"):
        grbl.move_to(float("nan"), 0.0)
    with pytest.raises(HbisInputError, match="within"):
        grbl.move_to(1e308, 70.0)
    with pytest.raises(HbisInputError, match="one line"):
        grbl.send("G0 X1\nG0 X2")


def test_socket_url():
    with GrblSimulator(speedup=50, tcp_port=0) as s, connect(s.port) as g:
        assert s.port.startswith("socket://127.0.0.1:")
        assert g.move_to(2.0, 3.0) == pytest.approx((2.0, 3.0), abs=0.02)


def test_spy_url_logs_the_traffic(sim, tmp_path):
    log = tmp_path / "spy.txt"
    with connect(f"spy://{sim.port}?file={log}") as g:
        g.move_to(1.0, 1.0)
    text = log.read_text()  # pyserial's hex dump: the reset byte out, "G21 G90" out, "Grbl" in
    assert "TX   0000  18 " in text and "47 32 31 20 47 39 30" in text and "47 72 62 6C" in text


def test_settings_sent_later_are_read_again_and_inches_are_refused(sim, grbl):
    assert not grbl.homing_enabled
    grbl.send("$22=1")
    assert grbl.homing_enabled  # read again after the write, not only when the port opened
    grbl.send("$100=100")
    assert grbl.steps_per_deg[0] == 100
    with pytest.raises(HbisInputError, match=r"refusing '\$13=1'"):
        grbl.send("$13=1")
    assert grbl.settings.get(13, 0) == 0
    grbl.send("$13=0")

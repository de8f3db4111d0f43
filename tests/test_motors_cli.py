"""``hbis motors`` against the simulator: status, goto (and its exit code on controller errors),
home/unlock, scan (AE printed first, capture command, resume), and the simulator's own CLI."""

import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from hbis_torch.cli import main
from hbis_torch.hardware import GrblSimulator

REPO = Path(__file__).resolve().parents[1]
FAST = ["--timeout-s", "0.5", "--welcome-timeout-s", "1"]


@pytest.fixture
def sim():
    with GrblSimulator(speedup=50, max_lifetime_s=60) as s:
        yield s


def read_back(out):
    m = re.search(r"at prism 1 (\S+) deg, prism 2 (\S+) deg", out)
    return float(m.group(1)), float(m.group(2))


def motors(port, *args):
    return main(["motors", "--port", port, *FAST, *args])


def test_status_text_and_json(sim, capsys):
    assert motors(sim.port, "status") == 0
    out = capsys.readouterr().out
    assert "GRBL 1.1h" in out and ": Idle" in out and "$100 = 35.556" in out and "disabled ($22=0)" in out
    assert motors(sim.port, "status", "--json") == 0
    data = json.loads(capsys.readouterr().out)
    assert data["state"] == "Idle" and data["phases_deg"] == [0.0, 0.0] and data["steps_per_deg"] == [35.556, 35.556]


def test_goto_moves_and_prints_the_read_back(sim, capsys):
    assert motors(sim.port, "goto", "5", "-20") == 0
    assert read_back(capsys.readouterr().out) == pytest.approx((5.0, -20.0), abs=0.5 / 35.5 + 1e-3)
    assert sim.machine.position_deg()[:2] == pytest.approx((5.0, -20.0), abs=0.02)


def test_goto_reports_the_controller_error_and_exits_2(sim, capsys):
    sim.inject("error", code=15)
    assert motors(sim.port, "goto", "5", "70") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith("hbis motors: error: controller rejected 'G21 G90 G53 G0 X5 Y70': error:15 (Travel exceeded")


def test_goto_in_alarm_exits_3_with_the_way_out(capsys):
    with GrblSimulator({22: 1}, speedup=50) as s:
        assert motors(s.port, "goto", "5", "70") == 3  # a device failure, not a bad command
        assert "home ($H) or unlock ($X) first" in capsys.readouterr().err
        assert motors(s.port, "home") == 0
        assert "homed: prism 1 0.000 deg" in capsys.readouterr().out
        assert motors(s.port, "goto", "5", "70") == 0


def test_unlock_and_missing_port(sim, capsys):
    assert motors(sim.port, "unlock") == 0
    assert "unlocked" in capsys.readouterr().out
    assert main(["motors", "status"]) == 2
    assert "--port is required" in capsys.readouterr().err


class FakePlanner(types.ModuleType):
    """Stands in for hbis_torch.scan with its documented contract (plan_scan, step_alignment_error)."""

    def __init__(self):
        super().__init__("hbis_torch.scan")
        self.seen_steps = None

    def plan_scan(self, system, h, initial_phases_deg=(5.0, 70.0), method="exact"):
        a, b = initial_phases_deg
        phases = torch.tensor([[a + 0.05 * i, b - 0.05 * j] for j in range(h) for i in range(h)], dtype=torch.float64)
        return types.SimpleNamespace(phases_deg=phases, reference_index=0, step_mm=system.object_pixel_mm / h, h=h)

    def step_alignment_error(self, system, plan, steps_per_deg):
        self.seen_steps = tuple(steps_per_deg)
        return {"ae_axis_max": 0.25, "ae_axis_mean": 0.125}


def test_scan_prints_ae_first_captures_each_frame_once_and_resumes(sim, tmp_path, monkeypatch, capsys):
    planner = FakePlanner()
    monkeypatch.setitem(sys.modules, "hbis_torch.scan", planner)
    log = tmp_path / "captures.txt"
    capture = f"{sys.executable} -c \"open('{log}', 'a').write('{{index}} {{phi1}} {{phi2}}\\n')\""
    journal, out = tmp_path / "journal.json", tmp_path / "phases.json"
    args = ["scan", "--h", "3", "--phases-deg", "5,70", "--settle-s", "0", "--journal", str(journal),
            "--capture-cmd", capture, "--out", str(out)]
    sim.inject("alarm", after_moves=4)
    assert motors(sim.port, *args) == 3
    first = capsys.readouterr()
    assert "predicted alignment error with these steps (fractions of SL): ae_axis_max = 0.2500" in first.out
    assert first.out.index("predicted alignment error") < first.out.index("frame 0 (1 of 9)")
    assert "ALARM:1" in first.err and "resume at frame 4" in first.err
    assert planner.seen_steps == (35.556, 35.556)
    assert motors(sim.port, "unlock") == 0
    assert motors(sim.port, *args) == 0
    second = capsys.readouterr().out
    assert "frame 4 (5 of 9)" in second and "frame 3 (4 of 9)" not in second.split("unlocked")[-1]
    assert "scan done: 9 frames (resumed at frame 4)" in second
    lines = log.read_text().splitlines()
    assert [int(line.split()[0]) for line in lines] == list(range(9))
    data = json.loads(out.read_text())
    assert data["predicted_ae"] == {"ae_axis_max": 0.25, "ae_axis_mean": 0.125}
    assert len(data["phases_deg"]) == 9
    for line, phases in zip(lines, data["phases_deg"]):  # the capture saw what the file records
        assert [float(v) for v in line.split()[1:]] == pytest.approx(phases, abs=1e-4)
    # Run again on the finished journal: refused (exit 2, nothing moved or captured) unless --resume.
    assert motors(sim.port, *args) == 2
    err = capsys.readouterr().err
    assert "already records all 9 frames" in err and "--resume" in err and len(err.strip().splitlines()) == 1
    assert motors(sim.port, *args, "--resume") == 0
    assert "none taken now" in capsys.readouterr().out
    assert len(log.read_text().splitlines()) == 9


def test_scan_dry_run_needs_no_controller(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "hbis_torch.scan", FakePlanner())
    assert main(["motors", "scan", "--h", "2", "--dry-run", "--steps-per-deg", "100,50"]) == 0
    out = capsys.readouterr().out
    assert "4 frames" in out and "0.01000 deg (prism 1), 0.02000 deg (prism 2)" in out


def test_scan_with_the_real_planner_reaches_the_predicted_phases(sim, tmp_path, capsys):
    scan = pytest.importorskip("hbis_torch.scan")  # skipped only where the planner is missing
    from hbis_torch.config import FoveaSystem

    out = tmp_path / "phases.json"
    assert motors(sim.port, "scan", "--h", "3", "--settle-s", "0", "--journal", str(tmp_path / "j.json"),
                  "--out", str(out)) == 0
    text = capsys.readouterr().out
    assert "initial phases moved to the motor step grid: (5, 70) -> (5.0062, 70.0022) deg" in text
    assert text.index("predicted alignment error") < text.index("frame 0 (1 of 9)") and "scan done: 9 frames" in text
    data = json.loads(out.read_text())
    plan = scan.plan_scan(FoveaSystem(), 3, initial_phases_deg=tuple(data["initial_phases_deg"]))
    predicted = scan.step_alignment_error(FoveaSystem(), plan, data["steps_per_deg"])
    assert data["predicted_ae"]["ae_axis_max"] == pytest.approx(predicted["ae_axis_max"], rel=1e-12)
    # The motors stop on the very steps the prediction rounded to. Two printouts blur it: MPos has
    # 3 decimals (0.0005 deg), and so has $101 (35.556 for the stored 35.5556, 1.2e-5 relative:
    # 0.0009 deg at 70 deg). A step is 0.028 deg, so a wrong step would show as >= 0.026 deg.
    read_back = torch.tensor(data["phases_deg"], dtype=torch.float64)
    blur = 5e-4 + 71.0 * 5e-4 / 35.556
    assert (read_back - predicted["quantised_phases_deg"]).abs().max() <= blur
    achieved = scan.axis_alignment_error(FoveaSystem(), plan, read_back)
    assert float(achieved.max()) == pytest.approx(predicted["ae_axis_max"], abs=0.01)


def test_simulator_command_line_serves_a_port_and_stops_by_itself(capsys):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "hbis_torch.hardware.simulator", "--speedup", "50",
                             "--duration", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=REPO)
    try:
        port = proc.stdout.readline().split(" serving on ")[1].strip()
        assert port.startswith("/dev/")
        assert motors(port, "goto", "10", "20") == 0
        assert read_back(capsys.readouterr().out) == pytest.approx((10.0, 20.0), abs=0.5 / 35.5 + 1e-3)
        assert proc.wait(timeout=10) == 0  # --duration ends it
        assert proc.stderr.read() == ""
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=10)


def test_a_silent_controller_exits_3_a_refused_line_2(sim, capsys):
    """Exit codes a script can act on: 3 when the bench failed (retry after fixing it), 2 when the
    command was wrong."""
    sim.inject("silent")
    assert motors(sim.port, "goto", "5", "70") == 3
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hbis motors: error: ") and "Traceback" not in err


def test_a_feed_hold_exits_3_naming_cycle_start(sim, capsys):
    sim.inject("hold")
    assert motors(sim.port, "goto", "90", "90") == 3
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "feed hold (Hold:0)" in err and "cycle start (~)" in err


def test_help_documents_exit_code_3(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "3 a device failed" in " ".join(capsys.readouterr().out.split())


@pytest.mark.skipif(os.name != "posix", reason="POSIX device files")
@pytest.mark.parametrize("kind", ["regular file", "directory", "/dev/null", "fifo"])
def test_a_port_that_can_never_be_serial_exits_2(kind, tmp_path, capsys):
    """A wrong --port is a bad argument (2): no retry mends it. A missing device stays 3 (unplugged)."""
    port = {"regular file": tmp_path / "port.txt", "directory": tmp_path, "/dev/null": Path(os.devnull),
            "fifo": tmp_path / "fifo"}[kind]
    if kind == "regular file":
        port.write_text("not a tty\n")
    elif kind == "fifo":
        os.mkfifo(port)
    assert motors(str(port), "status") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{str(port)!r} cannot be a serial port: it is " in err
    if kind == "regular file":
        assert port.read_text() == "not a tty\n"  # opened by nothing, written by nothing
    assert motors(str(tmp_path / "ttyUSB9"), "status") == 3
    assert "cannot open serial port" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--phases-deg", "1e9,0"], "--phases-deg must lie within"),
    (["--capture-cmd", "echo {foo}"], "--capture-cmd may only use {index}"),
    (["--camera", "webcam:0", "--frames", "f{index}.tif"], "--camera must be"),
    (["--camera", "sim:no-such-scene", "--frames", "f{index}.tif"], "unknown scene"),
    (["--journal", "CORRUPT"], "is corrupt"),
])
def test_scan_arguments_are_checked_before_the_controller_is_reset(extra, message, sim, tmp_path, monkeypatch,
                                                                   capsys):
    monkeypatch.setitem(sys.modules, "hbis_torch.scan", FakePlanner())
    monkeypatch.chdir(tmp_path)
    (tmp_path / "CORRUPT").write_text("{not json")
    assert motors(sim.port, "scan", "--h", "2", *extra) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and message in captured.err and len(captured.err.strip().splitlines()) == 1
    assert sim.machine.received_lines == []  # the port was not opened: no reset, no $$
    assert (tmp_path / "CORRUPT").read_text() == "{not json"


def test_scan_help_gives_the_form_of_negative_phases(monkeypatch, capsys):
    with pytest.raises(SystemExit):
        main(["motors", "scan", "--help"])
    assert "--phases-deg=-0.2,-70" in " ".join(capsys.readouterr().out.split())
    monkeypatch.setitem(sys.modules, "hbis_torch.scan", FakePlanner())
    assert main(["motors", "scan", "--h", "2", "--dry-run", "--steps-per-deg", "100,100",
                 "--phases-deg=-0.2,-70"]) == 0
    assert "from phases (-0.2000, -70.0000) deg" in capsys.readouterr().out

"""`hbis scan`: the docs/design.md section 2 JSON, the text table, and one-line errors (exit 2)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hbis_torch.cli import main

CONTRACT_KEYS = {"phases_deg", "phase_range_deg", "ae_axis_max", "ae_pixel_max", "ae_pixel_mean"}
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("method", ["paper", "exact"])
def test_scan_json_has_the_contract_keys(capsys, method):
    argv = ["scan", "--h", "7", "--phases-deg", "5,70", "--method", method, "--json",
            "--pixel-stride", "160"]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert CONTRACT_KEYS <= set(data)
    assert len(data["phases_deg"]) == 49 and all(len(p) == 2 for p in data["phases_deg"])
    assert data["phases_deg"][24] == [5.0, 70.0]
    assert len(data["phase_range_deg"]) == 2 and max(data["phase_range_deg"]) == pytest.approx(0.62, abs=0.01)
    if method == "paper":
        assert 0.005 < data["ae_axis_max"] < 0.01
    else:
        assert data["ae_axis_max"] < 1e-6
    assert 0.3 < data["ae_pixel_max"] < 0.8 and 0.03 < data["ae_pixel_mean"] < 0.12


def test_scan_motor_options(capsys):
    argv = ["scan", "--h", "4", "--phases-deg", "45,130", "--json", "--pixel-stride", "300",
            "--steps-per-deg", "200,400", "--ae-bound", "0.1"]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["steps_per_deg"] == [200.0, 400.0]
    assert 0 < data["ae_axis_max_quantised"] < 0.2
    assert data["required_steps_per_deg"] > 10


def test_scan_text_output(capsys):
    assert main(["scan", "--h", "2", "--phases-deg=-30,100", "--pixel-stride", "300"]) == 0
    out = capsys.readouterr().out
    assert "frame   3" in out and "ae_pixel_mean" in out


@pytest.mark.parametrize(
    "args,message",
    [
        (["--h", "0", "--phases-deg", "5,70"], "--h: must be an integer from 1 to 16"),
        (["--h", "3", "--phases-deg", "5"], "two numbers"),
        (["--h", "3", "--phases-deg", "5,nan"], "finite"),
        (["--h", "3", "--phases-deg", "5,6"], "maximum deviation"),
        (["--h", "3", "--phases-deg", "5,70", "--pixel-stride", "0"], "stride"),
        (["--h", "3", "--phases-deg", "5,70", "--steps-per-deg", "0,1"], "steps per degree"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, args, message):
    try:
        rc = main(["scan", *args])
    except SystemExit as exc:  # argparse's own range checks
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_bad_input_from_the_console_has_no_traceback():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "hbis_torch", "scan", "--h", "3", "--phases-deg",
                           "5,6"], capture_output=True, text=True, env=env, cwd=ROOT)
    assert proc.returncode == 2
    assert "maximum deviation" in proc.stderr and "Traceback" not in proc.stderr

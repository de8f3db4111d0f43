"""The `hbis` command line: design JSON, figures, demo, and one-line errors with exit code 2."""

import json
import subprocess
import sys

import pytest

from hbis_torch.cli import main

KEYS = {"theta_h_deg", "theta_v_deg", "phi_min_h_deg", "phi_min_v_deg", "varphi_h_max_deg",
        "varphi_v_max_deg", "fov_h_deg", "fov_v_deg", "fer_h", "fer_v", "varphi_c_deg", "H",
        "h_max", "bsr"}


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "hbis_torch", *args], capture_output=True, text=True)


def test_design_json_has_the_contract_keys(capsys):
    assert main(["design", "--json", "--varphi-h-deg", "15", "--varphi-v-deg", "10"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert KEYS <= set(data)
    assert set(data["bsr"]) == {str(h) for h in range(1, data["h_max"] + 1)}
    assert data["varphi_c_deg"] == pytest.approx(17.78, abs=0.01)


def test_design_flags_change_the_system(capsys):
    assert main(["design", "--json", "--alpha-deg", "1", "--n", "1.5"]) == 0
    assert json.loads(capsys.readouterr().out)["fer_h"] == pytest.approx(2.9, abs=0.05)


@pytest.mark.parametrize("args", [["design", "--n", "1.0"], ["design", "--alpha-deg", "95"],
                                  ["design", "--rows", "0"], ["design", "--n", "nan"],
                                  ["design", "--nope"], ["design", "--alpha-deg", "x"]])
def test_bad_arguments_exit_2_with_one_line(args):
    proc = run_cli(*args)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_figures_and_demo_write_files(tmp_path):
    assert main(["figures", "--only", "design", "--out", str(tmp_path / "fig")]) == 0
    names = {p.name for p in (tmp_path / "fig").iterdir()}
    assert {"fig4_fov_fer.png", "fig6_bsr.png", "fig10_fov_layout.png"} <= names
    assert all((tmp_path / "fig" / n).stat().st_size > 10_000 for n in names)

"""The results writer records where a result came from, atomically, in both kinds of file."""

import json
from pathlib import Path

import pytest

from hbis_torch import provenance as pv


def test_json_results_carry_command_commit_date_machine(tmp_path):
    out = tmp_path / "r.json"
    prov = pv.write_results(out, {"psnr": 31.5}, argv=["--quick", "a b"])
    data = json.loads(out.read_text())
    assert data["psnr"] == 31.5
    assert data["provenance"] == prov == pv.read_provenance(out)
    assert prov["command"].endswith("--quick 'a b'")
    assert len(prov["commit"]) == 40 or prov["commit"] == "unknown"
    assert prov["dirty"] in (True, False, None)
    assert prov["date"][:2] == "20" and prov["date"].endswith("+00:00")
    assert prov["machine"]["cores"] >= 1 and prov["machine"]["cpu"]
    assert set(prov["machine"]["flags"]) <= set(pv.CPU_FLAGS)
    assert "python" in prov["versions"] and "torch" in prov["versions"]


def test_list_payload_is_wrapped(tmp_path):
    out = tmp_path / "cells.json"
    pv.write_results(out, [1, 2], argv=[])
    assert json.loads(out.read_text())["results"] == [1, 2]


def test_markdown_header_round_trips_and_is_replaced_not_stacked(tmp_path):
    out = tmp_path / "table.md"
    pv.write_results(out, "| a | b |\n| 1 | 2 |\n", argv=["x"])
    first = out.read_text()
    assert first.splitlines()[1].startswith("_Made by `")
    assert pv.read_provenance(out)["command"].endswith(" x")
    # Rewriting a file that already has a header keeps one header and the body.
    pv.write_results(out, first, argv=["y"])
    text = out.read_text()
    assert text.count("<!-- provenance: ") == 1 and text.endswith("| 1 | 2 |\n")
    assert pv.read_provenance(out)["command"].endswith(" y")


def test_older_results_say_what_is_unknown(tmp_path):
    out = tmp_path / "old.txt"
    prov = pv.older_provenance("python benchmarks/bench_x.py", note="load 1.2")
    pv.write_results(out, "42 s\n", prov=prov)
    back = pv.read_provenance(out)
    assert back["recorded_before_provenance"] and back["commit"] == "unknown"
    assert "commit, date and machine unknown" in out.read_text()


def test_failed_write_leaves_the_old_file(tmp_path):
    out = tmp_path / "r.json"
    out.write_text("old\n")
    with pytest.raises(TypeError):
        pv.write_results(out, {1j: 1}, argv=[])  # a key JSON cannot hold
    assert out.read_text() == "old\n"


def test_printed_text_is_recorded_only_on_success(tmp_path, capsys):
    out = tmp_path / "printed.txt"
    with pv.record_printed(out, argv=["--n", "3"]):
        print("median 1.5 ms")
    assert "median 1.5 ms" in capsys.readouterr().out  # still printed
    assert out.read_text().endswith("median 1.5 ms\n") and pv.read_provenance(out)["command"].endswith("--n 3")
    failed = tmp_path / "failed.txt"
    with pytest.raises(RuntimeError), pv.record_printed(failed, argv=[]):
        print("half")
        raise RuntimeError
    assert not failed.exists()


def test_every_benchmark_writes_its_results_through_the_provenance_writer():
    # A results file written any other way would not say where it came from.
    import ast

    repo = Path(__file__).resolve().parents[1]  # the checkout (pv.REPO is the installed tree)
    scripts = sorted((repo / "benchmarks").glob("bench_*.py")) + [repo / "training" / "eval_matrix.py"]
    writers = {"write_results", "record_printed", "run_recorded", "finish"}
    raw = {"write_text", "atomic_write_text", "dump"}  # json.dump, Path.write_text, the bare atomic writer
    # bench_real_bursts also rewrites the generated table of its docs page (write_doc), which is a page,
    # not a results file; time_onnx_session runs in bare environments without this package (it prints).
    # bench_scale_out's main writes the listing of its inputs into its work folder (not a result).
    allowed_raw = {("bench_real_bursts.py", "write_doc"), ("bench_scale_out.py", "main")}
    for script in scripts:
        tree = ast.parse(script.read_text())
        called = {(n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", None))
                  for n in ast.walk(tree) if isinstance(n, ast.Call)}
        assert called & writers, f"{script.name} never calls write_results / record_printed / run_recorded / finish"
        for fn in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)):
            for n in ast.walk(fn):
                if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr in raw:
                    assert (script.name, fn.name) in allowed_raw, f"{script.name}:{n.lineno} writes {n.func.attr} directly"


def test_a_command_holding_an_html_comment_end_cannot_break_the_header(tmp_path):
    out = tmp_path / "r.md"
    pv.write_results(out, "body\n", prov=pv.older_provenance("python x.py > a.txt -->"))
    assert out.read_text().splitlines()[0].count("-->") == 1
    assert pv.read_provenance(out)["command"] == "python x.py > a.txt -->"

"""training/variants_ab.py: variants start as the same function and are scored as the held-out matrix scores."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "training" / "variants_ab.py"


def run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300)


def test_bad_variants_and_existing_out_are_refused_before_any_work(tmp_path, load_script, capsys):
    """In this process (a process of the script pays its imports, seconds each), then one process
    for the exit code."""
    script = load_script("training/variants_ab.py")
    out = tmp_path / "ab.json"
    for variants in ("a:wide:4:0", "a:32:4", "a:32:4:yes", "a:32:4:0:dense", "a:32:4:0:ir:1"):
        assert script.main(["--variants", variants, "--out", str(out)]) == 2, variants
        assert "name:width:blocks:blur" in capsys.readouterr().err and not out.exists(), variants
    assert script.main(["--variants", "s:32:4:0", "--out", str(out)]) == 2
    assert "'s'" in capsys.readouterr().err
    out.write_text("kept")
    exists = run("--out", str(out))
    assert exists.returncode == 2 and "exists" in exists.stderr and out.read_text() == "kept"


def test_a_tiny_run_scores_every_variant_and_the_shipped_model(tmp_path):
    out = tmp_path / "ab.json"
    result = run("--h", "2", "--variants", "a:8:1:0,b:8:1:1,c:8:2:0:ir", "--pool", "4", "--val", "1", "--cells", "1",
                 "--steps", "2", "--batch", "2", "--procs", "1", "--out", str(out))
    assert result.returncode == 0, result.stderr[-2000:]
    record = json.loads(out.read_text())
    assert record["steps"] == 2
    first = record["history"][0]
    assert first["step"] == 0 and first["a"] == first["b"]  # the blur channel starts at zero weight
    assert first["c"] == first["a"]  # any body: the last convolution starts at zero
    assert record["macs"]["c"] == 9 * 5 * 8 + 2 * (8 * 32 + 9 * 32 + 32 * 8) + 9 * 8 * 4  # head, 2 blocks, tail
    (cell,) = record["cells"]
    assert cell["condition"].startswith("F1.4, 10k e-, reference frame 0") and cell["photo"] == "camera"
    assert cell["s"] > 1.0  # the shipped h = 2 model, as in benchmarks/results/eval_matrix.json
    assert all(abs(cell[k]) < 0.5 for k in "abc")  # two steps: next to the classical image

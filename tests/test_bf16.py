"""--precision bf16: the float32 file run by OpenVINO in bfloat16, on CPUs with bf16 units
(float32, said so, on others); refused before any work where OpenVINO cannot run it."""

import numpy as np
import pytest

from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError
from hbis_torch import provenance
from hbis_torch.reconstruct.learned import LearnedSR, runtime
from hbis_torch.reconstruct.learned.runtime import check_model, check_precision, openvino_installed, with_precision
from hbis_torch.training.data import build_pool, whole_example

needs_openvino = pytest.mark.skipif(not openvino_installed(), reason="the openvino package is not installed")


def cpu_reports_bf16() -> bool:
    """Whether the CPU has bf16 units, asked of the CPU itself (/proc/cpuinfo) rather than of the
    detection under test; OpenVINO's answer only where /proc/cpuinfo is missing."""
    flags = provenance.machine()["flags"]
    return flags["avx512_bf16"] or flags["amx_bf16"] if flags else runtime.bf16_available()


def test_bf16_runs_the_float32_file_and_refuses_an_int8_one():
    path, meta = check_model(None, 4)
    assert with_precision(path, meta, "bf16") == (path, meta)
    int8, int8_meta = with_precision(path, meta, "int8")
    with pytest.raises(HbisInputError, match="is an int8 model; --precision bf16 needs its float32 file"):
        with_precision(int8, int8_meta, "bf16")


def test_bf16_needs_openvino(monkeypatch):
    with pytest.raises(HbisInputError, match="--provider cpu .* has no bf16"):
        check_precision("bf16", "cpu")
    monkeypatch.setattr(runtime, "openvino_installed", lambda: False)
    with pytest.raises(HbisInputError, match=r"OpenVINO, which is not installed: pip install 'hbis-torch\[openvino\]'"):
        check_precision("bf16", "auto")
    for precision in (None, "fp32", "int8"):  # the other precisions run anywhere
        check_precision(precision, "cpu")


@needs_openvino
@pytest.mark.parametrize("has_bf16", [True, False])
def test_bf16_output_is_near_the_float_one(has_bf16, monkeypatch):
    if has_bf16 and not cpu_reports_bf16():
        # the bfloat16 case needs the units; the float32 fallback is the other case
        pytest.skip("this CPU has no bf16 units (AMX or AVX-512 BF16): the bfloat16 path cannot run here")
    base, noise, _ = whole_example(build_pool(4, 1, 40, seed=99)[0], 4)
    fp32 = LearnedSR(h=4, provider="cpu").infer(base, noise)
    if not has_bf16:  # a CPU without bf16 units: float32 in OpenVINO, and a note saying so
        monkeypatch.setattr(runtime, "cpu_has_bf16", lambda core: False)
    net = LearnedSR(h=4, precision="bf16")
    assert net.provider == "openvino" and net.path.name == "hbis_sr_h4.onnx"
    diff = net.infer(base, noise) - fp32
    assert np.isfinite(diff).all()
    rms = float(np.sqrt(np.mean(diff**2)))
    if has_bf16:
        assert net.precision == "bf16" and net.note is None
        assert 0 < rms < 2e-3  # rounded to bfloat16 (not the float graph), and close
    else:
        assert net.precision == "fp32" and "no bf16 units" in net.note
        assert rms < 1e-5


@needs_openvino
def test_bf16_on_a_cpu_without_it_says_so(monkeypatch):
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda core: False)
    net = LearnedSR(h=4, precision="bf16")
    notes: list = []
    image = np.full((96, 96), 0.5, np.float32)
    net(image, (1e-4, 1e-6), messages=notes, extrapolate=True)
    assert notes == ["this CPU has no bf16 units (AMX or AVX-512 BF16): the network ran in float32"]


def test_cli_refuses_bf16_on_the_cpu_kernels_before_any_work(tmp_path, capsys):
    from test_learned_cli import simulated_stack_file

    stack, _ = simulated_stack_file(tmp_path, 4)
    out = tmp_path / "sr.tif"
    assert main(["reconstruct", str(stack), "--method", "learned", "--precision", "bf16", "--provider", "cpu",
                 "--out", str(out)]) == 2
    assert "has no bf16" in capsys.readouterr().err
    assert not out.exists()


@needs_openvino
def test_cli_bf16(tmp_path):
    from test_learned_cli import simulated_stack_file

    stack, _ = simulated_stack_file(tmp_path, 4)
    out = tmp_path / "sr.tif"
    assert main(["reconstruct", str(stack), "--method", "learned", "--precision", "bf16", "--out", str(out)]) == 0
    assert out.is_file()


@needs_openvino
def test_openvino_runs_from_several_threads_at_once():
    # hbis reconstruct --out-dir --jobs N runs stacks on threads that share one session: each
    # thread gets its own infer request (one request would be busy, or mix the threads' tiles)
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(0)
    inputs = [(rng.random((1, 16, 48, 40), dtype=np.float32) - 0.5, np.full((1, 1, 48, 40), 0.05, np.float32))
              for _ in range(8)]
    net = LearnedSR(h=4, provider="openvino")
    alone = [net.infer(*x) for x in inputs]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda x: net.infer(*x), inputs * 4))
    for k, out in enumerate(together):
        np.testing.assert_array_equal(out, alone[k % len(inputs)])

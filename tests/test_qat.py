"""Quantisation-aware fine-tuning (hbis_torch.training.qat): the rounding it trains with is the
int8 file's, the ranges reach the int8 file, and train_sr.py runs and resumes with them."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import numpy_helper

from hbis_torch.reconstruct.learned import default_model_path
from hbis_torch.reconstruct.learned.runtime import read_model_metadata
from hbis_torch.training.export import export_model
from hbis_torch.training.net import build_net
from hbis_torch.training.qat import (QuantSim, observe_ranges, onnx_tensor_ranges, scale_and_zero_point,
                                     tensor_names)
from hbis_torch.training.quantize import calibration_inputs, quantize_model
from test_training import history, run


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A small plain network with a non-zero correction, its float file carrying its ranges, and
    the int8 file quantize_model made from it."""
    torch.manual_seed(3)
    net = build_net({"h": 2, "width": 8, "blocks": 2, "kind": "plain"}).eval()
    torch.nn.init.normal_(net.tail.weight, std=0.05)
    feeds = calibration_inputs(2, count=1, size=20)
    ranges = observe_ranges(net, feeds)
    folder = tmp_path_factory.mktemp("qat")
    path = folder / "tiny.onnx"
    export_model(net, path, {"qat_ranges": ranges})
    return net, feeds, ranges, path, quantize_model(path, count=1)


def test_every_rounded_tensor_is_found_in_the_shipped_graphs():
    for h, tier in ((2, "fast"), (4, "best")):
        model = onnx.load(str(default_model_path(h, tier)))
        blocks = json.loads(read_model_metadata(default_model_path(h, tier))["model_config"])["blocks"]
        names = tensor_names(blocks)
        found = onnx_tensor_ranges(model, {name: (0.0, 1.0) for name in names})
        assert len(found) == len(names) == 3 * blocks + 3  # each name its own tensor


def test_the_int8_file_takes_the_trained_ranges(tiny):
    _, _, ranges, path, int8 = tiny
    meta = read_model_metadata(int8)
    assert json.loads(meta["calibration"])["activation_ranges"] == "quantisation-aware training's"
    q = onnx.load(str(int8))
    values = {t.name: numpy_helper.to_array(t) for t in q.graph.initializer}
    by_tensor = onnx_tensor_ranges(onnx.load(str(path)), ranges)
    quantized = {node.input[0]: node for node in q.graph.node if node.op_type == "QuantizeLinear"}
    assert set(by_tensor) <= set(quantized)
    for tensor, (lo, hi) in by_tensor.items():
        scale, zero = scale_and_zero_point(lo, hi)
        node = quantized[tensor]
        assert float(values[node.input[1]]) == pytest.approx(scale, rel=1e-6)
        assert int(values[node.input[2]]) == zero


def test_quant_sim_rounds_as_much_as_the_int8_file(tiny):
    """The emulation and the int8 file round the same tensors to the same steps, so they depart
    from the float network by about as much (not bit for bit: the integer kernels round their
    sums their own way, and a different rounding early changes which way later values round)."""
    net, feeds, ranges, _, int8 = tiny
    session = ort.InferenceSession(str(int8), providers=["CPUExecutionProvider"])
    feed = calibration_inputs(2, count=1, size=20, seed=77)[0]  # not the calibration's
    base, noise = (torch.from_numpy(feed[k]) for k in ("base", "noise"))
    with torch.no_grad():
        float_out = net(base, noise).numpy()
        sim_out = QuantSim(net, ranges)(base, noise).numpy()
    int8_out = session.run(None, feed)[0]
    sim_err = np.sqrt(np.mean((sim_out - float_out) ** 2))
    int8_err = np.sqrt(np.mean((int8_out - float_out) ** 2))
    assert sim_err > 0 and 0.5 < sim_err / int8_err < 2.0


def test_quant_sim_refuses_missing_ranges(tiny):
    net, _, ranges, _, _ = tiny
    with pytest.raises(ValueError, match="lack"):
        QuantSim(net, {k: v for k, v in ranges.items() if k != "tail"})


def test_qat_run_keeps_its_ranges_across_a_resume(tmp_path):
    shipped = default_model_path(2).with_suffix(".pt")
    args = ["width=32", "blocks=4", "qat=True", "qat_calibration_count=1", f"init_from={shipped}", "eval_interval=2"]
    first = run(args + ["max_steps=2"], tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    assert "quantisation-aware" in first.stdout
    ranges = torch.load(tmp_path / "ckpt.pt", weights_only=True)["qat_ranges"]
    assert set(ranges) == set(tensor_names(4))
    second = run(args + ["max_steps=4"], tmp_path)
    assert second.returncode == 0 and "resumed from" in second.stdout, second.stderr[-2000:]
    assert torch.load(tmp_path / "ckpt.pt", weights_only=True)["qat_ranges"] == ranges
    assert [r["step"] for r in history(tmp_path)] == [0, 2, 4]


def test_qat_with_the_float_network_as_teacher_runs(tmp_path):
    """qat_teacher=True: the loss's target is init_from's float network's output; the run trains
    and validates as a plain quantisation-aware one does."""
    shipped = default_model_path(2).with_suffix(".pt")
    result = run(["width=32", "blocks=4", "qat=True", "qat_teacher=True", "qat_calibration_count=1",
                  f"init_from={shipped}", "eval_interval=2", "max_steps=2"], tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert [r["step"] for r in history(tmp_path)] == [0, 2]
    assert json.loads((tmp_path / "history.json").read_text())["config"]["qat_teacher"] is True


def test_qat_needs_a_trained_network_and_float32(tmp_path):
    result = run(["qat_teacher=True", "max_steps=1"], tmp_path / "teacher")
    assert result.returncode != 0 and "qat_teacher=True is for qat=True" in result.stderr
    result = run(["qat=True", "max_steps=1"], tmp_path)
    assert result.returncode != 0 and "give it init_from" in result.stderr
    shipped = default_model_path(2).with_suffix(".pt")
    result = run(["qat=True", "bf16=True", f"init_from={shipped}", "max_steps=1"], tmp_path / "bf16")
    assert result.returncode != 0 and "drop bf16=True" in result.stderr

"""int8 models: the quantisation (hbis_torch.training.quantize), the runtime's choice of file
(--precision) and the shipped int8 files."""

import json
import shutil

import numpy as np
import onnx
import pytest

from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned import LearnedSR, default_model_path, int8_path, read_model_metadata
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.reconstruct.learned.runtime import check_model, with_precision
from hbis_torch.training.data import build_pool, whole_example
from hbis_torch.training.quantize import float_activations, float_nodes, quantize_model


@pytest.mark.parametrize("h, tier", [(2, "fast"), (3, "fast"), (4, "fast"), (7, "fast"), (2, "best"), (4, "best"),
                                     (7, "best")])
def test_shipped_int8_files_come_from_their_models_fine_tuned(h, tier):
    """Each shipped int8 file is its float model fine-tuned through the int8 rounding
    (hbis_torch.training.qat) and quantised with the ranges it trained with: the same network
    and format, a training of its own."""
    model = default_model_path(h, tier)
    path = int8_path(model)
    meta, fp32 = read_model_metadata(path), read_model_metadata(model)
    assert path.stat().st_size < model.stat().st_size  # int8 weights: smaller than float32
    assert meta["precision"] == "int8" and meta["quantized_from"].startswith(model.stem + ".qat.onnx sha256 ")
    same = ("format", "h", "frames", "normalisation", "opset", "parameters")
    assert {k: meta[k] for k in same} == {k: fp32[k] for k in same}
    assert Architecture.from_metadata(meta) == Architecture.from_metadata(fp32)
    config = json.loads(meta["training_config"])
    assert config["qat"] is True and config["init_from"].endswith(model.stem + ".pt")
    assert json.loads(meta["calibration"])["activation_ranges"] == "quantisation-aware training's"
    assert float(meta["val_psnr_db"]) > float(meta["val_classical_psnr_db"]) + 0.1  # not refused as unhelpful


def test_image_path_stays_float():
    model = onnx.load(str(default_model_path(4)))
    kept = float_nodes(model)
    ops = {node.name: node.op_type for node in model.graph.node}
    # the image's Sub, the split first convolution and its sum, the residual Add, DepthToSpace
    assert [ops[name] for name in kept] == ["Sub", "Conv", "Conv", "Add", "Add", "DepthToSpace"]
    quantized = onnx.load(str(int8_path(default_model_path(4))))
    residual = [n for n in quantized.graph.node if n.op_type == "Add" and "base" in n.input]
    assert len(residual) == 1  # the input itself, not a dequantised copy, is added to the correction


def test_int8_output_is_near_the_float_one():
    base, noise, _ = whole_example(build_pool(4, 1, 40, seed=99)[0], 4)
    fp32 = LearnedSR(h=4, provider="cpu", precision="fp32").infer(base, noise)
    int8 = LearnedSR(h=4, provider="cpu", precision="int8")
    assert int8.precision == "int8" and int8.path.name.endswith(".int8.onnx")
    diff = int8.infer(base, noise) - fp32
    assert np.isfinite(diff).all()
    assert 0 < np.sqrt(np.mean(diff**2)) < 5e-3  # it is quantised (not the float graph), and close


def test_float_activations_twin_clips_without_rounding(tmp_path):
    """The twin of an int8 file runs its weights and its activations' clips in float: no
    QuantizeLinear left; near the int8 file's output, but not equal to it (the rounding is
    gone); and its activations are clipped (the pairs stand for the ReLUs too): with no clip,
    the output moves far from the int8 file's."""
    int8 = int8_path(default_model_path(4))
    twin = float_activations(int8, tmp_path / "twin.onnx")
    graph = onnx.load(str(twin)).graph
    assert not [n for n in graph.node if n.op_type == "QuantizeLinear"]
    assert len([n for n in graph.node if n.op_type == "Clip"]) == len(
        [n for n in onnx.load(str(int8)).graph.node if n.op_type == "QuantizeLinear"])
    base, noise, _ = whole_example(build_pool(4, 1, 40, seed=99)[0], 4)
    rounded = LearnedSR(int8, provider="cpu").infer(base, noise)
    diff = LearnedSR(twin, provider="cpu").infer(base, noise) - rounded
    assert np.isfinite(diff).all() and 0 < np.sqrt(np.mean(diff**2)) < 2e-3
    unclipped = onnx.load(str(twin))
    for node in unclipped.graph.node:
        if node.op_type == "Clip":
            del node.input[1:]
    onnx.save(unclipped, str(tmp_path / "unclipped.onnx"))
    far = LearnedSR(tmp_path / "unclipped.onnx", provider="cpu").infer(base, noise) - rounded
    assert np.sqrt(np.mean(far**2)) > 10 * np.sqrt(np.mean(diff**2))
    with pytest.raises(HbisInputError, match="exists"):
        float_activations(int8, twin)
    with pytest.raises(HbisInputError, match="not an int8 file"):
        float_activations(default_model_path(4), tmp_path / "other.onnx")


def test_precision_picks_the_file_or_refuses(tmp_path):
    path, meta = check_model(None, 4)
    assert with_precision(path, meta)[0] == path  # the default: the file named
    assert with_precision(path, meta, "int8")[0] == int8_path(path)
    int8, int8_meta = with_precision(path, meta, "int8")
    assert with_precision(int8, int8_meta)[0] == int8  # an int8 file named runs as it is
    with pytest.raises(HbisInputError, match="needs its float32 file"):
        with_precision(int8, int8_meta, "fp32")
    lone = tmp_path / "lone.onnx"
    shutil.copy(path, lone)
    with pytest.raises(HbisInputError, match="no int8 file for lone.onnx"):
        with_precision(lone, meta, "int8")
    with pytest.raises(HbisInputError, match="unknown precision"):
        with_precision(path, meta, "fp16")


def test_quantize_any_model_file_and_refuse_to_overwrite(tmp_path):
    model = tmp_path / "mine_h4.onnx"
    shutil.copy(default_model_path(4), model)
    out = quantize_model(model, count=1, method="minmax")
    assert out == tmp_path / "mine_h4.int8.onnx"
    meta = read_model_metadata(out)
    assert meta["precision"] == "int8" and meta["h"] == "4"
    before = out.read_bytes()
    with pytest.raises(HbisInputError, match="exists"):
        quantize_model(model, count=1)
    assert out.read_bytes() == before
    with pytest.raises(HbisInputError, match="int8 already"):
        quantize_model(out, tmp_path / "again.onnx")


def test_cli_precision(tmp_path, capsys):
    from test_learned_cli import simulated_stack_file

    stack, _ = simulated_stack_file(tmp_path, 4)
    out = tmp_path / "sr.tif"
    assert main(["reconstruct", str(stack), "--method", "learned", "--precision", "int8", "--out", str(out)]) == 0
    assert out.is_file()
    assert main(["reconstruct", str(stack), "--precision", "int8", "--out", str(tmp_path / "c.tif")]) == 2
    assert "only for --method learned" in capsys.readouterr().err

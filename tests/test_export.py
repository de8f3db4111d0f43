"""ONNX export: opset, dynamic height/width, metadata, parity with torch at another size."""

import json
import os

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned import OPENVINO, LearnedSR, available_providers, read_model_metadata
from hbis_torch.training.export import CHECK_SIZE, EXPORT_SIZE, OPSET, TOLERANCE, check_parity, export_model
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.training.net import HbisSRNet, build_net, space_to_depth


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    model = HbisSRNet(3, width=12, blocks=2).eval()
    for p in model.tail.parameters():  # the tail starts at zero; make the whole net matter
        torch.nn.init.normal_(p, std=0.1)
    path = tmp_path_factory.mktemp("onnx") / "net.onnx"
    info = {"git_commit": "abc123", "val_psnr": 30.5, "step": 7, "config": {"h": 3}}
    export_model(model, path, info)
    return model, path


@pytest.mark.parametrize("provider", available_providers())
def test_parity_at_a_size_other_than_the_export_size(exported, provider):
    model, path = exported
    assert tuple(CHECK_SIZE) != tuple(EXPORT_SIZE)
    assert check_parity(path, model, provider=provider) <= TOLERANCE
    assert check_parity(path, model, size=(9, 130), provider=provider) <= TOLERANCE


def test_auto_takes_the_cpu_kernels_and_openvino_is_asked_for(exported):
    assert LearnedSR(exported[1]).provider == LearnedSR(exported[1], provider="cpu").provider == "cpu"
    if "openvino" in available_providers():
        assert LearnedSR(exported[1], provider="openvino").provider == "openvino"


def test_unknown_or_missing_provider_is_a_clear_input_error(exported, monkeypatch):
    import onnxruntime as ort

    from hbis_torch.reconstruct.learned import runtime

    with pytest.raises(HbisInputError, match="unknown execution provider 'gpu'"):
        LearnedSR(exported[1], provider="gpu")
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    monkeypatch.setattr(runtime, "openvino_installed", lambda: False)
    assert available_providers() == ["cpu"]
    with pytest.raises(HbisInputError, match=r"OpenVINO is not installed: pip install 'hbis-torch\[openvino\]'"):
        LearnedSR(exported[1], provider="openvino")
    assert LearnedSR(exported[1]).provider == "cpu"


def test_auto_falls_back_to_the_cpu_kernels_when_openvino_refuses_the_model(exported, monkeypatch):
    import onnxruntime as ort

    from hbis_torch.reconstruct.learned import runtime

    real = ort.InferenceSession

    def refusing_openvino(path, options, providers):
        if any(OPENVINO in p for p in providers):
            raise RuntimeError("OpenVINO cannot compile this model")
        return real(path, options, providers=providers)

    class RefusingOpenVINO:
        def __init__(self, path, threads):
            raise RuntimeError("OpenVINO cannot compile this model")

    monkeypatch.setattr(ort, "get_available_providers", lambda: [OPENVINO, "CPUExecutionProvider"])
    monkeypatch.setattr(ort, "InferenceSession", refusing_openvino)
    for package in (False, True):  # onnxruntime's OpenVINO provider; the openvino package
        monkeypatch.setattr(runtime, "openvino_installed", lambda package=package: package)
        monkeypatch.setattr(runtime, "_OpenVINOSession", RefusingOpenVINO)
        assert LearnedSR(exported[1]).provider == "cpu"
        with pytest.raises(HbisInputError, match="cannot load ONNX model"):
            LearnedSR(exported[1], provider="openvino")


@pytest.mark.skipif(not __import__("hbis_torch.reconstruct.learned.runtime", fromlist=["x"]).openvino_installed(),
                    reason="the openvino package (extra 'openvino') is not installed")
def test_the_openvino_package_runs_the_model_beside_onnxruntime(exported):
    """With the openvino extra, 'openvino' runs the model in the openvino package, whose output and
    metadata match onnxruntime's CPU kernels."""
    from hbis_torch.reconstruct.learned.runtime import _OpenVINOSession

    runner, cpu = LearnedSR(exported[1], provider="openvino"), LearnedSR(exported[1], provider="cpu")
    assert runner.provider == "openvino" and isinstance(runner.session, _OpenVINOSession)
    assert runner.metadata == cpu.metadata and runner.h == 3
    rng = np.random.default_rng(0)
    base = rng.random((1, 9, 11, 17), dtype=np.float32)
    noise = rng.random((1, 1, 11, 17), dtype=np.float32)
    assert np.abs(runner.infer(base, noise) - cpu.infer(base, noise)).max() < 1e-4


def test_height_and_width_are_dynamic_and_the_file_is_self_contained(exported):
    _, path = exported
    proto = onnx.load(str(path))
    assert [o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")] == [OPSET]
    for tensor in proto.graph.input:
        dims = tensor.type.tensor_type.shape.dim
        assert dims[2].dim_param and dims[3].dim_param and not dims[2].dim_value
    assert not list(path.parent.glob("*.data"))
    ops = {n.op_type for n in proto.graph.node}
    assert not ops & {"DeformConv", "Inverse", "SpaceToDepth"}


def test_metadata_props_carry_h_frames_normalisation_and_commit(exported):
    _, path = exported
    meta = read_model_metadata(path)
    assert meta["h"] == "3" and meta["frames"] == "9"
    assert "[0, 1]" in meta["normalisation"]
    assert meta["training_commit"] == "abc123"
    assert len(meta["export_commit"]) >= 7
    config = json.loads(meta["model_config"])
    assert {k: config[k] for k in ("h", "width", "blocks")} == {"h": 3, "width": 12, "blocks": 2}
    runner = LearnedSR(path)
    assert runner.h == 3
    assert runner.halo > 2 * 2 + 2  # wider than the receptive field


def test_tiled_inference_equals_one_pass(exported):
    model, path = exported
    runner = LearnedSR(path, tile=16)
    g = torch.Generator().manual_seed(3)
    base = torch.rand(1, 9, 40, 37, generator=g)
    noise = torch.rand(1, 1, 40, 37, generator=g)
    tiled = runner.run_network(base[0].numpy(), noise[0].numpy())
    with torch.no_grad():
        whole = model(base, noise)[0, 0].numpy()
    assert np.abs(tiled - whole).max() <= TOLERANCE
    # the halo is the receptive field's radius plus one: the tiles give the one pass's bits
    one_pass = LearnedSR(path, tile=64).run_network(base[0].numpy(), noise[0].numpy())
    assert runner.halo == runner.architecture.halo and np.array_equal(tiled, one_pass)


def test_space_to_depth_survives_the_dynamo_exporter(tmp_path):
    import onnxruntime as ort

    class Packer(torch.nn.Module):
        def forward(self, x):
            return space_to_depth(x, 4)

    rows, cols = torch.export.Dim("rows", min=1, max=512), torch.export.Dim("cols", min=1, max=512)
    path = tmp_path / "s2d.onnx"
    torch.onnx.export(Packer().eval(), (torch.randn(1, 2, 16, 24),), str(path), dynamo=True,
                      dynamic_shapes={"x": {2: 4 * rows, 3: 4 * cols}}, external_data=False)
    x = torch.randn(1, 2, 28, 12)
    got = ort.InferenceSession(str(path)).run(None, {"x": x.numpy()})[0]
    np.testing.assert_array_equal(got, F.pixel_unshuffle(x, 4).numpy())


def test_corrupt_model_file_is_a_clear_input_error(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file")
    with pytest.raises(HbisInputError, match="cannot load ONNX model"):
        LearnedSR(bad)


def test_depth_to_space_is_one_onnx_node_and_only_the_exact_pattern_is_rewritten(exported, tmp_path):
    from hbis_torch.training.onnx_rewrite import fuse_depth_to_space

    model, path = exported
    proto = onnx.load(str(path))
    ops = [n.op_type for n in proto.graph.node]
    assert ops.count("DepthToSpace") == 1 and "Transpose" not in ops and "Reshape" not in ops
    (node,) = [n for n in proto.graph.node if n.op_type == "DepthToSpace"]
    attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    assert attrs == {"blocksize": 3, "mode": b"CRD"}
    assert read_model_metadata(path)["graph_rewrites"] == "DepthToSpace x1"  # h = 3: no split head
    # Without the rewrite the exporter's reshape/transpose is there; a wrong block size leaves it.
    plain = tmp_path / "plain.onnx"
    export_model(model, plain, rewrite=False)
    proto = onnx.load(str(plain))
    assert "Transpose" in [n.op_type for n in proto.graph.node]
    assert fuse_depth_to_space(proto, 2) == 0 and fuse_depth_to_space(proto, 4) == 0
    assert fuse_depth_to_space(proto, 3) == 1
    onnx.checker.check_model(proto)


@pytest.mark.parametrize("h", [4, 7])
def test_the_first_convolution_is_split_from_h_4_with_the_same_outputs(h, tmp_path):
    torch.manual_seed(h)
    model = HbisSRNet(h, width=16, blocks=1).eval()
    torch.nn.init.normal_(model.tail.weight, std=0.1)
    path = tmp_path / "net.onnx"
    assert export_model(model, path)["graph_rewrites"] == "DepthToSpace x1, split head"
    graph = onnx.load(str(path)).graph
    weights = {t.name: t.dims for t in graph.initializer}
    heads = [list(weights[n.input[1]])[:2] for n in graph.node if n.op_type == "Conv" and n.name.startswith("head_")]
    main = h * h - h * h % 16  # 16 of 16 image channels at h = 4, 48 of 49 at h = 7
    assert heads == [[16, main], [16, h * h - main + 1]]
    assert "head.weight" not in weights and [n.op_type for n in graph.node].count("Split") == (h * h > main)
    for size in (CHECK_SIZE, (9, 130)):
        assert check_parity(path, model, size=size, provider="cpu") <= TOLERANCE


def test_the_split_head_keeps_onnxruntimes_blocked_layout_through_the_residual_sums(tmp_path):
    """Why the head is split: with it, the residual sums run fused into the convolutions in the
    blocked channel layout; without it, each block's input is reordered in and out of it."""
    import onnxruntime as ort

    from hbis_torch.training.onnx_rewrite import fuse_depth_to_space

    torch.manual_seed(0)
    model = HbisSRNet(4, width=32, blocks=3).eval()
    plain, split = tmp_path / "plain.onnx", tmp_path / "split.onnx"
    export_model(model, plain, rewrite=False)
    proto = onnx.load(str(plain))
    assert fuse_depth_to_space(proto, 4) == 1  # the only difference left is the split
    onnx.save(proto, str(plain))
    export_model(model, split)

    def optimised_ops(path):
        options = ort.SessionOptions()
        options.optimized_model_filepath = str(path.with_suffix(".optimised.onnx"))
        ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        return [n.op_type for n in onnx.load(options.optimized_model_filepath).graph.node]

    before, after = optimised_ops(plain), optimised_ops(split)
    reorders = ("ReorderInput", "ReorderOutput")
    if not any(op in reorders for op in before):
        pytest.skip("onnxruntime has no blocked-layout kernels on this CPU")
    assert sum(op in reorders for op in after) == 2  # the image in, the correction out
    assert sum(op in reorders for op in before) >= 2 * 3  # one in and one out for each block
    assert after.count("Add") < before.count("Add")  # the residual sums fused into the convolutions


def test_reexport_from_a_weights_file_keeps_the_training_metadata(tmp_path):
    from hbis_torch.training.export import export

    torch.manual_seed(1)
    model = HbisSRNet(2, width=8, blocks=1).eval()
    first = export_model(model, tmp_path / "first.onnx", {"git_commit": "f00d", "val_psnr": 31.25, "step": 42,
                                                          "config": {"h": 2, "lr": 0.001},
                                                          "history": [{"base_psnr": 30.5}, {"base_psnr": 30.5}]})
    assert first["val_classical_psnr_db"] == "30.500"
    weights = tmp_path / "weights.pt"
    torch.save({"model": model.state_dict(), "model_config": model.config(), "metadata": first}, weights)
    again = export(weights, tmp_path / "again.onnx")
    for key in ("training_commit", "val_psnr_db", "val_classical_psnr_db", "training_steps", "training_config",
                "model_config", "h"):
        assert again[key] == first[key], key
    assert again["training_commit"] == "f00d" and json.loads(again["training_config"])["lr"] == 0.001
    assert check_parity(tmp_path / "again.onnx", model) <= TOLERANCE


def test_two_onnxruntime_distributions_are_warned_about(exported, monkeypatch):
    from hbis_torch.reconstruct.learned import runtime as learned

    monkeypatch.setattr(learned, "onnxruntime_distributions", lambda: ["onnxruntime", "onnxruntime-openvino"])
    with pytest.warns(RuntimeWarning, match="both onnxruntime and onnxruntime-openvino"):
        LearnedSR(exported[1])


def test_the_scripts_export_and_check_from_any_folder(tmp_path):
    """export/export_onnx.py and export/check_onnx.py run as plain scripts (the package is
    installed; no path edits), from a folder other than the checkout."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    torch.manual_seed(2)
    model = HbisSRNet(2, width=8, blocks=1).eval()
    weights = tmp_path / "weights.pt"
    torch.save({"model": model.state_dict(), "model_config": model.config()}, weights)
    run = [sys.executable, str(repo / "export" / "export_onnx.py"), str(weights), "net.onnx"]
    result = subprocess.run(run, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "wrote net.onnx" in result.stdout and "parity torch vs onnxruntime" in result.stdout
    assert read_model_metadata(tmp_path / "net.onnx")["h"] == "2"
    check = [sys.executable, str(repo / "export" / "check_onnx.py"), "net.onnx", str(weights), "--size", "9", "11"]
    result = subprocess.run(check, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "at 9 x 11" in result.stdout and "tolerance 1e-04" in result.stdout


def test_the_exported_model_carries_its_architecture_and_the_runtime_sizes_its_halo_from_it(tmp_path):
    arch = Architecture(2, width=8, blocks=9, kind="ir")
    torch.manual_seed(0)
    model = build_net(arch).eval()
    path = tmp_path / "ir.onnx"
    metadata = export_model(model, path)
    assert json.loads(metadata["model_config"]) == {"h": 2, "width": 8, "blocks": 9, "kind": "ir"}
    runner = LearnedSR(path, provider="cpu")
    assert runner.architecture == arch and runner.halo == arch.halo == 12  # the receptive field's radius, plus one
    deep = Architecture(2, width=4, blocks=8)
    export_model(build_net(deep).eval(), tmp_path / "deep.onnx")
    assert LearnedSR(tmp_path / "deep.onnx", provider="cpu").halo == deep.halo == 19



def test_checkpoints_load_without_pickle_and_one_that_needs_it_is_refused(tmp_path):
    """torch.load(weights_only=True): the shipped weights load; a file that needs pickle (which
    could run code) is one HbisInputError line, and its code does not run."""
    import collections

    from hbis_torch.reconstruct.learned import models_dir
    from hbis_torch.training.export import load_checkpoint, load_weights

    for h in (2, 4, 7):
        model, ckpt = load_checkpoint(models_dir() / f"hbis_sr_h{h}.pt")
        assert ckpt["model_config"]["h"] == h
    evil = tmp_path / "evil.pt"
    torch.save({"model": {}, "model_config": collections.Counter(a=1), "x": _Runs(tmp_path / "ran")}, evil)
    with pytest.raises(HbisInputError, match="needs pickle to load") as info:
        load_weights(evil)
    assert "\n" not in str(info.value) and not (tmp_path / "ran").exists()
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(HbisInputError, match="not a readable checkpoint"):
        load_weights(tmp_path / "junk.pt")


class _Runs:
    """An object whose unpickling would leave a mark (it must never be unpickled)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (self.marker.touch, ())


def test_a_models_metadata_is_read_once_while_the_file_is_unchanged(exported, tmp_path):
    import shutil

    from hbis_torch.reconstruct.learned import runtime

    copy = tmp_path / "m.onnx"
    shutil.copy(exported[1], copy)
    first = runtime.read_model_metadata(copy)
    hits = runtime._metadata_items.cache_info().hits
    first["h"] = "mutated"  # the caller's dict is its own
    assert runtime.read_model_metadata(copy)["h"] != "mutated"
    assert runtime._metadata_items.cache_info().hits == hits + 1
    misses = runtime._metadata_items.cache_info().misses
    os.utime(copy, ns=(0, 0))  # a changed file is read again
    written = {p.key: p.value for p in onnx.load(str(exported[1])).metadata_props}
    assert runtime.read_model_metadata(copy) == written
    assert runtime._metadata_items.cache_info().misses == misses + 1

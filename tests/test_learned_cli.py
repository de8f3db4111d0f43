"""``hbis reconstruct --method learned``: the shipped model by default, --model for another;
the learned method's side of the sample-position policy."""


import numpy as np
import pytest
import tifffile

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SceneSpec, load_scene, simulate_stack
from hbis_torch.reconstruct.classical import optics_cutoff, reconstruct_classical
from hbis_torch.reconstruct.learned import (LearnedSR, available_providers, default_model_path, learned_sr,
                                            models_dir, noise_params_from_meta, read_model_metadata)
from hbis_torch.reconstruct.positions import optical_positions, stack_sample_positions
from hbis_torch.stack_io import read_stack, write_stack


def simulated_stack_file(tmp_path, h, size=24):
    system = FoveaSystem()
    pixel = system.object_pixel_mm
    spec = SceneSpec(size_mm=(size * pixel * 1.25,) * 2, pixel_mm=pixel, detail_mm=pixel / 16)
    stack, truth = simulate_stack(load_scene("words", spec, seed=7), system, plan_scan(system, h),
                                  roi=(600, 400, size, size), seed=7)
    path = tmp_path / f"stack_h{h}.tif"
    write_stack(path, stack)
    return path, truth


def test_default_model_is_shipped_small_and_described():
    path = default_model_path(4)
    assert path.parent == models_dir() and path.stat().st_size <= 5 * 2**20
    meta = read_model_metadata(path)
    assert meta["h"] == "4" and meta["frames"] == "16" and meta["training_commit"] != "unknown"


def test_reconstruct_learned_writes_the_h_times_image(tmp_path, capsys):
    stack_path, truth = simulated_stack_file(tmp_path, 4)
    out = tmp_path / "sr.tif"
    code = main(["reconstruct", str(stack_path), "--method", "learned", "--registration", "optics",
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    image = tifffile.imread(out)
    assert image.shape == truth.shape and image.dtype == np.float32
    assert np.isfinite(image).all() and 0 <= image.min() and image.max() <= 1
    classical = reconstruct_classical(read_stack(stack_path), "optics")
    assert np.abs(image - classical).max() > 1e-2  # the network ran (it moves edges by some 0.09 here)
    assert psnr(image, truth) > psnr(classical, truth) + 1.0  # measured: +1.7 dB (29.6 against 27.9)


def test_every_execution_provider_writes_the_same_image(tmp_path, capsys):
    stack_path, _ = simulated_stack_file(tmp_path, 4)
    images = {}
    for provider in ("auto", *available_providers()):
        out = tmp_path / f"sr_{provider}.tif"
        code = main(["reconstruct", str(stack_path), "--method", "learned", "--registration", "optics",
                     "--provider", provider, "--out", str(out)])
        assert code == 0, capsys.readouterr().err
        images[provider] = tifffile.imread(out)
    for image in images.values():
        assert np.abs(image - images["cpu"]).max() <= 1e-4


def test_a_model_for_another_h_is_a_clear_input_error(tmp_path, capsys):
    stack_path, _ = simulated_stack_file(tmp_path, 3, size=16)
    code = main(["reconstruct", str(stack_path), "--method", "learned",
                 "--model", str(default_model_path(4)), "--out", str(tmp_path / "x.tif")])
    assert code == 2
    err = capsys.readouterr().err
    assert "h = 4" in err and "h = 3" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.tif").exists()


def test_no_shipped_model_for_this_h_gives_the_classical_image_and_says_so(tmp_path, capsys):
    """The learned method refuses no stack the classical method takes: at an h no model is shipped
    for, it returns the classical image with one line saying why (as outside the training domain)."""
    assert not (models_dir() / "hbis_sr_h5.onnx").exists()
    stack_path, _ = simulated_stack_file(tmp_path, 5, size=24)
    out = tmp_path / "x.tif"
    code = main(["reconstruct", str(stack_path), "--method", "learned", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0 and "no learned model for h = 5" in err and "returns the classical image" in err
    classical = reconstruct_classical(read_stack(stack_path), "auto")
    np.testing.assert_array_equal(tifffile.imread(out), classical)
    # a model named explicitly must fit: one for another h stays an input error (above)


def test_learned_treats_untrusted_frames_as_the_classical_method_does(tmp_path, distrust_frame):
    """The learned method refines the classical image, so it follows the classical policy: with
    "data" an untrusted frame is left out (with a message), with "auto" it stays at its optical
    positions; learned_sr's own default is the optics alone."""
    stack_path, _ = simulated_stack_file(tmp_path, 2, size=32)
    stack = read_stack(stack_path)
    distrust_frame(1)
    _, trusted = stack_sample_positions(stack, "data")
    assert trusted.tolist() == [True, False, True, True]
    runner = LearnedSR(h=2, threads=1, provider="cpu")
    noise = noise_params_from_meta(stack.meta)  # a simulated stack records its sensor
    assert noise is not None
    for mode in ("data", "auto"):
        messages = []
        image = learned_sr(stack, registration=mode, messages=messages, threads=1, provider="cpu")
        classical_messages = []
        classical = reconstruct_classical(stack, mode, messages=classical_messages)
        assert messages == classical_messages
        left_out = "left out 1 frame(s) the registration could not trust"
        assert (left_out in messages) == (mode == "data")
        assert np.array_equal(image, runner(classical, noise, optics_cutoff(stack.system)))
    messages = []
    optics = learned_sr(stack, messages=messages, threads=1, provider="cpu")
    assert messages == []
    # the optics' node splines (the default) against every pixel's float64 position: the same
    # samples, their lattice offsets to float32 rounding
    assert np.abs(optics - learned_sr(stack, positions=optical_positions(stack), threads=1,
                                      provider="cpu")).max() < 1e-5


def test_repeated_calls_reuse_the_session_until_the_model_file_changes(tmp_path):
    import os
    import shutil

    from hbis_torch.reconstruct.learned import method

    stack_path, _ = simulated_stack_file(tmp_path, 2, size=16)
    stack = read_stack(stack_path)
    model = tmp_path / "m.onnx"
    shutil.copy(default_model_path(2), model)
    method._runner.cache_clear()
    first = learned_sr(stack, model=model)
    np.testing.assert_array_equal(learned_sr(stack, model=model), first)
    assert method._runner.cache_info().hits == 1 and method._runner.cache_info().misses == 1
    os.utime(model, ns=(1, 1))  # a new file in its place: a new session
    learned_sr(stack, model=model)
    assert method._runner.cache_info().misses == 2


def test_reconstruct_threads_sets_them_for_the_call_and_refuses_zero(tmp_path, capsys):
    import torch

    stack_path, _ = simulated_stack_file(tmp_path, 2, size=32)
    before = torch.get_num_threads()
    for method in ("classical", "learned"):
        images = []
        for threads in ([], ["--threads", "1"]):
            out = tmp_path / f"{method}{len(threads)}.tif"
            assert main(["reconstruct", str(stack_path), "--method", method, "--registration", "optics",
                         "--out", str(out)] + threads) == 0
            images.append(tifffile.imread(out))
        np.testing.assert_allclose(images[1], images[0], atol=1e-5)  # threads change sums' order only
        assert torch.get_num_threads() == before
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:
        main(["reconstruct", str(stack_path), "--threads", "0", "--out", str(tmp_path / "z.tif")])
    assert refused.value.code == 2 and "--threads" in capsys.readouterr().err
    assert not (tmp_path / "z.tif").exists()

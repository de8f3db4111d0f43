"""The two tiers of shipped models: ``--model fast`` (the default) and ``--model best``."""

import numpy as np
import pytest
import tifffile
import torch

from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import reconstruct
from hbis_torch.reconstruct.learned import LearnedSR, default_model_path, learned_sr, read_model_metadata
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.reconstruct.learned.runtime import missing_model, model_to_run
from hbis_torch.stack_io import read_stack
from hbis_torch.training.export import load_checkpoint
from hbis_torch.training.net import build_net, grow_net
from tests.test_learned_cli import simulated_stack_file


@pytest.mark.parametrize("h", [2, 4, 7])
def test_each_h_ships_a_best_model_larger_than_its_fast_one(h):
    fast, best = default_model_path(h, "fast"), default_model_path(h, "best")
    assert fast == default_model_path(h) and best != fast
    assert best.stat().st_size <= 20 * 2**20
    size = {t: Architecture.from_metadata(read_model_metadata(p)) for t, p in (("fast", fast), ("best", best))}
    assert size["best"].width * size["best"].blocks > size["fast"].width * size["fast"].blocks
    meta = read_model_metadata(best)
    assert float(meta["val_psnr_db"]) > float(meta["val_classical_psnr_db"]) + 0.1


def test_the_tier_names_pick_the_shipped_files_and_a_missing_tier_is_said():
    assert model_to_run("best", 4)[0] == default_model_path(4, "best")
    assert model_to_run(None, 4)[0] == model_to_run("fast", 4)[0] == default_model_path(4)
    path, meta, missing = model_to_run("best", 3)
    assert path is None and "no best learned model for h = 3" in missing
    assert LearnedSR("best", h=7).architecture.width == Architecture.from_metadata(
        read_model_metadata(default_model_path(7, "best"))).width


def test_model_best_on_the_command_line(tmp_path, capsys):
    stack_path, truth = simulated_stack_file(tmp_path, 4)
    images = {}
    for tier in ("fast", "best"):
        out = tmp_path / f"{tier}.tif"
        code = main(["reconstruct", str(stack_path), "--method", "learned", "--registration", "optics",
                     "--model", tier, "--out", str(out)])
        assert code == 0, capsys.readouterr().err
        images[tier] = tifffile.imread(out)
    assert images["best"].shape == truth.shape and np.isfinite(images["best"]).all()
    # On this fixed stack (words, h = 4, 24 x 24) measured: best 31.98 dB, fast 29.59 dB, classical
    # 27.92 dB. The best tier must beat the fast one, and both the classical image, by 1 dB; the
    # fast model run under the best tier's name, or the classical image returned, fails.
    score = {tier: psnr(image, truth) for tier, image in images.items()}
    score["classical"] = psnr(reconstruct(read_stack(stack_path), "classical", registration="optics"), truth)
    assert score["best"] > score["fast"] + 1.0 > score["classical"] + 2.0, score


def test_a_grown_network_computes_what_the_small_one_did_and_then_learns():
    small, _ = load_checkpoint(default_model_path(4).with_suffix(".pt"))
    torch.manual_seed(0)
    big = grow_net(small, Architecture(4, width=48, blocks=6))
    base, noise = torch.rand(2, 16, 20, 24), torch.rand(2, 1, 20, 24) * 0.2
    with torch.no_grad():
        torch.testing.assert_close(big(base, noise), small(base, noise), rtol=0, atol=1e-5)
    big(base, noise).square().mean().backward()
    assert big.tail.weight.grad[:, 32:].abs().max() > 0  # the new channels are trained at once
    assert big.body[5].conv2.weight.grad.abs().max() > 0  # and the new blocks
    with pytest.raises(HbisInputError, match="cannot grow"):
        grow_net(big, Architecture(4, width=32, blocks=6))
    with pytest.raises(HbisInputError, match="cannot grow"):
        grow_net(build_net(Architecture(4, 8, 1)), Architecture(7, 16, 2))


def test_the_best_tier_runs_the_fast_model_where_it_has_none(tmp_path):
    """h = 3 has a fast model only: --model best runs it (more than the classical image), and says so."""
    assert missing_model(3, "best") is not None and missing_model(3, "fast") is None
    stack = read_stack(simulated_stack_file(tmp_path, 3, size=16)[0])
    notes: list = []
    best = learned_sr(stack, registration="optics", model="best", messages=notes)
    assert notes == ["no best model for h = 3: the fast model runs"]
    np.testing.assert_array_equal(best, learned_sr(stack, registration="optics", model="fast"))
    # where neither tier has a model, the classical image as before
    notes = []
    learned_sr(read_stack(simulated_stack_file(tmp_path, 5, size=16)[0]), registration="optics", model="best",
               messages=notes)
    assert len(notes) == 1 and "no best learned model for h = 5" in notes[0]

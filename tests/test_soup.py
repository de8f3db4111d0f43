"""training/soup.py: the weight mixes of two runs of one network, each scored on its validation set."""

import pytest
import torch

from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.training.export import load_checkpoint
from hbis_torch.training.net import build_net


@pytest.fixture(scope="module")
def soup(load_script):
    return load_script("training/soup.py")


def _weights(path, seed, arch=Architecture(2, width=8, blocks=1)):
    torch.manual_seed(seed)
    net = build_net(arch.as_dict())
    config = {"val_size": 2, "val_roi": 16, "seed": 0}
    torch.save({"model": net.state_dict(), "model_config": arch.as_dict(), "config": config, "git_commit": "x"}, path)
    return net.state_dict()


def test_each_mix_lies_on_the_line_between_the_two_runs(soup, tmp_path, capsys):
    a, b = _weights(tmp_path / "a.pt", 0), _weights(tmp_path / "b.pt", 1)
    assert soup.main([str(tmp_path / "a.pt"), str(tmp_path / "b.pt"), "--alphas", "0", "0.5", "1",
                      "--out-dir", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().out.count("validation PSNR") == 3
    for alpha in (0, 0.5, 1):
        model, ckpt = load_checkpoint(tmp_path / "out" / f"soup_a{alpha:g}.pt")
        mixed = model.state_dict()
        for key in a:  # every mix from the two files, not from the mix before it
            torch.testing.assert_close(mixed[key], (1 - alpha) * a[key] + alpha * b[key])
        assert ckpt["val_psnr"] > 0 and '"alpha": %g' % alpha in ckpt["config"]["soup"]


def test_different_networks_are_refused(soup, tmp_path):
    _weights(tmp_path / "a.pt", 0)
    _weights(tmp_path / "b.pt", 1, Architecture(2, width=8, blocks=2))
    with pytest.raises(SystemExit, match="different architectures"):
        soup.main([str(tmp_path / "a.pt"), str(tmp_path / "b.pt"), "--out-dir", str(tmp_path / "out")])

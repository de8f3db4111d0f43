"""``hbis simulate`` as docs/design.md section 2 states it."""

from __future__ import annotations

import numpy as np
import pytest

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.scan import plan_scan
from hbis_torch.stack_io import read_image, read_stack

SMALL = ["--roi", "600,400,24,16"]


def test_simulate_writes_a_stack_and_its_truth(tmp_path, capsys):
    out, truth = tmp_path / "s.tif", tmp_path / "t.tif"
    rc = main(["simulate", "--scene", "siemens-star", "--h", "3", "--out", str(out), "--truth", str(truth), *SMALL])
    assert rc == 0
    stack = read_stack(out)
    image, meta = read_image(truth)
    assert stack.frames.shape == (9, 16, 24) and stack.frames.dtype == np.uint16 and stack.bit_depth == 12
    assert image.shape == (48, 72) and image.dtype == np.float32
    assert meta["h"] == 3 and meta["roi"] == [600, 400, 24, 16] and meta["reference_index"] == stack.reference_index
    plan = plan_scan(FoveaSystem(), 3)
    np.testing.assert_allclose(stack.phases_deg, plan.phases_deg.numpy())
    assert stack.reference_index == plan.reference_index
    assert "wrote" in capsys.readouterr().out


def test_defaults_and_options(tmp_path):
    out = tmp_path / "s.tif"
    assert main(["simulate", "--scene", "flat", "--h", "1", "--out", str(out)]) == 0
    stack = read_stack(out)
    assert stack.roi == (512, 352, 256, 256)  # the documented default: 256 x 256 at the centre
    rc = main(["simulate", "--scene", "flat", "--h", "2", "--out", str(out), "--overwrite", *SMALL, "--bit-depth", "float",
               "--no-noise", "--phases-deg", "45,130", "--method", "paper", "--fill-factor", "0.5",
               "--scene-size-mm", "2,3", "--seed", "4", "--alpha-deg", "3"])
    assert rc == 0
    stack = read_stack(out)
    assert stack.frames.dtype == np.float32 and np.ptp(stack.frames) < 1e-6
    assert stack.system.prisms.wedge_angle_deg == 3.0
    assert stack.meta["simulation"]["scene_size_mm"] == [2.0, 3.0]
    assert stack.meta["simulation"]["sensor"]["fill_factor"] == 0.5
    np.testing.assert_allclose(stack.phases_deg[stack.reference_index], [45.0, 130.0])


def test_scene_from_an_image_file(tmp_path):
    from PIL import Image

    picture = tmp_path / "pic.png"
    Image.fromarray((np.indices((40, 60)).sum(0) * 3 % 256).astype(np.uint8)).save(picture)
    out = tmp_path / "s.tif"
    assert main(["simulate", "--scene", str(picture), "--h", "2", "--out", str(out), *SMALL]) == 0
    assert read_stack(out).meta["simulation"]["scene"] == "pic.png"


@pytest.mark.parametrize(
    "args,message",
    [
        (["--scene", "nope"], "unknown scene 'nope'"),
        (["--scene", "flat", "--roi", "1270,0,24,16"], "outside"),
        (["--scene", "flat", "--fill-factor", "2"], "--fill-factor: must lie in (0, 1]"),
        (["--scene", "flat", "--bit-depth", "20"], "bit depth"),
        (["--scene", "missing.png"], "no such image file"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, message):
    argv = ["simulate", "--h", "2", "--out", str(tmp_path / "s.tif"), *SMALL, *args]
    if "--roi" in args:
        argv = ["simulate", "--h", "2", "--out", str(tmp_path / "s.tif"), *args]
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's own range checks (--fill-factor)
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "s.tif").exists()


def test_bad_arguments_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["simulate", "--scene", "flat", "--h", "2", "--out", str(tmp_path / "s.tif"), "--roi", "1,2,3"])
    assert info.value.code == 2
    assert "--roi" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["simulate", "--scene", "flat", "--out", "x.tif"])  # --h is required
    assert info.value.code == 2

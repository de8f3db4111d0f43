"""Every TIFF hbis writes records its pixel size (object plane) in the resolution tags, with one
ImageDescription: stacks, ground truths and the SR output of ``hbis reconstruct``."""

import json

import numpy as np
import pytest
import tifffile

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.stack_io import object_pixel_um, read_image, read_stack
from hbis_torch.tiff_io import read_pixel_size_um


def _descriptions(path) -> int:
    with tifffile.TiffFile(path) as tif:
        return sum(tag.name == "ImageDescription" for tag in tif.pages[0].tags.values())


def test_object_pixel_is_pitch_times_distance_over_focal_length():
    system = FoveaSystem()
    cam = system.camera
    expected = cam.pixel_pitch_um * system.object_distance_mm / cam.focal_length_mm
    assert object_pixel_um(system) == pytest.approx(expected)
    assert object_pixel_um(system, 4) == pytest.approx(expected / 4)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("scale")
    stack, truth, sr = out / "stack.tif", out / "truth.tif", out / "sr.tif"
    assert main(["simulate", "--scene", "bars", "--h", "2", "--roi", "600,440,24,20", "--no-noise",
                 "--out", str(stack), "--truth", str(truth), "-q"]) == 0
    assert main(["reconstruct", str(stack), "--out", str(sr), "--registration", "optics", "-q"]) == 0
    return stack, truth, sr


def test_stack_truth_and_sr_carry_their_pixel_size_and_one_description(written):
    stack, truth, sr = written
    pixel = object_pixel_um(read_stack(stack).system)
    assert read_pixel_size_um(stack) == pytest.approx(pixel, rel=1e-6)
    for path in (truth, sr):
        assert read_pixel_size_um(path) == pytest.approx(pixel / 2, rel=1e-6)
        image, meta = read_image(path)
        assert meta["pixel_size_um"] == pytest.approx(pixel / 2) and meta["pixel_plane"] == "object"
    for path in written:
        assert _descriptions(path) == 1
        with tifffile.TiffFile(path) as tif:
            assert tif.pages[0].tags["ResolutionUnit"].value == 3  # centimetre, as ImageJ reads it
    assert read_image(sr)[1]["format"] == "hbis-sr/1"
    assert json.loads(tifffile.TiffFile(sr).pages[0].description)["h"] == 2


def test_an_image_without_a_pixel_size_has_no_resolution_unit(tmp_path):
    from hbis_torch.stack_io import write_image

    write_image(tmp_path / "x.tif", np.zeros((4, 5), np.float32), {"format": "hbis-truth/1"})
    assert read_pixel_size_um(tmp_path / "x.tif") is None
    assert "pixel_size_um" not in read_image(tmp_path / "x.tif")[1]

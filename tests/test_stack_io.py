"""The hbis-stack/1 file format: round trips, and clear rejection of broken files."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import tifffile
import torch

from hbis_torch.config import Camera, FoveaSystem
from hbis_torch.errors import HbisInputError, StackFormatError
from hbis_torch.stack_io import (
    Stack,
    make_meta,
    read_image,
    read_stack,
    write_image,
    write_stack,
)


def _stack(dtype=np.uint16, frames=4, roi=(100, 50, 6, 5), bit_depth=12, **extra) -> Stack:
    rng = np.random.default_rng(0)
    shape = (frames, roi[3], roi[2])
    if np.dtype(dtype) == np.float32:
        data = rng.random(shape, dtype=np.float32)
    else:
        data = rng.integers(0, 2 ** (bit_depth or np.dtype(dtype).itemsize * 8), shape).astype(dtype)
    phases = np.column_stack((5 + 0.01 * np.arange(frames), 70 - 0.013 * np.arange(frames)))
    h = int(round(frames ** 0.5))
    meta = make_meta(FoveaSystem(), h, roi, phases, bit_depth=bit_depth,
                     reference_index=min(1, frames - 1), **extra)
    return Stack(data, meta)


def _raw_write(path, frames, meta) -> None:
    """Write a TIFF with any description, bypassing the writer's checks."""
    desc = meta if isinstance(meta, str) else json.dumps(meta)
    tifffile.imwrite(path, frames, description=desc, metadata=None, photometric="minisblack")


@pytest.mark.parametrize("dtype,bit_depth", [(np.uint8, 8), (np.uint16, 12), (np.float32, None)])
def test_round_trip_keeps_frames_meta_and_extra_keys(tmp_path, dtype, bit_depth):
    stack = _stack(dtype, bit_depth=bit_depth, simulation={"scene": "star", "seed": 3}, note="x")
    path = tmp_path / "s.tif"
    write_stack(path, stack)
    back = read_stack(path)
    assert back.frames.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.frames, stack.frames)
    assert back.meta == stack.meta
    assert back.meta["simulation"] == {"scene": "star", "seed": 3} and back.meta["note"] == "x"
    np.testing.assert_array_equal(back.phases_deg, stack.phases_deg)  # exact float64 round trip
    assert back.phases_deg.dtype == np.float64 and back.phases_deg.shape == (4, 2)
    assert back.roi == (100, 50, 6, 5) and back.h == 2 and back.reference_index == 1
    assert back.system == FoveaSystem()
    assert back.bit_depth == (bit_depth if bit_depth else None)
    assert not list(tmp_path.glob(".*tmp")), "the atomic writer left a temporary file"


def test_single_frame_stack_round_trips(tmp_path):
    stack = _stack(frames=1)
    write_stack(tmp_path / "one.tif", stack)
    assert read_stack(tmp_path / "one.tif").frames.shape == (1, 5, 6)


def test_to_float_uses_bit_depth_and_black_level():
    stack = _stack(np.uint16, bit_depth=12, black_level=64)
    stack.frames[:] = 64
    stack.frames[0, 0, 0] = 4095
    stack.frames[0, 0, 1] = 10  # below black: clipped to 0
    x = stack.to_float()
    assert x.dtype == torch.float32 and x.shape == (4, 5, 6)
    assert float(x[0, 0, 0]) == 1.0 and float(x[0, 0, 1]) == 0.0 and float(x[1].max()) == 0.0
    stack.frames[0, 0, 2] = 64 + 1000
    assert float(stack.to_float()[0, 0, 2]) == pytest.approx(1000 / (4095 - 64), rel=1e-6)
    floats = _stack(np.float32, bit_depth=None)
    assert torch.equal(floats.to_float(), torch.from_numpy(floats.frames))


def test_to_float_without_black_level_gives_the_in_place_formulas_bits():
    """With black level 0 the frames go to float32 in one division: the same bits as numpy's
    float32 division and as (x - 0) / white clipped to [0, 1], for every 8- and 16-bit value
    (those above a 12-bit white clipped); read-only frames are converted too, without a
    warning."""
    import warnings

    for dtype, bit_depth in ((np.uint16, 12), (np.uint16, 16), (np.uint8, 8)):
        values = np.arange(np.iinfo(dtype).max + 1, dtype=dtype).reshape(1, 1, -1)
        values.setflags(write=False)
        stack = _stack(dtype, frames=1, bit_depth=bit_depth)
        stack = Stack(values, stack.meta)
        white = 2 ** bit_depth - 1
        expected = torch.from_numpy(values.astype(np.float32)).sub_(0).div_(white).clamp_(0.0, 1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got = stack.to_float()
        assert got.dtype == torch.float32 and torch.equal(got, expected)
        by_numpy = np.minimum(np.divide(values, np.float32(white), dtype=np.float32), np.float32(1))
        assert np.array_equal(got.numpy(), by_numpy)


def test_defaults_when_optional_keys_are_absent(tmp_path):
    stack = _stack(np.uint8, bit_depth=None)
    del stack.meta["reference_index"]
    del stack.meta["camera"]["wavelength_nm"]
    write_stack(tmp_path / "s.tif", stack)
    back = read_stack(tmp_path / "s.tif")
    assert back.reference_index == 0 and back.bit_depth == 8
    assert back.system.camera.wavelength_nm == 550.0


def _broken(tmp_path, mutate, dtype=np.uint16, bit_depth=12):
    stack = _stack(dtype, bit_depth=bit_depth)
    frames, meta = stack.frames, copy.deepcopy(stack.meta)
    frames = mutate(frames, meta)
    path = tmp_path / "bad.tif"
    _raw_write(path, frames, meta)
    return path


def _drop(key):
    def mutate(frames, meta):
        del meta[key]
        return frames

    return mutate


def _set(key, value):
    def mutate(frames, meta):
        meta[key] = value
        return frames

    return mutate


@pytest.mark.parametrize(
    "mutate,message",
    [
        (_drop("phases_deg"), "missing key(s) phases_deg"),
        (_drop("roi"), "missing key(s) roi"),
        (_drop("camera"), "missing key(s) camera"),
        (lambda f, m: (m["camera"].pop("rows"), f)[1], "missing key(s) camera.rows"),
        (lambda f, m: (m["prisms"].pop("refractive_index"), f)[1], "prisms.refractive_index"),
        (_set("format", "hbis-stack/2"), "format is 'hbis-stack/2'"),
        (_set("h", 0), "h must be an integer from 1 to 16"),
        (_set("h", 2.5), "h must be an integer from 1 to 16"),
        (_set("h", 17), "h must be an integer from 1 to 16"),
        (lambda f, m: f[:3], "3 frame(s) but 4 entries in phases_deg"),
        (lambda f, m: (m.update(phases_deg=m["phases_deg"][:3]), f[:3])[1], "3 frame(s), but a scan with h = 2 has h x h = 4"),
        (_set("phases_deg", [[1, 2]] * 5), "4 frame(s) but 5 entries in phases_deg"),
        (_set("phases_deg", [[1, 2, 3]] * 4), "phases_deg must be a non-empty list"),
        (_set("roi", [1275, 50, 6, 5]), "lies outside the 960 x 1280"),
        (_set("roi", [-1, 50, 6, 5]), "lies outside"),
        (_set("roi", [100, 50, 7, 5]), "roi is 7 x 5 (width x height) but the frames are 6 x 5"),
        (_set("roi", [100, 50, 6]), "roi must be four integers"),
        (_set("bit_depth", 17), "bit_depth must be an integer from 1 to 16"),
        (_set("bit_depth", 10), "pixel values up to"),
        (lambda f, m: f.astype(np.int32), "frame dtype int32 is not one of"),
        (lambda f, m: f.astype(np.float64) / 4095, "frame dtype float64"),
        (_set("reference_index", 4), "reference_index 4 is not a frame index (0..3)"),
        (lambda f, m: (m["camera"].__setitem__("f_number", -1.4), f)[1], "f_number must be a finite"),
        (_set("black_level", 5000), "black_level 5000 is not below the white level 4095"),
    ],
)
def test_broken_files_are_rejected_with_the_right_message(tmp_path, mutate, message):
    path = _broken(tmp_path, mutate)
    with pytest.raises(StackFormatError) as info:
        read_stack(path)
    text = str(info.value)
    assert message in text, text
    assert text.startswith(str(path)) and "\n" not in text


def test_nan_and_out_of_range_floats_are_rejected(tmp_path):
    def nan(frames, meta):
        frames = frames.copy()
        frames[1, 2, 3] = np.nan
        return frames

    path = _broken(tmp_path, nan, np.float32, None)
    with pytest.raises(StackFormatError, match="NaN or infinite"):
        read_stack(path)
    path = _broken(tmp_path, lambda f, m: f * 2, np.float32, None)
    with pytest.raises(StackFormatError, match=r"must lie in \[0, 1\]"):
        read_stack(path)
    path = _broken(tmp_path, _set("phases_deg", [[1, float("nan")]] * 4), np.float32, None)
    with pytest.raises(StackFormatError, match="NaN is not a JSON number"):
        read_stack(path)


def test_files_that_are_not_stacks(tmp_path):
    with pytest.raises(StackFormatError, match="no such file"):
        read_stack(tmp_path / "missing.tif")
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"this is not a tiff at all")
    with pytest.raises(StackFormatError, match="not a readable TIFF"):
        read_stack(junk)
    stack = _stack()
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, stack.frames, metadata=None, photometric="minisblack")
    with pytest.raises(StackFormatError, match="no ImageDescription"):
        read_stack(plain)
    _raw_write(tmp_path / "text.tif", stack.frames, "hello")
    with pytest.raises(StackFormatError, match="not valid JSON"):
        read_stack(tmp_path / "text.tif")
    _raw_write(tmp_path / "list.tif", stack.frames, "[1, 2]")
    with pytest.raises(StackFormatError, match="not a JSON object"):
        read_stack(tmp_path / "list.tif")
    rgba = tmp_path / "rgba.tif"  # RGB frames are a colour stack; RGBA is no stack
    tifffile.imwrite(rgba, np.zeros((5, 6, 4), np.uint8), description=json.dumps(stack.meta),
                     metadata=None, photometric="rgb")
    with pytest.raises(StackFormatError, match="grayscale"):
        read_stack(rgba)
    truncated = tmp_path / "cut.tif"
    write_stack(truncated, _stack(np.uint16, frames=4, roi=(0, 0, 64, 64)))
    truncated.write_bytes(truncated.read_bytes()[: 2 * 64 * 64 * 2])
    with pytest.raises(StackFormatError):
        read_stack(truncated)


def test_writer_validates_and_leaves_no_file_behind(tmp_path):
    stack = _stack()
    stack.frames = stack.frames[:2]
    path = tmp_path / "s.tif"
    with pytest.raises(StackFormatError, match="2 frame"):
        write_stack(path, stack)
    assert not path.exists() and not list(tmp_path.iterdir())
    bad = _stack(np.float32, bit_depth=None)
    bad.frames[0, 0, 0] = np.nan
    with pytest.raises(HbisInputError, match="NaN"):
        write_stack(path, bad)
    good = _stack()
    good.meta["extra"] = float("nan")
    with pytest.raises(StackFormatError, match="cannot be written"):
        write_stack(path, good)


def test_overwrite_is_atomic_and_keeps_old_file_on_error(tmp_path):
    path = tmp_path / "s.tif"
    first = _stack()
    write_stack(path, first)
    broken = _stack()
    broken.meta["roi"] = [0, 0, 1, 1]
    with pytest.raises(StackFormatError):
        write_stack(path, broken)
    np.testing.assert_array_equal(read_stack(path).frames, first.frames)


def test_stack_from_another_camera(tmp_path):
    system = FoveaSystem(camera=Camera(rows=20, cols=30, pixel_pitch_um=2.0))
    meta = make_meta(system, 1, (0, 0, 30, 20), [[1.0, 2.0]], bit_depth=8)
    write_stack(tmp_path / "s.tif", Stack(np.zeros((1, 20, 30), np.uint8), meta))
    assert read_stack(tmp_path / "s.tif").system == system


def test_image_round_trip(tmp_path):
    image = np.random.default_rng(1).random((7, 9)).astype(np.float32)
    write_image(tmp_path / "t.tif", torch.from_numpy(image), {"h": 4, "roi": (1, 2, 3, 4)})
    back, meta = read_image(tmp_path / "t.tif")
    np.testing.assert_array_equal(back, image)
    assert meta == {"h": 4, "roi": [1, 2, 3, 4]}
    with pytest.raises(HbisInputError, match="NaN"):
        write_image(tmp_path / "n.tif", np.full((2, 2), np.nan))
    with pytest.raises(HbisInputError, match="NaN"):  # one infinity among finite values
        write_image(tmp_path / "i.tif", np.array([[0.5, np.inf], [0.1, 0.2]], dtype=np.float32))
    large = np.full((4, 4), 3e38, dtype=np.float32)  # finite, though its sum overflows
    write_image(tmp_path / "l.tif", large)
    np.testing.assert_array_equal(read_image(tmp_path / "l.tif")[0], large)

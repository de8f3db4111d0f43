"""Property tests (hypothesis): whatever the bytes of a stack file, the JSON text or the argument
text, the answer is a value or one input error, never anything else."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError, StackFormatError
from hbis_torch.io_utils import load_json
from hbis_torch.stack_io import Stack, make_meta, read_stack, write_stack

def _exit_code(argv) -> int:
    """``main(argv)``'s exit code, argparse's own errors (SystemExit) included."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def stack_bytes(tmp_path_factory):
    path = tmp_path_factory.mktemp("valid") / "s.tif"
    frames = np.random.default_rng(0).integers(0, 4096, (4, 6, 8)).astype(np.uint16)
    meta = make_meta(FoveaSystem(), 2, (600, 400, 8, 6), [[5, 70], [5.1, 70], [5, 70.1], [5.1, 70.1]], bit_depth=12)
    write_stack(path, Stack(frames, meta))
    return path.read_bytes()


@FAST
@given(data=st.data())
def test_any_damage_to_a_stack_file_is_a_stack_error_or_a_valid_stack(stack_bytes, tmp_path, data):
    blob = bytearray(stack_bytes)
    for _ in range(data.draw(st.integers(1, 8))):
        at = data.draw(st.integers(0, len(blob) - 1))
        blob[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(blob)))
    path = tmp_path / "damaged.tif"
    path.write_bytes(bytes(blob[:cut] if data.draw(st.booleans()) else blob))
    try:
        stack = read_stack(path)
    except StackFormatError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(path))
    else:
        stack.validate()  # what was read is a valid stack
        assert stack.frames.shape[0] == stack.h ** 2


@FAST
@given(blob=st.binary(max_size=512))
def test_random_bytes_are_a_stack_error(tmp_path, blob):
    path = tmp_path / "random.tif"
    path.write_bytes(blob)
    with pytest.raises(StackFormatError):
        read_stack(path)


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=3), inner, max_size=4),
    max_leaves=20,
)


@FAST
@given(text=st.one_of(st.text(max_size=200), JSONISH.map(lambda v: __import__("json").dumps(v))))
def test_load_json_returns_a_value_or_one_input_error(text):
    try:
        load_json(text, "t")
    except HbisInputError as exc:
        assert "\n" not in str(exc)


@FAST
@given(text=st.text(max_size=30), lo=st.integers(-5, 5), span=st.integers(0, 10))
def test_bounded_int_gives_a_value_in_range_or_an_argument_error(text, lo, span):
    try:
        value = bounded_int(lo, lo + span)(text)
    except argparse.ArgumentTypeError:
        return
    assert isinstance(value, int) and lo <= value <= lo + span


@FAST
@given(text=st.one_of(st.text(max_size=30), st.floats().map(repr)), lo_open=st.booleans(), hi_open=st.booleans())
def test_bounded_float_gives_a_finite_value_in_range_or_an_argument_error(text, lo_open, hi_open):
    try:
        value = bounded_float(-1.0, 2.0, lo_open=lo_open, hi_open=hi_open)(text)
    except argparse.ArgumentTypeError:
        return
    assert math.isfinite(value) and -1.0 <= value <= 2.0
    assert not (lo_open and value == -1.0) and not (hi_open and value == 2.0)


NUMBER_TEXT = st.one_of(st.integers(-10**6, 10**6).map(str), st.floats().map(repr),
                        st.sampled_from(["nan", "inf", "-inf", "1e309", "", "x", "0x10", "9" * 400]))
DESIGN_FLAGS = ["--h", "--rows", "--cols", "--pixel-pitch-um", "--focal-length-mm", "--f-number",
                "--wavelength-nm", "--alpha-deg", "--n", "--object-distance-mm", "--varphi-h-deg", "--varphi-v-deg"]


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flags=st.lists(st.tuples(st.sampled_from(DESIGN_FLAGS), NUMBER_TEXT), min_size=1, max_size=3))
def test_the_design_parser_answers_0_or_2_never_a_crash(capsys, flags):
    argv = ["design", "--json"] + [f"{flag}={value}" for flag, value in flags]
    rc = _exit_code(argv)
    err = capsys.readouterr().err
    assert rc in (0, 2), err
    assert "Traceback" not in err and len(err.strip().splitlines()) == (rc == 2)


SCAN_FLAGS = ["--h", "--pixel-stride", "--ae-bound"]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(phases=st.tuples(NUMBER_TEXT, NUMBER_TEXT), flags=st.lists(st.tuples(st.sampled_from(SCAN_FLAGS), NUMBER_TEXT),
                                                                   max_size=2))
def test_the_scan_parser_answers_0_or_2_never_a_crash(capsys, phases, flags):
    argv = ["scan", "--h", "2", "--json", "--pixel-stride", "400", f"--phases-deg={phases[0]},{phases[1]}"]
    argv += [f"{flag}={value}" for flag, value in flags]
    rc = _exit_code(argv)
    err = capsys.readouterr().err
    assert rc in (0, 2), err
    assert "Traceback" not in err and len(err.strip().splitlines()) == (rc == 2)

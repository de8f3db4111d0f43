"""What a newcomer tripped on (issue [cli-polish]): a plain image named as no stack, with how to
make one; one verbosity rule for every message (``-q`` leaves stderr empty); one meaning per flag;
one size order (W x H px); one word for a burst's factor; one overwrite rule; help texts with
examples, general options first, no torch for ``hbis simulate --help``; the README's commands."""

import argparse
import json
import logging
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from skimage import data, transform

import hbis_torch
from hbis_torch.cli import COMMANDS, build_parser, main
from hbis_torch.progress import set_progress

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(hbis_torch.__file__).resolve().parents[1]
H, W = 24, 32  # a burst's frames: not square, so that an order swapped shows


@pytest.fixture(autouse=True)
def clean_logging():
    """Leave the hbis_torch logger and the progress switch as they were."""
    logger = logging.getLogger("hbis_torch")
    level, handlers = logger.level, list(logger.handlers)
    yield
    logger.setLevel(level)
    logger.handlers[:] = handlers
    set_progress(None)


def _env():
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)}


@pytest.fixture(scope="module")
def burst_frames(tmp_path_factory):
    """A simulated burst of 6 frames, W x H = 32 x 24, 12-bit values in uint16 (so that assemble's
    bit-depth hint, a line that asks to act, has something to say)."""
    from hbis_torch.simulate.burst import random_motions, simulate_burst

    truth = transform.resize(data.camera().astype(float) / 255, (2 * H, 2 * W), anti_aliasing=True)
    motions = random_motions(6, (H, W), np.random.default_rng(1), 1.5, 1.0)
    burst = simulate_burst(truth, 2, motions, noise=0.005, seed=1)
    path = tmp_path_factory.mktemp("burst") / "frames.tif"
    tifffile.imwrite(path, burst.frames.astype(np.uint16) * 16, photometric="minisblack")
    return path


@pytest.fixture(scope="module")
def burst_stack(burst_frames):
    out = burst_frames.parent / "burst.tif"
    assert main(["-q", "assemble", "--burst", "--scale", "2", "--bit-depth", "12", "--out", str(out),
                 str(burst_frames)]) == 0
    return out


# --------------------------------------------------------------------------- 1. a plain image


@pytest.mark.parametrize("command", ["reconstruct", "validate"])
def test_a_plain_image_is_named_as_no_stack_with_how_to_make_one(burst_frames, tmp_path, command, capsys):
    out = tmp_path / "sr.tif"
    argv = [command, str(burst_frames)] + (["--out", str(out)] if command == "reconstruct" else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "missing key" not in err
    for words in ("not an hbis-stack/1 file", "hbis assemble --burst --scale S", "hbis assemble --phases",
                  "hbis simulate"):
        assert words in err, err
    assert not out.exists()


# --------------------------------------------------------------------------- 2. one verbosity rule

QUIET_RUN = """
import sys
from hbis_torch.cli import main
frames, work = sys.argv[1], sys.argv[2]
codes = [main(["-q", "assemble", "--burst", "--scale", "2", "--out", work + "/b.tif", frames]),
         main(["reconstruct", work + "/b.tif", "--method", "learned", "--out", work + "/sr.tif", "-q"]),
         main(["-q", "validate", work + "/b.tif", "--holdout", "1", "--method", "single,classical"])]
print(codes)
"""


def test_quiet_leaves_stderr_empty_on_the_burst_commands(burst_frames, tmp_path):
    """-q: no line at all on stderr from assemble --burst, reconstruct (learned: the network adapts
    to the burst and says so) and validate, in a process of its own (so that a dependency's warning
    or a runtime's own log would show too), where without -q assemble warns and with -v reconstruct
    says what it did (the next tests). One thread (OMP_NUM_THREADS): on a loaded 2-core machine
    the default threads wait on each other for minutes."""
    done = subprocess.run([sys.executable, "-c", QUIET_RUN, str(burst_frames), str(tmp_path)],
                          env={**_env(), "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=600)
    assert done.stdout.strip().splitlines()[-1] == "[0, 0, 0]", done.stderr
    assert done.stderr == ""
    assert "burst of 6 frames" in done.stdout and "sr.tif (64 x 48 px" in done.stdout  # results still on stdout
    assert "classical " in done.stdout


def test_warnings_that_ask_to_act_by_default_the_rest_with_v(burst_frames, burst_stack, tmp_path, capsys):
    # assemble: 12-bit values in 16-bit frames, no --bit-depth: a warning that names the flag to pass
    assert main(["assemble", "--burst", "--scale", "2", "--out", str(tmp_path / "b.tif"), str(burst_frames)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hbis assemble: warning: ") and "pass --bit-depth 12" in err[0]
    # reconstruct: what the method did (here, the network's adaptation to the burst) with -v, as info
    out = tmp_path / "sr.tif"
    assert main(["reconstruct", str(burst_stack), "--method", "learned", "--out", str(out), "-v"]) == 0
    err = capsys.readouterr().err
    assert "hbis reconstruct: the network was adapted to the burst's own frames" in err and "warning" not in err
    # validate: the table alone by default (above, -q); with -v each method's lines, named
    assert main(["-v", "validate", str(burst_stack), "--holdout", "1", "--method", "learned"]) == 0
    assert "hbis validate: learned: the network was adapted" in capsys.readouterr().err


@pytest.mark.parametrize("flags, shown", [([], ["hbis x: warning: act"]), (["-v"], ["hbis x: a: said", "hbis x: warning: act"]),
                                           (["-q"], [])])
def test_the_one_rule_for_what_a_step_says(flags, shown, capsys):
    from hbis_torch.cli import configure_logging
    from hbis_torch.cli.common import tell
    from hbis_torch.notices import act

    args = build_parser(["design"]).parse_args(["design", *flags])
    configure_logging(args.verbose, args.quiet)
    tell("x", ["said"], about="a")
    tell("x", [act("act")])
    assert capsys.readouterr().err.splitlines() == shown


def test_a_line_that_asks_to_act_is_marked_by_the_library():
    from hbis_torch.capture.frames import bit_depth_hint
    from hbis_torch.notices import asks_to_act
    from hbis_torch.reconstruct.learned.runtime import classical_returned

    assert asks_to_act(bit_depth_hint(np.full((2, 4, 4), 4000, np.uint16)))
    said: list = []
    classical_returned(np.zeros((4, 4), np.float32), "outside the training domain", said)
    assert [asks_to_act(line) for line in said] == [True]


# --------------------------------------------------------------------------- 3. one meaning per flag


def _parsers(parser=None):
    """Every parser of the CLI, sub-commands' too."""
    parser = parser or build_parser()
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                yield from _parsers(child)


def test_roi_is_u0_v0_w_h_wherever_it_is_shown():
    shown = [(p.prog, a) for p in _parsers() for a in p._actions if "--roi" in a.option_strings]
    assert {prog for prog, _ in shown} >= {"hbis simulate", "hbis assemble", "hbis motors scan", "hbis demo"}
    for prog, action in shown:
        if action.help == argparse.SUPPRESS:  # the demo's: refused with a pointer to --roi-size
            assert prog == "hbis demo"
            continue
        assert re.search(r"U0,V0,W(IDTH)?,H(EIGHT)?", f"{action.metavar} {action.help}"), prog


def test_demo_takes_roi_size_and_refuses_roi_naming_it(capsys):
    args = build_parser(["demo"]).parse_args(["demo", "--roi-size", "64"])
    assert args.roi_size == 64
    with pytest.raises(SystemExit) as exit_:
        main(["demo", "--roi", "608,456,64,48", "--out", "x"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--roi-size" in err and "U0,V0,WIDTH,HEIGHT" in err


def test_demo_model_takes_the_tier_names_as_reconstruct_does(tmp_path, monkeypatch, capsys):
    from hbis_torch.cli import cmd_demo

    ran = []
    monkeypatch.setattr(cmd_demo, "_run", lambda args: (ran.append(args.model), ({"figures": []}, None))[1])
    for tier in ("best", "fast"):
        assert main(["demo", "--model", tier, "--out", str(tmp_path / tier)]) == 0, capsys.readouterr().err
    assert ran == ["best", "fast"]
    assert main(["demo", "--model", "good", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "good: no such model file" in err and "'fast', 'best'" in err and ran == ["best", "fast"]


@pytest.mark.parametrize("command, flag", [("figures", "--only"), ("demo", "--figure-sets")])
def test_figure_sets_are_repeatable_or_a_comma_list_in_both_commands(command, flag, capsys):
    parse = build_parser([command]).parse_args
    dest = flag.lstrip("-").replace("-", "_")
    assert getattr(parse([command, flag, "design,scan"]), dest) == ["design", "scan"]
    assert getattr(parse([command, flag, "design", flag, "scan"]), dest) == ["design", "scan"]
    with pytest.raises(SystemExit) as exit_:
        parse([command, flag, "design,nope"])
    assert exit_.value.code == 2 and "no figure set 'nope'" in capsys.readouterr().err


# --------------------------------------------------------------------------- 4, 5. sizes and a burst's scale


def test_sizes_read_width_by_height_px_in_every_command(burst_frames, tmp_path, capsys):
    stack = tmp_path / "b.tif"
    assert main(["assemble", "--burst", "--scale", "2", "--bit-depth", "12", "--out", str(stack),
                 str(burst_frames)]) == 0
    assert f"of {W} x {H} px" in capsys.readouterr().out
    assert main(["reconstruct", str(stack), "--out", str(tmp_path / "sr.tif")]) == 0
    assert f"({2 * W} x {2 * H} px" in capsys.readouterr().out
    assert main(["simulate", "--scene", "flat", "--h", "2", "--roi", "600,450,20,12", "--out", str(tmp_path / "s.tif"),
                 "--truth", str(tmp_path / "t.tif")]) == 0
    out = capsys.readouterr().out
    assert "frames of 20 x 12 px" in out and "40 x 24 px float32" in out


def test_validate_calls_a_burst_s_factor_its_scale(burst_stack, capsys):
    assert main(["validate", str(burst_stack), "--holdout", "1", "--method", "single"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert "burst of 6 frames, scale S = 2," in header and "h =" not in header
    assert main(["validate", str(burst_stack), "--holdout", "1", "--method", "single", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["scale"] == 2 and "h" not in report


# --------------------------------------------------------------------------- 6. one overwrite rule


def test_out_refuses_and_out_dir_skips_an_existing_file_unless_overwrite(burst_stack, tmp_path, capsys):
    out, folder = tmp_path / "sr.tif", tmp_path / "many"
    folder.mkdir()
    for path in (out, folder / "burst.classical.tif"):
        path.write_bytes(b"keep me")
    assert main(["reconstruct", str(burst_stack), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "exists already; pass --overwrite to replace it" in err
    # --out-dir: a file that exists is what an earlier run wrote; skipped, so a rerun resumes
    # (with or without --scheduler, docs/scale-out.md)
    assert main(["reconstruct", str(burst_stack), "--out-dir", str(folder)]) == 0
    assert "reconstructed 0 of 1 stacks" in capsys.readouterr().out
    assert out.read_bytes() == b"keep me" and (folder / "burst.classical.tif").read_bytes() == b"keep me"
    for argv in (["--out", str(out)], ["--out-dir", str(folder)]):
        assert main(["reconstruct", str(burst_stack), *argv, "--overwrite"]) == 0
    assert tifffile.imread(out).shape == tifffile.imread(folder / "burst.classical.tif").shape == (2 * H, 2 * W)


@pytest.mark.parametrize("argv", [
    ["simulate", "--scene", "flat", "--h", "2", "--out", "{old}"],
    ["simulate", "--scene", "flat", "--h", "2", "--out", "{tmp}/new.tif", "--truth", "{old}"],
    ["assemble", "--burst", "--scale", "2", "--out", "{old}", "{frames}"],
])
def test_every_output_file_follows_the_rule(argv, burst_frames, tmp_path, capsys):
    old = tmp_path / "old.tif"
    old.write_bytes(b"keep me")
    argv = [a.format(old=old, tmp=tmp_path, frames=burst_frames) for a in argv]
    assert main(argv) == 2
    assert "pass --overwrite" in capsys.readouterr().err and old.read_bytes() == b"keep me"
    assert build_parser([argv[0]]).parse_args([*argv, "--overwrite"]).overwrite


# --------------------------------------------------------------------------- 7. help texts


def _help(argv, monkeypatch=None, columns=None):
    if monkeypatch is not None and columns:
        monkeypatch.setenv("COLUMNS", str(columns))
    try:
        main([*argv, "--help"])
    except SystemExit:
        pass


@pytest.mark.parametrize("command", ["", *(c for c in COMMANDS if c != "motors")])  # motors: another's files
def test_every_command_s_help_ends_with_an_example(command, capsys):
    _help([command] if command else [])
    out = capsys.readouterr().out
    tail = out[out.rindex("\nexample"):]
    assert re.search(r"^  hbis " + command + r" ?", tail, re.M), tail
    for line in (line.strip() for line in tail.splitlines() if line.startswith("  hbis ") and "COMMAND" not in line):
        build_parser(shlex.split(line)[1:]).parse_args(shlex.split(line)[1:])  # the example parses


def test_reconstruct_help_lists_the_general_options_before_a_method_s(capsys):
    _help(["reconstruct"])
    out = capsys.readouterr().out
    method = out.index("options of one method:")
    for general in ("--out OUT", "--out-dir DIR", "--jobs", "--threads", "--overwrite", "-q, --quiet", "--dark"):
        assert out.index(general) < method, general


def test_grbl_is_mentioned_only_by_motor_commands(capsys):
    for argv in (["design"], ["reconstruct"], ["validate"], ["motors"], ["motors", "scan"]):
        _help(argv)
        text = " ".join(capsys.readouterr().out.split())
        assert ("GRBL serial traffic" in text) == (argv[0] == "motors"), argv


def test_validate_s_description_wraps_to_the_terminal(monkeypatch, capsys):
    for columns in (60, 120):
        _help(["validate"], monkeypatch, columns)
        out = capsys.readouterr().out
        description = out[out.index("Score super-resolution"):out.index("positional arguments")]
        lines = description.splitlines()
        assert max(map(len, lines)) <= columns and "Limits: it measures" in description
        assert max(map(len, lines)) > columns - 15  # filled to the width, not left at a fixed one


def test_hbis_help_the_figures_command_and_the_readme_name_the_same_figures(capsys):
    from hbis_torch.cli.cmd_figures import PAPER_FIGURES

    drawn = set()
    for module in (REPO / "hbis_torch" / "figures").glob("*_figures.py"):
        drawn |= {int(n) for n in re.findall(r"fig(\d+)[a-z]?_\w+\.png", module.read_text())}
    assert sorted(drawn) == list(PAPER_FIGURES)
    _help([])
    listed = re.search(r"figures\s+draw the paper's figures \(([\d, ]+)\)", capsys.readouterr().out)
    readme = re.search(r"# the paper's figures ([\d, ]+)\n", (REPO / "README.md").read_text())
    for found in (listed, readme):
        assert found and [int(n) for n in found.group(1).split(",")] == list(PAPER_FIGURES)


def test_simulate_help_imports_no_torch_and_its_written_out_lists_agree():
    code = ("import sys\nfrom hbis_torch.cli import main\ntry:\n    main(['simulate', '--help'])\n"
            "except SystemExit:\n    pass\nprint([m for m in ('torch', 'numpy') if m in sys.modules], file=sys.stderr)")
    done = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=120)
    assert done.stderr.strip() == "[]" and "siemens-star" in done.stdout
    from dataclasses import asdict

    from hbis_torch.cli.cmd_simulate import SCENES, SENSOR_DEFAULTS
    from hbis_torch.simulate import BUILTIN_SCENES, SensorModel

    assert SCENES == tuple(sorted(BUILTIN_SCENES))
    assert {k: v for k, v in asdict(SensorModel()).items() if k in SENSOR_DEFAULTS} == SENSOR_DEFAULTS
    assert set(SENSOR_DEFAULTS) == {k for k in asdict(SensorModel()) if k != "noise"}


# --------------------------------------------------------------------------- 8. the README's commands


def test_the_readme_s_commands_parse():
    """Every ``hbis`` line of the README's command-line section parses (--out-dir among them)."""
    text = (REPO / "README.md").read_text()
    block = text[text.index("## Command line"):text.index("## Library")]
    lines = [line.split("#")[0].rstrip(" &") for line in block.splitlines() if line.startswith("hbis ")]
    assert any("--out-dir" in line for line in lines) and len(lines) >= 10
    for line in lines:
        argv = shlex.split(line)[1:]
        build_parser(argv).parse_args(argv)
    assert "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu" in text


def test_the_demo_can_draw_no_figures():
    from hbis_torch.cli import build_parser

    args = build_parser(["demo"]).parse_args(["demo", "--no-figures"])
    assert args.figure_sets == []
    assert build_parser(["demo"]).parse_args(["demo"]).figure_sets is None

"""The command-line conventions every subcommand keeps (docs/design.md, section 2)."""

import gc
import logging
import os
import platform
import subprocess
import sys

import pytest

import hbis_torch
import hbis_torch.cli as cli
from hbis_torch.cli import COMMANDS, GC_THRESHOLDS, build_parser, configure_logging, main
from hbis_torch.progress import progress, progress_enabled, set_progress


@pytest.fixture
def clean_logging():
    """Leave the hbis_torch logger and the progress switch as they were."""
    logger = logging.getLogger("hbis_torch")
    level, handlers = logger.level, list(logger.handlers)
    yield logger
    logger.setLevel(level)
    logger.handlers[:] = handlers
    set_progress(None)


def _run(*args, **kw):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (os.path.dirname(os.path.dirname(hbis_torch.__file__)),
                                                                      os.environ.get("PYTHONPATH")) if p)}
    return subprocess.run([sys.executable, *args], env=env, **kw)


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"hbis {hbis_torch.__version__}"


def test_a_command_runs_under_the_start_up_collector_thresholds_and_restores_them(monkeypatch):
    """main runs the command with GC_THRESHOLDS (fewer collections while the imports make their
    objects) and gives the caller's thresholds back, also when the command ends by SystemExit."""
    seen = []

    def command(argv):
        seen.append(gc.get_threshold())
        if argv:
            raise SystemExit(2)
        return 0

    monkeypatch.setattr(cli, "_main", command)
    before = gc.get_threshold()
    try:
        gc.set_threshold(123, 4, 5)
        assert main([]) == 0
        assert gc.get_threshold() == (123, 4, 5)
        with pytest.raises(SystemExit):
            main(["--version"])
        assert gc.get_threshold() == (123, 4, 5)
    finally:
        gc.set_threshold(*before)
    assert seen == [GC_THRESHOLDS, GC_THRESHOLDS] and GC_THRESHOLDS[0] > 700


def test_the_program_exits_with_main_s_code_after_freezing_the_collector(monkeypatch):
    """entry_point (the hbis script, python -m hbis_torch) exits with main's code, having frozen
    the objects alive so that the interpreter's last collection skips them; for real: a bad
    input exits 2 through python -m hbis_torch."""
    frozen, kept = [], []
    monkeypatch.setattr(cli, "main", lambda: 3)
    monkeypatch.setattr(cli, "keep_freed_memory", lambda: kept.append(not frozen))  # (not in pytest's process)
    monkeypatch.setattr(gc, "freeze", lambda: frozen.append(True))
    with pytest.raises(SystemExit) as exit_:
        cli.entry_point()
    assert exit_.value.code == 3 and frozen == [True] and kept == [True]
    run = subprocess.run([sys.executable, "-m", "hbis_torch", "reconstruct", "no-such-stack.tif", "--out", "x.tif"],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "no such file" in run.stderr


KEEPS = """
import sys, numpy as np
from hbis_torch.cli import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
def rss(): return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
before = rss()
block = np.ones(2**25, np.float32)  # 128 MB
del block
print(applied, rss() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_the_program_keeps_freed_memory_for_the_next_array():
    """The hbis program keeps freed memory in its heap (keep_freed_memory): a 128 MB array freed
    stays resident for the next, where by default it goes back to the system at once."""
    grown = {}
    for mode in ("default", "keep"):
        run = subprocess.run([sys.executable, "-c", KEEPS, mode], capture_output=True, text=True, check=True)
        applied, grown[mode] = run.stdout.split()
    assert applied == "True"
    assert float(grown["keep"]) > 120 and float(grown["default"]) < 20


MAPS = """
import sys, numpy as np
from hbis_torch.cli import LARGE_JOB_SAMPLES, keep_freed_memory, map_large_arrays
keep_freed_memory()
small, large = map_large_arrays(LARGE_JOB_SAMPLES), map_large_arrays(LARGE_JOB_SAMPLES + 1)
def rss(): return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
before = rss()
block = np.ones(2**25, np.float32)  # 128 MB
del block
print(small, large, map_large_arrays(LARGE_JOB_SAMPLES + 1), rss() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_a_large_job_maps_its_large_arrays_again():
    """A job past LARGE_JOB_SAMPLES gives its large blocks back when freed (map_large_arrays),
    once; a smaller one leaves the program's kept memory as it is."""
    run = subprocess.run([sys.executable, "-c", MAPS], capture_output=True, text=True, check=True)
    small, large, again, grown = run.stdout.split()
    assert (small, large, again) == ("False", "True", "False") and float(grown) < 20, run.stdout


def test_a_closed_pipe_ends_quietly():
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the first byte
    try:
        done = _run("-m", "hbis_torch", "scan", "--h", "2", "--phases-deg", "5,70", "--json",
                    stdout=write, stderr=subprocess.PIPE, text=True, timeout=300)
    finally:
        os.close(write)
    assert done.stderr == "" and done.returncode == 141


@pytest.mark.parametrize("argv, level", [([], logging.WARNING), (["-v"], logging.INFO), (["-vv"], logging.DEBUG),
                                         (["-q"], logging.ERROR)])
def test_verbosity_before_or_after_the_subcommand(argv, level, clean_logging, capsys):
    for args in (argv + ["design", "--json"], ["design", "--json"] + argv):
        assert main(args) == 0
        assert clean_logging.level == level
        if "-q" in argv:
            assert not progress_enabled()
    capsys.readouterr()


def test_the_library_logs_and_the_cli_shows_it_by_level(clean_logging, capsys):
    configure_logging(verbose=1)
    logging.getLogger("hbis_torch.hardware.grbl").info("controller message: hello")
    logging.getLogger("hbis_torch.hardware.grbl").debug("<- 'ok'")
    err = capsys.readouterr().err
    assert "controller message: hello" in err and "<- 'ok'" not in err
    configure_logging(quiet=True)
    logging.getLogger("hbis_torch.hardware.grbl").warning("ignored a line")
    assert capsys.readouterr().err == ""
    assert len([h for h in clean_logging.handlers if getattr(h, "_hbis_cli", False)]) == 1


def test_progress_only_on_a_terminal_and_never_when_quiet(clean_logging, monkeypatch):
    monkeypatch.setattr(sys, "stderr", open(os.devnull, "w"))  # not a terminal
    assert not progress_enabled()
    assert progress(range(3), desc="x").disable
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert progress_enabled()
    monkeypatch.setenv("HBIS_PROGRESS", "0")
    assert not progress_enabled()
    monkeypatch.delenv("HBIS_PROGRESS")
    set_progress(False)  # what -q does
    assert not progress_enabled()


def test_an_option_at_the_wrong_level_is_named(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["motors", "scan", "--port", "X", "--h", "2", "--dry-run"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1
    assert "--port is an option of 'hbis motors': put it before 'scan'" in err


def test_help_shows_the_table1_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for default in ("pixel pitch p [um] (default: 3.75)", "sensor rows M (default: 960)",
                    "F-number F (default: 1.4)", "prism wedge angle a [deg] (default: 4.0)"):
        assert default in out


def test_help_does_not_import_torch_or_matplotlib():
    code = ("import sys\nfrom hbis_torch.cli import main\n"
            "for argv in (['--help'], ['reconstruct', '--help'], ['figures', '--help'], ['motors', 'scan', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "print([m for m in ('torch', 'matplotlib', 'scipy', 'onnxruntime') if m in sys.modules], file=sys.stderr)")
    done = _run("-c", code, capture_output=True, text=True, timeout=120)
    assert done.stderr.strip() == "[]"


def test_every_subcommand_builds_and_the_written_out_choices_agree():
    from hbis_torch.cli import cmd_scan
    from hbis_torch.scan import CONVENTIONS, METHODS

    assert set(cmd_scan.METHODS) == set(METHODS) and set(cmd_scan.CONVENTIONS) == set(CONVENTIONS)
    parser = build_parser()
    for name in COMMANDS:
        assert name in parser.format_help()

"""A corpus of hostile files and clumsy arguments, generated here, small, run in CI.

For every case: exit code 2, exactly one line on stderr, no traceback, the input untouched, no
output file (not even a temporary one), within 2 s. The hostile files are also read directly
(``read_stack`` / ``read_image_file``) under tracemalloc: at most 300 MB allocated.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import tifffile

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError, StackFormatError
from hbis_torch.hardware.scan_executor import ScanJournal
from hbis_torch.stack_io import Stack, make_meta, read_stack, write_stack

REPO = Path(__file__).resolve().parents[1]
SECONDS = 2.0
MEMORY = 300 * 2**20
ROI = (600, 400, 16, 12)


# --------------------------------------------------------------------------- the corpus


def _meta(h=2, frames=4, bit_depth=12):
    phases = np.column_stack((5 + 0.01 * np.arange(frames), 70 - 0.01 * np.arange(frames)))
    return make_meta(FoveaSystem(), h, ROI, phases, bit_depth=bit_depth)


def _frames(n=4, dtype=np.uint16):
    return np.random.default_rng(0).integers(0, 4096, (n, ROI[3], ROI[2])).astype(dtype)


def _raw(path, frames, description):
    """Write pages with any description, bypassing the writer's checks."""
    tifffile.imwrite(path, frames, description=description, metadata=None, photometric="minisblack")


def _declare(path, width, height):
    """Make every page's header declare ``width`` x ``height`` (the data stays as small as it was)."""
    with tifffile.TiffFile(path, mode="r+") as tif:
        for page in tif.pages:
            page.tags["ImageWidth"].overwrite(width)
            page.tags["ImageLength"].overwrite(height)


def _png_declaring(path, width, height):
    """A 1 x 1 RGB PNG whose IHDR claims ``width`` x ``height`` (CRC fixed)."""
    from PIL import Image

    Image.new("RGB", (1, 1)).save(path)
    data = bytearray(path.read_bytes())
    ihdr = 8 + 8  # signature, then the IHDR chunk's length and type
    data[ihdr:ihdr + 8] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[ihdr + 13:ihdr + 17] = zlib.crc32(bytes(data[ihdr - 4:ihdr + 13])).to_bytes(4, "big")
    path.write_bytes(bytes(data))


def _valid(path):
    write_stack(path, Stack(_frames(), _meta()))


def _json_case(text):
    return lambda p: _raw(p, _frames(), text)


def _mixed(path):
    meta = json.dumps(_meta())
    tifffile.imwrite(path, _frames(1)[0], description=meta, metadata=None, photometric="minisblack")
    for frame in _frames(3, np.uint8):
        tifffile.imwrite(path, frame, append=True, metadata=None, photometric="minisblack")


def _truncated(path):
    _valid(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _bomb(path):  # 16 pages declaring 20000 x 20000 each, a few kB on disk
    _raw(path, np.zeros((16, 2, 2), np.uint8), json.dumps(_meta(h=4, frames=16)))
    _declare(path, 20000, 20000)


def _overclaim(path):  # under the size cap, but the data is not in the file
    _raw(path, _frames(), json.dumps(_meta()))
    _declare(path, 4000, 3000)


def _meta_text(**change):
    meta = _meta()
    for key, value in change.items():
        if "." in key:
            block, sub = key.split(".")
            meta[block][sub] = value
        else:
            meta[key] = value
    return json.dumps(meta)


STACKS = {
    "not a tiff": lambda p: p.write_bytes(os.urandom(4096)),
    "empty file": lambda p: p.write_bytes(b""),
    "tiff magic only": lambda p: p.write_bytes(b"II*\x00\x08\x00\x00\x00"),
    "16 pages of 20000 x 20000": _bomb,
    "data missing (header claims 4000 x 3000)": _overclaim,
    "truncated at half": _truncated,
    "mixed dtypes": _mixed,
    "3 frames for h = 2": lambda p: _raw(p, _frames(3), json.dumps(_meta(frames=3))),
    "300 pages": lambda p: _raw(p, np.zeros((300, 2, 2), np.uint8), "{}"),
    "rgb pages": lambda p: _raw(p, np.zeros((4, 12, 16, 3), np.uint8), json.dumps(_meta())),
    "no description": lambda p: tifffile.imwrite(p, _frames(), metadata=None, photometric="minisblack"),
    "description not json": _json_case("hello"),
    "json 5000-digit integer": _json_case('{"h": ' + "9" * 5000 + "}"),
    "json nested 100000 deep": _json_case("[" * 100_000 + "]" * 100_000),
    "json duplicate keys": _json_case(_meta_text()[:-1] + ', "h": 3}'),
    "json NaN phase": _json_case(_meta_text(phases_deg=[[float("nan"), 1.0]] * 4)),
    "json 1e999": _json_case(_meta_text(object_distance_mm=1).replace('"object_distance_mm": 1', '"object_distance_mm": 1e999')),
    "json phases 1e308": _json_case(_meta_text(phases_deg=[[1e308, 1.0]] * 4)),
    "json h 10**6": _json_case(_meta_text(h=10**6)),
    "json rows 10**12": _json_case(_meta_text(**{"camera.rows": 10**12})),
    "json roi huge": _json_case(_meta_text(roi=[0, 0, 10**9, 10**9])),
    "json format list": _json_case("[1, 2]"),
    "float frames with NaN": lambda p: _raw(p, np.full((4, 12, 16), np.nan, np.float32), json.dumps(_meta(bit_depth=None))),
}

SCENES = {
    "png declaring 10000 x 10000 rgb": lambda p: _png_declaring(p.with_suffix(".png"), 10000, 10000),
    "png declaring 30000 x 30000": lambda p: _png_declaring(p.with_suffix(".png"), 30000, 30000),
    "tiff declaring 20000 x 20000": lambda p: (_raw(p, np.zeros((2, 2), np.uint8), "{}"), _declare(p, 20000, 20000)),
    "png truncated": lambda p: (_png_declaring(p.with_suffix(".png"), 1, 1),
                                p.with_suffix(".png").write_bytes(p.with_suffix(".png").read_bytes()[:30])),
}


def _scene_path(path: Path) -> Path:
    return path.with_suffix(".png") if path.with_suffix(".png").exists() else path


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    files = {}
    for name, make in STACKS.items():
        path = root / f"stack-{len(files):02d}.tif"
        make(path)
        files[name] = path
    for name, make in SCENES.items():
        path = root / f"scene-{len(files):02d}.tif"
        make(path)
        files[name] = _scene_path(path)
    valid = root / "valid.tif"
    _valid(valid)
    files["valid"] = valid
    return files


# --------------------------------------------------------------------------- the checks


def _digest(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def _listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def refused(argv, capsys, out_dir: Path, inputs=()):
    """Run ``hbis argv`` in-process: exit 2, one stderr line, no traceback, inputs untouched,
    nothing new in ``out_dir``, within 2 s. Returns the stderr line."""
    before = {p: _digest(Path(p)) for p in inputs}
    listing = _listing(out_dir)
    capsys.readouterr()
    start = time.perf_counter()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own errors (one line, exit 2) leave main this way
        rc = exc.code
    elapsed = time.perf_counter() - start
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, f"exit {rc}: {err}"
    assert len(lines) == 1 and "Traceback" not in err, err
    assert elapsed < SECONDS, f"took {elapsed:.1f} s: {err}"
    assert {p: _digest(Path(p)) for p in inputs} == before, "an input was changed"
    assert _listing(out_dir) == listing, f"left {sorted(_listing(out_dir) - listing)}"
    return lines[0]


@pytest.fixture(scope="module", autouse=True)
def warm_imports():
    """Import what the commands import once, so that the 2 s bound measures the checks."""
    import hbis_torch.cli.cmd_demo  # noqa: F401
    import hbis_torch.reconstruct.registry  # noqa: F401
    import hbis_torch.simulate  # noqa: F401


@pytest.mark.parametrize("name", list(STACKS))
def test_hostile_stack_is_refused_by_reconstruct(corpus, name, capsys, tmp_path):
    path = corpus[name]
    line = refused(["reconstruct", path, "--out", tmp_path / "o.tif"], capsys, tmp_path, [path])
    assert line.startswith("hbis reconstruct: error: ")


@pytest.mark.parametrize("name", list(STACKS))
def test_hostile_stack_is_read_within_time_and_memory(corpus, name):
    path = corpus[name]
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(StackFormatError) as info:
            read_stack(path)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert time.perf_counter() - start < SECONDS
    assert peak < MEMORY, f"{peak / 2**20:.0f} MB"
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message


@pytest.mark.parametrize("name", list(SCENES))
def test_hostile_scene_image_is_refused(corpus, name, capsys, tmp_path):
    from hbis_torch.simulate.rasters import read_image_file

    path = corpus[name]
    tracemalloc.start()
    try:
        with pytest.raises(HbisInputError):
            read_image_file(path)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < MEMORY, f"{peak / 2**20:.0f} MB"
    refused(["simulate", "--scene", path, "--h", "2", "--roi", "600,400,16,12", "--out", tmp_path / "s.tif"],
            capsys, tmp_path, [path])


def test_the_bomb_in_a_fresh_process_stays_small(corpus, tmp_path):
    """The real exit code and stderr of a fresh process, and its peak memory over what the
    imports took (ru_maxrss before and after ``main``)."""
    script = ("import resource, sys; from hbis_torch.cli import main; import hbis_torch.reconstruct.registry; "
              "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss; rc = main(sys.argv[1:]); "
              "print(before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", script, "reconstruct", corpus["16 pages of 20000 x 20000"],
                           "--out", tmp_path / "o.tif"],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert "HBIS_MAX_STACK_MB" in proc.stderr
    before_kb, after_kb = (int(v) for v in proc.stdout.split())
    assert (after_kb - before_kb) * 1024 < MEMORY
    assert not (tmp_path / "o.tif").exists()


def test_the_default_limit_takes_a_large_burst_and_refuses_a_bomb(monkeypatch):
    """16 frames of 24 MP in 16-bit RGB (2197 MiB) fit the default decoding limit (1024 MiB had
    refused 12 MP ones); 16 pages of 20000 x 20000 do not, and a scene image keeps 1024 MiB."""
    from hbis_torch.capture.frames import FrameInfo, check_decoded_size
    from hbis_torch.simulate.rasters import SCENE_MAX_MB
    from hbis_torch.tiff_io import max_decoded_bytes

    monkeypatch.delenv("HBIS_MAX_STACK_MB", raising=False)
    burst = FrameInfo(16, (4000, 6000, 3), np.dtype(np.uint16))
    assert check_decoded_size([burst], ["burst.tif"]) == 16 * 4000 * 6000 * 3 * 2
    with pytest.raises(HbisInputError, match="over the limit of 4096 MiB"):
        check_decoded_size([FrameInfo(16, (20000, 20000), np.dtype(np.uint8))], ["bomb.tif"])
    assert max_decoded_bytes(SCENE_MAX_MB) == 1024 * 2**20 < max_decoded_bytes()


def test_the_size_limit_can_be_raised(corpus, monkeypatch):
    with pytest.raises(StackFormatError, match="over the limit of 4096 MiB"):
        read_stack(corpus["16 pages of 20000 x 20000"])
    monkeypatch.setenv("HBIS_MAX_STACK_MB", "0.001")
    with pytest.raises(StackFormatError, match="over the limit of 0 MiB"):
        read_stack(corpus["valid"])
    monkeypatch.setenv("HBIS_MAX_STACK_MB", "lots")
    with pytest.raises(HbisInputError, match="HBIS_MAX_STACK_MB must be"):
        read_stack(corpus["valid"])
    monkeypatch.setenv("HBIS_MAX_STACK_MB", "2048")
    assert read_stack(corpus["valid"]).frames.shape == (4, 12, 16)


# --------------------------------------------------------------------------- arguments


OUT = "{tmp}/out.tif"
ARGUMENTS = [
    ["demo", "--h", "0", "--out", "{tmp}/demo"],
    ["demo", "--h", "-1", "--out", "{tmp}/demo"],
    ["demo", "--h", "100", "--out", "{tmp}/demo"],
    ["demo", "--roi-size", "0", "--out", "{tmp}/demo"],
    ["demo", "--roi-size", "-5", "--out", "{tmp}/demo"],
    ["demo", "--roi-size", "100000", "--out", "{tmp}/demo"],
    ["demo", "--roi", "608,456,64,48", "--out", "{tmp}/demo"],  # --roi is U0,V0,W,H elsewhere: the demo names --roi-size
    ["demo", "--assembly-error-deg", "nan", "--out", "{tmp}/demo"],
    ["demo", "--seed", "-1", "--out", "{tmp}/demo"],
    ["demo", "--seed", str(2**70), "--out", "{tmp}/demo"],
    ["demo", "--threads", "0", "--out", "{tmp}/demo"],
    ["demo", "--h", "5", "--out", "{tmp}/demo"],  # no shipped model for h = 5
    ["demo", "--out", "{file}"],
    ["demo", "--out", "/proc/hbis-demo"],
    ["design", "--h", "1e9"],
    ["design", "--h", "17"],
    ["design", "--rows", "1000000000000"],
    ["design", "--cols", "0"],
    ["design", "--n", "1"],
    ["design", "--n", "inf"],
    ["design", "--alpha-deg", "90"],
    ["design", "--f-number", "-1.4"],
    ["design", "--wavelength-nm", "nan"],
    ["design", "--object-distance-mm", "1e400"],
    ["design", "--pixel-pitch-um", "0"],
    ["design", "--varphi-h-deg", "90"],
    ["design", "--focal-length-mm", "9" * 5000],
    ["scan", "--h", "2", "--phases-deg", "1e308,70"],
    ["scan", "--h", "2", "--phases-deg", "5,70", "--pixel-stride", "0"],
    ["scan", "--h", "2", "--phases-deg", "5,70", "--ae-bound", "-1"],
    ["motors", "goto", "1e308", "70"],
    ["motors", "goto", "nan", "70"],
    ["motors", "--baud", "99999999999", "status"],
    ["motors", "--timeout-s", "1e300", "status"],
    ["motors", "--timeout-s", "0", "status"],
    ["motors", "simulate", "--tcp", "-1"],
    ["motors", "simulate", "--tcp", "70000"],
    ["motors", "simulate", "--duration", "-1"],
    ["motors", "simulate", "--duration", "nan"],
    ["motors", "simulate", "--speedup", "0"],
    ["motors", "scan", "--h", "0", "--dry-run", "--steps-per-deg", "100,100"],
    ["motors", "scan", "--h", "2", "--settle-s", "-1", "--dry-run", "--steps-per-deg", "100,100"],
    ["motors", "--port", "loop://", "scan", "--h", "2", "--journal", "/proc/j.json"],
    ["simulate", "--scene", "flat", "--h", "100", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--seed", "-1", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--oversample", "100000", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--margin-px", "1e9", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--fill-factor", "0", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--phase-error-deg", "nan", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--roi", "0,0,0,0", "--out", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--out", OUT, "--truth", OUT],
    ["simulate", "--scene", "flat", "--h", "2", "--out", OUT, "--truth", "/proc/t.tif"],
    ["simulate", "--scene", "flat", "--h", "2", "--out", "{tmp}"],
    ["simulate", "--scene", "flat", "--h", "2", "--out", ""],
    ["simulate", "--scene", "flat", "--h", "2", "--out", "{file}/x.tif"],
    ["simulate", "--scene", "{valid}", "--h", "2", "--out", "{valid}"],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", "{valid}"],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", "{tmp}"],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", ""],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", "/proc/o.tif"],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", "{file}/o.tif"],
    ["reconstruct", "{valid}", "--registration", "optics", "--out", "{link_to_valid}"],
    ["figures", "--out", "{file}"],
    ["assemble", "{valid}", "--phases", "{file}", "--out", "{valid}"],
    ["assemble", "{valid}", "--phases", "{file}", "--out", "{file}"],
    ["assemble", "{valid}", "--phases", "{file}", "--out", "/proc/s.tif"],
    ["assemble", "{valid}", "--phases", "{file}", "--bit-depth", "17", "--out", OUT],
    ["assemble", "{valid}", "--phases", "{file}", "--black-level", "nan", "--out", OUT],
]


@pytest.mark.parametrize("argv", ARGUMENTS, ids=[" ".join(a) for a in ARGUMENTS])
def test_bad_argument_is_refused_at_the_door(corpus, argv, capsys, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    file = work / "a-file"
    file.write_text("not a folder")
    valid = work / "valid.tif"
    valid.write_bytes(corpus["valid"].read_bytes())
    link = work / "link.tif"
    link.symlink_to(valid)
    fill = {"tmp": work, "file": file, "valid": valid, "link_to_valid": link}
    refused([a.format(**fill) for a in argv], capsys, work, [file, valid])


def test_an_output_written_through_a_link_keeps_the_link_and_the_umask(corpus, tmp_path, capsys):
    target = tmp_path / "real.tif"
    target.write_bytes(b"old")
    link = tmp_path / "link.tif"
    link.symlink_to(target)
    old = os.umask(0o022)
    try:
        assert main(["reconstruct", str(corpus["valid"]), "--registration", "optics", "--no-deblur",
                     "--out", str(link), "--overwrite"]) == 0
        assert main(["reconstruct", str(corpus["valid"]), "--registration", "optics", "--no-deblur",
                     "--out", str(tmp_path / "new.tif")]) == 0
    finally:
        os.umask(old)
    assert link.is_symlink() and tifffile.imread(link).shape == (24, 32)
    assert (tmp_path / "new.tif").stat().st_mode & 0o777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.tif", "new.tif", "real.tif"]


# --------------------------------------------------------------------------- JSON elsewhere


HOSTILE_JSON = ["9" * 5000, "[" * 100_000 + "]" * 100_000, '{"h": 2, "h": 3}', "NaN", "{", "[1, 2]",
                '{"x": 1e999}', "\udcff"]


@pytest.mark.parametrize("text", HOSTILE_JSON)
def test_hostile_phases_and_system_files_are_one_input_error(tmp_path, text):
    from hbis_torch.capture import read_phases
    from hbis_torch.capture.system_file import load_system

    path = tmp_path / "f.json"
    path.write_text(text, errors="surrogateescape")
    for read in (read_phases, load_system):
        with pytest.raises(HbisInputError) as info:
            read(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("text", ["9" * 5000, "[" * 100_000 + "]" * 100_000,
                                  '{"format": "hbis-motor-journal/1", "format": "x"}', "NaN", "{", "[1, 2]"])
def test_hostile_journal_is_one_input_error(tmp_path, text):
    journal = tmp_path / "j.json"
    journal.write_text(text)
    with pytest.raises(HbisInputError, match="is corrupt") as info:
        ScanJournal.open(journal, [[5.0, 70.0]])
    assert "\n" not in str(info.value) and journal.read_text() == text


# --------------------------------------------------------------------------- captured frames and videos


def _frame_files(folder: Path, count=4):
    paths = []
    for k, frame in enumerate(_frames(count, np.uint16)):
        paths.append(folder / f"f{k}.tif")
        tifffile.imwrite(paths[-1], frame)
    return paths


def _avi(path: Path, frames=None):
    import av

    frames = np.zeros((4, ROI[3], ROI[2]), np.uint8) if frames is None else frames
    with av.open(str(path), "w") as out:
        stream = out.add_stream("rawvideo", rate=5)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "gray"
        for f in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(f, format="gray")))
        out.mux(stream.encode())
    return path


def _avi_declaring(path: Path, width: int, height: int):
    """A small raw AVI whose headers (avih and the stream's BITMAPINFOHEADER) claim another size."""
    _avi(path)
    data = bytearray(path.read_bytes())
    avih = data.index(b"avih") + 8
    data[avih + 32:avih + 40] = width.to_bytes(4, "little") + height.to_bytes(4, "little")
    strf = data.index(b"strf") + 8
    data[strf + 4:strf + 12] = width.to_bytes(4, "little") + height.to_bytes(4, "little")
    path.write_bytes(bytes(data))
    return path


FRAME_CASES = {
    # name: (make(folder) -> list of FRAME arguments, fragment of the one-line message)
    "30000 x 30000 PNG among 16 frames": (
        lambda d: [*_frame_files(d, 16)[:8], _png_declaring(d / "bomb.png", 30000, 30000) or d / "bomb.png",
                   *_frame_files(d, 16)[8:15]], "its header declares 30000 x 30000"),
    "TIFF pages declaring 20000 x 20000": (lambda d: [_bomb(d / "b.tif") or d / "b.tif"], "over the limit"),
    "AVI declaring 30000 x 30000": (lambda d: [_avi_declaring(d / "v.avi", 30000, 30000)], "v.avi: "),
    # (seeded: some random bytes probe as a container without video, "holds no video stream", or slowly)
    "random bytes as AVI": (lambda d: [(d / "r.avi").write_bytes(np.random.default_rng(7).bytes(4096)) and d / "r.avi"],
                            "r.avi: "),
    "empty MP4": (lambda d: [(d / "e.mp4").write_bytes(b"") or d / "e.mp4"], "not a readable video"),
    "truncated AVI": (lambda d: [(d / "t.avi").write_bytes(_avi(d / "full.avi").read_bytes()[:300]) and d / "t.avi"],
                      "t.avi: "),
    "video among images": (lambda d: [*_frame_files(d, 3), _avi(d / "v.avi")], "give it alone"),
    # what tifffile.imwrite(path, frames) makes of three grey frames unless told photometric='minisblack'
    "three frames as one planar RGB page": (lambda d: [_planar_rgb(d / "p.tif")], "photometric='minisblack'"),
}


def _planar_rgb(path: Path) -> Path:
    tifffile.imwrite(path, np.zeros((3, ROI[3], ROI[2]), np.uint16), photometric="rgb", planarconfig="separate")
    return path


@pytest.mark.parametrize("name", list(FRAME_CASES))
def test_hostile_frames_are_refused_from_their_headers(name, capsys, tmp_path):
    """`hbis assemble` on hostile frame files: one line, exit 2, within 2 s, nothing written; the
    frames are refused before anything large is decoded (under tracemalloc: 300 MB)."""
    from hbis_torch.capture.frames import read_frames

    work = tmp_path / "w"
    work.mkdir()
    make, fragment = FRAME_CASES[name]
    sources = [Path(p) for p in make(work)]
    phases = work / "phases.json"
    phases.write_text(json.dumps({"format": "hbis-motor-phases/1"}))
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(HbisInputError) as info:
            read_frames(sources, count=16)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert time.perf_counter() - start < SECONDS and peak < MEMORY, f"{peak / 2**20:.0f} MB"
    assert fragment in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_a_frame_of_the_wrong_size_for_the_sensor_is_refused_before_decoding(capsys, tmp_path):
    """One PNG declaring 10000 x 10000 (300 MB decoded, under the limit): `hbis assemble` refuses it
    from its header against the sensor, before decoding, in a fresh process that stays small."""
    png = tmp_path / "b.png"
    _png_declaring(png, 10000, 10000)
    from test_capture_assemble import write_phases

    phases = tmp_path / "phases.json"
    write_phases(phases, h=2)
    script = ("import resource, sys; from hbis_torch.cli import main; import hbis_torch.capture; "
              "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss; rc = main(sys.argv[1:]); "
              "print(before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", script, "assemble", "--phases", str(phases), "--out",
                           str(tmp_path / "o.tif"), str(png)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "the frames are 10000 x 10000 pixels but the sensor is 1280 x 960" in proc.stderr
    before_kb, after_kb = (int(v) for v in proc.stdout.split())
    assert (after_kb - before_kb) * 1024 < MEMORY
    assert not (tmp_path / "o.tif").exists()


# --------------------------------------------------------------------------- calibration files, large jobs


@pytest.mark.parametrize("name", ["two numbers for 3 x 3", "3e8 x 3e8 declared (XML)", "NaN in K", "not YAML at all",
                                  "image size 1e12", "a map without data"])
def test_hostile_calibration_is_refused_by_assemble(name, capsys, tmp_path):
    pytest.importorskip("cv2")
    from test_capture_calibration_files import BROKEN

    text, fragment = BROKEN[name]
    cal = tmp_path / ("cal.xml" if text.startswith("<?xml") else "cal.yml")
    cal.write_text(text)
    frame = tmp_path / "f.tif"
    tifffile.imwrite(frame, _frames(1)[0])
    line = refused(["assemble", "--phases", tmp_path / "none.json", "--calibration", cal, "--out", tmp_path / "o.tif",
                    frame], capsys, tmp_path, [cal, frame])
    assert fragment in line and str(cal) in line


def test_a_stereo_calibration_without_a_camera_chosen_is_refused(capsys, tmp_path):
    cv2 = pytest.importorskip("cv2")
    cal = tmp_path / "intrinsics.yml"
    fs = cv2.FileStorage(str(cal), cv2.FILE_STORAGE_WRITE)
    for name, value in (("M1", np.eye(3) * 500 + [[0, 0, 300], [0, 0, 200], [0, 0, -499]]), ("D1", np.zeros((1, 5)))):
        fs.write(name, value)
    fs.release()
    line = refused(["assemble", "--phases", tmp_path / "none.json", "--calibration", cal, "--out", tmp_path / "o.tif",
                    tmp_path / "f.tif"], capsys, tmp_path, [cal])
    assert "choose one with FILE:M1" in line


def test_a_legal_job_too_large_for_the_machine_is_refused_at_once(capsys, tmp_path, monkeypatch):
    """`hbis simulate --h 16 --roi full` is legal; on a machine with 8 GiB free it is refused from
    its estimate, in one line, before any work (it once ran past 60 s at 1.9 GB)."""
    from hbis_torch import budget

    monkeypatch.setattr(budget, "available_memory_bytes", lambda: 8 * 2**30)
    line = refused(["simulate", "--scene", "flat", "--h", "16", "--roi", "full", "--out", tmp_path / "s.tif"],
                   capsys, tmp_path)
    assert "give --force" in line and "GiB" in line

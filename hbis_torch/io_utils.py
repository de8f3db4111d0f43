"""Small file helpers: atomic writes, output paths checked before any work, and a JSON reader
that hostile files cannot crash.

* :func:`atomic_path` / :func:`atomic_write_text` / :func:`atomic_write_bytes`: an interrupted
  run never leaves a half file; new files get the mode the user's umask gives (an existing file
  keeps its mode); a symbolic link is written through (its target is replaced, the link stays).
* :func:`check_output_path`, :func:`check_output_dir`, :func:`check_distinct_paths`: what the
  command line runs at the door, so that a path that cannot be written, or an output that would
  replace an input, is refused in one line before any work.
* :func:`load_json`: ``json.loads`` that answers every malformed or hostile text (a 5,000-digit
  integer, nesting 100,000 deep, duplicate keys, ``NaN``) with one :class:`HbisInputError` line.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path

from hbis_torch.errors import HbisInputError

#: Largest JSON text :func:`load_json` parses (characters); a stack's description is a few kB.
MAX_JSON_CHARS = 16 * 2**20

# Places where a regular file can never be written, even by root.
_PSEUDO_FILESYSTEMS = ("/proc", "/sys")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_target(path: Path) -> Path:
    """The file a write to ``path`` really replaces: a symbolic link's final target."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically.

    On error the temporary file is removed and any existing ``path`` is left untouched. A new
    file gets mode ``0o666 & ~umask`` (what ``open(path, "w")`` gives), an existing one keeps
    its mode. If ``path`` is a symbolic link, its target is replaced and the link kept.
    """
    path = _write_target(Path(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except OSError:
        mode = 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, mode)
    finally:
        os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# --------------------------------------------------------------------------- paths at the door


def _first_existing(path: Path) -> Path:
    while not os.path.lexists(path) and path != path.parent:
        path = path.parent
    return path


def _probe_dir(folder: Path, what: str) -> None:
    """Create and remove one temporary file in ``folder``: the only sure test that it takes files."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".hbis-probe.", dir=folder)
    except OSError as exc:
        raise HbisInputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(tmp)


def _not_pseudo(path: Path, what: str) -> None:
    real = os.path.realpath(path)
    for root in _PSEUDO_FILESYSTEMS:
        if real == root or real.startswith(root + "/"):
            raise HbisInputError(f"{what}: {path} lies under {root}, where no output file can be written")


def check_output_path(path, what: str = "--out", overwrite: bool = True) -> Path:
    """Refuse, in one line, an output file path that cannot be written; return it as a Path.

    Refused: ``""``; an existing directory or anything that is not a regular file (a device, a
    FIFO); a path under /proc or /sys; a path whose parent is a file; a folder in which no
    file can be created (tried with a temporary file, removed at once); with ``overwrite``
    False, a file that exists already (the CLI's rule: replaced only with ``--overwrite``).
    Folders still missing are fine (the writers create them), provided the nearest existing one
    takes files.
    """
    if path is None or str(path).strip() == "":
        raise HbisInputError(f"{what}: the output path is empty")
    path = Path(path)
    _not_pseudo(path, what)
    target = _write_target(path)
    if target.is_dir():
        raise HbisInputError(f"{what}: {path} is a directory; give a file name")
    if os.path.lexists(target) and not target.is_file():
        raise HbisInputError(f"{what}: {path} exists and is not a regular file")
    if not overwrite and os.path.lexists(path):
        raise HbisInputError(f"{what}: {path} exists already; pass --overwrite to replace it")
    ancestor = _first_existing(target.parent)
    if not ancestor.is_dir():
        raise HbisInputError(f"{what}: {ancestor} is a file, so {path} cannot be created under it")
    _probe_dir(ancestor, what)
    return path


def check_output_dir(path, what: str = "--out") -> Path:
    """Refuse, in one line, an output folder that cannot be created or written; return it."""
    if path is None or str(path).strip() == "":
        raise HbisInputError(f"{what}: the output folder is empty")
    path = Path(path)
    _not_pseudo(path, what)
    if os.path.lexists(path) and not path.is_dir():
        raise HbisInputError(f"{what}: {path} exists and is not a folder")
    ancestor = _first_existing(path)
    if not ancestor.is_dir():
        raise HbisInputError(f"{what}: {ancestor} is a file, so the folder {path} cannot be created")
    _probe_dir(ancestor, what)
    return path


def _same_file(a, b) -> bool:
    a, b = Path(a), Path(b)
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_distinct_paths(inputs: dict, outputs: dict) -> None:
    """Refuse an output that is one of the inputs, or two outputs on one file.

    ``inputs`` and ``outputs`` map a name for the message (``"--out"``) to a path (None skipped).
    """
    outs = [(k, v) for k, v in outputs.items() if v is not None]
    for name, out in outs:
        for in_name, src in inputs.items():
            if src is not None and _same_file(src, out):
                raise HbisInputError(f"{name} {out} is the input {in_name}: it would be overwritten; "
                                     "choose another output file")
    for i, (name_a, a) in enumerate(outs):
        for name_b, b in outs[i + 1:]:
            if _same_file(a, b):
                raise HbisInputError(f"{name_a} and {name_b} are the same file ({a}); give each its own")


# --------------------------------------------------------------------------- JSON


def _no_duplicates(pairs):
    seen = {}
    for key, value in pairs:
        if key in seen:
            raise ValueError(f"duplicate key {key!r}")
        seen[key] = value
    return seen


def _no_constant(name):
    raise ValueError(f"{name} is not a JSON number")


#: Longest integer :func:`load_json` converts (digits): beyond int64, no value of hbis-torch.
_MAX_INT_DIGITS = 19


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > _MAX_INT_DIGITS:
        raise ValueError(f"an integer of {len(text.lstrip('-'))} digits")
    return int(text)


def _finite_float(text: str) -> float:
    value = float(text)
    if value in (float("inf"), float("-inf")):
        raise ValueError(f"{text[:20]} overflows a float")
    return value


def load_json(text, where: str):
    """Parse JSON text that may be hostile; raise :class:`HbisInputError` with one line if bad.

    Refused: text that is not JSON, longer than :data:`MAX_JSON_CHARS`, an integer of more than
    19 digits, a float that overflows (``1e999``), nesting too deep to parse, duplicate keys in
    one object, ``NaN`` or ``Infinity``. ``where`` (a file name, "page 0's ImageDescription of s.tif") starts the message.
    """
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode("utf-8", errors="replace")
    if len(text) > MAX_JSON_CHARS:
        raise HbisInputError(f"{where}: the JSON is {len(text)} characters, more than the "
                             f"{MAX_JSON_CHARS} accepted")
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_no_constant,
                          parse_int=_bounded_int, parse_float=_finite_float)
    except json.JSONDecodeError as exc:
        raise HbisInputError(f"{where}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    except RecursionError:
        raise HbisInputError(f"{where}: the JSON is nested too deeply") from None
    except ValueError as exc:  # a huge integer, a duplicate key, NaN
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise HbisInputError(f"{where}: the JSON is refused ({message})") from None


def read_json_file(path, what: str = "JSON file"):
    """Read and parse a JSON file with :func:`load_json`; a missing or unreadable file is one line too."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > 4 * MAX_JSON_CHARS:
            raise HbisInputError(f"{what} {path}: {size} bytes, too large for a JSON file of hbis-torch")
        text = path.read_bytes()
    except FileNotFoundError:
        raise HbisInputError(f"{what} {path}: no such file") from None
    except IsADirectoryError:
        raise HbisInputError(f"{what} {path}: is a directory") from None
    except OSError as exc:
        raise HbisInputError(f"{what} {path}: cannot be read ({exc.strerror or exc})") from None
    return load_json(text, f"{what} {path}")

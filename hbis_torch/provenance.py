"""Where a result came from: the one writer of every results file.

Every benchmark and ``training/eval_matrix.py`` write their results through
:func:`write_results`, so that each file names the command that made it, the commit (and whether
the tree held uncommitted changes), the date, the machine (CPU model, cores, the instruction sets
that decide the speed of int8 and bf16 inference) and the versions of the libraries that ran.

* ``.json`` results get a top-level ``"provenance"`` key (a payload that is not a dict, such as a
  list of cells, is wrapped as ``{"provenance": ..., "results": payload}``).
* ``.md`` / ``.txt`` results open with a header block: one machine-readable HTML comment holding
  the provenance as JSON, then one line a reader sees.

:func:`read_provenance` gives the dict back from either kind of file (``None`` when a file has
none), which is what the docs-figure test uses to check a cited file says where it came from.

Examples
--------
>>> p = provenance(["--quick"])
>>> sorted(k for k in p if k in ("command", "commit", "dirty", "date", "machine", "versions"))
['command', 'commit', 'date', 'dirty', 'machine', 'versions']
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import os
import platform
import re
import shlex
import subprocess
import sys
from importlib import metadata
from importlib.util import find_spec
from pathlib import Path

from hbis_torch.io_utils import atomic_write_text

__all__ = ["provenance", "write_results", "read_provenance", "older_provenance", "record_printed", "run_recorded", "machine", "REPO"]

#: The repository (or installed tree) holding this package.
REPO = Path(__file__).resolve().parents[1]

#: /proc/cpuinfo flags recorded, in this order: what int8 (VNNI, AMX-INT8) and bf16 (AVX512-BF16,
#: AMX-BF16) inference run on, and the vector widths beneath them.
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_int8", "amx_bf16")

#: Libraries whose versions are recorded when installed.
PACKAGES = ("torch", "numpy", "onnxruntime", "openvino", "kornia")

_MARK = "<!-- provenance: "


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _cpuinfo() -> dict:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    info = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key in ("model name", "flags") and key not in info:
            info[key] = value.strip()
    return info


def machine() -> dict:
    """The machine a result was measured on.

    Returns
    -------
    dict
        ``cpu`` (model name), ``cores`` (logical CPUs in the machine), ``cores_usable`` (those
        this process may run on), ``flags`` (each of :data:`CPU_FLAGS` -> bool; empty where
        /proc/cpuinfo is missing) and ``platform``. The host name is not recorded: it says
        nothing about speed and may be private.
    """
    info = _cpuinfo()
    have = set(info.get("flags", "").split())
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    return {
        "cpu": info.get("model name") or platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "cores_usable": usable,
        "flags": {f: f in have for f in CPU_FLAGS} if have else {},
        "platform": platform.platform(),
    }


def _versions() -> dict:
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        if find_spec(name) is None:
            continue
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            module = sys.modules.get(name)
            versions[name] = getattr(module, "__version__", "unknown")
    return versions


def _command(argv) -> str:
    prog = sys.argv[0] if sys.argv and sys.argv[0] else "python"
    try:
        prog = str(Path(prog).resolve().relative_to(REPO))
    except ValueError:
        pass
    args = sys.argv[1:] if argv is None else [str(a) for a in argv]
    head = ["python", prog] if prog.endswith(".py") else [Path(prog).name]
    return shlex.join(head + args)


def provenance(argv=None) -> dict:
    """Where a result is being made: command, commit, date, machine, library versions.

    Parameters
    ----------
    argv : list of str, optional
        The arguments the benchmark parsed (without the program); ``sys.argv[1:]`` by default.

    Returns
    -------
    dict
        ``command`` (str, shell-quoted, the script relative to the repository), ``commit``
        (``git rev-parse HEAD`` or ``"unknown"``), ``dirty`` (bool, tracked files changed since
        that commit; ``None`` when unknown), ``date`` (ISO 8601, UTC, seconds), ``machine``
        (:func:`machine`) and ``versions`` (python and each of :data:`PACKAGES` installed).
    """
    commit = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {
        "command": _command(argv),
        "commit": commit or "unknown",
        "dirty": None if status is None else bool(status),
        "date": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        "machine": machine(),
        "versions": _versions(),
    }


def older_provenance(command: str, path=None, note: str = "") -> dict:
    """Provenance for a result recorded before this module: what is known, and what is not.

    Parameters
    ----------
    command : str
        The command that makes the file (from the benchmark's docstring or the file itself).
    path : path-like, optional
        The results file; the commit that last changed it in git gives ``committed_in`` and
        ``committed_on`` (the result is at least that old).
    note : str
        Anything else known (a machine named in the file's text, a load average).
    """
    record = {"recorded_before_provenance": True, "command": command, "commit": "unknown",
              "dirty": None, "date": "unknown", "machine": "unknown"}
    if path is not None:
        log = _git("log", "-1", "--format=%H %cI", "--", str(Path(path).resolve().relative_to(REPO)))
        if log:
            sha, date = log.split()
            record["committed_in"], record["committed_on"] = sha, date
    if note:
        record["note"] = note
    return record


def _header(prov: dict) -> str:
    if prov.get("recorded_before_provenance"):
        where = f", committed in {prov['committed_in'][:10]} on {prov['committed_on'][:10]}" if "committed_in" in prov else ""
        line = (f"_Recorded before provenance was kept: command `{prov['command']}`, commit, date and "
                f"machine unknown{where}._")
    else:
        m = prov["machine"]
        flags = " ".join(f for f, on in m.get("flags", {}).items() if on) or "none recorded"
        dirty = {True: " (uncommitted changes)", False: "", None: " (tree state unknown)"}[prov["dirty"]]
        versions = ", ".join(f"{k} {v}" for k, v in prov["versions"].items())
        line = (f"_Made by `{prov['command']}` at commit {prov['commit'][:10]}{dirty}, {prov['date']}, "
                f"on {m['cpu']} ({m['cores_usable']} of {m['cores']} cores; {flags}); {versions}._")
    # ">" only ever sits inside JSON strings: escaped, no value can close the HTML comment early.
    return _MARK + json.dumps(prov, sort_keys=True).replace(">", "\\u003e") + " -->\n" + line + "\n\n"


def _strip_header(text: str) -> str:
    if text.startswith(_MARK):
        first, _, rest = text.partition("\n")
        second, _, rest = rest.partition("\n")
        return rest[1:] if rest.startswith("\n") else rest
    return text


def write_results(path, payload, argv=None, prov: dict | None = None) -> dict:
    """Write a results file atomically, with its provenance.

    Parameters
    ----------
    path : path-like
        ``.json``, ``.md`` or ``.txt`` (any other suffix is written as text with the header).
    payload : dict, list or str
        For ``.json`` the data (a dict gets a ``"provenance"`` key first; anything else is
        wrapped as ``{"provenance": ..., "results": payload}``). For text files a str, or a dict
        whose ``"text"`` item is written (a dict without one is written as indented JSON).
    argv : list of str, optional
        Passed to :func:`provenance`.
    prov : dict, optional
        Provenance to record instead of a fresh one (:func:`older_provenance` for old results).

    Returns
    -------
    dict
        The provenance recorded.
    """
    path = Path(path)
    prov = provenance(argv) if prov is None else prov
    if path.suffix == ".json":
        if isinstance(payload, dict):
            body = {"provenance": prov, **{k: v for k, v in payload.items() if k != "provenance"}}
        else:
            body = {"provenance": prov, "results": payload}
        atomic_write_text(path, json.dumps(body, indent=1, default=str) + "\n")
    else:
        if isinstance(payload, dict):
            payload = payload["text"] if "text" in payload else json.dumps(payload, indent=1, default=str) + "\n"
        atomic_write_text(path, _header(prov) + _strip_header(str(payload)))
    return prov


def read_provenance(path) -> dict | None:
    """The provenance a results file records, or ``None`` where it has none.

    Parameters
    ----------
    path : path-like
        A file written by :func:`write_results` (``.json`` with a ``"provenance"`` key, or text
        opening with the header block).
    """
    path = Path(path)
    text = path.read_text(errors="replace")
    if path.suffix == ".json":
        try:
            data = json.loads(text)
        except ValueError:
            return None
        return data.get("provenance") if isinstance(data, dict) else None
    if not text.startswith(_MARK):
        return None
    first = text.partition("\n")[0]
    match = re.fullmatch(re.escape(_MARK) + r"(.*) -->", first)
    return json.loads(match.group(1)) if match else None


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, text):
        for stream in self.streams:
            stream.write(text)
        return len(text)

    def flush(self):
        for stream in self.streams:
            stream.flush()


def run_recorded(prog: str, measure, args, argv=None) -> int:
    """A benchmark's ``main`` after its arguments are parsed: ``args.out`` checked as every output
    is (:func:`~hbis_torch.io_utils.check_output_path`: one line, exit 2, before any work), then
    ``measure(args)`` with what it prints recorded to ``args.out`` (:func:`record_printed`);
    ``measure``'s return value is the exit code."""
    from hbis_torch.errors import HbisInputError
    from hbis_torch.io_utils import check_output_path

    if args.out is not None:
        try:
            check_output_path(args.out, "--out")
        except HbisInputError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 2
    with record_printed(args.out, argv):
        return measure(args)


@contextlib.contextmanager
def record_printed(path, argv=None):
    """Print as usual and, when the block ends without an error, write what was printed to ``path``.

    For benchmarks whose result is the text they print: ``with record_printed(args.out, argv):``.
    ``path`` None records nothing. A ``.json`` path gets ``{"provenance": ..., "printed": text}``;
    any other the text under the provenance header (:func:`write_results`).
    """
    if path is None:
        yield
        return
    kept = io.StringIO()
    with contextlib.redirect_stdout(_Tee(sys.stdout, kept)):
        yield
    text = kept.getvalue()
    write_results(path, {"printed": text} if Path(path).suffix == ".json" else text, argv=argv)

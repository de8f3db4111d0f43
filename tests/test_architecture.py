"""The architecture rules of docs/architecture.md (docs/design.md, section 5), checked on the whole repository.

Two kinds of check:

* at run time, in fresh interpreters: each ``hbis`` command imports only what it needs (its
  ``--help`` loads no pyserial, GRBL simulator, matplotlib, onnxruntime, OpenCV, SciPy or
  Kornia), and importing a module that draws figures leaves matplotlib's backend alone;
* statically, with :mod:`ast`, over every ``.py`` file of the package and the scripts: no import
  cycle between modules or between subpackages (imports inside functions count: they only
  postpone the cycle), no ``sys.path`` edits, no ``matplotlib.use``, no function over 120 lines.
"""

from __future__ import annotations

import ast
import functools
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

import hbis_torch
from hbis_torch.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "hbis_torch"
#: The folders whose code the static rules cover.
CODE_FOLDERS = ("hbis_torch", "training", "export", "benchmarks", "examples")
MAX_FUNCTION_LINES = 120

#: Modules no ``--help`` may load: each belongs to the commands that run, not to their parsers.
HEAVY_MODULES = ("serial", "hbis_torch.hardware.simulator", "matplotlib", "onnxruntime", "cv2", "scipy", "kornia")

#: The modules that draw with matplotlib.
FIGURE_MODULES = ("hbis_torch.figures.design_figures", "hbis_torch.figures.scan_figures",
                  "hbis_torch.system.report.plots")


# --- run time -------------------------------------------------------------------------------

def _python(code: str, **env) -> str:
    """Run ``code`` in a fresh interpreter that imports this checkout's hbis_torch; its stdout.
    An environment variable given as None is removed."""
    checkout = str(Path(hbis_torch.__file__).resolve().parents[1])
    environ = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (checkout, os.environ.get("PYTHONPATH")) if p)}
    environ.update(env)
    environ = {key: value for key, value in environ.items() if value is not None}
    done = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def _modules_after(argv: list[str], watched) -> list[str]:
    """Which of ``watched`` are imported once ``hbis ARGV`` has run (in a fresh interpreter)."""
    code = ("import contextlib, io, sys\n"
            "from hbis_torch.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n"
            f"        main({argv!r})\n"
            "    except SystemExit:\n"
            "        pass\n"
            f"print(' '.join(m for m in {tuple(watched)!r} if m in sys.modules))\n")
    return _python(code).split()


@pytest.mark.parametrize("argv", [["--version"], ["--help"]] + [[name, "--help"] for name in COMMANDS],
                         ids=" ".join)
def test_help_imports_no_heavy_module(argv):
    assert _modules_after(argv, HEAVY_MODULES) == []


@pytest.mark.parametrize("argv", [["--version"], ["design", "--help"]], ids=" ".join)
def test_light_commands_start_without_numpy_or_torch(argv):
    # These build the parser of every command that has no SUMMARY line: none of them may need
    # NumPy or torch to do so.
    assert _modules_after(argv, ("numpy", "torch")) == []


def test_figure_modules_leave_the_matplotlib_backend_alone():
    # A backend chosen beforehand (svg: no display needed, and not the Agg a module might force)
    # must still be the backend once the figure modules are imported, and pyplot stays unloaded.
    code = ("import sys\n"
            "import matplotlib\n"
            "matplotlib.use('svg')\n"
            "before = matplotlib.get_backend()\n"
            + "".join(f"import {module}\n" for module in FIGURE_MODULES)
            + "print(before, matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)\n")
    before, after, pyplot = _python(code, MPLBACKEND=None).split()
    assert (after, pyplot) == (before, "False")


# --- static checks: helpers -----------------------------------------------------------------

def _python_files(folders=CODE_FOLDERS) -> list[Path]:
    return sorted(path for folder in folders for path in (ROOT / folder).rglob("*.py"))


@functools.cache
def _parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _where(path: Path, node: ast.AST) -> str:
    return f"{path.relative_to(ROOT)}:{node.lineno}"


def _package_modules() -> dict[str, Path]:
    """Every module of hbis_torch by dotted name (a package by its ``__init__.py``)."""
    modules = {}
    for path in _python_files([PACKAGE]):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _imported_modules(node: ast.AST, importer: str, is_package: bool, modules) -> list[str]:
    """The modules of ``modules`` an import statement loads by name: ``import a.b`` loads
    ``a.b``; ``from a.b import c`` loads ``a.b.c`` where that is a module, else ``a.b``.
    (The parent packages it runs as well are left out: every module would depend on them.)"""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:  # relative: counted from the importer's package
            package = importer if is_package else importer.rpartition(".")[0]
            anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            base = f"{anchor}.{base}" if base else anchor
        names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
    else:
        return []
    return [name for name in names if name in modules]


def _import_graph() -> dict[str, dict[str, list[str]]]:
    """``graph[a][b]``: where module ``a`` of hbis_torch imports module ``b``, anywhere in it
    (in functions too), as ``path:line``."""
    modules = _package_modules()
    graph: dict[str, dict[str, list[str]]] = {name: defaultdict(list) for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(_parse(path)):
            for target in _imported_modules(node, name, is_package, modules):
                if target != name:
                    graph[name][target].append(_where(path, node))
    return graph


def _subpackage(module: str, subpackages: set[str]) -> str | None:
    """The innermost subpackage of hbis_torch that ``module`` belongs to (None for the package's
    own top-level modules): ``hbis_torch.reconstruct.classical.sr`` belongs to
    ``hbis_torch.reconstruct.classical``, ``hbis_torch.reconstruct.registry`` to
    ``hbis_torch.reconstruct``."""
    if module in subpackages:
        return module
    parent = module.rpartition(".")[0]
    return parent if parent in subpackages else None


def _subpackage_graph() -> dict[str, dict[str, list[str]]]:
    """The import graph with each subpackage of hbis_torch as one node, nested ones included (a
    package and its own subpackage are two nodes: the methods under ``reconstruct`` may use the
    layer's shared modules, which then never import them)."""
    subpackages = {".".join(path.parent.relative_to(ROOT).parts)
                   for path in (ROOT / PACKAGE).rglob("__init__.py") if path.parent != ROOT / PACKAGE}
    graph: dict[str, dict[str, list[str]]] = {name: defaultdict(list) for name in subpackages}
    for module, targets in _import_graph().items():
        source = _subpackage(module, subpackages)
        for target, places in targets.items():
            destination = _subpackage(target, subpackages)
            if source and destination and source != destination:
                graph[source][destination].extend(places)
    return graph


def _reachable(graph, start: str) -> set[str]:
    """The nodes reached from ``start`` over one edge or more (``start`` itself only through a
    cycle)."""
    seen: set[str] = set()
    todo = list(graph[start])
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo.extend(graph[node])
    return seen


def _cycles(graph) -> list[list[str]]:
    """The groups of nodes that reach one another (strongly connected components of more than
    one node, or of one that imports itself), each sorted."""
    reach = {node: _reachable(graph, node) for node in graph}
    groups = {frozenset(other for other in reach[node] if node in reach[other]) for node in graph}
    return sorted(sorted(group) for group in groups if group)


def _describe(graph, cycles) -> str:
    """Each cycle with the imports that close it, for the failure message."""
    lines = []
    for group in cycles:
        lines.append("cycle: " + ", ".join(group))
        for source in group:
            for target in sorted(set(graph[source]) & set(group)):
                lines.append(f"    {source} -> {target}: " + ", ".join(sorted(set(graph[source][target]))))
    return "\n".join(lines)


def _functions(tree: ast.Module):
    return (node for node in ast.walk(tree) if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)))


def _is_sys_path(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "path"
            and isinstance(node.value, ast.Name) and node.value.id == "sys")


def _edits_sys_path(node: ast.AST) -> bool:
    """A call of a method of ``sys.path`` (insert, append, ...), or ``sys.path`` (or an item of
    it) assigned, augmented or deleted."""
    if isinstance(node, ast.Call):
        return isinstance(node.func, ast.Attribute) and _is_sys_path(node.func.value)
    if isinstance(node, ast.Assign):
        targets = node.targets
    elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
        targets = [node.target]
    elif isinstance(node, ast.Delete):
        targets = node.targets
    else:
        return False
    return any(_is_sys_path(t.value if isinstance(t, ast.Subscript) else t) for t in targets)


def _calls_matplotlib_use(tree: ast.Module) -> list[ast.Call]:
    """Calls of ``matplotlib.use``, under whatever name the file imports it."""
    modules, functions = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {alias.asname or alias.name for alias in node.names if alias.name == "matplotlib"}
        elif isinstance(node, ast.ImportFrom) and node.module == "matplotlib":
            functions |= {alias.asname or alias.name for alias in node.names if alias.name == "use"}
    calls = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if ((isinstance(func, ast.Attribute) and func.attr == "use" and isinstance(func.value, ast.Name)
             and func.value.id in modules) or (isinstance(func, ast.Name) and func.id in functions)):
            calls.append(node)
    return calls


# --- static checks --------------------------------------------------------------------------

def test_the_static_checks_see_the_code():
    # Guards the checks below against passing on nothing (a wrong root, a renamed folder).
    graph = _import_graph()
    assert len(graph) > 50 and "hbis_torch.cli.cmd_motors" in graph
    assert "hbis_torch.hardware.simulator" in graph["hbis_torch.cli.cmd_motors"]  # an import in a function
    assert {f"hbis_torch.{name}" for name in ("capture", "cli", "hardware", "simulate", "reconstruct.classical",
                                              "system.array")} <= set(_subpackage_graph())
    assert _cycles({"a": {"b": []}, "b": {"a": []}, "c": {"a": []}}) == [["a", "b"]]


def test_no_import_cycle_between_modules():
    graph = _import_graph()
    cycles = _cycles(graph)
    assert not cycles, _describe(graph, cycles)


def test_no_import_cycle_between_subpackages():
    graph = _subpackage_graph()
    cycles = _cycles(graph)
    assert not cycles, _describe(graph, cycles)


def _top_level_graph() -> dict[str, dict[str, list[str]]]:
    """The import graph with each top-level subpackage of hbis_torch (its nested ones inside it)
    as one node: ``hbis_torch.reconstruct.learned.adapt`` counts as ``hbis_torch.reconstruct``."""
    graph: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    packages = {f"{PACKAGE}.{path.parent.name}" for path in (ROOT / PACKAGE).glob("*/__init__.py")}

    def top(module: str) -> str | None:
        name = ".".join(module.split(".")[:2])
        return name if name in packages else None

    for module, targets in _import_graph().items():
        for target, places in targets.items():
            source, destination = top(module), top(target)
            if source and destination and source != destination:
                graph[source][destination].extend(places)
    for name in packages:
        graph[name]  # every subpackage is a node, importing or not
    return graph


def test_no_import_cycle_between_top_level_subpackages():
    # Counting nested subpackages as part of their top-level one: validate may use reconstruct,
    # so nothing under reconstruct may use validate (the forward model they share lives below both).
    graph = _top_level_graph()
    assert {"hbis_torch.reconstruct", "hbis_torch.validate", "hbis_torch.simulate"} <= set(graph)
    cycles = _cycles(graph)
    assert not cycles, _describe(graph, cycles)


def test_no_sys_path_edits():
    edits = [_where(path, node) for path in _python_files()
             for node in ast.walk(_parse(path)) if _edits_sys_path(node)]
    assert not edits, "sys.path edited at " + ", ".join(edits)


def test_no_long_functions():
    long = [f"{_where(path, node)} {node.name}() {node.end_lineno - node.lineno + 1} lines"
            for path in _python_files() for node in _functions(_parse(path))
            if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: " + ", ".join(long)


def test_no_matplotlib_backend_switch():
    calls = [_where(path, call) for path in _python_files() for call in _calls_matplotlib_use(_parse(path))]
    assert not calls, "matplotlib.use called (draw on matplotlib.figure.Figure instead) at " + ", ".join(calls)


def test_the_learned_method_at_run_time_imports_nothing_of_its_build_side():
    # Running a model (hbis reconstruct --method learned, the registry's raw-Bayer path too)
    # reaches neither the network in torch nor the training pipeline, even inside functions.
    graph = _import_graph()
    starts = ("hbis_torch.cli.cmd_reconstruct", "hbis_torch.reconstruct.registry",
              "hbis_torch.reconstruct.learned.method")
    reached = set().union(*(_reachable(graph, start) for start in starts))
    assert "hbis_torch.reconstruct.learned.runtime" in reached
    assert sorted(m for m in reached if m.startswith("hbis_torch.training")) == []


#: What a learned reconstruction does not use: every one of these was once imported on its path,
#: and each costs start-up (scipy.interpolate alone about half of ``import torch``).
NOT_ON_THE_RECONSTRUCT_PATH = ("scipy", "matplotlib", "cv2", "skimage", "onnx", "hbis_torch.training",
                               "hbis_torch.simulate", "hbis_torch.system")


def test_reconstruct_imports_only_what_it_uses(tmp_path):
    from test_learned_cli import simulated_stack_file

    stack, _ = simulated_stack_file(tmp_path, 2, size=24)
    argv = ["reconstruct", str(stack), "--method", "learned", "--out", str(tmp_path / "sr.tif")]
    assert _modules_after(argv, NOT_ON_THE_RECONSTRUCT_PATH) == []
    assert (tmp_path / "sr.tif").is_file()  # it did run

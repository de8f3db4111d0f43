"""The docstrings' Examples sections run as doctests (part of the README's test command).

Every module of the package with examples runs them, with NORMALIZE_WHITESPACE and ELLIPSIS; a
module in :data:`REQUIRED` without examples fails, so that the main public functions keep theirs.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

import hbis_torch

#: Modules whose public functions must show examples; any other module's examples run too.
REQUIRED = {
    "hbis_torch.checks",
    "hbis_torch.config",
    "hbis_torch.design",
    "hbis_torch.metrics",
    "hbis_torch.optics.pixels",
    "hbis_torch.optics.risley",
    "hbis_torch.reconstruct.registry",
    "hbis_torch.scan.plan",
    "hbis_torch.stack_io",
}


def _modules_with_examples() -> list[str]:
    root = Path(hbis_torch.__file__).parent
    names = []
    for path in sorted(root.rglob("*.py")):
        if ">>> " in path.read_text(encoding="utf-8"):
            parts = path.relative_to(root.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = sorted(set(_modules_with_examples()) | REQUIRED)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS,
                             verbose=False, report=True)
    assert result.attempted > 0 or name not in REQUIRED, f"{name} has no docstring examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"

"""The docstrings' Examples sections run as doctests (part of the README's test command).

Each listed module's examples must pass as written, with NORMALIZE_WHITESPACE and ELLIPSIS; a
module listed here that has no examples fails too, so that the list stays honest.
"""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "hbis_torch.checks",
    "hbis_torch.config",
    "hbis_torch.design",
    "hbis_torch.metrics",
    "hbis_torch.optics.pixels",
    "hbis_torch.optics.risley",
    "hbis_torch.scan.plan",
    "hbis_torch.stack_io",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS,
                             verbose=False, report=True)
    assert result.attempted > 0, f"{name} has no docstring examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"

"""Names a package exports but imports only on first use (PEP 562), so that importing the package
stays cheap: ``hbis --help`` and the run-time paths load only the modules they use."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, homes: dict[str, str], eager: dict | None = None):
    """The ``__getattr__`` and ``__dir__`` of a package whose names live in submodules.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    homes : dict
        Exported name -> the submodule (relative to ``package``) that defines it.
    eager : dict, optional
        The package's own globals, listed by ``__dir__`` beside the lazy names.

    Returns
    -------
    (callable, callable)
        ``__getattr__(name)``, importing ``package.homes[name]`` on first use (AttributeError for
        any other name), and ``__dir__()``.

    Examples
    --------
    >>> getattr_, dir_ = lazy_exports("json", {"JSONEncoder": "encoder"})
    >>> import json.encoder
    >>> getattr_("JSONEncoder") is json.encoder.JSONEncoder
    True
    >>> "JSONEncoder" in dir_()
    True
    """

    def __getattr__(name: str):
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)

    def __dir__() -> list[str]:
        return sorted(set(eager or ()) | set(homes))

    return __getattr__, __dir__

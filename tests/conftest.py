"""Shared fixtures."""

import dataclasses
import importlib.util
from pathlib import Path

import pytest
import torch


@pytest.fixture(scope="module")
def one_thread():
    """Run a module on one torch thread, then restore the count. Its tensors are small: on cores
    shared with other jobs, extra threads only wait on each other (up to 100x slower seen here)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def distrust_frame(monkeypatch):
    """``distrust_frame(k)``: from then on the registration returns its real result, except that
    it refuses to trust frame k."""
    import hbis_torch.registration as registration

    real = registration.register_stack

    def distrust(frame: int) -> None:
        def register(*args, **kw):
            reg = real(*args, **kw)
            ok = reg.ok.clone()
            ok[frame] = False
            return dataclasses.replace(reg, ok=ok)

        monkeypatch.setattr(registration, "register_stack", register)

    return distrust


@pytest.fixture(scope="session")
def load_script():
    """A loader of the repository's scripts (training/, benchmarks/) as modules, by their path from
    the repository's root: ``load_script("training/soup.py")``."""
    root = Path(__file__).resolve().parents[1]

    def load(relative: str):
        path = root / relative
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load

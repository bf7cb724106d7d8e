"""torchdoct's torch-free helper modules, reachable without importing torch.

``import torchdoct._files`` would run ``torchdoct/__init__.py``, which imports torch; the classify
path must not. ``torchdoct/_files.py`` (``check_out``, ``atomic_write``, ``shipped_files``) and
``torchdoct/conventions.py`` (resolution ↔ PSF sigma) and ``torchdoct/sim/signature.py`` (signature
feature names) import only the standard library, so when
torchdoct is not imported yet they are loaded from their files, without their package.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

__all__ = ["check_out", "atomic_write", "shipped_files", "conventions", "signature", "threads"]


def _standalone(name: str) -> ModuleType:
    """``torchdoct.<name>`` if torchdoct is imported, else the file loaded on its own."""
    full = f"torchdoct.{name}"  # a dotted name: a module of a subpackage (sim.signature)
    if full in sys.modules:
        return sys.modules[full]
    alias = f"classifier._torchdoct_{name.replace('.', '_')}"
    cached = sys.modules.get(alias)
    if cached is not None:
        return cached
    spec = importlib.util.find_spec("torchdoct")  # locates the package without executing it
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("torchdoct is not installed; install the project (pip install .)")
    loc = next(iter(spec.submodule_search_locations))
    file_spec = importlib.util.spec_from_file_location(alias, f"{loc}/{name.replace('.', '/')}.py")
    module = importlib.util.module_from_spec(file_spec)
    file_spec.loader.exec_module(module)
    sys.modules[alias] = module
    return module


def conventions() -> ModuleType:
    """:mod:`torchdoct.conventions` (the only place resolutions become PSF sigmas)."""
    return _standalone("conventions")


def signature() -> ModuleType:
    """:mod:`torchdoct.sim.signature` (names and units of the signature features; no torch at import)."""
    return _standalone("sim.signature")


def threads() -> ModuleType:
    """:mod:`torchdoct.threads` (the threading policy; torch only inside the functions that set it)."""
    return _standalone("threads")


def interrupt() -> ModuleType:
    """:mod:`torchdoct.interrupt` (Ctrl-C, SIGTERM and closed pipes at the entry points; standard library)."""
    return _standalone("interrupt")


def check_out(path, force, suffix, what="--out"):
    """:func:`torchdoct._files.check_out`."""
    return _standalone("_files").check_out(path, force, suffix, what)


def atomic_write(path, write):
    """:func:`torchdoct._files.atomic_write`."""
    return _standalone("_files").atomic_write(path, write)


def shipped_files(package, folder, suffix=".toml"):
    """:func:`torchdoct._files.shipped_files`."""
    return _standalone("_files").shipped_files(package, folder, suffix)

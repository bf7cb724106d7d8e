"""torchdoct: batched PyTorch simulation of dynamic OCT (DOCT) signals and their metrics.

Units and resolution conventions: :mod:`torchdoct.conventions`.

Importing ``torchdoct`` is light: the public names below and the subpackages load on first use
(``torchdoct.simulate``, ``torchdoct.sim``), so the torch-free modules (:mod:`torchdoct.conventions`,
:mod:`torchdoct.optics`, :mod:`torchdoct.measured.io`, :mod:`torchdoct.runtime.threads`, ...) can be imported
without torch.
"""

from __future__ import annotations

import importlib
from importlib import metadata as _metadata

try:  # the one version is the distribution's (pyproject.toml)
    __version__ = _metadata.version("torchdoct")
except _metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
del _metadata

#: Public name → the module that owns it (imported on first access).
_LAZY = {
    **dict.fromkeys(
        (
            "Analysis",
            "Diffusion",
            "Flow",
            "Noise",
            "OCTSystem",
            "Population",
            "Protocol",
            "RandomBallistic",
            "Scene",
            "SceneError",
            "SimulationSettings",
            "load_scene",
            "scene_from_dict",
        ),
        ".sim.config",
    ),
    **dict.fromkeys(("complex_variance", "lag_correlations", "liv", "ocds", "to_db"), ".sim.metrics"),
    **dict.fromkeys(("Phantom", "load_phantom", "phantom_from_dict"), ".image.phantom"),
    **dict.fromkeys(("Plan", "make_plan"), ".sim.plan"),
    **dict.fromkeys(("RenderResult", "render"), ".image.render"),
    "shipped_scenes": ".sim.scenes",
    **dict.fromkeys(("SimulationResult", "simulate"), ".sim.simulate"),
}
#: Subpackages and modules reachable as attributes (``torchdoct.sim``) without an explicit import.
_SUBMODULES = ("sim", "image", "measured", "study", "bench", "cli", "runtime", "conventions", "optics", "figures")

__all__ = [
    "Analysis",
    "Diffusion",
    "Flow",
    "Noise",
    "OCTSystem",
    "Population",
    "Protocol",
    "RandomBallistic",
    "Scene",
    "SceneError",
    "SimulationSettings",
    "load_scene",
    "scene_from_dict",
    "complex_variance",
    "lag_correlations",
    "liv",
    "ocds",
    "to_db",
    "Phantom",
    "load_phantom",
    "phantom_from_dict",
    "RenderResult",
    "render",
    "Plan",
    "make_plan",
    "shipped_scenes",
    "SimulationResult",
    "simulate",
    "__version__",
]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value  # later lookups skip this function
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public API only: the names of ``__all__`` and the stage packages (not this module's helpers)."""
    return sorted(set(__all__) | set(_SUBMODULES))

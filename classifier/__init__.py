"""Motion-type classifier for DOCT maps: diffusion, random-ballistic motion, flow or indeterminate.

The reference paper (Fujimura et al., §3.3, §4) finds that LIV and OCDS change with wavelength and
resolution differently for each motion type; this package learns that from simulated features
(:mod:`classifier.dataset`, via :func:`torchdoct.simulate`), ships the model as ONNX and classifies
every pixel of the maps written by ``torchdoct maps`` (``doct-classify``).

Modules: :mod:`~classifier.features` (feature specs), the training data (:mod:`~classifier.prior`,
:mod:`~classifier.truth`, :mod:`~classifier.simulation`, :mod:`~classifier.dataset`), :mod:`~classifier.model` (the network), :mod:`~classifier.train` (recipe),
:mod:`~classifier.export` (ONNX), :mod:`~classifier.infer` (classify maps; numpy + onnxruntime
only: :mod:`~classifier.runtime`, :mod:`~classifier.matching`, :mod:`~classifier.pooling`,
:mod:`~classifier.outputs`), :mod:`~classifier.rule` (the ``indeterminate`` outcome), :mod:`~classifier.report`.

Importing ``classifier`` does not import torch: the torch-based names (``train``, ``TrainConfig``,
``make_dataset``, ``Prior``, ``export_onnx``) load on first use.
"""

from __future__ import annotations

from torchdoct import __version__  # one distribution, one version (pyproject.toml)

from .features import Configuration, FeatureSpec, load_spec, shipped_specs
from .infer import classify_maps, load_model, read_maps, shipped_models, write_classification
from .rule import INDETERMINATE, apply_rule

_LAZY = {
    "train": ("train", "train"),
    "TrainConfig": ("train", "TrainConfig"),
    "TrainResult": ("train", "TrainResult"),
    "make_dataset": ("dataset", "make_dataset"),
    "Prior": ("prior", "Prior"),
    "export_onnx": ("export", "export_onnx"),
}

__all__ = [
    "__version__",
    "Configuration",
    "FeatureSpec",
    "load_spec",
    "shipped_specs",
    "classify_maps",
    "load_model",
    "read_maps",
    "shipped_models",
    "write_classification",
    "INDETERMINATE",
    "apply_rule",
    "train",
    "TrainConfig",
    "TrainResult",
    "make_dataset",
    "Prior",
    "export_onnx",
]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        mod, attr = _LAZY[name]
        return getattr(importlib.import_module(f"{__name__}.{mod}"), attr)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public API only: the names of ``__all__`` (not this module's helpers or loaded submodules)."""
    return sorted(__all__)

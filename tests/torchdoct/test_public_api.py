"""The public API: what the README documents stays importable under the same names."""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

import pytest

import classifier
import torchdoct as td

TOP_LEVEL = [
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
CLASSIFIER = [
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
#: Functions the README and the docs name by their module path.
DOCUMENTED = [
    "torchdoct.runtime.threads:set_default_threads",
    "torchdoct.measured.resolution:reduce_resolution",
    "torchdoct.measured.maps:compute_maps",
    "torchdoct.study.sweep:run_sweeps",
    "torchdoct.study:run_study",
    "torchdoct.study:load_study",
    "torchdoct.figures:show_bscan",
    "torchdoct.sim.metrics:summarize",
    "torchdoct.measured.io:read_sequence",
]


def test_top_level_names():
    assert set(TOP_LEVEL) <= set(td.__all__)
    for name in TOP_LEVEL:
        assert getattr(td, name) is not None, name
    assert set(CLASSIFIER) <= set(classifier.__all__)
    for name in CLASSIFIER:
        assert getattr(classifier, name) is not None, name


@pytest.mark.parametrize("ref", DOCUMENTED)
def test_documented_module_paths(ref):
    module, name = ref.split(":")
    assert callable(getattr(importlib.import_module(module), name))


def test_console_scripts():
    scripts = {
        e.name: e.value
        for e in entry_points(group="console_scripts")
        if e.name in ("torchdoct", "doct-train", "doct-classify")
    }
    assert scripts == {
        "torchdoct": "torchdoct.cli:main",
        "doct-train": "classifier.cli:train_main",
        "doct-classify": "classifier.cli:classify_main",
    }
    for value in scripts.values():
        module, name = value.split(":")
        assert callable(getattr(importlib.import_module(module), name))

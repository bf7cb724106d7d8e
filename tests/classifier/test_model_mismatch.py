"""An ONNX model whose network does not match its metadata (input width, class count) is refused by name
with the fix, before any pixel runs (before: onnxruntime's InvalidArgument traceback for the width, a
numpy broadcast error naming neither file nor fix for the classes)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _refusal import refused

from classifier.cli import classify_main


def _edited(tmp_path, name, change):
    import onnx

    from classifier.infer import shipped_models

    proto = onnx.load(str(shipped_models()["single-acquisition-bscan"]))
    for prop in proto.metadata_props:
        if prop.key == "torchdoct_classifier":
            meta = json.loads(prop.value)
            change(meta)
            prop.value = json.dumps(meta)
    path = tmp_path / name
    onnx.save(proto, str(path))
    return path


@pytest.mark.parametrize(
    "name, change, words",
    [
        (
            "width.onnx",
            lambda m: m["input"].update(columns=m["input"]["columns"][1:]),
            ("'features'", "6 input columns"),
        ),
        (
            "classes.onnx",
            lambda m: m["output"].update(classes=m["output"]["classes"] + ["extra"]),
            ("'probabilities'", "5 columns"),
        ),
    ],
)
def test_model_whose_network_differs_from_its_metadata_is_refused(tmp_path, capsys, name, change, words):
    from classifier.runtime import load_model

    path = _edited(tmp_path, name, change)
    with pytest.raises(ValueError, match="doct-train"):
        load_model(path)
    from _clf_maps import feature_channels, maps_meta, save_maps

    from classifier.features import load_spec

    spec = load_spec("single-acquisition-bscan")
    data = np.full((spec.n_features + 1, 4, 5), 5.0, np.float32)
    maps = save_maps(tmp_path / "maps.npz", data, maps_meta(spec, feature_channels(spec)))
    refused(
        capsys,
        tmp_path,
        [str(maps), "--model", str(path), "--out", str(tmp_path / "o")],
        name,
        *words,
        run=classify_main,
    )


def test_shipped_models_match_their_metadata():
    from classifier.infer import shipped_models
    from classifier.runtime import load_model

    for name in shipped_models():
        load_model(name)

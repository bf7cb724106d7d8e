"""Silent nonsense refused (issue class 6, the classifier's part): duplicate channel names in a maps
file, a wrongly typed model metadata field; and the default model's fallback note names
the signature channels the maps lack."""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps
from _refusal import refused

from classifier.cli import classify_main
from classifier.features import load_spec


def _maps(tmp_path, channels=None, name="maps.npz"):
    spec = load_spec("single-acquisition")
    rng = np.random.default_rng(0)
    n = spec.n_features
    feats = np.concatenate([rng.uniform(0.0, 12.0, (n // 2, 6, 7)), rng.uniform(0.0, 0.5, (n - n // 2, 6, 7))])
    chans = feature_channels(spec) if channels is None else channels(feature_channels(spec))
    return save_maps(
        tmp_path / name, np.concatenate([feats, np.full((1, 6, 7), 20.0)]).astype(np.float32), maps_meta(spec, chans)
    )


def test_duplicate_channel_names_in_a_maps_file_are_refused(tmp_path, capsys):
    def twice(ch):
        ch = copy.deepcopy(ch)
        ch[1]["name"] = ch[0]["name"]
        return ch

    bad = _maps(tmp_path, twice)
    refused(capsys, tmp_path, [str(bad), "--out", str(tmp_path / "o")], "maps.npz", "more than once", run=classify_main)


HUGE = object()  # an integer of 5000 digits, written into the JSON text (Python's json cannot write it)


@pytest.mark.parametrize(
    "field,value",
    [
        ("rule.min_probability", "0.5"),
        ("pool_pixels_max", 2.5),
        ("rule.kind", 3),
        ("output.classes", "diffusion"),
        ("pool_pixels_max", HUGE),
    ],
)
def test_a_wrongly_typed_model_metadata_field_is_refused_naming_it(tmp_path, field, value):
    onnx = pytest.importorskip("onnx")
    from classifier.runtime import METADATA_KEY, load_model, shipped_models

    model = onnx.load(str(shipped_models()["single-acquisition"]))
    prop = next(p for p in model.metadata_props if p.key == METADATA_KEY)
    meta = json.loads(prop.value)
    block, _, key = field.rpartition(".")
    (meta[block] if block else meta)[key] = "HUGE" if value is HUGE else value
    prop.value = json.dumps(meta).replace('"HUGE"', "1" * 5000)
    path = tmp_path / "edited.onnx"
    onnx.save(model, str(path))
    with pytest.raises(ValueError, match="edited.onnx: metadata field " + re.escape(field) + " must be"):
        load_model(path)


def test_the_fallback_note_names_the_missing_signature_channels():
    from classifier.matching import choose_default_model
    from classifier.runtime import load_model, shipped_models

    spec = load_spec("single-acquisition")
    from torchdoct.measured.mapsfile import Maps

    chans = feature_channels(spec)
    meta = maps_meta(spec, chans)
    meta["signature"] = {"features": [], "intensity_only": False}
    maps = Maps(maps=np.ones((len(chans), 3, 3), np.float32), channels=tuple(c["name"] for c in chans), meta=meta)
    name, note = choose_default_model([maps], shipped_models(), lambda n: load_model(n, threads=1))
    assert note is not None and "missing channel(s): " in note
    sig = load_model(note.split("instead of ")[1].split(":")[0], threads=1)
    first_missing = next(c["name"] for c in sig.columns[:-1] if c["name"] not in maps.channels)
    assert first_missing in note

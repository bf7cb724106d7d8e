"""``python -m research.systems --models DIR``: models trained earlier stand in for training (their reports give
the training time), and a folder without the system's model is refused naming it."""

from __future__ import annotations

import json

import pytest


def test_models_trained_earlier_are_copied_and_used_instead_of_training(tmp_path):
    from research.systems import train

    stored = tmp_path / "models" / "system-fast"
    stored.mkdir(parents=True)
    (stored / "like.onnx").write_bytes(b"not trained here")
    (stored / "like.json").write_text(json.dumps({"training": {"seconds": 12.5}}))
    out = tmp_path / "out"
    model, report = train(out, "system-fast", tmp_path / "absent-maps.npz", False, models=tmp_path / "models")
    assert model == out / "system-fast" / "like.onnx" and model.read_bytes() == b"not trained here"
    assert report == {"training": {"seconds": 12.5}}
    assert (stored / "like.onnx").exists()  # the stored model stays where it was


def test_a_models_folder_without_the_systems_model_is_refused_before_any_training(tmp_path):
    from research.systems import train

    (tmp_path / "models" / "system-1310nm").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"--models .*system-fast/\*\.onnx"):
        train(tmp_path / "out", "system-fast", tmp_path / "absent-maps.npz", False, models=tmp_path / "models")
    assert not (tmp_path / "out" / "system-fast").exists()

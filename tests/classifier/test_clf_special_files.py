"""Special files given to the classifier's commands (issue class 1): a FIFO, a character device or a
directory as the feature spec, the prior, the model or a maps file is refused at once with "is not a
regular file" (exit 2), never "no such file", never blocking on the open."""

from __future__ import annotations

import os

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps
from _refusal import refused
from _special import no_hang  # noqa: F401 (autouse fixture)
from _special import special as _special

from classifier.cli import classify_main, train_main
from classifier.features import load_spec

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")


@pytest.mark.parametrize("kind", ["fifo", "device", "directory"])
@pytest.mark.parametrize("role", ["spec", "prior", "model", "maps"])
def test_a_special_file_given_to_the_classifier_is_refused_at_once(tmp_path, capsys, role, kind):
    spec = load_spec("single-acquisition")
    rng = np.random.default_rng(0)
    n = spec.n_features
    feats = np.concatenate([rng.uniform(0.0, 12.0, (n // 2, 6, 7)), rng.uniform(0.0, 0.5, (n - n // 2, 6, 7))])
    good = save_maps(
        tmp_path / "maps.npz",
        np.concatenate([feats, np.full((1, 6, 7), 20.0)]).astype(np.float32),
        maps_meta(spec, feature_channels(spec)),
    )
    bad = _special(
        tmp_path / {"spec": "bad.toml", "prior": "bad.toml", "model": "bad.onnx", "maps": "bad.npz"}[role], kind
    )
    out = str(tmp_path / "o")
    run, argv = {
        "spec": (train_main, ["--spec", str(bad), "--out", out, "--dry-run"]),
        "prior": (train_main, ["--prior", str(bad), "--out", out, "--dry-run"]),
        "model": (classify_main, [str(good), "--model", str(bad), "--out", out]),
        "maps": (classify_main, [str(bad), "--out", out]),
    }[role]
    line = refused(capsys, tmp_path, argv, "bad", "is not a regular file", run=run)
    assert "no such file" not in line and "not found" not in line

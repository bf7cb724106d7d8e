"""Fixtures shared by the torchdoct tests."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture()
def seq(tmp_path):
    """A small complex B-scan sequence [T, Z, X] with its sidecar."""
    rng = np.random.default_rng(0)
    path = tmp_path / "seq.npy"
    np.save(path, (rng.standard_normal((8, 6, 5)) + 1j * rng.standard_normal((8, 6, 5))).astype(np.complex64))
    path.with_suffix(".json").write_text(
        json.dumps(
            {
                "axes": "TZX",
                "pitch_um": {"z": 2.0, "x": 2.0},
                "frame_times_s": [0.2048 * i for i in range(8)],
                "system": {
                    "name": "s",
                    "wavelength_um": 0.84,
                    "lateral_resolution_um": 4.9,
                    "axial_resolution_um": 3.8,
                    "refractive_index": 1.0,
                },
            }
        )
    )
    return path


@pytest.fixture()
def outdir(tmp_path):
    """``tmp_path`` with an empty ``out/`` folder for a command's outputs."""
    (tmp_path / "out").mkdir()
    return tmp_path


@pytest.fixture()
def default_input_limit(monkeypatch):
    """The readers' default input-size limit: no ``$TORCHDOCT_MAX_INPUT_GB`` and no limit set by the API,
    before and after the test (``torchdoct.measured.guards``)."""
    from torchdoct.measured import guards

    monkeypatch.delenv(guards.MAX_INPUT_ENV, raising=False)
    guards.set_max_input_gb(None)
    yield
    guards.set_max_input_gb(None)

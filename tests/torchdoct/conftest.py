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
    path.with_suffix(".json").write_text(json.dumps({
        "axes": "TZX", "pitch_um": {"z": 2.0, "x": 2.0}, "frame_times_s": [0.2048 * i for i in range(8)],
        "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8,
                   "refractive_index": 1.0}}))
    return path

"""doct-classify picks the model by the maps' geometry and phase correction, and refuses a mismatched one.

B-scan maps (lateral reduction along x only: 18 × 4.9 µm) take the B-scan models, volume maps
(isotropic) the volume ones; bulk-phase-corrected B-scan maps (``torchdoct maps --bulk-phase``) take
the model that also reads |g1|; a model of the other geometry, or a phase model on uncorrected maps,
is refused with the model or the command that fits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from classifier.infer import classify_maps, default_model_for, read_maps


def _sequence(tmp_path, axes: str):
    from torchdoct.measured.io import write_sequence

    rng = np.random.default_rng(5)
    shape = (10, 8) if axes == "TZX" else (3, 8, 8)
    t = 32
    e = np.empty((t, *shape), np.complex64)
    e[0] = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    for i in range(1, t):  # partially decorrelating speckle
        e[i] = 0.9 * e[i - 1] + math.sqrt(1 - 0.81) * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    pitch = {"z": 1.5, "x": 2.0} if axes == "TZX" else {"y": 2.0, "z": 1.5, "x": 2.0}
    return write_sequence(tmp_path / f"seq-{axes}.npz", e, {
        "axes": axes, "pitch_um": pitch, "frame_times_s": [0.2048 * i for i in range(t)],
        "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}})


def _maps(tmp_path, seq, name: str, *extra: str):
    from torchdoct.cli import main as td_main

    out = tmp_path / name
    assert td_main(["maps", str(seq), "--resolution", "original", "--resolution", "axial=14", "--resolution",
                    "lateral=18", "--signature", *extra, "--out", str(out), "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("geometry")
    bscan = _sequence(d, "TZX")
    return {"bscan": _maps(d, bscan, "bscan.npz"),
            "bscan-corrected": _maps(d, bscan, "bscan-bp.npz", "--bulk-phase", "weighted-mean"),
            "volume": _maps(d, _sequence(d, "TYZX"), "volume.npz")}


def test_default_model_follows_geometry_and_phase_correction(maps):
    assert default_model_for([read_maps(maps["bscan"])]) == ("signature-bscan", None)
    assert default_model_for([read_maps(maps["bscan-corrected"])]) == ("signature-bscan-field", None)
    assert default_model_for([read_maps(maps["volume"])]) == ("signature", None)
    assert read_maps(maps["bscan-corrected"]).meta["bulk_phase"]["method"] == "weighted-mean"


def test_a_model_of_the_other_geometry_is_refused_naming_the_right_one(maps):
    with pytest.raises(ValueError, match=r"B-scan maps \(lateral resolution reduced along x only\).*"
                                         r"--model signature-bscan"):
        classify_maps(maps["bscan"], "signature", threads=1, background_db="none")
    with pytest.raises(ValueError, match=r"volume maps \(isotropic\).*--model signature\)"):
        classify_maps(maps["volume"], "signature-bscan", threads=1, background_db="none")


def test_a_phase_model_needs_bulk_phase_corrected_maps(maps):
    with pytest.raises(ValueError, match=r"not bulk-phase corrected.*--bulk-phase"):
        classify_maps(maps["bscan"], "signature-bscan-field", threads=1, background_db="none")
    res = classify_maps(maps["bscan-corrected"], "signature-bscan-field", threads=1, background_db="none")
    assert res.model.spec.name == "signature-bscan-field" and res.info["classified"] == 80

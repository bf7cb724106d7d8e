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

#: [Z, X] of the B-scans and [Y, Z, X] of the volume: 10 × 1.5 µm deep and 10 × 2 µm wide (and long), so
#: every field of view holds the signature's targets (axial=14, lateral=18)
BSCAN, VOLUME = (10, 10), (10, 10, 10)


def _sequence(tmp_path, axes: str):
    from torchdoct.measured.io import write_sequence

    rng = np.random.default_rng(5)
    shape = BSCAN if axes == "TZX" else VOLUME
    t = 32
    e = np.empty((t, *shape), np.complex64)
    e[0] = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    for i in range(1, t):  # partially decorrelating speckle
        e[i] = 0.9 * e[i - 1] + math.sqrt(1 - 0.81) * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    pitch = {"z": 1.5, "x": 2.0} if axes == "TZX" else {"y": 2.0, "z": 1.5, "x": 2.0}
    return write_sequence(
        tmp_path / f"seq-{axes}.npz",
        e,
        {
            "axes": axes,
            "pitch_um": pitch,
            "frame_times_s": [0.2048 * i for i in range(t)],
            "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
        },
    )


def _maps(tmp_path, seq, name: str, *extra: str):
    from torchdoct.cli import main as td_main

    out = tmp_path / name
    assert (
        td_main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                *extra,
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    return out


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("geometry")
    bscan = _sequence(d, "TZX")
    return {
        "bscan": _maps(d, bscan, "bscan.npz"),
        "bscan-corrected": _maps(d, bscan, "bscan-bp.npz", "--bulk-phase", "weighted-mean"),
        "volume": _maps(d, _sequence(d, "TYZX"), "volume.npz"),
    }


def test_default_model_follows_geometry_and_phase_correction(maps):
    assert default_model_for([read_maps(maps["bscan"])]) == ("signature-bscan", None)
    assert default_model_for([read_maps(maps["bscan-corrected"])]) == ("signature-bscan-field", None)
    assert default_model_for([read_maps(maps["volume"])]) == ("signature", None)
    assert read_maps(maps["bscan-corrected"]).meta["bulk_phase"]["method"] == "weighted-mean"


def test_a_model_of_the_other_geometry_is_refused_naming_the_right_one(maps):
    with pytest.raises(
        ValueError,
        match=r"B-scan maps \(lateral resolution reduced along x only\).*"
        r"--model signature-bscan",
    ):
        classify_maps(maps["bscan"], "signature", threads=1, background_db="none")
    with pytest.raises(ValueError, match=r"volume maps \(isotropic\).*--model signature\)"):
        classify_maps(maps["volume"], "signature-bscan", threads=1, background_db="none")


def test_a_phase_model_needs_bulk_phase_corrected_maps(maps):
    with pytest.raises(ValueError, match=r"not bulk-phase corrected.*--bulk-phase"):
        classify_maps(maps["bscan"], "signature-bscan-field", threads=1, background_db="none")
    res = classify_maps(maps["bscan-corrected"], "signature-bscan-field", threads=1, background_db="none")
    assert res.model.spec.name == "signature-bscan-field" and res.info["classified"] == math.prod(BSCAN)


def test_features_outside_their_physical_range_are_masked_and_counted(tmp_path):
    """A feature no real sequence can give (a correlation of 3e38, a negative dB variance) is corrupt input:
    the pixel is masked like a NaN pixel and counted, never given a motion class."""
    from _clf_maps import feature_channels, maps_meta, save_maps

    from classifier.features import load_spec, physical_range

    spec = load_spec("signature")
    chans = feature_channels(spec)
    rng = np.random.default_rng(1)
    data = rng.uniform(0.2, 0.9, size=(len(chans), 6, 7)).astype(np.float32)
    names = [c["name"] for c in chans]
    for i, n in enumerate(names):
        if n.startswith("db_variance"):
            data[i] = rng.uniform(5.0, 30.0, size=(6, 7))
        if n.startswith("lin_contrast"):
            data[i] = rng.uniform(0.5, 1.5, size=(6, 7))
        if n.startswith("mean_db"):
            data[i] = 20.0
    data[names.index("rho_lin_1@original"), 0, 0] = 3e38
    data[names.index("db_variance@axial=14"), 2, 3] = -1.0
    path = save_maps(tmp_path / "corrupt.npz", data, maps_meta(spec, chans))
    res = classify_maps(path, "signature", threads=1, background_db="none")
    assert res.info["out_of_range_pixels"] == 2 and res.info["nan_pixels"] == 0
    assert not res.mask[0, 0] and not res.mask[2, 3] and res.mask.sum() == 6 * 7 - 2
    assert physical_range("rho_lin_3", 32) == (-1.001, 1.001) and physical_range("lin_contrast", 32)[1] > 31

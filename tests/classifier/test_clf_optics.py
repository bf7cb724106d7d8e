"""Channel optics as one value (torchdoct.optics.ChannelOptics) and its one match, as the maps, the specs
and doct-classify use it: tolerance, isotropic default, the y width of B-scan maps reduced along x, the
spec's optional lateral_resolution_y_um, and the classify switch that ignores y for now."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier import matching
from classifier.features import Configuration, load_spec, shipped_specs, spec_from_dict
from classifier.infer import assemble_features, load_model
from torchdoct.measured.mapsfile import Maps, read_maps
from torchdoct.optics import REL_TOL, ChannelOptics

BASE = ChannelOptics(0.84, 4.9, 3.8)


def test_match_tolerance_and_isotropic_default():
    assert REL_TOL == 1e-6
    assert BASE.matches(ChannelOptics(0.84 * (1 + 5e-7), 4.9, 3.8))
    assert not BASE.matches(ChannelOptics(0.84 * (1 + 5e-6), 4.9, 3.8))
    for k in range(3):  # each length on its own breaks the match
        v = [0.84, 4.9, 3.8]
        v[k] *= 1 + 5e-6
        assert not BASE.matches(ChannelOptics(*v))
    assert BASE.matches(ChannelOptics(0.84, 4.9, 3.8, 4.9)) and BASE.isotropic  # None = same as x
    aniso = ChannelOptics(0.84, 18.0, 3.8, 4.9)
    assert not aniso.isotropic and aniso.lateral_y_um == 4.9
    assert not aniso.matches(ChannelOptics(0.84, 18.0, 3.8)) and not ChannelOptics(0.84, 18.0, 3.8).matches(aniso)
    assert aniso.matches(ChannelOptics(0.84, 18.0, 3.8), lateral_y=False)  # x only
    assert aniso.describe() == "840 nm, lateral 18 × 4.9 µm (x × y), axial 3.8 µm"
    assert BASE.describe() == "840 nm, lateral 4.9 µm, axial 3.8 µm"


def _channel(lateral: float) -> dict:
    return {
        "name": f"liv@{lateral}",
        "metric": "liv",
        "unit": "dB^2",
        "resolution": "r",
        "wavelength_um": 0.84,
        "lateral_resolution_um": lateral,
        "axial_resolution_um": 3.8,
    }


@pytest.mark.parametrize("axes,reduced_y", [("X", 4.9), ("YX", None)])
def test_a_channel_reduced_along_x_only_keeps_the_original_width_along_y(tmp_path, axes, reduced_y):
    meta = {
        "channels": [_channel(4.9), _channel(18.0)],
        "axes": "CZX",
        "system": {"lateral_resolution_um": 4.9},
        "reduction": {"lateral_axes": axes},
    }
    path = tmp_path / "m.npz"
    np.savez(
        path,
        maps=np.zeros((2, 3, 3), np.float32),
        channels=np.array(["liv@4.9", "liv@18.0"]),
        meta_json=np.asarray(__import__("json").dumps(meta)),
    )
    m = read_maps(path)
    assert m.optics("liv@4.9") == ChannelOptics(0.84, 4.9, 3.8)  # not reduced: y = x
    assert m.optics(1) == ChannelOptics(0.84, 18.0, 3.8, reduced_y)
    assert m.find("liv", lateral_resolution_um=18.0) == ["liv@18.0"]  # find matches on x
    no_optics = Maps(
        maps=np.zeros((1, 2, 2), np.float32),
        channels=["x"],
        meta={"channels": [{**_channel(4.9), "name": "x", "wavelength_um": None}]},
    )
    assert no_optics.optics(0) is None and no_optics.find("liv") == []


def test_spec_lateral_resolution_y_is_optional_and_leaves_isotropic_specs_unchanged():
    for name in ("single-acquisition", "two-wavelength", "signature", "two-wavelength-signature"):
        spec = load_spec(shipped_specs()[name])
        assert all(c.lateral_resolution_y_um is None and c.optics.isotropic for c in spec.configurations)
        assert all("lateral_resolution_y_um" not in c for c in spec.to_dict()["configuration"])  # cache keys as before
    d = load_spec("single-acquisition").to_dict()
    d["configuration"][2]["lateral_resolution_y_um"] = 4.9
    spec = spec_from_dict(d)
    assert spec.configurations[2].optics == ChannelOptics(0.84, 18.0, 3.8, 4.9)
    assert spec_from_dict(spec.to_dict()) == spec
    with pytest.raises(ValueError, match="lateral_resolution_y_um"):
        Configuration(
            name="o",
            wavelength_um=0.84,
            lateral_resolution_um=4.9,
            axial_resolution_um=3.8,
            lateral_resolution_y_um=-1.0,
        )
    c = spec.configurations[2]
    assert c.matches(ChannelOptics(0.84, 18.0, 3.8, 4.9)) and not c.matches(0.84, 18.0, 3.8)
    assert c.matches(0.84, 18.0, 3.8, lateral_y=False)


def test_doct_classify_refuses_a_model_of_the_other_geometry(tmp_path, monkeypatch):
    """B-scan maps reduced along x only never feed a model trained on isotropic reductions: the error
    names the B-scan model (or its doct-train command); volume maps still match. With the switch off,
    the old behaviour (match on x, a note)."""
    spec = load_spec("single-acquisition")
    chans = feature_channels(spec)
    data = np.random.default_rng(2).uniform(0.1, 1.0, size=(len(chans), 5, 6)).astype(np.float32)
    data[-1] = 20.0
    meta = {**maps_meta(spec, chans), "reduction": {"lateral_axes": "X"}}
    path = save_maps(tmp_path / "bscan.npz", data, meta)
    model = load_model("single-acquisition", threads=1)
    assert matching.MATCH_LATERAL_Y is True
    with pytest.raises(
        ValueError,
        match=r"channel 'liv@lateral=18' has 840 nm, lateral 18 × 4.9 µm \(x × y\).*"
        r"B-scan maps.*single-acquisition-bscan",
    ):
        assemble_features([read_maps(path)], model)
    volume = save_maps(tmp_path / "vol.npz", data, {**meta, "reduction": {"lateral_axes": "YX"}})
    assert assemble_features([read_maps(volume)], model)[2]["notes"] == []  # isotropic channels match
    monkeypatch.setattr(matching, "MATCH_LATERAL_Y", False)
    feats, _, info = assemble_features([read_maps(path)], model)
    assert feats.shape == (6, 5, 6) and len(info["notes"]) == 1 and "lateral=18" in info["notes"][0]
    # a spec trained on the B-scan PSF (y = the original width) matches them, without a note
    aniso = dataclasses.replace(spec.configurations[2], lateral_resolution_y_um=4.9)
    assert aniso.optics.matches(read_maps(path).optics("liv@lateral=18"))

"""One A-line's time series (axes TZX, one pixel along x): the maps hold no lateral reduction, doct-classify
picks the A-line signature model, and with no neighbour across the beam it never founds flow on the speckle
or Doppler rules (whose false detections were recorded on 2-D windows and boxes): nothing is decided as
another motion beyond the window-1 bound."""

from __future__ import annotations

import numpy as np
import pytest

from classifier import ambiguity
from classifier.bench import cases
from classifier.bench.grid import CODES, layer_regions, signature_maps
from classifier.infer import classify_maps, default_model_for, load_model, read_maps

#: A-lines rendered (seeds), depth pixels per A-line, pixel pitch (µm).
N_ALINES, N_Z, PITCH_UM = 16, 96, 2.0


def _aline(seed: int) -> dict:
    """An A-line through three slabs: slow diffusion, slow random-ballistic motion and oblique flow, 20 dB, no
    static tissue (the case where a static-free A-line offers the Doppler reference a drifting population)."""
    motions = (
        {"kind": "diffusion", "diffusion_um2_per_s": 0.001},
        {"kind": "ballistic", "speed_um_per_s": 0.03},
        {"kind": "flow", "speed_um_per_s": 0.3, "polar_angle_deg": 45.0, "azimuth_deg": 60.0},
    )
    return {
        "name": "aline",
        "system": [dict(cases.SYSTEM)],
        "protocol": dict(cases.PROTOCOL),
        "grid": {"kind": "bscan", "n_x": 1, "n_z": N_Z, "pitch_x_um": PITCH_UM, "pitch_z_um": PITCH_UM, "y_um": 0.0},
        "region": layer_regions(N_Z * PITCH_UM, 0.05, motions),
        "noise": {"snr_db": 20.0},
        "simulation": {"seed": seed},
    }


def _mapped(tmp_path, seed: int):
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.measured.sequence import SequenceData, validate_meta

    spec = load_model("signature-aline").spec
    res = render(phantom_from_dict(_aline(seed)), seed=seed, threads=1)
    data = res.data[0].numpy()
    meta = res.metadata(0)
    meta.pop("phantom", None)
    seq = SequenceData(data=data, meta=validate_meta(meta, data.shape), source=f"aline-{seed}")
    maps = signature_maps(seq, spec)  # `torchdoct maps ALINE --resolution original --resolution axial=14 --signature`
    return res.labels, write_maps(tmp_path / f"aline-{seed}.npz", maps)


def test_an_axis_of_one_pixel_is_unseen_and_a_line_of_windows_founds_no_flow():
    assert ambiguity.single_pixel_axes({"z": 96, "x": 1}) == ["x"]
    assert ambiguity.single_pixel_axes({"y": 4, "z": 96, "x": 8}) == []
    assert ambiguity.line_windows({"z": 96, "x": 1}) and ambiguity.line_windows({"y": 1, "z": 96, "x": 1})
    assert not ambiguity.line_windows({"y": 1, "z": 96, "x": 8})  # a volume of one plane is a B-scan
    assert not ambiguity.line_windows({"z": 96, "x": 2})
    seen = ambiguity.unseen_axes("ZX", {"z": 2.0, "x": 2.0}, 4.9, 3.8)
    assert seen == ["y"]  # a B-scan at 2 µm sees x and z
    assert ambiguity.unseen_axes("ZX", {"z": 2.0, "x": 2.0}, 4.9, 3.8, extent_px={"z": 96, "x": 1}) == ["x", "y"]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_one_alines_maps_take_the_aline_model_and_decide_no_motion_as_another(tmp_path):
    """Sixteen A-lines, every pixel of each slab away from its borders: with the rules no motion has more than
    10 % of its pixels decided as another (the window-1 bound), flow is never founded by the speckle or Doppler
    rules, and the model alone decides some motion as another more often."""
    decided: dict[bool, dict[str, list[np.ndarray]]] = {True: {}, False: {}}
    for seed in range(N_ALINES):
        labels, path = _mapped(tmp_path, seed)
        for rules in (True, False):
            c = classify_maps(path, threads=1, abstain_ambiguous=rules, background_db="none")
            if seed == 0 and rules:
                assert default_model_for([read_maps(path)]) == ("signature-aline", None)
                amb = c.info["ambiguity"]
                assert amb["single_pixel_axes"] == ["x"] and {"x", "y"} <= set(amb["unseen_axes"])
                assert not {"coherent_motion", "translation", "doppler_drift"} & set(amb["rules"])
            out = np.asarray(c.labels).reshape(labels.shape)
            for name, code in CODES.items():
                z = np.where((labels == code).any(axis=1))[0]
                inner = out[z.min() + 6 : z.max() - 5, 0]  # 6 pixels (12 µm) from the slab's borders
                decided[rules].setdefault(name, []).append(inner)
    wrong = {}
    for rules in (True, False):
        for name, parts in decided[rules].items():
            got = np.concatenate(parts)
            others = [c.classes.index(m) for m in CODES if m != name]
            wrong[rules, name] = float(np.isin(got, others).mean())
    assert all(wrong[True, m] <= 0.10 for m in CODES), wrong
    assert max(wrong[False, m] for m in CODES) > 0.05, wrong  # the model alone: the rules had work to do
    with pytest.raises(ValueError, match="largest valid pool is 1"):
        classify_maps(path, threads=1, pool=5, background_db="none")


def test_one_alines_liv_ocds_maps_are_told_to_compute_the_signature_not_a_lateral_reduction(tmp_path):
    """The LIV/OCDS models read a lateral reduction, which one A-line cannot have: the refusal names the
    signature maps the A-line model reads instead of an impossible `--resolution lateral=18`."""
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render
    from torchdoct.measured.maps import compute_maps
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.measured.sequence import SequenceData, validate_meta

    res = render(phantom_from_dict(_aline(0)), seed=0, threads=1)
    data = res.data[0].numpy()
    meta = res.metadata(0)
    meta.pop("phantom", None)
    seq = SequenceData(data=data, meta=validate_meta(meta, data.shape), source="aline")
    path = write_maps(tmp_path / "liv.npz", compute_maps(seq, ["original", "axial=14"]))
    with pytest.raises(ValueError, match=r"cannot be reduced laterally.*--resolution axial=14 --signature") as err:
        classify_maps(path, threads=1)
    assert "lateral=18 ..." not in str(err.value)

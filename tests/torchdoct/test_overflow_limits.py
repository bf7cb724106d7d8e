"""Overflow and parse limits (issue class 4): numbers beyond any float (an integer of 400 or 100,000
digits, a radius whose square overflows) and HDF5 links into a loop end as exit 2 / ``ValueError``
naming the file and the field, never ``OverflowError``, ``RuntimeError`` or Python's digit limit."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _refusal import refused

from torchdoct.sim.config import SceneError, scene_from_dict

BIG = int("1" + "0" * 400)


def _meta(n=12):
    return {
        "axes": "TZX",
        "pitch_um": {"z": 2.0, "x": 2.0},
        "frame_times_s": [0.2048 * i for i in range(n)],
        "system": {
            "name": "s",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
            "refractive_index": 1.0,
        },
    }


def _seq(tmp_path, text):
    p = tmp_path / "s.npy"
    np.save(p, (np.random.default_rng(0).standard_normal((12, 6, 5)) + 1j).astype(np.complex64))
    p.with_suffix(".json").write_text(text)
    return p


@pytest.mark.parametrize(
    "field,text",
    [
        ("frame_times_s", json.dumps(_meta()).replace("[0.0,", f"[{BIG},")),
        ("pitch_um['z']", json.dumps(_meta()).replace('"z": 2.0', '"z": 1' + "0" * 100_000)),
        (
            "system.wavelength_um",
            json.dumps(_meta()).replace('"wavelength_um": 0.84', '"wavelength_um": ' + "9" * 5000),
        ),
    ],
)
def test_a_number_beyond_any_float_in_a_sidecar_names_the_field(tmp_path, capsys, field, text):
    seq = _seq(tmp_path, text)
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
        "s.npy",
        field,
        absent=("OverflowError", "set_int_max_str_digits", "Exceeds the limit"),
    )


@pytest.mark.parametrize("first", [-1.7e308, -1e300, -1e5])
def test_sidecar_frame_times_spanning_more_than_a_scene_may_are_refused_naming_the_field(tmp_path, capsys, first):
    meta = _meta()
    meta["frame_times_s"] = [first] + meta["frame_times_s"][1:]  # each finite; the span is not, or is over a day
    seq = _seq(tmp_path, json.dumps(meta))
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--out", str(tmp_path / "m.npz")],
        "s.npy",
        "frame_times_s",
        "86400 s",
        absent=("OverflowError",),
    )


def test_ocds_of_frame_times_whose_span_overflows_names_the_argument():
    import torch

    import torchdoct as td

    x = torch.rand(2, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64) + 0.5
    with pytest.raises(ValueError, match=r"ocds\(frame_times_s\).*beyond any float"):
        td.ocds(x, [-1e308] + [1e308 * (i / 7) for i in range(1, 8)], delay_range_s=(0.2, 0.6))


def test_a_frame_time_of_ten_to_the_400_in_a_scene_file_names_the_field():
    d = {
        "system": [{"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}],
        "protocol": {"n_frames": 3, "frame_times_s": [0.0, 0.2, BIG]},
        "population": [{"density_per_um3": 0.05}],
        "analysis": {"metrics": ["liv"]},
    }
    with pytest.raises(SceneError, match=r"frame_times_s.*finite.*401 digits"):
        scene_from_dict(d)


def test_a_sphere_radius_whose_square_overflows_is_refused_naming_it():
    from torchdoct.image.phantom import MAX_LENGTH_UM, phantom_from_dict

    d = {
        "system": [{"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}],
        "protocol": {"n_frames": 2, "frame_interval_s": 0.2},
        "analysis": {"metrics": ["liv"]},
        "grid": {"n_x": 8, "n_z": 8, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
        "region": [{"name": "ball", "shape": "sphere", "radius_um": 1e300, "density_per_um3": 0.05}],
    }
    with pytest.raises(SceneError, match=r"region\[0\]\.radius_um.*<= "):
        phantom_from_dict(d)
    assert (MAX_LENGTH_UM**2) < float("inf")


def test_hdf5_links_to_nothing_or_to_themselves(tmp_path, capsys):
    h5py = pytest.importorskip("h5py")
    data = (np.random.default_rng(0).standard_normal((12, 6, 5)) + 1j).astype(np.complex64)
    good = tmp_path / "good.h5"
    with h5py.File(good, "w") as f:  # a good dataset beside an unrelated dangling link and a loop: read
        f["data"] = data
        f.attrs["torchdoct"] = json.dumps(_meta())
        f["old"] = h5py.SoftLink("/nowhere")
        f["loop"] = h5py.SoftLink("/loop")
    from torchdoct.measured.io import read_sequence

    assert np.array_equal(read_sequence(good).data, data)
    bad = tmp_path / "bad.h5"
    with h5py.File(bad, "w") as f:
        f["data"] = h5py.SoftLink("/data")
        f.attrs["torchdoct"] = json.dumps(_meta())
    refused(
        capsys,
        tmp_path,
        ["maps", str(bad), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
        "bad.h5",
        "'data'",
        "link",
        absent=("RuntimeError", "corrupt"),
    )


@pytest.mark.parametrize("command", ["simulate", "plan", "render"])
def test_an_integer_of_thousands_of_digits_in_a_toml_file_names_its_line_and_key(tmp_path, capsys, command):
    from _scenes import SMALL_SCENE_TOML

    text = SMALL_SCENE_TOML.replace("seed = 7", "seed = 1" + "0" * 100_000)
    assert text != SMALL_SCENE_TOML
    path = tmp_path / "huge.toml"
    path.write_text(text)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if ln.startswith("seed"))
    argv = [command, str(path)] + (["--out", str(tmp_path / "r.npz")] if command == "render" else [])
    refused(
        capsys,
        tmp_path,
        argv,
        "huge.toml",
        f"line {line}",
        "seed",
        "100001 digits",
        absent=("set_int_max_str_digits", "Exceeds the limit"),
    )

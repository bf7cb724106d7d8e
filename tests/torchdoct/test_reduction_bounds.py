"""The reduction kernel's bound (issue class 3): a target PSF wider than the field of view is refused
before any work (a pitch given 1000× too fine made 4.4 GB of padding and a mean 10 dB off); the kernel
of :func:`reduce_resolution` is bounded by its axis; with ``normalization="power"`` the mean intensity of
speckle made with the original PSF is kept (away from the edges, whose extension is documented)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _refusal import refused

from torchdoct.cli import main
from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um
from torchdoct.measured.maps import compute_maps
from torchdoct.measured.resolution import gaussian_filter_axis, lateral_filter_sigma_um, reduce_resolution

SYSTEM = {"lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}


def test_a_target_wider_than_the_field_of_view_is_refused_at_once(tmp_path, capsys, seq):
    line = refused(
        capsys,
        tmp_path,
        [
            "maps",
            str(seq),
            "--pitch-um",
            "z=0.001,x=0.001",
            "--resolution",
            "lateral=18",
            "--metrics",
            "liv",
            "--out",
            str(tmp_path / "m.npz"),
            "--no-progress",
        ],
        "--resolution",
        "field of view",
        "narrower than the original",
        "--pitch-um",
    )
    assert "0.005 µm" in line  # 5 pixels × 0.001 µm


def _maps_argv(seq, tmp_path, *resolutions: str) -> list[str]:
    argv = ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz"), "--no-progress"]
    for r in resolutions:
        argv += ["--resolution", r]
    return argv


def test_a_target_of_many_fields_of_view_is_refused(tmp_path, capsys, seq):
    line = refused(
        capsys,
        tmp_path,
        _maps_argv(seq, tmp_path, "lateral=41"),
        "--resolution",
        "lateral resolution of 41",
        "wider than the field of view along x",
        "10 µm",
    )
    assert "lateral=10 or less" in line


def test_a_target_of_exactly_one_field_of_view_is_accepted(tmp_path, capsys, seq):
    """The fixture's field of view is 5 pixels × 2 µm = 10 µm along x and 6 × 2 µm = 12 µm along z: targets
    of exactly those widths are reduced."""
    from torchdoct.measured.io import read_maps

    assert main(_maps_argv(seq, tmp_path, "lateral=10", "axial=12", "axial=12,lateral=10")) == 0, capsys.readouterr()
    m = read_maps(tmp_path / "m.npz")
    assert list(m.channels) == ["liv@lateral=10", "liv@axial=12", "liv@axial=12,lateral=10"]
    assert np.isfinite(m.maps).all()


@pytest.mark.parametrize(
    "target, names",
    [
        ("lateral=10.01", ("a lateral resolution of 10.01 µm", "along x (5 pixels × 2 µm = 10 µm)", "lateral=10 or")),
        ("axial=12.01", ("an axial resolution of 12.01 µm", "along z (6 pixels × 2 µm = 12 µm)", "axial=12 or")),
    ],
)
def test_a_target_just_above_one_field_of_view_is_refused_naming_the_axis_and_the_fix(
    tmp_path, capsys, seq, target, names
):
    refused(
        capsys,
        tmp_path,
        _maps_argv(seq, tmp_path, "original", target),
        "--resolution",
        "wider than the field of view",
        *names,
        "--pitch-um",
    )


def test_a_lateral_target_longer_than_a_volume_of_few_b_scans_is_refused_along_y(tmp_path, capsys):
    """A volume's lateral reduction runs along y too: 3 B-scans 2 µm apart are 6 µm long, too short for an
    18 µm PSF, though the 20 µm along x would hold it."""
    from torchdoct.measured.io import write_sequence

    rng = np.random.default_rng(1)
    shape = (8, 3, 6, 10)
    path = write_sequence(
        tmp_path / "vol.npy",
        (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64),
        {
            "axes": "TYZX",
            "pitch_um": {"y": 2.0, "z": 2.0, "x": 2.0},
            "frame_times_s": [0.2048 * i for i in range(8)],
            "system": {"name": "s", "wavelength_um": 0.84, **SYSTEM},
        },
    )
    refused(
        capsys,
        tmp_path,
        _maps_argv(path, tmp_path, "lateral=18"),
        "--resolution",
        "lateral resolution of 18 µm is wider than the field of view along y (3 pixels × 2 µm = 6 µm)",
        "lateral=6 or less",
        "--pitch-um",
    )


def test_a_target_wider_than_the_field_of_view_is_refused_before_any_allocation(monkeypatch):
    """A pitch declared 200 times too fine (0.01 µm for 2 µm) makes a 4096-pixel B-scan 41 µm wide, so a
    100 µm lateral target (2.4 fields of view) would pad each line of x to about ten times its length:
    :func:`compute_maps` refuses it from the shape alone, before it reads a sample or allocates its output
    (the field is a zero-stride view of 16 MB that holds one value)."""
    import tracemalloc

    import torchdoct.measured.maps as maps_module
    import torchdoct.measured.resolution as resolution_module
    from torchdoct.measured.io import SequenceData, validate_meta

    def never(*args, **kwargs):
        raise AssertionError("the reduction ran")

    monkeypatch.setattr(maps_module, "reduce_resolution", never)
    monkeypatch.setattr(resolution_module, "gaussian_filter_axis", never)
    monkeypatch.setattr(maps_module, "_empty_floor", never)
    shape = (8, 64, 4096)
    data = np.broadcast_to(np.complex64(1 + 1j), shape)
    meta = {
        "axes": "TZX",
        "pitch_um": {"z": 2.0, "x": 0.01},
        "frame_times_s": [0.2048 * i for i in range(8)],
        "system": {"name": "s", "wavelength_um": 0.84, **SYSTEM},
    }
    seq = SequenceData(data=data, meta=validate_meta(meta, shape), source="wrong-pitch.npy")
    tracemalloc.start()
    try:
        with pytest.raises(ValueError) as err:
            compute_maps(seq, ["original", "lateral=100"], metrics=("liv",))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    msg = str(err.value)
    assert "wider than the field of view along x (4096 pixels × 0.01 µm = 40.96 µm)" in msg, msg
    assert "lateral=40.96 or less" in msg and "--pitch-um" in msg, msg
    assert peak < data.nbytes // 16, peak  # nothing of the field's size


def test_the_kernel_of_reduce_resolution_is_bounded_by_its_axis():
    x = torch.ones(2, 8, 8, dtype=torch.complex64)
    with pytest.raises(ValueError, match="wider than 4 times the axis"):
        reduce_resolution(x, pitch_um={"z": 0.001, "x": 0.001}, system=SYSTEM, lateral_resolution_um=18.0)


def test_power_normalization_keeps_the_mean_intensity_of_speckle():
    """Speckle with the original PSF (4.9 µm lateral, 3.8 µm axial at 1 µm pitch), reduced to 12 µm
    lateral: the mean intensity of the interior (3σ' from the edges) equals the input's within 4
    standard errors of the frame means."""
    g = torch.Generator().manual_seed(4)
    t, n, p = 48, 96, 1.0
    w = torch.complex(
        torch.randn(t, n, n, generator=g, dtype=torch.float64), torch.randn(t, n, n, generator=g, dtype=torch.float64)
    )
    x = gaussian_filter_axis(w, 2, amplitude_sigma_lateral_um(4.9) / p, edge_mode="wrap")
    x = gaussian_filter_axis(x, 1, amplitude_sigma_axial_um(3.8) / p, edge_mode="wrap")
    x = x / (x.abs() ** 2).mean().sqrt()  # unit mean intensity
    y = reduce_resolution(x, pitch_um={"z": p, "x": p}, system=SYSTEM, lateral_resolution_um=12.0)
    edge = int(math.ceil(3 * lateral_filter_sigma_um(4.9, 12.0) / p))
    per_frame = (y[:, :, edge : n - edge].abs() ** 2).mean(dim=(1, 2)).numpy()
    se = per_frame.std(ddof=1) / math.sqrt(t)
    assert abs(per_frame.mean() - 1.0) < 4 * se, (per_frame.mean(), se)
    assert np.isfinite(per_frame).all()

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

from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um
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


def test_a_target_of_many_fields_of_view_is_refused(tmp_path, capsys, seq):
    line = refused(
        capsys,
        tmp_path,
        [
            "maps",
            str(seq),
            "--resolution",
            "lateral=41",
            "--metrics",
            "liv",
            "--out",
            str(tmp_path / "m.npz"),
            "--no-progress",
        ],
        "--resolution",
        "lateral resolution of 41",
        "4 fields of view",
        "10 µm",
    )
    assert "lateral=40" in line


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

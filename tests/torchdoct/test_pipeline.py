"""The whole measured-data path on simulator output: render → sequence file → maps → compare.

Resolution reduction (paper Eqs. 1–8) of a rendered high-resolution sequence must equal, pixel for
pixel away from the image edges, a sequence rendered directly at the target resolution from the
same scatterers: the Gaussian PSF convolved with the Gaussian filter is the target Gaussian PSF, and
the phase exp(i·2kn·z_j) of each scatterer is untouched.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchdoct.cli import main
from torchdoct.image.phantom import phantom_from_dict
from torchdoct.image.render import render
from torchdoct.measured.io import read_maps, read_sequence
from torchdoct.measured.resolution import reduce_resolution
from torchdoct.sim.metrics import liv, ocds

HIGH = {"name": "high", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}


def _phantom(systems, grid, n_frames=6, density=0.05):
    analysis = (
        {"metrics": ["liv", "ocds"], "ocds_delay_range_s": [0.2048, 0.6144]} if n_frames >= 4 else {"metrics": ["liv"]}
    )
    return phantom_from_dict(
        {
            "name": "pipe",
            "system": systems,
            "grid": grid,
            "protocol": {"n_frames": n_frames, "frame_interval_s": 0.2048},
            "background": [
                {"density_per_um3": density, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.02}]}
            ],
            "analysis": analysis,
            "simulation": {"seed": 11, "truncation_tolerance": 1e-6},
        }
    )


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_axial_reduction_of_a_render_equals_a_direct_render():
    ax14 = dict(HIGH, name="ax14", axial_resolution_um=14.0)
    ph = _phantom([HIGH, ax14], {"n_x": 16, "n_z": 96, "pitch_x_um": 2.0, "pitch_z_um": 1.0})
    res = render(ph, dtype="float64")
    high, direct = res.data[0].numpy(), res.data[1].numpy()
    red = reduce_resolution(
        high, pitch_um=ph.grid.pitch_um, system=ph.scene.systems[0], axial_resolution_um=14.0, normalization="peak"
    )
    inner = slice(34, 62)  # 34 µm from the depth edges: beyond the filter's reach
    assert _rel_err(red[:, inner], direct[:, inner]) < 1e-4
    # and the untouched high-resolution field is far from it (the test can fail)
    assert _rel_err(high[:, inner], direct[:, inner]) > 0.3


def test_lateral_reduction_of_a_rendered_volume_equals_a_direct_render():
    lat18 = dict(HIGH, name="lat18", lateral_resolution_um=18.0)
    grid = {"kind": "volume", "n_x": 40, "n_y": 40, "n_z": 6, "pitch_x_um": 2.0, "pitch_y_um": 2.0, "pitch_z_um": 2.0}
    ph = _phantom([HIGH, lat18], grid, n_frames=2, density=0.01)
    ph = phantom_from_dict({**ph.to_dict(), "simulation": {"seed": 11, "truncation_tolerance": 1e-5}})
    res = render(ph, dtype="float64")
    high, direct = res.data[0].numpy(), res.data[1].numpy()
    red = reduce_resolution(
        high,
        pitch_um=ph.grid.pitch_um,
        system=ph.scene.systems[0],
        axes="TYZX",
        lateral_resolution_um=18.0,
        normalization="peak",
    )
    inner = slice(15, 25)  # 30 µm (5 filter sigmas) from the lateral edges
    got, want = red[:, inner, :, inner], direct[:, inner, :, inner]
    assert _rel_err(got, want) < 1e-3
    assert _rel_err(high[:, inner, :, inner], want) > 0.3


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_cli_render_maps_compare(tmp_path, capsys):
    """Render three samples, make maps at two resolutions from the command line, compare them.

    The maps of the axial=14 channel equal LIV and OCDS computed on a direct 14-µm render of the
    same scatterers (interior pixels); the comparison table has one row per metric.
    """
    ax14 = dict(HIGH, name="ax14", axial_resolution_um=14.0)
    src = tmp_path / "ph.toml"
    lines = ['name = "pipe"']
    for s in (HIGH, ax14):
        lines += ["[[system]]"] + [f"{k} = {v!r}".replace("'", '"') for k, v in s.items()]
    lines += [
        "[protocol]",
        "n_frames = 8",
        "frame_interval_s = 0.2048",
        "[grid]",
        "n_x = 12",
        "n_z = 120",
        "pitch_x_um = 2.0",
        "pitch_z_um = 1.0",
        "[[background]]",
        "density_per_um3 = 0.05",
        "[[background.motion]]",
        'kind = "diffusion"',
        "diffusion_um2_per_s = 0.02",
        "[analysis]",
        'metrics = ["liv", "ocds"]',
        "ocds_delay_range_s = [0.2048, 0.6144]",
        "[simulation]",
        "truncation_tolerance = 1e-6",
    ]
    src.write_text("\n".join(lines) + "\n", encoding="utf-8")
    maps_files = []
    for seed in (1, 2, 3):
        seq = tmp_path / f"s{seed}.npz"
        assert (
            main(
                [
                    "render",
                    str(src),
                    "--out",
                    str(seq),
                    "--seed",
                    str(seed),
                    "--no-progress",
                    "--no-preview",
                    "--dtype",
                    "float64",
                ]
            )
            == 0
        )
        out = tmp_path / f"s{seed}-maps.npz"
        assert (
            main(
                [
                    "maps",
                    str(tmp_path / f"s{seed}-high.npz"),
                    "--resolution",
                    "original",
                    "--resolution",
                    "axial=14",
                    "--ocds-delay-range-s",
                    "0.2048",
                    "0.6144",
                    "--out",
                    str(out),
                    "--no-progress",
                ]
            )
            == 0
        )
        maps_files.append(out)
    m = read_maps(maps_files[0])
    direct = read_sequence(tmp_path / "s1-ax14.npz")
    i = np.abs(direct.data) ** 2
    it = torch.from_numpy(np.moveaxis(i, 0, -1))
    want_liv = liv(it).numpy()
    want_ocds = ocds(it, direct.meta["frame_times_s"], delay_range_s=(0.2048, 0.6144)).numpy()
    inner = slice(45, 75)  # 45 µm from the depth edges: 5.5 sigmas of the axial filter (8.1 µm)
    ch = {c["name"]: k for k, c in enumerate(m.meta["channels"])}
    got_liv = m.maps[ch["liv@axial=14"]][inner]
    got_ocds = m.maps[ch["ocds@axial=14"]][inner]
    np.testing.assert_allclose(got_liv, want_liv[inner], rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(got_ocds, want_ocds[inner], rtol=1e-3, atol=1e-3)
    assert not np.allclose(m.maps[ch["liv@original"]][inner], want_liv[inner], atol=0.1)
    capsys.readouterr()
    table = tmp_path / "stats.csv"
    assert main(["compare", *map(str, maps_files), "--out", str(table)]) == 0
    text = table.read_text()
    assert "liv" in text and "ocds" in text and len(text.strip().splitlines()) >= 3

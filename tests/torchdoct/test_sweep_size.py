"""Sweep size (issue class 10): the cells are counted before any is built; past the cap the sweep is
refused with the count, an estimate of building them (measured on the first cell) and the
``--max-cells`` override; a field's ``num`` is capped before its values are made."""

from __future__ import annotations

import pytest
from _refusal import refused

from torchdoct.study import grid
from torchdoct.study.sweep import parse_sweep

BASE = """[[system]]
name = "s"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[protocol]
n_frames = 32
frame_interval_s = 0.2048
[[population]]
density_per_um3 = 0.05
[[population.motion]]
kind = "diffusion"
diffusion_um2_per_s = 0.1
[sweep]
[[sweep.field]]
path = "population.0.motion.0.diffusion_um2_per_s"
linear = {{ start = 0.01, stop = 10.0, num = {a} }}
[[sweep.field]]
path = "population.0.density_per_um3"
linear = {{ start = 0.01, stop = 1.0, num = {b} }}
"""


@pytest.fixture(autouse=True)
def default_cap():
    yield
    grid.set_max_cells(None)


def test_a_million_cell_product_is_refused_before_any_cell_is_built(tmp_path, capsys, monkeypatch):
    built = []
    import torchdoct.study.sweep as sweep

    real = sweep.scene_from_dict
    monkeypatch.setattr(sweep, "scene_from_dict", lambda d: built.append(1) or real(d))
    f = tmp_path / "big.toml"
    f.write_text(BASE.format(a=1000, b=1000))
    line = refused(
        capsys,
        tmp_path,
        ["sweep", str(f), "--out", str(tmp_path / "o")],
        "big.toml",
        "1,000,000 cells",
        "cap of 10,000",
        "--max-cells",
        "GB",
    )
    assert "1000 × 1000" in line and len(built) <= 2  # the base scene and the one cell of the estimate


def test_a_huge_num_is_refused_before_its_values_are_made(tmp_path, capsys):
    f = tmp_path / "num.toml"
    f.write_text(BASE.format(a=10**12, b=2))
    refused(
        capsys,
        tmp_path,
        ["sweep", str(f), "--out", str(tmp_path / "o")],
        "sweep.field[0].linear.num",
        "1,000,000,000,000",
        "--max-cells",
    )


def test_max_cells_moves_the_cap_both_ways():
    import tomllib

    data = tomllib.loads(BASE.format(a=3, b=3))
    assert len(parse_sweep(data).cells) == 9
    grid.set_max_cells(8)
    with pytest.raises(ValueError, match="9 cells, over the cap of 8"):
        parse_sweep(data)
    grid.set_max_cells(9)
    assert len(parse_sweep(data).cells) == 9
    with pytest.raises(ValueError, match="--max-cells must be a positive integer"):
        grid.set_max_cells(0)

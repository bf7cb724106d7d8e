"""Spatial simulator: phantom files, rendering, ground truth, consistency with the point model."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

import torchdoct.image.render  # noqa: F401  (the module; torchdoct.render is the function)

render_mod = sys.modules["torchdoct.image.render"]
from _stats import assert_within_se

from torchdoct import simulate
from torchdoct.conventions import (
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    mean_intensity,
    truncation_radius_factor,
)
from torchdoct.image.phantom import MOTION_CODES, load_phantom, phantom_from_dict, shipped_phantoms
from torchdoct.image.render import render
from torchdoct.sim.config import SceneError

SYSTEM = {"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}


def _phantom(grid, regions=(), background=None, n_frames=8, noise=None, **extra):
    d = {
        "name": "t",
        "system": [SYSTEM],
        "protocol": {"n_frames": n_frames, "frame_interval_s": 0.2048},
        "grid": grid,
        "analysis": {"metrics": ["liv", "ocds"], "ocds_delay_range_s": [0.2048, 0.6144]},
        "simulation": {"seed": 3},
        **extra,
    }
    if regions:
        d["region"] = list(regions)
    if background is not None:
        d["background"] = background
    if noise is not None:
        d["noise"] = {"snr_db": noise}
    return phantom_from_dict(d)


SMALL_GRID = {"n_x": 24, "n_z": 20, "pitch_x_um": 2.0, "pitch_z_um": 2.0}


# ------------------------------------------------------------------------------------------------
# phantom files


def test_shipped_phantoms_load_and_round_trip():
    names = shipped_phantoms()
    assert {"spheroid", "vessel-slab"} <= set(names)
    for path in names.values():
        ph = load_phantom(path)
        again = phantom_from_dict(ph.to_dict())
        assert again.scene == ph.scene and again.grid == ph.grid and again.regions == ph.regions


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d["region"][0].update(colour=1), r"region\[0\]: unknown key"),
        (lambda d: d["region"][0].pop("shape"), r"region\[0\]: missing key 'shape'"),
        (lambda d: d["region"][0].update(shape="cube"), r"region\[0\]\.shape"),
        (lambda d: d["region"][0].update(inner_radius_um=50.0), r"region\[0\]\.inner_radius_um"),
        (lambda d: d["region"][0].update(density_per_um3=-1.0), r"region\[0\]\.density_per_um3"),
        (lambda d: d["region"][0].update(density_per_um3=float("nan")), r"region\[0\]\.density_per_um3"),
        (lambda d: d["region"][0].update(motion=[{"kind": "swim"}]), r"region\[0\]\.motion\[0\]\.kind"),
        (lambda d: d["grid"].update(pitch_x_um=0.0), r"grid\.pitch_x_um"),
        (lambda d: d["grid"].update(kind="volume"), r"grid.*n_y"),
        (lambda d: d.update(population=[{"density_per_um3": 0.1}]), r"population.*\[\[region\]\]"),
        (lambda d: d["region"].append(dict(d["region"][0])), r"duplicate region name"),
    ],
)
def test_bad_phantoms_name_the_key(change, match):
    d = {
        "system": [SYSTEM],
        "protocol": {"n_frames": 4, "frame_interval_s": 0.2},
        "grid": dict(SMALL_GRID),
        "analysis": {"metrics": ["liv"]},
        "region": [{"name": "ball", "shape": "sphere", "radius_um": 20.0, "density_per_um3": 0.05}],
    }
    change(d)
    with pytest.raises((SceneError, TypeError), match=match):
        phantom_from_dict(d)


def test_label_image_region(tmp_path):
    img = np.zeros((20, 24), dtype=np.int16)
    img[5:12, 3:9] = 7
    np.save(tmp_path / "lab.npy", img)
    d = {
        "system": [SYSTEM],
        "protocol": {"n_frames": 2, "frame_interval_s": 0.2},
        "grid": dict(SMALL_GRID),
        "analysis": {"metrics": ["liv"]},
        "region": [
            {
                "name": "cells",
                "shape": "label-image",
                "file": "lab.npy",
                "value": 7,
                "density_per_um3": 0.05,
                "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.1}],
            }
        ],
    }
    ph = phantom_from_dict(d, base_dir=tmp_path)
    res = render(ph)
    assert np.array_equal(res.labels == MOTION_CODES["diffusion"], img == 7)
    d["region"][0]["value"] = 3
    with pytest.raises(SceneError, match=r"region\[0\]\.value: label 3 does not occur"):
        phantom_from_dict(d, base_dir=tmp_path)
    d["region"][0]["file"] = "missing.npy"
    with pytest.raises(FileNotFoundError, match="missing.npy"):
        phantom_from_dict(d, base_dir=tmp_path)
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    d["region"][0]["file"] = "objects.npy"
    with pytest.raises(SceneError, match="unpickling"):
        phantom_from_dict(d, base_dir=tmp_path)


# ------------------------------------------------------------------------------------------------
# rendering: structure, only-what-is-needed, reproducibility


def test_static_phantom_is_one_splat_and_frames_identical():
    ph = _phantom(SMALL_GRID, background={"density_per_um3": 0.05})
    res = render(ph)
    assert res.data.shape == (1, 8, 20, 24) and res.data.dtype == torch.complex64
    assert res.work["stages"] == ["static splat (once)", "no motion stage", "no noise stage"]
    assert torch.equal(res.data[0, 0], res.data[0, -1])
    m = res.maps()
    assert torch.all(m["liv"] == 0) and torch.all(m["ocds"] == 0)


def test_empty_outside_regions_and_labels():
    ph = _phantom(
        {"n_x": 40, "n_z": 30, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
        regions=[
            {
                "name": "ball",
                "shape": "sphere",
                "radius_um": 12.0,
                "density_per_um3": 0.1,
                "motion": [{"kind": "ballistic", "speed_um_per_s": 0.5}],
            }
        ],
    )
    res = render(ph)
    x = ph.grid.coords_um("x")[None, :]
    z = ph.grid.coords_um("z")[:, None]
    r = np.sqrt(x**2 + z**2)
    assert np.array_equal(res.labels == MOTION_CODES["ballistic"], r <= 12.0)
    assert np.all(res.labels[r > 12.0] == MOTION_CODES["empty"])
    assert np.allclose(res.label_params[1][r <= 12.0], 0.5) and np.all(res.label_params[0] == 0)
    # pixels farther than the PSF truncation plus the protocol reach from the ball see nothing
    c = truncation_radius_factor(ph.scene.simulation.truncation_tolerance)
    reach = 0.5 * 7 * 0.2048
    far = r > 12.0 + c * amplitude_sigma_lateral_um(4.9) + c * amplitude_sigma_axial_um(3.8) + reach
    assert far.any() and torch.all(res.data[0][:, torch.from_numpy(far)] == 0)
    assert (res.data[0][:, torch.from_numpy(r < 8)].abs() > 0).all()


def test_later_regions_paint_over_earlier_ones():
    """A static ball over a diffusing slab: inside the ball only static scatterers count."""
    ph = _phantom(
        {"n_x": 40, "n_z": 40, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
        regions=[
            {
                "name": "slab",
                "shape": "slab",
                "z_min_um": -100.0,
                "z_max_um": 100.0,
                "density_per_um3": 0.05,
                "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.1}],
            },
            {"name": "ball", "shape": "sphere", "radius_um": 30.0, "density_per_um3": 0.05},
        ],
    )
    res = render(ph)
    x = ph.grid.coords_um("x")[None, :]
    z = ph.grid.coords_um("z")[:, None]
    r = np.sqrt(x**2 + z**2)
    assert np.all(res.labels[r <= 30] == MOTION_CODES["static"])
    assert np.all(res.labels[r > 30.5] == MOTION_CODES["diffusion"])
    liv = res.maps()["liv"].numpy()
    deep = r < 30.0 - truncation_radius_factor(1e-2) * amplitude_sigma_axial_um(3.8) - 5 * math.sqrt(
        2 * 0.1 * 7 * 0.2048
    )
    assert deep.sum() > 20 and np.all(liv[deep] == 0)
    assert np.all(liv[r > 45] > 0)


def test_flow_region_is_rigid_translation_without_per_frame_draws(monkeypatch):
    calls = []
    real = torch.randn

    def spy(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(render_mod.torch, "randn", spy)
    ph = _phantom(
        SMALL_GRID,
        regions=[
            {
                "name": "vessel",
                "shape": "cylinder",
                "axis": [1, 0, 0],
                "radius_um": 10.0,
                "density_per_um3": 0.08,
                "motion": [{"kind": "flow", "speed_um_per_s": 2.0, "polar_angle_deg": 90.0}],
            }
        ],
    )
    res = render(ph)
    assert calls == [] and "diffusion" not in " ".join(res.work["stages"])
    # a flow along x by exactly one pixel per frame shifts the image by one pixel per frame
    ph2 = _phantom(
        SMALL_GRID,
        regions=[
            {
                "name": "vessel",
                "shape": "slab",
                "z_min_um": -50.0,
                "z_max_um": 50.0,
                "density_per_um3": 0.08,
                "motion": [{"kind": "flow", "speed_um_per_s": 2.0 / 0.2048, "polar_angle_deg": 90.0}],
            }
        ],
    )
    e = render(ph2, dtype="float64").data[0]
    assert torch.allclose(e[1, :, 1:], e[0, :, :-1], rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_reproducible_and_independent_of_chunking(monkeypatch):
    ph = _phantom(
        SMALL_GRID,
        regions=[
            {
                "name": "core",
                "shape": "sphere",
                "radius_um": 15.0,
                "density_per_um3": 0.06,
                "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.05}],
            }
        ],
        background={"density_per_um3": 0.02},
        noise=25.0,
    )
    a = render(ph, seed=5).data
    assert torch.equal(a, render(ph, seed=5).data)
    monkeypatch.setattr(render_mod, "_SPLAT_ELEMENTS", 97)
    assert torch.equal(a, render(ph, seed=5).data)
    assert not torch.equal(a, render(ph, seed=6).data)


def test_float32_matches_float64():
    ph = _phantom(
        {"n_x": 16, "n_z": 16, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
        background={
            "density_per_um3": 0.05,
            "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.02}, {"kind": "flow", "speed_um_per_s": 1.0}],
        },
    )
    # far from the origin: phases must stay accurate at large absolute depth
    a = render(ph, dtype="float64").data
    b = render(ph, dtype="float32").data
    scale = a.abs().max()
    assert float((a - b.to(a.dtype)).abs().max() / scale) < 2e-6


def test_noise_stage_only_when_asked_and_at_its_power():
    grid = {"n_x": 64, "n_z": 64, "pitch_x_um": 2.0, "pitch_z_um": 2.0}
    ph = _phantom(
        grid,
        regions=[
            {"name": "ball", "shape": "sphere", "radius_um": 5.0, "center_um": [200.0, 0, 0], "density_per_um3": 0.055}
        ],
        noise=20.0,
    )
    res = render(ph)
    assert "noise at 20.0 dB" in res.work["stages"]
    i = (res.data[0].abs() ** 2).double()
    expected = mean_intensity(0.055, 4.9, 3.8) / 100.0
    n = i.numel()  # noise-only pixels (the ball is outside the field of view)
    assert_within_se(float(i.mean()), expected, expected / math.sqrt(n))


def test_volume_shape_and_plane_statistics():
    grid = {"kind": "volume", "n_x": 12, "n_y": 10, "n_z": 14, "pitch_x_um": 2.0, "pitch_y_um": 2.0, "pitch_z_um": 2.0}
    ph = _phantom(
        grid, background={"density_per_um3": 0.05, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.01}]}
    )
    res = render(ph)
    assert res.data.shape == (1, 8, 10, 14, 12) and res.labels.shape == (10, 14, 12)
    assert np.all(res.labels == MOTION_CODES["diffusion"])


# ------------------------------------------------------------------------------------------------
# consistency with the point model


def _intensity_corr(i: torch.Tensor, lag: int, axis: int) -> float:
    a = i.narrow(axis, 0, i.shape[axis] - lag).reshape(-1).double()
    b = i.narrow(axis, lag, i.shape[axis] - lag).reshape(-1).double()
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / torch.sqrt((a * a).sum() * (b * b).sum()))


def test_speckle_correlation_matches_psf():
    """Intensity correlation of neighbouring pixels is exp(−Δ²/(2s²)) per axis; far pixels: 0.

    For a Gaussian PSF both the Gaussian-speckle term |∫h h'|² and the finite-scatterer term ∫h²h'²
    decay as exp(−Δ²/(2s²)), so this holds at any density (physics.md §5.4 applied across pixels).
    """
    grid = {"n_x": 96, "n_z": 96, "pitch_x_um": 1.0, "pitch_z_um": 1.0}
    sx, sz = amplitude_sigma_lateral_um(4.9), amplitude_sigma_axial_um(3.8)
    lags = {1: [1, 2, 3, 5, 16], 0: [1, 2, 3, 5, 20]}  # axis 1 = x, axis 0 = z
    est = {(ax, lag): [] for ax, ls in lags.items() for lag in ls}
    for seed in range(12):
        ph = _phantom(grid, background={"density_per_um3": 0.055}, n_frames=2, analysis={"metrics": ["liv"]})
        i = render(ph, seed=seed, dtype="float64").intensity()[..., 0]
        for ax, ls in lags.items():
            for lag in ls:
                est[(ax, lag)].append(_intensity_corr(i, lag, ax))
    for (ax, lag), vals in est.items():
        s = sx if ax == 1 else sz
        v = np.asarray(vals)
        assert_within_se(v.mean(), math.exp(-(lag**2) / (2 * s * s)), v.std(ddof=1) / math.sqrt(len(v)))


def test_uniform_region_matches_point_model():
    """Per-pixel mean intensity, LIV and OCDS (mean and spread) of independent pixels = point model."""
    d_um2 = 0.01
    # pixels farther apart than twice (truncation half-width + 5-sigma diffusion reach): independent
    grid = {"n_x": 16, "n_z": 16, "pitch_x_um": 20.0, "pitch_z_um": 24.0}
    bg = {"density_per_um3": 0.055, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": d_um2}]}
    pix = []
    for seed in (1, 2):
        res = render(_phantom(grid, background=bg, n_frames=16), seed=seed, dtype="float64")
        m = res.maps()
        i = res.intensity()
        pix.append(torch.stack([i.mean(-1), m["liv"], m["ocds"]], -1).reshape(-1, 3))
    pix = torch.cat(pix).numpy()
    ph = _phantom(grid, background=bg, n_frames=16)
    sim = simulate(ph.scene, trials=1024, seed=9, dtype=torch.float64)
    met = sim.metrics()
    pt = np.stack(
        [(sim.signals.abs() ** 2).mean(-1)[:, 0].numpy(), met["liv"][:, 0].numpy(), met["ocds"][:, 0].numpy()], -1
    )
    assert not np.isnan(pix).any() and not np.isnan(pt).any()
    for k in range(3):
        a, b = pix[:, k], pt[:, k]
        assert_within_se(a.mean(), b.mean(), math.hypot(a.std() / math.sqrt(len(a)), b.std() / math.sqrt(len(b))))
        da, db = (a - a.mean()) ** 2, (b - b.mean()) ** 2  # spread: compare the variances
        assert_within_se(da.mean(), db.mean(), math.hypot(da.std() / math.sqrt(len(da)), db.std() / math.sqrt(len(db))))
    assert_within_se(pix[:, 0].mean(), mean_intensity(0.055, 4.9, 3.8), pix[:, 0].std() / math.sqrt(len(pix)))


# ------------------------------------------------------------------------------------------------
# command line


def test_cli_render_writes_sequence_labels_preview_and_refuses_overwrite(tmp_path, capsys):
    from torchdoct.cli import main
    from torchdoct.measured.io import read_sequence

    src = tmp_path / "ph.toml"
    src.write_text(
        'name = "mini"\n[[system]]\nname = "840nm"\nwavelength_um = 0.84\nlateral_resolution_um = 4.9\n'
        "axial_resolution_um = 3.8\n[protocol]\nn_frames = 6\nframe_interval_s = 0.2048\n"
        "[grid]\nn_x = 20\nn_z = 16\npitch_x_um = 2.0\npitch_z_um = 2.0\n"
        '[[region]]\nname = "ball"\nshape = "sphere"\nradius_um = 10.0\ndensity_per_um3 = 0.05\n'
        '[[region.motion]]\nkind = "diffusion"\ndiffusion_um2_per_s = 0.02\n'
        '[analysis]\nmetrics = ["liv", "ocds"]\nocds_delay_range_s = [0.2048, 0.6144]\n',
        encoding="utf-8",
    )
    out = tmp_path / "seq.npz"
    assert main(["render", str(src), "--out", str(out), "--no-progress"]) == 0
    seq = read_sequence(out)
    assert seq.data.shape == (6, 16, 20) and seq.meta["axes"] == "TZX"
    assert seq.meta["pitch_um"] == {"z": 2.0, "x": 2.0} and len(seq.meta["frame_times_s"]) == 6
    assert seq.labels.shape == (16, 20) and set(np.unique(seq.labels)) == {0, MOTION_CODES["diffusion"]}
    assert (tmp_path / "seq.png").stat().st_size > 1000
    before = out.read_bytes()
    assert main(["render", str(src), "--out", str(out), "--no-progress", "--seed", "4"]) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["render", str(src), "--out", str(tmp_path / "seq.h5"), "--no-progress", "--no-preview"]) == 0
    h5 = read_sequence(tmp_path / "seq.h5")
    assert np.array_equal(h5.data, seq.data)
    assert main(["render", str(src), "--out", str(tmp_path / "seq.txt")]) == 2
    assert main(["render", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "x.npz")]) == 2


def test_any_scene_renders_as_a_uniform_medium(tmp_path, tmp_scene_file, capsys):
    """A point-model scene file (no regions) plus a grid: its populations fill the field of view."""
    from torchdoct.cli import main
    from torchdoct.measured.io import read_sequence

    out = tmp_path / "scene.npy"
    assert (
        main(["render", str(tmp_scene_file), "--grid", "12x10", "--pitch-um", "3", "--out", str(out), "--no-progress"])
        == 0
    )
    seq = read_sequence(out)
    assert seq.data.shape == (8, 12, 10) and seq.meta["pitch_um"] == {"z": 3.0, "x": 3.0}
    labels = np.load(tmp_path / "scene.labels.npz", allow_pickle=False)
    assert seq.meta["labels_file"] == "scene.labels.npz"
    assert np.all(labels["labels"] == MOTION_CODES["diffusion"]) and np.all(np.abs(seq.data) > 0)
    assert main(["render", str(tmp_scene_file), "--out", str(tmp_path / "b.npy")]) == 2
    assert "[grid]" in capsys.readouterr().err
    assert (
        main(["render", str(tmp_scene_file), "--grid", "4x", "--pitch-um", "1", "--out", str(tmp_path / "c.npy")]) == 2
    )


def test_mixed_background_populations_label():
    ph = _phantom(
        SMALL_GRID,
        background=[
            {"density_per_um3": 0.03},
            {"density_per_um3": 0.02, "name": "moving", "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.2}]},
        ],
    )
    res = render(ph)
    assert np.all(res.labels == MOTION_CODES["diffusion"])
    assert np.allclose(res.label_params[0], 0.2)
    assert res.phantom.region_table()[0]["density_per_um3"] == pytest.approx(0.05)

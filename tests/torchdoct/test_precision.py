"""Precision (issue class 8): numbers stored or computed in single precision give the result of the same
numbers in double precision, or a refusal that names the cause and the fix, never a wrong verdict."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import torchdoct as td
from torchdoct.conventions import delay_groups
from torchdoct.measured.mapsfile import read_maps

DT = 0.2048


def _times(n, dtype=np.float64):
    return [float(v) for v in np.asarray([DT * i for i in range(n)], dtype=dtype)]


@pytest.mark.parametrize("offset_s", [0.0, 1000.0])
def test_frame_times_stored_in_single_precision_have_the_delays_and_ocds_of_the_exact_times(offset_s):
    exact = [offset_s + t for t in _times(32)]
    single = [float(np.float32(t)) for t in exact]
    assert single != exact
    got, want = delay_groups(single), delay_groups(exact)
    assert [len(ij) for _, ij in got] == [len(ij) for _, ij in want] == list(range(31, 0, -1))
    x = torch.rand(64, 32, generator=torch.Generator().manual_seed(0), dtype=torch.float64) + 0.1
    torch.testing.assert_close(td.ocds(x, single), td.ocds(x, exact), rtol=1e-4, atol=0)


def test_non_uniform_single_precision_times_group_their_delays_as_the_exact_times():
    exact = [0.0, 0.1, 0.2, 0.5, 0.6, 0.7, 1.0, 1.1, 1.2]  # three bursts of three frames
    single = [float(np.float32(t)) for t in exact]
    got, want = delay_groups(single), delay_groups(exact)
    assert [ij for _, ij in got] == [ij for _, ij in want]
    np.testing.assert_allclose([d for d, _ in got], [d for d, _ in want], rtol=1e-6)


def test_maps_of_a_sidecar_with_single_precision_frame_times_equal_those_of_exact_times(seq, tmp_path):
    from torchdoct.cli import main

    meta = json.loads(seq.with_suffix(".json").read_text())
    single = tmp_path / "single.npy"
    single.write_bytes(seq.read_bytes())
    meta["frame_times_s"] = [float(np.float32(t)) for t in meta["frame_times_s"]]
    single.with_suffix(".json").write_text(json.dumps(meta))
    out = {}
    for name, path in (("exact", seq), ("single", single)):
        assert (
            main(
                [
                    "maps",
                    str(path),
                    "--ocds-delay-range-s",
                    "0.2048",
                    "1.2288",
                    "--no-progress",
                    "--out",
                    str(tmp_path / f"{name}-maps.npz"),
                ]
            )
            == 0
        )
        out[name] = read_maps(tmp_path / f"{name}-maps.npz")
    assert out["single"].channels == out["exact"].channels
    np.testing.assert_allclose(out["single"].maps, out["exact"].maps, rtol=1e-4, atol=1e-6)


def test_timestamps_far_from_zero_in_double_precision_keep_their_distinct_delays():
    bursts = [0.0, 0.1, 0.2, 0.5, 0.6, 0.7, 1.0, 1.1, 1.2]
    epoch = [1.7e9 + t for t in bursts]  # seconds since 1970: double precision resolves them to a microsecond
    got, want = delay_groups(epoch), delay_groups(bursts)
    assert [ij for _, ij in got] == [ij for _, ij in want]
    np.testing.assert_allclose([d for d, _ in got], [d for d, _ in want], atol=1e-6)


def _scaled(scene, reflectivity):
    return scene.replace(
        populations=tuple(p.__class__(**{**p.__dict__, "reflectivity": reflectivity}) for p in scene.populations)
    )


def test_a_reflectivity_whose_intensity_underflows_float32_is_refused_naming_it_and_float64_gives_its_liv(small_scene):
    tiny = _scaled(small_scene, 1e-30)
    with pytest.raises(ValueError, match=r"population\[0\]\.reflectivity = 1e-30.*float32.*dtype='float64'") as info:
        td.simulate(tiny, trials=64, seed=1, dtype="float32")
    assert "truncation" not in str(info.value)  # the cause named is the intensity scale
    ref = td.simulate(small_scene, trials=64, seed=1, dtype="float64").metrics()
    got = td.simulate(tiny, trials=64, seed=1, dtype="float64").metrics()
    for name in ("liv", "ocds"):  # scale-free
        assert torch.isfinite(got[name]).all()
        torch.testing.assert_close(got[name], ref[name], rtol=1e-9, atol=1e-9)


def test_a_reflectivity_beyond_float64_is_refused_in_float64_without_offering_float64(small_scene):
    with pytest.raises(
        ValueError, match=r"population\[0\]\.reflectivity = 1e-160.*outside what float64 computes"
    ) as info:
        td.simulate(_scaled(small_scene, 1e-160), trials=64, seed=1, dtype="float64")
    assert "simulate in float64" not in str(info.value) and "relative to the brightest" in str(info.value)


def _moving(scene, speed):
    motion = td.RandomBallistic(speed_um_per_s=speed)
    return scene.replace(populations=(scene.populations[0].__class__(density_per_um3=0.055, motion=(motion,)),))


def test_a_motion_below_float32_resolution_is_refused_naming_it_and_runs_in_float64(small_scene):
    slow = _moving(small_scene, 1e-6)
    with pytest.raises(
        ValueError,
        match=r"population\[0\]\.motion\[0\]\.speed_um_per_s.*float32 spacings.*"
        r"rounding noise.*--dtype float64",
    ):
        td.simulate(slow, trials=64, seed=1, dtype="float32")
    ocds = td.simulate(slow, trials=64, seed=1, dtype="float64").metrics()["ocds"]
    assert ocds.abs().max() < 1e-6  # float64 resolves it: this slow a motion barely decorrelates
    noisy = slow.replace(noise=td.Noise(snr_db=30.0))  # the noise changes every frame far more: float32 holds it
    assert torch.isfinite(td.simulate(noisy, trials=64, seed=1, dtype="float32").metrics()["ocds"]).all()


def test_the_slowest_motion_of_the_training_prior_runs_in_float32(small_scene):
    from classifier.prior import Prior

    slowest = Prior().speed_um_per_s[0]
    assert torch.isfinite(
        td.simulate(_moving(small_scene, slowest), trials=64, seed=1, dtype="float32").metrics()["ocds"]
    ).all()


def test_maps_of_a_field_whose_intensity_underflows_name_the_cause_and_complex128_gives_the_same_liv(
    seq, tmp_path, capsys
):
    from _refusal import refused

    from torchdoct.cli import main

    field = np.load(seq)
    meta = seq.with_suffix(".json").read_text()
    runs = {}
    for name, data in (
        ("tiny", (field * 1e-30).astype(np.complex64)),
        ("tiny128", field.astype(np.complex128) * 1e-30),
    ):
        path = tmp_path / f"{name}.npy"
        np.save(path, data)
        path.with_suffix(".json").write_text(meta)
        runs[name] = path
    refused(
        capsys,
        tmp_path,
        ["maps", str(runs["tiny"]), "--metrics", "liv", "--out", str(tmp_path / "t.npz")],
        "tiny.npy",
        "underflows float32",
        "complex128",
        "multiply it by 1e+30",
        absent=("no finite nonzero", "check the file"),
    )
    for name, path in (("ref", seq), ("tiny128", runs["tiny128"])):
        assert (
            main(["maps", str(path), "--metrics", "liv", "--no-progress", "--out", str(tmp_path / f"{name}-m.npz")])
            == 0
        )
    ref, got = read_maps(tmp_path / "ref-m.npz"), read_maps(tmp_path / "tiny128-m.npz")
    np.testing.assert_allclose(got.maps, ref.maps, rtol=1e-4, atol=1e-4)


def test_render_of_a_phantom_whose_image_would_underflow_float32_is_refused_naming_the_file(tmp_path, capsys):
    import re

    from _refusal import refused

    from torchdoct.files import shipped_files

    text = shipped_files("torchdoct", "data/phantoms")["spheroid"].read_text()
    text = re.sub(r"reflectivity = [0-9.]+", "reflectivity = 1e-30", text)
    text = re.sub(
        r"density_per_um3 = ([0-9.e-]+)\n(?!reflectivity)", r"density_per_um3 = \1\nreflectivity = 1e-30\n", text
    )
    path = tmp_path / "dim.toml"
    path.write_text(text)
    refused(
        capsys,
        tmp_path,
        ["render", str(path), "--grid", "16x16", "--pitch-um", "2", "--no-progress", "--out", str(tmp_path / "r.npz")],
        "dim.toml",
        "reflectivity = 1e-30",
        "float32",
        "--dtype float64",
    )


def test_a_sweep_with_a_cell_below_float32_resolution_is_refused_before_any_cell_runs(tmp_path, capsys):
    from _refusal import refused
    from _scenes import DIFFUSION_SWEEP_TOML

    text = DIFFUSION_SWEEP_TOML.format(trials=8).replace("start = 0.001", "start = 1e-14")
    assert "1e-14" in text
    path = tmp_path / "slow.toml"
    path.write_text(text)
    refused(
        capsys,
        tmp_path,
        ["sweep", str(path), "--out", str(tmp_path / "out"), "--no-progress"],
        "slow.toml",
        "cell 0",
        "diffusion_um2_per_s",
        "float32 spacings",
        "--dtype float64",
    )

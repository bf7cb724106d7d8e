"""Silent nonsense and wrong verdicts of the sequence reader (issue classes 5 and 6): frame times given as
strings and a refractive index outside the scene files' [1, 5] are refused naming the field; a legal
255-character sequence name whose sidecar name would be too long is read, not refused."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from _refusal import refused

from torchdoct.measured.io import read_sequence


def _meta(n=12, **system):
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
            **system,
        },
    }


def _seq(tmp_path, meta, name="s.npy"):
    p = tmp_path / name
    np.save(p, (np.random.default_rng(0).standard_normal((12, 6, 5)) + 1j).astype(np.complex64))
    if meta is not None:
        p.with_suffix(".json").write_text(json.dumps(meta))
    return p


def test_frame_times_given_as_strings_are_refused_as_pitches_are(tmp_path, capsys):
    meta = _meta()
    meta["frame_times_s"] = [str(t) for t in meta["frame_times_s"]]
    seq = _seq(tmp_path, meta)
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
        "s.npy",
        "frame_times_s[0]",
        "number of seconds",
    )


@pytest.mark.parametrize("n", [1e6, 0.5, 5.01])
def test_a_refractive_index_outside_the_scene_files_range_is_refused(tmp_path, capsys, n):
    seq = _seq(tmp_path, _meta(refractive_index=n))
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
        "s.npy",
        "system.refractive_index",
        "[1, 5]",
    )


@pytest.mark.parametrize("n", [1.0, 1.38, 5.0])
def test_refractive_indices_inside_the_range_are_read(tmp_path, n):
    assert read_sequence(_seq(tmp_path, _meta(refractive_index=n))).meta["system"]["refractive_index"] == n


def test_a_255_character_name_whose_sidecar_name_is_too_long_is_read(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    name = "x" * (limit - 4) + ".npy"  # the longest legal name; its '.json' sidecar would be one longer
    seq = _seq(tmp_path, None, name)
    got = read_sequence(seq, axes="TZX", frame_interval_s=0.2048)
    assert got.data.shape == (12, 6, 5)


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_a_255_character_npy_or_npz_name_is_read_and_mapped(tmp_path, suffix):
    from torchdoct.cli import main

    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    seq = _seq(tmp_path, None, "x" * (limit - len(suffix)) + suffix) if suffix == ".npy" else None
    if seq is None:
        seq = tmp_path / ("x" * (limit - 4) + ".npz")
        np.savez(seq, data=(np.random.default_rng(0).standard_normal((12, 6, 5)) + 1j).astype(np.complex64))
    out = tmp_path / ("m" * (limit - 4) + ".npz")  # a 255-character output: its temporaries fit too
    assert (
        main(
            [
                "maps",
                str(seq),
                "--axes",
                "TZX",
                "--frame-interval-s",
                "0.2048",
                "--metrics",
                "liv",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_an_output_whose_derived_names_are_too_long_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    import torchdoct.measured.maps as maps_module

    def started(*args, **kwargs):
        raise AssertionError("the maps were computed before the output names were checked")

    monkeypatch.setattr(maps_module, "compute_maps", started)
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    seq = _seq(tmp_path, _meta())
    out = tmp_path / ("m" * (limit - 4) + ".npz")  # legal itself; its PNGs (STEM_liv_original.png) are not
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--metrics", "liv", "--png", "--out", str(out)],
        "longer than the file system allows",
        "give a shorter --out",
        absent=("Errno",),
    )

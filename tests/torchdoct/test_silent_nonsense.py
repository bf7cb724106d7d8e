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
    return {"axes": "TZX", "pitch_um": {"z": 2.0, "x": 2.0}, "frame_times_s": [0.2048 * i for i in range(n)],
            "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8,
                       "refractive_index": 1.0, **system}}


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
    refused(capsys, tmp_path, ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
            "s.npy", "frame_times_s[0]", "number of seconds")


@pytest.mark.parametrize("n", [1e6, 0.5, 5.01])
def test_a_refractive_index_outside_the_scene_files_range_is_refused(tmp_path, capsys, n):
    seq = _seq(tmp_path, _meta(refractive_index=n))
    refused(capsys, tmp_path, ["maps", str(seq), "--metrics", "liv", "--out", str(tmp_path / "m.npz")],
            "s.npy", "system.refractive_index", "[1, 5]")


@pytest.mark.parametrize("n", [1.0, 1.38, 5.0])
def test_refractive_indices_inside_the_range_are_read(tmp_path, n):
    assert read_sequence(_seq(tmp_path, _meta(refractive_index=n))).meta["system"]["refractive_index"] == n


def test_a_255_character_name_whose_sidecar_name_is_too_long_is_read(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    name = "x" * (limit - 4) + ".npy"  # the longest legal name; its '.json' sidecar would be one longer
    seq = _seq(tmp_path, None, name)
    got = read_sequence(seq, axes="TZX", frame_interval_s=0.2048)
    assert got.data.shape == (12, 6, 5)

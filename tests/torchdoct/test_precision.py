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
        assert main(["maps", str(path), "--ocds-delay-range-s", "0.2048", "1.2288", "--no-progress",
                     "--out", str(tmp_path / f"{name}-maps.npz")]) == 0
        out[name] = read_maps(tmp_path / f"{name}-maps.npz")
    assert out["single"].channels == out["exact"].channels
    np.testing.assert_allclose(out["single"].maps, out["exact"].maps, rtol=1e-4, atol=1e-6)


def test_timestamps_far_from_zero_in_double_precision_keep_their_distinct_delays():
    bursts = [0.0, 0.1, 0.2, 0.5, 0.6, 0.7, 1.0, 1.1, 1.2]
    epoch = [1.7e9 + t for t in bursts]  # seconds since 1970: double precision resolves them to a microsecond
    got, want = delay_groups(epoch), delay_groups(bursts)
    assert [ij for _, ij in got] == [ij for _, ij in want]
    np.testing.assert_allclose([d for d, _ in got], [d for d, _ in want], atol=1e-6)

"""``torchdoct bench stream`` (torchdoct.bench.stream) on a small input: one run per size in a fresh process,
its peak and baseline resident memory (Linux), the table and the figure; the docs render the recorded file."""

from __future__ import annotations

import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's")


@pytest.mark.slow
def test_bench_stream_records_peak_memory_per_input_size(tmp_path):
    from torchdoct.bench.stream import bench_stream, format_stream_table, plot_stream

    seen = []
    res = bench_stream((0.0156,), budget_gb=0.05, workdir=tmp_path, on_run=seen.append)  # 8 frames, 512 x 512
    [run] = res["runs"]
    assert [r["complete"] for r in seen] == [True] and seen[0]["runs"] == res["runs"]  # each size as it ends
    assert run["frames"] == 8 and run["shape"] == [8, 512, 512] and res["sizes_gib_asked"] == [0.0156]
    assert 0 < run["baseline_rss_bytes"] <= run["peak_rss_bytes"] and run["growth_bytes"] >= 0
    assert "peak RSS MiB" in format_stream_table(res)
    plot_stream(res, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.png"]  # the input went with its run

"""``torchdoct bench stream``: peak resident memory of ``torchdoct maps --max-memory-gb`` against the input's
size (measured, never asserted). Each input is a memory-mapped ``.npy`` complex64 sequence of 512 × 512
B-scans whose size grows with the number of frames (so the output maps, which the budget also holds, stay
the same), written sparse in a temporary folder: the first frame random, the others zero (a hole that costs
no disk). Each size runs ``torchdoct maps`` in a fresh process that records its resident memory after the
imports and its peak (``VmRSS`` / ``VmHWM`` of ``/proc/self/status``, Linux); the growth is the peak minus
that baseline."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from collections.abc import Sequence as _Seq
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.machine import machine_info

__all__ = ["bench_stream", "format_stream_table", "plot_stream"]

_PROBE = (
    "import json, sys\nimport torch, torchdoct.measured.maps\nfrom torchdoct.cli import main\n"
    "def st(k):\n    return next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith(k))\n"
    "b = st('VmRSS:')\nc = main(sys.argv[1:])\nprint(json.dumps([c, b, st('VmHWM:')]))\n"
)
_BSCAN = (512, 512)


def _write_input(folder: Path, frames: int) -> Path:
    path = folder / "s.npy"
    a = np.lib.format.open_memmap(path, mode="w+", dtype=np.complex64, shape=(frames, *_BSCAN))
    rng = np.random.default_rng(0)
    a[0] = (rng.standard_normal(_BSCAN) + 1j * rng.standard_normal(_BSCAN)).astype(np.complex64)
    a.flush()
    del a
    meta = {"axes": "TZX", "pitch_um": {"z": 1.5, "x": 2.0}, "frame_times_s": [k * 0.2048 for k in range(frames)]}
    path.with_suffix(".json").write_text(json.dumps(meta))
    return path


def bench_stream(
    sizes_gb: _Seq[float] = (1.0, 4.0, 16.0),
    budget_gb: float = 0.25,
    workdir: str | os.PathLike | None = None,
    on_run: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Peak resident growth of ``torchdoct maps --max-memory-gb budget_gb`` on inputs of ``sizes_gb`` GiB
    (module docstring); ``workdir``: where the inputs are written (default the system's temporary folder),
    each removed after its run. A folder without room for the largest (sparse) input is refused first.
    ``on_run(result)``: called after each size with the result so far (``complete`` false until the last), so
    that a long run stopped half-way keeps the sizes it finished."""
    frame_bytes = 8 * _BSCAN[0] * _BSCAN[1]
    base = Path(workdir) if workdir is not None else Path(tempfile.gettempdir())
    free = shutil.disk_usage(base).free
    if free < 64 * frame_bytes:
        raise ValueError(f"bench stream: {base} has {free} bytes free; give --workdir on a disk with room")
    runs = []
    for gb in sizes_gb:
        frames = max(8, int(round(gb * (1 << 30) / frame_bytes)))  # 8: OCDS's default delays on 2+ frame pairs
        with tempfile.TemporaryDirectory(dir=base) as d:
            path = _write_input(Path(d), frames)
            argv = [
                "maps",
                str(path),
                "--out",
                str(Path(d) / "m.npz"),
                "--no-progress",
                "--max-memory-gb",
                str(budget_gb),
            ]
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True)
            seconds = time.perf_counter() - t0
            if out.returncode != 0:
                raise RuntimeError(f"bench stream: torchdoct maps failed on {gb} GiB: {out.stderr.strip()[-400:]}")
            code, rss0, peak = json.loads(out.stdout.strip().splitlines()[-1])
        runs.append(
            {
                "input_gib": frames * frame_bytes / (1 << 30),
                "frames": frames,
                "shape": [frames, *_BSCAN],
                "baseline_rss_bytes": rss0,
                "peak_rss_bytes": peak,
                "growth_bytes": peak - rss0,
                "seconds": seconds,
            }
        )
        if on_run is not None:
            on_run(_result(budget_gb, sizes_gb, runs, complete=len(runs) == len(sizes_gb)))
    return _result(budget_gb, sizes_gb, runs, complete=True)


def _result(budget_gb: float, sizes_gb: _Seq[float], runs: list[dict[str, Any]], complete: bool) -> dict[str, Any]:
    return {
        "benchmark": "stream",
        "command": "torchdoct maps INPUT.npy --max-memory-gb BUDGET",
        "budget_gib": budget_gb,
        "sizes_gib_asked": [float(g) for g in sizes_gb],
        "complete": complete,
        "bscan": list(_BSCAN),
        "runs": list(runs),
        "machine": machine_info(),
    }


def format_stream_table(res: dict[str, Any]) -> str:
    lines = [
        f"torchdoct maps --max-memory-gb {res['budget_gib']:g} on memory-mapped complex64 inputs:",
        f"{'input GiB':>10}  {'frames':>7}  {'peak RSS MiB':>12}  {'growth MiB':>10}  {'s':>7}",
    ]
    for r in res["runs"]:
        lines.append(
            f"{r['input_gib']:10.3g}  {r['frames']:7d}  {r['peak_rss_bytes'] / 2**20:12.0f}  "
            f"{r['growth_bytes'] / 2**20:10.0f}  {r['seconds']:7.1f}"
        )
    return "\n".join(lines)


def plot_stream(res: dict[str, Any], path: str | os.PathLike) -> None:
    """Peak RSS and its growth (MiB) against the input size (GiB), with the budget as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["input_gib"] for r in res["runs"]]
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.plot(x, [r["peak_rss_bytes"] / 2**20 for r in res["runs"]], "o-", color="#0072B2", label="peak RSS")
    ax.plot(x, [r["growth_bytes"] / 2**20 for r in res["runs"]], "s-", color="#E69F00", label="growth over the imports")
    ax.plot(x, x and [v * 1024 for v in x], ":", color="#999999", label="input size")
    ax.axhline(res["budget_gib"] * 1024, color="#009E73", ls="--", label="--max-memory-gb")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("input size (GiB)")
    ax.set_ylabel("memory (MiB)")
    ax.legend(fontsize=8)
    ax.set_title("torchdoct maps, streamed: peak memory against input size", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""Crash safety: a sweep killed mid-run and restarted recomputes only unfinished cells and writes the
same table as an uninterrupted run; no output file is ever left half-written under its final name."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from _scenes import DIFFUSION_SWEEP_TOML


def _cmd(scene: Path, out: Path, cache: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "torchdoct.cli",
        "sweep",
        str(scene),
        "--out",
        str(out),
        "--cache",
        str(cache),
        "--workers",
        "1",
        "--batch-cells",
        "1",
        "--no-progress",
    ]


def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.mark.slow
def test_killed_sweep_resumes_to_the_same_table(tmp_path):
    scene = tmp_path / "sweep.toml"
    scene.write_text(DIFFUSION_SWEEP_TOML.format(trials=256), encoding="utf-8")
    ref = subprocess.run(
        _cmd(scene, tmp_path / "ref", tmp_path / "ref-cache"), env=_env(), capture_output=True, text=True, timeout=600
    )
    assert ref.returncode == 0, ref.stderr
    cache = tmp_path / "cache"
    out = tmp_path / "out"
    proc = subprocess.Popen(
        _cmd(scene, out, cache),
        env=_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.time() + 300
    while time.time() < deadline and len(list(cache.glob("[!.]*.npz"))) < 4:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = {p.name: p.stat().st_mtime_ns for p in cache.glob("[!.]*.npz")}
    assert 4 <= len(done_before) < 16, "the kill must land mid-run"
    assert not (out / "results.csv").exists() and not (out / "results.parquet").exists()
    again = subprocess.run(_cmd(scene, out, cache), env=_env(), capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    # finished cells were not recomputed: their cache files are untouched
    for name, mtime in done_before.items():
        assert (cache / name).stat().st_mtime_ns == mtime
    cols = ["cell", "system", "metric", "mean", "sd", "se", "trials", "seed"]
    a = pd.read_csv(tmp_path / "ref" / "results.csv")
    b = pd.read_csv(out / "results.csv")
    keep = [c for c in cols if c in a.columns]
    assert len(keep) >= 5
    pd.testing.assert_frame_equal(a[keep].reset_index(drop=True), b[keep].reset_index(drop=True))

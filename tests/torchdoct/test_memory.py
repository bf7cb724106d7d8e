"""Memory stays bounded: the chunked simulator's peak RSS does not grow with the number of trials."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

_SCRIPT = r"""
import json, resource, sys
import torchdoct as td
from torchdoct.bench import paper_motions, paper_systems
system = paper_systems()[3]                      # 840 nm, lateral 18 µm: the largest PSF volume
motion = paper_motions()[sys.argv[1]]
scene = td.Scene(systems=(system,), protocol=td.Protocol(n_frames=32, frame_interval_s=0.2048),
                 populations=(td.Population(density_per_um3=0.055, motion=(motion,)),))
res = td.simulate(scene, trials=int(sys.argv[2]), seed=1, threads=2)  # chunks in flight = threads
# VmHWM: the peak of this process's own address space. ru_maxrss is not: Linux folds the RSS of the
# address space exec replaced (the parent's, at the fork) into it, so under a large test runner it
# reports the runner's size.
try:
    with open("/proc/self/status") as f:
        peak_kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
except (OSError, StopIteration):
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"maxrss_kb": peak_kb, "finite": bool(res.signals.isfinite().all())}))
"""


def _peak_rss_gb(motion: str, trials: int) -> float:
    env = dict(os.environ, MALLOC_ARENA_MAX="2")  # less allocator fragmentation noise
    out = subprocess.run(
        [sys.executable, "-c", _SCRIPT, motion, str(trials)], capture_output=True, text=True, check=True, env=env
    )
    info = json.loads(out.stdout.strip().splitlines()[-1])
    assert info["finite"]
    return info["maxrss_kb"] / 2**20


@pytest.mark.slow
@pytest.mark.parametrize("motion", ["diffusion D=15", "ballistic v=6", "flow v=6 (45°)"])
def test_peak_memory_bounded_and_independent_of_trials(motion):
    """Largest paper cells: peak RSS under 4 GB, and 4x the trials does not grow it with the trials.

    Two threads (two chunks in flight), whatever the machine's cores: the default gives every core a
    chunk, so the peak of a default run grows with the cores, not with the trials.

    Memory that scaled with the trials (no chunking) would add several GB; allocator noise is
    ~0.3 GB.
    """
    small = _peak_rss_gb(motion, 1024)
    large = _peak_rss_gb(motion, 4096)
    assert large < 4.0, large
    assert large - small < 0.5, (small, large)

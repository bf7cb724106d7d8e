"""``torchdoct bench cog``: torchdoct against the COG point simulator, cell by cell, on one core.

The COG DOCT simulation library (``doctSimulator.py``, ComputationalOpticsGroup on GitHub) simulates
one pixel with NumPy: ``scattererPositions`` + ``complexOctPixel``, one frame at a time, as in its
``example_point.py``. The user points ``--cog`` at a clone of it; nothing of it ships with torchdoct.
Its module imports CuPy at the top although the point simulator uses only NumPy, so where CuPy is
not installed the benchmark imports it with empty stand-ins for ``cupy``/``cupyx``.

Both run the paper's 12 cells (:func:`torchdoct.bench.paper_systems` × :func:`paper_motions`:
0.055 µm⁻³, 32 frames at 204.8 ms) on one thread, and the benchmark reports the CPU time per trial of
each and their ratio (best of ``repeats``). COG's own domain (PSF box plus the largest
displacement) holds 6,000-50,000 scatterers per trial; torchdoct's plan draws only those that can
come within the truncation tolerance, which is most of the difference.
"""

from __future__ import annotations

import importlib.util
import math
import sys
import time
import types
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

from ..runtime.machine import machine_info
from ..sim.config import Diffusion, Flow, Population, Protocol, RandomBallistic, Scene
from ..sim.simulate import simulate
from . import paper_motions, paper_systems

__all__ = ["load_cog", "bench_cog", "format_cog_table"]

_FRAMES, _DT = 32, 0.2048


def load_cog(directory: str | Path):
    """The ``doctSimulator`` module of a COG clone at ``directory`` (ValueError naming the fix if absent)."""
    path = Path(directory).expanduser() / "doctSimulator.py"
    if not path.is_file():
        raise ValueError(
            f"--cog {directory}: no doctSimulator.py there; clone the COG DOCT simulation library "
            "(github.com/ComputationalOpticsGroup/COG-dynamic-OCT-contrast-simulation-library) and "
            "pass its folder"
        )
    stubs = {}
    for name in ("cupy", "cupyx"):
        if importlib.util.find_spec(name) is None:
            stubs[name] = sys.modules[name] = types.ModuleType(name)
    try:
        spec = importlib.util.spec_from_file_location("doctSimulator", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        for name in stubs:
            sys.modules.pop(name, None)
    return module


def _cog_motion(motion) -> tuple[str, Any]:
    """COG's motion name and parameter (SI units) for a torchdoct motion."""
    import numpy as np

    if isinstance(motion, Diffusion):
        return "diffusion", np.array([motion.diffusion_um2_per_s * 1e-12])
    if isinstance(motion, RandomBallistic):
        return "randomBallistic", motion.speed_um_per_s * 1e-6
    if isinstance(motion, Flow):
        return "flow", [
            motion.speed_um_per_s * 1e-6,
            math.radians(motion.polar_angle_deg),
            math.radians(motion.azimuth_deg),
        ]
    raise ValueError(f"no COG equivalent of {motion!r}")


def _cog_trial(dos, system, motion) -> int:
    """One COG point-simulator trial of 32 frames; returns its number of scatterers."""
    import numpy as np

    res = np.array([system.lateral_resolution_um, system.lateral_resolution_um, system.axial_resolution_um]) * 1e-6
    n0d = dos.numerical0dParameters(_DT * _FRAMES, res, system.wavelength_um * 1e-6)
    name, param = _cog_motion(motion)
    sp = dos.scattererPositions(0.055e18, n0d, name, param)
    sp.velocitiesSet()
    px = dos.complexOctPixel(n0d)
    for _ in range(_FRAMES):
        sp.positionsUpdate(_DT)
        px.generate(sp)
    return int(sp.numScatter)


def bench_cog(
    cog: str | Path, *, cog_trials: int = 10, trials: int = 1024, repeats: int = 3, progress: bool = False
) -> dict[str, Any]:
    """CPU time per trial of COG and torchdoct on the 12 paper cells, one thread each."""
    dos = load_cog(cog)
    cells = [(s, m) for m in paper_motions().items() for s in paper_systems()]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(cells), desc="bench cog", unit="cell")
    rows = []
    protocol = Protocol(n_frames=_FRAMES, frame_interval_s=_DT)
    with threadpool_limits(1):
        for system, (mname, motion) in cells:
            scene = Scene(
                systems=(system,), protocol=protocol, populations=(Population(density_per_um3=0.055, motion=(motion,)),)
            )
            _cog_trial(dos, system, motion)
            simulate(scene, trials=64, seed=1, threads=1)  # warm-up
            cog_s, ours_s, n_cog = math.inf, math.inf, 0
            for r in range(repeats):
                c0 = time.process_time()
                for _ in range(cog_trials):
                    n_cog = _cog_trial(dos, system, motion)
                cog_s = min(cog_s, (time.process_time() - c0) / cog_trials)
                c0 = time.process_time()
                res = simulate(scene, trials=trials, seed=2 + r, threads=1)
                ours_s = min(ours_s, (time.process_time() - c0) / trials)
            rows.append(
                {
                    "system": system.name,
                    "motion": mname,
                    "cog_ms_per_trial": 1e3 * cog_s,
                    "cog_scatterers": n_cog,
                    "torchdoct_ms_per_trial": 1e3 * ours_s,
                    "torchdoct_scatterers": res.plan.expected_scatterers_per_trial,
                    "ratio": cog_s / ours_s,
                }
            )
            if bar is not None:
                bar.update()
    if bar is not None:
        bar.close()
    ratios = [r["ratio"] for r in rows]
    from ..sim import kernel

    return {
        "benchmark": "cog",
        "cog_trials": cog_trials,
        "trials": trials,
        "repeats": repeats,
        "cells": rows,
        "geometric_mean_ratio": math.exp(sum(math.log(x) for x in ratios) / len(ratios)),
        "kernel": kernel.backend(),
        "machine": machine_info(),
    }


def format_cog_table(res: dict[str, Any]) -> str:
    lines = [
        "| system | motion | COG ms/trial (scatterers) | torchdoct ms/trial (scatterers) | COG ÷ torchdoct |",
        "|---|---|---:|---:|---:|",
    ]
    for r in res["cells"]:
        lines.append(
            f"| {r['system']} | {r['motion']} | {r['cog_ms_per_trial']:.2f} ({r['cog_scatterers']}) | "
            f"{r['torchdoct_ms_per_trial']:.3f} ({r['torchdoct_scatterers']:.0f}) | {r['ratio']:.0f}× |"
        )
    lines.append(
        f"\ngeometric mean {res['geometric_mean_ratio']:.0f}× (one thread each, CPU time, best of "
        f"{res['repeats']}; torchdoct kernel: {res['kernel']})"
    )
    return "\n".join(lines)

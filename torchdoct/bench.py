"""Benchmarks (``torchdoct bench ...``): measured throughput, reported, never asserted.

``bench_simulate`` times the paper's four systems × three motions at their largest parameters
(D = 15 µm²/s; v = 6 µm/s random ballistic and 45° flow; 0.055 µm⁻³, 32 frames at 204.8 ms),
one single-system scene per cell, and reports scatterers per trial, trials/s and scatterer-frame
evaluations/s.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import torch

from .config import Diffusion, Flow, OCTSystem, Population, Protocol, RandomBallistic, Scene
from .plan import make_plan
from .simulate import simulate

__all__ = ["paper_systems", "paper_motions", "bench_simulate", "machine_info", "format_simulate_table", "write_json"]


def paper_systems() -> list[OCTSystem]:
    """The reference paper's four system configurations (n = 1)."""
    return [
        OCTSystem(name="840nm-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8),
        OCTSystem(name="1310nm-high", wavelength_um=1.31, lateral_resolution_um=4.9, axial_resolution_um=3.8),
        OCTSystem(name="840nm-axial14", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=14.0),
        OCTSystem(name="840nm-lateral18", wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8),
    ]


def paper_motions() -> dict[str, Any]:
    """The paper's three motion models at their largest parameters."""
    return {
        "diffusion D=15": Diffusion(diffusion_um2_per_s=15.0),
        "ballistic v=6": RandomBallistic(speed_um_per_s=6.0, directions="uniform-angles"),
        "flow v=6 (45°)": Flow(speed_um_per_s=6.0, polar_angle_deg=45.0),
    }


def machine_info() -> dict[str, Any]:
    return {
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
    }


def bench_simulate(*, trials: int = 1024, dtype: str = "float32", repeats: int = 1,
                   progress: bool = False) -> dict[str, Any]:
    """Time the 12 paper cells; returns a JSON-ready dict (see the module docstring)."""
    protocol = Protocol(n_frames=32, frame_interval_s=0.2048)
    rows = []
    cells = [(s, m) for m in paper_motions().items() for s in paper_systems()]
    it = cells
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(cells, desc="bench simulate", unit="cell")
    for system, (mname, motion) in it:
        scene = Scene(systems=(system,), protocol=protocol,
                      populations=(Population(density_per_um3=0.055, motion=(motion,)),),
                      name=f"{system.name} {mname}")
        plan = make_plan(scene)
        simulate(scene, trials=64, seed=1, dtype=dtype)  # warm-up
        best = float("inf")
        for r in range(repeats):
            t0 = time.perf_counter()
            res = simulate(scene, trials=trials, seed=2 + r, dtype=dtype)
            best = min(best, time.perf_counter() - t0)
        rows.append({
            "system": system.name,
            "motion": mname,
            "scatterers_per_trial": plan.expected_scatterers_per_trial,
            "evaluations_per_trial": plan.evaluations_per_trial,
            "seconds": best,
            "ms_per_trial": 1e3 * best / trials,
            "trials_per_s": trials / best,
            "evaluations_per_s": plan.evaluations_per_trial * trials / best,
            "finite": bool(torch.isfinite(res.signals.real).all()),
        })
    mean_ms = sum(r["ms_per_trial"] for r in rows) / len(rows)
    return {
        "benchmark": "simulate",
        "trials_per_cell": trials,
        "dtype": dtype,
        "repeats": repeats,
        "machine": machine_info(),
        "cells": rows,
        "mean_ms_per_trial": mean_ms,
        "target_ms_per_trial": 0.3,
        "paper_study_trials": 186_000,
        "paper_study_estimate_s": mean_ms * 1e-3 * 186_000,
    }


def format_simulate_table(result: dict[str, Any]) -> str:
    lines = ["| system | motion | scatterers/trial | ms/trial | trials/s | evaluations/s |",
             "|---|---|---:|---:|---:|---:|"]
    for r in result["cells"]:
        lines.append(f"| {r['system']} | {r['motion']} | {r['scatterers_per_trial']:.0f} | "
                     f"{r['ms_per_trial']:.3f} | {r['trials_per_s']:.0f} | {r['evaluations_per_s']:.3g} |")
    m = result["machine"]
    lines.append("")
    lines.append(f"mean {result['mean_ms_per_trial']:.3f} ms/trial over {len(result['cells'])} cells "
                 f"(target {result['target_ms_per_trial']} ms); paper study (~186,000 trials) "
                 f"≈ {result['paper_study_estimate_s']:.0f} s; {result['trials_per_cell']} trials/cell, "
                 f"{result['dtype']}, {m['cpu_count']} cores, torch {m['torch']} with {m['torch_threads']} threads")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: str | Path) -> None:
    Path(path).write_text(json.dumps(result, indent=2))


def bench_render(*, phantom: str = "spheroid", repeats: int = 3, dtype: str = "float32") -> dict[str, Any]:
    """Time :func:`torchdoct.render.render` on a shipped phantom (best of ``repeats``).

    Reports the wall time, pixel-frames per second and the scatterer evaluations of the run.
    """
    from .phantom import load_phantom
    from .render import render

    ph = load_phantom(phantom)
    times = []
    res = None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = render(ph, dtype=dtype)
        times.append(time.perf_counter() - t0)
    best = min(times)
    shape = tuple(res.data.shape)
    pixel_frames = shape[1] * int(torch.tensor(shape[2:]).prod()) * shape[0]
    return {
        "benchmark": "render",
        "phantom": phantom,
        "shape_STZX": list(shape),
        "pitch_um": ph.grid.pitch_um,
        "dtype": dtype,
        "wall_s_best": best,
        "wall_s_all": times,
        "pixel_frames_per_s": pixel_frames / best,
        "populations": res.work["populations"],
        "stages": res.work["stages"],
        "target_s": 20.0,
        "machine": machine_info(),
    }

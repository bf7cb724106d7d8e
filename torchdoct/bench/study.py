"""The study benchmark (``torchdoct bench study``): wall time of a whole study from an empty cache,
tables, figures and report included (:func:`bench_study`), and optionally the cost of one cell with
all systems in one scene against the comparisons' pairs (the choice of ``grouping``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from ..runtime.machine import machine_info
from ..study.run import run_study
from ..study.spec import Study, load_study
from ..study.sweeps import study_sweeps

__all__ = ["bench_study", "format_bench_study"]


def _grouping_cells(study: Study, trials: int) -> list[dict[str, Any]]:
    """ms per cell of one motion value with all systems in one scene vs the comparisons' pairs."""
    from ..sim.simulate import simulate

    rows = []
    for pname in study.figure_parts:
        part = study.part(pname)
        pos = [v for v in part.values if v > 0]
        for v in sorted({pos[0], pos[len(pos) // 2], pos[-1]}):
            t = {}
            for grouping in ("all", "pairs"):
                s = Study(
                    **{
                        **study.__dict__,
                        "grouping": grouping,
                        "parts": (part,),
                        "figure_parts": (part.name,),
                        "direction_parts": (),
                    }
                )
                total = 0.0
                for sw in study_sweeps(s):
                    cell = next(c for c in sw.cells if c.values["value"] == v)
                    simulate(cell.scene, trials=64, seed=1, dtype=study.dtype)  # warm-up
                    t0 = time.perf_counter()
                    simulate(cell.scene, trials=trials, seed=2, dtype=study.dtype)
                    total += time.perf_counter() - t0
                t[grouping] = total
            rows.append(
                {
                    "part": pname,
                    "value": v,
                    "trials": trials,
                    "all_s": t["all"],
                    "pairs_s": t["pairs"],
                    "all_ms_per_trial": 1e3 * t["all"] / trials,
                    "pairs_ms_per_trial": 1e3 * t["pairs"] / trials,
                }
            )
    return rows


def bench_study(
    study: str | os.PathLike = "paper-reduced",
    *,
    trials: int | None = None,
    groupings: bool = False,
    grouping_trials: int = 128,
    study_out: str | os.PathLike | None = None,
    force: bool = False,
    workers: int = 1,
    progress: bool = False,
) -> dict[str, Any]:
    """Wall time of a whole study from an empty cache (tables, figures, report included) as JSON-ready data.

    ``study_out``: keep the study's outputs and cell cache there (default: a temporary directory, no
    cache); a later ``torchdoct study`` with ``--out`` study_out reuses the cells. ``groupings``: also
    time one cell per part at three motion values with all systems in one scene and as the comparisons'
    pairs (the choice of ``grouping``).
    """
    import tempfile

    import torch

    st = load_study(study)
    out: dict[str, Any] = {
        "benchmark": "study",
        "study": st.name,
        "machine": machine_info(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
    }
    cache = None
    if study_out is not None:  # keep the cells too, so that ``torchdoct study`` on study_out resumes from them
        cache = Path(study_out) / "cache"
        if cache.is_dir() and any(cache.glob("*.npz")):
            raise ValueError(
                f"--study-out: {cache} holds cached cells; the benchmark times a run from an empty "
                "cache: give a new directory"
            )
    with tempfile.TemporaryDirectory(prefix="torchdoct-bench-study-") as tmp:
        t0 = time.perf_counter()
        r = run_study(
            st,
            study_out if study_out is not None else Path(tmp) / "out",
            trials=trials,
            cache_dir=cache,
            force=force,
            workers=workers,
            progress=progress,
        )
        wall = time.perf_counter() - t0
    per_part: dict[str, float] = {}
    for c in r.sweep_result.cells:
        per_part[c.cell.sweep.split("/")[0]] = per_part.get(c.cell.sweep.split("/")[0], 0.0) + c.elapsed_s
    out.update(
        {
            "grouping": r.study.grouping,
            "trials_per_point": r.study.trials,
            "cells": len(r.sweep_result.cells),
            "motion_values": sum(len(p.values) for p in r.study.parts),
            "system_trials": r.sweep_result.system_trials,
            "wall_s": wall,
            "simulate_s": r.timings["simulate_s"],
            "figures_s": r.timings["figures_s"],
            "ms_per_system_trial": 1e3 * r.timings["simulate_s"] / r.sweep_result.system_trials,
            "simulate_s_per_part": per_part,
            "target_s_full_paper_study": 60.0,
            "workers": workers,
            "torch_threads": torch.get_num_threads(),
        }
    )
    if groupings:
        out["groupings"] = _grouping_cells(st, grouping_trials)
    return out


def format_bench_study(res: dict[str, Any]) -> str:
    lines = [
        f"study {res['study']}: {res['cells']} cells ({res['motion_values']} motion values, grouping "
        f"{res['grouping']}), {res['trials_per_point']} trials per point, {res['system_trials']} system-trials",
        f"wall time {res['wall_s']:.1f} s (simulation {res['simulate_s']:.1f} s, figures {res['figures_s']:.1f} s); "
        f"{res['ms_per_system_trial']:.3f} ms per system-trial (wall); {res['workers']} cells side by side"
        + " with one torch thread each",
        "cell time per part (summed over workers): "
        + ", ".join(f"{k} {v:.1f} s" for k, v in res["simulate_s_per_part"].items()),
    ]
    if "groupings" in res:
        lines += [
            "",
            "| part | value | all systems in one scene (ms/trial) | comparisons' pairs (ms/trial) |",
            "|---|---:|---:|---:|",
        ]
        for g in res["groupings"]:
            lines.append(
                f"| {g['part']} | {g['value']:g} | {g['all_ms_per_trial']:.2f} | {g['pairs_ms_per_trial']:.2f} |"
            )
        a = sum(g["all_s"] for g in res["groupings"])
        p = sum(g["pairs_s"] for g in res["groupings"])
        lines.append(f"\ntotal over these cells: all {a:.2f} s, pairs {p:.2f} s (pairs/all = {p / a:.2f})")
    return "\n".join(lines)

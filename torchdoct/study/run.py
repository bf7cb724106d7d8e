"""Running a study: :func:`run_study` builds its sweeps, runs them (cached, resumable, locally or on
Dask), and writes the files :func:`study_outputs` lists (described in :mod:`torchdoct.study`): the
tables, the paired differences, the figures, the claims report and ``study.json``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..files import atomic_write, output_set
from ..runtime.interrupt import progress_disabled
from .claims import claims_report
from .figures import _save_figure, plot_comparison, plot_directions
from .spec import Study, load_study
from .stats import direction_differences, paired_differences
from .sweep import SweepResult, check_cache_dir, check_sweep_resources, prepare_out_dir, run_sweeps, write_table
from .sweeps import study_sweeps

__all__ = ["StudyResult", "study_outputs", "run_study"]


def study_outputs(study: Study, out_dir: str | os.PathLike) -> list[Path]:
    """Every file :func:`run_study` writes into ``out_dir``."""
    d = Path(out_dir)
    files = [d / "results.csv", d / "results.parquet", d / "differences.csv", d / "differences.parquet"]
    if study.direction_parts:
        files += [d / "directions.csv", d / "directions.parquet"]
    for c in study.comparisons:
        files += [d / f"{c.figure}.png", d / f"{c.figure}.svg"]
    if study.direction_parts:
        files += [d / "fig-directions.png", d / "fig-directions.svg"]
    files += [d / "claims.md", d / "study.json"]
    return files


@dataclass
class StudyResult:
    """What :func:`run_study` produced."""

    study: Study
    sweep_result: SweepResult
    table: Any
    differences: Any
    directions: Any
    report: str
    files: list[Path]
    timings: dict[str, float]


def run_study(
    study: Study | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    trials: int | None = None,
    seed: int | None = None,
    cache_dir: str | os.PathLike | None = "default",
    scheduler: str | None = None,
    batch_cells: int = 1,
    workers: int = 1,
    force: bool = False,
    progress: bool = False,
) -> StudyResult:
    """Run a study and write its table, differences, figures, claims report and ``study.json``.

    ``cache_dir``: ``"default"`` is ``out_dir/cache``; ``None`` disables the cache. ``trials``/``seed``
    override the study's. Every output file is checked before any simulation: an existing one is an
    error unless ``force``. A rerun reuses the cached cells.
    """
    from .. import __version__

    if not isinstance(study, Study):
        study = load_study(study)
    if trials is not None or seed is not None:
        study = Study(
            **{
                **study.__dict__,
                "trials": trials if trials is not None else study.trials,
                "seed": seed if seed is not None else study.seed,
            }
        )
    files = study_outputs(study, out_dir)
    check_cache_dir(None if cache_dir == "default" else cache_dir)
    if cache_dir == "default":
        cache_dir = Path(out_dir) / "cache"
    sweeps = study_sweeps(study)
    check_sweep_resources(
        sweeps, cache_dir=cache_dir, scheduler=scheduler, batch_cells=batch_cells, workers=workers
    )  # memory and disk, before the output folder is made
    out = prepare_out_dir(out_dir, files, force)
    t0 = time.perf_counter()
    res = run_sweeps(
        sweeps,
        cache_dir=cache_dir,
        scheduler=scheduler,
        batch_cells=batch_cells,
        workers=workers,
        progress=progress,
        desc=f"study {study.name}",
    )
    t_sim = time.perf_counter() - t0
    table = res.table()
    diffs = paired_differences(study, res)
    dirs = direction_differences(study, res)
    with output_set(files, force) as stage:  # every file appears at once, or none (an error, Ctrl-C, SIGTERM)
        at = stage(out / "results.csv").parent
        write_table(table, at / "results", force=force)
        write_table(diffs, at / "differences", force=force)
        if study.direction_parts:
            write_table(dirs, at / "directions", force=force)
        t1 = time.perf_counter()
        from tqdm.auto import tqdm

        # the figures take a while for the paper study (torchdoct bench study): a bar per figure and the report
        bar = tqdm(
            total=len(study.comparisons) + bool(study.direction_parts) + 1,
            unit="step",
            leave=False,
            desc=f"study {study.name}: figures and claims report",
            disable=progress_disabled(progress),
        )
        for c in study.comparisons:
            _save_figure(plot_comparison(study, c, diffs), at / c.figure, force)
            bar.update(1)
        if study.direction_parts:
            _save_figure(plot_directions(study, dirs), at / "fig-directions", force)
            bar.update(1)
        t_fig = time.perf_counter() - t1
        timings = {"simulate_s": t_sim, "figures_s": t_fig}
        runtime = {
            "cells": len(res.cells),
            "computed": res.computed,
            "cached": res.cached,
            "system_trials": res.system_trials,
            "simulate_s": t_sim,
            "total_s": time.perf_counter() - t0,
            "version": __version__,
        }
        report = claims_report(study, res, diffs, dirs, runtime=runtime)
        atomic_write(at / "claims.md", lambda tmp: Path(tmp).write_text(report, encoding="utf-8"))
        bar.update(1)
        bar.close()
        timings["total_s"] = time.perf_counter() - t0
        record = {
            "torchdoct_version": __version__,
            "study": study.to_dict(),
            "timings_s": timings,
            "cells": [
                {
                    "sweep": c.cell.sweep,
                    "cell": c.cell.index,
                    "value": c.cell.values["value"],
                    "seed": c.seed,
                    "trials": c.trials,
                    "dtype": c.dtype,
                    "cache_key": c.cache_key,
                    "cached": c.cached,
                    "elapsed_s": c.elapsed_s,
                }
                for c in res.cells
            ],
            "computed": res.computed,
            "cached": res.cached,
            "system_trials": res.system_trials,
        }
        atomic_write(
            at / "study.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=2), encoding="utf-8")
        )
    written = files
    return StudyResult(
        study=study,
        sweep_result=res,
        table=table,
        differences=diffs,
        directions=dirs,
        report=report,
        files=written,
        timings=timings,
    )

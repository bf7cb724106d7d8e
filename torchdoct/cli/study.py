"""Command line: ``torchdoct sweep`` and ``torchdoct study`` (its benchmark: :mod:`torchdoct.cli.bench`).

Entries of the command table of :mod:`torchdoct.cli` (:data:`COMMANDS`). Each handler parses, calls one library
function (:mod:`torchdoct.study.sweep`, :mod:`torchdoct.study`) and prints.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .command import Command, workers

__all__ = ["COMMANDS"]


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="output directory (created if its parent exists)")
    p.add_argument("--trials", type=int, default=None, help="trials per cell (default: the file's)")
    p.add_argument("--seed", type=int, default=None, help="base seed; each cell derives its own (default: the file's)")
    p.add_argument(
        "--cache", default=None, help="cache directory of finished cells (default: OUT/cache); reruns resume from it"
    )
    p.add_argument("--no-cache", action="store_true", help="do not read or write the cell cache")
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the cells on an existing Dask distributed cluster (e.g. tcp://host:8786)",
    )
    p.add_argument("--batch-cells", type=int, default=1, help="cells per task (results do not depend on it)")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="cells computed side by side, one torch thread each (default: --threads, else the usable "
        "cores; 1 runs one cell at a time on one core)",
    )
    p.add_argument("--force", action="store_true", help="overwrite output files that exist")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--max-cells",
        type=int,
        default=None,
        metavar="N",
        help="run sweeps of more cells than the cap (default 10000; every cell is built before the first runs)",
    )


def _sweep_arguments(sw) -> None:
    sw.add_argument("scene", help="TOML scene file with a [sweep] table")
    _add_run_options(sw)
    sw.add_argument("--dtype", choices=("float32", "float64"), default=None)
    sw.add_argument("--tolerance", type=float, default=None, help="PSF truncation tolerance (amplitude)")


def _study_arguments(st) -> None:
    st.add_argument("study", help="study TOML file or shipped study name (paper, paper-reduced)")
    _add_run_options(st)


def _cache(args) -> object:
    if args.no_cache:
        return None
    return args.cache if args.cache is not None else Path(args.out) / "cache"


def _sweep(args) -> int:
    from ..study.grid import set_max_cells
    from ..study.sweep import (
        check_cache_dir,
        format_table,
        load_sweep,
        prepare_out_dir,
        run_sweep,
        sweep_outputs,
        write_sweep_outputs,
    )

    set_max_cells(args.max_cells)
    sweep = load_sweep(args.scene)
    check_cache_dir(_cache(args))  # a file there: refused before the output folder is made
    from ..study.sweep import check_sweep_resources

    try:
        check_sweep_resources(
            [sweep],
            trials=args.trials,
            seed=args.seed,
            dtype=args.dtype,
            tolerance=args.tolerance,
            cache_dir=_cache(args),
            scheduler=args.scheduler,
            batch_cells=args.batch_cells,
            workers=workers(args),
        )  # precision, memory and disk, before the output folder is made
    except ValueError as err:
        raise ValueError(f"{args.scene}: {err}") from None
    prepare_out_dir(args.out, sweep_outputs(args.out), args.force)
    res = run_sweep(
        sweep,
        trials=args.trials,
        seed=args.seed,
        dtype=args.dtype,
        tolerance=args.tolerance,
        cache_dir=_cache(args),
        scheduler=args.scheduler,
        batch_cells=args.batch_cells,
        workers=workers(args),
        progress=not args.no_progress,
        desc=f"sweep {sweep.name}",
    )
    files = write_sweep_outputs(res, args.out, force=args.force)
    print(
        f"sweep {sweep.name!r}: {len(res.cells)} cells ({res.computed} computed, {res.cached} from the cache), "
        f"{res.system_trials} system-trials, {res.elapsed_s:.1f} s"
    )
    print(format_table(res.table()))
    for f in files:
        print(f"wrote {f}")
    return 0


def _study(args) -> int:
    from ..study import run_study
    from ..study.grid import set_max_cells

    set_max_cells(args.max_cells)
    r = run_study(
        args.study,
        args.out,
        trials=args.trials,
        seed=args.seed,
        cache_dir=None if args.no_cache else (args.cache if args.cache is not None else "default"),
        scheduler=args.scheduler,
        batch_cells=args.batch_cells,
        workers=workers(args),
        force=args.force,
        progress=not args.no_progress,
    )
    sr = r.sweep_result
    print(
        f"study {r.study.name!r}: {len(sr.cells)} cells ({sr.computed} computed, {sr.cached} from the cache), "
        f"{sr.system_trials} system-trials; simulation {r.timings['simulate_s']:.1f} s, "
        f"total {r.timings['total_s']:.1f} s"
    )
    for f in r.files:
        print(f"wrote {f}")
    return 0


COMMANDS = {
    "sweep": Command("run a scene file's [sweep] grid; write a tidy table (CSV, Parquet)", _sweep_arguments, _sweep),
    "study": Command("run a study (e.g. 'paper'): table, Figs. 6-8, claims report", _study_arguments, _study),
}

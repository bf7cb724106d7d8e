"""``torchdoct bench NAME``: every benchmark, one table (:func:`benchmarks`), each a thin call into
:mod:`torchdoct.bench` that prints its table and writes its JSON only when ``--out`` asks for it.

The built-in benchmarks and those other installed packages add (entry-point group ``torchdoct.bench``,
:mod:`torchdoct.cli.extensions`: ``classify``) share the table; ``bench all`` runs every entry but ``cog``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..files import atomic_write, check_out
from .command import Command, add_parsers, add_threads, command_main, parse_floats, run_parsed, workers

__all__ = ["COMMANDS", "benchmarks", "run_benchmark"]


def _add_out(p, help_text: str = "also write the result as JSON (default: printed only, nothing written)") -> None:
    p.add_argument("--out", default=None, metavar="FILE.json", help=help_text)


def run_benchmark(args, compute: Callable[[], dict[str, Any]], fmt: Callable[[dict[str, Any]], str]) -> int:
    """A benchmark command: check ``--out``, run ``compute``, print ``fmt`` of the result, write the JSON."""
    out = check_out(args.out, args.force, ".json")
    res = compute()
    print(fmt(res))
    if out is not None:  # asked for with --out: nothing is written into the current folder unasked
        atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
        print(f"wrote {out}")
    return 0


# ----------------------------------------------------------------------------------------------
# the simulator


def _simulate_arguments(bs) -> None:
    bs.add_argument("--trials", type=int, default=1024, help="trials per cell")
    bs.add_argument("--repeats", type=int, default=1, help="repeats per cell (best is kept)")
    bs.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    bs.add_argument(
        "--load",
        action="store_true",
        help="also time every cell on one thread, and beside a busy process that it starts and stops",
    )
    _add_out(bs)
    bs.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _simulate(args) -> int:
    from .. import bench

    return run_benchmark(
        args,
        lambda: bench.bench_simulate(
            trials=args.trials,
            dtype=args.dtype,
            repeats=args.repeats,
            threads=args.threads,
            load=args.load,
            progress=True,
        ),
        bench.format_simulate_table,
    )


def _tradeoffs_arguments(bt) -> None:
    bt.add_argument("--part", choices=("all", "simulator", "study", "classifier", "fidelity"), default="all")
    bt.add_argument("--trials", type=int, default=8192, help="simulator: trials per tolerance point")
    bt.add_argument("--reference-trials", type=int, default=16384, help="simulator: trials of the reference")
    bt.add_argument(
        "--fidelity-trials",
        type=int,
        default=4096,
        help="fidelity: trials per cell and simulator setting (bias of every model feature)",
    )
    bt.add_argument(
        "--fidelity-reference-trials",
        type=int,
        default=8192,
        help="fidelity: trials per cell of the tight reference (tolerance 1e-6, float64)",
    )
    bt.add_argument("--quick", action="store_true", help="reduced sizes (minutes)")
    _add_out(
        bt, "also write the result as JSON (PNGs of the fronts beside it) (default: printed only, nothing written)"
    )
    bt.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _tradeoffs(args) -> int:
    """Trade-off curves of the simulator, the paper study and the classifier (``--part``)."""
    from ..bench import tradeoffs

    out = check_out(args.out, args.force, ".json")
    parts = ["simulator", "study", "classifier", "fidelity"] if args.part == "all" else [args.part]
    pngs = (
        {}
        if out is None
        else {
            p: Path(args.out).with_name(f"{Path(args.out).stem}-{p}.png")
            for p in parts
            if p not in ("study", "fidelity")
        }
    )
    for png in pngs.values():
        check_out(str(png), args.force, ".png")
    res: dict[str, Any] = {}
    if "simulator" in parts:
        n, ref = (512, 1024) if args.quick else (args.trials, args.reference_trials)
        res["simulator"] = tradeoffs.simulator_tradeoffs(trials=n, reference_trials=ref, progress=True)
        print(tradeoffs.format_table(res["simulator"]))
    if "study" in parts:
        grid, ref = ((16, 64), 128) if args.quick else ((16, 32, 64, 128, 256), 512)
        res["study"] = tradeoffs.study_tradeoffs(trials_grid=grid, reference_trials=ref, progress=True)
        print(tradeoffs.format_study_table(res["study"]))
    if "classifier" in parts:
        from . import extensions

        clf_tradeoffs = extensions.load(
            extensions.TRADEOFFS, "classifier", command="torchdoct bench tradeoffs --part classifier"
        )
        res["classifier"] = clf_tradeoffs.compute(quick=args.quick, progress=True)
        print(clf_tradeoffs.format_table(res["classifier"]))
    if "fidelity" in parts:
        n, ref = (512, 1024) if args.quick else (args.fidelity_trials, args.fidelity_reference_trials)
        res["fidelity"] = tradeoffs.feature_fidelity(trials=n, reference_trials=ref, progress=True)
        print(tradeoffs.format_fidelity_table(res["fidelity"]))
    if out is None:  # nothing is written into the current folder unasked
        return 0
    atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
    if "simulator" in pngs:
        atomic_write(pngs["simulator"], lambda tmp: tradeoffs.plot_tradeoffs(res["simulator"], tmp))
    if "classifier" in pngs:
        atomic_write(pngs["classifier"], lambda tmp: clf_tradeoffs.plot(res["classifier"], tmp))
    print(f"wrote {out}" + "".join(f", {p}" for p in pngs.values()))
    return 0


def _load_arguments(bl) -> None:
    bl.add_argument("--repeats", type=int, default=3, help="runs per figure (best is kept)")
    _add_out(bl)
    bl.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _load(args) -> int:
    from .. import bench
    from .render import COMMANDS as RENDER

    return run_benchmark(
        args,
        lambda: bench.bench_load(
            repeats=args.repeats, threads=args.threads, progress=True, command=command_main(RENDER)
        ),
        bench.format_load_table,
    )


def _cog_arguments(bg) -> None:
    bg.add_argument("--cog", required=True, metavar="DIR", help="folder of a clone of the COG DOCT simulation library")
    bg.add_argument("--cog-trials", type=int, default=10, help="COG trials per cell and repeat")
    bg.add_argument("--trials", type=int, default=1024, help="torchdoct trials per cell and repeat")
    bg.add_argument("--repeats", type=int, default=3, help="repeats per cell (best is kept)")
    _add_out(bg)
    bg.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _cog(args) -> int:
    from ..bench import cog

    return run_benchmark(
        args,
        lambda: cog.bench_cog(
            args.cog, cog_trials=args.cog_trials, trials=args.trials, repeats=args.repeats, progress=True
        ),
        cog.format_cog_table,
    )


# ----------------------------------------------------------------------------------------------
# rendering, maps, bulk phase, the study


def _render_arguments(b) -> None:
    b.add_argument("--phantom", default="spheroid")
    b.add_argument("--repeats", type=int, default=3, help="repeats (best is kept)")
    b.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    _add_out(b)
    b.add_argument("--force", action="store_true")


def _render(args) -> int:
    from ..bench import bench_render

    out = check_out(args.out, args.force, ".json")
    res = bench_render(phantom=args.phantom, repeats=args.repeats, dtype=args.dtype)
    print(json.dumps({k: v for k, v in res.items() if k != "machine"}, indent=2))
    if out is not None:  # asked for with --out: nothing is written into the current folder unasked
        atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
        print(f"wrote {out}")
    return 0


def _maps_arguments(bm) -> None:
    bm.add_argument("--frames", type=int, default=32)
    bm.add_argument("--size", nargs=2, type=int, default=[512, 512], metavar=("Z", "X"))
    bm.add_argument(
        "--resolution", action="append", default=None, metavar="R", help="default: original, axial=14, lateral=18"
    )
    bm.add_argument("--aliv", action="store_true", help="include aLIV and Swiftness")
    bm.add_argument("--signature", action="store_true", help="include the signature channels (maps --signature)")
    bm.add_argument("--speckle", action="store_true", help="include the speckle-motion channels (maps --speckle)")
    bm.add_argument(
        "--doppler",
        action="store_true",
        help="include the Doppler reference (maps --doppler; the random field has none, so no channel)",
    )
    bm.add_argument("--repeats", type=int, default=1, help="timed repeats (best is kept)")
    _add_out(bm)
    bm.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _maps(args: argparse.Namespace) -> int:
    from ..bench.maps import bench_maps

    def compute() -> dict[str, Any]:
        if args.frames < 2 or min(args.size) < 1:
            raise ValueError("--frames must be >= 2 and --size positive")
        metrics = ["liv", "ocds", "mean_db"] + (["aliv", "swiftness"] if args.aliv else [])
        return bench_maps(
            frames=args.frames,
            shape=tuple(args.size),
            resolutions=args.resolution or ["original", "axial=14", "lateral=18"],
            metrics=metrics,
            repeats=args.repeats,
            signature=args.signature,
            speckle=args.speckle,
            doppler=args.doppler,
        )

    def fmt(res: dict[str, Any]) -> str:
        per = ", ".join(f"{k} {v:.2f} s" for k, v in res["seconds_per_resolution"].items())
        m = res["machine"]
        return (
            f"maps of a complex64 {res['shape']} stack, {len(res['resolutions'])} resolutions, "
            f"{'+'.join(res['metrics'] + ['signature'] * res['signature'] + ['speckle'] * res['speckle'] + ['doppler'] * res.get('doppler', False))}: "
            f"{res['seconds_total']:.2f} s total ({per}); "
            f"target {res['target_seconds']:.0f} s; {m['cpu_count']} cores, torch {m['torch']} with "
            f"{m['torch_threads']} threads"
        )

    return run_benchmark(args, compute, fmt)


def _maps_channels_arguments(bm) -> None:
    bm.add_argument("--frames", type=int, default=32)
    bm.add_argument("--size", nargs=2, type=int, default=[256, 256], metavar=("Z", "X"))
    bm.add_argument("--repeats", type=int, default=3, help="rounds, each timing every channel set once (best is kept)")
    bm.add_argument(
        "--load", action="store_true", help="also the rounds beside a busy process that it starts and stops"
    )
    _add_out(bm)
    bm.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _maps_channels(args: argparse.Namespace) -> int:
    from ..bench.maps import bench_maps_channels

    def compute() -> dict[str, Any]:
        if args.frames < 2 or min(args.size) < 1 or args.repeats < 1:
            raise ValueError("--frames must be >= 2, --size positive and --repeats >= 1")
        return bench_maps_channels(frames=args.frames, shape=tuple(args.size), repeats=args.repeats, load=args.load)

    def fmt(res: dict[str, Any]) -> str:
        lines = [
            f"maps of a complex64 {res['shape']} stack at {len(res['resolutions'])} resolutions, best of {res['repeats']} rounds:"
        ]
        for name, rec in res["sets"].items():
            lines.append(
                f"  {name}: "
                + "; ".join(
                    f"{m} {rec[f'seconds_{m}']:.2f} s ({rec[f'ratio_to_signature_{m}']:.2f} x signature)"
                    for m in res["modes"]
                )
            )
        return "\n".join(lines)

    return run_benchmark(args, compute, fmt)


def _stream_arguments(bs) -> None:
    bs.add_argument("--sizes-gb", default="1,4,16", help="input sizes (GiB; default 1,4,16)")
    bs.add_argument("--budget-gb", type=float, default=0.25, help="--max-memory-gb of the maps (default 0.25)")
    bs.add_argument("--workdir", default=None, help="folder for the sparse inputs (default the temporary folder)")
    bs.add_argument("--figure", default=None, metavar="FILE.png", help="also draw peak RSS against input size")
    _add_out(bs)
    bs.add_argument("--force", action="store_true", help="overwrite --out / --figure if they exist")


def _stream(args) -> int:
    from ..bench.stream import bench_stream, format_stream_table, plot_stream

    out = check_out(args.out, args.force, ".json", what="--out")
    fig = check_out(args.figure, args.force, ".png", what="--figure")

    def keep(partial: dict) -> None:  # each size as it finishes: a run stopped half-way keeps what it measured
        if out is not None and not partial["complete"]:
            atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(partial, indent=2)))

    res = bench_stream(
        parse_floats(args.sizes_gb, None, "--sizes-gb"), budget_gb=args.budget_gb, workdir=args.workdir, on_run=keep
    )
    print(format_stream_table(res))
    if out is not None:  # asked for with --out: nothing is written into the current folder unasked
        atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
        print(f"wrote {out}")
    if fig is not None:
        atomic_write(fig, lambda tmp: plot_stream(res, tmp))
        print(f"wrote {fig}")
    return 0


def _bulk_phase_arguments(bb) -> None:
    bb.add_argument("--snr-db", default="10,20,30,40", help="comma list of SNRs (dB; default 10,20,30,40)")
    bb.add_argument("--depth", type=int, default=64, help="depth pixels per A-line (default 64)")
    bb.add_argument("--frames", type=int, default=32)
    bb.add_argument("--lines", type=int, default=2000, help="A-lines per SNR (default 2000)")
    bb.add_argument("--seed", type=int, default=0)
    bb.add_argument(
        "--phantom",
        default=None,
        metavar="NAME",
        help="also render this B-scan phantom (e.g. vessel-slab, which has moving regions) and measure "
        "every method and mask on it at 20, 30, 40 dB",
    )
    _add_out(bb)
    bb.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def _bulk_phase(args: argparse.Namespace) -> int:
    from ..bench.bulkphase import bench_bulk_phase, bench_bulk_phase_phantom, format_bench_bulk_phase

    def compute() -> dict[str, Any]:
        if args.frames < 2 or args.depth < 3 or args.lines < 2:
            raise ValueError("--frames must be >= 2, --depth >= 3 and --lines >= 2")
        res = bench_bulk_phase(
            snr_db=parse_floats(args.snr_db, None, "--snr-db"),
            n_z=args.depth,
            frames=args.frames,
            lines=args.lines,
            seed=args.seed,
        )
        if args.phantom:
            res["phantom"] = bench_bulk_phase_phantom(args.phantom)
        return res

    return run_benchmark(args, compute, format_bench_bulk_phase)


def _study_arguments(bs) -> None:
    bs.add_argument("--study", default="paper-reduced", help="study file or shipped name (default paper-reduced)")
    bs.add_argument("--trials", type=int, default=None, help="trials per point (default: the study's)")
    bs.add_argument(
        "--groupings",
        action="store_true",
        help="also time cells with all systems in one scene vs the comparisons' pairs",
    )
    bs.add_argument("--grouping-trials", type=int, default=128, help="trials per timed cell for --groupings")
    bs.add_argument(
        "--study-out",
        default=None,
        metavar="DIR",
        help="keep the study's table, figures and report in DIR (default: a temporary directory)",
    )
    _add_out(bs)
    bs.add_argument("--force", action="store_true", help="overwrite --out (and --study-out files) if they exist")
    bs.add_argument(
        "--workers",
        type=int,
        default=None,
        help="cells computed side by side (default: --threads, else the usable cores)",
    )
    bs.add_argument("--no-progress", action="store_true", help="no progress bar")


def _study(args) -> int:
    from ..bench.study import bench_study, format_bench_study

    out = check_out(args.out, args.force, ".json")
    res = bench_study(
        args.study,
        trials=args.trials,
        groupings=args.groupings,
        grouping_trials=args.grouping_trials,
        study_out=args.study_out,
        force=args.force,
        workers=workers(args),
        progress=not args.no_progress,
    )
    print(format_bench_study(res))
    if out is not None:  # asked for with --out: nothing is written into the current folder unasked
        atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2), encoding="utf-8"))
        print(f"wrote {out}")
    return 0


# ----------------------------------------------------------------------------------------------
# all of them


def _all_arguments(ba) -> None:
    ba.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    ba.add_argument("--quick", action="store_true", help="reduced sizes (a smoke run, minutes)")
    ba.add_argument("--force", action="store_true", help="overwrite existing results")


#: ``bench all --quick``: the reduced sizes of the benchmarks without a ``--quick`` option.
_QUICK = {
    "simulate": ["--trials", "256"],
    "tradeoffs": ["--quick"],
    "render": ["--repeats", "1"],
    "load": ["--repeats", "1"],
    "stream": ["--sizes-gb", "0.0625,0.25"],
    "maps-channels": ["--size", "64", "64", "--repeats", "1"],
}


def _all(args) -> int:
    """Run every benchmark of the table in turn (not ``cog``, which needs ``--cog``); each writes
    ``DIR/bench-NAME.json``."""
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    parser = argparse.ArgumentParser(prog="torchdoct bench")
    _bench_arguments(parser)
    parser.set_defaults(func=_bench)
    sub = parser.subcommands
    names = [n for n in sub.choices if n not in ("all", "cog")]
    failed = []
    for name in names:
        argv = [name, "--out", str(out_dir / f"bench-{name}.json")]
        if args.force:
            argv.append("--force")
        if args.quick:
            argv += _QUICK.get(name, ["--quick"] if "--quick" in sub.choices[name].format_usage() else [])
        print(f"== torchdoct bench {' '.join(argv)}", flush=True)
        code = run_parsed(parser.parse_args(argv))
        if code != 0:
            failed.append(name)
    print(f"benchmarks: {len(names) - len(failed)} of {len(names)} done" + (f"; failed: {failed}" if failed else ""))
    return 1 if failed else 0


# ----------------------------------------------------------------------------------------------
# the table


def _extension_benchmark(part: Any) -> Command:
    """A benchmark another installed package registers (entry-point group ``torchdoct.bench``): a module
    with ``HELP``, ``DESCRIPTION``, ``add_arguments(parser)`` and ``benchmark(args) -> (compute, format)``."""
    return Command(
        part.HELP, part.add_arguments, lambda args: run_benchmark(args, *part.benchmark(args)), part.DESCRIPTION
    )


def benchmarks() -> dict[str, Any]:
    """Every benchmark of ``torchdoct bench``, by name: the built-in ones, then those of the entry-point group
    ``torchdoct.bench`` (:func:`torchdoct.cli.extensions.benchmarks`), then ``all``."""
    from . import extensions

    table: dict[str, Any] = {
        "simulate": Command(
            "paper's 4 systems x 3 motions at their largest parameters", _simulate_arguments, _simulate
        ),
        "tradeoffs": Command(
            "what accuracy costs in time: simulator, study and classifier", _tradeoffs_arguments, _tradeoffs
        ),
        "load": Command(
            "simulate, render and sweep: alone on 1 and N threads, and beside a busy process", _load_arguments, _load
        ),
        "cog": Command(
            "the paper's 12 cells against the COG point simulator (a clone of it), one core", _cog_arguments, _cog
        ),
        "render": Command("spheroid phantom: 32-frame 256×256 B-scan sequence", _render_arguments, _render),
        "maps": Command("time maps of a random complex stack at several resolutions", _maps_arguments, _maps),
        "maps-channels": Command(
            "maps with and without the signature, speckle and Doppler channels, compared in one run",
            _maps_channels_arguments,
            _maps_channels,
        ),
        "stream": Command(
            "peak memory of streamed maps against input size (--max-memory-gb)", _stream_arguments, _stream
        ),
        "bulk-phase": Command(
            "residual phase error of the bulk-phase correction against SNR", _bulk_phase_arguments, _bulk_phase
        ),
        "study": Command("wall time of a whole study from an empty cache", _study_arguments, _study),
    }
    for name, part in extensions.benchmarks():
        table[name] = _extension_benchmark(part)
    table["all"] = Command(
        "every benchmark, each writing DIR/bench-NAME.json (not cog, which needs --cog)", _all_arguments, _all
    )
    return table


def _bench_arguments(p) -> None:
    """The benchmarks as subcommands of ``p``; ``p.subcommands`` holds them (read by ``bench all`` and
    :func:`torchdoct.cli.command.add_threads`)."""
    sub = p.add_subparsers(dest="bench", required=True)
    add_parsers(sub, benchmarks(), dest="run_benchmark")
    p.subcommands = sub
    add_threads(sub)


def _bench(args) -> int:
    return int(args.run_benchmark(args))


COMMANDS = {"bench": Command("benchmarks (throughput, written as JSON)", _bench_arguments, _bench)}

"""Command line: ``torchdoct {scenes,plan,simulate,bench}``. Parse, call one library function, print."""

from __future__ import annotations

import argparse
import json
import importlib
import importlib.util
import sys
from pathlib import Path
from typing import Any, Sequence

from ..files import atomic_write, check_out
from ..interrupt import entry_point

__all__ = ["build_parser", "main", "EXIT_CODES"]

#: Exit codes of every command (``torchdoct``, ``doct-train``, ``doct-classify``; README, Command line).
EXIT_CODES = {
    0: "done",
    1: "failed for a reason other than the input: the system refused a read or write (permissions, disk "
       "full; one `error:` line) or an internal error (a traceback: please report it)",
    2: "bad input or usage: unknown option, missing, empty or corrupt file, invalid value, unusable "
       "device, output that exists without --force (one `error:` line naming the file or option and "
       "the fix; nothing is written)",
    130: "interrupted by Ctrl-C: one line says what was kept and how to resume (torchdoct.interrupt)",
    141: "the output pipe closed early (`| head`): ended quietly",
    143: "terminated by SIGTERM: one line says what was kept and how to resume",
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchdoct", description="Dynamic OCT simulation and metrics.")
    sub = p.add_subparsers(dest="command", required=True)

    sub.add_parser("scenes", help="list the shipped example scenes")

    pl = sub.add_parser("plan", help="print what a simulation of a scene will run")
    pl.add_argument("scene", help="scene TOML file or shipped scene name")
    pl.add_argument("--trials", type=int, default=None, help="trials to cost (default: the scene's)")
    pl.add_argument("--tolerance", type=float, default=None, help="PSF truncation tolerance (amplitude)")
    pl.add_argument("--json", action="store_true", help="print the plan as JSON")

    sm = sub.add_parser("simulate", help="simulate a scene and print its LIV/OCDS summary")
    sm.add_argument("scene", help="scene TOML file or shipped scene name")
    sm.add_argument("--trials", type=int, default=None, help="number of trials (default: the scene's)")
    sm.add_argument("--seed", type=int, default=None, help="random seed (default: the scene's)")
    sm.add_argument("--dtype", choices=("float32", "float64"), default=None)
    sm.add_argument("--tolerance", type=float, default=None, help="PSF truncation tolerance (amplitude)")
    sm.add_argument("--device", default=None, help="torch device (default cpu)")
    sm.add_argument("--out", default=None, help="write signals, metrics and the resolved scene to this .npz")
    sm.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    sm.add_argument("--json", action="store_true", help="print the summary as JSON")
    sm.add_argument("--no-progress", action="store_true", help="no progress bar")

    from .. import extensions

    for name, command in extensions.commands():  # commands other installed packages add (translate)
        cp = sub.add_parser(name, help=command.HELP, description=command.DESCRIPTION)
        command.add_arguments(cp)
        cp.set_defaults(func=command.run)

    bn = sub.add_parser("bench", help="benchmarks (throughput, written as JSON)")
    bsub = bn.add_subparsers(dest="bench", required=True)
    bs = bsub.add_parser("simulate", help="paper's 4 systems x 3 motions at their largest parameters")
    bs.add_argument("--trials", type=int, default=1024, help="trials per cell")
    bs.add_argument("--repeats", type=int, default=1, help="repeats per cell (best is kept)")
    bs.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    bs.add_argument("--load", action="store_true",
                    help="also time every cell on one thread, and beside a busy process that it starts and stops")
    bs.add_argument("--out", default=None, metavar="FILE.json",
                    help="also write the result as JSON (default: printed only, nothing written)")
    bs.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    bt = bsub.add_parser("tradeoffs", help="what accuracy costs in time: simulator, study and classifier")
    bt.add_argument("--part", choices=("all", "simulator", "study", "classifier", "fidelity"), default="all")
    bt.add_argument("--trials", type=int, default=8192, help="simulator: trials per tolerance point")
    bt.add_argument("--reference-trials", type=int, default=16384, help="simulator: trials of the reference")
    bt.add_argument("--fidelity-trials", type=int, default=4096,
                    help="fidelity: trials per cell and simulator setting (bias of every model feature)")
    bt.add_argument("--fidelity-reference-trials", type=int, default=8192,
                    help="fidelity: trials per cell of the tight reference (tolerance 1e-6, float64)")
    bt.add_argument("--quick", action="store_true", help="reduced sizes (minutes)")
    bt.add_argument("--out", default=None, metavar="FILE.json",
                    help="also write the result as JSON (PNGs of the fronts beside it) (default: printed only, nothing written)")
    bt.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    bc = bsub.add_parser("classify", help="doct-classify throughput on a 512×512 synthetic maps file")
    bc.add_argument("--size", type=int, default=512, help="pixels per side")
    bc.add_argument("--repeats", type=int, default=3)
    bc.add_argument("--out", default=None, metavar="FILE.json",
                    help="also write the result as JSON (default: printed only, nothing written)")
    bc.add_argument("--model", default=None, help="shipped model name or .onnx path (default: the LIV/OCDS model)")
    bc.add_argument("--force", action="store_true")
    bl = bsub.add_parser("load", help="simulate, render and sweep: alone on 1 and N threads, and beside a busy process")
    bl.add_argument("--repeats", type=int, default=3, help="runs per figure (best is kept)")
    bl.add_argument("--out", default=None, metavar="FILE.json",
                    help="also write the result as JSON (default: printed only, nothing written)")
    bl.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    bg = bsub.add_parser("cog", help="the paper's 12 cells against the COG point simulator (a clone of it), one core")
    bg.add_argument("--cog", required=True, metavar="DIR", help="folder of a clone of the COG DOCT simulation library")
    bg.add_argument("--cog-trials", type=int, default=10, help="COG trials per cell and repeat")
    bg.add_argument("--trials", type=int, default=1024, help="torchdoct trials per cell and repeat")
    bg.add_argument("--repeats", type=int, default=3, help="repeats per cell (best is kept)")
    bg.add_argument("--out", default=None, metavar="FILE.json",
                    help="also write the result as JSON (default: printed only, nothing written)")
    bg.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    ba = bsub.add_parser("all", help="every benchmark, each writing DIR/bench-NAME.json (not cog, which needs --cog)")
    ba.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    ba.add_argument("--quick", action="store_true", help="reduced sizes (a smoke run, minutes)")
    ba.add_argument("--force", action="store_true", help="overwrite existing results")
    for name in _EXTENSIONS:
        if importlib.util.find_spec(f"{__package__}.{name}") is not None:
            importlib.import_module(f"{__package__}.{name}").register(sub, bsub)
    _add_threads(sub, bsub)
    p.bench_subparsers = bsub  # read by `bench all`
    return p


#: Commands that only list or describe: no --threads.
_NO_COMPUTE = {"scenes", "phantoms", "plan", "bench", "cog"}


def _add_threads(*subparser_groups) -> None:
    """One knob on every command that computes: ``--threads N`` (:mod:`torchdoct.threads`)."""
    for group in subparser_groups:
        for name, sp in group.choices.items():
            if name in _NO_COMPUTE or any("--threads" in a.option_strings for a in sp._actions):
                continue
            sp.add_argument("--threads", type=int, default=None, metavar="N",
                            help="cores to use (default: the usable cores, or $TORCHDOCT_THREADS); each works "
                                 "with one torch thread, so other busy processes do not stall it; results do "
                                 "not depend on N")


_check_out = check_out  # its ValueError is bad input: exit code 2 (EXIT_CODES)


_atomic_write = atomic_write

#: Modules that add subcommands: each has ``register(sub, bench_sub)``, adding parsers whose
#: ``func`` default is the handler ``func(args) -> int``.
_EXTENSIONS = ("render", "data", "study")


def _format_summary(summary: dict[str, Any], result) -> str:
    sc = result.scene
    lines = [f"scene {sc.name!r}: {result.trials} trials, seed {result.seed}, "
             f"{sc.protocol.n_frames} frames, {result.signals.dtype}, {result.elapsed_s:.2f} s"]
    est = sc.analysis.ocds_estimator
    lines.append(f"LIV: ddof-0 variance of 10·log10 I (dB²); OCDS: −slope of the {est} correlation of the "
                 f"{sc.analysis.ocds_scale} intensity over {list(sc.analysis.ocds_delay_range_s)} s (1/s)")
    lines.append(f"{'system':>16}  {'LIV mean ± SD (SE) [dB²]':>28}  {'OCDS mean ± SD (SE) [1/s]':>30}  empty")
    for name, row in summary.items():
        cells = []
        for key, fmt in (("liv", "{:7.3f} ± {:6.3f} ({:.3f})"), ("ocds", "{:7.4f} ± {:6.4f} ({:.4f})")):
            if key in row:
                r = row[key]
                cells.append(fmt.format(r["mean"], r["sd"], r["se"]))
            else:
                cells.append("-")
        lines.append(f"{name:>16}  {cells[0]:>28}  {cells[1]:>30}  {row['zero_intensity_trials']}")
    if any(r["zero_intensity_trials"] for r in summary.values()):
        lines.append("empty: trials with I = 0 at some frame (no scatterer within the PSF truncation); "
                     "their dB metrics are NaN and excluded from the means")
    return "\n".join(lines)


def _save_npz(path: Path, result, metrics: dict[str, Any]) -> None:
    import numpy as np

    arrays: dict[str, Any] = {
        "signals": result.signals.cpu().numpy(),
        "frame_times_s": np.asarray(result.frame_times_s, dtype=np.float64),
        "system_names": np.asarray(result.system_names, dtype=np.str_),
        "seed": np.int64(result.seed),
        "trials": np.int64(result.trials),
        "scene_json": np.asarray(json.dumps(result.scene.to_dict())),
        "plan_json": np.asarray(result.plan.to_json()),
        "zero_intensity": metrics["zero_intensity"].cpu().numpy(),
    }
    for k, v in metrics.items():
        if k != "zero_intensity":
            arrays[k] = v.cpu().numpy()

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    _atomic_write(path, write)


def _bench_tradeoffs(args) -> int:
    """Trade-off curves of the simulator, the paper study and the classifier (``--part``)."""
    from ..bench import tradeoffs

    out = _check_out(args.out, args.force, ".json")
    parts = ["simulator", "study", "classifier", "fidelity"] if args.part == "all" else [args.part]
    pngs = {} if out is None else {p: Path(args.out).with_name(f"{Path(args.out).stem}-{p}.png")
                                   for p in parts if p not in ("study", "fidelity")}
    for png in pngs.values():
        _check_out(str(png), args.force, ".png")
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
        from .. import extensions

        clf_tradeoffs = extensions.load(extensions.TRADEOFFS, "classifier",
                                        command="torchdoct bench tradeoffs --part classifier")
        res["classifier"] = clf_tradeoffs.compute(quick=args.quick, progress=True)
        print(clf_tradeoffs.format_table(res["classifier"]))
    if "fidelity" in parts:
        n, ref = (512, 1024) if args.quick else (args.fidelity_trials, args.fidelity_reference_trials)
        res["fidelity"] = tradeoffs.feature_fidelity(trials=n, reference_trials=ref, progress=True)
        print(tradeoffs.format_fidelity_table(res["fidelity"]))
    if out is None:  # nothing is written into the current folder unasked
        return 0
    _atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
    if "simulator" in pngs:
        _atomic_write(pngs["simulator"], lambda tmp: tradeoffs.plot_tradeoffs(res["simulator"], tmp))
    if "classifier" in pngs:
        _atomic_write(pngs["classifier"], lambda tmp: clf_tradeoffs.plot(res["classifier"], tmp))
    print(f"wrote {out}" + "".join(f", {p}" for p in pngs.values()))
    return 0


def _bench(args, compute, fmt) -> int:
    """A benchmark command: check ``--out``, run, print the table, write the JSON."""
    out = _check_out(args.out, args.force, ".json")
    res = compute()
    print(fmt(res))
    if out is not None:  # asked for with --out: nothing is written into the current folder unasked
        _atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=2)))
        print(f"wrote {out}")
    return 0


def _bench_all(args) -> int:
    """Run every registered benchmark in turn; each writes ``DIR/bench-NAME.json``."""
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    quick = {"simulate": ["--trials", "256"], "tradeoffs": ["--quick"], "render": ["--repeats", "1"], "load": ["--repeats", "1"]}
    bench_sub = build_parser().bench_subparsers
    names = [n for n in bench_sub.choices if n not in ("all", "cog")]
    failed = []
    for name in names:
        argv = ["bench", name, "--out", str(out_dir / f"bench-{name}.json")]
        if args.force:
            argv.append("--force")
        if args.quick:
            argv += quick.get(name, ["--quick"] if "--quick" in bench_sub.choices[name].format_usage() else [])
        print(f"== torchdoct {' '.join(argv)}", flush=True)
        code = _main(argv)
        if code != 0:
            failed.append(name)
    print(f"benchmarks: {len(names) - len(failed)} of {len(names)} done" + (f"; failed: {failed}" if failed else ""))
    return 1 if failed else 0


@entry_point  # Ctrl-C/SIGTERM: one line, exit 130/143; a closed output pipe: quiet exit 141
def main(argv: Sequence[str] | None = None) -> int:
    return _main(argv)


def _main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from ..sim import config
    from ..threads import set_default_threads

    try:
        set_default_threads(getattr(args, "threads", None))
    except ValueError as err:
        print(f"error: --threads: {err}", file=sys.stderr)
        return 2
    from ..threads import limit_process_threads

    limit_process_threads()  # parallel work runs over independent pieces (torchdoct.threads)
    from ..sim.scenes import shipped_scenes

    try:
        if getattr(args, "device", None) is not None:  # every command with --device (simulate, render, maps)
            from .._device import check_device

            check_device(args.device)
        if getattr(args, "func", None) is not None:
            return int(args.func(args))
        if args.command == "scenes":
            for name, path in shipped_scenes().items():
                sc = config.load_scene(path)
                print(f"{name:>22}: {sc.description}")
            return 0
        if args.command == "plan":
            from ..sim.plan import make_plan

            scene = config.load_scene(args.scene)
            plan = make_plan(scene, truncation_tolerance=args.tolerance)
            print(plan.to_json() if args.json else plan.describe(args.trials or scene.simulation.trials))
            return 0
        if args.command == "simulate":
            from ..sim.simulate import simulate

            out = _check_out(args.out, args.force, ".npz")
            scene = config.load_scene(args.scene)
            result = simulate(scene, trials=args.trials, seed=args.seed, dtype=args.dtype,
                              device=args.device, truncation_tolerance=args.tolerance,
                              progress=not args.no_progress)
            metrics = result.metrics()
            from ..sim.metrics import summarize

            summary = summarize(metrics, result.system_names)
            if args.json:
                print(json.dumps(summary, indent=2))
            else:
                print(_format_summary(summary, result))
            if out is not None:
                _save_npz(out, result, metrics)
                print(f"wrote {out}")
            return 0
        if args.command == "bench" and args.bench == "tradeoffs":
            return _bench_tradeoffs(args)
        if args.command == "bench" and args.bench == "classify":
            from .. import extensions

            compute, fmt = extensions.load(extensions.BENCH, "classify", command="torchdoct bench classify")(args)
            return _bench(args, compute, fmt)
        if args.command == "bench" and args.bench == "all":
            return _bench_all(args)
        if args.command == "bench" and args.bench == "load":
            from .. import bench

            return _bench(args, lambda: bench.bench_load(repeats=args.repeats, threads=args.threads, progress=True),
                          bench.format_load_table)
        if args.command == "bench" and args.bench == "cog":
            from ..bench import cog

            return _bench(args, lambda: cog.bench_cog(args.cog, cog_trials=args.cog_trials, trials=args.trials,
                                                      repeats=args.repeats, progress=True), cog.format_cog_table)
        if args.command == "bench" and args.bench == "simulate":
            from .. import bench

            return _bench(args, lambda: bench.bench_simulate(trials=args.trials, dtype=args.dtype, repeats=args.repeats,
                                                             threads=args.threads, load=args.load, progress=True),
                          bench.format_simulate_table)
    except (config.SceneError, TypeError, ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of the output went away: torchdoct.interrupt ends quietly
        raise
    except OSError as err:  # the system refused a read or write (permissions, disk full)
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 1

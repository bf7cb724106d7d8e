"""Benchmarks (``torchdoct bench ...``): measured throughput, reported, never asserted.

``bench_simulate`` times the paper's four systems × three motions at their largest parameters
(D = 15 µm²/s; v = 6 µm/s random ballistic and 45° flow; 0.055 µm⁻³, 32 frames at 204.8 ms),
one single-system scene per cell, and reports scatterers per trial, trials/s and scatterer-frame
evaluations/s. Besides the wall time it reports the CPU time of the process (all its threads: the
per-core cost), which other busy processes on a shared machine disturb much less.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from ..runtime.machine import machine_info
from ..sim.config import Diffusion, Flow, OCTSystem, Population, Protocol, RandomBallistic, Scene
from ..sim.plan import make_plan
from ..sim.simulate import simulate

__all__ = ["paper_systems", "paper_motions", "bench_simulate", "format_simulate_table", "write_json"]


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


#: Scatterer-frame evaluations per second per core of a fused kernel (a straight path's Gaussian weight
#: and phase advance by one complex multiplication per frame): the yardstick of the evaluation rate.
EVALUATION_LIMIT_PER_S = 1.0e9


def bench_simulate(
    *,
    trials: int = 1024,
    dtype: str = "float32",
    repeats: int = 1,
    threads: int | None = None,
    load: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """Time the 12 paper cells; returns a JSON-ready dict (see the module docstring).

    ``threads``: as in :func:`torchdoct.simulate`. ``load``: also time every cell on one thread alone
    and with ``threads`` beside a busy neighbour process (:class:`BusyNeighbour`).
    """
    protocol = Protocol(n_frames=32, frame_interval_s=0.2048)
    rows = []
    cells = [(s, m) for m in paper_motions().items() for s in paper_systems()]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(cells) * (3 if load else 1), desc="bench simulate", unit="cell")
    scenes = [
        Scene(
            systems=(system,),
            protocol=protocol,
            populations=(Population(density_per_um3=0.055, motion=(motion,)),),
            name=f"{system.name} {mname}",
        )
        for system, (mname, motion) in cells
    ]

    def best_of(scene: Scene, t: int | None) -> tuple[float, Any, float]:
        """Best wall time, a result, best CPU time of the process (s)."""
        best, res, best_cpu = float("inf"), None, float("inf")
        for r in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            res = simulate(scene, trials=trials, seed=2 + r, dtype=dtype, threads=t)
            best = min(best, time.perf_counter() - t0)
            best_cpu = min(best_cpu, time.process_time() - c0)
        if bar is not None:
            bar.update()
        return best, res, best_cpu

    from ..runtime.threads import resolve_threads

    n_threads = resolve_threads(threads)
    for scene, (system, (mname, _motion)) in zip(scenes, cells):
        plan = make_plan(scene)
        simulate(scene, trials=64, seed=1, dtype=dtype, threads=threads)  # warm-up
        best, res, cpu = best_of(scene, threads)
        rows.append(
            {
                "system": system.name,
                "motion": mname,
                "scatterers_per_trial": plan.expected_scatterers_per_trial,
                "evaluations_per_trial": plan.evaluations_per_trial,
                "seconds": best,
                "ms_per_trial": 1e3 * best / trials,
                "trials_per_s": trials / best,
                "evaluations_per_s": plan.evaluations_per_trial * trials / best,
                "of_evaluation_limit": plan.evaluations_per_trial
                * trials
                / best
                / (EVALUATION_LIMIT_PER_S * n_threads),
                "cpu_ms_per_trial": 1e3 * cpu / trials,
                "evaluations_per_cpu_s": plan.evaluations_per_trial * trials / cpu,
                "finite": bool(torch.isfinite(res.signals.real).all()),
            }
        )
    if load:
        for scene, row in zip(scenes, rows):
            row["ms_per_trial_1_thread"] = 1e3 * best_of(scene, 1)[0] / trials
        with BusyNeighbour():
            for scene, row in zip(scenes, rows):
                row["ms_per_trial_loaded"] = 1e3 * best_of(scene, threads)[0] / trials
                row["loaded_over_1_thread_alone"] = row["ms_per_trial_loaded"] / row["ms_per_trial_1_thread"]
    if bar is not None:
        bar.close()
    mean_ms = sum(r["ms_per_trial"] for r in rows) / len(rows)
    mean_cpu = sum(r["cpu_ms_per_trial"] for r in rows) / len(rows)
    extra: dict[str, Any] = {}
    if load:
        extra = {
            "mean_ms_per_trial_1_thread": sum(r["ms_per_trial_1_thread"] for r in rows) / len(rows),
            "mean_ms_per_trial_loaded": sum(r["ms_per_trial_loaded"] for r in rows) / len(rows),
            "worst_loaded_over_1_thread_alone": max(r["loaded_over_1_thread_alone"] for r in rows),
            "neighbour": "one process simulating the example scene on one core",
        }
    return {
        "benchmark": "simulate",
        "trials_per_cell": trials,
        "dtype": dtype,
        "repeats": repeats,
        "threads": n_threads,
        "evaluation_limit_per_s": EVALUATION_LIMIT_PER_S,
        **extra,
        "machine": machine_info(),
        "cells": rows,
        "mean_ms_per_trial": mean_ms,
        "mean_cpu_ms_per_trial": mean_cpu,
        "target_ms_per_trial": 0.3,
        "paper_study_trials": 186_000,
        "paper_study_estimate_s": mean_ms * 1e-3 * 186_000,
    }


def format_simulate_table(result: dict[str, Any]) -> str:
    load = "mean_ms_per_trial_loaded" in result
    t = result.get("threads", "?")
    head = (
        f"| system | motion | scatterers/trial | ms/trial ({t} threads) | trials/s | evaluations/s | of limit | "
        f"CPU ms/trial | evaluations per CPU s |"
    )
    rule = "|---|---|---:|---:|---:|---:|---:|---:|---:|"
    if load:
        head += " ms/trial (1 thread) | ms/trial beside a busy job | ÷ 1 thread alone |"
        rule += "---:|---:|---:|"
    lines = [head, rule]
    for r in result["cells"]:
        line = (
            f"| {r['system']} | {r['motion']} | {r['scatterers_per_trial']:.0f} | "
            f"{r['ms_per_trial']:.3f} | {r['trials_per_s']:.0f} | {r['evaluations_per_s']:.3g} | "
            f"{r.get('of_evaluation_limit', float('nan')):.3f} | {r.get('cpu_ms_per_trial', float('nan')):.3f} | "
            f"{r.get('evaluations_per_cpu_s', float('nan')):.3g} |"
        )
        if load:
            line += (
                f" {r['ms_per_trial_1_thread']:.3f} | {r['ms_per_trial_loaded']:.3f} | "
                f"{r['loaded_over_1_thread_alone']:.2f} |"
            )
        lines.append(line)
    m = result["machine"]
    lines.append("")
    lines.append(
        f"mean {result['mean_ms_per_trial']:.3f} ms/trial (CPU {result.get('mean_cpu_ms_per_trial', float('nan')):.3f} "
        f"ms/trial, all threads) over {len(result['cells'])} cells "
        f"(target {result['target_ms_per_trial']} ms); paper study (~186,000 trials) "
        f"≈ {result['paper_study_estimate_s']:.0f} s; {result['trials_per_cell']} trials/cell, "
        f"{result['dtype']}, {m['cpu_count']} cores, {t} simulation threads with one torch thread each; "
        f"evaluation limit {result.get('evaluation_limit_per_s', EVALUATION_LIMIT_PER_S):.0e}/s per core"
    )
    if load:
        lines.append(
            f"beside a busy job: mean {result['mean_ms_per_trial_loaded']:.3f} ms/trial "
            f"(1 thread alone {result['mean_ms_per_trial_1_thread']:.3f}); worst cell "
            f"{result['worst_loaded_over_1_thread_alone']:.2f}× its one-thread time alone (target 1.5×)"
        )
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: str | Path) -> None:
    Path(path).write_text(json.dumps(result, indent=2))


def bench_render(*, phantom: str = "spheroid", repeats: int = 3, dtype: str = "float32") -> dict[str, Any]:
    """Time :func:`torchdoct.image.render.render` on a shipped phantom (best of ``repeats``).

    Reports the wall time, pixel-frames per second and the scatterer evaluations of the run.
    """
    from ..image.phantom import load_phantom
    from ..image.render import render

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


# ----------------------------------------------------------------------------------------------
# under load: each figure idle and beside a busy process


def _burn() -> None:  # pragma: no cover - runs in the neighbour process
    """A second torchdoct job: simulate the example scene on one core, forever."""
    import sys

    from ..runtime.threads import set_default_threads
    from ..sim.config import load_scene

    torch.set_num_threads(1)
    set_default_threads(1)
    scene = load_scene("example")
    print("ready", flush=True)
    sys.stdout.close()
    while True:
        simulate(scene, trials=256, seed=1)


class BusyNeighbour:
    """Context manager: a separate process that keeps one core busy with a torchdoct simulation
    (started on entry, killed on exit), as a second job on a shared machine would."""

    def __enter__(self) -> BusyNeighbour:
        import subprocess
        import sys

        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from torchdoct.bench import _burn; _burn()"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        line = self.proc.stdout.readline()
        if b"ready" not in line:
            self.proc.kill()
            self.proc.wait()
            self.proc.stdout.close()
            raise RuntimeError("the busy neighbour process did not start")
        time.sleep(0.5)  # let it reach its steady loop
        return self

    def __exit__(self, *exc) -> None:
        self.proc.kill()
        self.proc.wait()
        self.proc.stdout.close()


def _workloads(tmp: Path, command: Callable[[list[str]], int]) -> dict[str, Any]:
    """The commands a user runs, as library calls taking ``threads``; ``command(argv)`` runs ``torchdoct render``."""
    from ..sim.config import load_scene, read_toml
    from ..sim.scenes import resolve_scene_path
    from ..study.sweep import make_sweep, run_sweeps

    example = load_scene("example")
    sweep = make_sweep(
        read_toml(resolve_scene_path("example")),
        [{"path": "population.0.motion.0.diffusion_um2_per_s", "log": {"start": 0.001, "stop": 15.0, "num": 32}}],
        name="bench-load",
    )

    def render(threads: int) -> None:
        import contextlib
        import io

        with contextlib.redirect_stdout(io.StringIO()):
            code = command(
                [
                    "render",
                    "example",
                    "--grid",
                    "64x64",
                    "--pitch-um",
                    "2",
                    "--system",
                    "840nm-high",
                    "--out",
                    str(tmp / "r.npz"),
                    "--force",
                    "--no-progress",
                    "--threads",
                    str(threads),
                ]
            )
        if code != 0:
            raise RuntimeError("torchdoct render example failed")

    return {
        "simulate example (500 trials)": lambda t: simulate(example, trials=500, threads=t),
        "render example --grid 64x64 --system 840nm-high": render,
        "sweep example, 32 cells × 64 trials": lambda t: run_sweeps([sweep], trials=64, workers=t),
        "simulate paper cell, diffusion D=15, 840 nm (256 trials)": lambda t: simulate(
            _paper_cell(), trials=256, threads=t
        ),
    }


def _paper_cell() -> Scene:
    return Scene(
        systems=(paper_systems()[0],),
        protocol=Protocol(n_frames=32, frame_interval_s=0.2048),
        populations=(Population(density_per_um3=0.055, motion=(paper_motions()["diffusion D=15"],)),),
        name="840nm-high diffusion D=15",
    )


def bench_load(
    *, command: Callable[[list[str]], int], repeats: int = 3, threads: int | None = None, progress: bool = False
) -> dict[str, Any]:
    """Each workload alone on one thread, alone with ``threads`` (default: the usable cores), and with
    ``threads`` beside a busy neighbour process (:class:`BusyNeighbour`); best of ``repeats`` each.

    ``command(argv) -> int``: the command line that runs the ``render`` workload as a user would
    (``torchdoct bench load`` passes its own; this package imports no command line).

    The policy's target: beside a second job, every workload within 1.5× of its one-thread time alone.
    """
    import tempfile

    from ..runtime.threads import resolve_threads

    threads = resolve_threads(threads)
    rows: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = _workloads(Path(tmp), command)
        for fn in work.values():  # warm-up (imports, caches)
            fn(1)

        def best(fn, t: int) -> float:
            out = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn(t)
                out = min(out, time.perf_counter() - t0)
            return out

        steps = [(name, mode) for mode in ("alone, 1 thread", f"alone, {threads} threads") for name in work]
        steps += [(name, f"loaded, {threads} threads") for name in work]
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(steps), desc="bench load", unit="run")
        for name, mode in steps[: 2 * len(work)]:
            rows.setdefault(name, {})[mode] = best(work[name], 1 if mode.endswith(" 1 thread") else threads)
            if bar is not None:
                bar.update()
        with BusyNeighbour():
            for name, mode in steps[2 * len(work) :]:
                rows[name][mode] = best(work[name], threads)
                if bar is not None:
                    bar.update()
        if bar is not None:
            bar.close()
    out = []
    for name, r in rows.items():
        one = r["alone, 1 thread"]
        out.append(
            {
                "workload": name,
                "alone_1_thread_s": one,
                "alone_s": r[f"alone, {threads} threads"],
                "loaded_s": r[f"loaded, {threads} threads"],
                "speedup_alone": one / r[f"alone, {threads} threads"],
                "loaded_over_1_thread_alone": r[f"loaded, {threads} threads"] / one,
            }
        )
    return {
        "benchmark": "load",
        "threads": threads,
        "repeats": repeats,
        "target_ratio": 1.5,
        "neighbour": "one process simulating the example scene on one core",
        "machine": machine_info(),
        "rows": out,
    }


def format_load_table(result: dict[str, Any]) -> str:
    t = result["threads"]
    lines = [
        f"| workload | 1 thread alone (s) | {t} threads alone (s) | {t} threads beside a busy job (s) | "
        f"beside a busy job ÷ 1 thread alone |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['workload']} | {r['alone_1_thread_s']:.2f} | {r['alone_s']:.2f} | {r['loaded_s']:.2f} | "
            f"{r['loaded_over_1_thread_alone']:.2f} |"
        )
    lines.append("")
    lines.append(
        f"target: beside a busy job within {result['target_ratio']}× of the one-thread time alone; "
        f"best of {result['repeats']}; {result['machine']['cpu_count']} cores"
    )
    return "\n".join(lines)

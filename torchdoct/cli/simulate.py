"""``torchdoct scenes``, ``torchdoct plan`` and ``torchdoct simulate``: the shipped scenes, what a
simulation will run, and a simulation's LIV/OCDS summary."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..files import atomic_write, check_out
from .command import Command

__all__ = ["COMMANDS"]


def _scenes_arguments(p) -> None:
    pass


def _scenes(args) -> int:
    from ..sim import config
    from ..sim.scenes import shipped_scenes

    for name, path in shipped_scenes().items():
        sc = config.load_scene(path)
        print(f"{name:>22}: {sc.description}")
    return 0


def _plan_arguments(pl) -> None:
    pl.add_argument("scene", help="scene TOML file or shipped scene name")
    pl.add_argument("--trials", type=int, default=None, help="trials to cost (default: the scene's)")
    pl.add_argument("--tolerance", type=float, default=None, help="PSF truncation tolerance (amplitude)")
    pl.add_argument("--json", action="store_true", help="print the plan as JSON")


def _plan(args) -> int:
    from ..sim import config
    from ..sim.plan import make_plan

    scene = config.load_scene(args.scene)
    plan = make_plan(scene, truncation_tolerance=args.tolerance)
    print(plan.to_json() if args.json else plan.describe(args.trials or scene.simulation.trials))
    return 0


def _simulate_arguments(sm) -> None:
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


def _simulate(args) -> int:
    from ..sim import config
    from ..sim.metrics import summarize
    from ..sim.simulate import simulate

    out = check_out(args.out, args.force, ".npz")
    scene = config.load_scene(args.scene)
    try:
        result = simulate(
            scene,
            trials=args.trials,
            seed=args.seed,
            dtype=args.dtype,
            device=args.device,
            truncation_tolerance=args.tolerance,
            progress=not args.no_progress,
        )
    except ValueError as err:  # what the scene asks that the run cannot hold: named with its file
        raise ValueError(f"{args.scene}: {err}") from None
    metrics = result.metrics()
    summary = summarize(metrics, result.system_names)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_format_summary(summary, result))
    if out is not None:
        _save_npz(out, result, metrics)
        print(f"wrote {out}")
    return 0


def _format_summary(summary: dict[str, Any], result) -> str:
    sc = result.scene
    lines = [
        f"scene {sc.name!r}: {result.trials} trials, seed {result.seed}, "
        f"{sc.protocol.n_frames} frames, {result.signals.dtype}, {result.elapsed_s:.2f} s"
    ]
    est = sc.analysis.ocds_estimator
    lines.append(
        f"LIV: ddof-0 variance of 10·log10 I (dB²); OCDS: −slope of the {est} correlation of the "
        f"{sc.analysis.ocds_scale} intensity over {list(sc.analysis.ocds_delay_range_s)} s (1/s)"
    )
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
        lines.append(
            "empty: trials with I = 0 at some frame (no scatterer within the PSF truncation); "
            "their dB metrics are NaN and excluded from the means"
        )
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

    atomic_write(path, write)


COMMANDS = {
    "scenes": Command("list the shipped example scenes", _scenes_arguments, _scenes),
    "plan": Command("print what a simulation of a scene will run", _plan_arguments, _plan),
    "simulate": Command("simulate a scene and print its LIV/OCDS summary", _simulate_arguments, _simulate),
}

"""What accuracy costs in time: measured trade-off curves of the point simulator.

For each test cell (one motion seen by the paper's 840-nm, 4.9/3.8-µm system, 32 frames at 204.8 ms)
the knobs a user turns are measured against a converged reference:

* **truncation tolerance** (PSF amplitude cutoff): the bias of mean LIV and mean OCDS against the
  reference (tolerance 1e-8, float64, many trials) ± its standard error; the relative error of the
  mean intensity against ``⟨I⟩ = ρ·π^{3/2}·s_x²·s_z`` (physics.md §5.2) and of g1 at one frame lag
  against its closed form (physics.md §5.3); the documented bound on the relative mean-square field
  error, ``Q(3/2, 2·ln(1/tol))``. A bias smaller than its standard error is reported as unresolved;
* **trials**: the error of a mean is its standard error ``SD/√n`` (measured SD of a large reference);
* **dtype**: float32 vs float64 with one seed (same scatterers): the largest per-trial LIV/OCDS
  difference and the bias of the means;
* **chunk size**: results are bit-identical (asserted here too), only time and memory change.

Every point carries its measured wall time. The total error of a (tolerance, trials, dtype) choice
is ``√(bias² + SE²)``; the Pareto front is the set of choices no other choice beats in both time
and error. :func:`recommend` picks, for a target error, the cheapest choice on the front.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from ..conventions import mean_intensity, truncation_error_bound
from ..runtime.interrupt import progress_disabled
from ..runtime.machine import machine_info
from ..sim.config import Analysis, Diffusion, Flow, OCTSystem, Population, Protocol, RandomBallistic, Scene
from ..sim.simulate import simulate

__all__ = [
    "tradeoff_cells",
    "simulator_tradeoffs",
    "pareto_front",
    "recommend",
    "plot_tradeoffs",
    "format_table",
    "DEFAULTS",
    "fidelity_cells",
    "fidelity_settings",
    "feature_fidelity",
    "format_fidelity_table",
]

#: The shipped defaults (what a scene gets without a [simulation] table, and the paper's trials).
DEFAULTS = {"truncation_tolerance": 1e-2, "dtype": "float32", "trials": 500}
_REFERENCE_TOLERANCE = 1e-8


def tradeoff_cells() -> dict[str, Scene]:
    """Three motions at mid-range parameters, and diffusion at the paper's largest D (where the
    periodic cell of the random walk is largest), on the paper's 840-nm high-resolution system."""
    system = OCTSystem(name="840nm-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    protocol = Protocol(n_frames=32, frame_interval_s=0.2048)
    analysis = Analysis(metrics=("liv", "ocds"))
    motions = {
        "diffusion D=0.05": Diffusion(diffusion_um2_per_s=0.05),
        "ballistic v=0.5": RandomBallistic(speed_um_per_s=0.5, directions="uniform-angles"),
        "flow v=1 (45°)": Flow(speed_um_per_s=1.0, polar_angle_deg=45.0),
        "diffusion D=15": Diffusion(diffusion_um2_per_s=15.0),
    }
    return {
        name: Scene(
            systems=(system,),
            protocol=protocol,
            analysis=analysis,
            name=name,
            populations=(Population(density_per_um3=0.055, motion=(m,)),),
        )
        for name, m in motions.items()
    }


def _g1_theory(scene: Scene, lag: int) -> float:
    from ..sim import theory

    s = scene.systems[0]
    m = scene.populations[0].motion[0]
    tau = lag * scene.protocol.frame_interval_s
    kw = dict(
        lateral_resolution_um=s.lateral_resolution_um,
        axial_resolution_um=s.axial_resolution_um,
        wavelength_um=s.wavelength_um,
        refractive_index=s.refractive_index,
    )
    if isinstance(m, Diffusion):
        g = theory.g1_diffusion(tau, diffusion_um2_per_s=m.diffusion_um2_per_s, **kw)
    elif isinstance(m, RandomBallistic):
        g = theory.g1_ballistic(tau, speed_um_per_s=m.speed_um_per_s, directions=m.directions, **kw)
    else:
        g = theory.g1_flow(tau, speed_um_per_s=m.speed_um_per_s, polar_angle_deg=m.polar_angle_deg, **kw)
    return complex(np.asarray(g)).real if np.iscomplexobj(g) else float(g)


def _g1_sim(signals: torch.Tensor, lag: int) -> tuple[complex, float]:
    """Estimate of g1(lag) = <E(t+τ) E*(t)>/<I> and its standard error over trials."""
    e = signals[:, 0].to(torch.complex128)
    i_mean = float((e.abs() ** 2).mean())
    per_trial = (e[:, lag:] * e[:, :-lag].conj()).mean(-1) / i_mean
    est = complex(per_trial.mean())
    se = float(per_trial.real.std() / math.sqrt(per_trial.numel()))
    return est, se


def _run(scene: Scene, trials: int, seed: int, tol: float, dtype: str, chunk: int | None = None):
    t0 = time.perf_counter()
    res = simulate(scene, trials=trials, seed=seed, dtype=dtype, truncation_tolerance=tol, chunk_trials=chunk)
    wall = time.perf_counter() - t0
    m = res.metrics()
    return res, {k: m[k][:, 0].double() for k in ("liv", "ocds")}, wall


def _paired(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    ok = torch.isfinite(a) & torch.isfinite(b)
    d = (a - b)[ok]
    return float(d.mean()), float(d.std() / math.sqrt(max(1, d.numel())))


def simulator_tradeoffs(
    *,
    trials: int = 8192,
    reference_trials: int = 16384,
    tolerances: Sequence[float] = (1e-1, 1e-2, 1e-3, 1e-4),
    trials_grid: Sequence[int] = (64, 128, 256, 500, 1024, 2048, 4096),
    chunk_trials: Sequence[int] = (64, 256, 1024, 4096),
    seed: int = 20261122,
    progress: bool = False,
) -> dict[str, Any]:
    """Measure every knob of every :func:`tradeoff_cells` cell; returns a JSON-ready dict."""
    from tqdm.auto import tqdm

    cells_out = []
    cells = tradeoff_cells()
    bar = tqdm(
        total=len(cells) * (2 + len(tolerances) + len(trials_grid) + len(chunk_trials)),
        desc="trade-offs",
        disable=progress_disabled(progress),
    )
    for name, scene in cells.items():
        ref_res, ref, ref_wall = _run(scene, reference_trials, seed + 1, _REFERENCE_TOLERANCE, "float64")
        bar.update(1)
        sd = {k: float(v[torch.isfinite(v)].std()) for k, v in ref.items()}
        ref_mean = {k: float(v[torch.isfinite(v)].mean()) for k, v in ref.items()}
        g1_true = _g1_theory(scene, 1)
        tol_rows = []
        i_true = mean_intensity(
            scene.populations[0].density_per_um3,
            scene.systems[0].lateral_resolution_um,
            scene.systems[0].axial_resolution_um,
        )
        for tol in tolerances:
            res, met, wall = _run(scene, trials, seed, tol, "float32")
            g1, g1_se = _g1_sim(res.signals, 1)
            inten = (res.signals.abs() ** 2).double().mean(-1)[:, 0]
            row = {
                "tolerance": tol,
                "dtype": "float32",
                "wall_s": wall,
                "ms_per_trial": 1e3 * wall / trials,
                "field_mse_bound": truncation_error_bound(tol),
                "g1_lag1": g1.real,
                "g1_lag1_se": g1_se,
                "g1_lag1_error": abs(g1.real - g1_true),
                "mean_intensity_rel_error": float(inten.mean()) / i_true - 1.0,
                "mean_intensity_rel_se": float(inten.std()) / math.sqrt(trials) / i_true,
            }
            for k in ("liv", "ocds"):
                v = met[k][torch.isfinite(met[k])]
                row[f"{k}_bias"] = float(v.mean()) - ref_mean[k]
                row[f"{k}_bias_se"] = math.hypot(
                    float(v.std()) / math.sqrt(v.numel()), sd[k] / math.sqrt(reference_trials)
                )
            tol_rows.append(row)
            bar.update(1)
        # dtype at the default tolerance, same seed
        n_small = min(trials, 2048)
        _, m32, w32 = _run(scene, n_small, seed, DEFAULTS["truncation_tolerance"], "float32")
        _, m64, w64 = _run(scene, n_small, seed, DEFAULTS["truncation_tolerance"], "float64")
        bar.update(1)
        dtype_row = {
            "trials": n_small,
            "float32_ms_per_trial": 1e3 * w32 / n_small,
            "float64_ms_per_trial": 1e3 * w64 / n_small,
        }
        for k in ("liv", "ocds"):
            dtype_row[f"{k}_max_abs_diff"] = float((m32[k] - m64[k]).abs().nan_to_num(0.0).max())
            dtype_row[f"{k}_bias"], dtype_row[f"{k}_bias_se"] = _paired(m32[k], m64[k])
        trial_rows = []
        for n in trials_grid:
            _, met, wall = _run(scene, n, seed + 2, DEFAULTS["truncation_tolerance"], "float32")
            row = {"trials": n, "wall_s": wall, "ms_per_trial": 1e3 * wall / n}
            for k in ("liv", "ocds"):
                v = met[k][torch.isfinite(met[k])]
                row[f"{k}_error"] = abs(float(v.mean()) - float(ref[k][torch.isfinite(ref[k])].mean()))
                row[f"{k}_se"] = sd[k] / math.sqrt(n)
            trial_rows.append(row)
            bar.update(1)
        chunk_rows = []
        first = None
        for c in chunk_trials:
            res, _, wall = _run(scene, n_small, seed, DEFAULTS["truncation_tolerance"], "float32", chunk=c)
            if first is None:
                first = res.signals
            identical = bool(torch.equal(first, res.signals))
            if not identical:
                raise AssertionError(f"{name}: chunk_trials={c} changed the result")
            chunk_rows.append(
                {
                    "chunk_trials": c,
                    "trials": n_small,
                    "wall_s": wall,
                    "ms_per_trial": 1e3 * wall / n_small,
                    "bit_identical": identical,
                }
            )
            bar.update(1)
        cells_out.append(
            {
                "cell": name,
                "reference": {
                    "trials": reference_trials,
                    "tolerance": _REFERENCE_TOLERANCE,
                    "dtype": "float64",
                    "wall_s": ref_wall,
                    "liv_mean": float(ref["liv"].nanmean()),
                    "liv_sd": sd["liv"],
                    "ocds_mean": float(ref["ocds"].nanmean()),
                    "ocds_sd": sd["ocds"],
                    "g1_lag1_theory": g1_true,
                },
                "tolerance": tol_rows,
                "dtype": dtype_row,
                "trials": trial_rows,
                "chunk": chunk_rows,
            }
        )
    bar.close()
    out = {
        "benchmark": "tradeoffs-simulate",
        "trials_per_point": trials,
        "seed": seed,
        "defaults": DEFAULTS,
        "machine": machine_info(),
        "cells": cells_out,
    }
    out["pareto"] = {c["cell"]: pareto_front(_choices(c)) for c in cells_out}
    out["recommendation"] = {c["cell"]: recommend(_choices(c), c) for c in cells_out}
    out["combined"] = combined_front(out)
    return out


def combined_front(result: dict[str, Any]) -> dict[str, Any]:
    """One default must serve every motion: the front over all cells together.

    A (tolerance, dtype, trials) choice costs the sum of its times over the cells and its error is
    the largest of its cells' errors (each ``√(bias² + SD²/n)`` of the mean LIV, in dB²). Returns the
    front, the defaults' point and whether the defaults are on it.
    """
    per_cell = [{(c["tolerance"], c["dtype"], c["trials"]): c for c in _choices(cell)} for cell in result["cells"]]
    keys = set.intersection(*(set(p) for p in per_cell))
    choices = [
        {
            "tolerance": k[0],
            "dtype": k[1],
            "trials": k[2],
            "time_s": sum(p[k]["time_s"] for p in per_cell),
            "error": max(p[k]["error"] for p in per_cell),
        }
        for k in sorted(keys)
    ]
    front = pareto_front(choices)
    d = _defaults_choice(choices)
    return {"front": front, "defaults": d, "defaults_on_front": any(c is d for c in front)}


def _choices(cell: dict[str, Any], metric: str = "liv") -> list[dict[str, Any]]:
    """(tolerance, dtype, trials) choices with predicted time and total error of the mean ``metric``.

    Time = measured ms/trial at that tolerance and dtype × trials; error = √(bias² + (SD/√n)²), the
    bias taken as its measured value or its standard error, whichever is larger (an unresolved bias
    counts as large as it could be).
    """
    sd = cell["reference"][f"{metric}_sd"]
    out = []
    for row in cell["tolerance"]:
        bias = max(abs(row[f"{metric}_bias"]), row[f"{metric}_bias_se"])
        for n in sorted({r["trials"] for r in cell["trials"]}):
            out.append(
                {
                    "tolerance": row["tolerance"],
                    "dtype": row["dtype"],
                    "trials": n,
                    "time_s": row["ms_per_trial"] * n / 1e3,
                    "error": math.sqrt(bias * bias + sd * sd / n),
                    "bias": bias,
                }
            )
    return out


def pareto_front(choices: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Choices that no other choice beats in both time and error (sorted by time)."""
    front = []
    best = math.inf
    for c in sorted(choices, key=lambda c: (c["time_s"], c["error"])):
        if c["error"] < best:
            front.append(c)
            best = c["error"]
    return front


def _defaults_choice(choices: list[dict[str, Any]]) -> dict[str, Any]:
    """The choice of the shipped defaults (the measured trial count nearest to the default's)."""
    n = min({c["trials"] for c in choices}, key=lambda n: abs(n - DEFAULTS["trials"]))
    return next(
        c
        for c in choices
        if c["tolerance"] == DEFAULTS["truncation_tolerance"] and c["dtype"] == DEFAULTS["dtype"] and c["trials"] == n
    )


def recommend(choices: list[dict[str, Any]], cell: dict[str, Any]) -> dict[str, Any]:
    """For the error of the shipped defaults, the cheapest choice on the front, and where the defaults sit."""
    front = pareto_front(choices)
    d = _defaults_choice(choices)
    cheapest = min((c for c in choices if c["error"] <= d["error"] * 1.02), key=lambda c: c["time_s"])
    on_front = any(c is d for c in front) or (d["time_s"] <= cheapest["time_s"] * 1.10)
    return {
        "defaults": d,
        "cheapest_at_same_error": cheapest,
        "defaults_on_front": bool(on_front),
        "time_ratio_defaults_vs_cheapest": d["time_s"] / cheapest["time_s"],
    }


def plot_tradeoffs(result: dict[str, Any], path: str) -> None:
    """Error of the mean LIV against wall time per cell, with the Pareto front and the defaults."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = result["cells"]
    fig, axes = plt.subplots(1, len(cells), figsize=(5 * len(cells), 4.2), constrained_layout=True)
    axes = np.atleast_1d(axes)
    for ax, cell in zip(axes, cells):
        ch = _choices(cell)
        tols = [math.log10(c["tolerance"]) for c in ch]
        sc = ax.scatter(
            [c["time_s"] for c in ch],
            [c["error"] for c in ch],
            s=14,
            c=tols,
            cmap="viridis",
            vmin=min(tols),
            vmax=max(tols),
            label="(tolerance, trials)",
        )
        front = pareto_front(ch)
        ax.plot([c["time_s"] for c in front], [c["error"] for c in front], "k-", lw=1, label="Pareto front")
        rec = recommend(ch, cell)["defaults"]
        ax.plot([rec["time_s"]], [rec["error"]], "r*", ms=14, label="defaults")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("error of mean LIV (dB²)")
        ax.set_title(cell["cell"])
        ax.legend(fontsize=7)
    fig.colorbar(sc, ax=axes, label="log10 truncation tolerance")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def format_table(result: dict[str, Any]) -> str:
    """Markdown tables: per cell and tolerance, time and errors; dtype and chunk rows; the defaults."""
    lines = []
    for cell in result["cells"]:
        ref = cell["reference"]
        lines.append(
            f"### {cell['cell']} (reference: {ref['trials']} trials, tolerance {ref['tolerance']:g}, "
            f"float64: LIV {ref['liv_mean']:.3f} ± SD {ref['liv_sd']:.2f} dB², OCDS "
            f"{ref['ocds_mean']:.4f} ± SD {ref['ocds_sd']:.3f} 1/s)"
        )
        lines.append(
            "| tolerance | ms/trial | field MSE bound | ⟨I⟩ rel. error | g1(Δt) error | "
            "LIV bias (dB²) | OCDS bias (1/s) |"
        )
        lines.append("|---:|---:|---:|---:|---:|---:|---:|")
        for r in cell["tolerance"]:
            lines.append(
                f"| {r['tolerance']:g} | {r['ms_per_trial']:.3f} | {r['field_mse_bound']:.1e} | "
                f"{r['mean_intensity_rel_error']:+.4f} ± {r['mean_intensity_rel_se']:.4f} | "
                f"{r['g1_lag1_error']:.4f} (SE {r['g1_lag1_se']:.4f}) | "
                f"{r['liv_bias']:+.3f} ± {r['liv_bias_se']:.3f} | {r['ocds_bias']:+.4f} ± {r['ocds_bias_se']:.4f} |"
            )
        d = cell["dtype"]
        lines.append(
            f"float32 {d['float32_ms_per_trial']:.3f} ms/trial vs float64 {d['float64_ms_per_trial']:.3f}; "
            f"same scatterers: max |ΔLIV| {d['liv_max_abs_diff']:.2e} dB², max |ΔOCDS| "
            f"{d['ocds_max_abs_diff']:.2e} 1/s"
        )
        lines.append(
            "chunk trials → ms/trial (bit-identical results): "
            + ", ".join(f"{c['chunk_trials']} → {c['ms_per_trial']:.3f}" for c in cell["chunk"])
        )
        rec = result["recommendation"][cell["cell"]]
        dft, ch = rec["defaults"], rec["cheapest_at_same_error"]
        lines.append(
            f"defaults (tol {dft['tolerance']:g}, {dft['dtype']}, {dft['trials']} trials): "
            f"{dft['time_s']:.3f} s, LIV error {dft['error']:.3f} dB²; cheapest at that error: tol "
            f"{ch['tolerance']:g}, {ch['trials']} trials, {ch['time_s']:.3f} s; defaults on the front: "
            f"{rec['defaults_on_front']}"
        )
        lines.append("")
    comb = result.get("combined") or combined_front(result)
    d = comb["defaults"]
    lines.append(
        "all cells together (time summed, error the worst cell's): front "
        + ", ".join(
            f"tol {c['tolerance']:g}/{c['trials']} trials ({c['time_s']:.3f} s, {c['error']:.3f} dB²)"
            for c in comb["front"]
        )
    )
    lines.append(
        f"defaults (tol {d['tolerance']:g}, {d['trials']} trials): {d['time_s']:.3f} s, worst-cell LIV error "
        f"{d['error']:.3f} dB²; on the combined front: {comb['defaults_on_front']}"
    )
    return "\n".join(lines)


def study_tradeoffs(
    study: str = "paper-reduced",
    *,
    trials_grid: Sequence[int] = (16, 32, 64, 128, 256),
    reference_trials: int = 512,
    workers: int = 1,
    progress: bool = False,
) -> dict[str, Any]:
    """Figure-level error of a study against trials per point, with the wall time of each run.

    Every curve point (part × comparison × motion value × system × metric) of the study is run at
    each trial count with the study's seed + 1 and compared with a reference run at
    ``reference_trials`` (the study's own seed, so the two are independent). The figure-level error
    is the RMS over points of ``mean_n − mean_ref``, per metric; its expectation from the standard
    errors, ``√mean(SE_n² + SE_ref²)``, is reported beside it. The full study's time at ``n`` trials
    is predicted from the measured ms per cell-trial.
    """
    from ..study import load_study, study_sweeps
    from ..study.sweep import run_sweeps

    st = load_study(study)
    sweeps = study_sweeps(st)
    keys = ["sweep", "cell", "system", "metric"]
    t0 = time.perf_counter()
    ref = run_sweeps(sweeps, trials=reference_trials, workers=workers, progress=progress, desc="reference")
    ref_wall = time.perf_counter() - t0
    rt = ref.table().set_index(keys)
    rows = []
    for n in trials_grid:
        t0 = time.perf_counter()
        res = run_sweeps(
            sweeps, trials=int(n), seed=st.seed + 1, workers=workers, progress=progress, desc=f"{n} trials"
        )
        wall = time.perf_counter() - t0
        tab = res.table().set_index(keys)
        row: dict[str, Any] = {
            "trials": int(n),
            "wall_s": wall,
            "cells": len(res.cells),
            "ms_per_cell_trial": 1e3 * wall / (len(res.cells) * n),
        }
        for metric in ("liv", "ocds"):
            a = tab.xs(metric, level="metric")
            b = rt.xs(metric, level="metric").loc[a.index]
            ok = np.isfinite(a["mean"].to_numpy()) & np.isfinite(b["mean"].to_numpy())
            d = a["mean"].to_numpy()[ok] - b["mean"].to_numpy()[ok]
            se2 = a["se"].to_numpy()[ok] ** 2 + b["se"].to_numpy()[ok] ** 2
            row[f"{metric}_rms_error"] = float(np.sqrt(np.mean(d * d)))
            row[f"{metric}_rms_expected"] = float(np.sqrt(np.mean(se2)))
            row[f"{metric}_max_abs_error"] = float(np.abs(d).max())
        rows.append(row)
    return {
        "benchmark": "tradeoffs-study",
        "study": study,
        "reference_trials": reference_trials,
        "reference_wall_s": ref_wall,
        "cells": len(ref.cells),
        "rows": rows,
        "machine": machine_info(),
    }


def format_study_table(result: dict[str, Any]) -> str:
    lines = [
        f"study `{result['study']}` ({result['cells']} cells) against a {result['reference_trials']}-trial "
        "reference: RMS over curve points of the error of the mean (expected from the SEs in brackets)",
        "| trials/point | wall (s) | ms per cell-trial | LIV RMS error (dB²) | OCDS RMS error (1/s) |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['trials']} | {r['wall_s']:.1f} | {r['ms_per_cell_trial']:.2f} | "
            f"{r['liv_rms_error']:.3f} ({r['liv_rms_expected']:.3f}) | "
            f"{r['ocds_rms_error']:.4f} ({r['ocds_rms_expected']:.4f}) |"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------
# fidelity chosen on what the models read


#: Features whose bias the fidelity part measures: the signature spec's intensity features (what the
#: shipped signature models read), the field group, and LIV/OCDS (the LIV/OCDS models).
FIDELITY_SIGNATURE = (
    tuple(f"rho_lin_{m}" for m in (1, 2, 3, 4, 6, 8, 11, 16, 22, 28))
    + ("lin_contrast", "db_variance")
    + tuple(f"g1_{m}" for m in (1, 2, 3, 4, 6, 8))
    + tuple(f"g1_phase_{m}" for m in (1, 2, 3, 4, 6, 8))
    + ("phase_ramp",)
)
FIDELITY_FEATURES = FIDELITY_SIGNATURE + ("liv", "ocds")
#: Family-wise false-alarm rate of the "resolvable bias" decision of one setting (Bonferroni over its
#: cells × configurations × features).
FIDELITY_ALPHA = 0.01
_FIDELITY_REFERENCE = {"truncation_tolerance": 1e-6, "truncation": "hard", "dtype": "float64"}


def fidelity_cells() -> dict[str, Scene]:
    """Hard cells for a truncated PSF, seen by the shipped signature models' three configurations
    (840 nm at 4.9/3.8 µm, axial=14, lateral=18; 32 frames at 204.8 ms; 0.05 scatterers/µm³):
    slow flow near the beam axis (short lags), slow diffusion, slow random-ballistic motion."""
    systems = (
        OCTSystem(name="original", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8),
        OCTSystem(name="axial=14", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=14.0),
        OCTSystem(name="lateral=18", wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8),
    )
    protocol = Protocol(n_frames=32, frame_interval_s=0.2048)
    motions = {
        "flow v=0.5 θ=20°": Flow(speed_um_per_s=0.5, polar_angle_deg=20.0, azimuth_deg=30.0),
        "flow v=0.2 θ=0°": Flow(speed_um_per_s=0.2, polar_angle_deg=0.0),
        "diffusion D=0.002": Diffusion(diffusion_um2_per_s=0.002),
        "ballistic v=0.03": RandomBallistic(speed_um_per_s=0.03, directions="isotropic"),
        "ballistic v=0.3 uniform-angles": RandomBallistic(speed_um_per_s=0.3, directions="uniform-angles"),
    }
    return {
        name: Scene(
            systems=systems,
            protocol=protocol,
            analysis=Analysis(metrics=("liv", "ocds")),
            name=name,
            populations=(Population(density_per_um3=0.05, motion=(m,)),),
        )
        for name, m in motions.items()
    }


def _truncation_modes() -> tuple[str, ...]:
    import inspect

    return ("hard", "taper") if "truncation" in inspect.signature(simulate).parameters else ("hard",)


def fidelity_settings() -> list[dict[str, Any]]:
    """(tolerance, truncation, dtype) rows: hard 1e-2/1e-3/1e-4 in float32 and float64, and the smooth
    taper at 1e-2 and 1e-3 in float32 where the simulator has it."""
    rows = [
        {"truncation_tolerance": t, "truncation": "hard", "dtype": d}
        for t in (1e-2, 1e-3, 1e-4)
        for d in ("float32", "float64")
    ]
    if "taper" in _truncation_modes():
        rows += [{"truncation_tolerance": t, "truncation": "taper", "dtype": "float32"} for t in (1e-2, 1e-3)]
    return rows


def _fidelity_run(scene: Scene, trials: int, seed: int, setting: dict[str, Any]) -> tuple[dict[str, np.ndarray], float]:
    """Features ``{name: [trials, systems]}`` (float64) of one run, and its wall time on one thread."""
    from ..sim.metrics import compute_metrics
    from ..sim.signature import signature

    kw = dict(truncation_tolerance=setting["truncation_tolerance"], dtype=setting["dtype"])
    if setting.get("truncation", "hard") != "hard" or "taper" in _truncation_modes():
        kw["truncation"] = setting.get("truncation", "hard")
    t0 = time.perf_counter()
    res = simulate(scene, trials=trials, seed=seed, threads=1, **kw)
    wall = time.perf_counter() - t0
    x = res.signals.to(torch.complex128)
    _, f = signature(x, res.frame_times_s, names=FIDELITY_SIGNATURE)
    out = {n: f[..., i].numpy() for i, n in enumerate(FIDELITY_SIGNATURE)}
    met = compute_metrics(x, res.frame_times_s, scene.analysis)
    out["liv"], out["ocds"] = met["liv"].numpy(), met["ocds"].numpy()
    return out, wall


def _moments(v: np.ndarray) -> tuple[float, float, int]:
    v = v[np.isfinite(v)]
    return float(v.mean()), float(v.std(ddof=1)), int(v.size)


def feature_fidelity(
    *,
    trials: int = 8192,
    reference_trials: int = 16384,
    seed: int = 20261201,
    settings: Sequence[dict[str, Any]] | None = None,
    cells: Sequence[str] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Bias of every model feature against a tight reference, per simulator setting, and its cost.

    For each :func:`fidelity_cells` cell, each configuration and each feature of
    :data:`FIDELITY_FEATURES`: ``bias = mean − mean_ref`` with ``SE = √(SD²/n + SD_ref²/n_ref)`` and
    ``z = bias/SE``, the reference being torchdoct at tolerance 1e-6 (hard), float64 (a scatterer
    enters at 1e-6 of the peak amplitude; the independent reference simulator of the test suite
    agrees with torchdoct at 1e-4 on every feature, ``tests/reference``). A setting has *no
    resolvable bias* when every ``|z|`` is within the Bonferroni bound at family-wise rate
    :data:`FIDELITY_ALPHA` over its comparisons; the smallest bias it could resolve is that bound
    times the SE (reported for ``rho_lin_1``). Cost: ms per trial of the three configurations on one
    thread. ``cells``: a subset of the cell names (default all). Returns a JSON-ready dict with the
    cheapest setting without resolvable bias.
    """
    from scipy import special
    from tqdm.auto import tqdm

    settings = list(settings) if settings is not None else fidelity_settings()
    all_cells = fidelity_cells()
    wanted = list(all_cells) if cells is None else list(cells)
    unknown = sorted(set(wanted) - set(all_cells))
    if unknown:
        raise ValueError(f"unknown fidelity cell(s) {unknown}; known: {list(all_cells)}")
    cells = {k: all_cells[k] for k in wanted}
    bar = tqdm(total=len(cells) * (1 + len(settings)), desc="fidelity", disable=progress_disabled(progress))
    per_setting: list[dict[str, Any]] = [{**s, "cells": [], "wall_s": 0.0, "trials": 0} for s in settings]
    ref_out = []
    for c, (name, scene) in enumerate(cells.items()):
        ref, ref_wall = _fidelity_run(scene, reference_trials, seed + 1000 + c, _FIDELITY_REFERENCE)
        bar.update(1)
        ref_m = {f: [_moments(ref[f][:, s]) for s in range(len(scene.systems))] for f in FIDELITY_FEATURES}
        ref_out.append(
            {
                "cell": name,
                "wall_s": ref_wall,
                "trials": reference_trials,
                "means": {f: [m[0] for m in v] for f, v in ref_m.items()},
                "sds": {f: [m[1] for m in v] for f, v in ref_m.items()},
            }
        )
        for row in per_setting:
            feats, wall = _fidelity_run(scene, trials, seed + c, row)
            bar.update(1)
            comps = []
            for f in FIDELITY_FEATURES:
                for s, system in enumerate(scene.systems):
                    m, sd, n = _moments(feats[f][:, s])
                    rm, rsd, rn = ref_m[f][s]
                    se = math.sqrt(sd * sd / n + rsd * rsd / rn)
                    bias = m - rm
                    comps.append(
                        {
                            "feature": f,
                            "config": system.name,
                            "mean": m,
                            "reference": rm,
                            "bias": bias,
                            "se": se,
                            "z": bias / se if se > 0 else 0.0,
                            "nan": int(feats[f].shape[0] - n),
                        }
                    )
            row["cells"].append({"cell": name, "wall_s": wall, "ms_per_trial": 1e3 * wall / trials, "rows": comps})
            row["wall_s"] += wall
            row["trials"] += trials
    bar.close()
    for row in per_setting:
        comps = [r for cell in row["cells"] for r in cell["rows"]]
        bound = float(-special.ndtri(FIDELITY_ALPHA / (2.0 * len(comps))))
        worst = max(comps, key=lambda r: abs(r["z"]))
        ll = [r for r in comps if r["feature"] in ("liv", "ocds")]
        worst_ll = max(ll, key=lambda r: abs(r["z"]))
        r1 = [r for r in comps if r["feature"] == "rho_lin_1"]
        row.update(
            {
                "ms_per_trial": 1e3 * row["wall_s"] / row["trials"],
                "z_bound": bound,
                "comparisons": len(comps),
                "max_abs_z": abs(worst["z"]),
                "worst": worst,
                "resolvable_bias": abs(worst["z"]) > bound,
                "max_abs_z_liv_ocds": abs(worst_ll["z"]),
                "worst_liv_ocds": worst_ll,
                "rho_lin_1_worst": max(r1, key=lambda r: abs(r["z"])),
                "rho_lin_1_max_se": max(r["se"] for r in r1),
                "resolvable_features": sorted({r["feature"] for r in comps if abs(r["z"]) > bound}),
            }
        )
    clean = [r for r in per_setting if not r["resolvable_bias"]]
    choice = min(clean, key=lambda r: r["ms_per_trial"]) if clean else None
    return {
        "benchmark": "tradeoffs-fidelity",
        "trials": trials,
        "reference_trials": reference_trials,
        "seed": seed,
        "reference": _FIDELITY_REFERENCE,
        "features": list(FIDELITY_FEATURES),
        "alpha": FIDELITY_ALPHA,
        "cells": ref_out,
        "settings": per_setting,
        "machine": machine_info(),
        "cheapest_without_resolvable_bias": None
        if choice is None
        else {k: choice[k] for k in ("truncation_tolerance", "truncation", "dtype", "ms_per_trial")},
    }


def _setting_label(r: dict[str, Any]) -> str:
    return f"{r['truncation']} {r['truncation_tolerance']:g} {r['dtype']}"


def format_fidelity_table(result: dict[str, Any]) -> str:
    """Markdown: per setting, cost, the worst |z| over every feature (and over LIV/OCDS alone), the
    ``rho_lin_1`` bias, and the features with a resolvable bias; then per-cell ``rho_lin_1`` biases."""
    ref = result["reference"]
    lines = [
        f"feature bias against torchdoct at tolerance {ref['truncation_tolerance']:g} ({ref['truncation']}, "
        f"{ref['dtype']}, {result['reference_trials']} trials per cell); {result['trials']} trials per cell and "
        f"setting; cells: {', '.join(c['cell'] for c in result['cells'])}; |z| bound: Bonferroni at family-wise "
        f"{result['alpha']:g} over each setting's comparisons",
        "| truncation | tolerance | dtype | ms/trial | max \\|z\\| (feature@config) | bound | max \\|z\\| LIV/OCDS | "
        "worst rho_lin_1 bias ± SE | resolvable bias in |",
        "|---|---:|---|---:|---|---:|---:|---|---|",
    ]
    for r in result["settings"]:
        w, r1 = r["worst"], r["rho_lin_1_worst"]
        lines.append(
            f"| {r['truncation']} | {r['truncation_tolerance']:g} | {r['dtype']} | {r['ms_per_trial']:.3f} | "
            f"{r['max_abs_z']:.1f} ({w['feature']}@{w['config']}) | {r['z_bound']:.2f} | "
            f"{r['max_abs_z_liv_ocds']:.1f} | {r1['bias']:+.4f} ± {r1['se']:.4f} ({r1['config']}) | "
            f"{', '.join(r['resolvable_features']) or 'none'} |"
        )
    lines.append("")
    lines.append("rho_lin_1 bias ± SE per cell (worst configuration):")
    lines.append("| setting | " + " | ".join(c["cell"] for c in result["cells"]) + " |")
    lines.append("|---|" + "---:|" * len(result["cells"]))
    for r in result["settings"]:
        cells = []
        for cell in r["cells"]:
            r1 = max((x for x in cell["rows"] if x["feature"] == "rho_lin_1"), key=lambda x: abs(x["z"]))
            cells.append(f"{r1['bias']:+.4f} ± {r1['se']:.4f}")
        lines.append(f"| {_setting_label(r)} | " + " | ".join(cells) + " |")
    ch = result["cheapest_without_resolvable_bias"]
    lines.append("")
    lines.append(
        "cheapest setting with no resolvable bias on any feature: "
        + (
            f"{ch['truncation']} truncation at {ch['truncation_tolerance']:g}, {ch['dtype']} ({ch['ms_per_trial']:.3f} ms/trial)"
            if ch
            else "none"
        )
    )
    return "\n".join(lines)

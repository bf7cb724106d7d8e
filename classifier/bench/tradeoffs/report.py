"""The result as Markdown tables (:func:`format_table`) and a PNG of the fronts (:func:`plot_tradeoffs`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .pareto import _Z_DOMINATED
from .plan import ONE_CONFIGURATION


def _f(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def _pm(m: dict[str, Any] | None, key: str, digits: int = 2) -> str:
    if m is None or m.get(key) is None:
        return "–"
    se = m.get(f"{key}_se")
    return f"{m[key]:.{digits}f} ± {se:.{digits}f}" if se is not None else f"{m[key]:.{digits}f}"


_TIME_LABELS = {
    "build_s": "build time [s]",
    "training_s": "training [s]",
    "inference_ort_us": "onnxruntime [µs/sample]",
    "inference_us_per_pixel": "inference [µs/pixel]",
    "pixels_per_decision": "pixels per decision",
}


def format_table(result: dict[str, Any]) -> str:
    """Markdown: one table per axis (± bootstrap SE), then the Pareto fronts and recommendations."""
    r = result
    mach = r["machine"]
    L = [
        f"Classifier trade-offs{' (quick)' if r['quick'] else ''}: test split seed {r['test_split']['seed']}, "
        f"{r['test_split']['draws']} draws × {r['test_split']['replicates']} replicates × "
        f"{r['test_split']['trials_per_draw']} trials; error = 1 − balanced accuracy (identifiable, decided); "
        f"± = bootstrap SE over test draws ({r['test_split']['bootstrap_resamples']} resamples). torch "
        f"{mach['torch']}, {mach['torch_threads']} thread(s), {mach['cpu_count']} CPUs; total {r['total_s']:.0f} s.",
        "",
    ]
    pools = r["evaluation_pools"]
    fronts = {
        (p["axis"], p["time_key"], p["pool"]): set(p["front"])
        for ax in r["axes"].values()
        for p in ax["pareto"]
        if p["error_key"] == "error"
    }
    for name in ("training_draws", "feature_spec", "model_size"):
        ax = r["axes"][name]
        tk = ax["time_keys"][0]
        L.append(f"### {ax['title']}")
        L.append("")
        head = [
            "setting",
            "simulation [s]",
            "training [s]",
            "epochs",
            "build [s]",
            "torch [µs/sample]",
            "onnxruntime [µs/sample]",
        ]
        if name == "model_size":
            head.insert(1, "weights")
        for pool in pools:
            head += [f"coverage (pool {pool})", f"bal. acc. (pool {pool})", f"strict acc. (pool {pool})"]
        head += [f"front (pool {pool})" for pool in pools]
        L.append("| " + " | ".join(head) + " |")
        L.append("|---|" + "---:|" * (len(head) - 1))
        for row in ax["rows"]:
            cells = [
                f"**{row['label']}** (default)" if row["is_default"] else row["label"],
                _f(row["simulation_s"], 1),
                _f(row["training_s"], 1),
                str(row["epochs"]),
                _f(row["build_s"], 1),
                _f(row["inference_torch_us"], 2),
                _f(row["inference_ort_us"], 2),
            ]
            if name == "model_size":
                cells.insert(1, str(row["parameters"]))
            for pool in pools:
                m = row["pools"].get(pool)
                cells += [_pm(m, "coverage"), _pm(m, "balanced_accuracy"), _pm(m, "strict_accuracy_common")]
            cells += ["✓" if row["label"] in fronts.get((name, tk, pool), ()) else "" for pool in pools]
            L.append("| " + " | ".join(cells) + " |")
        L.append("")
        if name == "feature_spec":
            L.append(
                "Coverage and balanced accuracy use each spec's own ground truth (fewer configurations: more "
                "draws indeterminate); the strict accuracy uses the draws identifiable under the "
                "single-acquisition truth for every spec."
            )
            L.append("")
    ax = r["axes"]["pool"]
    L.append(f"### {ax['title']}")
    L.append("")
    L.append(
        "| pool (independent pixels) | window | inference [µs/pixel] | coverage | bal. acc. | strict acc. | ECE "
        "| front (time) | front (pixels per decision) |"
    )
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in ax["rows"]:
        m = row["pools"]["own"]
        lab = f"**{row['pool']}** (default)" if row["is_default"] else str(row["pool"])
        L.append(
            f"| {lab} | {row['window']}×{row['window']} | {_f(row['inference_us_per_pixel'], 3)} | "
            f"{_pm(m, 'coverage')} | {_pm(m, 'balanced_accuracy')} | {_pm(m, 'strict_accuracy_common')} | "
            f"{_f(m['ece'], 3)} | "
            f"{'✓' if row['label'] in fronts[('pool', 'inference_us_per_pixel', 'own')] else ''} | "
            f"{'✓' if row['label'] in fronts[('pool', 'pixels_per_decision', 'own')] else ''} |"
        )
    L.append("")
    L.append("### Pareto fronts (cost vs error) and recommendations")
    L.append("")
    L.append(
        f"Error `1−bal`: 1 − balanced accuracy of the decided identifiable samples; settings deciding less than "
        f"{r['plan']['min_coverage']:g} of them are left off (excluded). Error `1−strict`: 1 − strict accuracy "
        "(undecided counts as wrong) on the draws identifiable under the single-acquisition truth. Recommended: "
        "the cheapest setting whose error is within one paired SE of the lowest (for `1−bal` also with "
        "coverage within one paired SE of that setting's)."
    )
    L.append("")
    L.append(
        "| axis | cost | error | pool | front (cheapest first) | excluded | defaults | on front "
        "| significantly dominated by (z > 2) | recommended (1-SE rule) |"
    )
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for name, ax in r["axes"].items():
        for p in ax["pareto"]:
            sig = [
                f"{d['label']} (Δ {d['error_gain']:.3f}, z {d['z']:.1f})"
                for d in p["defaults_dominated_by"]
                if d["z"] is None or d["z"] > _Z_DOMINATED
            ]
            on = {True: "yes", False: "no", None: "–"}[p["defaults_on_front"]]
            L.append(
                f"| {name} | {_TIME_LABELS.get(p['time_key'], p['time_key'])} | "
                f"{'1−bal' if p['error_key'] == 'error' else '1−strict'} | {p['pool']} | "
                f"{', '.join(p['front'])} | {', '.join(x['label'] for x in p['excluded']) or '–'} | "
                f"{p['defaults'] or '–'} | {on} | {', '.join(sig) or 'none'} | {p['recommended'] or '–'} |"
            )
    L.append("")
    parity = [row.get("max_abs_diff_vs_shipped") for row in r["axes"]["training_draws"]["rows"] if row["is_default"]]
    if parity and parity[0] is not None:
        L.append(
            f"The retrained default model against the shipped ONNX model on the pool-1 test inputs: max |Δp| = "
            f"{parity[0]:.1e}."
        )
    ratio = r["one_configuration_cost_ratio"]
    L.append(
        f"Simulation cost per draw: single-acquisition {r['simulation_seconds_per_draw']['single-acquisition']:.3f} s, "
        f"two-wavelength {r['simulation_seconds_per_draw']['two-wavelength']:.3f} s, one-configuration "
        f"{r['simulation_seconds_per_draw'][ONE_CONFIGURATION]:.3f} s (ratio {ratio['ratio']:.2f} to "
        f"single-acquisition, timed on {ratio['draws_timed']} draws)."
    )
    return "\n".join(L)


def plot_tradeoffs(result: dict[str, Any], path) -> None:
    """Error (1 − balanced accuracy) against cost per axis (pool 1 filled, largest pool open; ± SE), the
    Pareto fronts, the defaults (star), and the learning curve (balanced accuracy and coverage). PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = result
    pools = r["evaluation_pools"]
    panels = [
        ("training_draws", "build_s"),
        ("feature_spec", "build_s"),
        ("model_size", "inference_ort_us"),
        ("model_size", "training_s"),
        ("pool", "inference_us_per_pixel"),
    ]
    fig, axs = plt.subplots(2, 3, figsize=(16, 9.5), constrained_layout=True)
    for ax, (name, tk) in zip(axs.flat, panels):
        a = r["axes"][name]
        for entry in a["pareto"]:
            if entry["time_key"] != tk or entry["error_key"] != "error":
                continue
            own = entry["pool"] == "own"
            color = "C0" if entry["pool"] in ("1", "own") else "C3"
            pts = entry["points"]
            lab = "" if own else f" (pool {entry['pool']})"
            ax.errorbar(
                [p["time"] for p in pts],
                [p["error"] for p in pts],
                yerr=[p["error_se"] or 0 for p in pts],
                fmt="o" if entry["pool"] in ("1", "own") else "s",
                color=color,
                mfc=color if entry["pool"] in ("1", "own") else "none",
                ms=6,
                capsize=2,
                ls="none",
                label="points" + lab,
            )
            front = [next(p for p in pts if p["label"] == lbl) for lbl in entry["front"]]
            ax.step(
                [p["time"] for p in front],
                [p["error"] for p in front],
                where="post",
                color=color,
                lw=1,
                label="Pareto front" + lab,
            )
            d = next((p for p in pts if p["label"] == entry["defaults"]), None)
            if d is not None:
                ax.plot(
                    [d["time"]],
                    [d["error"]],
                    "*",
                    color="gold",
                    mec="k",
                    ms=16,
                    zorder=5,
                    label="shipped defaults" if entry["pool"] in ("1", "own") else None,
                )
            for p in pts:
                ax.annotate(
                    p["label"],
                    (p["time"], p["error"]),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=7,
                    color=color,
                )
        ax.set_xscale("log")
        ax.set_xlabel(_TIME_LABELS.get(tk, tk))
        ax.set_ylabel("1 − balanced accuracy")
        ax.set_title(a["title"], fontsize=9)
        ax.legend(fontsize=7)
    ax = axs.flat[5]
    rows = r["axes"]["training_draws"]["rows"]
    draws = [row["draws_train"] for row in rows]
    floor = r["plan"]["min_coverage"]
    for pool, color in zip(pools, ("C0", "C3")):
        for key, mk, lab in (("balanced_accuracy", "o-", "balanced accuracy"), ("coverage", "s--", "coverage")):
            ms = [row["pools"][pool] for row in rows]
            # a balanced accuracy over too few decisions is not drawn (the fronts leave it off too)
            vals = [m[key] if key == "coverage" or (m["coverage"] or 0.0) >= floor else None for m in ms]
            ses = [m[f"{key}_se"] or 0 for m in ms]
            ax.errorbar(
                draws,
                [np.nan if v is None else v for v in vals],
                yerr=ses,
                fmt=mk,
                color=color,
                capsize=2,
                mfc=color if key == "balanced_accuracy" else "none",
                label=f"{lab}, pool {pool}",
            )
    ax.axvline(r["defaults"]["draws_train"], color="k", lw=0.8, ls=":", label="shipped")
    ax.set_xscale("log")
    ax.set_xticks(draws, [str(n) for n in draws])
    ax.minorticks_off()
    ax.set_ylim(0, 1)
    ax.set_xlabel("training draws (× 8 replicates × 64 trials)")
    ax.set_title("learning curve (single-acquisition)", fontsize=9)
    ax.legend(fontsize=7)
    fig.suptitle("motion-type classifier: what accuracy costs in time" + (" (quick)" if r["quick"] else ""))
    fig.savefig(path, dpi=90, format="png")
    plt.close(fig)

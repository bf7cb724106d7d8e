"""Render the project's results files as Markdown for the documentation site.

Every measured figure on the site comes from a JSON file that a named command writes (a benchmark, a
model's training report, a validation run). A page asks for a table with a marker line::

    <!-- render: bench-simulate -->

and :func:`render` replaces it with the table, the command that wrote the file and the file's path.
Nothing here measures anything: it reads files and formats them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: Folders searched, in order, for a results file by its name (relative to the repository root).
RESULT_DIRS = (
    "docs/results",
    "docs/results/speckle-maps",
    "docs/benchmarks",
    "benchmarks/results",
    "benchmarks",
    "notebooks/bench",
    "research/results",
    "classifier/data",
)


class MissingResult(LookupError):
    """A page asks for a results file that is not in the repository."""


def find(root: Path, name: str) -> Path:
    for d in RESULT_DIRS:
        p = root / d / name
        if p.is_file():
            return p
    raise MissingResult(f"results file {name} not found in any of {', '.join(RESULT_DIRS)}")


def load(root: Path, name: str) -> tuple[dict[str, Any], str]:
    p = find(root, name)
    return json.loads(p.read_text(encoding="utf-8")), p.relative_to(root).as_posix()


# ---------------------------------------------------------------- formatting
def num(x: Any, digits: int = 3) -> str:
    """A number with ``digits`` significant figures (integers as they are); missing values as "n/a"."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}".replace(",", " ") if abs(x) >= 10000 else str(x)
    if x == 0:
        return "0"
    if abs(x) >= 1e5 or abs(x) < 1e-3:
        return f"{x:.{digits - 1}e}"
    if abs(x) >= 10**digits:
        return str(round(x))
    return f"{x:.{digits}g}"


def pm(x: Any, se: Any, digits: int = 3) -> str:
    if se is None:
        return num(x, digits)
    return f"{num(x, digits)} ± {num(se, 2)}"


def cell(x: Any) -> str:
    return str(x).replace("|", "\\|").replace("\n", " ")


def table(header: list[str], rows: list[list[Any]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(cell(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def source(command: str, path: str, extra: str = "") -> str:
    line = f"Written by `{command}` into `{path}`"
    return f"*{line}{'; ' + extra if extra else ''}.*"


def machine(d: dict[str, Any]) -> str:
    m = d.get("machine")
    if not m:
        return ""
    return (
        f"machine: {m.get('cpu_count')} cores, torch {m.get('torch')}, {m.get('torch_threads')} torch "
        f"thread(s), Python {m.get('python')}"
    )


# ---------------------------------------------------------------- benchmarks
def bench_simulate(root: Path) -> str:
    d, p = load(root, "bench-simulate.json")
    thr = d.get("threads")
    rows = [
        [
            c["system"],
            c["motion"],
            num(c["scatterers_per_trial"], 4),
            num(c["ms_per_trial"]),
            num(c["evaluations_per_s"]),
            num(c["of_evaluation_limit"]),
            num(c.get("ms_per_trial_1_thread")),
            num(c.get("ms_per_trial_loaded")),
            num(c.get("loaded_over_1_thread_alone")),
        ]
        for c in d["cells"]
    ]
    t = table(
        [
            "system",
            "motion",
            "scatterers/trial",
            f"ms/trial ({thr} threads)",
            "evaluations/s",
            "of the limit",
            "ms/trial, 1 thread",
            "ms/trial beside a busy job",
            "÷ 1 thread alone",
        ],
        rows,
    )
    summary = (
        f"Mean over the cells: {num(d['mean_ms_per_trial'])} ms/trial on {thr} threads, "
        f"{num(d.get('mean_ms_per_trial_1_thread'))} on one, {num(d.get('mean_ms_per_trial_loaded'))} beside "
        f"a busy job (target {num(d['target_ms_per_trial'])}); {d['trials_per_cell']} trials per cell, "
        f"{d['dtype']}, best of {d['repeats']}; the limit is {num(d['evaluation_limit_per_s'])} "
        "scatterer-frame evaluations per second per core."
    )
    return "\n\n".join([t, summary, source("torchdoct bench simulate --load --repeats 2 --out FILE", p, machine(d))])


def bench_study(root: Path) -> str:
    rows, paths = [], []
    for name, what in (
        ("bench-study-paper.json", "idle"),
        ("bench-study-paper-loaded.json", "beside a busy job"),
        ("bench-study.json", "idle"),
    ):
        try:
            d, p = load(root, name)
        except MissingResult:
            continue
        paths.append(p)
        rows.append(
            [
                d["study"],
                what,
                d["cells"],
                num(d["system_trials"]),
                d["trials_per_point"],
                num(d["wall_s"]),
                num(d["simulate_s"]),
                num(d["figures_s"]),
                d.get("workers"),
            ]
        )
    t = table(
        [
            "study",
            "machine",
            "cells",
            "system-trials",
            "trials/point",
            "wall (s)",
            "simulation (s)",
            "figures and report (s)",
            "workers",
        ],
        rows,
    )
    return "\n\n".join([t, source("torchdoct bench study [--study paper] --out FILE", ", ".join(paths))])


def bench_cog(root: Path) -> str:
    d, p = load(root, "bench-cog.json")
    rows = [
        [
            c["system"],
            c["motion"],
            num(c["cog_scatterers"]),
            num(c["torchdoct_scatterers"], 4),
            num(c["cog_ms_per_trial"]),
            num(c["torchdoct_ms_per_trial"]),
            f"{num(c['ratio'])}×",
        ]
        for c in d["cells"]
    ]
    t = table(
        [
            "system",
            "motion",
            "COG scatterers/trial",
            "torchdoct scatterers/trial",
            "COG ms/trial",
            "torchdoct ms/trial",
            "COG ÷ torchdoct",
        ],
        rows,
    )
    return "\n\n".join(
        [
            t,
            f"Geometric mean of the ratios: {num(d['geometric_mean_ratio'])}× (one core each, CPU "
            f"time, best of {d['repeats']}).",
            source("torchdoct bench cog --cog DIR --out FILE", p),
        ]
    )


def bench_render(root: Path) -> str:
    d, p = load(root, "bench-render.json")
    pops = ", ".join(f"{k}: {num(v['scatterers'])} scatterers" for k, v in d["populations"].items())
    t = table(
        ["phantom", "shape [S, T, Z, X]", "pitch (µm)", "wall (s), best", "pixel-frames/s", "target (s)"],
        [
            [
                d["phantom"],
                "×".join(map(str, d["shape_STZX"])),
                ", ".join(f"{k} {v}" for k, v in d["pitch_um"].items()),
                num(d["wall_s_best"]),
                num(d["pixel_frames_per_s"]),
                num(d["target_s"]),
            ]
        ],
    )
    return "\n\n".join([t, f"Populations: {pops}.", source("torchdoct bench render --out FILE", p, machine(d))])


def bench_maps(root: Path) -> str:
    d, p = load(root, "bench-maps.json")
    per = d["seconds_per_resolution"]
    t = table(
        ["stack", "channels", "total (s)", *[f"{k} (s)" for k in per], "target (s)"],
        [
            [
                f"{d['shape']} {d['dtype']}",
                ", ".join(d["metrics"]),
                num(d["seconds_total"]),
                *[num(v) for v in per.values()],
                num(d["target_seconds"]),
            ]
        ],
    )
    return "\n\n".join([t, source("torchdoct bench maps --out FILE", p, machine(d))])


def maps_channels(root: Path) -> str:
    """``torchdoct bench maps-channels``: each channel set's time and its ratio to the signature maps."""
    d, p = load(root, "maps-channels.json")
    modes = d["modes"]
    head = ["channels", *[f"{m} (s)" for m in modes], *[f"{m}: × signature" for m in modes]]
    rows = [
        [
            name,
            *[num(rec[f"seconds_{m}"]) for m in modes],
            *[num(rec[f"ratio_to_signature_{m}"]) for m in modes],
        ]
        for name, rec in d["sets"].items()
    ]
    shape = " × ".join(map(str, d["shape"]))
    note = (
        f"A random complex64 stack of {shape} (frames × Z × X) at {len(d['resolutions'])} resolutions; every "
        f"round times each set once, in turn, the best of {d['repeats']} rounds kept per set"
        + ("; `loaded`: the rounds again beside a busy process." if "loaded" in modes else ".")
    )
    cmd = "torchdoct bench maps-channels --size 256 256 --repeats 5 --load --out FILE"
    return "\n\n".join([table(head, rows), note, source(cmd, p, machine(d))])


def bench_stream(root: Path) -> str:
    d, p = load(root, "bench-stream.json")
    mib = 1 << 20
    rows = [
        [
            num(r["input_gib"]),
            r["frames"],
            "×".join(map(str, r["shape"])),
            num(r["baseline_rss_bytes"] / mib),
            num(r["peak_rss_bytes"] / mib),
            num(r["growth_bytes"] / mib),
            num(r["seconds"]),
        ]
        for r in d["runs"]
    ]
    t = table(
        [
            "input (GiB)",
            "frames",
            "shape [T, Z, X]",
            "RSS after the imports (MiB)",
            "peak RSS (MiB)",
            "growth (MiB)",
            "wall (s)",
        ],
        rows,
    )
    sizes = ", ".join(num(r["input_gib"]) for r in d["runs"])
    note = (
        f"`{d['command']}` with `--max-memory-gb {num(d['budget_gib'])}` "
        f"({num(d['budget_gib'] * 1024)} MiB) on memory-mapped complex64 inputs of {sizes} GiB."
    )
    return "\n\n".join(
        [t, note, source("torchdoct bench stream --sizes-gb ... --out FILE --figure FILE.png", p, machine(d))]
    )


def bench_classify(root: Path) -> str:
    rows, paths = [], []
    for name in ("bench-classify.json", "bench-classify-signature.json"):
        try:
            d, p = load(root, name)
        except MissingResult:
            continue
        paths.append(p)
        for r in d["rows"]:
            st = r.get("stages_s", {})
            rows.append(
                [
                    d["model"],
                    r["pool"],
                    f"{d['size']} × {d['size']}",
                    num(r["pixels_per_s"]),
                    num(st.get("read")),
                    num(st.get("features")),
                    num(st.get("onnxruntime")),
                    num(st.get("rule")),
                    num(d["target_pixels_per_s"]),
                ]
            )
    t = table(
        [
            "model",
            "pool",
            "maps",
            "pixels/s",
            "read (s)",
            "features (s)",
            "onnxruntime (s)",
            "rule (s)",
            "target pixels/s",
        ],
        rows,
    )
    return "\n\n".join([t, source("torchdoct bench classify [--model signature] --out FILE", ", ".join(paths))])


_BULK_PHASE_COMMAND = "torchdoct bench bulk-phase --phantom vessel-slab --threads 1 --out FILE"


def bench_bulk_phase(root: Path) -> str:
    """Residual phase of the bulk-phase estimate on static speckle against the first-order prediction."""
    d, p = load(root, "bench-bulk-phase.json")
    by = {(r["snr_db"], r["method"]): r for r in d["rows"]}
    rows = []
    for snr in sorted({r["snr_db"] for r in d["rows"]}):
        wm, hi = by.get((snr, "weighted-mean")), by.get((snr, "histogram"))
        ref = wm or hi
        first_order = 1e3 / math.sqrt(2 * d["n_z"] * 10 ** (snr / 10))
        rows.append(
            [
                num(snr),
                f"{first_order:.2f}",
                f"{1e3 * ref['predicted_rms_rad']:.2f}",
                *[
                    x
                    for r in (wm, hi)
                    for x in (
                        (f"{1e3 * r['residual_rms_rad']:.2f} ± {1e3 * r['se_rad']:.2f}", f"{r['ratio']:.3f}")
                        if r
                        else ("", "")
                    )
                ],
            ]
        )
    t = table(["SNR (dB)", "1/√(2·N·SNR)", "predicted", "weighted-mean", "ratio", "histogram", "ratio"], rows)
    text = (
        f"Residuals in mrad: {num(d['lines'])} A-lines of {d['n_z']} rows of static speckle, {d['frames']} frames, "
        f"seed {d['seed']}; {d['model']}; ± the standard error over A-lines; ratio = measured ÷ predicted."
    )
    return "\n\n".join([t, text, source(_BULK_PHASE_COMMAND, p, machine(d))])


def bench_bulk_phase_phantom(root: Path) -> str:
    """Residual phase of the bulk-phase estimate on a rendered phantom, per method and mask."""
    d, p = load(root, "bench-bulk-phase.json")
    ph = d["phantom"]
    columns = list(dict.fromkeys((r["method"], r["mask"]) for r in ph["rows"]))
    by = {(r["snr_db"], r["method"], r["mask"]): r for r in ph["rows"]}
    rows = [
        [
            f"{num(snr)} dB",
            *[
                f"{by[(snr, m, k)]['residual_rms_rad']:.4f} ({by[(snr, m, k)]['g1_4_static_z']:+.1f})"
                if (snr, m, k) in by
                else ""
                for m, k in columns
            ],
        ]
        for snr in sorted({r["snr_db"] for r in ph["rows"]})
    ]
    t = table(["SNR", *[f"{m}, {k}" for m, k in columns]], rows)
    text = (
        f"`{ph['phantom']}` rendered with seed {ph['seed']} ({' × '.join(map(str, ph['shape']))} [T, Z, X]); "
        f"{ph['model']}. Each cell: the RMS residual in rad, and in parentheses the mean change of the static "
        "tissue's g1_4 in standard errors of that mean."
    )
    return "\n\n".join([t, text, source(_BULK_PHASE_COMMAND, p, machine(ph))])


def bench_load(root: Path) -> str:
    d, p = load(root, "bench-load.json")
    rows = [
        [
            r["workload"],
            num(r["alone_1_thread_s"]),
            num(r["alone_s"]),
            num(r["loaded_s"]),
            num(r["loaded_over_1_thread_alone"]),
        ]
        for r in d["rows"]
    ]
    t = table(
        [
            "command",
            "1 thread alone (s)",
            f"{d['threads']} threads alone (s)",
            f"{d['threads']} threads beside a busy job (s)",
            "÷ 1 thread alone",
        ],
        rows,
    )
    worst = max(r["loaded_over_1_thread_alone"] for r in d["rows"])
    return "\n\n".join(
        [
            t,
            f"Worst ratio {num(worst)} (target ≤ {num(d['target_ratio'])}); the busy job: {d['neighbour']}.",
            source(f"torchdoct bench load --repeats {d['repeats']} --out FILE", p, machine(d)),
        ]
    )


def tradeoffs_simulator(root: Path) -> str:
    d, p = load(root, "bench-tradeoffs.json")
    s = d["simulator"]
    rows = []
    for c in s["cells"]:
        for t in c["tolerance"]:
            rows.append(
                [
                    num(t["tolerance"]),
                    c["cell"],
                    num(t["ms_per_trial"]),
                    pm(t["mean_intensity_rel_error"], t["mean_intensity_rel_se"], 2),
                    pm(t["liv_bias"], t["liv_bias_se"], 2),
                    pm(t["ocds_bias"], t["ocds_bias_se"], 2),
                ]
            )
    rows.sort(key=lambda r: -float(r[0]))
    ref = s["cells"][0]["reference"]
    t = table(["tolerance", "cell", "ms/trial", "⟨I⟩ relative error", "LIV bias (dB²)", "OCDS bias (1/s)"], rows)
    dt = [
        [
            c["cell"],
            num(c["dtype"]["float32_ms_per_trial"]),
            num(c["dtype"]["float64_ms_per_trial"]),
            num(c["dtype"]["liv_max_abs_diff"]),
        ]
        for c in s["cells"]
    ]
    t2 = table(["cell", "float32 ms/trial", "float64 ms/trial", "largest per-trial LIV difference (dB²)"], dt)
    text = (
        f"{num(s['trials_per_point'])} trials per tolerance against a {num(ref['trials'])}-trial {ref['dtype']} "
        f"reference at tolerance {num(ref['tolerance'])}; bias ± standard error of the mean."
    )
    return "\n\n".join([t, text, t2, source("torchdoct bench tradeoffs --part simulator --out FILE", p, machine(s))])


def tradeoffs_study(root: Path) -> str:
    d, p = load(root, "bench-tradeoffs.json")
    s = d["study"]
    rows = [
        [
            r["trials"],
            num(r["wall_s"]),
            f"{num(r['liv_rms_error'])} ({num(r['liv_rms_expected'])})",
            f"{num(r['ocds_rms_error'])} ({num(r['ocds_rms_expected'])})",
        ]
        for r in s["rows"]
    ]
    t = table(["trials per point", "wall (s)", "LIV RMS error, dB² (expected)", "OCDS RMS error, 1/s (expected)"], rows)
    return "\n\n".join(
        [
            t,
            f"`{s['study']}`, {s['cells']} cells, against a {s['reference_trials']}-trial reference; "
            "in brackets the error expected from the standard errors.",
            source("torchdoct bench tradeoffs --part study --out FILE", p),
        ]
    )


def tradeoffs_fidelity(root: Path) -> str:
    d, p = load(root, "bench-tradeoffs-fidelity.json")
    f = d["fidelity"]
    rows = []
    for s in f["settings"]:
        feats = [r for c in s["cells"] for r in c["rows"]]
        worst = max(feats, key=lambda r: abs(r["z"]) if r["z"] == r["z"] else 0)
        lo = [r for r in feats if r["feature"] in ("liv", "ocds")]
        zlo = max((abs(r["z"]) for r in lo if r["z"] == r["z"]), default=float("nan"))
        ms = sum(c["ms_per_trial"] for c in s["cells"]) / len(s["cells"])
        rows.append(
            [
                s["truncation"],
                num(s["truncation_tolerance"]),
                s["dtype"],
                num(ms),
                f"{num(abs(worst['z']), 2)} (`{worst['feature']}`@{worst['config']})",
                num(zlo, 2),
            ]
        )
    t = table(
        ["truncation", "tolerance", "dtype", "ms/trial", "max \\|z\\| (feature@configuration)", "max \\|z\\| LIV/OCDS"],
        rows,
    )
    ch = f["cheapest_without_resolvable_bias"]
    ref = f["reference"]
    text = (
        f"{num(f['trials'])} trials per setting against {num(f['reference_trials'])} at tolerance "
        f"{num(ref['truncation_tolerance'])} ({ref['truncation']}, {ref['dtype']}); family-wise α = {f['alpha']}. "
        f"Cheapest setting without a resolvable bias: {ch['truncation']} at {num(ch['truncation_tolerance'])}, "
        f"{ch['dtype']}."
    )
    return "\n\n".join([t, text, source("torchdoct bench tradeoffs --part fidelity --out FILE", p, machine(f))])


def tradeoffs_classifier(root: Path) -> str:
    d, p = load(root, "bench-tradeoffs.json")
    c = d["classifier"]
    rows = []
    for axis in c["axes"].values():
        for r in axis["rows"]:
            cost = " / ".join(f"{k} {num(r.get(k))}" for k in axis["time_keys"])
            p1, p25 = r["pools"].get("1", {}), r["pools"].get("25", {})
            label = f"**{r['label']}**" if r.get("is_default") else r["label"]
            rows.append(
                [
                    axis["title"],
                    label,
                    cost,
                    pm(p1.get("balanced_accuracy"), p1.get("balanced_accuracy_se")),
                    pm(p1.get("coverage"), p1.get("coverage_se")),
                    pm(p25.get("balanced_accuracy"), p25.get("balanced_accuracy_se")) if p25 else "",
                ]
            )
    t = table(
        [
            "axis",
            "setting (shipped in bold)",
            "cost (s or µs)",
            "bal. acc. pool 1",
            "coverage pool 1",
            "bal. acc. pool 25",
        ],
        rows,
    )
    fronts = [
        f"{axis}: {v['defaults']} {'on' if v['defaults_on_front'] else 'off'} the front of {what}"
        for axis, sm in c["summary"].items()
        for what, v in sm.items()
        if what.startswith("error @")
    ]
    ts = c["test_split"]
    text = (
        f"Single-acquisition recipe, test split of {ts['draws']} draws × {ts['replicates']} replicates × "
        f"{ts['trials_per_draw']} trials, ± bootstrap SE ({ts['bootstrap_resamples']} resamples). Pareto fronts "
        f"of error against cost: " + "; ".join(fronts) + "."
    )
    return "\n\n".join([t, text, source("torchdoct bench tradeoffs --part classifier --out FILE", p, machine(c))])


def simulate_example(root: Path) -> str:
    d, p = load(root, "simulate-example.json")
    rows = [
        [
            name,
            pm(s["liv"]["mean"], s["liv"]["se"], 4),
            num(s["liv"]["sd"], 4),
            pm(s["ocds"]["mean"], s["ocds"]["se"], 4),
            num(s["ocds"]["sd"], 4),
            s["liv"]["n"],
            s["zero_intensity_trials"],
        ]
        for name, s in d.items()
    ]
    t = table(
        ["system", "LIV mean ± SE (dB²)", "LIV SD (dB²)", "OCDS mean ± SE (1/s)", "OCDS SD (1/s)", "trials", "empty"],
        rows,
    )
    return "\n\n".join([t, source("torchdoct simulate example --json > FILE", p)])


# ---------------------------------------------------------------- classifier results
def quick_train(root: Path) -> str:
    d, p = load(root, "quick-single-acquisition.json")
    t1, se = d["test"]["network"]["1"], d["standard_errors"]["1"]
    rows = [
        [k.replace("_", " "), pm(t1[k], se.get(k))]
        for k in ("coverage_identifiable", "accuracy_identifiable", "balanced_accuracy_identifiable", "ece")
    ]
    t = table(["pool 1, own test split", "value ± bootstrap SE"], rows)
    dr = d["data"]["draws"]
    return "\n\n".join(
        [
            t,
            f"Draws train / validation / test: {dr['train']} / {dr['validation']} / {dr['test']}.",
            source("doct-train --quick --no-cache --out DIR", p, "the report is `DIR/single-acquisition.json`"),
        ]
    )


def _pool_row(label: str, m: dict[str, Any], se: dict[str, Any] | None) -> list[str]:
    se = se or {}
    return [
        label,
        pm(m.get("coverage_identifiable"), se.get("coverage_identifiable")),
        pm(m.get("balanced_accuracy_identifiable"), se.get("balanced_accuracy_identifiable")),
        pm(m.get("accuracy_identifiable"), se.get("accuracy_identifiable")),
        pm(m.get("ece"), se.get("ece")),
    ]


def _wrong_shares(per_class: dict[str, Any]) -> dict[str, float]:
    """Per motion of a ``score_images`` ``per_class`` block: the share of its pixels decided as another motion."""
    return {k: sum(n for c, n in q["decided_as"].items() if c != k) / max(q["pixels"], 1) for k, q in per_class.items()}


def systems_validation(root: Path) -> str:
    d, p = load(root, "systems-validation.json")
    rows = []
    pools = [k for k in d["systems"][0]["scores"] if k != "5-default"]
    default = any("5-default" in s["scores"] for s in d["systems"])
    for s in d["systems"]:
        sc = {k: s["scores"][k][0]["overall"] for k in pools}
        own = s.get("own_test_pool1", {})
        row = [
            f"`{s['system']}`: {s['description']}",
            num(s["training_s"] / 60, 3),
            f"{num(own.get('balanced_accuracy_identifiable'))} @ {num(own.get('coverage_identifiable'))}",
            *[f"{num(o['balanced_accuracy'])} @ {num(o['coverage'])}" for o in sc.values()],
        ]
        if "5" in sc:  # the model's own decisions at pool 5: each class's pixels decided as another class
            per5 = sc["5"]["per_class"]
            row.append(", ".join(f"{k} {num(w)}" for k, w in _wrong_shares(per5).items()))
        if default:
            o = s["scores"]["5-default"][0]["overall"]
            per = o["per_class"]
            rec = [q["recall"] for q in per.values() if q.get("recall") is not None]
            wrong = _wrong_shares(per)
            row += [
                f"{num(sum(rec) / len(rec)) if rec else '–'} @ {num(o['coverage'])}",
                ", ".join(f"{k} {num(w)}" for k, w in wrong.items()),
            ]
        rows.append(row)
    heads = [
        "system",
        "`doct-train --like` (min)",
        "own test split, pool 1",
        *[f"pool {k}, model decisions: bal. acc. @ coverage" for k in pools],
    ]
    if "5" in pools:
        heads.append("pool 5, model decisions: wrong share")
    if default:
        heads += ["pool 5, default decision: bal. acc. on decided @ coverage", "pool 5, default: wrong share"]
    return "\n\n".join(
        [
            table(heads, rows),
            f"First seed of {', '.join(map(str, d['seeds']))}. The model decisions are `doct-classify "
            "--decide-ballistic`; pool `5@0.6` adds `--min-probability 0.6`. The default decision abstains where "
            "the physics cannot tell (a B-scan's ballistic decisions become `ballistic-or-flow`); its balanced "
            "accuracy counts the classes with decided pixels, and a class's wrong share is the share of its pixels "
            "decided as another class.",
            source(d["command"], p),
        ]
    )


def systems_probes(root: Path) -> str:
    """The grid's probes with each system's own model (``research.systems``, step 5)."""
    d, p = load(root, "systems-validation.json")
    rows = []
    motions = ("diffusion", "ballistic", "flow")
    for s in d["systems"]:
        probes = s.get("probes") or []
        for q in probes:
            if not q["rules"]:
                continue
            alone = next(a for a in probes if a["probe"] == q["probe"] and a["pool"] == q["pool"] and not a["rules"])
            per, per0 = q["all_pixels"]["per_class"], alone["all_pixels"]["per_class"]

            def cell(src: dict, key: str) -> str:
                return " / ".join("–" if src[k][key] is None else num(src[k][key]) for k in motions)

            rows.append(
                [
                    s["system"],
                    q["probe"],
                    q["pool"],
                    cell(per, "coverage"),
                    cell(per, "wrong_share"),
                    cell(per0, "wrong_share"),
                ]
            )
    if not rows:
        return "(no probes recorded)"
    heads = [
        "system",
        "probe",
        "window",
        "default: coverage diffusion / ballistic / flow",
        "default: wrong share",
        "model alone (`--decide-ballistic`): wrong share",
    ]
    return "\n\n".join(
        [
            table(heads, rows),
            "Every pixel of each motion, borders included; a motion the probe lacks is `–`. The probes are the "
            "phantom grid's (docs/benchmarks/grid.md), built from each system at the speed levels and lowest "
            "density of its model's training prior.",
            source(d["command"], p),
        ]
    )


def translation_validation(root: Path) -> str:
    d, p = load(root, "translation-validation.json")
    rows = []
    for motion, s in d["summary"].items():
        if not isinstance(s, dict) or "liv" not in s:
            continue
        lv, oc = s["liv"], s["ocds"]
        rows.append(
            [
                motion,
                num(s.get("translated_share")),
                f"{num(lv['median_abs_bias_over_sd'], 2)} ({num(lv['regions_within_goal'], 2)})",
                num(lv["coverage_68"], 2),
                f"{num(oc['median_abs_bias_over_sd'], 2)} ({num(oc['regions_within_goal'], 2)})",
                num(oc["coverage_68"], 2),
                f"{num(lv['untranslated_median_abs_bias_over_sd'], 2)} / {num(oc['untranslated_median_abs_bias_over_sd'], 2)}",
            ]
        )
    g = d["goals"]
    rows.append(
        [
            "goal",
            "",
            f"≤ {num(g['abs_bias_over_sd'], 2)}",
            f"{g['coverage_68'][0]}-{g['coverage_68'][1]}",
            f"≤ {num(g['abs_bias_over_sd'], 2)}",
            f"{g['coverage_68'][0]}-{g['coverage_68'][1]}",
            "",
        ]
    )
    t = table(
        [
            "motion",
            "translated",
            "LIV: \\|bias\\|/SD median (regions within goal)",
            "LIV: 68 % cover",
            "OCDS: \\|bias\\|/SD median (within goal)",
            "OCDS: 68 % cover",
            "untranslated LIV / OCDS \\|bias\\|/SD",
        ],
        rows,
    )
    return "\n\n".join([t, source(d["command"], p)])


def validation_table(root: Path) -> str:
    d, p = load(root, "validation-table.json")
    rows = [
        [
            r["motion"],
            f"{num(r['lag_s'], 4)} s",
            r["g1_simulated"],
            r["g1_theory"],
            pm(r["intensity_cov_simulated"], r["intensity_cov_se"], 4),
            num(r["intensity_cov_theory"], 4),
            num(r["max_abs_z"], 2),
        ]
        for r in d["rows"]
    ]
    t = table(
        ["motion", "τ", "g1 simulated", "g1 theory", "⟨I I_τ⟩/⟨I⟩² − 1 simulated", "theory", "largest \\|z\\|"], rows
    )
    return "\n\n".join(
        [
            t,
            f"{num(d['trials'])} trials per row, seed {d['seed']}, {d['density_per_um3']} µm⁻³, "
            f"{d['n_frames']} frames at {d['frame_interval_s']} s, {d['dtype']}.",
            source(d["command"], p),
        ]
    )


# ---------------------------------------------------------------- what accuracy costs in acquisition time
#: Where ``python -m classifier.bench.protocol --stem protocol-NAME --out DIR`` runs are recorded.
PROTOCOL_DIR = "docs/benchmarks"


def _protocol(root: Path, name: str) -> str:
    """A recorded run of ``python -m classifier.bench.protocol``: per decision, the frame counts at the
    system's interval in one line per window, then per variant the coverage, balanced accuracy on decided
    pixels, worst wrong share, each band's coverage and accuracy, and the seconds."""
    p = root / PROTOCOL_DIR / f"{name}.json"
    if not p.is_file():
        raise MissingResult(f"results file {name}.json not found in {PROTOCOL_DIR}")
    d = json.loads(p.read_text(encoding="utf-8"))
    rel = p.relative_to(root).as_posix()
    m, s, ph = d["motions"], d["system"], d["phantom"]
    bal = m["ballistic"]
    setting = (
        f"System of spec `{s['spec']}` ({num(s['wavelength_um'] * 1000)} nm, lateral {num(s['lateral_resolution_um'])} µm, "
        f"axial {num(s['axial_resolution_um'])} µm, own protocol {s['n_frames']} frames at {num(s['frame_interval_s'])} s); "
        f"flow {num(m['flow']['speed_um_per_s'])} µm/s at polar {num(m['flow']['polar_angle_deg'])}°, azimuth "
        f"{num(m['flow']['azimuth_deg'])}°; random-ballistic motion {num(bal['speed_um_per_s'])} µm/s "
        + (
            f"(matched to the flow's single-pixel correlation at {num(bal['matched_at_s'])} s)"
            if bal["matched"]
            else "(stated)"
        )
        + f"; pitch {num(ph['pitch_um'])} µm, {ph['seeds']} scatterer realisation(s) per protocol, "
        + ("no noise" if ph["snr_db"] is None else f"{num(ph['snr_db'])} dB SNR")
        + "."
    )
    head = [
        "frames",
        "interval (s)",
        "acquisition (s)",
        "window (px)",
        "coverage",
        "balanced accuracy",
        "worst wrong share",
        "flow coverage",
        "flow accuracy",
        "ballistic coverage",
        "ballistic accuracy",
        "compute (s)",
    ]
    parts = [setting]
    for dec in ("rules", "offset-as-flow"):
        rs = [r for r in d["rows"] if r["decision"] == dec]
        if not rs:
            continue
        lines = []
        for f, w in sorted(
            {(r["interval_factor"], r["window"]) for r in rs}
        ):  # the frame counts at the system's interval
            line = sorted((r for r in rs if (r["interval_factor"], r["window"]) == (f, w)), key=lambda r: r["n_frames"])
            if len(line) > 1 and f == 1.0:
                lines.append(
                    f"* interval {num(f)}× the system's, window {w} px: "
                    + "; ".join(
                        f"{r['n_frames']} frames → accuracy {num(r['balanced_accuracy'])}, coverage {num(r['coverage'])}, "
                        f"wrong {num(r['wrong_share_max'])}"
                        for r in line
                    )
                )
        rows = [
            [
                r["n_frames"],
                num(r["interval_s"]),
                num(r["acquisition_s"]),
                r["window"],
                num(r["coverage"]),
                num(r["balanced_accuracy"]),
                num(r["wrong_share_max"]),
                *[num(r["per_band"][b][k]) for b in ("flow", "ballistic") for k in ("coverage", "accuracy")],
                num(r["seconds"]["total"]),
            ]
            for r in rs
        ]
        parts += [f"**Decision `{dec}`** (flow vs ballistic):", "\n".join(lines), table(head, rows)]
    total = f"{num(d['seconds'])} s in all"
    parts.append(
        source(
            d["command"], rel, f"{total}; {machine(d)}; per band and rule: `{name}.csv`, `{name}.md`, plot `{name}.png`"
        )
    )
    return "\n\n".join(p for p in parts if p)


def protocol_full(root: Path) -> str:
    return _protocol(root, "protocol-full")


def protocol_quick(root: Path) -> str:
    return _protocol(root, "protocol-quick")


def translation_rule(root: Path) -> str:
    """How often rule 5 of classifier.ambiguity fires on independent patches, per motion and noise."""
    d, p = load(root, "translation-rule/translation-rule.json")
    rows = []
    for r in d["rows"]:
        if r["motion"] == "diffusion":
            what = f"diffusion, D = {num(r['diffusion_um2_s'])} µm²/s"
        elif r["motion"] == "ballistic":
            what = f"random ballistic, {num(r['speed_um_s'])} µm/s"
        else:
            what = f"flow, {num(r['speed_um_s'])} µm/s, polar {num(r['polar_deg'])}°, azimuth {num(r['azimuth_deg'])}°"
        snr = "none" if r["snr_db"] is None else f"{num(r['snr_db'])} dB"
        rows.append([what, snr, pm(r["fired"], r["se"]), pm(r["fired_window_alone"], r["se_window_alone"])])
    th = d["thresholds"]
    return "\n\n".join(
        [
            table(["motion", "noise (SNR)", "share of trials where rule 5 fires", "the pixel's window alone"], rows),
            f"Direction-symmetric motions (false detections): mean {num(d['null_mean'])}, worst condition "
            f"{num(d['null_max'])}; judged on the pixel's window alone, without the vote of its neighbours: mean "
            f"{num(d['null_mean_window_alone'])}, worst {num(d['null_max_window_alone'])}. Thresholds: held peak ≥ "
            f"{num(th['hold_min'])}, move ≥ {num(th['growth_min_pitch'])} pitch, line residual ≤ "
            f"{num(th['linear_max_pitch'])} pitch, vote ≥ {num(th['support_min'])} of the windows around; pixel "
            f"pitch {num(d['pitch_um'])} µm, patches of {d['patch_px']} × {d['patch_px']} pixels.",
            source(d["command"], p),
        ]
    )


def grid_context(root: Path, key: str = "summary_by_context", name: str = "grid-default.json") -> str:
    """A recorded grid (``name``: the default one unless given) pooled per geometry, static context and window
    (``key``: ``summary_by_context``, the band interiors; ``summary_by_context_all_pixels``, borders included)."""
    d, p = load(root, name)
    ctx = d.get(key)
    if not ctx:
        raise MissingResult(f"{p} has no {key}: re-record it with the command in its 'command' field")
    motions = list(ctx[0]["per_class"])
    rows = []
    for s in ctx:
        pc = s["per_class"]
        rows.append(
            [
                s["geometry"],
                s["context"],
                s["pool"],
                s["cells"],
                num(s["coverage"]),
                num(s["balanced_accuracy"]),
                num(s["worst_wrong_share"]),
            ]
            + [f"{num(pc[m]['coverage'])} / {num(pc[m]['wrong_share'])}" for m in motions]
        )
    header = [
        "geometry",
        "static context",
        "window",
        "cells",
        "coverage",
        "balanced accuracy (decided)",
        "worst wrong share",
    ] + [f"{m}: coverage / wrong" for m in motions]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def grid_rules(root: Path) -> str:
    """The default grid pooled per geometry, static context and window: per rule of ``classifier.ambiguity``, the
    pixels it changed as a share of the classified pixels (``rules_changed_share``)."""
    d, p = load(root, "grid-default.json")
    ctx = [s for s in d.get("summary_by_context") or [] if s.get("rules_changed_share")]
    if not ctx:
        raise MissingResult(f"{p} has no rules_changed_share: re-record it with the command in its 'command' field")
    rules = list(dict.fromkeys(k for s in ctx for k in s["rules_changed_share"]))
    rows = [
        [s["geometry"], s["context"], s["pool"]]
        + [num(s["rules_changed_share"][k]) if k in s["rules_changed_share"] else "–" for k in rules]
        for s in ctx
    ]
    return "\n\n".join([table(["geometry", "static context", "window", *rules], rows), source(d["command"], p)])


def grid_doppler(root: Path) -> str:
    """The default grid pooled per geometry, static context and window, over the cells whose maps hold a Doppler
    channel: rule 10's statistic on the direction-symmetric motions (the null, its largest magnitude) and on
    flow (the median over the cells of each cell's median magnitude)."""
    d, p = load(root, "grid-default.json")
    ctx = [s for s in d.get("summary_by_context") or [] if (s.get("doppler") or {}).get("cells")]
    if not ctx:
        raise MissingResult(f"{p} has no doppler summary: re-record it with the command in its 'command' field")
    rows = [
        [
            s["geometry"],
            s["context"],
            s["pool"],
            s["doppler"]["cells"],
            num(s["doppler"]["null_max"]),
            num(s["doppler"]["flow_median"]),
        ]
        for s in ctx
    ]
    head = [
        "geometry",
        "static context",
        "window",
        "cells with a Doppler channel",
        "null: largest magnitude (diffusion, ballistic)",
        "flow: median magnitude",
    ]
    return "\n\n".join([table(head, rows), source(d["command"], p)])


def grid_summary(root: Path) -> str:
    """The default grid's summary per window: the band interiors' worst wrong share, cells over 10 %, mean and
    lowest coverage and mean balanced accuracy; over every band pixel the worst cell's wrong share and the cells
    over 5 %."""
    d, p = load(root, "grid-default.json")
    rows = []
    for pool, s in d["summary"].items():
        if "worst_wrong_share_all_pixels" not in s:
            raise MissingResult(f"{p} has no all-pixels summary: re-record it with the command in its 'command' field")
        rows.append(
            [
                pool,
                s["cells"],
                num(s["worst_wrong_share"]),
                s["cells_over_10pct_wrong"],
                num(s["mean_coverage"]),
                num(s["min_coverage"]),
                num(s["mean_balanced_accuracy"]),
                num(s["worst_wrong_share_all_pixels"]),
                s["cells_over_5pct_wrong_all_pixels"],
            ]
        )
    header = [
        "window",
        "cells",
        "worst wrong share",
        "cells > 10 % wrong",
        "mean coverage",
        "lowest coverage",
        "mean balanced accuracy",
        "all pixels: worst wrong share",
        "all pixels: cells > 5 % wrong",
    ]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def grid_probes(root: Path) -> str:
    """The default grid's probes (phantoms whose regions touch): per probe and window, coverage and wrong
    share per motion on the pixels away from other regions, and the worst wrong share over every pixel."""
    d, p = load(root, "grid-default.json")
    probes = d.get("probes")
    if not probes:
        raise MissingResult(f"{p} has no probes: re-record it with the command in its 'command' field")
    motions = list(probes[0]["per_class"])
    rows = []
    for r in probes:
        pc = r["per_class"]
        rows.append(
            [r["probe"], r["pool"], num(r["coverage"]), num(r["wrong_share_max"])]
            + [f"{num(pc[m]['coverage'])} / {num(pc[m]['wrong_share'])}" if pc[m]["pixels"] else "–" for m in motions]
            + [num(r["all_pixels"]["wrong_share_max"])]
        )
    header = ["probe", "window", "coverage", "worst wrong share"] + [f"{m}: coverage / wrong" for m in motions]
    header.append("all pixels: worst wrong share")
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def mixture(m: dict | None) -> str:
    """A mixed region's cell of the cases table: coverage / wrong share, and what it was decided as."""
    if not m or not m["pixels"]:
        return "–"
    held = ", ".join(f"{k} {num(v)}" for k, v in m["decided_as"].items() if v)
    return f"{num(m['coverage'])} / {num(m['wrong_share'])}" + (f" ({held})" if held else "")


def cases(root: Path) -> str:
    """The cases (``classifier.bench.cases``): per case, window and decision (the rules, the model alone),
    coverage and balanced accuracy, per motion its coverage and wrong share, and the worst wrong share, over
    every pixel of each motion."""
    d, p = load(root, "cases.json")
    motions = ("diffusion", "ballistic", "flow")
    rows = []
    for r in d["rows"]:
        a = r["all_pixels"]
        pc = a["per_class"]
        rows.append(
            [r["case"], r["pool"], "rules (default)" if r["rules"] else "model alone", num(a["coverage"])]
            + [num(a["balanced_accuracy"])]
            + [f"{num(pc[m]['coverage'])} / {num(pc[m]['wrong_share'])}" if pc[m]["pixels"] else "–" for m in motions]
            + [mixture(r.get("mixed"))]
            + [num(a["wrong_share_max"])]
        )
    header = ["case", "window", "decision", "coverage", "balanced accuracy"]
    header += [f"{m}: coverage / wrong" for m in motions] + ["mixture: coverage / wrong", "worst wrong share"]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def cases_regions(root: Path) -> str:
    """The cases scored region by region (``per_region`` of ``cases.json``): per case, region, window and
    decision, the region's coverage and wrong share over its every pixel."""
    d, p = load(root, "cases.json")
    rows = [
        [
            r["case"],
            g["region"],
            g["motion"],
            g["pixels"],
            r["pool"],
            "rules (default)" if r["rules"] else "model alone",
        ]
        + [num(g["coverage"]), num(g["wrong_share"])]
        for r in d["rows"]
        for g in r.get("per_region", [])
    ]
    header = ["case", "region", "motion", "pixels", "window", "decision", "coverage", "wrong share"]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def random_phantoms(root: Path) -> str:
    """The random phantoms (``classifier.bench.random_phantoms``): per geometry, window and decision, the draws,
    their median coverage, the share of draws whose worst wrong share exceeds each bound, and per motion its
    coverage and wrong share over the pixels of every draw."""
    d, p = load(root, "random-phantoms.json")
    motions = ("diffusion", "ballistic", "flow")
    bounds = [f"{b:g}" for b in d["bounds"]]
    rows = [
        [s["geometry"], s["pool"], "rules (default)" if s["rules"] else "model alone", s["draws"]]
        + [num(s["median_coverage"])]
        + [num(s["over_bound"][b]) for b in bounds]
        + [f"{num(s['per_class'][m]['coverage'])} / {num(s['per_class'][m]['wrong_share'])}" for m in motions]
        for s in d["summary"]
    ]
    header = ["geometry", "window", "decision", "draws", "median coverage"]
    header += [f"share of draws over {b}" for b in bounds] + [f"{m}: coverage / wrong" for m in motions]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def random_phantoms_worst(root: Path) -> str:
    """The draws whose worst wrong share with the rules (the default decision) exceeds the first bound: the
    geometry, window, draw index, that share, the motion it falls on, and the draw's structure, context, noise,
    density and motions."""
    d, p = load(root, "random-phantoms.json")
    by_key = {(x["geometry"], x["index"]): x for x in d["draws"]}
    rows = []
    for s in d["summary"]:
        for w in s["worst"] if s["rules"] else ():
            if w["wrong_share_max"] <= d["bounds"][0]:
                continue
            x = by_key[(s["geometry"], w["index"])]
            m = x["motions"]
            rows.append(
                [s["geometry"], s["pool"], w["index"], num(w["wrong_share_max"]), w["motion"], x["structure"]]
                + [x["context"], "none" if x["snr_db"] is None else f"{x['snr_db']:g} dB"]
                + [num(x["density_per_um3"]), num(m["diffusion"]["diffusion_um2_per_s"])]
                + [num(m["ballistic"]["speed_um_per_s"]), num(m["flow"]["speed_um_per_s"])]
                + [f"{m['flow']['polar_angle_deg']:.0f}° / {m['flow']['azimuth_deg']:.0f}°"]
            )
    if not rows:
        return f"No draw's worst wrong share with the rules exceeds {d['bounds'][0]:g}.\n\n" + source(d["command"], p)
    header = ["geometry", "window", "draw", "worst wrong share", "on", "structure", "static", "noise"]
    header += ["density (µm⁻³)", "D (µm²/s)", "ballistic (µm/s)", "flow (µm/s)", "flow polar / azimuth"]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def spill_rules(root: Path) -> str:
    """The candidate rules against the random phantoms' slow-region spill (``research.spill``): per geometry,
    window and candidate, the share of draws over each bound, the coverage per motion, the worst pooled wrong
    share of a motion, and the shares of the default decision's right single-class decisions (all, and those
    far from every other region) and wrong ones that the candidate sets aside."""
    d, p = load(root, "spill-rules.json")
    motions = ("diffusion", "ballistic", "flow")
    rows = [
        [s["geometry"], s["pool"], s["variant"], s["draws"]]
        + [num(s["over_bound"][b]) for b in ("0.05", "0.1")]
        + [num(s["per_class"][m]["coverage"]) for m in motions]
        + [num(max(s["per_class"][m]["wrong_share"] or 0.0 for m in motions))]
        + [num(s.get("flagged_right")), num(s.get("flagged_right_interior")), num(s.get("flagged_wrong"))]
        + [s.get("wrong_decisions", "")]
        for s in d["summary"]
    ]
    header = ["geometry", "window", "candidate", "draws", "share of draws over 0.05", "over 0.1"]
    header += [f"{m} coverage" for m in motions] + ["worst pooled wrong share"]
    header += ["right decisions set aside", "of them inside a region", "wrong decisions set aside"]
    header += ["wrong decisions (default)"]
    return "\n\n".join([table(header, rows), source(d["command"], p)])


def spill_null(root: Path) -> str:
    """Rule 12's statistic inside one region (``research.spill --null``): per geometry, static context and
    motion, the share of a region's interior pixels whose footprint mean exceeds each threshold, and the smallest
    threshold at or under the stated rate for the decisions the rule sets aside."""
    d, p = load(root, "spill-null.json")
    s = d["summary"]
    rows = [
        [g["geometry"], g["context"], m, v["pixels"]] + [num(x) for x in v["share_over"]]
        for g in s["groups"]
        for m, v in g["per_motion"].items()
    ]
    header = ["geometry", "static context", "motion", "interior pixels"] + [f"over {t:g}" for t in s["thresholds"]]
    chosen = "none of them" if s["chosen"] is None else f"{s['chosen']:g}"
    note = (
        f"The smallest threshold whose share is at or under {s['rate']:g} for {', '.join(s['flags'])} in every "
        f"geometry: {chosen} (the grid's cells at seed {d['seed']})."
    )
    return "\n\n".join([table(header, rows), note, source(d["command"], p)])


def dynamic_speckle(root: Path) -> str:
    """What the dynamic field's speckle channels add to the default decision (``research.dynamic_speckle``): per
    part of the phantom grid and window, the default decision on the ``--signature`` maps and on the same maps
    with ``--speckle-dynamic``: coverage, balanced accuracy, wrong shares, the worst cell; and the maps' time."""
    d, p = load(root, "dynamic-speckle.json")
    motions = ("diffusion", "ballistic", "flow")
    rows = []
    for part, pr in d["parts"].items():
        for w, e in pr["windows"].items():
            for v in ("default", "dynamic"):
                s = e[v]
                pm = s["per_motion"]
                rows.append(
                    [part, w, "with the dynamic channels" if v == "dynamic" else "--signature"]
                    + [num(s["coverage"]), num(s["balanced_accuracy"]), num(s["worst_wrong_share"])]
                    + [f"{num(s['worst_cell'])} ({s['cells_over']})"]
                    + [" / ".join(num(pm[m]["coverage"]) for m in motions)]
                )
    header = ["grid part", "window", "maps", "coverage", "bal. acc.", "worst wrong share"]
    header += [f"worst cell (cells over {d['cell_wrong_max']:g})", "coverage diffusion / ballistic / flow"]
    cost = [
        [part, num(pr["seconds"]["signature_maps"]), num(pr["seconds"]["dynamic_channels"])]
        + [num(pr["seconds"]["dynamic_channels"] / max(pr["seconds"]["signature_maps"], 1e-9))]
        for part, pr in d["parts"].items()
    ]
    cost_header = ["grid part", "signature maps (s)", "dynamic channels alone (s)", "ratio"]
    return "\n\n".join([table(header, rows), table(cost_header, cost), source(d["command"], p)])


# ---------------------------------------------------------------- the classifier's goals
def _met(ok: bool) -> str:
    return "met" if ok else "**not met**"


def _context(d: dict[str, Any], geometry: str, context: str, pool: int) -> dict[str, Any]:
    return next(
        s for s in d["summary_by_context"] if (s["geometry"], s["context"], int(s["pool"])) == (geometry, context, pool)
    )


def _decidable(cell: dict[str, Any], motion: str) -> bool:
    """Whether some statistic of a grid cell's data can decide ``motion`` at all (docs/abstention.md): not
    random-ballistic motion in a B-scan (rule 1: flow across the plane looks the same) nor in a volume
    without static tissue for a phase reference (rule 11: a sheared flow looks the same), not flow across a
    B-scan's plane (polar 80°, azimuth 90°) without static tissue."""
    if motion == "ballistic":
        return cell["geometry"] == "volume" and cell["context"] != "none"
    if motion == "flow" and cell["geometry"] == "bscan" and cell["context"] == "none":
        return (cell["polar_deg"], cell["azimuth_deg"]) != (80.0, 90.0)
    return True


def _coverage_ceiling(d: dict[str, Any], geometry: str, context: str, pool: int) -> float:
    """The coverage of a grid row if every pixel of a motion its cell's data can decide were decided
    (:func:`_decidable`), over the same pixels as the row's coverage (each cell's band interiors)."""
    cells = [c for c in d["cells"] if (c["geometry"], c["context"], int(c["pool"])) == (geometry, context, pool)]
    total = sum(q["pixels"] for c in cells for q in c["per_class"].values())
    can = sum(q["pixels"] for c in cells for m, q in c["per_class"].items() if _decidable(c, m))
    return can / total


def _system_rows(sv: dict[str, Any], path: str, how: str, bound: tuple[float, float, float]) -> list[list[Any]]:
    """The goals row of the 1310-nm system of a systems validation (``research.systems``): the default decision
    at window 5 on the renderings it did not train on (every seed but the first), the mean balanced accuracy
    and coverage over them and the worst motion's wrong share on any of them."""
    ba_min, cov_min, wrong_max = bound
    out = []
    for sysrec in sv["systems"]:
        if sysrec["system"] != "system-1310nm" or "5-default" not in sysrec["scores"]:
            continue
        held = sysrec["scores"]["5-default"][1:]  # the first seed's rendering trained the model
        bas, covs, wrongs = [], [], []
        for sc in held:
            o = sc["overall"]
            rec = [q["recall"] for q in o["per_class"].values() if q.get("recall") is not None]
            bas.append(sum(rec) / len(rec) if rec else 0.0)
            covs.append(o["coverage"])
            wrongs.append(max(_wrong_shares(o["per_class"]).values()))
        ba, cov, wrong = sum(bas) / len(bas), sum(covs) / len(covs), max(wrongs)
        out.append(
            [
                f"`doct-train --like`, a 1310-nm system, {how}, window 5",
                f"≥ {ba_min} at ≥ {cov_min}; wrong ≤ {wrong_max}",
                f"{num(ba)} at {num(cov)}; wrong {num(wrong)} ({len(held)} renderings it did not train on)",
                _met(ba >= ba_min and cov >= cov_min and wrong <= wrong_max),
                f"`{path}`",
            ]
        )
    return out


#: the goals rows the parts of ``research.grid_ceiling`` bound
_CEILING_PARTS = {
    "bscan-none": "B-scans without static tissue",
    "bscan-background": "inside static tissue, bscan",
    "volume-background": "inside static tissue, volume",
}


def _grid_ceiling_rows(root: Path) -> tuple[list[list[Any]], list[str]]:
    """The goals rows of the measured ceilings of the grid's unmet rows (``research.grid_ceiling``): per part and
    window, the estimator trained on the continuous prior that decides the most at its best threshold under the
    goal's bounds and the grid's per-cell bound, there and at the threshold held out from its training set; and
    the line naming the command that wrote them."""
    try:
        c, cp = load(root, "grid-ceiling.json")
    except MissingResult:
        return [], []
    out = []

    def said(s: dict[str, Any]) -> str:
        return f"{num(s['balanced_accuracy'])} at {num(s['coverage'])}; wrong {num(s['worst_wrong_share'])}"

    for part, what in _CEILING_PARTS.items():
        pr = c["parts"].get(part)
        if pr is None:
            continue
        for w in ("5", "1"):
            g = pr["goal"][w]
            ba, cov, wrong = g["balanced_accuracy"], g["coverage"], g["wrong_share"]

            def met(s: dict[str, Any], ba=ba, cov=cov, wrong=wrong) -> bool:
                return (
                    (s["balanced_accuracy"] or 0.0) >= ba and s["coverage"] >= cov and s["worst_wrong_share"] <= wrong
                )

            # the estimator trained on the continuous prior that decides the most within every bound
            name, est = max(
                ((k, v) for k, v in pr["windows"][w]["inputs"].items() if k.endswith(", prior")),
                key=lambda kv: kv[1]["with_cell_bound"]["scores"]["coverage"],
            )
            e = est["with_cell_bound"]
            best, held = e["scores"], e["scores_threshold_from_training"]
            over = e["cells_threshold_from_training"]["cells_over_10pct_wrong"]  # the best threshold has none
            default = pr["windows"][w]["default_decision"]["scores"]
            out.append(
                [
                    f"*Ceiling*, {what}, window {w}: the best gradient boosting trained on a continuous prior, "
                    "no cell's wrong share over 0.1",
                    f"≥ {ba} at ≥ {cov}; wrong ≤ {wrong}",
                    f"inputs `{name.split(', ')[0]}`; best threshold: {said(best)}; threshold held out from "
                    f"training: {said(held)}, {over} cells over 0.1"
                    + ("; the default decision decides more" if default["coverage"] > best["coverage"] else ""),
                    ("within reach" if met(best) else "out of reach")
                    + (
                        " (also at the held-out threshold)"
                        if met(held) and over == 0
                        else " (not at the held-out threshold)"
                    ),
                    f"`{cp}` ({pr['cells']} cells)",
                ]
            )
    return out, [source(c["command"], cp)]


def _dynamic_rows(root: Path) -> tuple[list[list[Any]], list[str]]:
    """The goals rows inside static tissue with the dynamic field's speckle channels (``research.dynamic_speckle``:
    ``torchdoct maps --speckle-dynamic``, not yet in the default maps), beside the same record's default maps; and
    the line naming the command that wrote them."""
    try:
        d, dp = load(root, "dynamic-speckle.json")
    except MissingResult:
        return [], []
    out = []
    for geometry in ("bscan", "volume"):
        pr = d["parts"].get(f"{geometry}-background")
        if pr is None:
            continue
        for w in ("5", "1"):
            e = pr["windows"][w]
            base, dyn = e["default"], e["dynamic"]
            ok = (
                (dyn["balanced_accuracy"] or 0.0) >= 0.95
                and dyn["coverage"] >= 0.70
                and dyn["worst_wrong_share"] <= 0.05
                and dyn["cells_over"] == 0
            )
            out.append(
                [
                    f"With `--speckle-dynamic` (not in the default maps yet), inside static tissue, {geometry}, "
                    f"window {w}",
                    "≥ 0.95 at ≥ 0.7; wrong ≤ 0.05; no cell's wrong share > 0.1",
                    f"{num(dyn['balanced_accuracy'])} at {num(dyn['coverage'])}; wrong "
                    f"{num(dyn['worst_wrong_share'])}, {dyn['cells_over']} cells over 0.1 (the default maps in the "
                    f"same run: {num(base['balanced_accuracy'])} at {num(base['coverage'])})",
                    _met(ok),
                    f"`{dp}` ({pr['cells']} cells)",
                ]
            )
    return out, [source(d["command"], dp)]


def goals(root: Path) -> str:
    """The classifier's accuracy goals (docs/benchmarks/goals.md), each against the recorded run that measures it:
    the phantom grid's default decision (band interiors), the independent per-pixel evaluation, the systems
    validation and the maps timings. A goal's thresholds are this page's; every measured value is read here."""
    g, gp = load(root, "grid-default.json")
    rows: list[list[Any]] = []

    def ctx_row(what: str, geometry: str, context: str, pool: int, ba: float, cov: float, wrong: float) -> None:
        s = _context(g, geometry, context, pool)
        ok = (s["balanced_accuracy"] or 0.0) >= ba and s["coverage"] >= cov and s["worst_wrong_share"] <= wrong
        rows.append(
            [
                what,
                f"≥ {ba} at ≥ {cov}; wrong ≤ {wrong}",
                f"{num(s['balanced_accuracy'])} at {num(s['coverage'])} (ceiling "
                f"{num(_coverage_ceiling(g, geometry, context, pool))}); wrong {num(s['worst_wrong_share'])}",
                _met(ok),
                f"`{gp}` ({s['cells']} cells)",
            ]
        )

    ctx_row("B-scans without static tissue, window 5", "bscan", "none", 5, 0.95, 0.60, 0.05)
    ctx_row("B-scans without static tissue, window 1", "bscan", "none", 1, 0.90, 0.50, 0.10)
    crossing = [
        c["per_class"]["flow"]["wrong_share"]
        for c in g["cells"]
        if (c["geometry"], c["context"], c["polar_deg"], c["azimuth_deg"]) == ("bscan", "none", 80.0, 90.0)
    ]
    rows.append(
        [
            "Flow across the B-scan plane, no static tissue (polar 80°, azimuth 90°), both windows",
            "flow wrong ≤ 0.1",
            f"worst flow wrong share {num(max(crossing))}",
            _met(max(crossing) <= 0.10),
            f"`{gp}` ({len(crossing)} cell rows)",
        ]
    )
    for geometry in ("bscan", "volume"):
        for pool in (5, 1):
            ctx_row(f"Inside static tissue, {geometry}, window {pool}", geometry, "background", pool, 0.95, 0.70, 0.05)
    dynamic_rows, dynamic_source = _dynamic_rows(root)
    rows += dynamic_rows
    ceiling_rows, ceiling_source = _grid_ceiling_rows(root)
    rows += ceiling_rows
    worst = max(s["worst_wrong_share"] for s in g["summary"].values())
    over = sum(s["cells_over_10pct_wrong"] for s in g["summary"].values())
    rows.append(
        [
            "Every grid cell, both windows",
            "no cell's wrong share > 0.1",
            f"{over} cells over; worst {num(worst)}",
            _met(over == 0),
            f"`{gp}`",
        ]
    )

    e, ep = load(root, "signature-independent.json")
    m = e["results"]["1"]["metrics"]
    conf = m["confusion"]  # rows: true diffusion, ballistic, flow, indeterminate; columns: decided as the same
    wrong_ind = max(sum(r[j] for j in range(3) if j != i) / max(sum(r), 1) for i, r in enumerate(conf[:3]))
    bands = [t for t in e["targets"] if "flow recall, polar band" in t["what"]]
    ok = (
        m["balanced_accuracy_identifiable"] >= 0.88
        and m["coverage_identifiable"] >= 0.80
        and wrong_ind <= 0.08
        and all(t["value"] >= 0.80 for t in bands)
    )
    rows.append(
        [
            "Independent simulator, per pixel (the per-pixel model, its own rule)",
            "≥ 0.88 at ≥ 0.8; flow recall ≥ 0.8 in each polar band; wrong ≤ 0.08",
            f"{num(m['balanced_accuracy_identifiable'])} at {num(m['coverage_identifiable'])}; flow recall "
            + " / ".join(num(t["value"]) for t in bands)
            + f"; wrong {num(wrong_ind)}",
            _met(ok),
            f"`{ep}`",
        ]
    )

    c = e["results"]["1"].get("conformal")
    if c:
        for label, block in (("sets", c["per_class"]), ("sets and rule 1", c["rule_1"])):
            n = {k: c["per_class"][k]["samples"] for k in block}
            right = {k: (q["decided"] or 0.0) * n[k] for k, q in block.items()}
            wrong = {k: (q["wrong_share"] or 0.0) * n[k] for k, q in block.items()}
            rec = [right[k] / (right[k] + wrong[k]) for k in block if right[k] + wrong[k] > 0]
            ba = sum(rec) / len(rec) if rec else 0.0
            cov = (sum(right.values()) + sum(wrong.values())) / max(sum(n.values()), 1)
            worst = max((q["wrong_share"] or 0.0) for q in block.values())
            rows.append(
                [
                    f"Independent simulator, per pixel, `doct-classify`'s {label} (α = {c['alpha']:g})",
                    "≥ 0.88 at ≥ 0.8; wrong ≤ 0.08",
                    f"{num(ba)} at {num(cov)}; wrong {num(worst)}",
                    _met(ba >= 0.88 and cov >= 0.80 and worst <= 0.08),
                    f"`{ep}`",
                ]
            )

    sv, sp = load(root, "systems-validation.json")
    rows += _system_rows(sv, sp, "full training", (0.93, 0.90, 0.05))
    try:
        qv, qp = load(root, "systems-validation-quick.json")
    except MissingResult:
        qv = None
    if qv is not None:
        rows += _system_rows(qv, qp, "`--quick`", (0.75, 0.70, 0.20))
    longest = max(s["training_s"] for s in sv["systems"])
    rows.append(
        [
            "Full `doct-train --like` on 2 cores",
            "≤ 15 min",
            f"longest of {len(sv['systems'])} systems {num(longest / 60)} min",
            _met(longest <= 15 * 60),
            f"`{sp}`",
        ]
    )
    mc, mp = load(root, "maps-channels.json")
    for name, what in (
        ("signature+speckle+doppler", "Maps with the speckle and Doppler channels"),
        ("signature+speckle+doppler+dynamic", "The same with `--speckle-dynamic` (not in the default maps yet)"),
    ):
        rec = mc["sets"].get(name)
        if rec is None:
            continue
        ratios = {m: rec[f"ratio_to_signature_{m}"] for m in mc["modes"]}
        rows.append(
            [
                what,
                "≤ 2 × the signature maps' time",
                "; ".join(f"{m} {num(r)} ×" for m, r in ratios.items())
                + f" ({' × '.join(map(str, mc['shape']))}, best of {mc['repeats']} rounds)",
                _met(max(ratios.values()) <= 2.0),
                f"`{mp}`",
            ]
        )
    return "\n\n".join(
        [
            table(["goal", "bound", "measured", "", "recorded in"], rows),
            "Balanced accuracy is the mean recall over the motions with decided pixels (a motion the decision "
            "always abstains on counts for coverage, not for accuracy); a motion's wrong share is the share of "
            "its pixels decided as another motion, the worst motion shown. The grid rows read the default "
            "decision over the band interiors (`summary_by_context`, `summary`).",
            source(g["command"], gp),
            *dynamic_source,
            *ceiling_source,
            source(e.get("command", "python -m tests.reference.evaluate_models --model signature --out DIR"), ep),
            source(sv["command"], sp),
            *([source(qv["command"], qp)] if qv is not None else []),
            source("torchdoct bench maps-channels --size 256 256 --repeats 5 --load --out FILE", mp),
        ]
    )


RENDERERS: dict[str, Callable[[Path], str]] = {
    "bench-simulate": bench_simulate,
    "bench-study": bench_study,
    "bench-cog": bench_cog,
    "bench-render": bench_render,
    "bench-maps": bench_maps,
    "maps-channels": maps_channels,
    "bench-stream": bench_stream,
    "bench-classify": bench_classify,
    "bench-load": bench_load,
    "bench-bulk-phase": bench_bulk_phase,
    "bench-bulk-phase-phantom": bench_bulk_phase_phantom,
    "tradeoffs-simulator": tradeoffs_simulator,
    "tradeoffs-study": tradeoffs_study,
    "tradeoffs-fidelity": tradeoffs_fidelity,
    "tradeoffs-classifier": tradeoffs_classifier,
    "simulate-example": simulate_example,
    "quick-train": quick_train,
    "systems-validation": systems_validation,
    "systems-probes": systems_probes,
    "translation-validation": translation_validation,
    "validation-table": validation_table,
    "protocol-full": protocol_full,
    "protocol-quick": protocol_quick,
    "translation-rule": translation_rule,
    "grid-context": grid_context,
    "grid-summary": grid_summary,
    "grid-rules": grid_rules,
    "grid-doppler": grid_doppler,
    "grid-probes": grid_probes,
    "cases": cases,
    "cases-regions": cases_regions,
    "random-phantoms": random_phantoms,
    "random-phantoms-worst": random_phantoms_worst,
    "spill-rules": spill_rules,
    "spill-null": spill_null,
    "dynamic-speckle": dynamic_speckle,
    "goals": goals,
    "grid-context-all-pixels": lambda root: grid_context(root, "summary_by_context_all_pixels"),
    "grid-context-uniform-angles": lambda root: grid_context(
        root, "summary_by_context_all_pixels", "grid-uniform-angles.json"
    ),
}


def render(root: Path, name: str) -> str:
    try:
        fn = RENDERERS[name]
    except KeyError:
        raise KeyError(f"unknown results table {name!r}; known: {', '.join(sorted(RENDERERS))}") from None
    return fn(root)

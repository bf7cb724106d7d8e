"""Evaluation metrics and the training report (JSON + Markdown + PNG). numpy/matplotlib only.

Metrics (classes = the model's classes, the last being ``indeterminate``):

* **accuracy / balanced accuracy (all)**: decisions after the indeterminate rule against the
  truth including the indeterminate class (balanced = mean per-class recall);
* **identifiable**: over samples whose motion is identifiable by the ground truth
  (:func:`classifier.truth.identifiability`): ``coverage`` = fraction the rule decides;
  ``accuracy`` and ``balanced_accuracy`` over the decided ones (motion classes only); ``strict``
  accuracy counts undecided samples as wrong;
* **ECE**: expected calibration error of the top-class probability before the rule, 15 equal-width
  bins, truth including the indeterminate class.

Kept whole (over 800 lines): the metrics and the sections of the report that render them share one
results dictionary; keeping the metric beside the section that prints it keeps the schema in one place.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .rule import REASONS, apply_rule

__all__ = [
    "expected_calibration_error",
    "evaluate",
    "bootstrap_draws",
    "bootstrap_se",
    "coverage_curve",
    "magnitude_table",
    "write_report",
    "format_markdown",
    "undefined_reason",
    "summary_line",
    "training_summary",
    "finite",
    "COVERAGE_THRESHOLDS",
]

#: ``min_probability`` values of the accuracy-coverage table (:func:`coverage_curve`).
COVERAGE_THRESHOLDS = (0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def expected_calibration_error(probabilities: np.ndarray, truth: np.ndarray, bins: int = 15) -> tuple[float, list]:
    """Top-label ECE and its reliability table ``[(confidence, accuracy, count), ...]`` per bin."""
    p = np.asarray(probabilities, dtype=np.float64)
    conf = p.max(1)
    ok = (p.argmax(1) == np.asarray(truth)).astype(np.float64)
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.clip(np.digitize(conf, edges[1:-1]), 0, bins - 1)
    ece = 0.0
    table = []
    for b in range(bins):
        m = idx == b
        n = int(m.sum())
        if n:
            ece += n / len(conf) * abs(conf[m].mean() - ok[m].mean())
            table.append((float(conf[m].mean()), float(ok[m].mean()), n))
    return float(ece), table


def _recalls(truth: np.ndarray, pred: np.ndarray, classes: Sequence[int]) -> list[float]:
    out = []
    for c in classes:
        m = truth == c
        out.append(float((pred[m] == c).mean()) if m.any() else math.nan)
    return out


def evaluate(
    probabilities: np.ndarray, y: np.ndarray, status: np.ndarray, class_names: Sequence[str], rule: dict[str, Any]
) -> dict[str, Any]:
    """All metrics of the module docstring for one set of samples.

    ``y`` motion labels (0..C−2), ``status`` 0 where identifiable (ground truth).
    """
    n_cls = len(class_names)
    ind = n_cls - 1
    truth = np.where(status == 0, y, ind)
    pred, reasons = apply_rule(probabilities, class_names, rule)
    ident = status == 0
    decided = ident & (pred != ind)
    cm = np.zeros((n_cls, n_cls), np.int64)
    np.add.at(cm, (truth, pred), 1)
    rec_all = _recalls(truth, pred, range(n_cls))
    rec_id = _recalls(y[decided], pred[decided], range(n_cls - 1))
    ece, table = expected_calibration_error(probabilities, truth)
    return {
        "samples": int(len(y)),
        "accuracy_all": float((pred == truth).mean()),
        "balanced_accuracy_all": float(np.nanmean(rec_all)),
        "recall_all": dict(zip(class_names, rec_all)),
        "identifiable_samples": int(ident.sum()),
        "coverage_identifiable": float(decided.sum() / max(ident.sum(), 1)),
        "accuracy_identifiable": float((pred[decided] == y[decided]).mean()) if decided.any() else math.nan,
        "balanced_accuracy_identifiable": float(np.nanmean(rec_id)) if decided.any() else math.nan,
        "recall_identifiable": dict(zip(class_names[:-1], rec_id)),
        "strict_accuracy_identifiable": float((pred[ident] == y[ident]).mean()) if ident.any() else math.nan,
        "indeterminate_fraction": float((pred == ind).mean()),
        "indeterminate_reasons": {r: int((reasons == i).sum()) for i, r in enumerate(REASONS)},
        "ece": ece,
        "reliability": table,
        "confusion": cm.tolist(),
    }


#: Polar bands of a flow's direction from the beam (depth) axis, degrees (folded into [0°, 90°]:
#: a flow and its reverse decorrelate alike in intensity).
POLAR_BANDS = ((0.0, 30.0), (30.0, 60.0), (60.0, 90.0))


def flow_recall_by_band(
    probabilities: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    polar_angle_deg: np.ndarray,
    magnitude: np.ndarray,
    class_names: Sequence[str],
    rule: dict[str, Any],
) -> dict[str, Any]:
    """Flow recall by polar band and by speed decade, on identifiable flow samples.

    Per band (``θ`` folded to ``min(θ, 180° − θ)``, :data:`POLAR_BANDS`) and per decade of the speed
    (µm/s): ``samples``, ``coverage`` (share the rule decides), ``recall`` (share of the decided called
    flow) and ``as`` (share of the decided called each class). Bands with no sample are left out.
    """
    flow = list(class_names).index("flow")
    pred, _ = apply_rule(probabilities, class_names, rule)
    ind = len(class_names) - 1
    sel = (status == 0) & (y == flow) & np.isfinite(polar_angle_deg)
    theta = np.minimum(polar_angle_deg, 180.0 - polar_angle_deg)
    decade = np.floor(np.log10(np.maximum(magnitude, 1e-300)))

    def row(mask: np.ndarray) -> dict[str, Any]:
        dec = mask & (pred != ind)
        n_dec = int(dec.sum())
        return {
            "samples": int(mask.sum()),
            "coverage": float(n_dec / max(int(mask.sum()), 1)),
            "recall": float((pred[dec] == flow).mean()) if n_dec else math.nan,
            "as": {c: float((pred[dec] == i).mean()) if n_dec else math.nan for i, c in enumerate(class_names[:-1])},
        }

    bands = {f"{lo:g}-{hi:g}": row(sel & (theta >= lo) & ((theta < hi) | (hi == 90.0))) for lo, hi in POLAR_BANDS}
    decades = {f"1e{int(d)}": row(sel & (decade == d)) for d in np.unique(decade[sel])}
    return {
        "polar_bands": {k: v for k, v in bands.items() if v["samples"]},
        "speed_decades": {k: v for k, v in decades.items() if v["samples"]},
    }


def bootstrap_draws(
    fn: Callable[[np.ndarray], dict[str, float]], draw: np.ndarray, *, n_boot: int = 200, seed: int = 0
) -> dict[str, float]:
    """Standard errors of the scalars ``fn(index) -> {name: value}`` from ``n_boot`` resamples of the draws
    (the independent unit) with a seeded generator: the SD (ddof 1) of each scalar's finite values, NaN
    with fewer than 2 of them; ``{}`` with fewer than 2 draws. The resampling of
    :func:`bootstrap_se` and of :func:`classifier.evaluation.evaluate_set`'s other standard errors."""
    rng = np.random.default_rng(seed)
    draws = np.unique(draw)
    if draws.size < 2:
        return {}
    index = {k: np.flatnonzero(draw == k) for k in draws}
    vals: dict[str, list[float]] = {}
    for _ in range(n_boot):
        pick = np.concatenate([index[k] for k in rng.choice(draws, draws.size, replace=True)])
        for key, v in fn(pick).items():
            vals.setdefault(key, []).append(v)
    out = {}
    for key, values in vals.items():
        a = np.asarray(values, dtype=np.float64)
        a = a[np.isfinite(a)]
        out[key] = float(np.std(a, ddof=1)) if a.size >= 2 else math.nan
    return out


def bootstrap_se(
    probabilities: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    draw: np.ndarray,
    class_names: Sequence[str],
    rule: dict[str, Any],
    *,
    n_boot: int = 200,
    seed: int = 0,
    keys: Sequence[str] = (
        "accuracy_identifiable",
        "balanced_accuracy_identifiable",
        "coverage_identifiable",
        "accuracy_all",
        "ece",
    ),
) -> dict[str, float]:
    """Standard errors of :func:`evaluate`'s metrics from a bootstrap over *draws* (the independent
    unit: trials of a draw share its parameters), ``n_boot`` resamples with a seeded generator
    (:func:`bootstrap_draws`).

    NaN (undefined, see :func:`undefined_reason`) with fewer than 2 draws, or when fewer than 2
    resamples give a defined value."""

    def scalars(i: np.ndarray) -> dict[str, float]:
        m = evaluate(probabilities[i], y[i], status[i], class_names, rule)
        return {k: m[k] for k in keys}

    se = bootstrap_draws(scalars, draw, n_boot=n_boot, seed=seed)
    return {k: se.get(k, math.nan) for k in keys}


def coverage_curve(
    probabilities: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    class_names: Sequence[str],
    rule: dict[str, Any],
    thresholds: Sequence[float] = COVERAGE_THRESHOLDS,
) -> list[dict[str, Any]]:
    """Accuracy against coverage as the rule's ``min_probability`` varies, the rest of the rule fixed:
    what ``doct-classify --min-probability`` trades. Per threshold: coverage, accuracy and balanced
    accuracy on the identifiable samples (as :func:`evaluate`) and the share of the non-identifiable
    samples that is decided (given a motion class although the ground truth is indeterminate; NaN
    without such samples). A higher threshold decides a subset of the pixels a lower one decides."""
    rows = []
    for t in thresholds:
        m = evaluate(probabilities, y, status, class_names, {**rule, "min_probability": float(t)})
        non = m["confusion"][-1]  # truth indeterminate = the non-identifiable samples, by decision
        rows.append(
            {
                "min_probability": float(t),
                "coverage_identifiable": m["coverage_identifiable"],
                "accuracy_identifiable": m["accuracy_identifiable"],
                "balanced_accuracy_identifiable": m["balanced_accuracy_identifiable"],
                "non_identifiable_decided": (sum(non) - non[-1]) / sum(non) if sum(non) else math.nan,
            }
        )
    return rows


#: Why a metric of :func:`evaluate` can be undefined (None in the JSON report, "n/a" in the text).
_NO_IDENTIFIABLE = "the test set has no identifiable sample"
_NONE_DECIDED = (
    "no identifiable test sample was decided: coverage 0, the network called all of them "
    "indeterminate; train on more draws or lower --min-probability"
)
_IDENTIFIABLE_KEYS = (
    "accuracy_identifiable",
    "balanced_accuracy_identifiable",
    "strict_accuracy_identifiable",
    "coverage_identifiable",
)


def _undefined(v: Any) -> bool:
    return v is None or (isinstance(v, float) and not math.isfinite(v))


def undefined_reason(metrics: dict[str, Any], key: str) -> str | None:
    """Why ``metrics[key]`` (an :func:`evaluate` result) is undefined; ``None`` when it is defined."""
    if not _undefined(metrics.get(key)):
        return None
    if key in _IDENTIFIABLE_KEYS:
        return _NO_IDENTIFIABLE if not metrics.get("identifiable_samples") else _NONE_DECIDED
    return "undefined on this test set"


def summary_line(metrics: dict[str, Any]) -> str:
    """One line of the headline test metrics; an undefined one reads "n/a (reason)", each reason once."""
    said: set[str] = set()

    def f(key: str) -> str:
        reason = undefined_reason(metrics, key)
        if reason is None:
            return f"{metrics[key]:.3f}"
        if reason in said:
            return "n/a"
        said.add(reason)
        return f"n/a ({reason})"

    return (
        f"accuracy {f('accuracy_all')}, balanced {f('balanced_accuracy_all')}; identifiable: coverage "
        f"{f('coverage_identifiable')}, accuracy {f('accuracy_identifiable')}, balanced "
        f"{f('balanced_accuracy_identifiable')}; ECE {f('ece')}"
    )


def training_summary(report: dict[str, Any]) -> str:
    """The line ``doct-train`` prints after a run: the network's test metrics at pool 1
    (:func:`summary_line`), the ONNX parity and the total time."""
    return (
        f"test (pool 1): {summary_line(report['test']['network']['1'])}; ONNX max |dp| "
        f"{report['onnx_parity_max_abs_diff']:.1e}; total {report['total_s']:.0f} s"
    )


def finite(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by None (strict JSON; an undefined metric reads
    "n/a" in the text, :func:`undefined_reason`), through dicts, lists and tuples (as lists)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def magnitude_table(
    probabilities: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    magnitude: np.ndarray,
    class_names: Sequence[str],
    rule: dict[str, Any],
    ranges: Sequence[tuple[float, float]],
    bins: int = 8,
) -> list[dict[str, Any]]:
    """Per motion class and log-magnitude bin: counts, truth-indeterminate fraction, predicted
    indeterminate fraction, and accuracy on the identifiable, decided samples."""
    ind = len(class_names) - 1
    pred, _ = apply_rule(probabilities, class_names, rule)
    rows = []
    for c in range(len(class_names) - 1):
        lo, hi = ranges[c]
        edges = np.geomspace(lo, hi, bins + 1)
        m = y == c
        idx = np.clip(np.digitize(magnitude[m], edges[1:-1]), 0, bins - 1)
        for b in range(bins):
            sel = idx == b
            if not sel.any():
                continue
            st = status[m][sel]
            pr = pred[m][sel]
            dec = (st == 0) & (pr != ind)
            rows.append(
                {
                    "class": class_names[c],
                    "low": float(edges[b]),
                    "high": float(edges[b + 1]),
                    "samples": int(sel.sum()),
                    "truth_indeterminate": float((st != 0).mean()),
                    "truth_static": float((st == 1).mean()),
                    "truth_decorrelated": float((st == 2).mean()),
                    "predicted_indeterminate": float((pr == ind).mean()),
                    "accuracy_decided": float((pr[dec] == c).mean()) if dec.any() else math.nan,
                    "coverage": float(dec.sum() / max((st == 0).sum(), 1)) if (st == 0).any() else math.nan,
                }
            )
    return rows


def _fmt(v: Any, digits: int = 3) -> str:
    if _undefined(v):
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _section(
    L: list[str], title: str, note: str | None, header: Sequence[str], align: str, rows: Sequence[Sequence[Any]]
) -> None:
    """Append a Markdown section: ``## title``, an optional note, a table (``align``: ``-`` left,
    ``r`` right per column) and a blank line."""
    L += [f"## {title}", ""] + ([note, ""] if note else [])
    L.append("| " + " | ".join(header) + " |")
    L.append("|" + "".join("---:|" if a == "r" else "---|" for a in align))
    L += ["| " + " | ".join(str(v) for v in row) + " |" for row in rows]
    L.append("")


def _magnitude_rows(L: list[str], title: str, rows: Sequence[dict[str, Any]]) -> None:
    """Append one :func:`magnitude_table` as a Markdown table under the heading ``title``."""
    L += [title, ""]
    L.append(
        "| class | magnitude | samples | truth static | truth decorrelated | decided indeterminate "
        "| coverage (identifiable) | accuracy (decided) |"
    )
    L.append("|---|---|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        L.append(
            f"| {row['class']} | {row['low']:.2g}–{row['high']:.2g} | {row['samples']} | "
            f"{_fmt(row['truth_static'], 2)} | {_fmt(row['truth_decorrelated'], 2)} | "
            f"{_fmt(row['predicted_indeterminate'], 2)} | {_fmt(row['coverage'], 2)} | "
            f"{_fmt(row['accuracy_decided'], 2)} |"
        )
    L.append("")


def _coverage_section(L: list[str], title: str, curves: dict[str, list[dict[str, Any]]], rule: dict[str, Any]) -> None:
    """One :func:`coverage_curve` table per report section, pools one after the other."""
    _section(
        L,
        title,
        f"The rule at each min_probability (the model's: {rule['min_probability']:g}); identifiable "
        "test samples, and the share of the non-identifiable ones given a motion class.",
        [
            "pool",
            "min_probability",
            "coverage",
            "acc. identifiable",
            "bal. acc. identifiable",
            "non-identifiable decided",
        ],
        "rrrrrr",
        [
            [
                pool,
                f"{c['min_probability']:g}",
                _fmt(c["coverage_identifiable"]),
                _fmt(c["accuracy_identifiable"]),
                _fmt(c["balanced_accuracy_identifiable"]),
                _fmt(c["non_identifiable_decided"]),
            ]
            for pool, rows in curves.items()
            for c in rows
        ],
    )


def flow_bands_section(L: list[str], title: str, bands: dict[str, dict[str, Any]]) -> None:
    """One table of :func:`flow_recall_by_band` results, pools one after the other."""
    rows = []
    for pool, fb in bands.items():
        for kind, key in (("polar", "polar_bands"), ("speed", "speed_decades")):
            for name, r in fb.get(key, {}).items():
                label = f"{name}°" if kind == "polar" else f"{name} µm/s decade"
                rows.append(
                    [
                        pool,
                        label,
                        r["samples"],
                        _fmt(r["coverage"]),
                        _fmt(r["recall"]),
                        _fmt(r["as"].get("ballistic", math.nan)),
                        _fmt(r["as"].get("diffusion", math.nan)),
                    ]
                )
    _section(
        L,
        title,
        "Identifiable flow samples by the polar angle of the flow from the beam axis (folded into "
        "0–90°) and by speed decade: share decided (coverage), share of the decided called flow (recall), "
        "ballistic, diffusion.",
        ["pool", "band", "samples", "coverage", "flow recall", "as ballistic", "as diffusion"],
        "rlrrrrr",
        rows,
    )


def _shifted_section(L: list[str], sp: dict[str, Any], rule: dict[str, Any]) -> None:
    """The shifted-prior test set (``report["shifted_prior"]``, :data:`classifier.train.SHIFTED_PRIOR`)."""
    pr = sp["prior"]
    noise = (
        f"noise with probability {pr['noise_probability']:g} at SNR {pr['snr_db'][0]:g}–{pr['snr_db'][1]:g} dB"
        if pr["noise_probability"] > 0
        else "no noise"
    )
    static = (
        "no static fraction"
        if pr["static_probability"] == 0
        else f"static fraction {pr['static_fraction'][0]:g}–{pr['static_fraction'][1]:g} with probability "
        f"{pr['static_probability']:g}"
    )
    dens = pr["density_per_um3"]
    dens_s = f"{dens[0]:g}" if dens[0] == dens[1] else f"{dens[0]:g}–{dens[1]:g}"
    note = (
        f"The network on test draws from another prior: flow at {pr['flow_polar_angle_deg'][0]:g}–"
        f"{pr['flow_polar_angle_deg'][1]:g}° from the depth axis (isotropic within), moving-scatterer density "
        f"{dens_s} µm⁻³, {static}, {noise}, random-ballistic direction laws: {pr['ballistic_directions']}; "
        f"motion types, magnitudes and simulator seeds those of the test draws. {sp['draws']} draws, "
        f"{sp['samples']} samples; ground truth per draw: "
        + ", ".join(f"{k} {v}" for k, v in sp["draw_status_counts"].items())
        + "."
    )
    ses = sp.get("standard_errors", {})

    def pm(pool: str, key: str) -> str:
        v = sp["test"][pool][key]
        se = ses.get(pool, {}).get(key)
        return _fmt(v) + ("" if se is None or _undefined(se) or _undefined(v) else f" ± {se:.3f}")

    _section(
        L,
        "Shifted-prior test set (network)",
        note,
        ["pool", "samples", "coverage", "acc. identifiable", "bal. acc. identifiable", "ECE", "indeterminate"],
        "rrrrrrr",
        [
            [
                pool,
                m["samples"],
                pm(pool, "coverage_identifiable"),
                pm(pool, "accuracy_identifiable"),
                pm(pool, "balanced_accuracy_identifiable"),
                pm(pool, "ece"),
                _fmt(m["indeterminate_fraction"]),
            ]
            for pool, m in sp["test"].items()
        ],
    )
    if ses:
        L += ["± : standard error, bootstrap over the draws.", ""]
    reasons = sorted(
        {why for m in sp["test"].values() for key in _IDENTIFIABLE_KEYS if (why := undefined_reason(m, key))}
    )
    if reasons:
        L += [f"n/a: {why}.  " for why in reasons] + [""]
    t = sp.get("targets")
    if t is not None:
        m = sp["test"][t["pool"]]
        L += [
            f"Targets (pool {t['pool']}): balanced accuracy (identifiable) ≥ "
            f"{t['balanced_accuracy_identifiable']:g}: {_fmt(m['balanced_accuracy_identifiable'])}; "
            f"ECE ≤ {t['ece']:g}: {_fmt(m['ece'])}; "
            f"**{'met' if t['met'] else 'not met'}**.",
            "",
        ]
    if "coverage_curve" in sp:
        _coverage_section(
            L, "Shifted prior: accuracy against coverage (`--min-probability`)", sp["coverage_curve"], rule
        )
    if "flow_bands" in sp:
        flow_bands_section(L, "Shifted prior: flow recall by direction and speed", sp["flow_bands"])
    for pool, rows in sp.get("by_magnitude", {}).items():
        _magnitude_rows(L, f"### Shifted prior: accuracy against motion magnitude, pool {pool}", rows)
    if "magnitude" in sp:
        _section(
            L,
            "Shifted prior: motion magnitude (network; identifiable samples, head of the true class)",
            None,
            ["pool", "samples", "median abs. log10 error", "68 % coverage", "95 % coverage"],
            "rrrrr",
            [
                [
                    pool,
                    m["samples"],
                    _fmt(m.get("median_abs_log10_error")),
                    _fmt(m.get("coverage_68")),
                    _fmt(m.get("coverage_95")),
                ]
                for pool, m in sp["magnitude"].items()
            ],
        )


def format_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown (tables of the JSON)."""
    r = report
    cls = r["classes"]
    L = [f"# Motion-type classifier report: `{r['spec']['name']}`", ""]
    L.append(f"Spec: {r['spec']['description']}  ")
    L.append(f"Features: {', '.join(r['feature_names'])} (+ `pool_pixels`)  ")
    L.append(
        f"Classes: {', '.join(cls)}; rule: {r['rule']['definition']} min_probability = "
        f"{r['rule']['min_probability']}, epsilon = {r['rule']['epsilon']}.  "
    )
    d = r["data"]
    L.append(
        f"Data: seed {r['seed']}; draws train/validation/test = {d['draws']['train']}/"
        f"{d['draws']['validation']}/{d['draws']['test']} × {d['replicates']} (static fraction, SNR) replicates × "
        f"{d['trials_per_draw']} trials; simulation {d['simulation_s']:.1f} s ({d['s_per_draw']:.3f} s per draw, "
        f"{d['ms_per_trial']:.2f} ms per simulated trial; torch threads: {d['threads']}); training {r['training']['seconds']:.1f} s, {r['training']['epochs']} epochs, "
        f"temperature {r['training']['temperature']:.3f}."
    )
    L.append("")
    L.append("## Test set, by pooled pixels")
    L.append("")
    L.append(
        "`pool` = independent pixels (trials of one draw) averaged per feature vector. Identifiable = "
        "ground truth; accuracy over the decided ones; coverage = decided share; strict counts undecided as wrong."
    )
    L.append("")
    L.append(
        "| model | pool | acc. all | bal. acc. all | coverage | acc. identifiable | bal. acc. identifiable "
        "| strict acc. | ECE | indeterminate |"
    )
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, per in r["test"].items():
        for pool, m in per.items():
            L.append(
                f"| {name} | {pool} | {_fmt(m['accuracy_all'])} | {_fmt(m['balanced_accuracy_all'])} | "
                f"{_fmt(m['coverage_identifiable'])} | {_fmt(m['accuracy_identifiable'])} | "
                f"{_fmt(m['balanced_accuracy_identifiable'])} | {_fmt(m['strict_accuracy_identifiable'])} | "
                f"{_fmt(m['ece'])} | {_fmt(m['indeterminate_fraction'])} |"
            )
    L.append("")
    reasons = sorted(
        {
            why
            for per in r["test"].values()
            for m in per.values()
            for key in _IDENTIFIABLE_KEYS
            if (why := undefined_reason(m, key))
        }
    )
    for why in reasons:
        L.append(f"n/a: {why}.  ")
    if reasons:
        L.append("")
    if "standard_errors" in r:
        L.append(
            "Standard errors of the network's numbers (bootstrap over test draws, the independent unit): "
            + "; ".join(
                f"pool {pool}: "
                + ", ".join(
                    f"{k.replace('_', ' ')} " + ("n/a" if _undefined(v) else f"±{v:.3f}") for k, v in se.items()
                )
                for pool, se in r["standard_errors"].items()
            )
            + ".  "
        )
        if any(_undefined(v) for se in r["standard_errors"].values() for v in se.values()):
            L.append(
                "n/a: the metric is undefined in all but at most one bootstrap resample, or the test set "
                "has fewer than 2 draws."
            )
        L.append("")
    if "coverage_curve" in r:
        _coverage_section(
            L, "Accuracy against coverage (network): the `--min-probability` trade-off", r["coverage_curve"], r["rule"]
        )
    if "flow_bands" in r:
        flow_bands_section(L, "Flow recall by direction and speed (network)", r["flow_bands"])
    L.append("## Models: training and inference time")
    L.append("")
    L.append(
        "| model | training [s] | inference [µs/sample] | acc. identifiable (pool 1) | bal. acc. identifiable (pool 1) |"
    )
    L.append("|---|---:|---:|---:|---:|")
    for name, t in r["timing"].items():
        m = r["test"].get(name, r["test"]["network"])["1"]
        L.append(
            f"| {name} | {_fmt(t['train_s'], 2)} | {t['inference_us_per_sample']:.2f} | "
            f"{_fmt(m['accuracy_identifiable'])} | {_fmt(m['balanced_accuracy_identifiable'])} |"
        )
    L.append("")
    for pool in r["confusion_pools"]:
        cm = r["test"]["network"][pool]["confusion"]
        L.append(f"## Confusion matrix (network, pool {pool}; rows truth, columns decision)")
        L.append("")
        L.append("| truth \\ decision | " + " | ".join(cls) + " |")
        L.append("|---|" + "---:|" * len(cls))
        for c, row in zip(cls, cm):
            L.append(f"| {c} | " + " | ".join(str(v) for v in row) + " |")
        L.append("")
    L.append("## Where the outcome is indeterminate, and accuracy against motion magnitude (network)")
    L.append("")
    L.append(
        "Magnitude: D in µm²/s (diffusion), v in µm/s (ballistic, flow). Truth static/decorrelated: "
        "share of samples whose ground truth is indeterminate for that reason."
    )
    L.append("")
    for pool, rows in r["by_magnitude"].items():
        _magnitude_rows(L, f"### pool {pool}", rows)
    if "by_condition" in r:
        _section(
            L,
            "Accuracy by acquisition condition (network, identifiable samples, pool 1)",
            None,
            ["condition", "samples", "coverage", "accuracy (decided)", "balanced accuracy (decided)"],
            "-rrrr",
            [
                [
                    name,
                    m["identifiable_samples"],
                    _fmt(m["coverage_identifiable"]),
                    _fmt(m["accuracy_identifiable"]),
                    _fmt(m["balanced_accuracy_identifiable"]),
                ]
                for name, m in r["by_condition"].items()
            ],
        )
    if "magnitude" in r:
        _section(
            L,
            "Motion magnitude (network; identifiable test samples, head of the true class)",
            "log10 D (µm²/s) for diffusion, log10 v (µm/s) for ballistic motion and flow; interval = mean ± SD "
            "(68 %) and ± 1.96 SD (95 %) of the predicted Gaussian.",
            [
                "pool",
                "samples",
                "median abs. log10 error",
                "mean abs. log10 error",
                "68 % coverage",
                "95 % coverage",
                "median SD",
                "median error diffusion / ballistic / flow",
            ],
            "rrrrrrr-",
            [
                [
                    pool,
                    m["samples"],
                    _fmt(m.get("median_abs_log10_error")),
                    _fmt(m.get("mean_abs_log10_error")),
                    _fmt(m.get("coverage_68")),
                    _fmt(m.get("coverage_95")),
                    _fmt(m.get("median_predicted_sd")),
                    " / ".join(_fmt(m.get("by_class", {}).get(c, {}).get("median_abs_log10_error")) for c in cls[:-1]),
                ]
                for pool, m in r["magnitude"].items()
            ],
        )
    if "bulk_phase" in r:
        _section(
            L,
            "Random bulk phase per frame (network; the test draws with a uniform random phase per frame)",
            None,
            ["pool", "coverage", "acc. identifiable", "bal. acc. identifiable", "ECE"],
            "rrrrr",
            [
                [
                    pool,
                    _fmt(m["coverage_identifiable"]),
                    _fmt(m["accuracy_identifiable"]),
                    _fmt(m["balanced_accuracy_identifiable"]),
                    _fmt(m["ece"]),
                ]
                for pool, m in r["bulk_phase"].items()
            ],
        )
    if "shifted_prior" in r:
        _shifted_section(L, r["shifted_prior"], r["rule"])
    if "onnx_parity_max_abs_diff" in r:
        L.append(
            f"ONNX (opset {r.get('onnx_opset')}) against torch on the test set: max |Δp| = "
            f"{r['onnx_parity_max_abs_diff']:.2e}."
        )
        L.append("")
    return "\n".join(L)


def plot_report(report: dict[str, Any], path: str) -> None:
    """Confusion matrices, accuracy and indeterminate share against magnitude, reliability diagram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = report
    cls = r["classes"]
    pools = r["confusion_pools"]
    fig, axes = plt.subplots(2, 3, figsize=(15, 9))
    for ax, pool in zip(axes[0, :2], pools):
        cm = np.array(r["test"]["network"][pool]["confusion"], dtype=float)
        frac = cm / np.maximum(cm.sum(1, keepdims=True), 1)
        ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
        for i in range(len(cls)):
            for j in range(len(cls)):
                ax.text(
                    j,
                    i,
                    f"{frac[i, j]:.2f}",
                    ha="center",
                    va="center",
                    color="white" if frac[i, j] > 0.6 else "black",
                    fontsize=8,
                )
        ax.set_xticks(range(len(cls)), cls, rotation=30, fontsize=8)
        ax.set_yticks(range(len(cls)), cls, fontsize=8)
        ax.set_xlabel("decision")
        ax.set_ylabel("truth")
        ax.set_title(f"confusion (row-normalised), pool {pool}")
    ax = axes[0, 2]
    for pool, style in zip(pools, ("-", "--")):
        table = r["test"]["network"][pool]["reliability"]
        if table:
            c, a, _ = zip(*table)
            ax.plot(c, a, "o" + style, label=f"pool {pool} (ECE {r['test']['network'][pool]['ece']:.3f})")
    shifted = r.get("shifted_prior", {}).get("test", {}).get("1")
    if shifted and shifted["reliability"]:
        c, a, _ = zip(*shifted["reliability"])
        ax.plot(c, a, "^:", color="C3", label=f"shifted prior, pool 1 (ECE {shifted['ece']:.3f})")
    ax.plot([0, 1], [0, 1], "k:", lw=1)
    ax.set_xlabel("top-class probability")
    ax.set_ylabel("observed accuracy")
    ax.set_title("reliability")
    ax.legend(fontsize=8)
    colors = {"diffusion": "C0", "ballistic": "C1", "flow": "C2"}
    units = {"diffusion": "D [µm²/s]", "ballistic": "v [µm/s]", "flow": "v [µm/s]"}
    for ax, c in zip(axes[1], cls[:-1]):
        for pool, style in zip(pools, ("-", "--")):
            rows = [row for row in r["by_magnitude"][pool] if row["class"] == c]
            mid = [math.sqrt(row["low"] * row["high"]) for row in rows]
            ax.plot(
                mid,
                [row["accuracy_decided"] for row in rows],
                "o" + style,
                color=colors.get(c, "k"),
                label=f"accuracy (decided), pool {pool}",
            )
            ax.plot(
                mid,
                [row["predicted_indeterminate"] for row in rows],
                "s" + style,
                color="grey",
                label=f"decided indeterminate, pool {pool}",
            )
        rows = [row for row in r["by_magnitude"][pools[0]] if row["class"] == c]
        mid = [math.sqrt(row["low"] * row["high"]) for row in rows]
        ax.fill_between(
            mid, 0, [row["truth_indeterminate"] for row in rows], color="red", alpha=0.15, label="truth indeterminate"
        )
        ax.set_xscale("log")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel(units.get(c, "magnitude"))
        ax.set_title(c)
        ax.legend(fontsize=7)
    fig.suptitle(f"{r['spec']['name']}: test set")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(report: dict[str, Any], json_path, md_path, png_path) -> None:
    """Write the three report files (each atomically; callers check overwriting first)."""
    from torchdoct.files import atomic_write

    def w_json(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=1, default=_json_default)

    def w_md(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(format_markdown(report) + "\n")

    atomic_write(json_path, w_json)
    atomic_write(md_path, w_md)
    atomic_write(png_path, lambda tmp: plot_report(report, tmp))


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")

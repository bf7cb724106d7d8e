"""One setting fitted, timed (torch, onnxruntime) and scored with paired bootstrap standard errors."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

# ---------------------------------------------------------------------------------------------
# training (the recipe of classifier.train.train, steps 3-5, on given datasets)


def _fit(train_ds, val_ds, spec, cfg) -> dict[str, Any]:
    """:func:`classifier.train.fit_network` on given splits (the network of ``train``)."""
    from classifier.train import fit_network

    fit = fit_network(train_ds, val_ds, spec, cfg)
    fit.pop("first_samples")
    return fit


# ---------------------------------------------------------------------------------------------
# evaluation with paired bootstrap standard errors


def _bootstrap_weights(n_draws: int, n_boot: int, seed: int) -> np.ndarray:
    """``[n_boot, n_draws]`` resample counts of the draws: the resamples of
    :func:`classifier.report.bootstrap_se` (same generator calls) when every draw is present."""
    rng = np.random.default_rng(seed)
    draws = np.arange(n_draws)
    w = np.empty((n_boot, n_draws))
    for b in range(n_boot):
        w[b] = np.bincount(rng.choice(draws, draws.size, replace=True), minlength=n_draws)
    return w


def _draw_counts(
    pred: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    draw: np.ndarray,
    common: np.ndarray,
    n_draws: int,
    n_motion: int,
) -> dict[str, np.ndarray]:
    ind = n_motion
    ident = status == 0
    decided = ident & (pred != ind)

    def count(mask: np.ndarray) -> np.ndarray:
        return np.bincount(draw[mask], minlength=n_draws).astype(np.float64)

    return {
        "ident": count(ident),
        "dec": np.stack([count(decided & (y == c)) for c in range(n_motion)], 1),
        "cor": np.stack([count(decided & (y == c) & (pred == c)) for c in range(n_motion)], 1),
        "common": count(common),
        "common_correct": count(common & (pred == y)),
    }


def _weighted_stats(counts: dict[str, np.ndarray], w: np.ndarray) -> dict[str, np.ndarray]:
    """Balanced accuracy (identifiable, decided), coverage and common strict accuracy per weight row
    (definitions of :func:`classifier.report.evaluate`: mean recall over the classes present)."""
    ident = w @ counts["ident"]
    dec = w @ counts["dec"]
    cor = w @ counts["cor"]
    present = dec > 0
    recall = np.where(present, cor / np.where(present, dec, 1.0), 0.0)
    n_present = present.sum(-1)
    bal = np.where(n_present > 0, recall.sum(-1) / np.maximum(n_present, 1), np.nan)
    cov = np.where(ident > 0, dec.sum(-1) / np.where(ident > 0, ident, 1.0), np.nan)
    cc = w @ counts["common"]
    strict = np.where(cc > 0, (w @ counts["common_correct"]) / np.where(cc > 0, cc, 1.0), np.nan)
    return {"balanced_accuracy": bal, "coverage": cov, "strict_accuracy_common": strict}


def _sd(v: np.ndarray) -> float:
    v = np.asarray(v, np.float64)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if v.size >= 2 else math.nan


class _Evaluator:
    """Metrics of one predictor on the test samples of one spec, plus bootstrap replicates."""

    def __init__(self, weights: np.ndarray, common_by_draw: np.ndarray, rule: dict[str, Any]):
        self.weights = weights
        self.common_by_draw = common_by_draw
        self.rule = rule

    def __call__(self, probabilities: np.ndarray, s: dict[str, np.ndarray]) -> tuple[dict[str, Any], np.ndarray]:
        from classifier.report import evaluate
        from classifier.rule import apply_rule
        from classifier.train import CLASS_NAMES

        m = evaluate(probabilities, s["y"], s["status"], CLASS_NAMES, self.rule)
        pred, _ = apply_rule(probabilities, CLASS_NAMES, self.rule)
        n_draws = self.weights.shape[1]
        common = self.common_by_draw[s["draw"]]
        counts = _draw_counts(pred, s["y"], s["status"], s["draw"], common, n_draws, len(CLASS_NAMES) - 1)
        point = _weighted_stats(counts, np.ones((1, n_draws)))
        reps = _weighted_stats(counts, self.weights)
        bal = m["balanced_accuracy_identifiable"]
        out = {
            "samples": m["samples"],
            "identifiable_samples": m["identifiable_samples"],
            "balanced_accuracy": bal,
            "balanced_accuracy_se": _sd(reps["balanced_accuracy"]),
            "coverage": m["coverage_identifiable"],
            "coverage_se": _sd(reps["coverage"]),
            "accuracy": m["accuracy_identifiable"],
            "ece": m["ece"],
            "strict_accuracy_common": float(point["strict_accuracy_common"][0]),
            "strict_accuracy_common_se": _sd(reps["strict_accuracy_common"]),
            "error": 1.0 - bal,
            "error_se": _sd(reps["balanced_accuracy"]),
        }
        out["strict_error"] = 1.0 - out["strict_accuracy_common"]
        out["strict_error_se"] = out["strict_accuracy_common_se"]
        return out, {
            "error": 1.0 - reps["balanced_accuracy"],
            "coverage": reps["coverage"],
            "strict_error": 1.0 - reps["strict_accuracy_common"],
        }


def _best_time(fn: Callable[[], Any], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _ort_session(model, spec, threads: int):
    from classifier import __version__
    from classifier.export import onnx_model
    from classifier.runtime import onnx_session
    from classifier.train import CLASS_NAMES

    meta = {
        "classifier_version": __version__,
        "output": {"classes": list(CLASS_NAMES)},
        "input": {"columns": [{"name": n} for n in (*spec.feature_names, "pool_pixels")]},
    }
    return onnx_session(onnx_model(model, meta).SerializeToString(), threads=threads)

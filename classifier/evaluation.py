"""One evaluation for every test set: the metrics block of a classifier's decisions on labelled samples.

:func:`evaluate_set` scores the probabilities (and, for magnitude models, the predicted log10 magnitude and
its SD) that a model gives for one set of samples, whatever the set: the training's own test split, the
shifted-prior and random-bulk-phase test splits of :func:`classifier.train.train`, and independent data
(``tests/reference/evaluate_models.py``). The block (the definitions are those of :mod:`classifier.report`):

* ``metrics``: :func:`classifier.report.evaluate`: balanced accuracy and coverage on identifiable
  samples, per-class recall, ECE, confusion;
* ``standard_errors``: :func:`classifier.report.bootstrap_se`, a bootstrap over draws (the independent unit);
* ``flow_bands``: flow recall by polar band and speed decade (:func:`classifier.report.flow_recall_by_band`);
* ``coverage_curve``: accuracy against coverage as ``min_probability`` varies
  (:func:`classifier.report.coverage_curve`);
* ``by_magnitude``: accuracy and indeterminate shares against the motion magnitude
  (:func:`classifier.report.magnitude_table`);
* ``by_condition``: :func:`classifier.report.evaluate` per acquisition condition (noise, static fraction);
* ``magnitude``: the magnitude head's |log10 error| and the coverage of its 68 % and 95 % intervals
  (:func:`magnitude_metrics`).

A *sample set* is a dict of arrays of equal length: ``x`` (model inputs), ``y`` (motion label), ``status``
(0 where the ground truth says the motion is identifiable, :data:`classifier.truth.STATUS`), ``draw``
(the independent unit of the bootstrap), ``magnitude`` (D in µm²/s or v in µm/s), ``polar_angle_deg``
(the flow's angle from the depth axis; NaN for other motion), and for ``by_condition`` ``snr_db`` and
``static_fraction`` (:func:`classifier.train.eval_samples` makes them from a dataset). numpy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .prior import CLASSES
from .report import (
    COVERAGE_THRESHOLDS,
    bootstrap_draws,
    bootstrap_se,
    coverage_curve,
    evaluate,
    flow_recall_by_band,
    magnitude_table,
)
from .rule import INDETERMINATE

__all__ = ["CLASS_NAMES", "evaluate_set", "magnitude_metrics", "bootstrap_draws", "coverage_thresholds", "CONDITIONS"]

#: Output classes of every model: the motion types, then ``indeterminate``.
CLASS_NAMES = (*CLASSES, INDETERMINATE)

#: Half-widths of the central 68 % and 95 % intervals of a Gaussian, in SDs.
_INTERVALS = (("coverage_68", 1.0), ("coverage_95", 1.959964))


def coverage_thresholds(rule: dict[str, Any]) -> list[float]:
    """The ``min_probability`` values of the accuracy-coverage table: :data:`classifier.report.COVERAGE_THRESHOLDS`
    and the rule's own threshold."""
    return sorted({*COVERAGE_THRESHOLDS, float(rule["min_probability"])})


def magnitude_metrics(
    mean: np.ndarray,
    sd: np.ndarray,
    y: np.ndarray,
    status: np.ndarray,
    magnitude: np.ndarray,
    *,
    class_names: Sequence[str] = CLASSES,
    class_samples: bool = True,
) -> dict[str, Any]:
    """|log10 error| of the predicted magnitude and the coverage of its intervals, on identifiable samples.

    ``mean``, ``sd``: predicted log10 magnitude and its predictive SD per motion class, ``[N, K]`` (only the
    identifiable rows are read); the head of the true class ``y`` is scored against ``log10 magnitude``.
    Returns ``samples``, the median and mean absolute log10 error, the shares of errors within ±1 SD
    (``coverage_68``) and ±1.96 SD (``coverage_95``), the median predicted SD and the same per motion
    class (``by_class``; with its ``samples`` when ``class_samples``). Without identifiable samples:
    ``{"samples": 0}``.
    """
    ident = status == 0
    yy = y[ident]
    if yy.size == 0:
        return {"samples": 0}
    rows = np.arange(yy.size)
    mu = mean[ident][rows, yy].astype(np.float64)
    s = sd[ident][rows, yy].astype(np.float64)
    err = np.abs(mu - np.log10(magnitude[ident]))
    out: dict[str, Any] = {
        "samples": int(yy.size),
        "median_abs_log10_error": float(np.median(err)),
        "mean_abs_log10_error": float(err.mean()),
    }
    for key, k in _INTERVALS:
        out[key] = float(np.mean(err <= k * s))
    out["median_predicted_sd"] = float(np.median(s))
    by_class = {}
    for c in range(len(class_names)):
        m = yy == c
        if not np.any(m):
            continue
        row: dict[str, Any] = {"samples": int(np.sum(m))} if class_samples else {}
        row["median_abs_log10_error"] = float(np.median(err[m]))
        for key, k in _INTERVALS:
            row[key] = float(np.mean(err[m] <= k * s[m]))
        by_class[class_names[c]] = row
    out["by_class"] = by_class
    return out


def _band_scalars(fb: dict[str, Any]) -> dict[str, float]:
    return {f"{kind}:{name}": r["recall"] for kind in ("polar_bands", "speed_decades") for name, r in fb[kind].items()}


#: The acquisition conditions of ``by_condition``: (noise, static fraction) present or not.
CONDITIONS = ("no noise, no static", "no noise, static fraction", "noise, no static", "noise and static fraction")


def _conditions(s: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    noisy = np.isfinite(s["snr_db"])
    mixed = s["static_fraction"] > 0
    return dict(zip(CONDITIONS, (~noisy & ~mixed, ~noisy & mixed, noisy & ~mixed, noisy & mixed)))


def evaluate_set(
    probabilities: np.ndarray,
    samples: dict[str, np.ndarray],
    rule: dict[str, Any],
    *,
    class_names: Sequence[str] = CLASS_NAMES,
    magnitude: tuple[np.ndarray, np.ndarray] | None = None,
    ranges: Sequence[tuple[float, float]] | None = None,
    detail: bool = True,
    by_condition: bool = False,
    resampled_errors: bool = False,
    thresholds: Sequence[float] | None = None,
    n_boot: int = 200,
    seed: int = 0,
    class_samples: bool = True,
) -> dict[str, Any]:
    """The metrics block (module docstring) of one sample set, decided by ``rule`` (:mod:`classifier.rule`).

    ``probabilities`` ``[N, C]`` over ``class_names`` (the last ``indeterminate``); ``samples`` the sample set
    (module docstring). ``detail``: besides ``metrics``, the bootstrap ``standard_errors`` (``n_boot``
    resamples, ``seed``), ``flow_bands``, the ``coverage_curve`` (at ``thresholds``, default
    :func:`coverage_thresholds`) and, given the motion classes' magnitude ``ranges``, ``by_magnitude``;
    ``by_condition``: the metrics per acquisition condition (:data:`CONDITIONS`); ``magnitude``: the predicted
    ``(log10 magnitude, SD)`` ``[N, K]`` → ``magnitude`` (:func:`magnitude_metrics`; ``class_samples``
    passed on); ``resampled_errors``: bootstrap SEs also of the flow recall per band (``flow_bands_se``),
    the per-class recall (``recall_se``) and the magnitude metrics (``magnitude_se``), by
    :func:`bootstrap_draws`. Keys in that order, after ``samples``.
    """
    p = np.asarray(probabilities)
    y, st, dr = samples["y"], samples["status"], samples["draw"]
    names = class_names
    out: dict[str, Any] = {"samples": int(len(y)), "metrics": evaluate(p, y, st, names, rule)}
    if detail:
        out["standard_errors"] = bootstrap_se(p, y, st, dr, names, rule, n_boot=n_boot, seed=seed)
        theta, mag = samples["polar_angle_deg"], samples["magnitude"]
        out["flow_bands"] = flow_recall_by_band(p, y, st, theta, mag, names, rule)
        if resampled_errors:
            out["flow_bands_se"] = bootstrap_draws(
                lambda i: _band_scalars(flow_recall_by_band(p[i], y[i], st[i], theta[i], mag[i], names, rule)),
                dr,
                n_boot=n_boot,
                seed=seed,
            )
            out["recall_se"] = bootstrap_draws(
                lambda i: evaluate(p[i], y[i], st[i], names, rule)["recall_identifiable"], dr, n_boot=n_boot, seed=seed
            )
        out["coverage_curve"] = coverage_curve(
            p, y, st, names, rule, coverage_thresholds(rule) if thresholds is None else thresholds
        )
        if ranges is not None:
            out["by_magnitude"] = magnitude_table(p, y, st, mag, names, rule, ranges)
    if by_condition:
        out["by_condition"] = {
            name: evaluate(p[m], y[m], st[m], names, rule) for name, m in _conditions(samples).items() if m.any()
        }
    if magnitude is not None:
        mean, sd = magnitude
        motion = names[:-1]
        out["magnitude"] = magnitude_metrics(
            mean, sd, y, st, samples["magnitude"], class_names=motion, class_samples=class_samples
        )
        if resampled_errors:
            out["magnitude_se"] = bootstrap_draws(
                lambda i: {
                    k: v
                    for k, v in magnitude_metrics(
                        mean[i],
                        sd[i],
                        y[i],
                        st[i],
                        samples["magnitude"][i],
                        class_names=motion,
                        class_samples=class_samples,
                    ).items()
                    if isinstance(v, float)
                },
                dr,
                n_boot=n_boot,
                seed=seed,
            )
    return out

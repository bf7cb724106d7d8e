"""Fast checks of the magnitude ceiling (:mod:`magnitude_ceiling`): the quantile regressors recover a
known conditional distribution (median error and interval shares of a Gaussian, within the Monte Carlo
error), the metrics are exact on known intervals, and a small run reads the shared feature cache and
writes its report. The report's numbers come from ``python -m tests.reference.magnitude_ceiling``
(research/results/independent-magnitude-ceiling.md)."""

from __future__ import annotations

import json
import math

import magnitude_ceiling as mc
import numpy as np
import pytest

SIGMA = 0.1


def _synthetic(n: int, seed: int):
    """Inputs U[0, 1]³, target a step function of the first input (4 levels, trees fit it exactly) plus
    Gaussian noise of SD :data:`SIGMA`: the conditional median is the step, its 68.27 % and 95.45 %
    central intervals ±1 and ±2 SD around it."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(size=(n, 3))
    step = 0.5 * np.floor(4 * x[:, 0])
    return x, step + SIGMA * rng.standard_normal(n), step


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_quantile_regressors_recover_a_known_gaussian():
    n_train, n_test = 20000, 20000
    x, t, _ = _synthetic(n_train, 1)
    models = mc.fit_quantiles(x, t, seed=0)
    xt, tt, step = _synthetic(n_test, 2)
    pred = mc.predict_quantiles(models, xt)
    r = mc.interval_metrics(pred, tt, np.zeros(n_test, np.int64), np.arange(n_test), n_boot=0, seed=0)
    # the intervals are conformalised on the held-out share of the training samples: its binomial error
    # adds to the test set's
    n_cal = n_train * mc.CALIBRATION_SHARE
    n_cell = n_train * (1 - mc.CALIBRATION_SHARE) / 4 * (1 - mc.GBR_PARAMS["validation_fraction"])
    for key, p in mc.LEVELS:
        se = math.sqrt(p * (1 - p) * (1 / n_test + 1 / n_cal))
        assert abs(r[key] - p) < 3 * se, (key, r[key], p, se)
    # median |N(0, σ)| = 0.6745 σ; SE of a sample median: 1 / (2 f(m) √n), f = 2 φ(0.6745) / σ
    m = 0.6744898 * SIGMA
    f = 2 * math.exp(-0.5 * 0.6744898**2) / math.sqrt(2 * math.pi) / SIGMA
    se_med = 1 / (2 * f * math.sqrt(n_test))
    # an error δ of the fitted median (SE σ√(π/2)/√n_cell) raises median |N + δ| by about δ²/(2σ)·...: bounded
    bias = (3 * SIGMA * math.sqrt(math.pi / 2) / math.sqrt(n_cell)) ** 2 / SIGMA
    assert abs(r["median_abs_log10_error"] - m) < 3 * se_med + bias, (r["median_abs_log10_error"], m)


def test_interval_ends_are_ordered():
    x, t, _ = _synthetic(2000, 3)
    pred = mc.predict_quantiles(mc.fit_quantiles(x, t, seed=0), _synthetic(500, 4)[0])
    assert np.all(pred[:, 3] <= pred[:, 1]) and np.all(pred[:, 1] <= pred[:, 0])
    assert np.all(pred[:, 0] <= pred[:, 2]) and np.all(pred[:, 2] <= pred[:, 4])


def test_interval_metrics_on_known_intervals():
    truth = np.array([0.0, 0.0, 0.0, 0.0])
    # medians off by 0.1, 0.2, 0.3, 0.4; 68 % intervals ±0.25 around them; 95 % intervals ±0.35
    med = np.array([0.1, -0.2, 0.3, -0.4])
    pred = np.stack([med, med - 0.25, med + 0.25, med - 0.35, med + 0.35], axis=1)
    r = mc.interval_metrics(pred, truth, np.array([0, 0, 1, 2]), np.arange(4), n_boot=0, seed=0)
    assert r["median_abs_log10_error"] == pytest.approx(0.25)
    assert r["coverage_68"] == pytest.approx(0.5)  # |0.1|, |0.2| inside ±0.25
    assert r["coverage_95"] == pytest.approx(0.75)  # and |0.3|
    assert r["median_half_width_68"] == pytest.approx(0.25)
    assert r["by_class"]["diffusion"]["coverage_68"] == pytest.approx(1.0)
    assert r["by_class"]["flow"]["coverage_95"] == pytest.approx(0.0)


def test_too_few_samples_is_refused():
    with pytest.raises(ValueError, match="too few"):
        mc.fit_quantiles(np.zeros((10, 2)), np.zeros(10))


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_small_run_writes_its_report(tmp_path, capsys):
    args = [
        "--out",
        str(tmp_path),
        "--parts",
        "c",
        "--train-draws",
        "12",
        "--test-draws",
        "6",
        "--trials",
        "32",
        "--boot",
        "2",
        "--no-progress",
    ]
    assert mc.main(args) == 0
    rep = json.loads((tmp_path / "independent-magnitude-ceiling.json").read_text())
    r1 = rep["parts"]["c"]["pools"]["1"]
    assert r1["test_samples"] == 6 * 32  # every draw of the independent prior is identifiable
    for key in ("quantile_gb", "shipped"):
        assert 0.0 <= r1[key]["coverage_68"] <= r1[key]["coverage_95"] <= 1.0
        assert r1[key]["median_abs_log10_error"] >= 0.0
    assert "quantile GB" in (tmp_path / "independent-magnitude-ceiling.md").read_text()
    assert mc.main(args) == 2  # never over an existing report
    assert "exists" in capsys.readouterr().err

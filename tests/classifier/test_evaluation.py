"""One evaluation for every test set (classifier.evaluation) and the public steps of classifier.train.train."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from classifier.evaluation import CLASS_NAMES, bootstrap_draws, evaluate_set, magnitude_metrics
from classifier.report import bootstrap_se, coverage_curve, evaluate, flow_recall_by_band
from classifier.rule import make_rule

ROOT = Path(__file__).resolve().parents[2]


def _samples(n_draws: int = 12, per_draw: int = 10, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A random sample set (motion labels, ground truth, draws, magnitudes, flow angles, conditions) and
    probabilities that favour the true class."""
    rng = np.random.default_rng(seed)
    n = n_draws * per_draw
    draw = np.repeat(np.arange(n_draws), per_draw)
    y = draw % 3
    status = np.where(rng.random(n_draws) < 0.8, 0, 1 + (rng.random(n_draws) < 0.5))[draw]
    logits = rng.normal(size=(n, 4))
    logits[np.arange(n), np.where(status == 0, y, 3)] += 1.5
    p = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
    s = {
        "x": np.zeros((n, 2), np.float32),
        "y": y,
        "status": status,
        "draw": draw,
        "magnitude": 10.0 ** rng.uniform(-2, 1, n_draws)[draw],
        "polar_angle_deg": np.where(y == 2, rng.uniform(0, 180, n_draws)[draw], np.nan),
        "snr_db": np.where(rng.random(n_draws) < 0.5, 20.0, np.inf)[draw],
        "static_fraction": np.where(rng.random(n_draws) < 0.5, 0.3, 0.0)[draw],
    }
    return p, s


def test_the_block_is_the_report_functions_on_the_same_samples():
    """Every part of the block is the metric of classifier.report it names, on the very samples."""
    p, s = _samples()
    rule = make_rule(0.05, 0.5)
    ranges = [(1e-2, 10.0)] * 3
    b = evaluate_set(p, s, rule, ranges=ranges, by_condition=True, seed=3)
    y, st = s["y"], s["status"]
    assert b["samples"] == len(y)
    assert b["metrics"] == evaluate(p, y, st, CLASS_NAMES, rule)
    assert b["standard_errors"] == bootstrap_se(p, y, st, s["draw"], CLASS_NAMES, rule, seed=3)
    assert b["flow_bands"] == flow_recall_by_band(p, y, st, s["polar_angle_deg"], s["magnitude"], CLASS_NAMES, rule)
    curve = coverage_curve(p, y, st, CLASS_NAMES, rule, [0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    assert [r["min_probability"] for r in b["coverage_curve"]] == [0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
    assert b["coverage_curve"] == curve
    # at the rule's threshold the curve is the metrics' coverage; a threshold of the rule's own is added
    assert b["coverage_curve"][1]["coverage_identifiable"] == b["metrics"]["coverage_identifiable"]
    own = evaluate_set(p, s, make_rule(0.05, 0.55))["coverage_curve"]
    assert [r["min_probability"] for r in own] == [0.4, 0.5, 0.55, 0.6, 0.7, 0.8, 0.9]
    # by condition: the metrics of each condition's samples, which partition the set
    conds = b["by_condition"]
    assert sum(m["samples"] for m in conds.values()) == len(y)
    noisy_static = np.isfinite(s["snr_db"]) & (s["static_fraction"] > 0)
    assert conds["noise and static fraction"] == evaluate(
        p[noisy_static], y[noisy_static], st[noisy_static], CLASS_NAMES, rule
    )
    lean = evaluate_set(p, s, rule, detail=False)
    assert list(lean) == ["samples", "metrics"]  # the metrics alone: the baselines and the bulk-phase set


def test_magnitude_metrics_on_a_constructed_case():
    """Errors and SDs set by hand: median and mean |log10 error| and the interval shares counted."""
    y = np.array([0, 0, 1, 1, 2, 2])
    status = np.array([0, 0, 0, 0, 0, 1])  # the last is not identifiable: not scored
    magnitude = np.full(6, 10.0)  # log10 = 1
    err = np.array([0.1, 0.5, 0.2, 1.5, 0.3, 9.0])
    mean = np.full((6, 3), np.nan)
    mean[np.arange(6), y] = 1.0 + err * np.array([1, -1, 1, -1, 1, 1])
    sd = np.full((6, 3), 0.4)
    m = magnitude_metrics(mean, sd, y, status, magnitude)
    scored = err[:5]
    assert m["samples"] == 5
    assert m["median_abs_log10_error"] == pytest.approx(np.median(scored))
    assert m["mean_abs_log10_error"] == pytest.approx(scored.mean())
    assert m["coverage_68"] == pytest.approx(3 / 5)  # 0.1, 0.2, 0.3 ≤ 0.4
    assert m["coverage_95"] == pytest.approx(4 / 5)  # and 0.5 ≤ 1.96 · 0.4
    assert m["median_predicted_sd"] == pytest.approx(0.4)
    assert m["by_class"]["ballistic"] == {
        "samples": 2,
        "median_abs_log10_error": pytest.approx(0.85),
        "coverage_68": 0.5,
        "coverage_95": 0.5,
    }
    assert "samples" not in magnitude_metrics(mean, sd, y, status, magnitude, class_samples=False)["by_class"]["flow"]
    assert magnitude_metrics(mean, sd, y, np.ones(6, np.int64), magnitude) == {"samples": 0}


def test_bootstrap_draws_resamples_as_bootstrap_se():
    """The same draws resampled with the same seed: the SE of a metric is bootstrap_se's."""
    p, s = _samples()
    rule = make_rule(0.05, 0.5)
    y, st, dr = s["y"], s["status"], s["draw"]
    se = bootstrap_draws(
        lambda i: {"ece": evaluate(p[i], y[i], st[i], CLASS_NAMES, rule)["ece"]}, dr, n_boot=50, seed=4
    )
    assert se["ece"] == bootstrap_se(p, y, st, dr, CLASS_NAMES, rule, n_boot=50, seed=4)["ece"]
    assert bootstrap_draws(lambda i: {"n": float(len(i))}, np.zeros(5), n_boot=10) == {}  # one draw: none
    b = evaluate_set(
        p, s, rule, magnitude=(np.zeros((len(y), 3)), np.ones((len(y), 3))), resampled_errors=True, n_boot=50, seed=4
    )
    assert list(b) == [
        "samples",
        "metrics",
        "standard_errors",
        "flow_bands",
        "flow_bands_se",
        "recall_se",
        "coverage_curve",
        "magnitude",
        "magnitude_se",
    ]
    assert set(b["recall_se"]) == {"diffusion", "ballistic", "flow"}
    assert all(math.isfinite(v) and v >= 0 for v in b["magnitude_se"].values())


def test_training_report_is_evaluate_set_on_each_test_set(tmp_path):
    """The report's numbers of the test split, the bulk-phase set and the shifted prior are evaluate_set on
    the samples evaluation_sets draws from each, with the network's predictions."""
    from classifier.train import (
        TrainConfig,
        evaluate_test_sets,
        evaluation_sets,
        fit_models,
        network_predictions,
        plan_training,
        simulate_data,
        train,
        training_report,
    )

    cfg = TrainConfig(
        spec="two-wavelength",
        draws_train=9,
        draws_validation=6,
        draws_test=6,
        replicates=2,
        max_epochs=2,
        singles_per_group=16,
        pooled_per_group=4,
        baselines=False,
        magnitude=True,
        shifted_test=True,
        bulk_phase_test=True,
    )
    plan = plan_training(cfg)
    assert plan.magnitude and plan.shifted_test and plan.bulk_phase_test
    data = simulate_data(plan, cache_dir=tmp_path, log=None)
    fitted = fit_models(plan, data, log=None)
    evaluation = evaluate_test_sets(plan, data, fitted, log=None)
    report = training_report(plan, data, fitted, evaluation)
    whole = train(cfg, cache_dir=tmp_path, log=None)  # the steps one after the other are train()
    assert (
        whole.report["test"] == report["test"]
        and whole.report["shifted_prior"]["test"] == report["shifted_prior"]["test"]
    )
    model = fitted.model
    for name, ds, _key, stream in (
        ("test", data.splits["test"], None, 9),
        ("bulk_phase", data.bulk_phase, "bulk_phase", 9),
        ("shifted_prior", data.shifted_prior, "shifted_prior", 10),
    ):
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(stream,)))
        sets, _ = evaluation_sets(ds, cfg, plan.spec, rng)
        s = sets["1"]
        p, mag = network_predictions(model, s, magnitude=True)
        block = evaluate_set(p, s, plan.rule, magnitude=mag, class_samples=False, seed=cfg.seed)
        if name == "test":
            assert report["test"]["network"]["1"] == block["metrics"]
            assert report["standard_errors"]["1"] == block["standard_errors"]
            assert report["flow_bands"]["1"] == block["flow_bands"]
            assert report["coverage_curve"]["1"] == block["coverage_curve"]
            assert report["magnitude"]["1"] == block["magnitude"]
        elif name == "bulk_phase":
            assert report["bulk_phase"]["1"] == block["metrics"]
        else:
            sp = report["shifted_prior"]
            assert sp["test"]["1"] == block["metrics"] and sp["magnitude"]["1"] == block["magnitude"]
            assert sp["coverage_curve"]["1"] == block["coverage_curve"] and sp["flow_bands"]["1"] == block["flow_bands"]


def _private_classifier_imports(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if (
            isinstance(node, ast.ImportFrom)
            and node.module
            and node.module.split(".")[0] == "classifier"
            and node.level == 0
        ):
            found += [
                f"{path.relative_to(ROOT)}: from {node.module} import {a.name}"
                for a in node.names
                if a.name.startswith("_") and not a.name.endswith("__")
            ]
    return found


def test_research_and_reference_code_use_public_names_of_classifier():
    """research/ and tests/reference/ import no private name of a classifier module."""
    files = sorted((ROOT / "research").rglob("*.py")) + sorted((ROOT / "tests" / "reference").glob("*.py"))
    assert files
    bad = [hit for f in files for hit in _private_classifier_imports(f)]
    assert not bad, bad

"""Conformal prediction sets (classifier.conformal): finite-sample coverage on known distributions, nested
sets, the set labels, and the shipped calibrations."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from classifier import conformal
from classifier.conformal import (
    conformal_quantile,
    pool_thresholds,
    prediction_sets,
    scores_lac,
    set_label_names,
    set_labels,
)

CLASSES = ["diffusion", "ballistic", "flow", "indeterminate"]


@pytest.mark.parametrize("n, alpha", [(50, 0.1), (199, 0.05), (400, 0.2)])
def test_conformal_quantile_covers_new_draws_at_its_finite_sample_level(n, alpha):
    """Exchangeable continuous scores: P(s_new ≤ q̂) = ⌈(n+1)(1−α)⌉/(n+1) exactly (≥ 1 − α). R independent
    (calibration, new draw) pairs of exponential scores: the hit rate within 4 binomial SEs of that value."""
    rng = np.random.default_rng(12)
    reps = 20000
    cal = rng.exponential(size=(reps, n))
    new = rng.exponential(size=reps)
    q = np.array([conformal_quantile(c, alpha) for c in cal])
    hit = new <= q
    k = math.ceil((n + 1) * (1 - alpha))
    p = k / (n + 1)
    se = math.sqrt(p * (1 - p) / reps)
    assert p >= 1 - alpha
    assert abs(hit.mean() - p) < 4 * se, (hit.mean(), p, se)


def test_conformal_quantile_is_infinite_when_too_few_samples_and_refuses_bad_input():
    assert conformal_quantile(np.arange(5.0), 0.1) == math.inf  # ⌈6·0.9⌉ = 6 > 5: every class in the set
    assert conformal_quantile(np.arange(1.0, 20.0), 0.1) == 18.0  # ⌈20·0.9⌉ = 18th smallest
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="alpha"):
            conformal_quantile(np.arange(10.0), bad)
    with pytest.raises(ValueError, match="finite"):
        conformal_quantile(np.array([0.1, np.nan]), 0.1)


def _synthetic(rng, n):
    """Probabilities of a model that is right 70 % of the time, and the true classes."""
    truth = rng.integers(0, 4, n)
    logits = rng.normal(size=(n, 4))
    logits[np.arange(n), truth] += 1.5
    p = np.exp(logits)
    return p / p.sum(1, keepdims=True), truth


def test_class_conditional_sets_cover_every_class_within_its_binomial_error():
    """Mondrian thresholds: coverage of each class's new pixels ≥ 1 − α (within 4 SEs of the binomial rate),
    although the classes differ in how hard they are (class 3's scores shifted)."""
    rng = np.random.default_rng(5)
    alpha = 0.1
    p_cal, t_cal = _synthetic(rng, 4000)
    p_new, t_new = _synthetic(rng, 40000)
    for p in (p_cal, p_new):  # class 3 made hard: its probability halved, the rest renormalised
        p[:, 3] *= 0.5
        p /= p.sum(1, keepdims=True)
    pool = {"scores": list(scores_lac(p_cal, t_cal)), "truth": list(t_cal)}
    q = pool_thresholds(pool, 4, alpha)
    members = prediction_sets(p_new, q)
    for k in range(4):
        cov = members[t_new == k, k].mean()
        m = int((t_new == k).sum())
        se = math.sqrt(alpha * (1 - alpha) / m) + math.sqrt(alpha * (1 - alpha) / int((t_cal == k).sum()))
        assert cov >= 1 - alpha - 4 * se, (k, cov)
        assert cov <= 1 - alpha + 1 / ((t_cal == k).sum() + 1) + 4 * se, (k, cov)
    # the marginal threshold covers the pixels overall but not the hard class
    qm = pool_thresholds(pool, 4, alpha, "marginal")
    mm = prediction_sets(p_new, qm)
    assert abs(mm[np.arange(t_new.size), t_new].mean() - (1 - alpha)) < 0.01
    assert mm[t_new == 3, 3].mean() < 1 - alpha - 0.02


def test_sets_shrink_as_alpha_grows():
    """A larger α: a lower quantile per class, so every set is a subset of the smaller α's set."""
    rng = np.random.default_rng(9)
    p_cal, t_cal = _synthetic(rng, 2000)
    p_new, _ = _synthetic(rng, 5000)
    pool = {"scores": list(scores_lac(p_cal, t_cal)), "truth": list(t_cal)}
    prev, sizes = None, []
    for alpha in (0.02, 0.05, 0.1, 0.2, 0.4):
        m = prediction_sets(p_new, pool_thresholds(pool, 4, alpha))
        if prev is not None:
            assert not (m & ~prev).any()  # nested
        prev = m
        sizes.append(m.sum(1).mean())
    assert all(a > b for a, b in zip(sizes, sizes[1:])), sizes


def test_set_labels_name_the_motion_classes_in_the_set():
    names = CLASSES + set_label_names(CLASSES)
    assert names[4:] == ["diffusion-or-ballistic", "diffusion-or-flow", "ballistic-or-flow"]
    rows = {  # membership over (diffusion, ballistic, flow, indeterminate) -> label
        (0, 0, 1, 0): "flow",
        (0, 0, 1, 1): "flow",
        (0, 0, 0, 1): "indeterminate",
        (0, 0, 0, 0): "indeterminate",
        (0, 1, 1, 0): "ballistic-or-flow",
        (1, 0, 1, 1): "diffusion-or-flow",
        (1, 1, 0, 0): "diffusion-or-ballistic",
        (1, 1, 1, 0): "indeterminate",
        (1, 1, 1, 1): "indeterminate",
        (1, 0, 0, 0): "diffusion",
    }
    got = set_labels(np.array(list(rows), bool), CLASSES)
    assert [names[g] for g in got] == list(rows.values())


@pytest.mark.parametrize("name", ["signature-bscan", "signature"])
def test_shipped_calibrations_load_with_the_model_and_cover_their_own_samples(name):
    """The calibration beside each shipped default model: read with it, every pool with its samples, and on
    its own samples at least 1 − α of each class covered (the quantile's definition)."""
    from classifier.infer import load_model

    m = load_model(name, threads=1)
    cal = m.calibration
    assert cal is not None and cal["model"] == name and cal["classes"] == m.classes
    assert [p["pool_pixels"] for p in cal["pools"]] == [1, 4, 9, 25]
    d = cal["description"]
    assert d["static_free_groups"] > 0 and d["flow_groups_polar_above_60deg_static_free"] > 0
    for p in cal["pools"]:
        sc, tr = np.asarray(p["scores"]), np.asarray(p["truth"])
        assert sc.size == p["samples"] == d["groups"]
        for alpha in (0.05, 0.1, 0.2):
            q = pool_thresholds(p, len(m.classes), alpha)
            for k in range(len(m.classes)):
                if (tr == k).any():
                    assert (sc[tr == k] <= q[k]).mean() >= 1 - alpha
            for r in p["reliability"].values():
                assert 0.0 <= r["ece"] < 0.1


def test_a_corrupt_calibration_is_refused_naming_the_file(tmp_path):
    import shutil

    from classifier.infer import load_model, shipped_models

    src = shipped_models()["signature-bscan"]
    dst = tmp_path / "m.onnx"
    shutil.copy(src, dst)
    bad = tmp_path / "m.calibration.json"
    good = json.loads(src.with_name("signature-bscan.calibration.json").read_text())
    for text in (
        "{not json",
        json.dumps({**good, "schema_version": 99}),
        json.dumps({**good, "classes": ["a", "b", "c", "d"]}),
        json.dumps({**good, "pools": [{**good["pools"][0], "truth": [9] * good["pools"][0]["samples"]}]}),
    ):
        bad.write_text(text)
        with pytest.raises(ValueError, match="m.calibration.json"):
            load_model(dst, threads=1)
    bad.unlink()
    assert load_model(dst, threads=1).calibration is None


def test_default_alpha_is_documented():
    assert conformal.DEFAULT_ALPHA == 0.1

"""Classifier trade-offs: a tiny run of every axis, its Pareto fronts, and the pieces it relies on."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from classifier.bench.tradeoffs import (
    DEFAULTS,
    TradeoffPlan,
    _bootstrap_weights,
    _Evaluator,
    _fit,
    _pareto,
    derive_dataset,
    format_table,
    one_configuration_spec,
    plot_tradeoffs,
    prefix_dataset,
    run_tradeoffs,
)
from classifier.dataset import make_dataset
from classifier.features import load_spec
from classifier.prior import Prior
from classifier.report import bootstrap_se, evaluate
from classifier.rule import make_rule
from classifier.train import CLASS_NAMES, TrainConfig, train
from classifier.truth import STATUS

TINY = TradeoffPlan(
    draws_grid=(3, 6),
    draws_base=6,
    draws_validation=3,
    draws_test=6,
    replicates=2,
    hidden_grid=((4,), (8, 8)),
    pools=(1, 4, 25),
    max_epochs=5,
    timing_draws=1,
    map_side=32,
    timing_repeats=1,
    n_boot=50,
)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("clf-tradeoffs-cache")


@pytest.fixture(scope="module")
def result(cache_dir):
    return run_tradeoffs(TINY, cache_dir=cache_dir)


def test_result_is_json_ready_and_round_trips(result):
    text = json.dumps(result, allow_nan=False)
    assert json.loads(text) == result
    assert set(result["axes"]) == {"training_draws", "feature_spec", "model_size", "pool"}
    assert [r["draws_train"] for r in result["axes"]["training_draws"]["rows"]] == list(TINY.draws_grid)
    assert [r["label"] for r in result["axes"]["feature_spec"]["rows"]] == [
        "one-configuration",
        "single-acquisition",
        "two-wavelength",
    ]
    assert [r["pool"] for r in result["axes"]["pool"]["rows"]] == list(TINY.pools)
    assert result["plan"] == TINY.to_dict() and result["defaults"] == DEFAULTS
    # fronts: both errors against an axis's primary cost, the balanced error against the others
    assert {(p["time_key"], p["error_key"], p["pool"]) for p in result["axes"]["model_size"]["pareto"]} == {
        (tk, ek, pool)
        for tk, ek in (("inference_ort_us", "error"), ("inference_ort_us", "strict_error"), ("training_s", "error"))
        for pool in ("1", "25")
    }


def test_pareto_fronts_are_non_dominated_and_complete(result):
    entries = [p for ax in result["axes"].values() for p in ax["pareto"]]
    assert entries
    for e in entries:
        pts = {p["label"]: p for p in e["points"]}
        front = [pts[lbl] for lbl in e["front"]]
        assert bool(front) == bool(pts), e["axis"]  # points = settings with a finite error
        times = [p["time"] for p in front]
        errors = [p["error"] for p in front]
        assert times == sorted(times) and all(a > b for a, b in zip(errors, errors[1:]))
        for f in front:  # nothing beats a front point in both time and error
            assert not any(
                q["time"] <= f["time"]
                and q["error"] <= f["error"]
                and (q["time"] < f["time"] or q["error"] < f["error"])
                for q in pts.values()
            )
        for p in pts.values():  # every other point is (weakly) dominated by a front point
            assert any(f["time"] <= p["time"] and f["error"] <= p["error"] for f in front)
        if e["defaults"] is not None and e["defaults"] not in pts:  # left off for low coverage
            assert e["defaults_on_front"] is None and e["defaults"] in [x["label"] for x in e["excluded"]]
        elif e["defaults"] is not None:
            d = pts[e["defaults"]]
            faster_better = [q["label"] for q in pts.values() if q["time"] < d["time"] and q["error"] < d["error"]]
            assert sorted(x["label"] for x in e["defaults_dominated_by"]) == sorted(faster_better)
            assert e["defaults_on_front"] == (d["label"] in e["front"])
        if e["error_key"] == "strict_error":  # coverage is part of this error: nothing is left off for it
            assert not [x for x in e["excluded"] if x["reason"].startswith("coverage")]
        if pts:
            assert e["recommended"] in pts and e["best"] in pts
            assert pts[e["recommended"]]["time"] <= pts[e["best"]]["time"]
    pool = result["axes"]["pool"]["pareto"][0]  # the shipped model decides: its axis has points
    assert len(pool["points"]) == len(TINY.pools) and pool["defaults"] == f"pool {DEFAULTS['pool']}"


def test_pareto_dominance_and_one_se_rule_on_constructed_points():
    rng = np.random.default_rng(0)

    def unit(n=400):
        z = rng.normal(size=n)
        return (z - z.mean()) / z.std(ddof=1)

    z1, z2, z3 = unit(), unit(), unit()
    errors = {
        "A": (1.0, 0.30, 0.05 * z2),
        "B": (2.0, 0.25, 0.1 * z1),
        "C": (3.0, 0.26, 0.1 * z1 + 0.001 * z3),
        "D": (4.0, 0.20, 0.0 * z1),
        "E": (0.5, 0.10, 0.0 * z1),
    }
    coverage = {"A": 0.5, "B": 0.5, "C": 0.5, "D": 0.5, "E": 0.05}  # E decides too little to count
    rows = [
        {
            "label": k,
            "t_s": t,
            "pools": {"1": {"error": e, "error_se": 0.0, "coverage": coverage[k], "coverage_se": 0.0}},
        }
        for k, (t, e, _) in errors.items()
    ]
    reps = {(k, "1"): {"error": e + noise, "coverage": coverage[k] + 0.0 * z1} for k, (_, e, noise) in errors.items()}
    out = _pareto("x", rows, reps, "t_s", "1", "C", 0.1)
    assert out["front"] == ["A", "B", "D"] and [x["label"] for x in out["excluded"]] == ["E"]
    assert out["defaults_on_front"] is False and out["defaults_significantly_dominated"] is True
    (dom,) = out["defaults_dominated_by"]
    assert dom["label"] == "B" and dom["z"] == pytest.approx(0.01 / 0.001, rel=1e-6)
    # best D; B is 0.05 worse with paired SE 0.1 (kept), A 0.10 worse with paired SE 0.05 (dropped)
    assert out["best"] == "D" and out["recommended"] == "B"
    loose = _pareto(
        "x", rows, {**reps, ("C", "1"): {"error": 0.26 + 0.1 * z2, "coverage": 0.5 + 0.0 * z1}}, "t_s", "1", "C", 0.1
    )
    assert loose["defaults_significantly_dominated"] is False  # 0.01 against a paired SE of ~0.14
    # a cheaper setting as accurate but deciding clearly less is not recommended
    fewer = {**reps, ("B", "1"): {"error": reps[("B", "1")]["error"], "coverage": 0.3 + 0.01 * z3}}
    rows_b = [dict(r, pools={"1": {**r["pools"]["1"], "coverage": 0.3}}) if r["label"] == "B" else r for r in rows]
    assert _pareto("x", rows_b, fewer, "t_s", "1", "C", 0.1)["recommended"] == "C"  # next cheapest within 1 SE
    assert _pareto("x", rows, reps, "t_s", "1", "C", 0.0)["front"] == ["E"]  # without the floor E wins


def test_defaults_are_marked_where_the_grid_holds_them(result):
    ax = result["axes"]
    assert [r["label"] for r in ax["feature_spec"]["rows"] if r["is_default"]] == [DEFAULTS["spec"]]
    assert [r["pool"] for r in ax["pool"]["rows"] if r["is_default"]] == [DEFAULTS["pool"]]
    assert not any(r["is_default"] for r in ax["training_draws"]["rows"])  # 270 draws is not in the tiny grid
    assert all(p["defaults"] is None for p in ax["training_draws"]["pareto"])


def test_recorded_times_are_positive(result):
    for name in ("training_draws", "feature_spec", "model_size"):
        for row in result["axes"][name]["rows"]:
            for key in (
                "simulation_s",
                "validation_simulation_s",
                "training_s",
                "build_s",
                "inference_torch_us",
                "inference_ort_us",
            ):
                assert row[key] > 0, (name, row["label"], key)
            assert row["build_s"] == pytest.approx(
                row["simulation_s"] + row["validation_simulation_s"] + row["training_s"]
            )
            assert row["epochs"] >= row["best_epoch"] >= 1
    assert all(r["inference_us_per_pixel"] > 0 for r in result["axes"]["pool"]["rows"])
    assert all(v > 0 for v in result["simulation_seconds_per_draw"].values()) and result["total_s"] > 0


def test_pooling_does_not_lose_accuracy(result):
    """The shipped model: pool 25 at least as good as pool 1 within 4 standard errors (paired SE ≤ the sum)."""
    rows = {r["pool"]: r["pools"]["own"] for r in result["axes"]["pool"]["rows"]}
    a, b = rows[1], rows[25]
    for key in ("balanced_accuracy", "coverage"):
        assert b[key] >= a[key] - 4 * (a[f"{key}_se"] + b[f"{key}_se"]), key


def test_every_setting_is_evaluated_on_the_same_test_draws(result):
    rows = result["axes"]["training_draws"]["rows"] + result["axes"]["model_size"]["rows"]
    assert {r["pools"]["1"]["samples"] for r in rows} == {TINY.draws_test * TINY.replicates * TINY.trials_per_draw}
    # one-configuration keeps the single-acquisition samples; its identifiable ones are a subset
    spec_rows = {r["label"]: r["pools"]["1"] for r in result["axes"]["feature_spec"]["rows"]}
    assert spec_rows["one-configuration"]["samples"] == spec_rows["single-acquisition"]["samples"]
    assert (
        spec_rows["one-configuration"]["identifiable_samples"]
        <= spec_rows["single-acquisition"]["identifiable_samples"]
    )


def test_one_configuration_columns_and_ground_truth(cache_dir, result):
    spec = load_spec("single-acquisition")
    one = one_configuration_spec()
    assert len(one.configurations) == 1 and one.configurations[0].matches(0.84, 4.9, 3.8)
    assert (one.n_frames, one.frame_interval_s, one.ocds_delay_range_s) == (
        spec.n_frames,
        spec.frame_interval_s,
        spec.ocds_delay_range_s,
    )
    ds = make_dataset(
        spec, seed=TINY.seed, split="test", draws=TINY.draws_test, replicates=TINY.replicates, cache_dir=cache_dir
    )
    assert ds.meta["from_cache"]  # written by the module run
    sub = derive_dataset(ds, spec, one, Prior())
    names = list(spec.feature_names)
    assert np.array_equal(sub.x, ds.x[:, [names.index("liv@original"), names.index("ocds@original")]])
    # "static"/"decorrelated" need the criterion at every configuration: fewer configurations, more indeterminate
    assert np.all(ds.status[sub.status == 0] == 0)
    assert sum(sub.meta["draw_status_counts"].values()) == TINY.draws_test
    assert sub.meta["draw_status_counts"]["identifiable"] <= ds.meta["draw_status_counts"]["identifiable"]
    assert set(sub.meta["draw_status_counts"]) == set(STATUS)


def test_prefix_equals_a_smaller_split_and_fit_reproduces_train(tmp_path):
    cfg = TrainConfig(
        spec="two-wavelength",
        draws_train=9,
        draws_validation=6,
        draws_test=6,
        replicates=2,
        max_epochs=3,
        singles_per_group=16,
        pooled_per_group=4,
        baselines=False,
    )
    full = make_dataset("two-wavelength", seed=0, split="train", draws=12, replicates=2, cache_dir=tmp_path)
    res = train(cfg, cache_dir=tmp_path, log=None)
    pre = prefix_dataset(full, 9)
    for k, v in res.datasets["train"].arrays().items():
        assert np.array_equal(getattr(pre, k), v, equal_nan=True), k
    fitted = _fit(pre, res.datasets["validation"], load_spec("two-wavelength"), cfg)
    x = torch.from_numpy(res.test_inputs)
    with torch.no_grad():
        assert torch.equal(fitted["model"](x), res.model(x))
    assert fitted["temperature"] == res.report["training"]["temperature"]
    assert fitted["epochs"] == res.report["training"]["epochs"]
    with pytest.raises(ValueError, match="prefix of 13 draws"):
        prefix_dataset(full, 13)


def test_evaluator_matches_report_evaluate_and_bootstrap_se():
    rng = np.random.default_rng(3)
    n_draws, per = 12, 20
    draw = np.repeat(np.arange(n_draws), per)
    y = draw % 3
    status = np.repeat(rng.choice([0, 0, 1, 2], n_draws), per)
    logits = rng.normal(size=(draw.size, 4)) + 2.0 * np.eye(4)[np.where(status == 0, y, 3)]
    p = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
    rule = make_rule(0.05, 0.5)
    s = {"y": y, "status": status, "draw": draw}
    common = np.zeros(n_draws, bool)
    common[np.unique(draw[status == 0])] = True
    m, reps = _Evaluator(_bootstrap_weights(n_draws, 60, 5), common, rule)(p, s)
    ref = evaluate(p, y, status, CLASS_NAMES, rule)
    se = bootstrap_se(p, y, status, draw, CLASS_NAMES, rule, n_boot=60, seed=5)
    assert m["balanced_accuracy"] == ref["balanced_accuracy_identifiable"]
    assert m["coverage"] == ref["coverage_identifiable"]
    assert m["strict_accuracy_common"] == pytest.approx(ref["strict_accuracy_identifiable"], abs=1e-12)
    assert m["balanced_accuracy_se"] == pytest.approx(se["balanced_accuracy_identifiable"], rel=1e-9)
    assert m["coverage_se"] == pytest.approx(se["coverage_identifiable"], rel=1e-9)
    assert reps["error"].shape == reps["coverage"].shape == (60,) and m["error"] == pytest.approx(
        1 - m["balanced_accuracy"]
    )


def test_plan_validation():
    with pytest.raises(ValueError, match="perfect squares"):
        TradeoffPlan(pools=(1, 5))
    with pytest.raises(ValueError, match="draws_base"):
        TradeoffPlan(draws_grid=(10, 20), draws_base=30)
    with pytest.raises(ValueError, match="draws_test"):
        TradeoffPlan(draws_test=2)
    with pytest.raises(ValueError, match="trials_per_draw"):
        TradeoffPlan(trials_per_draw=16)
    with pytest.raises(TypeError, match="TradeoffPlan"):
        run_tradeoffs({"draws_grid": (3,)})
    assert dataclasses.replace(TINY, seed=1).seed == 1


def test_table_and_plot(result, tmp_path):
    md = format_table(result)
    for ax in result["axes"].values():
        assert ax["title"] in md
    assert md.count("| training_draws |") == len(result["axes"]["training_draws"]["pareto"])
    assert "nan" not in md and "None" not in md
    path = tmp_path / "tradeoffs.png"
    plot_tradeoffs(result, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

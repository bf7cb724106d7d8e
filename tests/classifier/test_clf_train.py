"""Training recipe, pooled samples, evaluation metrics and the indeterminate rule."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from classifier.cli import train_main
from classifier.dataset import Dataset
from classifier.export import onnx_parity
from classifier.report import coverage_curve, evaluate, expected_calibration_error, format_markdown
from classifier.rule import INDETERMINATE, apply_rule, make_rule
from classifier.train import CLASS_NAMES, TrainConfig, pooled_samples, train

TINY_RECIPE = dict(
    spec="two-wavelength",
    draws_train=9,
    draws_validation=6,
    draws_test=6,
    replicates=2,
    max_epochs=4,
    singles_per_group=16,
    pooled_per_group=4,
)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("clf-cache")


def test_rule_decides_and_abstains():
    rule = make_rule(0.05, 0.5)
    names = list(CLASS_NAMES)
    p = np.array(
        [
            [0.7, 0.1, 0.1, 0.1],  # clear diffusion
            [0.4, 0.35, 0.2, 0.05],  # top < 0.5: low probability
            [0.1, 0.1, 0.1, 0.7],  # indeterminate class
            [0.2, 0.5, 0.2, 0.1],
        ]
    )  # exactly the threshold: decided
    labels, reasons = apply_rule(p, names, rule)
    assert labels.tolist() == [0, 3, 3, 1] and reasons.tolist() == [0, 2, 1, 0]
    labels, _ = apply_rule(p, names, rule, min_probability=0.0)
    assert labels.tolist() == [0, 0, 3, 1]
    with pytest.raises(ValueError, match="kind"):
        apply_rule(p, names, {**rule, "kind": "magic"})
    with pytest.raises(ValueError, match=r"\[N, 4\]"):
        apply_rule(p[:, :3], names, rule)
    with pytest.raises(ValueError, match="min_probability"):
        make_rule(0.05, 1.0)
    assert rule["indeterminate_class"] == INDETERMINATE == names[-1]


def test_ece_and_evaluate_on_constructed_cases():
    # 10 samples at confidence 0.7 of which exactly 7 correct: perfectly calibrated, ECE = 0
    p = np.tile([0.7, 0.1, 0.1, 0.1], (10, 1))
    truth = np.array([0] * 7 + [1] * 3)
    ece, table = expected_calibration_error(p, truth)
    assert ece == pytest.approx(0.0, abs=1e-12) and table == [(pytest.approx(0.7), pytest.approx(0.7), 10)]
    # always 0.9 confident, right half the time: ECE = 0.4
    p2 = np.tile([0.9, 0.05, 0.03, 0.02], (10, 1))
    assert expected_calibration_error(p2, np.array([0, 1] * 5))[0] == pytest.approx(0.4)
    # evaluate: confusion counts, coverage and accuracies by hand
    y = np.array([0, 0, 1, 2, 1, 2])
    status = np.array([0, 0, 0, 0, 1, 2])  # last two: truth indeterminate
    p3 = np.array(
        [
            [0.9, 0.05, 0.03, 0.02],
            [0.3, 0.3, 0.2, 0.2],
            [0.1, 0.8, 0.05, 0.05],
            [0.6, 0.2, 0.1, 0.1],
            [0.05, 0.05, 0.1, 0.8],
            [0.7, 0.1, 0.1, 0.1],
        ]
    )
    m = evaluate(p3, y, status, CLASS_NAMES, make_rule(0.05, 0.5))
    assert np.array(m["confusion"]).sum() == 6
    assert m["confusion"][0] == [1, 0, 0, 1] and m["confusion"][3] == [1, 0, 0, 1]
    assert m["coverage_identifiable"] == pytest.approx(3 / 4)
    assert m["accuracy_identifiable"] == pytest.approx(2 / 3)
    assert m["strict_accuracy_identifiable"] == pytest.approx(2 / 4)
    assert m["accuracy_all"] == pytest.approx(3 / 6)
    assert m["indeterminate_reasons"] == {"decided": 4, "indeterminate class": 1, "low probability": 1}


def test_coverage_curve_trades_coverage_for_accuracy_by_the_threshold():
    """The --min-probability trade-off on a constructed case: decided sets nest, counts by hand."""
    y = np.array([0, 0, 1, 2, 1, 2, 0])
    status = np.array([0, 0, 0, 0, 0, 1, 2])  # last two: truth indeterminate
    p = np.array(
        [
            [0.9, 0.05, 0.03, 0.02],  # right, confident
            [0.45, 0.4, 0.1, 0.05],  # right, unsure
            [0.65, 0.2, 0.1, 0.05],  # wrong (ballistic called diffusion)
            [0.1, 0.1, 0.75, 0.05],  # right
            [0.1, 0.2, 0.1, 0.6],  # indeterminate class: never decided
            [0.55, 0.3, 0.1, 0.05],  # non-identifiable, decided below 0.55
            [0.05, 0.05, 0.05, 0.85],
        ]
    )
    rule = make_rule(0.05, 0.5)
    rows = coverage_curve(p, y, status, CLASS_NAMES, rule, thresholds=(0.4, 0.5, 0.7, 0.95))
    assert [r["min_probability"] for r in rows] == [0.4, 0.5, 0.7, 0.95]
    assert [r["coverage_identifiable"] for r in rows] == pytest.approx([4 / 5, 3 / 5, 2 / 5, 0.0])
    assert [r["accuracy_identifiable"] for r in rows[:3]] == pytest.approx([3 / 4, 2 / 3, 1.0])
    assert np.isnan(rows[3]["accuracy_identifiable"])
    assert [r["non_identifiable_decided"] for r in rows] == pytest.approx([1 / 2, 1 / 2, 0.0, 0.0])
    # at the rule's own threshold the curve is evaluate()'s result
    m = evaluate(p, y, status, CLASS_NAMES, rule)
    assert rows[1]["coverage_identifiable"] == m["coverage_identifiable"]
    assert rows[1]["balanced_accuracy_identifiable"] == m["balanced_accuracy_identifiable"]
    assert np.isnan(coverage_curve(p[:5], y[:5], status[:5], CLASS_NAMES, rule)[0]["non_identifiable_decided"])


def _toy_dataset() -> Dataset:
    rng = np.random.default_rng(0)
    n = 3 * 10
    return Dataset(
        x=rng.normal(size=(n, 2)).astype(np.float32),
        y=np.repeat([0, 1, 2], 10),
        draw=np.repeat([0, 1, 2], 10),
        group=np.repeat([0, 1, 2], 10),
        status=np.zeros(n, np.int64),
        magnitude=np.ones(n),
        density=np.ones(n),
        static_fraction=np.zeros(n),
        snr_db=np.full(n, np.nan),
    )


def test_pooled_samples_are_subset_means_of_one_group():
    ds = _toy_dataset()
    rng = np.random.default_rng(1)
    out = pooled_samples(ds, [np.array([10, 1, 3]), np.array([10]), np.array([2, 2])], rng)
    assert out["x"].shape == (6, 3)
    np.testing.assert_allclose(out["x"][0, :2], ds.x[:10].mean(0), rtol=1e-5)  # the whole group
    np.testing.assert_allclose(out["x"][3, :2], ds.x[10:20].mean(0), rtol=1e-5)
    assert any(np.allclose(out["x"][1, :2], row) for row in ds.x[:10])  # n = 1: one of its trials
    assert out["x"][:, -1].tolist() == [10, 1, 3, 10, 2, 2]
    assert out["y"].tolist() == [0, 0, 0, 1, 2, 2]
    # a size beyond the group is capped at the group
    capped = pooled_samples(ds, [np.array([50]), np.array([]), np.array([])], rng)
    assert capped["x"][0, -1] == 10


def test_pooled_samples_do_not_depend_on_how_the_groups_are_blocked(monkeypatch):
    """All groups at once give the numbers of drawing them one group at a time with the same generator, bit
    for bit, whatever the block size; groups of unequal size (dropped trials) included."""
    import classifier.train as tr

    rng = np.random.default_rng(3)
    counts = np.array([10, 7, 10, 4, 10, 9])
    group = np.repeat(np.arange(counts.size), counts)
    n = int(counts.sum())
    ds = Dataset(
        x=rng.normal(size=(n, 3)).astype(np.float32),
        y=group % 3,
        draw=group,
        group=group,
        status=np.zeros(n, np.int64),
        magnitude=np.ones(n),
        density=np.ones(n),
        static_fraction=np.zeros(n),
        snr_db=np.full(n, np.nan),
    )
    sizes = [
        np.array([3, 10, 2]),
        np.array([], np.int64),
        np.array([5]),
        np.array([9, 1]),
        np.array([2] * 5),
        np.array([8]),
    ]
    one_by_one, g1 = [], np.random.default_rng(7)
    for k in range(counts.size):
        keep = group == k
        sub = Dataset(**{key: v[keep] for key, v in ds.arrays().items()})
        if sizes[k].size:
            one_by_one.append(pooled_samples(sub, [sizes[k]], g1)["x"])
    expected = np.concatenate(one_by_one)
    for block in (tr._POOL_BLOCK, 40, 1):
        monkeypatch.setattr(tr, "_POOL_BLOCK", block)
        g2 = np.random.default_rng(7)
        out = pooled_samples(ds, sizes, g2)
        assert np.array_equal(out["x"], expected)
        assert out["group"].tolist() == [k for k in range(counts.size) for _ in range(sizes[k].size)]
    g2 = np.random.default_rng(7)
    pooled_samples(ds, sizes, g2)
    assert g2.random() == g1.random()  # the generator ends where drawing group by group left it


def test_train_config_validation():
    with pytest.raises(ValueError, match="max_pool_pixels"):
        TrainConfig(max_pool_pixels=100, trials_per_draw=64)
    with pytest.raises(ValueError, match="draws_test"):
        TrainConfig(draws_test=2)
    with pytest.raises(ValueError, match="eval_pools"):
        TrainConfig(eval_pools=(4, 9))


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_tiny_training_is_reproducible_and_exports_with_parity(cache_dir, tmp_path):
    cfg = TrainConfig(**TINY_RECIPE)
    a = train(cfg, cache_dir=cache_dir, log=None)
    b = train(cfg, cache_dir=cache_dir, log=None)
    assert all(b.datasets[k].meta["from_cache"] for k in b.datasets)
    for k, v in a.model.state_dict().items():
        assert torch.equal(v, b.model.state_dict()[k]), k
    assert a.report["test"]["network"]["1"] == b.report["test"]["network"]["1"]
    rep = a.report
    assert rep["classes"] == list(CLASS_NAMES)
    for name in ("network", "logistic_regression", "gradient_boosting"):
        for pool in ("1", "4", "9", "25"):
            m = rep["test"][name][pool]
            for key in ("accuracy_all", "balanced_accuracy_all", "coverage_identifiable", "ece"):
                assert 0.0 <= m[key] <= 1.0
        assert rep["timing"][name]["train_s"] >= 0 and rep["timing"][name]["inference_us_per_sample"] > 0
    assert {row["class"] for row in rep["by_magnitude"]["1"]} <= set(CLASS_NAMES[:3])
    for pool, rows in rep["coverage_curve"].items():  # nested decided sets: coverage falls as the threshold rises
        cov = [r["coverage_identifiable"] for r in rows]
        assert cov == sorted(cov, reverse=True)
        at_rule = next(r for r in rows if r["min_probability"] == rep["rule"]["min_probability"])
        assert at_rule["coverage_identifiable"] == rep["test"]["network"][pool]["coverage_identifiable"]
    assert "`--min-probability` trade-off" in format_markdown(rep)
    # doct-train: files, ONNX parity on the test set, refusal to overwrite
    out = tmp_path / "model"
    argv = [
        "--out",
        str(out),
        "--spec",
        "two-wavelength",
        "--draws-train",
        "9",
        "--draws-validation",
        "6",
        "--draws-test",
        "6",
        "--replicates",
        "2",
        "--max-epochs",
        "4",
        "--calibration-draws",
        "0",
        "--cache",
        str(cache_dir),
        "--no-progress",
    ]
    assert train_main(argv) == 0
    report = json.loads((out / "two-wavelength.json").read_text())
    assert report["onnx_parity_max_abs_diff"] <= 1e-5 and report["onnx_opset"] == 17
    assert (out / "two-wavelength.md").read_text().startswith("# Motion-type classifier report")
    assert (out / "two-wavelength.png").stat().st_size > 0
    assert train_main(argv) == 2  # exists, no --force
    assert train_main([*argv, "--force"]) == 0
    assert train_main(["--out", str(out), "--spec", "nope"]) == 2


def test_parity_on_the_test_split(cache_dir, tmp_path):
    """onnxruntime against torch on every test-set input of a trained model: max |Δp| <= 1e-5."""
    from classifier.export import build_metadata, export_onnx

    res = train(TrainConfig(**TINY_RECIPE), cache_dir=cache_dir, log=None)
    path = tmp_path / "m.onnx"
    export_onnx(res.model, build_metadata(res), path)
    assert onnx_parity(res.model, path, res.test_inputs) <= 1e-5


TINY_ARGV = [
    "--spec",
    "two-wavelength",
    "--draws-train",
    "9",
    "--draws-validation",
    "6",
    "--draws-test",
    "6",
    "--replicates",
    "2",
    "--calibration-draws",
    "0",
    "--no-progress",
]


def test_undecided_network_reports_na_with_the_reason(cache_dir, tmp_path, capsys):
    """A network that decides no identifiable test sample: the metrics over decided samples are
    undefined; the run still succeeds and says n/a and why, in the summary line and the report."""
    out = tmp_path / "model"
    argv = [
        "--out",
        str(out),
        *TINY_ARGV,
        "--max-epochs",
        "1",
        "--min-probability",
        "0.999",
        "--no-baselines",
        "--cache",
        str(cache_dir),
    ]
    assert train_main(argv) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "two-wavelength.json").read_text())
    m1 = report["test"]["network"]["1"]
    assert m1["identifiable_samples"] > 0 and m1["coverage_identifiable"] == 0.0  # the case under test
    assert m1["accuracy_identifiable"] is None and m1["balanced_accuracy_identifiable"] is None
    assert "accuracy n/a (no identifiable test sample was decided" in printed, printed
    own = [r for r in report["coverage_curve"]["1"] if r["min_probability"] == 0.999]  # the model's threshold
    assert len(own) == 1 and own[0]["coverage_identifiable"] == 0.0 and own[0]["accuracy_identifiable"] is None
    md = (out / "two-wavelength.md").read_text()
    assert "| n/a |" in md and "n/a: no identifiable test sample was decided" in md
    assert sorted(p.name for p in out.iterdir()) == [
        "two-wavelength.json",
        "two-wavelength.md",
        "two-wavelength.onnx",
        "two-wavelength.png",
    ]


def test_baselines_cover_classes_absent_from_a_small_training_split(cache_dir, tmp_path, capsys):
    """Three training draws that are all identifiable: the scikit-learn baselines never see the
    indeterminate class; their probabilities still have one column per class (0 for the absent one)
    and the run succeeds (was 'probabilities must be [N, 4]; got (192, 3)' after training)."""
    out = tmp_path / "model"
    argv = [
        "--out",
        str(out),
        "--spec",
        "single-acquisition",
        "--draws-train",
        "3",
        "--draws-validation",
        "3",
        "--draws-test",
        "3",
        "--replicates",
        "1",
        "--max-epochs",
        "1",
        "--calibration-draws",
        "0",
        "--cache",
        str(cache_dir),
        "--no-progress",
    ]
    assert train_main(argv) == 0, capsys.readouterr().err
    assert "'static': 0, 'decorrelated': 0" in capsys.readouterr().out.splitlines()[0]  # the case under test
    report = json.loads((out / "single-acquisition.json").read_text())
    for name in ("logistic_regression", "gradient_boosting"):
        m1 = report["test"][name]["1"]
        assert m1["identifiable_samples"] > 0 and 0.0 <= m1["coverage_identifiable"] <= 1.0


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_failed_run_leaves_no_model_and_keeps_the_old_one(cache_dir, tmp_path, monkeypatch, capsys):
    import classifier.report as report

    out = tmp_path / "model"
    argv = ["--out", str(out), *TINY_ARGV, "--max-epochs", "1", "--no-baselines", "--cache", str(cache_dir)]

    def broken(*args, **kwargs):
        raise RuntimeError("figure failed")

    monkeypatch.setattr(report, "plot_report", broken)
    with pytest.raises(RuntimeError, match="figure failed"):  # an internal error: exit 1 with its traceback
        train_main(argv)
    assert not out.exists() or list(out.iterdir()) == []  # no model without its report, no temporary files
    monkeypatch.undo()
    assert train_main(argv) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report, "plot_report", full)
    assert train_main([*argv, "--force", "--seed", "1"]) == 1
    assert "No space left" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the previous model is intact


def test_quick_sets_the_documented_sizes_and_explicit_sizes_win(tmp_path, monkeypatch):
    import classifier.train as train_module
    from classifier.cli import QUICK

    seen = []

    def stop(cfg, **kwargs):
        seen.append(cfg)
        raise KeyboardInterrupt  # stop before any simulation

    monkeypatch.setattr(train_module, "train", stop)
    out = tmp_path / "q"
    for argv in (["--quick"], ["--quick", "--draws-train", "12"], []):
        assert train_main(["--out", str(out), "--no-progress", *argv]) == 130  # Ctrl-C: one line, exit 130
        assert not out.exists()  # an interrupted run leaves nothing, not even the directory it created
    quick, explicit, default = seen
    assert {k: getattr(quick, k) for k in QUICK} == QUICK
    assert explicit.draws_train == 12 and explicit.draws_test == QUICK["draws_test"]
    assert default == TrainConfig()  # without --quick: the shipped model's recipe
    assert QUICK["draws_train"] * QUICK["replicates"] < TrainConfig().draws_train * TrainConfig().replicates / 5


@pytest.mark.slow
def test_quick_run_gives_a_usable_model(tmp_path, capsys):
    """`doct-train --quick`: the model decides and beats chance."""
    out = tmp_path / "q"
    assert train_main(["--out", str(out), "--quick", "--no-progress", "--cache", str(tmp_path / "cache")]) == 0
    m1 = json.loads((out / "single-acquisition.json").read_text())["test"]["network"]["1"]
    assert m1["coverage_identifiable"] > 0.2 and m1["balanced_accuracy_identifiable"] > 0.5  # chance: 1/3
    assert "n/a" not in capsys.readouterr().out


def test_shifted_prior_test_set_is_evaluated_and_reported(cache_dir, tmp_path):
    """A tiny training with the shifted-prior test set: its split follows SHIFTED_PRIOR (cached apart),
    the report holds every eval pool with finite metrics, and the main evaluation is untouched."""
    import dataclasses
    import math

    from classifier.prior import Prior
    from classifier.report import format_markdown, plot_report
    from classifier.train import SHIFTED_PRIOR, SHIFTED_TARGETS, shifted_prior

    assert TrainConfig.for_spec("signature").shifted_test is None  # None: on for signature specs
    assert SHIFTED_PRIOR.flow_polar_angle_deg == (10.0, 80.0) and SHIFTED_PRIOR.density_per_um3 == (0.05, 0.05)
    assert SHIFTED_PRIOR.static_probability == 0.0 and SHIFTED_PRIOR.noise_probability == 1.0
    assert SHIFTED_PRIOR.snr_db == (15.0, 25.0) and SHIFTED_PRIOR.ballistic_directions == "both"
    narrow = Prior(speed_um_per_s=(0.01, 1.0))
    assert shifted_prior(narrow) == dataclasses.replace(SHIFTED_PRIOR, speed_um_per_s=(0.01, 1.0))
    plain = train(TrainConfig(**TINY_RECIPE, baselines=False), cache_dir=cache_dir, log=None)
    res = train(TrainConfig(**TINY_RECIPE, baselines=False, shifted_test=True), cache_dir=cache_dir, log=None)
    assert "shifted_prior" not in plain.report  # two-wavelength is not a signature spec: off by default
    assert res.report["test"] == plain.report["test"]  # the extra split does not touch the main evaluation
    ds = res.datasets["shifted_prior"]
    assert ds.meta["prior"] == SHIFTED_PRIOR.to_dict() and ds.meta["key"] != res.datasets["test"].meta["key"]
    assert np.all(ds.density == 0.05) and np.all(ds.static_fraction == 0.0)
    assert np.all((ds.snr_db >= 15.0) & (ds.snr_db <= 25.0))
    sp = res.report["shifted_prior"]
    assert sp["prior"] == SHIFTED_PRIOR.to_dict() and sp["samples"] == len(ds)
    assert set(sp["test"]) == {"1", "4", "9", "25"}
    for pool, m in sp["test"].items():
        assert m["samples"] > 0 and m["identifiable_samples"] > 0
        for key in ("accuracy_all", "balanced_accuracy_all", "coverage_identifiable", "ece"):
            assert 0.0 <= m[key] <= 1.0 and math.isfinite(m[key]), (pool, key)
    assert set(sp["by_magnitude"]) == {"1", "25"} and sp["by_magnitude"]["1"]
    assert all(math.isfinite(v) for v in sp["standard_errors"]["1"].values())
    m1 = sp["test"]["1"]
    want = (
        m1["balanced_accuracy_identifiable"] >= SHIFTED_TARGETS["balanced_accuracy_identifiable"]
        and m1["ece"] <= SHIFTED_TARGETS["ece"]
    )
    assert sp["targets"]["met"] == want
    for pool, rows in sp["coverage_curve"].items():  # the shifted set's --min-probability trade-off
        at_rule = next(r for r in rows if r["min_probability"] == res.report["rule"]["min_probability"])
        assert at_rule["coverage_identifiable"] == sp["test"][pool]["coverage_identifiable"]
    md = format_markdown(res.report)
    assert "## Shifted prior: accuracy against coverage" in md
    assert "## Shifted-prior test set (network)" in md and "flow at 10–80° from the depth axis" in md
    assert "density 0.05 µm⁻³" in md and "SNR 15–25 dB" in md and "### Shifted prior: accuracy against" in md
    assert f"ECE ≤ 0.05: {m1['ece']:.3f}" in md
    plot_report(res.report, str(tmp_path / "r.png"))
    assert (tmp_path / "r.png").stat().st_size > 0
    from classifier.dataset import make_dataset

    cfg = res.config
    again = make_dataset(
        cfg.spec,
        SHIFTED_PRIOR,
        seed=cfg.seed,
        split="test",
        draws=cfg.draws_test,
        trials_per_draw=cfg.trials_per_draw,
        replicates=cfg.replicates,
        cache_dir=cache_dir,
    )
    assert again.meta["from_cache"] and np.array_equal(again.x, ds.x)  # cached under its own key


def test_interval_scale_matches_the_nominal_interval_shares():
    """The SD factor makes ±1 and ±1.96 SD contain 68.27 % and 95.45 % of the standardised errors."""
    from classifier.train import interval_scale

    rng = np.random.default_rng(3)
    z = np.abs(rng.standard_normal(200_000))
    for true in (0.5, 1.0, 2.5):  # Gaussian errors whose SD is `true` × the predicted one: the factor is `true`
        assert interval_scale(true * z) == pytest.approx(true, rel=0.01)
    # heavy tails (Student t, 4 dof): the maximum-likelihood factor sqrt(<z^2>) puts 77 % in the 68 %
    # interval; the fitted one misses each level by less and by < 0.04 (the least-squares compromise)
    t = np.abs(rng.standard_t(4, 200_000))
    c, ml = interval_scale(t), float(np.sqrt(np.mean(t**2)))

    def miss(f):
        return np.array([abs(np.mean(t <= f) - 0.6827), abs(np.mean(t <= 1.959964 * f) - 0.9545)])

    assert np.all(miss(c) < 0.04) and miss(ml)[0] > 0.07 and np.sum(miss(c) ** 2) < np.sum(miss(ml) ** 2)
    assert interval_scale(np.array([])) == 1.0 and interval_scale(np.array([np.nan])) == 1.0

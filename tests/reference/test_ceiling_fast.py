"""Fast checks of the ceiling measurement (:mod:`ceiling`): disjoint training and test draws, the cache
and the classifier reproducible from the seed, the metrics exact on known decisions, the coverage
threshold deciding the asked share. A few draws of 8 trials; the numbers of the report come from
``python -m tests.reference.ceiling`` (research/results/independent-ceiling.md)."""

from __future__ import annotations

import time

import ceiling as ce
import evaluate_models as em
import numpy as np
import pytest

from classifier.features import load_spec

TRIALS = 8


def _cache(tmp_path, seed: int, name: str = "signature", source: str = "refsim") -> ce.FeatureCache:
    return ce.FeatureCache(tmp_path / "cache", load_spec(name), source, seed, TRIALS, 0.05)


def test_training_draws_are_disjoint_from_the_test_draws(tmp_path):
    test = [em.draw_independent(0, k) for k in range(300)]
    train = [em.draw_independent(1, k) for k in range(1200)]
    assert not {d.sim_seed for d in test} & {d.sim_seed for d in train}
    assert not {d.magnitude for d in test} & {d.magnitude for d in train}
    # the same prior: the same motion type sequence, magnitudes inside the same ranges
    assert [d.label for d in train[:300]] == [d.label for d in test]
    for d in train:
        lo, hi = em.RANGES[d.motion]
        assert lo <= d.magnitude <= hi
    caches = ce.caches_for(
        tmp_path, ["a", "b", "c"], sizes=[6, 12], test_draws=9, trials=TRIALS, train_seed=1, test_seed=0, epsilon=0.05
    )
    dirs = {c.dir.name: n for c, n in caches}
    assert dirs == {
        f"refsim-signature-seed0-trials{TRIALS}": 9,
        f"refsim-signature-bscan-field-seed0-trials{TRIALS}": 9,
        f"refsim-signature-seed1-trials{TRIALS}": 12,
        f"refsim-signature-bscan-field-seed1-trials{TRIALS}": 12,
        f"torchdoct-signature-seed1-trials{TRIALS}": 12,
    }
    assert ce.main(["--out", str(tmp_path / "x"), "--train-seed", "0", "--test-seed", "0"]) == 2


def test_cache_resumes_to_the_same_features_and_the_fit_is_deterministic(tmp_path):
    a = _cache(tmp_path / "one", 1)
    assert not a.fill(6, deadline=time.perf_counter() - 1.0)  # stops after the first draw
    assert a.missing(6) == list(range(1, 6))
    assert a.fill(6)
    b = _cache(tmp_path / "two", 1)
    assert b.fill(6)
    for k in range(6):
        np.testing.assert_array_equal(a.load(k), b.load(k))
    assert set(a.seconds()) == {str(k) for k in range(6)}
    # the features are the evaluation's own (evaluate_models.draw_features of the same draw)
    np.testing.assert_array_equal(a.load(4), em.draw_features(a.spec, em.draw_independent(1, 4), TRIALS))
    ds = ce.load_set(a, 6)
    assert ds.x.shape == (6 * TRIALS, a.spec.n_features)
    assert np.array_equal(np.unique(ds.draw), np.arange(6))
    assert list(ds.y[::TRIALS]) == [k % 3 for k in range(6)]
    p1 = ce.predict_gb(ce.fit_gb(ds.x, ds.y, seed=1), ds.x)
    p2 = ce.predict_gb(ce.fit_gb(ce.load_set(b, 6).x, ds.y, seed=1), ds.x)
    np.testing.assert_array_equal(p1, p2)
    assert p1.shape == (len(ds.y), 4) and np.all(p1[:, 3] == 0)
    np.testing.assert_allclose(p1[:, :3].sum(1), 1.0, atol=1e-12)
    s = ce.pool_samples(ds, 4, seed=0, per_draw=3)
    assert s["x"].shape == (18, a.spec.n_features)
    # a pooled sample is the mean of 4 pixels of its own draw
    lo = s["x"] <= np.stack([ds.x[ds.draw == d].max(0) for d in s["draw"]]) + 1e-6
    hi = s["x"] >= np.stack([ds.x[ds.draw == d].min(0) for d in s["draw"]]) - 1e-6
    assert np.all(lo & hi)


def _samples(n_per_class: int = 60, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    y = np.repeat(np.arange(3), n_per_class)
    return {
        "y": y,
        "status": np.zeros_like(y),
        "draw": np.arange(y.size) // 4,
        "magnitude": np.where(y == 0, 1e-3, 0.2 + 2.0 * rng.random(y.size)),
        "polar_angle_deg": np.where(y == 2, 90.0 * rng.random(y.size), np.nan),
    }


def test_a_perfect_predictor_scores_one_and_a_known_confusion_scores_exactly():
    s = _samples()
    perfect = np.eye(4)[s["y"]]
    r = ce.score(perfect, s, threshold=ce.coverage_threshold(perfect, s["status"], 1.0), n_boot=20)
    assert r["coverage"] == 1.0 and r["balanced_accuracy"] == 1.0
    assert all(v == 1.0 for v in r["recall"].values())
    assert set(r["flow_polar_bands"]) == {"0-30", "30-60", "60-90"} and all(
        v == 1.0 for v in r["flow_polar_bands"].values()
    )
    assert r["se"]["balanced_accuracy"] == 0.0
    # every flow called ballistic: recalls 1 / 1 / 0, balanced accuracy 2/3, every band 0
    wrong = perfect.copy()
    wrong[s["y"] == 2] = np.eye(4)[1]
    r = ce.score(wrong, s, threshold=0.5, n_boot=0)
    assert r["balanced_accuracy"] == pytest.approx(2.0 / 3.0, abs=1e-12)
    assert r["recall"]["flow"] == 0.0 and all(v == 0.0 for v in r["flow_polar_bands"].values())


def test_the_coverage_threshold_decides_the_asked_share():
    rng = np.random.default_rng(3)
    s = _samples(200, seed=3)
    p = rng.dirichlet(np.ones(3), size=s["y"].size)
    p = np.concatenate([p, np.zeros((len(p), 1))], axis=1)
    n = s["y"].size
    for q in (0.1, 0.5, 0.7, 0.8, 0.9):
        thr = ce.coverage_threshold(p, s["status"], q)
        assert ce.score(p, s, threshold=thr, n_boot=0)["coverage"] == round(q * n) / n  # continuous: no ties
    assert ce.coverage_threshold(p, s["status"], 1.0) == 0.0
    assert ce.score(p, s, threshold=0.0, n_boot=0)["coverage"] == 1.0
    # non-identifiable samples do not count, and a row whose top class is "indeterminate" is never decided
    st = s["status"].copy()
    st[: n // 2] = 1
    thr = ce.coverage_threshold(p, st, 0.5)
    assert np.sum((p.max(1) >= thr) & (st == 0)) == round(0.5 * (n - n // 2))
    p2 = p.copy()
    p2[:100] = [0.1, 0.1, 0.1, 0.7]
    assert ce.score(p2, s, threshold=ce.coverage_threshold(p2, s["status"], 1.0), n_boot=0)["coverage"] == (n - 100) / n
    with pytest.raises(ValueError):
        ce.coverage_threshold(p, s["status"], 0.0)


def test_the_intensity_columns_of_the_field_spec_are_the_bscan_spec():
    spec = load_spec("signature-bscan-field")
    cols = ce.part_columns(spec, "intensity")
    assert [spec.feature_names[i] for i in cols] == list(load_spec("signature-bscan").feature_names)
    assert len(ce.part_columns(spec, "all")) == spec.n_features > len(cols)


def test_the_shared_speed_prior_moves_only_the_speeds_to_the_same_quantile(tmp_path):
    import math

    lo, hi = (math.log(v) for v in ce.SHARED_SPEED)
    for k in range(60):
        m, s = em.draw_independent(1, k), ce.draw_for("shared", 1, k)
        assert ce.draw_for("matched", 1, k) == m
        assert (s.label, s.sim_seed, s.polar_angle_deg, s.snr_db, s.ballistic_directions) == (
            m.label,
            m.sim_seed,
            m.polar_angle_deg,
            m.snr_db,
            m.ballistic_directions,
        )
        if m.label == 0:
            assert s == m
            continue
        a, b = (math.log(v) for v in em.RANGES[m.motion])
        assert ce.SHARED_SPEED[0] <= s.magnitude <= ce.SHARED_SPEED[1]
        assert (math.log(s.magnitude) - lo) / (hi - lo) == pytest.approx(
            (math.log(m.magnitude) - a) / (b - a), abs=1e-12
        )
    assert (
        _cache(tmp_path, 1).dir
        != ce.FeatureCache(tmp_path / "cache", load_spec("signature"), "refsim", 1, TRIALS, 0.05, "shared").dir
    )
    with pytest.raises(ValueError):
        ce.draw_for("wide", 1, 0)


def test_the_contrasts_are_the_log_decorrelation_slopes_and_configuration_differences():
    spec = load_spec("signature")
    cols = ce.part_columns(spec, "all")
    lags = sorted({int(m.split("_")[-1]) for m, _ in spec.features if m.startswith("rho_lin_")})
    confs = [c.name for c in spec.configurations]
    power = {confs[0]: 1.0, confs[1]: 2.0, confs[2]: 1.5}
    x = np.full((2, spec.n_features), 0.5)
    for i, (m, c) in enumerate(spec.features):
        if m.startswith("rho_lin_"):
            x[:, i] = 1.0 - np.array([1e-3, 2e-3]) * int(m.split("_")[-1]) ** power[c.name]
    z = ce.derived_features(spec, x, cols)
    n_slopes, n_diff = len(confs) * (len(lags) - 1), (len(confs) - 1) * len(lags)
    assert z.shape == (2, n_slopes + n_diff)

    def L(a, c, m):
        return np.log(a * m ** power[c] + ce.DERIVED_OFFSET)

    a = np.array([1e-3, 2e-3])
    expected = []
    for c in confs:  # the order of derived_features: per configuration, its slopes, then its differences
        expected += [(L(a, c, m2) - L(a, c, m1)) / np.log(m2 / m1) for m1, m2 in zip(lags[:-1], lags[1:])]
        if c != confs[0]:
            expected += [L(a, c, m) - L(a, confs[0], m) for m in lags]
    np.testing.assert_allclose(z, np.stack(expected, axis=1), rtol=1e-12)
    # far above the offset the slope is the power law's exponent (1 diffusion-like, 2 ballistic-like)
    assert z[1, len(lags) - 2] == pytest.approx(1.0, abs=0.01)
    # the intensity-only columns of the field spec give no g1 contrast
    fspec = load_spec("signature-bscan-field")
    assert (
        ce.derived_features(fspec, np.full((1, fspec.n_features), 0.5), ce.part_columns(fspec, "intensity")).shape[1]
        == n_slopes + n_diff
    )


@pytest.mark.slow
def test_parts_d_and_e_train_on_the_shipped_and_the_scaled_prior_from_make_dataset(tmp_path):
    from classifier.own_system import identifiable_range, prior_for_spec
    from classifier.prior import Prior

    spec = load_spec("signature")
    d, e = ce.dataset_prior("training", spec, 0.05), ce.dataset_prior("scaled", spec, 0.05)
    assert d == Prior(flow_polar_law="uniform-angle")  # the shipped signature recipe's prior
    assert e == prior_for_spec(spec, d)[0] and e.flow_polar_law == "uniform-angle"
    # the scaled prior spans each type's identifiable range, and the diffusion range ends where it does
    lo, hi = identifiable_range(spec, 0, e)
    assert e.diffusion_um2_per_s[0] < lo < hi < e.diffusion_um2_per_s[1] < d.diffusion_um2_per_s[1]
    assert ce.dataset_prior("training", spec, 0.1).identifiability_epsilon == 0.1
    with pytest.raises(ValueError):
        ce.dataset_prior("matched", spec, 0.05)
    # no simulation for them in the feature caches: make_dataset's own split under <out>/cache/make_dataset
    caches = ce.caches_for(
        tmp_path, ["d", "e"], sizes=[6], test_draws=9, trials=TRIALS, train_seed=1, test_seed=0, epsilon=0.05
    )
    assert {c.dir.name: n for c, n in caches} == {f"refsim-signature-seed0-trials{TRIALS}": 9}
    assert ce.dataset_set(tmp_path, spec, "scaled", 1, 6, TRIALS, 0.05, simulate=False) is None
    ds = ce.dataset_set(tmp_path, spec, "scaled", 1, 6, TRIALS, 0.05)
    assert not ds.meta["from_cache"] and ds.x.shape[1] == spec.n_features
    assert sorted(np.unique(ds.draw)) == list(range(6)) and np.all(ds.group == ds.draw)  # one replicate
    again = ce.dataset_set(tmp_path, spec, "scaled", 1, 6, TRIALS, 0.05, simulate=False)
    assert again.meta["from_cache"]
    np.testing.assert_array_equal(again.x, ds.x)
    for k in range(6):  # every magnitude inside the scaled prior's range of its type
        m = ds.magnitude[ds.draw == k]
        lo, hi = e.magnitude_range(k % 3)
        assert m.size == 0 or lo <= m[0] <= hi

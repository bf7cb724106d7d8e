"""research.grid_ceiling: the scores and the threshold of the grid ceiling, and its continuous training prior."""

import numpy as np
import pytest

from classifier.bench import grid as G
from research import grid_ceiling as C


def test_scores_count_a_motion_decided_as_another_as_its_wrong_share():
    y = np.array([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2])
    dec = np.array([0, 0, -1, 1, 1, 1, -1, -1, 2, 2, 2, 2])
    s = C.scores(y, dec)
    assert s["coverage"] == pytest.approx(9 / 12)
    assert s["per_motion"]["diffusion"]["wrong_share"] == pytest.approx(1 / 4)
    assert s["per_motion"]["ballistic"]["coverage"] == pytest.approx(2 / 4)
    assert s["worst_wrong_share"] == pytest.approx(1 / 4)
    # recalls on decided pixels: 2/3, 2/2, 4/4
    assert s["balanced_accuracy"] == pytest.approx((2 / 3 + 1 + 1) / 3)


def test_a_motion_never_decided_leaves_the_balanced_accuracy_undefined():
    y = np.array([0, 1, 2])
    assert C.scores(y, np.array([0, -1, 2]))["balanced_accuracy"] is None


def test_best_threshold_decides_everything_where_the_top_class_is_always_right():
    rng = np.random.default_rng(0)
    y = rng.integers(0, 3, 300)
    proba = np.full((300, 3), 0.1)
    proba[np.arange(300), y] = 0.8 + 0.1 * rng.random(300)
    t, dec = C.best_threshold(y, proba)
    assert t is not None and np.array_equal(dec, y)


def test_best_threshold_abstains_on_the_uncertain_pixels_only():
    # confident pixels are right, unsure ones (top probability 0.4) are wrong: the threshold keeps the first
    y = np.repeat([0, 1, 2], 100)
    proba = np.full((300, 3), 0.05)
    proba[np.arange(300), y] = 0.9
    unsure = np.arange(300) % 10 == 0
    proba[unsure] = 0.3
    proba[unsure, (y[unsure] + 1) % 3] = 0.4
    t, dec = C.best_threshold(y, proba)
    assert 0.4 < t <= 0.9
    assert np.all(dec[unsure] == -1) and np.array_equal(dec[~unsure], y[~unsure])


def test_best_threshold_gives_none_where_no_threshold_meets_the_goal():
    y = np.repeat([0, 1, 2], 50)
    proba = np.full((150, 3), 0.1)
    proba[np.arange(150), (y + 1) % 3] = 0.8  # always confidently wrong
    t, dec = C.best_threshold(y, proba)
    assert t is None and np.all(dec == -1)


def test_prior_cells_span_the_range_whose_20_50_80_percent_points_are_the_grid_levels():
    levels = {m: {"slow": 0.01, "mid": 0.1, "fast": 1.0} for m in C.MOTIONS}
    cells = C.prior_cells(400, 1, levels)
    mags = np.array([[lv[m]["draw"] for m in C.MOTIONS] for _, lv in cells])
    # log10 range: -2 - 0.2/0.6*2 .. 0 + 0.2/0.6*2, i.e. [-2.667, 0.667]
    lo, hi = -2 - 2 / 3, 2 / 3
    assert np.all(np.log10(mags) >= lo - 1e-3) and np.all(np.log10(mags) <= hi + 1e-3)
    # log-uniform: each third of the log range holds a third of the draws (400 draws: SE of a share 0.024, z = 4)
    share = np.mean(np.log10(mags[:, 2]) < lo + (hi - lo) / 3)
    assert abs(share - 1 / 3) < 4 * np.sqrt(1 / 3 * 2 / 3 / 400)
    assert {c.snr_db for c, _ in cells} == {None, G.SNR_DB}
    assert all(c.geometry == C.GEOMETRY and c.context == C.CONTEXT for c, _ in cells)
    assert all(0.0 <= c.polar_deg <= 90.0 and 0.0 <= c.azimuth_deg <= 90.0 for c, _ in cells)
    assert C.prior_cells(5, 1, levels) == cells[:5] and C.prior_cells(5, 2, levels) != cells[:5]


def test_grid_ceiling_refuses_one_seed_for_training_and_test(tmp_path, capsys):
    with pytest.raises(SystemExit):
        C.main(["--out", str(tmp_path), "--train-seed", "0", "--test-seed", "0"])
    assert "must differ" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())

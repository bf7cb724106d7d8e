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
    cells = C.prior_cells(400, 1, levels, "volume", "background")
    mags = np.array([[lv[m]["draw"] for m in C.MOTIONS] for _, lv in cells])
    # log10 range: -2 - 0.2/0.6*2 .. 0 + 0.2/0.6*2, i.e. [-2.667, 0.667]
    lo, hi = -2 - 2 / 3, 2 / 3
    assert np.all(np.log10(mags) >= lo - 1e-3) and np.all(np.log10(mags) <= hi + 1e-3)
    # log-uniform: each third of the log range holds a third of the draws (400 draws: SE of a share 0.024, z = 4)
    share = np.mean(np.log10(mags[:, 2]) < lo + (hi - lo) / 3)
    assert abs(share - 1 / 3) < 4 * np.sqrt(1 / 3 * 2 / 3 / 400)
    assert {c.snr_db for c, _ in cells} == {None, G.SNR_DB}
    assert all(c.geometry == "volume" and c.context == "background" for c, _ in cells)
    assert all(0.0 <= c.polar_deg <= 90.0 and 0.0 <= c.azimuth_deg <= 90.0 for c, _ in cells)
    assert C.prior_cells(5, 1, levels, "volume", "background") == cells[:5]
    assert C.prior_cells(5, 2, levels, "volume", "background") != cells[:5]


def test_grid_ceiling_refuses_one_seed_for_training_and_test(tmp_path, capsys):
    with pytest.raises(SystemExit):
        C.main(["--out", str(tmp_path), "--train-seed", "0", "--test-seed", "0"])
    assert "must differ" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_grid_ceiling_refuses_unknown_or_repeated_parts(tmp_path, capsys):
    for parts in ("bscan-none,bscan-none", "volume-edge", ""):
        with pytest.raises(SystemExit):
            C.main(["--out", str(tmp_path), "--parts", parts])
        assert "--parts" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_every_part_has_a_goal_per_window():
    assert {(p, w) for p in C.PARTS for w in C.POOLS} == set(C.GOALS)


def test_worst_cell_counts_the_cells_where_a_motion_is_decided_wrong_over_a_tenth():
    y = np.tile([0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2], 3)
    dec = y.copy()
    cell_of = np.repeat([0, 1, 2], 15)
    dec[5] = 2  # cell 0: one ballistic pixel of five decided as flow
    dec[15 + 10] = -1  # cell 1: one flow pixel left undecided (not wrong)
    w = C.worst_cell(y, dec, cell_of)
    assert w == {"worst": pytest.approx(1 / 5), "cells_over_10pct_wrong": 1}


def test_pixel_features_average_the_window_and_read_the_doppler_phasor_over_rule_10s_box():
    shape = (8, 9)
    xc = np.arange(72, dtype=np.float64).reshape(shape)
    xc[0, 0] = np.nan  # a pixel without a value counts for no box
    phase = np.full(shape, 0.5)
    phase[:, :3] = np.nan  # no reference in the first three A-lines
    probs = np.full((4, *shape), 0.25, np.float32)
    channels = {"xc_centre_2@original": xc, "xc_shift_x_2@original": -xc, "doppler_phase_1@original": phase}
    names, f = C.pixel_features(channels, probs, ["diffusion", "ballistic", "flow", "indeterminate"], 3)
    col = dict(zip(names, f))
    assert col["xc_centre_2@original"][4, 4] == pytest.approx(xc[3:6, 3:6].mean())
    assert col["xc_centre_2@original"][0, 1] == pytest.approx(np.nanmean(xc[0:2, 0:3]))
    assert col["abs_xc_shift_x_2@original"][4, 4] == pytest.approx(xc[3:6, 3:6].mean())
    # the Doppler box is rule 10's, at least 5 pixels per axis: at (4, 4) it spans A-lines 2..6, one without a phase
    assert col["doppler_im"][4, 4] == pytest.approx(np.sin(0.5), rel=1e-6)
    assert col["doppler_re"][4, 4] == pytest.approx(np.cos(0.5), rel=1e-6)
    assert col["doppler_share"][4, 4] == pytest.approx(4 / 5)
    assert np.isnan(col["doppler_im"][4, 0]) and col["doppler_share"][4, 0] == 0.0
    assert col["p_flow"][4, 4] == pytest.approx(0.25)


def test_best_threshold_under_the_cell_bound_abstains_where_one_cell_is_confidently_wrong():
    # 20 cells of 30 pixels; in cell 0 every flow pixel is decided ballistic with probability 0.8: 10/200 flow
    # pixels wrong pooled (0.05, within the goal), all ten of that cell's (over its per-cell bound)
    y = np.tile(np.repeat([0, 1, 2], 10), 20)
    cell_of = np.repeat(np.arange(20), 30)
    proba = np.full((600, 3), 0.02)
    proba[np.arange(600), y] = 0.96
    bad = (cell_of == 0) & (y == 2)
    proba[bad] = [0.1, 0.8, 0.1]
    t_pooled, dec_pooled = C.best_threshold(y, proba, C.INSIDE)
    assert t_pooled is not None and np.all(dec_pooled >= 0)
    t_cell, dec_cell = C.best_threshold(y, proba, C.INSIDE, cell_of)
    assert 0.8 < t_cell <= 0.96
    assert np.all(dec_cell[bad] == -1) and np.array_equal(dec_cell[~bad], y[~bad])
    assert C.worst_cell(y, dec_cell, cell_of)["cells_over_10pct_wrong"] == 0


def test_box_sum_equals_the_brute_force_sum_over_the_box_cut_at_the_edges():
    v = np.random.default_rng(3).random((6, 7, 5))
    got = C._box_sum(v, 5)
    want = np.empty_like(v)
    for idx in np.ndindex(v.shape):
        box = tuple(slice(max(i - 2, 0), i + 3) for i in idx)
        want[idx] = v[box].sum()
    assert np.allclose(got, want, rtol=1e-12, atol=1e-12)

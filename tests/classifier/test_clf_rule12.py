"""Rule 12 of classifier.ambiguity: a diffusion decision whose finest footprint decays faster, in shape, at a
coarser configuration is indeterminate, pooled over five pixels or more. Its statistic is free of each
configuration's noise factor, negative inside one region and positive where a coarse footprint mixes a faster
region in; its mean over the footprint is the brute-force mean; it flags only diffusion decisions over its
threshold; doct-classify applies it last and counts it; its threshold is the recorded null's."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from classifier.ambiguity import (
    MIXED_SHAPE_FLAGS,
    MIXED_SHAPE_MIN,
    MIXED_SHAPE_POOL_MIN,
    SHAPE_FLOOR,
    footprint_mean,
    mixed_shape,
    shape_excess,
)

REPO = Path(__file__).resolve().parents[2]
MOTIONS = ("diffusion", "ballistic", "flow")
NAMES = ["diffusion", "ballistic", "flow", "indeterminate", "ballistic-or-flow", "diffusion-or-flow"]
LAGS = (1, 2, 4, 8)
COLUMNS = [{"metric": f"rho_lin_{m}", "configuration": c} for c in ("fine", "coarse") for m in LAGS] + [
    {"metric": "pool_pixels"}
]
TAU = np.array(LAGS, float)[:, None]
RATES = np.array([0.05, 0.2, 0.5])[None, :]


def _rows(fine, coarse):
    return np.column_stack([*fine, *coarse, np.ones(len(fine[0]))])


def test_the_shape_excess_is_the_mean_over_later_lags_of_the_difference_of_normalised_decays():
    rng = np.random.default_rng(4)
    fine, coarse = rng.uniform(0.3, 1.0, (4, 20)), rng.uniform(0.3, 1.0, (4, 20))
    got = shape_excess(COLUMNS, _rows(fine, coarse), "fine")
    expected = np.mean([fine[k] / fine[0] - coarse[k] / coarse[0] for k in range(1, 4)], axis=0)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    # the largest over the coarser configurations
    cols = COLUMNS[:-1] + [{"metric": f"rho_lin_{m}", "configuration": "wide"} for m in LAGS] + COLUMNS[-1:]
    wide = fine * 0.5
    x = np.column_stack([*fine, *coarse, *wide, np.ones(20)])
    other = np.mean([fine[k] / fine[0] - wide[k] / wide[0] for k in range(1, 4)], axis=0)
    np.testing.assert_allclose(shape_excess(cols, x, "fine"), np.maximum(expected, other), atol=1e-12)
    # one configuration, or one common lag: nothing to compare
    assert shape_excess(COLUMNS[4:], _rows(fine, coarse)[:, 4:], "coarse") is None
    one_lag = [COLUMNS[0], COLUMNS[4], COLUMNS[-1]]
    assert shape_excess(one_lag, _rows(fine, coarse)[:, [0, 4, 8]], "fine") is None


def test_the_shape_excess_is_free_of_each_configurations_noise_factor_and_signs_a_mixed_footprint():
    """Noise independent from frame to frame multiplies every correlation at a lag of a frame or more by one
    factor per configuration (physics.md §8): the statistic does not change. One region (the coarser decays
    slower) gives a negative excess; a coarse decay that mixes in a faster region a positive one."""
    fine, coarse = np.exp(-RATES * TAU), np.exp(-0.5 * RATES * TAU)
    clean = shape_excess(COLUMNS, _rows(fine, coarse), "fine")
    np.testing.assert_allclose(shape_excess(COLUMNS, _rows(0.4 * fine, 0.9 * coarse), "fine"), clean, atol=1e-12)
    assert np.all(clean < 0)
    mixed = _rows(fine, 0.5 * np.exp(-RATES * TAU) + 0.5 * np.exp(-4.0 * RATES * TAU))
    assert np.all(shape_excess(COLUMNS, mixed, "fine") > 0)
    # below the floor at the shortest lag in either configuration: undefined
    assert np.all(np.isnan(shape_excess(COLUMNS, _rows(fine * (SHAPE_FLOOR * 0.9), coarse), "fine")))
    assert np.all(np.isnan(shape_excess(COLUMNS, _rows(fine, coarse * (SHAPE_FLOOR * 0.9)), "fine")))


@pytest.mark.parametrize("shape, window", [((9, 11), (3, 5)), ((4, 7, 6), (3, 3, 5))])
def test_the_footprint_mean_is_the_mean_of_the_finite_values_of_the_cut_box(shape, window):
    rng = np.random.default_rng(5)
    full = rng.normal(size=shape)
    full[rng.random(shape) < 0.2] = np.nan
    idx = np.flatnonzero(rng.random(int(np.prod(shape))) > 0.3)  # the classified pixels
    got = footprint_mean(full.reshape(-1)[idx], idx, shape, window)
    grid = np.full(full.size, np.nan)
    grid[idx] = full.reshape(-1)[idx]
    grid = grid.reshape(shape)
    for k, flat in enumerate(idx):
        p = np.unravel_index(flat, shape)
        box = grid[tuple(slice(max(0, i - w // 2), i + w // 2 + 1) for i, w in zip(p, window))]
        inside = box[np.isfinite(box)]
        if inside.size:
            assert got[k] == pytest.approx(inside.mean(), abs=1e-12)
        else:
            assert np.isnan(got[k])
    with pytest.raises(ValueError, match="rule 12"):
        footprint_mean(full.reshape(-1)[idx], idx, shape, (3,) * (len(shape) + 1))


def test_rule_12_flags_only_diffusion_decisions_whose_footprint_mean_exceeds_the_threshold():
    assert MIXED_SHAPE_FLAGS == ("diffusion",) and MIXED_SHAPE_POOL_MIN == 5
    shape = (1, 7)
    idx = np.arange(7)
    labels = np.array([0, 1, 2, 3, 4, 5, 0])  # every outcome, and a second diffusion decision
    over = np.full(7, MIXED_SHAPE_MIN + 0.01)
    flagged, mean = mixed_shape(labels, NAMES, idx, shape, (1, 1), over, MIXED_SHAPE_POOL_MIN)
    assert flagged.tolist() == [True, False, False, False, False, False, True]
    np.testing.assert_allclose(mean, over)
    at, _ = mixed_shape(labels, NAMES, idx, shape, (1, 1), np.full(7, MIXED_SHAPE_MIN), 5)
    assert not at.any()  # at the threshold: not over it
    undefined, _ = mixed_shape(labels, NAMES, idx, shape, (1, 3), np.full(7, np.nan), 5)
    assert not undefined.any()
    # below the pooling window it was recorded at, and without the statistic: nothing, and no mean
    for pool, excess in ((MIXED_SHAPE_POOL_MIN - 1, over), (MIXED_SHAPE_POOL_MIN, None)):
        none, m = mixed_shape(labels, NAMES, idx, shape, (1, 1), excess, pool)
        assert not none.any() and m is None
    # one pixel over the threshold among pixels at zero: under it once averaged over a wider footprint
    lone = np.zeros(7)
    lone[3] = 2.5 * MIXED_SHAPE_MIN
    diffusion = np.zeros(7, int)
    assert np.flatnonzero(mixed_shape(diffusion, NAMES, idx, shape, (1, 1), lone, 5)[0]).tolist() == [3]
    assert not mixed_shape(diffusion, NAMES, idx, shape, (1, 3), lone, 5)[0].any()


def test_doct_classify_applies_rule_12_last_at_pooled_windows_and_counts_it(tmp_path, monkeypatch):
    from classifier import ambiguity
    from classifier.bench.classify import _synthetic_maps
    from classifier.infer import classify_maps, load_model

    mdl = load_model("signature")
    path = _synthetic_maps(tmp_path / "maps.npz", mdl.spec, 24, 0)
    base = classify_maps(path, mdl, pool=5, background_db=None)
    amb = base.info["ambiguity"]
    assert amb["rules"][-1] == "mixed_shape" and amb["mixed_shape_min"] == MIXED_SHAPE_MIN
    assert amb["mixed_shape_pool_min"] == MIXED_SHAPE_POOL_MIN and amb["shape_floor"] == SHAPE_FLOOR
    unpooled = classify_maps(path, mdl, pool=1, background_db=None)
    assert "mixed_shape" not in unpooled.info["ambiguity"]["rules"]
    assert unpooled.info["ambiguity"]["changed_pixels"]["mixed_shape"] == 0
    single = [mdl.classes.index(m) for m in ("diffusion", "ballistic", "flow")]
    n_single = int(np.isin(base.labels, single).sum())
    assert n_single > 0
    # every decision it flags becomes indeterminate and is counted, after rules 6 and 8 (their counts stay)
    monkeypatch.setattr(
        ambiguity,
        "mixed_shape",
        lambda labels, names, *a, **k: (np.isin(labels, [list(names).index(m) for m in MOTIONS]), None),
    )
    flagged = classify_maps(path, mdl, pool=5, background_db=None)
    assert not np.isin(flagged.labels, single).any()
    assert flagged.info["ambiguity"]["changed_pixels"]["mixed_shape"] == n_single
    for rule in ("unshared", "contradicted", "mixed_footprint"):
        assert flagged.info["ambiguity"]["changed_pixels"][rule] == amb["changed_pixels"][rule]


def test_rule_12s_threshold_is_the_recorded_nulls_choice():
    """The threshold is the smallest of the null run's thresholds at which at most the stated rate of the grid's
    diffusion interiors exceed it in every geometry (research/results/spill-null.json, research.spill --null);
    the record holds every geometry, static context and motion, and its counts are its cells'."""
    from classifier.bench.grid import CONTEXTS, GEOMETRIES, MOTIONS, full_cells
    from research.spill import NULL_RATE, NULL_SEED, NULL_THRESHOLDS, summarize_null

    record = json.loads((REPO / "research" / "results" / "spill-null.json").read_text())
    assert (
        record["command"].startswith("python -m research.spill --null --out DIR") and "--cells" not in record["command"]
    )
    assert record["seed"] == NULL_SEED and len(record["cells"]) == len(full_cells(NULL_SEED))
    s = record["summary"]
    assert s["chosen"] == MIXED_SHAPE_MIN and s["rate"] == NULL_RATE and s["thresholds"] == list(NULL_THRESHOLDS)
    assert s["flags"] == list(MIXED_SHAPE_FLAGS)
    assert {(g["geometry"], g["context"]) for g in s["groups"]} == set(
        itertools.product(GEOMETRIES, ("all", *CONTEXTS))
    )
    assert summarize_null(record["cells"]) == s
    k = s["thresholds"].index(s["chosen"])
    for g in s["groups"]:
        assert set(g["per_motion"]) == set(MOTIONS)
        if g["context"] == "all":
            assert g["per_motion"]["diffusion"]["share_over"][k] <= NULL_RATE
    if k:  # the next threshold down exceeds the rate somewhere
        assert any(
            g["per_motion"][m]["share_over"][k - 1] > NULL_RATE
            for g in s["groups"]
            if g["context"] == "all"
            for m in MIXED_SHAPE_FLAGS
        )


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_the_null_run_reproduces_the_recorded_first_cell(tmp_path):
    """``python -m research.spill --null --cells 1`` gives the recorded run's first cell exactly: the record is what
    its command writes."""
    from research.spill import main

    assert main(["--null", "--out", str(tmp_path), "--cells", "1"]) == 0
    got = json.loads((tmp_path / "spill-null.json").read_text())
    record = json.loads((REPO / "research" / "results" / "spill-null.json").read_text())
    assert got["command"] == "python -m research.spill --null --out DIR --cells 1"
    assert got["cells"] == record["cells"][:1]
    assert (tmp_path / "spill-null.md").read_text().startswith("| geometry | static context |")

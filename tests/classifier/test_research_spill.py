"""``research.spill``: the candidate rules against the random phantoms' slow-region spill, their box mean,
what each flags, how flags are scored, and the recorded run (research/results/spill-rules.json)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from classifier.ambiguity import MIXED_DECAY_MIN, SHAPE_FLOOR, mixed_footprint
from classifier.bench.grid import CODES
from research.spill import (
    BOX_THRESHOLDS,
    SHAPE_BOX_THRESHOLDS,
    box_mean,
    candidates,
    decay_excess,
    excludes,
    score,
    summarize,
)

REPO = Path(__file__).resolve().parents[2]
NAMES = ["diffusion", "ballistic", "flow", "indeterminate", "ballistic-or-flow", "diffusion-or-flow"]


def test_an_outcome_excludes_a_decision_it_does_not_name():
    assert excludes("ballistic", "diffusion") and excludes("ballistic-or-flow", "diffusion")
    assert not excludes("diffusion", "diffusion") and not excludes("diffusion-or-flow", "diffusion")
    assert not excludes("indeterminate", "flow")


@pytest.mark.parametrize("shape, window", [((9, 11), (3, 5)), ((4, 7, 6), (3, 3, 5))])
def test_box_mean_is_the_mean_over_the_valid_pixels_of_the_cut_box(shape, window):
    rng = np.random.default_rng(1)
    values = rng.normal(size=shape)
    valid = rng.random(shape) > 0.4
    got = box_mean(values, valid, window)
    for p in itertools.product(*(range(n) for n in shape)):
        box = tuple(slice(max(0, i - w // 2), i + w // 2 + 1) for i, w in zip(p, window))
        inside = values[box][valid[box]]
        if inside.size:
            assert got[p] == pytest.approx(inside.mean(), abs=1e-12)
        else:
            assert np.isnan(got[p])


def _both(values):
    return {"mixed": values, "shape": values}


def test_candidates_flag_only_single_random_motion_decisions_over_their_threshold():
    labels = np.array([[0, 1, 2, 3, 4, 0]])
    excess = np.full(labels.shape, MIXED_DECAY_MIN + 0.05)  # every pixel over rule 9's threshold
    flags = candidates(labels, NAMES, _both(excess), (1, 1), None)
    # diffusion and ballistic decisions only: flow is rule 9's own, sets and indeterminate are no decision
    for name in ("mixed-pixel", "shape-pixel"):
        assert flags[name].tolist() == [[True, True, False, False, False, True]]
    assert "pool-1-excludes" not in flags
    below = candidates(labels, NAMES, _both(np.full(labels.shape, MIXED_DECAY_MIN)), (1, 1), None)
    assert not below["mixed-pixel"].any() and not below["shape-pixel"].any()
    undefined = candidates(labels, NAMES, _both(np.full(labels.shape, np.nan)), (3, 3), None)
    assert not any(f.any() for f in undefined.values())
    # the box mean: one pixel over every threshold among eight at zero, averaged over a full 1 × 5 box, is
    # under every threshold
    thresholds = [f"mixed-box-{t:g}" for t in BOX_THRESHOLDS] + [f"shape-box-{t:g}" for t in SHAPE_BOX_THRESHOLDS]
    lo, hi = min(BOX_THRESHOLDS + SHAPE_BOX_THRESHOLDS), max(BOX_THRESHOLDS + SHAPE_BOX_THRESHOLDS)
    assert 5 * lo > hi
    one = np.zeros((1, 9))
    one[0, 4] = 4.5 * lo
    boxed = candidates(np.zeros((1, 9), int), NAMES, _both(one), (1, 1), None)
    wide = candidates(np.zeros((1, 9), int), NAMES, _both(one), (1, 5), None)
    for name in thresholds:
        assert np.flatnonzero(boxed[name]).tolist() == [4], name
        assert not wide[name].any(), name


LAGS = (1, 2, 4, 8)
COLUMNS = [{"metric": f"rho_lin_{m}", "configuration": c} for c in ("fine", "coarse") for m in LAGS] + [
    {"metric": "pool"}
]


def _rows(fine, coarse):
    return np.column_stack([*fine, *coarse, np.ones(len(fine[0]))])


def test_the_raw_excess_is_rule_9s():
    rng = np.random.default_rng(3)
    x = _rows(rng.uniform(-0.2, 1.0, (4, 50)), rng.uniform(-0.2, 1.0, (4, 50)))
    _, expected = mixed_footprint(np.zeros(50, int), NAMES, COLUMNS, x, "fine")
    np.testing.assert_allclose(decay_excess(x, COLUMNS, "fine"), expected, rtol=0, atol=1e-12)
    assert decay_excess(x, COLUMNS[4:], "coarse") is None  # one configuration: nothing to compare


def test_the_shape_excess_is_free_of_each_configurations_noise_factor():
    """Noise independent from frame to frame multiplies every correlation at a lag of a frame or more by one
    factor per configuration (physics.md §8): the shape excess does not change, the raw one does."""
    tau = np.array(LAGS, float)[:, None]
    rates = np.array([0.05, 0.2, 0.5])[None, :]
    fine, coarse = np.exp(-rates * tau), np.exp(-0.5 * rates * tau)  # the coarser decays slower: one region
    clean = _rows(fine, coarse)
    noisy = _rows(0.4 * fine, 0.9 * coarse)
    shape_clean = decay_excess(clean, COLUMNS, "fine", shape=True)
    np.testing.assert_allclose(decay_excess(noisy, COLUMNS, "fine", shape=True), shape_clean, atol=1e-12)
    assert np.all(shape_clean < 0)  # one region: the coarser configuration's shape lies above
    assert not np.allclose(decay_excess(noisy, COLUMNS, "fine"), decay_excess(clean, COLUMNS, "fine"))
    # a coarse PSF that reaches a faster region decays faster in shape: positive excess
    mixed = _rows(fine, 0.5 * np.exp(-rates * tau) + 0.5 * np.exp(-4.0 * rates * tau))
    assert np.all(decay_excess(mixed, COLUMNS, "fine", shape=True) > 0)
    # below the floor at the shortest lag in either configuration: undefined
    low = _rows(fine * (SHAPE_FLOOR * 0.9), coarse)
    assert np.all(np.isnan(decay_excess(low, COLUMNS, "fine", shape=True)))


def test_a_pooled_decision_is_flagged_where_the_pixels_own_outcome_excludes_it():
    pooled = np.array([[0, 0, 0, 0, 2, 2]])
    own = np.array([[0, 3, 5, 4, 1, 2]])  # diffusion, indeterminate, diffusion-or-flow, ballistic-or-flow, ...
    flags = candidates(pooled, NAMES, _both(np.zeros(pooled.shape)), (1, 1), (own, NAMES))
    assert flags["pool-1-excludes"].tolist() == [[False, False, False, True, True, False]]


def test_flags_are_scored_against_the_right_and_wrong_decisions_they_take():
    d, b, f = (CODES[m] for m in ("diffusion", "ballistic", "flow"))
    truth = np.array([[d, d, d, f, f, b, 1]])  # 1: static, no motion's pixel
    labels = np.array([[0, 0, 3, 0, 0, 1, 0]])
    flagged = np.array([[True, False, False, True, False, False, True]])
    row = score(truth, labels, NAMES, flagged)
    assert row["flagged"] == {"right": 1, "right_of": 3, "wrong": 1, "wrong_of": 2}
    interior = np.array([[True, True, True, True, False, False, False]])
    inner = score(truth, labels, NAMES, flagged, interior)["flagged"]
    assert (inner["right_interior"], inner["right_interior_of"]) == (1, 2)  # pixels 0 and 1; 0 flagged
    assert row["per_class"]["flow"]["wrong_share"] == pytest.approx(0.5)
    assert row["per_class"]["diffusion"]["coverage"] == pytest.approx(1 / 3)
    base = score(truth, labels, NAMES, None)
    assert "flagged" not in base and base["per_class"]["flow"]["wrong_share"] == pytest.approx(1.0)


def test_the_recorded_run_summarizes_its_draws():
    result = json.loads((REPO / "research" / "results" / "spill-rules.json").read_text())
    assert result["command"].startswith("python -m research.spill")
    assert result["summary"] == json.loads(json.dumps(summarize(result["draws"])))
    variants = {s["variant"] for s in result["summary"]}
    assert {"default", "mixed-pixel", "pool-1-excludes"} <= variants
    assert {f"mixed-box-{t:g}" for t in BOX_THRESHOLDS} <= variants
    assert {"shape-pixel"} | {f"shape-box-{t:g}" for t in SHAPE_BOX_THRESHOLDS} <= variants

"""Flow recall by polar band and speed decade (classifier.report.flow_recall_by_band)."""

import math

import numpy as np

from classifier.dataset import Prior, draw_parameters
from classifier.report import flow_recall_by_band
from classifier.rule import make_rule

CLASSES = ["diffusion", "ballistic", "flow", "indeterminate"]


def _probs(pred: np.ndarray) -> np.ndarray:
    p = np.full((pred.size, 4), 0.01)
    p[np.arange(pred.size), pred] = 0.97
    return p


def test_bands_fold_the_polar_angle_and_count_each_decision():
    # four flow samples near the axis (two pointing up, 170° = 10° folded), two oblique, one lateral;
    # one diffusion sample (not counted); one non-identifiable flow sample (not counted)
    polar = np.array([5.0, 170.0, 20.0, 25.0, 45.0, 130.0, 89.0, math.nan, 10.0])
    y = np.array([2, 2, 2, 2, 2, 2, 2, 0, 2])
    status = np.array([0, 0, 0, 0, 0, 0, 0, 0, 1])
    pred = np.array([2, 1, 2, 3, 2, 2, 0, 0, 2])
    speed = np.array([0.5, 0.5, 5.0, 5.0, 0.05, 0.5, 0.5, 1.0, 1.0])
    out = flow_recall_by_band(_probs(pred), y, status, polar, speed, CLASSES, make_rule(0.05, 0.5))
    near = out["polar_bands"]["0-30"]
    assert near["samples"] == 4 and near["coverage"] == 0.75
    assert math.isclose(near["recall"], 2 / 3) and math.isclose(near["as"]["ballistic"], 1 / 3)
    assert out["polar_bands"]["30-60"] == {"samples": 2, "coverage": 1.0, "recall": 1.0,
                                           "as": {"diffusion": 0.0, "ballistic": 0.0, "flow": 1.0}}
    assert out["polar_bands"]["60-90"]["recall"] == 0.0  # 89°: called diffusion
    assert out["speed_decades"]["1e-2"]["samples"] == 1 and out["speed_decades"]["1e0"]["samples"] == 2


def test_uniform_angle_prior_puts_a_third_of_flow_within_30_degrees():
    prior = Prior(flow_polar_angle_deg=(0.0, 90.0), flow_polar_law="uniform-angle")
    iso = Prior(flow_polar_angle_deg=(0.0, 90.0))
    n = 3 * 600
    th_u = np.array([draw_parameters(prior, 0, "train", k).polar_angle_deg for k in range(2, n, 3)])
    th_i = np.array([draw_parameters(iso, 0, "train", k).polar_angle_deg for k in range(2, n, 3)])
    se = math.sqrt(1 / 3 * 2 / 3 / th_u.size)
    assert abs((th_u < 30).mean() - 1 / 3) < 4 * se
    p_iso = 1 - math.cos(math.radians(30))  # cos θ uniform on [0, 1]
    assert abs((th_i < 30).mean() - p_iso) < 4 * math.sqrt(p_iso * (1 - p_iso) / th_i.size)
    assert th_u.min() >= 0 and th_u.max() <= 90

"""Flow recall by polar band and speed decade (classifier.report.flow_recall_by_band)."""

import math

import numpy as np

from classifier.prior import Prior, draw_parameters
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
    assert out["polar_bands"]["30-60"] == {
        "samples": 2,
        "coverage": 1.0,
        "recall": 1.0,
        "as": {"diffusion": 0.0, "ballistic": 0.0, "flow": 1.0},
    }
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


def _field_spec():
    from classifier.features import load_spec, spec_from_dict

    d = load_spec("signature").to_dict()
    d["name"], d["metrics"] = "field-test", d["metrics"] + ["g1_1", "g1_2"]
    return spec_from_dict(d)


def test_bulk_residual_random_walk_leaves_intensity_and_shrinks_g1_as_predicted():
    """A residual bulk phase (random walk, step SD σ, common to the configurations) changes no intensity
    feature and multiplies |g1| of a static sample by E|⟨exp(iδ)⟩| over the T − 1 lag-1 pairs."""
    from classifier.prior import Draw
    from classifier.simulation import simulate_draw

    spec = _field_spec()
    draw = Draw(
        label=0,
        magnitude=1e-7,
        polar_angle_deg=0.0,
        azimuth_deg=0.0,
        density_per_um3=0.05,
        sim_seed=7,
        nuisance=((0.0, math.nan),),
    )
    sigma = 0.3
    x0, _, _ = simulate_draw(spec, draw, Prior(), trials=128, truncation_tolerance=1e-2)
    x1, _, _ = simulate_draw(
        spec, draw, Prior(bulk_residual_step_rad=(sigma, sigma)), trials=128, truncation_tolerance=1e-2
    )
    names = list(spec.feature_names)
    g1 = [i for i, n in enumerate(names) if n.startswith("g1_1@")]
    inten = [i for i, n in enumerate(names) if not n.startswith("g1_")]
    # intensity features of a moving sample (D = 0.1 µm²/s): unchanged up to float32 rounding of the phasor
    moving = Draw(
        label=0,
        magnitude=0.1,
        polar_angle_deg=0.0,
        azimuth_deg=0.0,
        density_per_um3=0.05,
        sim_seed=7,
        nuisance=((0.0, math.nan),),
    )
    m0, _, _ = simulate_draw(spec, moving, Prior(), trials=64, truncation_tolerance=1e-2)
    m1, _, _ = simulate_draw(
        spec, moving, Prior(bulk_residual_step_rad=(sigma, sigma)), trials=64, truncation_tolerance=1e-2
    )
    np.testing.assert_allclose(m1[0][:, inten], m0[0][:, inten], rtol=1e-4, atol=1e-4)
    base = x0[0][:, g1[0]].astype(np.float64)
    assert base.mean() > 0.999  # a (nearly) static sample: |g1| ≈ 1 without the residual
    rng = np.random.default_rng(0)
    d = rng.normal(0.0, sigma, size=(200_000, spec.n_frames - 1))
    expect = np.abs(np.exp(1j * d).mean(axis=1))  # |⟨exp(iδ)⟩| over the lag-1 pairs of one trial
    got = x1[0][:, g1].astype(np.float64)
    per_trial = got[:, 0]
    se = math.sqrt(expect.var() / per_trial.size + base.var() / base.size)
    assert abs(per_trial.mean() - expect.mean() * base.mean()) < 4 * se
    # the walk is common to the configurations: their |g1| move together
    assert np.corrcoef(got[:, 0], got[:, 2])[0, 1] > 0.9

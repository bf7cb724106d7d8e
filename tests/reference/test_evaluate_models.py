"""The evaluation on independent data (:mod:`evaluate_models`): its simulator shares scatterers between
configurations, its prior is the documented one, and the harness is deterministic and counts the
ground truth as :func:`classifier.truth.identifiability` does.

Fast tests (default suite); the comparison of per-configuration feature means with :mod:`refsim`'s
independent systems is marked slow.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import evaluate_models as em
import numpy as np
import pytest
import refcompare as rc
import refsim

from classifier.features import load_spec
from classifier.truth import STATUS, identifiability

ORIGINAL = refsim.Optics(0.84, 4.9, 3.8)
AXIAL = refsim.Optics(0.84, 4.9, 14.0)
LATERAL = refsim.Optics(0.84, 18.0, 3.8)
STATIC = refsim.Motion("static")


def _gauss_integral(*inv_two_var: np.ndarray) -> float:
    """∫ exp(−Σ_a k_a x_a²) d³x = π^{3/2}/√(Π k_a), with k_a the sum of the given per-axis coefficients."""
    k = np.sum(inv_two_var, axis=0)
    return float(math.pi**1.5 / math.sqrt(np.prod(k)))


def _intensity_correlation(density: float, a: refsim.Optics, b: refsim.Optics) -> float:
    """Correlation across pixels of the intensities of two same-wavelength configurations that see the same
    static Poisson scatterers (phases uniform): ``Cov = ρ∫h_a²h_b² + (ρ∫h_a h_b)²``,
    ``Var = ρ∫h⁴ + (ρ∫h²)²``, with ``h = exp(−Σ x²/(2s²))`` (physics.md §5.1-5.2)."""
    ka = 1.0 / (2.0 * np.array(a.sigmas_um) ** 2)
    kb = 1.0 / (2.0 * np.array(b.sigmas_um) ** 2)
    cov = density * _gauss_integral(2 * ka, 2 * kb) + (density * _gauss_integral(ka, kb)) ** 2
    va = density * _gauss_integral(4 * ka) + (density * _gauss_integral(2 * ka)) ** 2
    vb = density * _gauss_integral(4 * kb) + (density * _gauss_integral(2 * kb)) ** 2
    return cov / math.sqrt(va * vb)


def _corr_and_se(i1: np.ndarray, i2: np.ndarray, n_boot: int = 300) -> tuple[float, float]:
    """Pearson correlation across trials and its bootstrap SE over trials."""
    r = float(np.corrcoef(i1, i2)[0, 1])
    rng = np.random.default_rng(0)
    boot = [np.corrcoef(i1[k], i2[k])[0, 1] for k in rng.integers(0, i1.size, (n_boot, i1.size))]
    return r, float(np.std(boot, ddof=1))


def test_equal_configurations_see_identical_fields():
    """Two configurations with the same optics get the same scatterers and paths: identical fields (the
    limit of equal resolution of a dataset and its reduction), for static and moving scenes."""
    for motion in (
        STATIC,
        refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=30.0),
        refsim.Motion("diffusion", diffusion_um2_per_s=0.01),
    ):
        e = em.simulate_joint(
            [ORIGINAL, AXIAL, ORIGINAL],
            motion,
            density_per_um3=0.04,
            n_frames=6,
            frame_interval_s=0.2048,
            trials=16,
            seed=1,
        )
        assert np.array_equal(e[:, 0], e[:, 2]), motion.kind
        assert not np.allclose(e[:, 0], e[:, 1]), motion.kind


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_static_scene_fields_correlated_as_shared_scatterers_predict():
    """Original and axial-reduced configurations of one trial see the same static scatterers: their
    intensities are correlated across trials as the closed form says (0.57 here); with refsim's
    independent scatterers per system the correlation is 0. Tolerance: 4 bootstrap SEs."""
    kw = dict(density_per_um3=0.05, n_frames=2, frame_interval_s=0.2048, trials=2048)
    joint = em.simulate_joint([ORIGINAL, AXIAL], STATIC, seed=5, **kw)
    inten = np.abs(joint[:, :, 0]) ** 2
    r, se = _corr_and_se(inten[:, 0], inten[:, 1])
    want = _intensity_correlation(0.05, ORIGINAL, AXIAL)
    assert 0.4 < want < 0.8
    assert abs(r - want) < 4 * se, (r, want, se)
    # the mean intensity of each configuration is its closed form ρ·π^{3/2}·s_x·s_y·s_z (physics.md §5.2)
    for c, o in enumerate((ORIGINAL, AXIAL)):
        mean, sd = inten[:, c].mean(), inten[:, c].std(ddof=1) / math.sqrt(inten.shape[0])
        assert abs(mean - refsim.mean_intensity(o, 0.05)) < 4 * sd
    ind = refsim.simulate([ORIGINAL, AXIAL], STATIC, seed=5, **kw)
    inten = np.abs(ind[:, :, 0]) ** 2
    r0, se0 = _corr_and_se(inten[:, 0], inten[:, 1])
    assert abs(r0) < 4 * se0, (r0, se0)


def test_prior_is_the_documented_one():
    draws = [em.draw_independent(7, k) for k in range(3000)]
    assert [d.label for d in draws[:6]] == [0, 1, 2, 0, 1, 2]
    for d in draws:
        lo, hi = em.RANGES[d.motion]
        assert lo <= d.magnitude <= hi
        assert em.SNR_DB[0] <= d.snr_db <= em.SNR_DB[1]
        assert 0.0 <= d.polar_angle_deg <= 90.0 and 0.0 <= d.azimuth_deg < 360.0
    # the polar angle is uniform: each band 0-30, 30-60, 60-90 holds a third of the draws (4 binomial SEs)
    theta = np.array([d.polar_angle_deg for d in draws])
    for lo in (0.0, 30.0, 60.0):
        share = np.mean((theta >= lo) & (theta < lo + 30.0))
        assert abs(share - 1 / 3) < 4 * math.sqrt(2 / 9 / theta.size)
    laws = np.array([d.ballistic_directions == "uniform-angles" for d in draws])
    assert abs(laws.mean() - 0.5) < 4 * math.sqrt(0.25 / laws.size)
    # a draw does not depend on how many are made, and seeds differ
    assert em.draw_independent(7, 11) == draws[11]
    assert em.draw_independent(8, 11) != draws[11]


def test_optics_follow_the_spec_including_a_bscan_lateral_width_along_y():
    """Wavelength, lateral x (and y where a configuration gives it), axial width and refractive index
    come from the model's spec; a configuration without ``lateral_resolution_y_um`` is isotropic."""
    conf = [
        SimpleNamespace(
            wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8, lateral_resolution_y_um=4.9
        ),
        SimpleNamespace(wavelength_um=1.31, lateral_resolution_um=4.9, axial_resolution_um=14.0),
    ]
    optics = em.optics_for(SimpleNamespace(configurations=conf, refractive_index=1.33))
    assert optics == [
        refsim.Optics(0.84, 18.0, 3.8, lateral_y_um=4.9, refractive_index=1.33),
        refsim.Optics(1.31, 4.9, 14.0, lateral_y_um=None, refractive_index=1.33),
    ]
    assert optics[0].sigmas_um[1] == pytest.approx(4.9 / (2 * math.sqrt(2)))


def test_features_of_a_draw_do_not_depend_on_the_trial_count():
    spec = load_spec("signature")
    d = em.draw_independent(0, 2)  # flow
    a = em.draw_features(spec, d, 10)
    b = em.draw_features(spec, d, 3)
    assert a.shape == (10, spec.n_features) and np.all(np.isfinite(a))
    assert np.array_equal(a[:3], b)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_harness_deterministic_and_counts_ground_truth(monkeypatch):
    """Same seed, same report; the ground truth per draw is classifier.truth.identifiability's, and the
    identifiable samples are the trials of the identifiable draws. Diffusion is moved to D in [0.05, 0.1]
    µm²/s (decorrelated within a frame interval) so that both outcomes occur."""
    monkeypatch.setitem(em.RANGES, "diffusion", (0.05, 0.1))
    kw = dict(draws=5, trials=4, seed=3, n_boot=5, progress=False)
    a = em.evaluate_model("signature", **kw)
    b = em.evaluate_model("signature", **kw)
    a.pop("seconds"), b.pop("seconds")
    assert a == b
    spec = load_spec("signature")
    prior = em.independent_prior(a["rule"]["epsilon"])
    status = [identifiability(spec, em.dataset_draw(em.draw_independent(3, k)), prior)[0] for k in range(5)]
    assert [d["status"] for d in a["per_draw"]] == status
    assert a["draw_status_counts"] == {s: status.count(s) for s in STATUS}
    assert status.count("decorrelated") == 2 and status.count("identifiable") == 3
    m = a["results"]["1"]["metrics"]
    assert m["samples"] == 5 * 4 and m["identifiable_samples"] == 4 * status.count("identifiable")
    pooled = a["results"]["4"]  # pool 25 capped at the 4 trials
    assert pooled["samples"] == 5 * em.POOLED_PER_DRAW
    assert {t["what"].split(":")[0] for t in a["targets"]} == {"pool 1"}
    assert em.evaluate_model("signature", **{**kw, "seed": 4})["per_draw"] != a["per_draw"]


def test_conformal_scores_count_decisions_wrong_ones_and_missed_sets_per_motion():
    """Known probabilities against thresholds of 0.5 (a class is in the set when p ≥ 0.5): flow decided, decided
    as ballistic, or in a two-motion set; rule 1 turns the ballistic decision into ballistic-or-flow; a wrong
    decision always misses its own motion; non-identifiable rows are not counted."""
    classes = ["diffusion", "ballistic", "flow", "indeterminate"]
    cal = {
        "classes": classes,
        "mode": "marginal",
        "pools": [{"pool_pixels": 1, "scores": [0.5] * 9, "truth": [0] * 9}],
    }  # the marginal quantile of nine scores of 0.5 at any alpha < 1: 0.5
    p = np.array(
        [
            [0.0, 0.0, 0.9, 0.1],  # flow: decided flow
            [0.0, 0.8, 0.2, 0.0],  # flow: decided ballistic (wrong; rule 1: ballistic-or-flow)
            [0.0, 0.5, 0.5, 0.0],  # flow: ballistic-or-flow
            [0.0, 0.9, 0.1, 0.0],  # flow, not identifiable: not counted
            [0.9, 0.1, 0.0, 0.0],  # diffusion: decided diffusion
        ]
    )
    truth = np.array([2, 2, 2, 2, 0])
    ident = np.array([True, True, True, False, True])
    c = em.conformal_scores(p, np.ones(5), truth, ident, classes, cal, 0.1)
    f, d, b = c["per_class"]["flow"], c["per_class"]["diffusion"], c["per_class"]["ballistic"]
    assert f["samples"] == 3 and f["decided"] == pytest.approx(1 / 3) and f["wrong_share"] == pytest.approx(1 / 3)
    assert f["set_miss_share"] == pytest.approx(1 / 3) and f["mean_set_size"] == pytest.approx(4 / 3)
    assert c["rule_1"]["flow"] == {"decided": pytest.approx(1 / 3), "wrong_share": 0.0}
    assert d["decided"] == 1.0 and d["wrong_share"] == 0.0 and b["samples"] == 0 and b["decided"] is None
    for q in c["per_class"].values():  # a wrong decision is a set without the motion
        assert q["wrong_share"] is None or q["wrong_share"] <= q["set_miss_share"]


def test_the_harness_scores_a_calibrated_models_prediction_sets(monkeypatch):
    """A calibrated model's report holds its prediction sets at doct-classify's default level at every pool,
    for the three motions; rule 1 never adds a wrong decision."""
    from classifier.conformal import DEFAULT_ALPHA

    r = em.evaluate_model("signature", draws=3, trials=4, seed=3, n_boot=5, progress=False)
    for res in r["results"].values():
        c = res["conformal"]
        assert c["alpha"] == DEFAULT_ALPHA and set(c["per_class"]) == set(em._CLASSES)
        for name, q in c["per_class"].items():
            if q["samples"]:
                assert c["rule_1"][name]["wrong_share"] <= q["wrong_share"] <= q["set_miss_share"]
    assert "prediction sets" in em.format_markdown(r)


@pytest.mark.slow
def test_shared_scatterers_leave_each_configuration_as_refsim_simulates_it():
    """Sharing scatterers between configurations changes no configuration's own statistics: per-feature
    means of simulate_joint and refsim.simulate (independent systems) agree within the Bonferroni bound
    of refcompare, for flow, random-ballistic motion and diffusion at the three signature configurations."""
    names = ("rho_lin_1", "rho_lin_2", "rho_lin_4", "rho_lin_8", "rho_lin_16", "lin_contrast", "db_variance")
    motions = (
        refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=20.0, azimuth_deg=30.0),
        refsim.Motion("ballistic", speed_um_per_s=0.1, directions="uniform-angles"),
        refsim.Motion("diffusion", diffusion_um2_per_s=0.003),
    )
    optics = [ORIGINAL, AXIAL, LATERAL]
    n = 768
    bound = rc.z_bound(len(names) * len(optics) * len(motions))
    for motion in motions:
        kw = dict(density_per_um3=0.04, n_frames=32, frame_interval_s=0.2048, trials=n, snr_db=25.0)
        fa = refsim.features(em.simulate_joint(optics, motion, seed=1, **kw), 0.2048, names)
        fb = refsim.features(refsim.simulate(optics, motion, seed=2, **kw), 0.2048, names)
        for name in names:
            z = (fa[name].mean(0) - fb[name].mean(0)) / np.sqrt(
                fa[name].var(0, ddof=1) / n + fb[name].var(0, ddof=1) / n
            )
            assert np.all(np.abs(z) < bound), (motion.kind, name, z)

"""The per-pixel least-squares g1 fit (research.g1fit): closed-form curves, static term, batching,
undefined input, the CLI's refusals. The full comparison with the network is not a test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from research import g1fit
from research.g1fit import DEFAULT_LAGS, GRID_PER_DECADE, REASONS, fit_g1
from torchdoct.sim import theory

DT = 0.2048
CONFS = [(0.84, 4.9, 3.8), (0.84, 4.9, 14.0), (0.84, 18.0, 3.8)]  # the signature spec's configurations
KW = dict(configurations=CONFS, lags=DEFAULT_LAGS, frame_interval_s=DT, n_frames=32)
STEP = 1.0 / GRID_PER_DECADE  # dex


def _curve(kind: str, mag: float, theta: float = 60.0, law: str = "isotropic") -> np.ndarray:
    tau = np.asarray(DEFAULT_LAGS) * DT
    out = []
    for wl, lat, ax in CONFS:
        kw = dict(wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax)
        if kind == "diffusion":
            out.append(theory.g1_diffusion(tau, diffusion_um2_per_s=mag, **kw))
        elif kind == "ballistic":
            out.append(theory.g1_ballistic(tau, speed_um_per_s=mag, directions=law, **kw))
        else:
            out.append(theory.g1_flow(tau, speed_um_per_s=mag, polar_angle_deg=theta, **kw))
    return np.asarray(out, dtype=np.complex128)


def _on_grid(k: int) -> float:
    return 10.0 ** (k / GRID_PER_DECADE)


# magnitudes on the grid (10^(k/20)): diffusion 1e-3..0.03 µm²/s, ballistic 0.01..0.1 µm/s (both laws),
# flow 0.3..3 µm/s at 60°, 90° (transverse) and 107° (upwards, cos θ = −0.3)
_UP = 180.0 - math.degrees(math.acos(0.3))
CASES = (
    [("diffusion", _on_grid(k), 60.0, "isotropic") for k in (-60, -50, -40, -30)]
    + [("ballistic", _on_grid(k), 60.0, law) for k in (-40, -30, -20) for law in ("isotropic", "uniform-angles")]
    + [("flow", _on_grid(k), th, "isotropic") for k in (-10, 0, 10) for th in (60.0, 90.0, _UP)]
)


def test_noise_free_curves_are_classified_and_sized():
    ms, mf = 0.3, 0.6
    y = np.stack([ms + mf * _curve(*c) for c in CASES])
    res = fit_g1(y, **KW)
    names = ("diffusion", "ballistic", "flow")
    for i, (kind, mag, theta, law) in enumerate(CASES):
        assert REASONS[res.reason[i]] == "decided", (kind, mag, theta, REASONS[res.reason[i]])
        assert names[res.label[i]] == kind, (kind, mag, theta, law, res.bic[i])
        assert res.magnitude[i] == pytest.approx(mag, rel=1e-9)
        # exact for the real models; flow's phase step is estimated to ~1e-3 rad per frame
        np.testing.assert_allclose(res.static[i], ms, atol=1e-6 if kind != "flow" else 2e-3)
        if kind == "flow":
            assert res.polar_angle_deg[i] == pytest.approx(theta, abs=1e-6)
            step = -2 * (2 * math.pi / 0.84) * mag * math.cos(math.radians(theta)) * DT
            assert abs(math.remainder(res.phase_step_rad[i] - step, 2 * math.pi)) < 0.01


def test_off_grid_magnitudes_within_the_grid_resolution():
    # half-way between grid points: the true model's magnitude is the nearest point or the next one
    # (the amplitudes Ms, Mf absorb part of the mismatch), i.e. within 1.5 steps of 1/20 dex
    cases = [(k, m * 10 ** (0.5 * STEP), th, law) for k, m, th, law in CASES]
    y = np.stack([0.3 + 0.6 * _curve(*c) for c in cases])
    res = fit_g1(y, **KW)
    for i, (kind, mag, theta, law) in enumerate(cases):
        got = res.magnitude_by_model[i, ("diffusion", "ballistic", "flow").index(kind)]
        assert abs(math.log10(got / mag)) <= 1.5 * STEP + 1e-9, (kind, mag, theta, law, got)


def test_static_term_and_grid_magnitudes_are_recovered_exactly():
    # magnitudes on the grid: the fit is exact (Ms, Mf, magnitude, RSS 0) whatever the static share
    # (flow moving transversely: no phase step to estimate)
    cases = [("diffusion", _on_grid(-50)), ("ballistic", _on_grid(-30)), ("flow", 1.0)]
    for ms in (0.0, 0.25, 0.7):
        mf = 0.95 - ms
        y = np.stack([ms + mf * _curve(k, m, theta=90.0) for k, m in cases])
        res = fit_g1(y, **KW)
        np.testing.assert_allclose(res.magnitude, [m for _, m in cases], rtol=1e-9)
        np.testing.assert_allclose(res.static, ms, atol=1e-6)
        np.testing.assert_allclose(res.moving, mf, atol=1e-6)
        assert list(res.label) == [0, 1, 2]
        assert res.rss[np.arange(3), res.model].max() < 1e-10


def test_batched_equals_per_pixel(monkeypatch):
    rng = np.random.default_rng(3)
    base = np.stack([0.2 + 0.7 * _curve(*c) for c in CASES[::3]])
    y = np.repeat(base, 4, axis=0)
    y = y + 0.05 * (rng.standard_normal(y.shape) + 1j * rng.standard_normal(y.shape))
    monkeypatch.setattr(g1fit, "_CHUNK", 5)  # several chunks, one of them partial
    whole = fit_g1(y, **KW)
    for i in range(len(y)):
        one = fit_g1(y[i : i + 1], **KW)
        for field in ("label", "reason", "model", "magnitude", "magnitude_by_model", "polar_angle_deg"):
            np.testing.assert_array_equal(getattr(one, field)[0], getattr(whole, field)[i], err_msg=field)
        # the Doppler phase step comes from a float32 search (g1fit._phase_search), whose BLAS products may
        # round differently with the batch size: the step's parabola refinement then moves by float32
        # round-off of the criterion (measured 3e-7 rad; bound 1e-5 rad, 1e-4 of a phase-grid step), and the
        # flow model's amplitudes and RSS, which use that step, agree to ~1e-6 relative
        for field in ("static", "moving", "rss"):
            np.testing.assert_allclose(
                getattr(one, field)[0], getattr(whole, field)[i], rtol=1e-6, atol=1e-9, err_msg=field
            )
        np.testing.assert_allclose(one.phase_step_rad[0], whole.phase_step_rad[i], rtol=0, atol=1e-5)


def test_undefined_and_indeterminate_pixels():
    good = 0.2 + 0.7 * _curve("flow", 1.0)
    y = np.stack(
        [good, good, good, np.zeros_like(good), np.full_like(good, 0.9), 0.3 + 0.6 * _curve("diffusion", 30.0), good]
    )
    y[0, 1, 3] = np.nan
    y[1, 0, 0] = complex(np.inf, 0.0)
    y[2, 2, 9] = complex(0.0, np.nan)
    res = fit_g1(y, **KW)
    assert [REASONS[r] for r in res.reason[:3]] == ["invalid input"] * 3
    assert np.all(res.label[:6] == 3) and res.label[6] == 2
    assert np.isnan(res.magnitude[:3]).all() and np.isnan(res.static[:3]).all()
    assert REASONS[res.reason[3]] == "no moving term"  # nothing at all
    assert REASONS[res.reason[4]] in ("static", "no moving term")  # no decorrelation over the acquisition
    assert REASONS[res.reason[5]] in ("decorrelated", "no moving term")  # gone within one frame interval
    assert np.all(res.one_hot()[:6, 3] == 1.0)
    empty = fit_g1(np.zeros((0, 3, len(DEFAULT_LAGS)), complex), **KW)
    assert empty.label.shape == (0,)


def test_bad_input_is_refused():
    y = np.zeros((2, 3, len(DEFAULT_LAGS)), complex)
    with pytest.raises(ValueError, match="configurations"):
        fit_g1(y[:, :2], **KW)
    with pytest.raises(ValueError, match="lags"):
        fit_g1(np.zeros((2, 3, 2), complex), **{**KW, "lags": (0, 1)})
    with pytest.raises(ValueError, match="one wavelength"):
        fit_g1(y, **{**KW, "configurations": [(0.84, 4.9, 3.8), (1.31, 4.9, 3.8), (0.84, 18.0, 3.8)]})
    with pytest.raises(ValueError, match="ballistic_directions"):
        fit_g1(y, **KW, ballistic_directions="sideways")


def test_superset_spec_columns_and_complex_curve():
    from classifier.features import load_spec
    from research.g1fit import complex_g1, g1_columns, superset_spec

    spec = load_spec("signature")
    sup = superset_spec(spec, (1, 2, 5))
    assert sup.configurations == spec.configurations and sup.metrics[: len(spec.metrics)] == spec.metrics
    mag, ph = g1_columns(sup.feature_names, sup, (1, 2, 5))
    x = np.zeros((1, sup.n_features), np.float32)
    x[0, mag] = np.arange(9) + 1
    x[0, ph] = 0.5
    y = complex_g1(x, mag, ph, 3)
    assert y.shape == (1, 3, 3) and y[0, 1, 2] == pytest.approx(6 * np.exp(0.5j))
    assert sup.feature_names[mag[5]] == f"g1_5@{spec.configurations[1].name}"
    with pytest.raises(ValueError, match="superset_spec"):
        g1_columns(spec.feature_names, spec, (1,))


def test_cli_refuses_existing_output(tmp_path, capsys):
    out = tmp_path / "cmp.json"
    out.write_text("keep")
    assert g1fit.main(["--out", str(out), "--draws", "1"]) == 2
    assert out.read_text() == "keep" and "exists" in capsys.readouterr().out
    md = tmp_path / "other.md"
    md.write_text("keep md")
    assert g1fit.main(["--out", str(tmp_path / "other.json"), "--draws", "1"]) == 2
    assert md.read_text() == "keep md" and not (tmp_path / "other.json").exists()
    assert g1fit.main(["--out", str(tmp_path / "x.txt")]) == 2
    assert g1fit.main(["--out", str(tmp_path / "y.json"), "--lags", "1,a"]) == 2
    assert g1fit.main(["--out", str(tmp_path / "y.json"), "--draws", "0"]) == 2
    assert g1fit.main(["--out", str(tmp_path / "y.json"), "--model", "single-acquisition"]) == 2
    assert "signature model" in capsys.readouterr().out
    assert not list(tmp_path.glob("y.*")) and not list(tmp_path.glob("x.*"))


def test_bootstrap_fast_path_matches_the_report_definitions():
    from classifier.report import evaluate
    from classifier.rule import make_rule
    from classifier.train import CLASS_NAMES
    from research.g1fit import _abs_log10_error, _headline, _magnitude_errors

    rng = np.random.default_rng(5)
    n = 3000
    pred = rng.integers(0, 4, n)
    s = {
        "y": rng.integers(0, 3, n),
        "status": rng.choice(3, n, p=[0.6, 0.2, 0.2]),
        "magnitude": 10 ** rng.uniform(-3, 1, n),
    }
    est = np.log10(s["magnitude"])[:, None] + rng.normal(0, 0.2, (n, 3))
    fast = _headline(pred, s["y"], s["status"], _abs_log10_error(est, s))
    full = evaluate(np.eye(4)[pred], s["y"], s["status"], CLASS_NAMES, make_rule(0.05))
    mag = _magnitude_errors(est, s, pred == s["y"])
    assert fast["balanced_accuracy_identifiable"] == pytest.approx(full["balanced_accuracy_identifiable"], abs=1e-12)
    assert fast["coverage_identifiable"] == pytest.approx(full["coverage_identifiable"], abs=1e-12)
    assert fast["median_abs_log10_error"] == pytest.approx(mag["decided_correct"]["median_abs_log10_error"], abs=1e-12)

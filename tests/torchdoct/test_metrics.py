"""DOCT metrics (torchdoct.sim.metrics) against numpy references and a process of known correlation.

Statistical checks use AR(1) sequences in dB, s_t = a·s_{t−1} + √(1−a²)·e_t (stationary, ρ_m = a^m),
with fixed seeds; tolerances are z = 4 Monte Carlo standard errors computed from the sample.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchdoct.sim.config import Analysis
from torchdoct.sim.metrics import (
    complex_variance,
    compute_metrics,
    lag_correlations,
    liv,
    ocds,
    ocds_from_correlations,
    summarize,
    to_db,
)

DT_S = 0.2048
Z = 4.0
DTYPES = [torch.float64, torch.float32]
# relative tolerance of a float computation against the float64 numpy reference
RTOL = {torch.float64: 1e-10, torch.float32: 1e-4}


def _times(n: int) -> list[float]:
    return [DT_S * i for i in range(n)]


def _intensity(shape, dtype, seed=0) -> torch.Tensor:
    """Positive intensities spanning several decades (exponential speckle-like values)."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.exponential(size=shape) + 1e-3).to(dtype)


def _ar1_db(realizations: int, frames: int, a: float, seed: int) -> np.ndarray:
    """Stationary AR(1) sequences (unit variance, ρ_m = a^m) along the last axis."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((realizations, frames))
    s = np.empty_like(e)
    s[:, 0] = e[:, 0]
    c = math.sqrt(1.0 - a * a)
    for t in range(1, frames):
        s[:, t] = a * s[:, t - 1] + c * e[:, t]
    return s


def _db_to_intensity(s_db: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(10.0 ** (s_db / 10.0))


def _pearson_np(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.corrcoef(x, y)[0, 1])


# ----------------------------------------------------------------------------------------------------------
# LIV
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
def test_liv_is_ddof0_variance_of_db(dtype):
    intensity = _intensity((50, 32), dtype, seed=1)
    ref = np.var(10.0 * np.log10(intensity.double().numpy()), axis=-1, ddof=0)
    got = liv(intensity)
    assert got.dtype == dtype and got.shape == (50,)
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=RTOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("value", [3.7, 0.1, 1e-6, 12345.678])
def test_liv_of_constant_sequence_is_exactly_zero(dtype, value):
    intensity = torch.full((3, 32), value, dtype=dtype)
    assert torch.equal(liv(intensity), torch.zeros(3, dtype=dtype))


def test_liv_is_invariant_to_scaling_the_intensity():
    intensity = _intensity((40, 32), torch.float64, seed=2)
    base = liv(intensity)
    for c in (1e-6, 0.37, 7.3, 1e5):
        torch.testing.assert_close(liv(c * intensity), base, rtol=0.0, atol=1e-9)


# ----------------------------------------------------------------------------------------------------------
# lag correlations and OCDS
# ----------------------------------------------------------------------------------------------------------
def test_pearson_lag_correlation_matches_numpy_per_sequence():
    s = _ar1_db(20, 32, 0.6, seed=3)
    delays, rho = lag_correlations(torch.from_numpy(s), _times(32))
    np.testing.assert_allclose(delays.numpy(), DT_S * np.arange(1, 32), rtol=1e-12)
    assert rho.shape == (20, 31)
    for r in range(20):
        for m in (1, 2, 6, 20, 29):
            ref = _pearson_np(s[r, :-m], s[r, m:])
            assert rho[r, m - 1].item() == pytest.approx(ref, abs=1e-10)


def test_biased_lag_correlation_matches_numpy_per_sequence():
    s = _ar1_db(20, 32, 0.6, seed=4)
    _, rho = lag_correlations(torch.from_numpy(s), _times(32), estimator="biased")
    xm = s - s.mean(-1, keepdims=True)
    for m in (1, 3, 6, 31):
        ref = (xm[:, :-m] * xm[:, m:]).sum(-1) / (xm * xm).sum(-1)
        np.testing.assert_allclose(rho[:, m - 1].numpy(), ref, rtol=0, atol=1e-12)


def test_pearson_lag_correlation_of_ar1_averages_to_a_power_m():
    # The per-lag Pearson estimator subtracts the sample means of both sub-sequences, which biases it by
    # O(S/n) (S = Σ_k ρ_k = (1+a)/(1−a), n = N − m pairs; Kendall 1954), i.e. ~30 standard errors of the
    # 4000-realization mean at N = 32. Longer sequences (N = 128) make the bias small but it still exceeds
    # the SE, so the tolerance is z·SE plus an explicit allowance of 1.5·S/n (measured: 0.85–1.0·S/n at
    # a = 0.5). The cost of lag_correlations grows as N² (every delay is computed).
    a, n_frames, reps = 0.5, 128, 4000
    s = _ar1_db(reps, n_frames, a, seed=5)
    _, rho = lag_correlations(torch.from_numpy(s), _times(n_frames))
    m = np.arange(1, 7)
    r = rho[:, :6].numpy()
    se = r.std(0, ddof=1) / math.sqrt(reps)
    bias_allowance = 1.5 * (1 + a) / (1 - a) / (n_frames - m)
    err = np.abs(r.mean(0) - a**m)
    assert np.all(err <= Z * se + bias_allowance), (r.mean(0), a**m, se, bias_allowance)
    # and the estimate really decays like a^m: lag 1 far above lag 3, lag 3 above lag 6
    assert r.mean(0)[0] > 0.45 and r.mean(0)[2] < 0.15 and abs(r.mean(0)[5]) < 0.03


def test_biased_estimator_is_shrunk_by_one_minus_m_over_n():
    a, n_frames, reps = 0.5, 32, 4000
    s = torch.from_numpy(_ar1_db(reps, n_frames, a, seed=6))
    _, rp = lag_correlations(s, _times(n_frames), estimator="pearson")
    _, rb = lag_correlations(s, _times(n_frames), estimator="biased")
    m = np.arange(1, 7)
    rp = rp[:, :6].numpy()
    rb = rb[:, :6].numpy()
    shrink = 1.0 - m / n_frames
    se = np.sqrt(rb.var(0, ddof=1) / reps + shrink**2 * rp.var(0, ddof=1) / reps)
    assert np.all(np.abs(rb.mean(0) - shrink * rp.mean(0)) <= Z * se)


@pytest.mark.parametrize("dtype", DTYPES)
def test_ocds_is_minus_ols_slope_of_the_correlations(dtype):
    s = _ar1_db(200, 32, 0.8, seed=7)
    intensity = _db_to_intensity(s).to(dtype)
    times = _times(32)
    for estimator in ("pearson", "biased"):
        got = ocds(intensity, times, estimator=estimator)  # default range [0.2048, 1.2288] s: lags 1..6
        assert got.dtype == dtype and got.shape == (200,)
        delays, rho = lag_correlations(to_db(intensity), times, estimator=estimator)
        x = delays[:6].double().numpy()
        np.testing.assert_allclose(x, DT_S * np.arange(1, 7), rtol=1e-6)
        ref = np.array([-np.polyfit(x, rho[i, :6].double().numpy(), 1)[0] for i in range(200)])
        np.testing.assert_allclose(got.double().numpy(), ref, rtol=0, atol=1e-6 if dtype == torch.float64 else 1e-4)
        # closed form of physics.md §2.4: −Σ (m − 3.5) ρ_m / (17.5 Δt)
        closed = -((np.arange(1, 7) - 3.5) * rho[:, :6].double().numpy()).sum(-1) / (17.5 * DT_S)
        np.testing.assert_allclose(got.double().numpy(), closed, rtol=0, atol=1e-9 if dtype == torch.float64 else 1e-4)
    # a decaying correlation (ρ_m = 0.8^m) gives a positive OCDS on average
    assert ocds(intensity, times).double().mean().item() > 0


def test_ocds_linear_scale_uses_linear_intensity():
    intensity = _intensity((10, 16), torch.float64, seed=8)
    times = _times(16)
    delays, rho = lag_correlations(intensity, times)
    torch.testing.assert_close(ocds(intensity, times, scale="linear"), ocds_from_correlations(rho, delays))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("estimator", ["pearson", "biased"])
def test_constant_sequence_has_unit_correlation_and_zero_ocds(dtype, estimator):
    intensity = torch.full((2, 3, 32), 3.7, dtype=dtype)
    _, rho = lag_correlations(to_db(intensity), _times(32), estimator=estimator)
    assert torch.equal(rho, torch.ones_like(rho))
    got = ocds(intensity, _times(32), estimator=estimator)
    assert got.shape == (2, 3) and not torch.isnan(got).any()
    assert got.abs().max().item() <= 10 * torch.finfo(dtype).eps  # exactly 0: see the test below


@pytest.mark.parametrize("dtype", DTYPES)
def test_bug_constant_sequence_ocds_is_exactly_zero(dtype):
    # ρ is exactly 1 at every lag, but ocds_from_correlations computes −Σ y·xc / Σ xc² without centring y,
    # and Σ xc is not exactly 0 in floating point: 5e-16 (float64), 1.2e-7 s⁻¹ (float32) instead of 0.
    intensity = torch.full((2, 32), 3.7, dtype=dtype)
    assert torch.equal(ocds(intensity, _times(32)), torch.zeros(2, dtype=dtype))


def test_one_constant_subsequence_has_zero_correlation():
    s = torch.tensor([[1.0, 1.0, 1.0, 2.0, 5.0]], dtype=torch.float64)
    _, rho = lag_correlations(s, [0, 1, 2, 3, 4])
    # lag 2: {1, 1, 1} against {1, 2, 5}: one side constant -> 0 (not NaN)
    assert rho[0, 1].item() == 0.0
    assert not torch.isnan(rho).any()


def test_non_uniform_frame_times_group_delays():
    s = torch.tensor([[0.3, -1.2, 2.5], [1.0, 4.0, 2.0]], dtype=torch.float64)
    delays, rho = lag_correlations(s, [0.0, 1.0, 3.0])
    assert delays.tolist() == [1.0, 2.0, 3.0]
    assert rho.shape == (2, 3)
    # longer schedule: every delay is the Pearson correlation over exactly the pairs at that delay
    times = [0.0, 1.0, 3.0, 4.0, 6.0, 7.0, 10.0]
    x = _ar1_db(5, len(times), 0.7, seed=9)
    delays, rho = lag_correlations(torch.from_numpy(x), times)
    pairs: dict[float, list[tuple[int, int]]] = {}
    for i in range(len(times)):
        for j in range(i + 1, len(times)):
            pairs.setdefault(times[j] - times[i], []).append((i, j))
    assert delays.tolist() == sorted(pairs)
    for k, d in enumerate(sorted(pairs)):
        ii = [p[0] for p in pairs[d]]
        jj = [p[1] for p in pairs[d]]
        for r in range(5):
            if len(ii) >= 2:
                assert rho[r, k].item() == pytest.approx(_pearson_np(x[r, ii], x[r, jj]), abs=1e-10)
            else:  # one pair: both sides constant
                assert rho[r, k].item() == 1.0


def test_non_uniform_times_with_offset_match_uniform_times():
    intensity = _intensity((4, 10), torch.float64, seed=10)
    uniform = ocds(intensity, _times(10), delay_range_s=(0.2048, 0.8192))
    shifted = ocds(intensity, [5.0 + t for t in _times(10)], delay_range_s=(0.2048, 0.8192))
    torch.testing.assert_close(shifted, uniform, rtol=0, atol=1e-12)


@pytest.mark.parametrize("delay_range", [(10.0, 20.0), (0.3, 0.4), (1.0, 1.3)])
def test_ocds_needs_two_delays_in_range(delay_range):
    intensity = _intensity((2, 6), torch.float64, seed=11)
    with pytest.raises(ValueError, match=r"delay range \[.*\] s holds fewer than 2 delays") as info:
        ocds(intensity, _times(6), delay_range_s=delay_range)
    assert f"[{delay_range[0]}, {delay_range[1]}]" in str(info.value)


def test_lag_correlation_argument_errors():
    s = torch.zeros(2, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match="5 frames but 4 frame times"):
        lag_correlations(s, [0, 1, 2, 3])
    with pytest.raises(TypeError, match="real signal"):
        lag_correlations(torch.zeros(2, 5, dtype=torch.complex128), _times(5))
    with pytest.raises(ValueError, match="estimator"):
        lag_correlations(s, _times(5), estimator="unbiased")
    with pytest.raises(ValueError, match="scale"):
        ocds(s + 1, _times(5), scale="ln")


# ----------------------------------------------------------------------------------------------------------
# complex variance, shapes
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
def test_complex_variance_is_numpy_var_of_complex_samples(dtype):
    rng = np.random.default_rng(12)
    z = rng.standard_normal((30, 32)) + 1j * rng.standard_normal((30, 32)) + (3 - 2j)
    field = torch.from_numpy(z).to(torch.complex128 if dtype == torch.float64 else torch.complex64)
    got = complex_variance(field)
    assert got.dtype == dtype
    ref = np.var(field.numpy().astype(np.complex128), axis=-1, ddof=0)
    np.testing.assert_allclose(got.double().numpy(), ref, rtol=RTOL[dtype])
    const = torch.full((4, 8), 1.5 - 0.25j, dtype=field.dtype)
    assert torch.equal(complex_variance(const), torch.zeros(4, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_metrics_work_on_any_leading_shape(dtype):
    n_frames = 16
    rng = np.random.default_rng(13)
    z = rng.standard_normal((2, 3, 5, n_frames)) + 1j * rng.standard_normal((2, 3, 5, n_frames))
    field = torch.from_numpy(z).to(torch.complex128 if dtype == torch.float64 else torch.complex64)
    intensity = field.real**2 + field.imag**2
    times = _times(n_frames)
    kw = dict(delay_range_s=(0.2048, 1.2288))
    batched = {
        "liv": liv(intensity),
        "ocds": ocds(intensity, times, **kw),
        "cv": complex_variance(field),
        "rho": lag_correlations(to_db(intensity), times)[1],
    }
    assert batched["liv"].shape == batched["ocds"].shape == batched["cv"].shape == (2, 3, 5)
    assert batched["rho"].shape == (2, 3, 5, n_frames - 1)
    tol = dict(rtol=RTOL[dtype], atol=1e-12 if dtype == torch.float64 else 1e-5)
    for idx in np.ndindex(2, 3, 5):
        row_i = intensity[idx][None]
        torch.testing.assert_close(batched["liv"][idx], liv(row_i)[0], **tol)
        torch.testing.assert_close(batched["ocds"][idx], ocds(row_i, times, **kw)[0], **tol)
        torch.testing.assert_close(batched["cv"][idx], complex_variance(field[idx][None])[0], **tol)
        torch.testing.assert_close(batched["rho"][idx], lag_correlations(to_db(row_i), times)[1][0], **tol)
    # a single 1-D sequence works too
    torch.testing.assert_close(liv(intensity[0, 0, 0]), batched["liv"][0, 0, 0], **tol)


# ----------------------------------------------------------------------------------------------------------
# compute_metrics / summarize with empty resolution volumes (I = 0)
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
def test_compute_metrics_flags_zero_intensity_and_summarize_excludes_it(dtype):
    n_trials, n_systems, n_frames = 6, 2, 8
    rng = np.random.default_rng(14)
    z = rng.standard_normal((n_trials, n_systems, n_frames)) + 1j * rng.standard_normal((n_trials, n_systems, n_frames))
    signals = torch.from_numpy(z).to(torch.complex128 if dtype == torch.float64 else torch.complex64)
    signals[1, 0, 3] = 0
    signals[4, 1, 0] = 0
    signals[4, 0, :] = 0  # an all-empty trial
    times = _times(n_frames)
    analysis = Analysis(
        metrics=("liv", "ocds", "complex_variance", "autocorrelation"), ocds_delay_range_s=(0.2048, 0.6144)
    )
    out = compute_metrics(signals, times, analysis)
    zero = torch.zeros(n_trials, n_systems, dtype=torch.bool)
    zero[1, 0] = zero[4, 1] = zero[4, 0] = True
    assert torch.equal(out["zero_intensity"], zero)
    for key in ("liv", "ocds"):
        assert out[key].dtype == dtype and out[key].shape == (n_trials, n_systems)
        assert torch.isnan(out[key][zero]).all()
        assert torch.isfinite(out[key][~zero]).all()
    assert torch.isnan(out["autocorrelation"][zero]).all()
    assert torch.isfinite(out["autocorrelation"][~zero]).all()
    assert torch.isfinite(out["complex_variance"]).all()
    # the finite entries are the plain metrics of those rows
    intensity = signals.real**2 + signals.imag**2
    torch.testing.assert_close(out["liv"][~zero], liv(intensity[~zero]))
    torch.testing.assert_close(out["ocds"][~zero], ocds(intensity[~zero], times, delay_range_s=(0.2048, 0.6144)))

    summary = summarize(out, ["a", "b"])
    assert summary["a"]["zero_intensity_trials"] == 2
    assert summary["b"]["zero_intensity_trials"] == 1
    for s, name in enumerate(("a", "b")):
        for key in ("liv", "ocds"):
            values = out[key][:, s].double().numpy()
            ok = ~zero[:, s].numpy()
            row = summary[name][key]
            assert row["n"] == int(ok.sum())
            assert row["mean"] == pytest.approx(values[ok].mean(), rel=1e-12)
            assert row["sd"] == pytest.approx(values[ok].std(ddof=1), rel=1e-10)
            assert row["se"] == pytest.approx(values[ok].std(ddof=1) / math.sqrt(ok.sum()), rel=1e-10)
        assert summary[name]["complex_variance"]["n"] == n_trials


def test_compute_metrics_linear_scale_keeps_zero_rows():
    signals = torch.ones(3, 1, 8, dtype=torch.complex128)
    signals[:, 0, ::2] = 2.0
    signals[1, 0, 5] = 0
    analysis = Analysis(metrics=("ocds",), ocds_delay_range_s=(0.2048, 0.6144), ocds_scale="linear")
    out = compute_metrics(signals, _times(8), analysis)
    assert out["zero_intensity"][:, 0].tolist() == [False, True, False]
    assert torch.isfinite(out["ocds"]).all()  # linear intensity 0 is a valid value

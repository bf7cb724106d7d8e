"""Bulk-phase correction (torchdoct.measured.bulkphase, physics.md §12) and ``torchdoct maps --bulk-phase``.

Sequences with a simulated bulk motion of known size: a uniform random phase per frame and A-line
(0 at the first frame) multiplies a synthetic field of static and moving circular-Gaussian speckle in
white noise, so the truth (the same field without the bulk phase) is known exactly.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchdoct.bench.bulkphase import _synthetic, residual_rms
from torchdoct.cli import main
from torchdoct.measured.bulkphase import (
    BulkPhase,
    apply_bulk_phase,
    corrected_sequence,
    estimate_bulk_phase,
    phase_steps,
    predicted_residual_rms,
)
from torchdoct.measured.io import SequenceData, read_maps, validate_meta
from torchdoct.measured.maps import compute_maps
from torchdoct.sim.signature import signature

SYSTEM = {
    "name": "840nm",
    "wavelength_um": 0.84,
    "lateral_resolution_um": 4.9,
    "axial_resolution_um": 3.8,
    "refractive_index": 1.0,
}
DT = 0.2048


def cgauss(rng, shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / math.sqrt(2.0)


def make_field(t, z, x, *, snr_db, p_static=1.0, g=0.9, seed=0, flow_rows=None, delta=0.0, y=None):
    """Truth field [T, (Y), Z, X] (complex128): static speckle of power ``p_static``, AR(1) moving speckle of
    power ``1 − p_static`` and lag-1 correlation ``g``, white noise at ``snr_db`` (signal power 1). ``flow_rows``
    (slice of depth): those rows hold one speckle pattern whose phase grows by ``delta`` rad per frame (the Doppler
    ramp of scatterers moving deeper, ``δ = 2kn·v_z·Δt``; g1_phase_1 = −δ, torchdoct.sim.signature)."""
    rng = np.random.default_rng(seed)
    sp = (z, x) if y is None else (y, z, x)
    s = cgauss(rng, sp) * math.sqrt(p_static)
    m = cgauss(rng, sp) * math.sqrt(1.0 - p_static)
    frames = []
    for i in range(t):
        if i:
            m = g * m + math.sqrt(1 - g * g) * cgauss(rng, sp) * math.sqrt(1.0 - p_static)
        frames.append(s + m)
    e = np.array(frames)
    if flow_rows is not None:
        f = cgauss(rng, e[:, ..., flow_rows, :].shape[1:])
        e[..., flow_rows, :] = f[None] * np.exp(1j * delta * np.arange(t)).reshape(-1, *[1] * f.ndim)
    e = e + cgauss(rng, e.shape) * math.sqrt(10.0 ** (-snr_db / 10.0))
    return e


def bulk_phase_of(t, lines_shape, seed):
    rng = np.random.default_rng(seed + 1000)
    phi = rng.uniform(-math.pi, math.pi, (t, *lines_shape))
    phi[0] = 0.0
    return phi


def with_bulk(e, phi):
    """e [T, (Y), Z, X] times exp(iφ) with φ [T, (Y), X] broadcast over depth."""
    return e * np.expand_dims(np.exp(1j * phi), -2)


def make_seq(data, *, volume=False) -> SequenceData:
    meta = {
        "axes": "TYZX" if volume else "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0, **({"y": 3.0} if volume else {})},
        "frame_times_s": [DT * i for i in range(data.shape[0])],
        "system": SYSTEM,
    }
    return SequenceData(data=data, meta=validate_meta(meta, data.shape), source="test.npy")


def residual(bp: BulkPhase, phi: np.ndarray) -> np.ndarray:
    """Corrected minus true phase per frame and A-line (the corrected field is truth·exp(−i·r)); wrapped."""
    return np.angle(np.exp(1j * (bp.phase - phi)))


def features(e: np.ndarray, names):
    """Signature features [..., F] of a field [T, Z, X] per pixel."""
    x = torch.from_numpy(np.ascontiguousarray(np.moveaxis(e, 0, -1)))
    return signature(x, [DT * i for i in range(e.shape[0])], names=names)[1].numpy()


# ----------------------------------------------------------------------------------------------------------
# residual phase error against SNR: the first-order theory of physics.md §12
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("snr_db", [10.0, 20.0, 30.0, 40.0])
def test_weighted_mean_residual_equals_the_first_order_prediction(snr_db):
    x, phi = _synthetic(800, 64, 32, snr_db, seed=int(snr_db))
    steps, none = phase_steps(x, "weighted-mean")
    assert not none.any()
    rms, se = residual_rms(steps, phi)
    pred = predicted_residual_rms(snr_db, 64, 32)
    assert abs(rms - pred) <= 4 * se, (rms, se, pred)


@pytest.mark.parametrize("snr_db", [10.0, 20.0, 30.0, 40.0])
def test_histogram_residual_is_within_five_percent_of_the_weighted_mean(snr_db):
    """Trimming pixels pair by pair breaks the exact cancellation of the frame errors between consecutive
    steps: the histogram method pays a few per cent (measured 1.00-1.03 of the prediction, 2000 A-lines)."""
    x, phi = _synthetic(800, 64, 32, snr_db, seed=int(snr_db))
    rms, se = residual_rms(phase_steps(x, "histogram")[0], phi)
    pred = predicted_residual_rms(snr_db, 64, 32)
    assert pred - 4 * se <= rms <= 1.05 * pred + 4 * se, (rms, se, pred)


def test_residual_at_high_snr_is_one_over_root_two_n_snr():
    """At high SNR the random-walk term vanishes: residual → 1/√(2·N_z·SNR) (fixed-amplitude A-line)."""
    snr = 10.0**4.0
    assert predicted_residual_rms(40.0, 64, 32, speckle=False) == pytest.approx(
        math.sqrt((1 - 1 / 32) / (2 * 64 * snr)), rel=3e-3
    )


def test_noise_only_rows_add_only_the_random_walk_term_and_rows_or_median_mask_skip_them():
    """An A-line with signal in its upper 32 rows and noise only in the lower 32 (SNR 10 dB in the signal):
    all 64 rows, the signal rows only (rows 0:32) and the median mask, against the theory."""
    t, n, lines, snr_db = 32, 32, 800, 10.0
    g = torch.Generator().manual_seed(7)

    def cn(*shape):
        return torch.complex(
            torch.randn(*shape, generator=g, dtype=torch.float64), torch.randn(*shape, generator=g, dtype=torch.float64)
        ) / math.sqrt(2.0)

    sig = torch.cat([cn(lines, n), torch.zeros(lines, n, dtype=torch.complex128)], -1)
    noise = cn(t, lines, 2 * n) * math.sqrt(10.0 ** (-snr_db / 10.0))
    phi = (torch.rand(t, lines, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    phi[0] = 0
    x = ((sig[None] + noise) * torch.exp(1j * phi)[..., None]).to(torch.complex64)
    rms_all, se_all = residual_rms(phase_steps(x, "weighted-mean")[0], phi)
    rms_top, se_top = residual_rms(phase_steps(x[..., :n], "weighted-mean")[0], phi)
    rms_med, _ = residual_rms(phase_steps(x, "weighted-mean", mask="median")[0], phi)
    pred_all = predicted_residual_rms(snr_db, n, t, noise_only=n)
    pred_top = predicted_residual_rms(snr_db, n, t)
    assert abs(rms_all - pred_all) <= 4 * se_all, (rms_all, pred_all)
    assert abs(rms_top - pred_top) <= 4 * se_top, (rms_top, pred_top)
    assert pred_all > 1.1 * pred_top  # the noise floor costs something here ...
    assert rms_med < rms_all - 4 * se_all  # ... and the median mask avoids most of it


def test_moving_speckle_alone_leaves_a_random_walk_of_the_predicted_step():
    """An A-line of moving speckle only (AR(1), lag-1 correlation g, no static part, no noise): the estimate
    cannot tell the bulk phase from the A-line's own mean phase evolution and removes it too; the residual is
    a random walk of variance (1 − g²)/(2g²(N_z − 1)) per step (physics.md §12)."""
    t, n, lines, gc = 16, 48, 1500, 0.9
    rng = np.random.default_rng(3)
    m = cgauss(rng, (lines, n))
    frames = [m]
    for _ in range(t - 1):
        m = gc * m + math.sqrt(1 - gc * gc) * cgauss(rng, (lines, n))
        frames.append(m)
    e = np.array(frames)  # [T, L, Z]
    phi = bulk_phase_of(t, (lines,), 3)
    x = torch.from_numpy(e * np.exp(1j * phi)[..., None])
    steps, _ = phase_steps(x, "weighted-mean")
    est = np.concatenate([np.zeros((1, lines)), np.cumsum(steps.numpy(), 0)])
    r = np.angle(np.exp(1j * (est - phi)))  # [T, L], r[0] = 0
    var = (r * r).mean(1)
    i = np.arange(t)
    slope = float((i * var).sum() / (i * i).sum())
    pred = (1 - gc * gc) / (2 * gc * gc * (n - 1))
    # SE of the slope from the spread over A-lines of the per-line slope
    per_line = (i[:, None] * r * r).sum(0) / (i * i).sum()
    se = float(per_line.std() / math.sqrt(lines))
    assert abs(slope - pred) <= 4 * se, (slope, se, pred)


@pytest.mark.parametrize("n_z,p_static,seed", [(96, 0.85, 1), (32, 0.7, 2), (64, 0.5, 3)])
def test_static_plus_moving_residual_matches_the_prediction(n_z, p_static, seed):
    """Static speckle plus AR(1) moving speckle (g = 0.95) at 30 dB: the moving part's projection on the static
    field and the random walk of its own products add to the noise terms (physics.md §12.3)."""
    t, x, g = 16, 600, 0.95
    truth = make_field(t, n_z, x, snr_db=30.0, p_static=p_static, g=g, seed=seed)
    phi = bulk_phase_of(t, (x,), seed)
    lines = torch.from_numpy(np.ascontiguousarray(np.moveaxis(with_bulk(truth, phi), 1, 2)))  # [T, X, Z]
    rms, se = residual_rms(phase_steps(lines, "weighted-mean")[0], torch.from_numpy(phi))
    pred = predicted_residual_rms(30.0, n_z, t, moving_fraction=1 - p_static, moving_g=g)
    assert abs(rms - pred) <= 4 * se, (rms, se, pred)
    assert pred > 3 * predicted_residual_rms(30.0, n_z, t)  # the moving part dominates the noise here


def test_stable_mask_uses_only_the_static_rows_of_a_layered_a_line():
    """48 rows of static speckle above 48 rows of moving speckle (AR(1), g = 0.9), 30 dB: with every pixel the
    moving rows add their terms (physics.md §12.3); the stable mask (temporal intensity contrast <= 0.05, a
    bulk-phase-invariant property) keeps the static rows only, and the residual is the static-only prediction."""
    t, x, n, g = 32, 600, 48, 0.9
    rng = np.random.default_rng(21)
    s = cgauss(rng, (x, n))
    m = cgauss(rng, (x, n))
    frames = []
    for i in range(t):
        if i:
            m = g * m + math.sqrt(1 - g * g) * cgauss(rng, (x, n))
        frames.append(np.concatenate([s, m], -1))
    e = np.array(frames) + cgauss(rng, (t, x, 2 * n)) * math.sqrt(1e-3)
    phi = bulk_phase_of(t, (x,), 21)
    lines = torch.from_numpy(e * np.exp(1j * phi)[..., None])
    truth = torch.from_numpy(phi)
    rms_s, se_s = residual_rms(phase_steps(lines, "weighted-mean", mask="stable")[0], truth)
    rms_a, se_a = residual_rms(phase_steps(lines, "weighted-mean", mask="all")[0], truth)
    pred = predicted_residual_rms(30.0, n, t)
    assert abs(rms_s - pred) <= 4 * se_s, (rms_s, se_s, pred)
    assert rms_a > 10 * rms_s


def test_rendered_phantom_with_moving_regions():
    """The shipped vessel-slab phantom (static tissue, a slowly diffusing layer, a flow channel, an empty
    layer below), rendered, with white noise 30 dB below the static tissue's mean intensity and a random
    bulk phase per frame and A-line. With every pixel the estimate also removes the phase the A-line's own
    moving speckle shares (~0.1 rad here), which lowers g1_4 of the static tissue measurably; the stable
    mask removes only the bulk phase (residual < 0.01 rad) and every region's mean field features equal
    those without bulk motion within the Monte Carlo error of that mean."""
    from torchdoct import load_phantom, render

    res = render(load_phantom("vessel-slab"), seed=1, threads=1)
    e = res.data[0].numpy().astype(np.complex128)
    lab = res.labels
    p = float((np.abs(e) ** 2).mean(0)[lab == 1].mean())
    rng = np.random.default_rng(0)
    truth = e + cgauss(rng, e.shape) * math.sqrt(p * 1e-3)
    phi = bulk_phase_of(e.shape[0], (e.shape[2],), 0)
    seq = make_seq(with_bulk(truth, phi).astype(np.complex64))
    names = ("g1_1", "g1_4", "phase_ramp")
    f_true = features(truth.astype(np.complex64), names)
    rms = {}
    for mask in ("all", "stable"):
        bp = estimate_bulk_phase(seq, "histogram", mask=mask)
        r = residual(bp, phi)
        rms[mask] = float(np.sqrt(((r - r.mean(0)) ** 2).mean()))
        if mask == "stable":
            f = features(corrected_sequence(seq, bp).data, names)
            for code in (1, 2, 4):  # static, diffusion, flow
                sel = lab == code
                for k, name in enumerate(names):
                    d = f[sel][:, k] - f_true[sel][:, k]
                    sd = float(f_true[sel][:, k].std())
                    assert abs(float(d.mean())) <= 3 * sd / math.sqrt(int(sel.sum())), (code, name, d.mean(), sd)
    assert rms["stable"] < 0.01 and rms["all"] > 5 * rms["stable"], rms


# ----------------------------------------------------------------------------------------------------------
# the corrected field: features against the truth
# ----------------------------------------------------------------------------------------------------------
FIELD = ("g1_1", "g1_2", "g1_4", "phase_ramp")
INTENSITY = ("rho_lin_1", "rho_lin_4", "lin_contrast", "db_variance")


@pytest.mark.parametrize("method", ["weighted-mean", "histogram"])
def test_field_features_after_correction_equal_those_without_bulk_motion(method):
    t, z, x = 24, 48, 150
    truth = make_field(t, z, x, snr_db=30.0, p_static=0.6, g=0.9, seed=11)
    phi = bulk_phase_of(t, (x,), 11)
    seq = make_seq(with_bulk(truth, phi).astype(np.complex64))
    bp = estimate_bulk_phase(seq, method)
    assert bp.phase.shape == (t, x) and bp.pairs_without_signal == 0
    corr = corrected_sequence(seq, bp)
    assert corr.meta["bulk_phase"]["method"] == method and corr.data.dtype == np.complex64
    f_true = features(truth.astype(np.complex64), FIELD)
    f_bulk = features(seq.data, FIELD)
    f_corr = features(corr.data, FIELD)
    r = residual(bp, phi)  # [T, X]
    for k, name in enumerate(FIELD):
        d = f_corr[..., k] - f_true[..., k]
        sd = float(np.std(f_true[..., k]))
        n_pix = d.size
        # the mean over pixels equals the truth's within the Monte Carlo error of that mean
        assert abs(float(d.mean())) <= 3 * sd / math.sqrt(n_pix), (name, d.mean(), sd)
        # and each pixel's feature moves by far less than its own sampling spread
        assert float(np.abs(d).mean()) <= 0.05 * sd, (name, np.abs(d).mean(), sd)
        # while the bulk phase destroys it
        assert abs(float((f_bulk[..., k] - f_true[..., k]).mean())) > 20 * sd / math.sqrt(n_pix), name
        if name.startswith("g1_"):  # Cauchy-Schwarz: |Δ|g1(m)|| <= max_i |r_{i+m} − r_i| of the A-line
            m = int(name.split("_")[1])
            bound = np.abs(r[m:] - r[:-m]).max(0)  # [X]
            assert (np.abs(d) <= bound[None, :] + 2e-5).all(), name


def test_intensity_features_and_maps_are_unchanged():
    t, z, x = 20, 40, 60
    truth = make_field(t, z, x, snr_db=20.0, p_static=0.5, seed=2)
    phi = bulk_phase_of(t, (x,), 2)
    seq = make_seq(with_bulk(truth, phi).astype(np.complex64))
    bp = estimate_bulk_phase(seq, "histogram")
    corr = corrected_sequence(seq, bp)
    # |E|² equal to the rounding of complex64
    i0, i1 = np.abs(seq.data.astype(np.complex128)) ** 2, np.abs(corr.data.astype(np.complex128)) ** 2
    np.testing.assert_allclose(i1, i0, rtol=4 * np.finfo(np.float32).eps, atol=0)
    np.testing.assert_allclose(features(corr.data, INTENSITY), features(seq.data, INTENSITY), rtol=2e-5, atol=2e-5)
    # maps at the original resolution do not read the phase: bit for bit
    a = compute_maps(seq, ["original"], metrics=("liv", "ocds", "mean_db", "aliv"))
    b = compute_maps(seq, ["original"], metrics=("liv", "ocds", "mean_db", "aliv"), bulk_phase=bp)
    np.testing.assert_array_equal(a.maps, b.maps)
    assert "bulk_phase" not in a.meta and b.meta["bulk_phase"]["reference"] == "consecutive frames"


def test_reduced_maps_after_correction_match_the_truth():
    """A lateral reduction adds neighbouring A-lines: with the bulk phase it decorrelates the reduced speckle
    (LIV up by ~20 dB², OCDS collapses); corrected, the reduced maps equal those of the field without bulk
    motion up to the residual (here 0.014 rad RMS: 85 % static power, 96 rows, 30 dB). The median over pixels
    is compared: a dark reduced pixel turns a small phase error into a large dB change."""
    t, z, x = 16, 96, 80
    truth = make_field(t, z, x, snr_db=30.0, p_static=0.85, g=0.95, seed=4).astype(np.complex64)
    phi = bulk_phase_of(t, (x,), 4)
    seq_t, seq_b = make_seq(truth), make_seq(with_bulk(truth, phi).astype(np.complex64))
    res = ["lateral=18"]
    m_t = compute_maps(seq_t, res)
    m_b = compute_maps(seq_b, res)
    m_c = compute_maps(seq_b, res, bulk_phase="weighted-mean")
    assert m_c.meta["bulk_phase"]["method"] == "weighted-mean"
    for ch in ("liv@lateral=18", "ocds@lateral=18", "mean_db@lateral=18"):
        sd = float(np.std(m_t[ch]))
        err_c = float(np.median(np.abs(m_c[ch] - m_t[ch])))
        err_b = float(np.median(np.abs(m_b[ch] - m_t[ch])))
        assert err_c <= 0.1 * sd and err_b >= 10 * err_c, (ch, err_c, err_b, sd)


def test_flow_layer_doppler_ramp_survives_the_histogram_and_is_biased_by_the_weighted_mean():
    """A flowing layer over 6 of 64 rows (9 %) with a Doppler step δ = 0.8 rad per frame in static tissue,
    30 dB. Histogram: the layer keeps g1_phase_1 = −δ and the static tissue 0. Weighted mean: the step is
    b = arg(Σ_static |E_{i+1}E_i| + Σ_flow |E_{i+1}E_i|·e^{iδ}) ≈ w_f·δ, so the layer's rate shrinks to δ − b and
    the tissue acquires −b (g1_phase_1 = −δ + b and +b)."""
    t, z, x, delta = 24, 64, 160, 0.8
    rows = slice(28, 34)
    truth = make_field(t, z, x, snr_db=30.0, p_static=1.0, seed=5, flow_rows=rows, delta=delta)
    phi = bulk_phase_of(t, (x,), 5)
    seq = make_seq(with_bulk(truth, phi).astype(np.complex64))
    names = ("g1_phase_1", "phase_ramp")
    flow = np.zeros(z, bool)
    flow[rows] = True
    out = {}
    for method in ("histogram", "weighted-mean"):
        bp = estimate_bulk_phase(seq, method)
        f = features(corrected_sequence(seq, bp).data, names)
        out[method] = (bp, f)
    f_true = features(truth.astype(np.complex64), names)
    # truth: the layer turns by δ per frame, the tissue not at all
    assert abs(float(f_true[flow, :, 0].mean()) + delta) < 0.01
    bp, f = out["histogram"]
    for sel, want in ((flow, -delta), (~flow, 0.0)):
        v = f[sel, :, 0]
        se = float(v.std()) / math.sqrt(v.size)
        assert abs(float(v.mean()) - want) <= 4 * se + 1e-3, (want, v.mean(), se)
    assert float(f[flow, :, 1].mean()) > 0.99  # phase_ramp: a constant rate
    # weighted mean: the predicted biased step per A-line from the truth's amplitudes
    i_true = np.abs(truth[:-1]) * np.abs(truth[1:])  # [T-1, Z, X]
    b = np.angle(i_true[:, ~flow].sum(1) + i_true[:, flow].sum(1) * np.exp(1j * delta))  # [T-1, X]
    bp_w, f_w = out["weighted-mean"]
    steps = np.diff(bp_w.phase, axis=0) - np.diff(phi, axis=0)
    err = np.angle(np.exp(1j * (steps - b)))
    noise = predicted_residual_rms(30.0, z, t) * math.sqrt(2)  # RMS of one step's error, about
    assert float(np.sqrt((err**2).mean())) < 2 * noise, (np.sqrt((err**2).mean()), noise)
    bias = float(b.mean())
    assert bias > 0.03  # a visible share of δ is taken from the layer ...
    assert abs(float(f_w[flow, :, 0].mean()) - (-delta + bias)) < 0.01
    assert abs(float(f_w[~flow, :, 0].mean()) - bias) < 0.01  # ... and given to the tissue
    assert float(f_w[flow, :, 1].mean()) > 0.99  # the ramp stays linear: its rate is what is biased


# ----------------------------------------------------------------------------------------------------------
# volumes, slabs, options, refusals
# ----------------------------------------------------------------------------------------------------------
def test_volume_per_y_x_and_slab_invariance():
    t, y, z, x = 12, 7, 32, 20  # 7 B-scans × 3 µm: the field of view along y holds the lateral=18 target
    truth = make_field(t, z, x, snr_db=30.0, seed=8, y=y).astype(np.complex64)
    phi = bulk_phase_of(t, (y, x), 8)
    seq = make_seq(with_bulk(truth, phi).astype(np.complex64), volume=True)
    for method in ("weighted-mean", "histogram"):
        a = estimate_bulk_phase(seq, method)
        b = estimate_bulk_phase(seq, method, slab_elements=1)  # one B-scan per slab
        np.testing.assert_array_equal(a.phase, b.phase)
        assert a.phase.shape == (t, y, x)
        r = residual(a, phi)
        r = r - r.mean(0)
        assert np.abs(r).max() < 5 * predicted_residual_rms(30.0, z, t), np.abs(r).max()
    bs = make_seq(with_bulk(truth[:, 0], phi[:, 0]).astype(np.complex64))
    np.testing.assert_array_equal(
        estimate_bulk_phase(bs, "histogram").phase, estimate_bulk_phase(bs, "histogram", slab_elements=1).phase
    )  # one A-line per slab
    # maps with the correction do not depend on the slab size either
    m1 = compute_maps(seq, ["lateral=18"], bulk_phase=a)
    m2 = compute_maps(seq, ["lateral=18"], bulk_phase=a, slab_elements=5000)
    np.testing.assert_allclose(m1.maps, m2.maps, rtol=1e-5, atol=1e-5)


def test_rows_option_equals_the_cropped_sequence_and_apply_is_the_phasor():
    t, z, x = 10, 40, 12
    truth = make_field(t, z, x, snr_db=20.0, seed=9).astype(np.complex64)
    seq = make_seq(truth)
    a = estimate_bulk_phase(seq, "weighted-mean", rows="5:25")
    b = estimate_bulk_phase(make_seq(np.ascontiguousarray(truth[:, 5:25])), "weighted-mean")
    np.testing.assert_array_equal(a.phase, b.phase)
    assert a.meta()["rows"] == [5, 25]
    out = apply_bulk_phase(truth, a, "TZX")
    np.testing.assert_allclose(out, truth * np.exp(-1j * a.phase)[:, None, :], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(corrected_sequence(seq, a).data, out)
    assert estimate_bulk_phase(seq, "histogram", mask="stable").meta()["mask"] == "stable:0.05"
    assert estimate_bulk_phase(seq, "histogram", mask=" Stable:0.2").meta()["mask"] == "stable:0.2"
    thr = estimate_bulk_phase(seq, "weighted-mean", mask=-200.0)  # a threshold below every pixel = all
    np.testing.assert_array_equal(thr.phase, estimate_bulk_phase(seq, "weighted-mean").phase)


def test_empty_a_lines_get_zero_steps_and_are_counted():
    t, z, x = 6, 16, 5
    truth = make_field(t, z, x, snr_db=30.0, seed=10).astype(np.complex64)
    truth[:, :, 2] = 0
    truth[3, :, 4] = np.nan
    bp = estimate_bulk_phase(make_seq(truth), "histogram")
    assert np.all(bp.phase[:, 2] == 0)
    assert bp.pairs_without_signal == (t - 1) + 2  # A-line 2 every pair; A-line 4 the pairs (2, 3) and (3, 4)
    assert np.isfinite(bp.phase).all()


def test_refusals_name_the_file_and_the_fix():
    inten = make_seq(np.abs(make_field(6, 8, 4, snr_db=20.0)).astype(np.float32) ** 2)
    with pytest.raises(ValueError, match=r"test\.npy holds intensity only.*complex"):
        estimate_bulk_phase(inten, "weighted-mean")
    with pytest.raises(ValueError, match=r"test\.npy holds intensity only"):
        compute_maps(inten, ["original"], metrics=["liv"], bulk_phase="histogram")
    seq = make_seq(make_field(6, 8, 4, snr_db=20.0).astype(np.complex64))
    with pytest.raises(ValueError, match="must be one of weighted-mean, histogram"):
        estimate_bulk_phase(seq, "sd")
    with pytest.raises(ValueError, match=r"all, median, stable\[:C\] or a dB threshold"):
        estimate_bulk_phase(seq, "weighted-mean", mask="brightest")
    with pytest.raises(ValueError, match="stable:C needs a contrast C > 0"):
        estimate_bulk_phase(seq, "weighted-mean", mask="stable:-1")
    with pytest.raises(ValueError, match=r"0 <= Z0 < Z1 <= 8"):
        estimate_bulk_phase(seq, "weighted-mean", rows="4:9")
    other = estimate_bulk_phase(make_seq(make_field(6, 8, 5, snr_db=20.0).astype(np.complex64)), "weighted-mean")
    with pytest.raises(ValueError, match="does not match the sequence"):
        compute_maps(seq, ["original"], metrics=["liv"], bulk_phase=other)


# ----------------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------------
def write_npy(tmp_path, name, data):
    np.save(tmp_path / f"{name}.npy", data)
    meta = {
        "axes": "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0},
        "frame_times_s": [DT * i for i in range(data.shape[0])],
        "system": SYSTEM,
    }
    (tmp_path / f"{name}.json").write_text(json.dumps(meta))
    return str(tmp_path / f"{name}.npy")


def test_cli_maps_bulk_phase_with_signature(tmp_path, capsys):
    t, z, x = 12, 24, 16
    truth = make_field(t, z, x, snr_db=40.0, p_static=1.0, seed=12).astype(np.complex64)
    phi = bulk_phase_of(t, (x,), 12)
    src = write_npy(tmp_path, "seq", with_bulk(truth, phi).astype(np.complex64))
    out = tmp_path / "m.npz"
    rc = main(
        [
            "maps",
            src,
            "--resolution",
            "original",
            "--resolution",
            "lateral=18",
            "--signature",
            "--bulk-phase",
            "histogram",
            "--bulk-phase-mask",
            "median",
            "--bulk-phase-rows",
            "2:22",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "bulk phase (histogram, mask median)" in text
    m = read_maps(out)
    info = m.meta["bulk_phase"]
    assert info["method"] == "histogram" and info["reference"] == "consecutive frames"
    assert info["mask"] == "median" and info["rows"] == [2, 22]
    # a static sample at 40 dB: the corrected field is coherent over the frames (the bulk-corrupted one is not)
    assert float(np.median(m["g1_1@original"])) > 0.99 and float(np.median(m["g1_4@lateral=18"])) > 0.99


def test_cli_maps_bulk_phase_errors(tmp_path, capsys):
    d = make_field(
        8, 8, 4, snr_db=20.0
    )  # 8 frames: the default OCDS delays (to 6 lags) rest on 2+ pairs.astype(np.complex64)
    src = write_npy(tmp_path, "seq", d)
    isrc = write_npy(tmp_path, "inten", (np.abs(d) ** 2).astype(np.float32))
    cases = [
        (["maps", isrc, "--bulk-phase", "weighted-mean"], "inten.npy holds intensity only"),
        (["maps", src, "--bulk-phase-mask", "median"], "need --bulk-phase METHOD"),
        (["maps", src, "--bulk-phase", "histogram", "--bulk-phase-mask", "x"], "all, median, stable[:C] or a dB"),
        (["maps", src, "--bulk-phase", "histogram", "--bulk-phase-rows", "9"], "Z0:Z1"),
    ]
    for argv, msg in cases:
        rc = main(argv + ["--out", str(tmp_path / "o.npz"), "--no-progress"])
        err = capsys.readouterr().err
        assert rc != 0 and msg in err and "Traceback" not in err, (argv, err)
        assert not (tmp_path / "o.npz").exists()


def test_cli_bench_bulk_phase(tmp_path, capsys):
    out = tmp_path / "b.json"
    assert main(["bench", "bulk-phase", "--snr-db", "20", "--lines", "200", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert [r["method"] for r in res["rows"]] == ["weighted-mean", "histogram"]
    assert all(0.8 < r["ratio"] < 1.2 for r in res["rows"])
    assert "predicted" in capsys.readouterr().out


def test_bench_on_a_rendered_phantom():
    from torchdoct.bench.bulkphase import bench_bulk_phase_phantom, format_bench_bulk_phase

    ph = bench_bulk_phase_phantom("vessel-slab", snr_db=(30.0,), methods=("histogram",), masks=("all", "stable"))
    rows = {r["mask"]: r for r in ph["rows"]}
    assert set(rows) == {"all", "stable:0.05"}
    assert rows["stable:0.05"]["residual_rms_rad"] < 0.01 < rows["all"]["residual_rms_rad"]
    assert abs(rows["stable:0.05"]["g1_4_static_z"]) < 3
    text = format_bench_bulk_phase({"lines": 1, "n_z": 1, "frames": 1, "rows": [], "phantom": ph})
    assert "vessel-slab" in text and "stable:0.05" in text

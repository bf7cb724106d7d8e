"""Speckle-motion features (torchdoct.sim.speckle) against the closed forms of docs/concepts/speckle-motion.md.

The synthetic fields are circular Gaussian speckle (N_eff → ∞) of the Gaussian amplitude PSF of the
840-nm system (conventions), periodic and band-limited on a 1-µm grid, so a translation by any vector is
exact (a phase ramp in the Fourier domain): E(r, t) = E₀(r − d(t)). Tolerances: z = 3.5 standard errors of
the mean over independent fields (one window, the centre pixel's, per field).
"""

from __future__ import annotations

import math

import pytest
import torch
from _speckle_fields import translated_speckle

from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um
from torchdoct.sim.speckle import (
    default_speckle_features,
    dynamic_speckle_features,
    halo_pixels,
    is_dynamic_feature,
    parse_speckle_feature,
    speckle_features,
    speckle_motion,
)

Z_SE = 3.5
DT = 0.2048
T = 32
S_X = amplitude_sigma_lateral_um(4.9)
S_Z = amplitude_sigma_axial_um(3.8)
PITCH = {"z": 1.0, "x": 1.0, "y": 1.0}


def centre_features(field: torch.Tensor, names, ndim: int = 2, window: int = 9) -> torch.Tensor:
    """Features of the centre pixel of each field (a crop that holds its window and offsets): ``[N, F]``."""
    h = halo_pixels(window) + 1
    sp = field.shape[-ndim:]
    sl = tuple(slice(n // 2 - h, n // 2 + h + 1) for n in sp)
    crop = field[(slice(None), slice(None), *sl)]
    _, f = speckle_motion(crop, PITCH, DT, names, window=window, ndim=ndim)
    return f[(slice(None), slice(None), *([h] * ndim))]


def _mean_se(v: torch.Tensor) -> tuple[float, float]:
    return float(v.mean()), float(v.std() / math.sqrt(v.numel()))


@pytest.fixture(scope="module")
def flow_bscan():
    v = (0.2, 0.25)  # µm/s along z (deeper), x

    def d(i):
        return (v[0] * i * DT, v[1] * i * DT)

    return v, translated_speckle(48, (32, 32), (S_Z, S_X), d, seed=11)


def test_translated_speckle_peak_offset_is_v_tau(flow_bscan):
    v, field = flow_bscan
    names = ("xc_shift_z_16", "xc_shift_x_16", "xc_velocity_z", "xc_velocity_x")
    f = centre_features(field, names)
    tau = 16 * DT
    for i, expect in enumerate((v[0] * tau, v[1] * tau, v[0], v[1])):
        mean, se = _mean_se(f[:, i])
        assert abs(mean - expect) < Z_SE * se, (names[i], mean, expect, se)
        assert se < 0.2 * abs(expect)  # the test can tell the offset from zero


def test_translated_gaussian_speckle_keeps_correlation_one_at_its_peak():
    """ρ(Δ, τ) = exp(−(Δ_x − d_x)²/(2s_x²) − (Δ_z − d_z)²/(2s_z²)) for Gaussian speckle: the centred value
    decays as exp(−d_x²/(2s_x²) − d_z²/(2s_z²)), the peak stays 1. The window's ratio estimator is biased
    by O(1/N_ind) (N_ind the window's independent speckle count, classifier.pooling's convention;
    docs/concepts/speckle-motion.md §6), so the tolerance is z·SE + 1/N_ind at a 25-pixel window."""
    from classifier.pooling import effective_count

    v, w = (0.2, 0.25), 25

    def d(i):
        return (v[0] * i * DT, v[1] * i * DT)

    field = translated_speckle(48, (40, 40), (S_Z, S_X), d, seed=21)
    n_ind = effective_count(w, 1.0, S_X) * effective_count(w, 1.0, S_Z)
    f = centre_features(field, ("xc_centre_8", "xc_centre_16", "xc_peak_16"), window=w)
    for i, m in enumerate((8, 16)):
        dz, dx = v[0] * m * DT, v[1] * m * DT
        expect = math.exp(-(dx**2) / (2 * S_X**2) - dz**2 / (2 * S_Z**2))
        mean, se = _mean_se(f[:, i])
        assert abs(mean - expect) < Z_SE * se + 1.0 / n_ind, (m, mean, expect, se)
    mean, se = _mean_se(f[:, 2])
    assert abs(mean - 1.0) < Z_SE * se + 1.0 / n_ind, (mean, se)


def test_direction_symmetric_motion_has_no_antisymmetric_part(flow_bscan):
    """Two independent patterns moving at +v and −v (a direction-symmetric motion): the signed offset and
    velocity vanish in expectation, and the moving share stays well below translation's."""
    v, field = flow_bscan

    def back(i):
        return (-v[0] * i * DT, -v[1] * i * DT)

    field2 = translated_speckle(48, (32, 32), (S_Z, S_X), back, seed=12)
    names = ("xc_shift_z_16", "xc_shift_x_16", "xc_velocity_z", "xc_velocity_x", "xc_share_16")
    sym = centre_features(field + field2, names)
    for i in range(4):
        mean, se = _mean_se(sym[:, i])
        assert abs(mean) < Z_SE * se, (names[i], mean, se)
    one = centre_features(field, names)
    m_sym, se_sym = _mean_se(sym[:, 4])
    m_one, se_one = _mean_se(one[:, 4])
    assert m_one - m_sym > Z_SE * math.hypot(se_sym, se_one)


def test_mirrored_field_mirrors_every_signed_feature(flow_bscan):
    _, field = flow_bscan
    x = field[:4, :, 8:25, 8:25]
    names = speckle_features(2)
    _, f = speckle_motion(x, PITCH, DT, names)
    _, g = speckle_motion(x.flip(-1), PITCH, DT, names)
    g = g.flip(-1)
    for i, n in enumerate(names):
        _, axis, _ = parse_speckle_feature(n)
        sign = -1.0 if axis == "x" else 1.0
        torch.testing.assert_close(g[:, i], sign * f[:, i], rtol=1e-9, atol=1e-9, msg=n)


def test_features_do_not_depend_on_the_field_scale_or_batch(flow_bscan):
    _, field = flow_bscan
    x = field[:3, :, 8:25, 8:25]
    names = speckle_features(2)
    _, f = speckle_motion(x, PITCH, DT, names)
    _, g = speckle_motion(x * 1e-7, PITCH, DT, names)
    torch.testing.assert_close(g, f, rtol=1e-9, atol=1e-9)
    _, one = speckle_motion(x[1:2], PITCH, DT, names)
    assert torch.equal(one[0], f[1])  # each field's features are its own, whatever the batch
    _, again = speckle_motion(x, PITCH, DT, names)
    assert torch.equal(again, f)
    _, inten = speckle_motion(x.abs() ** 2, PITCH, DT, names)  # the intensity gives the same numbers
    torch.testing.assert_close(inten, f, rtol=1e-9, atol=1e-9)


def test_volume_sees_the_offset_along_y():
    v = (0.3, 0.0, 0.0)  # µm/s along y, z, x: flow across the B-scans

    def d(i):
        return (v[0] * i * DT, v[1] * i * DT, v[2] * i * DT)

    field = translated_speckle(24, (16, 16, 16), (S_X, S_Z, S_X), d, seed=5)
    f = centre_features(field, ("xc_velocity_y", "xc_velocity_z", "xc_velocity_x"), ndim=3, window=5)
    for i, expect in enumerate(v):
        mean, se = _mean_se(f[:, i])
        assert abs(mean - expect) < Z_SE * se, (i, mean, expect, se)
    assert abs(float(f[:, 0].mean())) > 5 * float(f[:, 0].std() / math.sqrt(24))


def test_invalid_pixel_is_nan_and_leaves_its_neighbours_defined(flow_bscan):
    _, field = flow_bscan
    x = (field[:1, :, 8:25, 8:25].abs() ** 2).clone()
    x[0, 5, 8, 8] = 0.0
    _, f = speckle_motion(x, PITCH, DT)
    assert torch.isnan(f[0, :, 8, 8]).all()
    assert torch.isfinite(f[0, :, 8, 9]).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"window": 4}, "odd"),
        ({"max_offset": 0}, "max_offset"),
        ({"names": ("xc_centre_31",)}, "lag"),
        ({"names": ("xc_shift_y_2",)}, "no axis"),
        ({"names": ("xc_bogus_2",)}, "unknown speckle feature"),
    ],
)
def test_bad_arguments_are_refused(kwargs, match):
    x = torch.rand(1, T, 12, 12, generator=torch.Generator().manual_seed(0)) + 0.1
    with pytest.raises(ValueError, match=match):
        speckle_motion(x, PITCH, DT, **kwargs)


def test_missing_pitch_is_refused():
    with pytest.raises(ValueError, match="pitch"):
        speckle_motion(torch.ones(1, T, 12, 12), {"z": 1.0}, DT)


def test_default_features_are_named_with_units():
    names = default_speckle_features(2)
    assert "xc_speed" in names and "xc_share_16" in names
    assert {parse_speckle_feature(n)[0] for n in names} == {"centre", "peak", "share", "asym", "shift", "speed"}


# ---- the dynamic field (docs/concepts/speckle-motion.md §3 (f)) ------------------------------------------
DYN = ("xcd_peak_2", "xcd_centre_2", "xcd_shift_z_2", "xcd_shift_x_2")


def _fast_flow_with_static(static_amplitude: float, seed: int):
    """A flow fast enough to renew its pattern several times over the acquisition (0.8/1.0 µm/s along z/x,
    3-4 PSF widths of travel), plus frozen speckle of ``static_amplitude²`` times its power."""
    v = (0.8, 1.0)
    flow = translated_speckle(32, (32, 32), (S_Z, S_X), lambda i: (v[0] * i * DT, v[1] * i * DT), seed=seed)
    static = translated_speckle(32, (32, 32), (S_Z, S_X), lambda i: (0.0, 0.0), seed=seed + 100, n_frames=1)
    return v, flow, flow + static_amplitude * static


def test_the_dynamic_field_of_static_tissue_plus_motion_is_that_of_the_motion_alone():
    """A static population's field is its temporal mean, so removing the mean removes it exactly: every
    feature of the dynamic field is the same with and without it (to rounding)."""
    _, flow, mixed = _fast_flow_with_static(2.0, seed=41)
    names = (*DYN, "xcd_share_8", "xcd_asym_8", "xcd_shift_16")
    a = centre_features(flow, names)
    b = centre_features(mixed, names)
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


def test_static_tissue_holds_the_peak_at_the_centre_and_the_dynamic_field_shows_the_flow_moving():
    """Frozen speckle of four times the flow's power (§3 (d)): the field's peak stays mostly at the centre; in
    the dynamic field the moved share of the peak, (peak − centre)/peak, is larger by more than Z_SE standard
    errors, and the offset points along the flow."""
    v, _, mixed = _fast_flow_with_static(2.0, seed=43)
    f = centre_features(mixed, ("xc_peak_2", "xc_centre_2", *DYN))
    moved_field = (f[:, 0] - f[:, 1]) / f[:, 0]
    moved_dyn = (f[:, 2] - f[:, 3]) / f[:, 2]
    m_f, se_f = _mean_se(moved_field)
    m_d, se_d = _mean_se(moved_dyn)
    assert m_d - m_f > Z_SE * math.hypot(se_f, se_d), (m_f, m_d)
    for i, vc in ((4, v[0]), (5, v[1])):
        mean, se = _mean_se(f[:, i])
        assert mean > Z_SE * se and vc > 0, (DYN[i - 2], mean, se)


def test_direction_symmetric_motion_stays_centred_in_the_dynamic_field(flow_bscan):
    """Removing a per-pixel mean acts alike at r and r + Δ: two patterns moving at ±v beside static tissue give
    signed offsets of zero mean in the dynamic field too."""
    v, field = flow_bscan

    def back(i):
        return (-v[0] * i * DT, -v[1] * i * DT)

    field2 = translated_speckle(48, (32, 32), (S_Z, S_X), back, seed=12)
    static = translated_speckle(48, (32, 32), (S_Z, S_X), lambda i: (0.0, 0.0), seed=13, n_frames=1)
    names = ("xcd_shift_z_8", "xcd_shift_x_8", "xcd_shift_z_16", "xcd_shift_x_16")
    sym = centre_features(field + field2 + 2.0 * static, names)
    for i, n in enumerate(names):
        mean, se = _mean_se(sym[:, i])
        assert abs(mean) < Z_SE * se, (n, mean, se)


def test_dynamic_features_need_a_complex_field_and_are_named_as_the_fields():
    inten = torch.rand(2, 8, 9, 9, generator=torch.Generator().manual_seed(0)) + 0.1
    with pytest.raises(ValueError, match="complex field"):
        speckle_motion(inten, PITCH, DT, ["xcd_peak_2"], window=3)
    with pytest.raises(ValueError, match="unknown speckle feature"):
        parse_speckle_feature("xcd_velocity_x")
    assert parse_speckle_feature("xcd_shift_y_4") == ("shift", "y", 4)
    assert dynamic_speckle_features(3, (2, 4)) == (
        "xcd_centre_2",
        "xcd_peak_2",
        "xcd_shift_y_2",
        "xcd_shift_z_2",
        "xcd_shift_x_2",
        "xcd_centre_4",
        "xcd_peak_4",
        "xcd_shift_y_4",
        "xcd_shift_z_4",
        "xcd_shift_x_4",
    )
    assert is_dynamic_feature("xcd_peak_2") and not is_dynamic_feature("xc_peak_2")


def test_a_bulk_phase_left_in_the_data_gives_the_dynamic_field_no_false_offset(flow_bscan):
    """A random phase per frame common to the window (an uncorrected bulk motion) rotates the static field, so its
    temporal mean no longer removes it (§3 (f)); what is left is still direction-symmetric: two patterns at ±v
    beside static tissue under a random bulk phase keep zero mean signed offsets in the dynamic field (3.5 SE)."""
    v, field = flow_bscan

    def back(i):
        return (-v[0] * i * DT, -v[1] * i * DT)

    field2 = translated_speckle(48, (32, 32), (S_Z, S_X), back, seed=14)
    static = translated_speckle(48, (32, 32), (S_Z, S_X), lambda i: (0.0, 0.0), seed=15, n_frames=1)
    gen = torch.Generator().manual_seed(16)
    bulk = torch.exp(1j * 2 * math.pi * torch.rand(48, T, 1, 1, generator=gen, dtype=torch.float64))
    names = ("xcd_shift_z_8", "xcd_shift_x_8", "xcd_shift_z_16", "xcd_shift_x_16")
    sym = centre_features((field + field2 + 2.0 * static) * bulk, names)
    for i, n in enumerate(names):
        mean, se = _mean_se(sym[:, i])
        assert abs(mean) < Z_SE * se, (n, mean, se)

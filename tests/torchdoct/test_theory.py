"""Deterministic checks of torchdoct.sim.theory (physics.md §1, §2.4, §5, §6).

No Monte Carlo: every closed form is compared with a direct numerical integration of the expectation that
defines it (physics.md §5.3, §5.4), with the reference tables of physics.md §5.7 and §6, and with limits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from torchdoct.conventions import (
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    n_eff,
    wavenumber_per_um,
)
from torchdoct.sim import theory as th

DT_S = 0.2048
N_FRAMES = 32
LAGS_S = np.array([0.2048, 0.4096, 1.2288, 6.3488])
# (wavelength µm, lateral 1/e² width µm, axial FWHM µm); s_x < s_z (β > 0) except the 18-µm lateral one (β < 0)
SYSTEMS = [
    (0.84, 4.9, 3.8),
    (1.31, 4.9, 3.8),
    (1.31, 18.0, 14.0),
    (0.84, 4.9, 14.0),
    (0.84, 18.0, 3.8),
]
DIFFUSIONS = [0.005, 0.5, 15.0]
SPEEDS = [0.1, 3.0, 6.0]
ATOL = 1e-7
HIGH_RES = dict(wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
HIGH_RES_J = dict(lateral_resolution_um=4.9, axial_resolution_um=3.8)
RHO_SPHEROID_PER_UM3 = 0.055


def _sys_id(system):
    return f"{int(system[0] * 1000)}nm-{system[1]}x{system[2]}um"


def _widths(lat, ax):
    return amplitude_sigma_lateral_um(lat), amplitude_sigma_axial_um(ax)


# ----------------------------------------------------------------------------------------------------------
# 1. closed forms vs numerical integration of the defining expectations
# ----------------------------------------------------------------------------------------------------------
def _gauss_expectation_1d(sigma, weight_inv, q):
    """E[exp(−x²·weight_inv − i q x)], x ~ N(0, σ²), by the trapezoid rule (exponentially accurate here)."""
    step = min(sigma, 1.0 / math.sqrt(weight_inv)) / 12.0
    if q > 0:
        step = min(step, 0.25 / q)
    half = 14.0 * sigma
    x = np.arange(-half, half + step / 2, step)
    dens = np.exp(-0.5 * (x / sigma) ** 2) / (sigma * math.sqrt(2.0 * math.pi))
    vals = dens * np.exp(-(x**2) * weight_inv) * np.exp(-1j * q * x)
    return np.sum(vals) * step


@pytest.mark.parametrize("system", SYSTEMS, ids=_sys_id)
def test_diffusion_closed_forms_match_gaussian_expectation(system):
    # Δ ~ N(0, 2Dτ I₃) has independent coordinates, so the 3-D Gaussian expectation is the product of
    # three 1-D ones; each is integrated numerically.
    wl, lat, ax = system
    sx, sz = _widths(lat, ax)
    q = 2.0 * wavenumber_per_um(wl)
    for diff in DIFFUSIONS:
        g1 = th.g1_diffusion(
            LAGS_S, diffusion_um2_per_s=diff, wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax
        )
        j = th.j_diffusion(LAGS_S, diffusion_um2_per_s=diff, lateral_resolution_um=lat, axial_resolution_um=ax)
        for i, tau in enumerate(LAGS_S):
            sigma = math.sqrt(2.0 * diff * tau)
            g1_num = _gauss_expectation_1d(sigma, 1 / (4 * sx**2), 0.0) ** 2 * _gauss_expectation_1d(
                sigma, 1 / (4 * sz**2), q
            )
            j_num = _gauss_expectation_1d(sigma, 1 / (2 * sx**2), 0.0) ** 2 * _gauss_expectation_1d(
                sigma, 1 / (2 * sz**2), 0.0
            )
            assert abs(g1[i] - g1_num) < ATOL, (diff, tau)
            assert abs(j[i] - j_num) < ATOL, (diff, tau)


def test_diffusion_g1_full_3d_gauss_hermite():
    # A genuinely 3-D (non-factorized) tensor Gauss–Hermite integration where the phase is resolvable.
    wl, lat, ax = SYSTEMS[0]
    sx, sz = _widths(lat, ax)
    kn = wavenumber_per_um(wl)
    nodes, weights = np.polynomial.hermite_e.hermegauss(60)
    weights = weights / math.sqrt(2.0 * math.pi)
    for diff, tau in [(0.005, 0.2048), (0.005, 1.2288), (0.0005, 6.3488)]:
        sigma = math.sqrt(2.0 * diff * tau)
        dx, dy, dz = np.meshgrid(sigma * nodes, sigma * nodes, sigma * nodes, indexing="ij")
        w3 = weights[:, None, None] * weights[None, :, None] * weights[None, None, :]
        g1_int = np.exp(-2j * kn * dz - (dx**2 + dy**2) / (4 * sx**2) - dz**2 / (4 * sz**2))
        j_int = np.exp(-(dx**2 + dy**2) / (2 * sx**2) - dz**2 / (2 * sz**2))
        g1 = th.g1_diffusion(tau, diffusion_um2_per_s=diff, **HIGH_RES)
        j = th.j_diffusion(tau, diffusion_um2_per_s=diff, **HIGH_RES_J)
        assert abs(g1 - np.sum(w3 * g1_int)) < ATOL
        assert abs(j - np.sum(w3 * j_int)) < ATOL


_N_MID = 200_000
_MU = (np.arange(_N_MID) + 0.5) / _N_MID  # midpoint nodes on [0, 1]
_PHI = _MU * np.pi  # midpoint nodes on [0, π]


@pytest.mark.parametrize("system", SYSTEMS, ids=_sys_id)
def test_ballistic_closed_forms_match_midpoint_rule(system):
    wl, lat, ax = system
    sx, sz = _widths(lat, ax)
    kn = wavenumber_per_um(wl)
    kw = dict(wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax)
    jw = dict(lateral_resolution_um=lat, axial_resolution_um=ax)
    for v in SPEEDS:
        g_iso = th.g1_ballistic(LAGS_S, speed_um_per_s=v, **kw)
        g_ua = th.g1_ballistic(LAGS_S, speed_um_per_s=v, directions="uniform-angles", **kw)
        j_iso = th.j_ballistic(LAGS_S, speed_um_per_s=v, **jw)
        j_ua = th.j_ballistic(LAGS_S, speed_um_per_s=v, directions="uniform-angles", **jw)
        for i, tau in enumerate(LAGS_S):
            u = v * tau
            q, a, b = 2 * kn * u, u**2 / (4 * sx**2), u**2 / (4 * sz**2)
            # isotropic: μ = cos(polar) ~ U[−1, 1]; the odd (sine) part integrates to zero
            iso = np.mean(np.exp((a - b) * _MU**2 - a) * np.cos(q * _MU))
            iso_j = np.mean(np.exp(2 * (a - b) * _MU**2 - 2 * a))
            # uniform angles: φ ~ U[0, π], Δz = u cos φ, Δx² + Δy² = u² sin² φ
            cphi, sphi = np.cos(_PHI), np.sin(_PHI)
            ua = np.mean(np.exp(-1j * q * cphi - a * sphi**2 - b * cphi**2))
            ua_j = np.mean(np.exp(-2 * a * sphi**2 - 2 * b * cphi**2))
            assert abs(ua.imag) < 1e-12
            assert abs(g_iso[i] - iso) < ATOL, (v, tau)
            assert abs(g_ua[i] - ua.real) < ATOL, (v, tau)
            assert abs(j_iso[i] - iso_j) < ATOL, (v, tau)
            assert abs(j_ua[i] - ua_j) < ATOL, (v, tau)


def test_beta_signs_covered():
    betas = []
    for _, lat, ax in SYSTEMS:
        sx, sz = _widths(lat, ax)
        betas.append(1 / (4 * sx**2) - 1 / (4 * sz**2))
    assert min(betas) < 0 < max(betas)


@pytest.mark.parametrize("system", SYSTEMS, ids=_sys_id)
def test_flow_matches_explicit_displacement(system):
    wl, lat, ax = system
    sx, sz = _widths(lat, ax)
    kn = wavenumber_per_um(wl)
    for v in SPEEDS:
        for theta_deg in (0.0, 30.0, 45.0, 90.0, 135.0):
            th_rad = math.radians(theta_deg)
            g1 = th.g1_flow(
                LAGS_S,
                speed_um_per_s=v,
                polar_angle_deg=theta_deg,
                wavelength_um=wl,
                lateral_resolution_um=lat,
                axial_resolution_um=ax,
            )
            j = th.j_flow(
                LAGS_S, speed_um_per_s=v, polar_angle_deg=theta_deg, lateral_resolution_um=lat, axial_resolution_um=ax
            )
            assert g1.dtype == np.complex128
            np.testing.assert_allclose(j, np.abs(g1) ** 2, rtol=0, atol=1e-14)
            for psi in np.linspace(0.0, 2 * np.pi, 7):  # the azimuth must not matter
                d = (
                    v
                    * LAGS_S[:, None]
                    * np.array([math.sin(th_rad) * math.cos(psi), math.sin(th_rad) * math.sin(psi), math.cos(th_rad)])
                )
                ref = np.exp(
                    -2j * kn * d[:, 2] - (d[:, 0] ** 2 + d[:, 1] ** 2) / (4 * sx**2) - d[:, 2] ** 2 / (4 * sz**2)
                )
                ref_j = np.exp(-(d[:, 0] ** 2 + d[:, 1] ** 2) / (2 * sx**2) - d[:, 2] ** 2 / (2 * sz**2))
                np.testing.assert_allclose(g1, ref, rtol=0, atol=1e-12)
                np.testing.assert_allclose(j, ref_j, rtol=0, atol=1e-12)


def test_flow_moving_deeper_has_negative_phase():
    g1 = th.g1_flow(0.01, speed_um_per_s=1.0, polar_angle_deg=0.0, **HIGH_RES)
    assert g1.imag < 0  # exp(−i 2kn v τ) for small 2knvτ


# ----------------------------------------------------------------------------------------------------------
# 2. physics.md §6 reference table (840 nm, 4.9/3.8 µm, ρ = 0.055 µm⁻³): g1 and cov = |g1|² + j/N_eff
# ----------------------------------------------------------------------------------------------------------
_TAB6 = [  # (kind, parameter, lag index, g1 theory, cov theory) as printed in physics.md §6
    ("diff", 0.005, 0, 0.7949, 0.8002),
    ("diff", 0.005, 1, 0.6319, 0.5675),
    ("diff", 0.005, 2, 0.2526, 0.2315),
    ("diff", 0.005, 3, 0.0008, 0.1641),
    ("diff", 0.5, 0, 0.0, 0.1548),
    ("diff", 0.5, 1, 0.0, 0.1428),
    ("diff", 0.5, 2, 0.0, 0.1076),
    ("diff", 0.5, 3, 0.0, 0.0363),
    ("iso", 0.1, 0, 0.9844, 1.1376),
    ("iso", 0.1, 1, 0.9385, 1.0492),
    ("iso", 0.1, 2, 0.5240, 0.4428),
    ("iso", 0.1, 3, -0.0078, 0.1592),
    ("iso", 3.0, 0, 0.0244, 0.1603),
    ("iso", 3.0, 1, -0.0225, 0.1364),
    ("iso", 3.0, 2, -0.0093, 0.0253),
    ("iso", 3.0, 3, 0.0, 0.0),
    ("cog", 0.1, 0, 0.9766, 1.1224),
    ("cog", 0.1, 1, 0.9082, 0.9934),
    ("cog", 0.1, 2, 0.3173, 0.2689),
    ("cog", 0.1, 3, -0.1901, 0.1960),
    ("cog", 3.0, 0, -0.1328, 0.1780),
    ("cog", 3.0, 1, 0.0536, 0.1412),
    ("cog", 3.0, 2, -0.0320, 0.0310),
    ("cog", 3.0, 3, 0.0, 0.0),
    ("flow", 0.1, 0, 0.9766 - 0.2149j, 1.1685),
    ("flow", 0.1, 1, 0.9075 - 0.4198j, 1.1683),
    ("flow", 0.1, 2, 0.2674 - 0.9626j, 1.1662),
    ("flow", 0.1, 3, 0.8841 - 0.4084j, 1.1083),
    ("flow", 1.0, 0, -0.5595 - 0.8255j, 1.1621),
    ("flow", 1.0, 1, -0.3664 + 0.9187j, 1.1431),
    ("flow", 1.0, 2, 0.8223 - 0.3794j, 0.9584),
    ("flow", 1.0, 3, -0.0266 + 0.0657j, 0.0059),
]
_HALF_LAST_DIGIT = 0.5e-4 + 1e-9


def _g1_j(kind, param, tau, wavelength_um=0.84, lat=4.9, ax=3.8):
    g = dict(wavelength_um=wavelength_um, lateral_resolution_um=lat, axial_resolution_um=ax)
    jw = dict(lateral_resolution_um=lat, axial_resolution_um=ax)
    if kind == "diff":
        return (
            th.g1_diffusion(tau, diffusion_um2_per_s=param, **g),
            th.j_diffusion(tau, diffusion_um2_per_s=param, **jw),
        )
    if kind in ("iso", "cog"):
        directions = "isotropic" if kind == "iso" else "uniform-angles"
        return (
            th.g1_ballistic(tau, speed_um_per_s=param, directions=directions, **g),
            th.j_ballistic(tau, speed_um_per_s=param, directions=directions, **jw),
        )
    if kind == "flow":
        return (
            th.g1_flow(tau, speed_um_per_s=param, polar_angle_deg=45.0, **g),
            th.j_flow(tau, speed_um_per_s=param, polar_angle_deg=45.0, **jw),
        )
    raise AssertionError(kind)


@pytest.mark.parametrize("kind,param,lag,g1_ref,cov_ref", _TAB6)
def test_reference_table_section6(kind, param, lag, g1_ref, cov_ref):
    g1, j = _g1_j(kind, param, LAGS_S[lag])
    neff = n_eff(RHO_SPHEROID_PER_UM3, 4.9, 3.8)
    assert abs(np.real(g1) - np.real(g1_ref)) <= _HALF_LAST_DIGIT
    assert abs(np.imag(g1) - np.imag(g1_ref)) <= _HALF_LAST_DIGIT
    assert abs(th.intensity_autocovariance(g1, j, neff) - cov_ref) <= _HALF_LAST_DIGIT


def test_contrast_at_zero_lag():
    neff = n_eff(RHO_SPHEROID_PER_UM3, 4.9, 3.8)
    g1, j = _g1_j("diff", 0.5, 0.0)
    assert th.intensity_autocovariance(g1, j, neff) == pytest.approx(1.1685, abs=1e-4)
    assert th.intensity_correlation_coefficient(g1, j, neff) == pytest.approx(1.0, abs=1e-15)


# ----------------------------------------------------------------------------------------------------------
# 3. limits and hard cases
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("system", SYSTEMS, ids=_sys_id)
def test_zero_lag_and_zero_motion_give_one(system):
    wl, lat, ax = system
    kw = dict(wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax)
    jw = dict(lateral_resolution_um=lat, axial_resolution_um=ax)
    tau = np.array([0.0, 0.2048, 6.3488])
    for motion in (0.0, 1.0):
        mask = np.ones(3, bool) if motion == 0 else np.array([True, False, False])
        vals = [
            th.g1_diffusion(tau, diffusion_um2_per_s=motion, **kw),
            th.j_diffusion(tau, diffusion_um2_per_s=motion, **jw),
            th.g1_ballistic(tau, speed_um_per_s=motion, **kw),
            th.g1_ballistic(tau, speed_um_per_s=motion, directions="uniform-angles", **kw),
            th.j_ballistic(tau, speed_um_per_s=motion, **jw),
            th.j_ballistic(tau, speed_um_per_s=motion, directions="uniform-angles", **jw),
            th.g1_flow(tau, speed_um_per_s=motion, polar_angle_deg=30.0, **kw),
            th.j_flow(tau, speed_um_per_s=motion, polar_angle_deg=30.0, **jw),
        ]
        for val in vals:
            assert np.all(np.isfinite(val))
            np.testing.assert_allclose(val[mask], 1.0, rtol=0, atol=1e-15)


def test_point_like_psf_limit_is_sinc():
    tau = np.linspace(0.0, 6.3488, 200)
    v = 0.1
    big = dict(wavelength_um=0.84, lateral_resolution_um=1e6, axial_resolution_um=1.3e6)
    g1 = th.g1_ballistic(tau, speed_um_per_s=v, **big)
    q = 2 * wavenumber_per_um(0.84) * v * tau
    np.testing.assert_allclose(g1, np.sinc(q / np.pi), rtol=0, atol=1e-9)
    # uniform angles in the same limit: J0(2kvτ)
    from scipy.special import j0

    g1_ua = th.g1_ballistic(tau, speed_um_per_s=v, directions="uniform-angles", **big)
    np.testing.assert_allclose(g1_ua, j0(q), rtol=0, atol=1e-9)


def test_equal_widths_beta_zero_limits():
    # s_x == s_z exactly (β = 0): e^{−A} sin Q / Q and e^{−A} J0(Q)
    lat = 4.9
    ax = 4.9 * 2 * math.sqrt(math.log(2.0)) / (2 * math.sqrt(2.0))
    sx, sz = _widths(lat, ax)
    assert abs(1 / sx**2 - 1 / sz**2) < 1e-14
    tau = np.array([0.0, 0.1, 1.0, 6.3488])
    v = 0.5
    kw = dict(wavelength_um=0.84, lateral_resolution_um=lat, axial_resolution_um=ax)
    u = v * tau
    a = u**2 / (4 * sx**2)
    q = 2 * wavenumber_per_um(0.84) * u
    from scipy.special import j0

    np.testing.assert_allclose(
        th.g1_ballistic(tau, speed_um_per_s=v, **kw), np.exp(-a) * np.sinc(q / np.pi), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        th.g1_ballistic(tau, speed_um_per_s=v, directions="uniform-angles", **kw),
        np.exp(-a) * j0(q),
        rtol=0,
        atol=1e-12,
    )


def test_isotropic_branch_switch_is_continuous():
    # sweep the axial width through s_z = s_x: β goes through 0 and the Faddeeva/limit/quadrature branches
    sx = 1.7
    rel = np.concatenate([-np.logspace(-1, -15, 60), [0.0], np.logspace(-15, -1, 60)])
    sz = sx * (1.0 + rel)
    lat = 2 * math.sqrt(2.0) * sx
    ax = 2 * math.sqrt(math.log(2.0)) * sz
    for v, tau in [(0.1, 1.2288), (0.01, 0.2048), (3.0, 6.3488), (1e-4, 0.2048)]:
        g1 = th.g1_ballistic(
            tau, speed_um_per_s=v, wavelength_um=0.84, lateral_resolution_um=lat, axial_resolution_um=ax
        )
        u = v * tau
        a, b = u**2 / (4 * sx**2), u**2 / (4 * sz**2)
        q = 2 * wavenumber_per_um(0.84) * u
        ref = np.array([np.mean(np.exp((a - bb) * _MU**2 - a) * np.cos(q * _MU)) for bb in b])
        np.testing.assert_allclose(g1, ref, rtol=0, atol=1e-9)


def test_huge_speed_no_overflow():
    tau = np.array([0.0, 1e-6, 0.2048, 6.3488, 1e3])
    for directions in ("isotropic", "uniform-angles"):
        for v in (1e3, 1e5):
            g1 = th.g1_ballistic(tau, speed_um_per_s=v, directions=directions, **HIGH_RES)
            j = th.j_ballistic(tau, speed_um_per_s=v, directions=directions, **HIGH_RES_J)
            assert np.all(np.isfinite(g1)) and np.all(np.isfinite(j))
            assert g1[0] == 1.0 and j[0] == 1.0
            assert np.all(np.abs(g1[2:]) < 1e-3) and np.all(j[2:] < 1e-30)
    g1 = th.g1_diffusion(tau, diffusion_um2_per_s=1e6, **HIGH_RES)
    assert np.all(np.isfinite(g1)) and np.all(g1[1:] < 1e-12)
    g1 = th.g1_flow(tau, speed_um_per_s=1e5, polar_angle_deg=10.0, **HIGH_RES)
    assert np.all(np.isfinite(g1)) and np.all(np.abs(g1[2:]) == 0.0)


def test_uniform_angles_series_large_q_and_large_a_minus_b():
    # Q up to ~1e4 and (A − B) ≫ 1: compare with a (spectrally accurate) periodic midpoint rule.
    phi = (np.arange(400_000) + 0.5) / 400_000 * np.pi
    cphi, sphi = np.cos(phi), np.sin(phi)
    kn = wavenumber_per_um(0.84)
    cases = [(1.0, 5e3), (0.1, 1e4), (1.0, 2e3)]  # (lat, ax) extreme shapes
    for lat, ax in cases:
        sx, sz = _widths(lat, ax)
        for u in (0.5, 50.0, 660.0):
            q, a, b = 2 * kn * u, u**2 / (4 * sx**2), u**2 / (4 * sz**2)
            ref = np.mean(np.exp(-1j * q * cphi - a * sphi**2 - b * cphi**2)).real
            got = th.g1_ballistic(
                u,
                speed_um_per_s=1.0,
                directions="uniform-angles",
                wavelength_um=0.84,
                lateral_resolution_um=lat,
                axial_resolution_um=ax,
            )
            assert abs(got - ref) < 1e-9, (lat, ax, u)


def test_uniform_angles_extreme_width_ratio():
    # |A − B| > 2e8: beyond scipy's ive range; g1 uses the Laplace form, j the Hankel expansion of I0
    phi = (np.arange(2_000_000) + 0.5) / 2_000_000 * np.pi
    cphi, sphi = np.cos(phi), np.sin(phi)
    kn = wavenumber_per_um(0.84)
    for lat, ax, u in [(0.5, 2e4, 6e3), (2e5, 0.4, 8e3)]:
        sx, sz = _widths(lat, ax)
        q, a, b = 2 * kn * u, u**2 / (4 * sx**2), u**2 / (4 * sz**2)
        assert abs(a - b) > 2e8 and min(a, b) < 50
        ref = np.mean(np.exp(-1j * q * cphi - a * sphi**2 - b * cphi**2)).real
        ref_j = np.mean(np.exp(-2 * a * sphi**2 - 2 * b * cphi**2))
        got = th.g1_ballistic(
            u,
            speed_um_per_s=1.0,
            directions="uniform-angles",
            wavelength_um=0.84,
            lateral_resolution_um=lat,
            axial_resolution_um=ax,
        )
        got_j = th.j_ballistic(
            u, speed_um_per_s=1.0, directions="uniform-angles", lateral_resolution_um=lat, axial_resolution_um=ax
        )
        assert abs(got - ref) < 1e-10 and abs(got_j - ref_j) < 1e-10, (lat, ax)


def test_flow_modulus_independent_of_wavelength():
    tau = np.linspace(0.0, 6.3488, 50)
    g840 = th.g1_flow(tau, speed_um_per_s=1.0, polar_angle_deg=45.0, **HIGH_RES)
    g1310 = th.g1_flow(
        tau,
        speed_um_per_s=1.0,
        polar_angle_deg=45.0,
        wavelength_um=1.31,
        lateral_resolution_um=4.9,
        axial_resolution_um=3.8,
        refractive_index=1.37,
    )
    np.testing.assert_allclose(np.abs(g840), np.abs(g1310), rtol=1e-13, atol=0)
    assert not np.allclose(g840, g1310)


def test_refractive_index_scales_phase_rates():
    tau = np.array([0.2048, 1.2288])
    n = 1.37
    d = th.g1_diffusion(tau, diffusion_um2_per_s=0.002, refractive_index=n, **HIGH_RES)
    # D·n² in the phase term only: check against the closed form with kn
    sx, sz = _widths(4.9, 3.8)
    kn = wavenumber_per_um(0.84, n)
    dt = 0.002 * tau
    ref = np.exp(-4 * kn**2 * dt / (1 + dt / sz**2)) / ((1 + dt / sx**2) * np.sqrt(1 + dt / sz**2))
    np.testing.assert_allclose(d, ref, rtol=1e-14)
    # point-PSF ballistic: Q = 2 k n v τ
    big = dict(wavelength_um=0.84, lateral_resolution_um=1e6, axial_resolution_um=1e6)
    g = th.g1_ballistic(tau, speed_um_per_s=0.1, refractive_index=n, **big)
    np.testing.assert_allclose(g, np.sinc(2 * kn * 0.1 * tau / np.pi), atol=1e-9)


def test_broadcasting_and_dtypes():
    tau = np.array([[0.2048], [1.2288]])  # (2, 1)
    speeds = np.array([0.1, 1.0, 3.0])  # (3,)
    for directions in ("isotropic", "uniform-angles"):
        g = th.g1_ballistic(tau, speed_um_per_s=speeds, directions=directions, **HIGH_RES)
        j = th.j_ballistic(tau, speed_um_per_s=speeds, directions=directions, **HIGH_RES_J)
        assert g.shape == (2, 3) and g.dtype == np.float64
        assert j.shape == (2, 3) and j.dtype == np.float64
        for r in range(2):
            for c in range(3):
                assert g[r, c] == pytest.approx(
                    float(th.g1_ballistic(tau[r, 0], speed_um_per_s=speeds[c], directions=directions, **HIGH_RES)),
                    abs=1e-15,
                )
    scalar = th.g1_diffusion(0.2048, diffusion_um2_per_s=0.005, **HIGH_RES)
    assert isinstance(scalar, np.ndarray) and scalar.shape == () and scalar.dtype == np.float64
    wl = np.array([0.84, 1.31])
    g = th.g1_diffusion(
        0.2048, diffusion_um2_per_s=0.005, wavelength_um=wl, lateral_resolution_um=4.9, axial_resolution_um=3.8
    )
    assert g.shape == (2,) and g[1] > g[0]
    assert th.j_flow(tau, speed_um_per_s=speeds, polar_angle_deg=45.0, **HIGH_RES_J).shape == (2, 3)
    assert th.g1_flow(tau, speed_um_per_s=speeds, polar_angle_deg=45.0, **HIGH_RES).shape == (2, 3)
    assert th.j_diffusion(tau, diffusion_um2_per_s=speeds, **HIGH_RES_J).shape == (2, 3)


def test_invalid_inputs_raise():
    with pytest.raises(ValueError):
        th.g1_diffusion(-1.0, diffusion_um2_per_s=0.1, **HIGH_RES)
    with pytest.raises(ValueError):
        th.g1_ballistic(1.0, speed_um_per_s=-0.1, **HIGH_RES)
    with pytest.raises(ValueError):
        th.j_ballistic(1.0, speed_um_per_s=0.1, directions="sphere", **HIGH_RES_J)
    with pytest.raises(ValueError):
        th.g1_flow(
            1.0,
            speed_um_per_s=0.1,
            polar_angle_deg=0.0,
            wavelength_um=0.84,
            lateral_resolution_um=0.0,
            axial_resolution_um=3.8,
        )
    with pytest.raises(ValueError):
        th.liv_gaussian_limit(np.zeros(30), 32)
    with pytest.raises(ValueError):
        th.dilog(1.5)


def test_dilog_and_db_variance():
    assert th.dilog(1.0) == pytest.approx(math.pi**2 / 6, abs=1e-15)
    assert th.dilog(0.0) == 0.0
    assert th.dilog(0.5) == pytest.approx(math.pi**2 / 12 - math.log(2.0) ** 2 / 2, abs=1e-15)
    assert th.db_variance_gaussian_speckle() == pytest.approx(31.03, abs=0.01)
    assert isinstance(th.db_variance_gaussian_speckle(), float)
    np.testing.assert_allclose(th.rho_db_gaussian_limit(np.array([0.0, 1.0, -1.0, 1j])), [0, 1, 1, 1], atol=1e-15)


def test_liv_gaussian_limit_extremes():
    full = th.liv_gaussian_limit(np.zeros(N_FRAMES - 1), N_FRAMES)
    assert isinstance(full, float)
    assert full == pytest.approx((1 - 1 / N_FRAMES) * th.db_variance_gaussian_speckle(), abs=1e-12)
    assert full == pytest.approx(30.06, abs=0.005)
    assert th.liv_gaussian_limit(np.ones(N_FRAMES - 1), N_FRAMES) == pytest.approx(0.0, abs=1e-12)
    batch = th.liv_gaussian_limit(np.stack([np.zeros(31), np.ones(31)]), N_FRAMES)
    np.testing.assert_allclose(batch, [full, 0.0], atol=1e-12)


def test_liv_gaussian_limit_matches_direct_covariance_sum():
    # Var over frames of a stationary sequence with Cov(ln I_a, ln I_b) = Li2(|g1|²): ddof-0 expectation
    g = th.g1_diffusion(np.arange(1, N_FRAMES) * DT_S, diffusion_um2_per_s=0.003, **HIGH_RES)
    lag_cov = np.concatenate([[math.pi**2 / 6], th.dilog(g**2)])
    idx = np.arange(N_FRAMES)
    cov = lag_cov[np.abs(idx[:, None] - idx[None, :])]
    expected = (np.trace(cov) / N_FRAMES - cov.sum() / N_FRAMES**2) * (10 / math.log(10)) ** 2
    assert th.liv_gaussian_limit(g, N_FRAMES) == pytest.approx(expected, abs=1e-10)


# ----------------------------------------------------------------------------------------------------------
# 4. OCDS bounds (physics.md §2.4)
# ----------------------------------------------------------------------------------------------------------
WINDOW_S = np.arange(1, 7) * DT_S


def test_ocds_bounds():
    linear = (6 - np.arange(1, 7)) / 5.0
    val = th.ocds_from_correlations(linear, WINDOW_S)
    assert isinstance(val, float)
    assert val == pytest.approx(1.0 / (5 * DT_S), rel=1e-14)
    assert round(val, 2) == 0.98
    step = np.array([1.0, 0, 0, 0, 0, 0])
    val = th.ocds_from_correlations(step, WINDOW_S)
    assert val == pytest.approx(2.5 / (17.5 * DT_S), rel=1e-14)
    assert round(val, 2) == 0.70
    # maximum of the linear functional for ρ ∈ [0, 1]: ρ = 1 on lags 1..3, 0 on 4..6 → 1.26
    assert round(th.ocds_from_correlations([1, 1, 1, 0, 0, 0], WINDOW_S), 2) == 1.26
    # constant curve → 0; batch shape
    out = th.ocds_from_correlations(np.stack([linear, np.full(6, 0.3)]), WINDOW_S)
    np.testing.assert_allclose(out, [1.0 / (5 * DT_S), 0.0], atol=1e-14)


# ----------------------------------------------------------------------------------------------------------
# 5. physics.md §5.7 table: LIV_G (N = 32, Δt = 0.2048 s) and OCDS_l, 840 / 1310 nm, 4.9/3.8 µm, n = 1
# ----------------------------------------------------------------------------------------------------------
_TAB57 = [  # kind, parameter, LIV_G 840, LIV_G 1310, OCDS_lin 840, 1310, OCDS_dB 840, 1310
    ("diff", 0.001, 20.0, 13.6, 0.28, 0.14, 0.37, 0.24),
    ("diff", 0.003, 26.3, 21.5, 0.47, 0.32, 0.46, 0.40),
    ("diff", 0.01, 29.3, 27.4, 0.30, 0.47, 0.23, 0.43),
    ("diff", 0.1, 30.1, 30.0, 0.01, 0.03, 0.00, 0.01),
    ("iso", 0.03, 12.8, 8.1, 0.08, 0.03, 0.19, 0.10),
    ("iso", 0.1, 24.0, 20.8, 0.60, 0.32, 0.73, 0.50),
    ("iso", 0.3, 28.5, 27.2, 0.52, 0.77, 0.47, 0.74),
    ("cog", 0.03, 15.3, 10.2, 0.12, 0.05, 0.25, 0.14),
    ("flow", 1.0, 16.2, 16.2, 0.17, 0.17, 0.30, 0.30),
    ("flow", 6.0, 28.0, 28.0, 0.78, 0.78, 0.61, 0.61),
]
_ALL_LAGS_S = np.arange(1, N_FRAMES) * DT_S


@pytest.mark.parametrize("row", _TAB57, ids=lambda r: f"{r[0]}-{r[1]}")
def test_reference_table_section57(row):
    kind, param, *refs = row
    neff = n_eff(RHO_SPHEROID_PER_UM3, 4.9, 3.8)
    for w_idx, wl in enumerate((0.84, 1.31)):
        g1, j = _g1_j(kind, param, _ALL_LAGS_S, wavelength_um=wl)
        liv = th.liv_gaussian_limit(np.abs(g1), N_FRAMES)
        assert abs(liv - refs[w_idx]) <= 0.1, (wl, liv)
        rho_lin = th.intensity_correlation_coefficient(g1[:6], j[:6], neff)
        rho_db = th.rho_db_gaussian_limit(g1[:6])
        assert abs(th.ocds_from_correlations(rho_lin, WINDOW_S) - refs[2 + w_idx]) <= 0.005 + 1e-9
        assert abs(th.ocds_from_correlations(rho_db, WINDOW_S) - refs[4 + w_idx]) <= 0.005 + 1e-9


def test_section57_diffusion_001_rounding():
    # physics.md §5.7 prints 29.3 for diffusion D = 0.01 µm²/s at 840 nm; the formula gives 29.2476, which
    # rounds to 29.2 (the table's last digit is off by one; every other LIV_G entry rounds correctly).
    g1, _ = _g1_j("diff", 0.01, _ALL_LAGS_S)
    assert th.liv_gaussian_limit(g1, N_FRAMES) == pytest.approx(29.2476, abs=1e-4)

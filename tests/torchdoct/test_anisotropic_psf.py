"""A lateral PSF with separate x and y widths (physics.md §5.8): conventions, scene files, plan,
closed forms against direct averages, the simulator against the closed forms (fixed seeds, z ≤ 4 of
the MC SE), bit identity of the fused kernel and its torch twin, and the renderer's PSF."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _stats import assert_within_se, batch_means, contrast2, cov_at_lag, g1_at_lag, mean_intensity

import torchdoct as td
from torchdoct import conventions as cv
from torchdoct.sim import kernel
from torchdoct.sim import theory as th
from torchdoct.sim.config import scene_from_dict

DT = 0.2048
RHO = 0.055
# a B-scan channel after a lateral reduction along x only: 18 µm along x, the system's 4.9 µm along y
BSCAN = td.OCTSystem(
    name="bscan-lat18",
    wavelength_um=0.84,
    lateral_resolution_um=18.0,
    axial_resolution_um=3.8,
    lateral_resolution_y_um=4.9,
)
HIGH = td.OCTSystem(name="840-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)

needs_compiled = pytest.mark.skipif(not kernel.compiled(), reason="the compiled kernel was not built")


def _scene(motion=(), systems=(BSCAN,), n_frames=8, rho=RHO, **sim):
    return td.Scene(
        systems=tuple(systems),
        protocol=td.Protocol(n_frames=n_frames, frame_interval_s=DT),
        populations=(td.Population(density_per_um3=rho, motion=tuple(motion)),),
        analysis=td.Analysis(metrics=("liv",)),
        simulation=td.SimulationSettings(**sim),
    )


# ------------------------------------------------------------------------------------------------
# conventions, scene files, plan


def test_conventions_use_one_sigma_per_axis():
    sx, sy, sz = (
        cv.amplitude_sigma_lateral_um(18.0),
        cv.amplitude_sigma_lateral_um(4.9),
        cv.amplitude_sigma_axial_um(3.8),
    )
    kw = dict(lateral_resolution_y_um=4.9)
    assert cv.psf_integral_um3(18.0, 3.8, **kw) == pytest.approx(math.pi**1.5 * sx * sy * sz, rel=1e-14)
    assert cv.n_eff(RHO, 18.0, 3.8, **kw) == pytest.approx(RHO * (2 * math.pi) ** 1.5 * sx * sy * sz, rel=1e-14)
    assert cv.ens_paper(RHO, 18.0, 3.8, **kw) == pytest.approx(RHO * 18.0 * 4.9 * 3.8, rel=1e-14)
    assert cv.mean_intensity(RHO, 18.0, 3.8, 2.0, **kw) == pytest.approx(4.0 * RHO * math.pi**1.5 * sx * sy * sz)
    c = cv.truncation_radius_factor(1e-2)
    assert cv.truncation_half_widths_um(18.0, 3.8, 1e-2, **kw) == pytest.approx((c * sx, c * sy, c * sz), rel=1e-14)
    # the y width defaults to the x width, and giving it equal changes no bit
    for f in (cv.psf_integral_um3, lambda *a, **k: cv.n_eff(RHO, *a, **k), lambda *a, **k: cv.ens_paper(RHO, *a, **k)):
        assert f(4.9, 3.8) == f(4.9, 3.8, lateral_resolution_y_um=4.9) == f(4.9, 3.8, lateral_resolution_y_um=None)
    # swapping the lateral widths changes nothing that does not depend on the direction
    assert cv.n_eff(RHO, 4.9, 3.8, lateral_resolution_y_um=18.0) == pytest.approx(cv.n_eff(RHO, 18.0, 3.8, **kw))


def test_scene_file_key_round_trips_and_is_left_out_when_not_given():
    d = {
        "system": [
            {
                "name": "b",
                "wavelength_um": 0.84,
                "lateral_resolution_um": 18.0,
                "axial_resolution_um": 3.8,
                "lateral_resolution_y_um": 4.9,
            }
        ],
        "protocol": {"n_frames": 4, "frame_interval_s": DT},
        "population": [{"density_per_um3": RHO}],
        "analysis": {"metrics": ["liv"]},
    }
    sc = scene_from_dict(d)
    assert sc.systems[0].lateral_resolution_y_um == 4.9
    assert sc.systems[0].lateral_widths_um == (18.0, 4.9)
    assert not sc.systems[0].is_isotropic
    assert scene_from_dict(sc.to_dict()) == sc
    assert sc.to_dict()["system"][0]["lateral_resolution_y_um"] == 4.9
    del d["system"][0]["lateral_resolution_y_um"]
    iso = scene_from_dict(d)
    assert iso.systems[0].lateral_widths_um == (18.0, 18.0) and iso.systems[0].is_isotropic
    assert "lateral_resolution_y_um" not in iso.to_dict()["system"][0]  # files written before read the same


def test_plan_reports_the_anisotropic_box_and_counts():
    plan = td.make_plan(_scene((td.Diffusion(diffusion_um2_per_s=1.0),)))
    s = plan.systems[0]
    assert s.truncation_half_widths_um == pytest.approx(
        cv.truncation_half_widths_um(18.0, 3.8, 1e-2, lateral_resolution_y_um=4.9)
    )
    assert s.n_eff == pytest.approx(cv.n_eff(RHO, 18.0, 3.8, lateral_resolution_y_um=4.9))
    assert s.truncation_half_widths_um[0] > 3 * s.truncation_half_widths_um[1]
    # the periodic cell holds the box on every axis
    cell = plan.populations[0].domain_half_widths_um
    assert all(c >= h for c, h in zip(cell, s.truncation_half_widths_um))


# ------------------------------------------------------------------------------------------------
# closed forms (physics.md §5.8)


def _directions(law: str, n: int, rng) -> np.ndarray:
    u0, u1 = rng.random(n), rng.random(n)
    mu = 2 * u0 - 1 if law == "isotropic" else np.cos(np.pi * u0)
    st = np.sqrt(1 - mu * mu)
    return np.stack([st * np.cos(2 * np.pi * u1), st * np.sin(2 * np.pi * u1), mu])


@pytest.mark.parametrize("law", ["isotropic", "uniform-angles"])
@pytest.mark.parametrize("v, tau", [(0.3, 1.0), (3.0, 0.6), (1.0, 2.0), (6.0, 0.2)])
def test_anisotropic_ballistic_matches_the_direct_average(law, v, tau):
    """g1 and j of random-ballistic motion = the average of their integrands over sampled directions."""
    rng = np.random.default_rng(int(100 * v + 10 * tau))
    n = 1_000_000
    nx, ny, nz = _directions(law, n, rng)
    sx, sy, sz = (
        cv.amplitude_sigma_lateral_um(18.0),
        cv.amplitude_sigma_lateral_um(4.9),
        cv.amplitude_sigma_axial_um(3.8),
    )
    k = cv.wavenumber_per_um(0.84)
    u = v * tau
    quad = u * u * (nx**2 / sx**2 + ny**2 / sy**2 + nz**2 / sz**2)
    g_mc = np.cos(2 * k * u * nz) * np.exp(-quad / 4)
    j_mc = np.exp(-quad / 2)
    kw = dict(
        speed_um_per_s=v,
        lateral_resolution_um=18.0,
        axial_resolution_um=3.8,
        directions=law,
        lateral_resolution_y_um=4.9,
    )
    g = float(th.g1_ballistic(tau, wavelength_um=0.84, **kw))
    j = float(th.j_ballistic(tau, **kw))
    assert_within_se(g_mc.mean(), g, g_mc.std() / math.sqrt(n), what="g1")
    assert_within_se(j_mc.mean(), j, j_mc.std() / math.sqrt(n), what="j")


@pytest.mark.parametrize("law", ["isotropic", "uniform-angles"])
def test_anisotropic_ballistic_reduces_to_the_isotropic_closed_forms(law):
    """With s_y → s_x the quadrature gives the Faddeeva/Bessel closed forms (to 1e-9) over wide ranges;
    swapping the two lateral widths changes nothing (the direction laws are symmetric in azimuth)."""
    tau = np.geomspace(1e-3, 10.0, 25)
    for lat, ax in ((1.0, 3.8), (4.9, 3.8), (18.0, 3.8), (4.9, 14.0)):
        for v in (0.01, 0.3, 6.0, 30.0):
            kw = dict(speed_um_per_s=v, lateral_resolution_um=lat, axial_resolution_um=ax, directions=law)
            near = dict(kw, lateral_resolution_y_um=lat * (1 + 1e-12))
            assert (
                np.abs(
                    th.g1_ballistic(tau, wavelength_um=0.84, **kw) - th.g1_ballistic(tau, wavelength_um=0.84, **near)
                ).max()
                < 1e-9
            )
            assert np.abs(th.j_ballistic(tau, **kw) - th.j_ballistic(tau, **near)).max() < 1e-9
    a = dict(speed_um_per_s=2.0, axial_resolution_um=3.8, directions=law)
    g_xy = th.g1_ballistic(tau, wavelength_um=0.84, lateral_resolution_um=18.0, lateral_resolution_y_um=4.9, **a)
    g_yx = th.g1_ballistic(tau, wavelength_um=0.84, lateral_resolution_um=4.9, lateral_resolution_y_um=18.0, **a)
    assert np.abs(g_xy - g_yx).max() < 1e-12
    assert np.all(
        th.g1_ballistic(0.0, wavelength_um=0.84, lateral_resolution_um=18.0, lateral_resolution_y_um=4.9, **a) == 1.0
    )


def test_anisotropic_diffusion_and_flow_closed_forms():
    """Diffusion: one factor per axis; flow: the lateral decay follows the azimuth; equal widths: the
    isotropic forms exactly."""
    tau = np.array([0.0, 0.2, 1.0, 6.0])
    sx, sy = cv.amplitude_sigma_lateral_um(18.0), cv.amplitude_sigma_lateral_um(4.9)
    sz = cv.amplitude_sigma_axial_um(3.8)
    k = cv.wavenumber_per_um(0.84)
    D = 0.7
    dt = D * tau
    ref = np.exp(-4 * k * k * dt / (1 + dt / sz**2)) / np.sqrt((1 + dt / sx**2) * (1 + dt / sy**2) * (1 + dt / sz**2))
    kw = dict(lateral_resolution_um=18.0, axial_resolution_um=3.8, lateral_resolution_y_um=4.9)
    assert np.allclose(th.g1_diffusion(tau, diffusion_um2_per_s=D, wavelength_um=0.84, **kw), ref, rtol=1e-13, atol=0)
    jref = 1 / np.sqrt((1 + 2 * dt / sx**2) * (1 + 2 * dt / sy**2) * (1 + 2 * dt / sz**2))
    assert np.allclose(th.j_diffusion(tau, diffusion_um2_per_s=D, **kw), jref, rtol=1e-13, atol=0)
    # flow along x sees s_x, along y sees s_y (the isotropic forms of those widths)
    fl = dict(speed_um_per_s=2.0, polar_angle_deg=90.0, wavelength_um=0.84)
    along_x = th.g1_flow(tau, azimuth_deg=0.0, **fl, **kw)
    along_y = th.g1_flow(tau, azimuth_deg=90.0, **fl, **kw)
    assert np.allclose(along_x, th.g1_flow(tau, **fl, lateral_resolution_um=18.0, axial_resolution_um=3.8), rtol=1e-12)
    assert np.allclose(along_y, th.g1_flow(tau, **fl, lateral_resolution_um=4.9, axial_resolution_um=3.8), rtol=1e-12)
    assert np.allclose(
        th.j_flow(tau, speed_um_per_s=2.0, polar_angle_deg=90.0, azimuth_deg=90.0, **kw),
        np.abs(along_y) ** 2,
        rtol=1e-12,
    )
    for f, extra in (
        (th.g1_diffusion, dict(diffusion_um2_per_s=D, wavelength_um=0.84)),
        (th.j_diffusion, dict(diffusion_um2_per_s=D)),
        (th.g1_flow, dict(speed_um_per_s=1.0, polar_angle_deg=30.0, wavelength_um=0.84, azimuth_deg=40.0)),
    ):
        iso = dict(lateral_resolution_um=4.9, axial_resolution_um=3.8)
        assert np.array_equal(f(tau, **extra, **iso), f(tau, **extra, **iso, lateral_resolution_y_um=4.9))


# ------------------------------------------------------------------------------------------------
# the simulator against the closed forms


CASES = [
    pytest.param(td.Diffusion(diffusion_um2_per_s=0.5), id="diffusion-0.5"),
    pytest.param(td.Diffusion(diffusion_um2_per_s=15.0), id="diffusion-15"),
    pytest.param(td.RandomBallistic(speed_um_per_s=3.0), id="ballistic-iso-3"),
    pytest.param(td.RandomBallistic(speed_um_per_s=0.3, directions="uniform-angles"), id="ballistic-angles-0.3"),
    pytest.param(td.Flow(speed_um_per_s=3.0, polar_angle_deg=70.0, azimuth_deg=90.0), id="flow-along-y"),
    pytest.param(td.Flow(speed_um_per_s=3.0, polar_angle_deg=70.0, azimuth_deg=0.0), id="flow-along-x"),
]


@pytest.mark.parametrize("motion", CASES)
def test_simulator_matches_the_anisotropic_closed_forms(motion):
    """⟨I⟩, C² = 1 + 1/N_eff, g1 and |g1|² + j/N_eff at lags 1, 2, 6 with s_x ≠ s_y (float64 torch path)."""
    res = td.simulate(_scene((motion,)), trials=4096, seed=17, dtype="float64")
    E = res.signals[:, 0, :]
    ne = cv.n_eff(RHO, 18.0, 3.8, lateral_resolution_y_um=4.9)
    mi, se, _ = batch_means(mean_intensity, E)
    assert_within_se(mi.real, cv.mean_intensity(RHO, 18.0, 3.8, lateral_resolution_y_um=4.9), se, what="<I>")
    c2, se, _ = batch_means(contrast2, E)
    assert_within_se(c2.real, 1 + 1 / ne, se, what="C^2")
    lags = np.array([1, 2, 6])
    g1_th, j_th = th.g1_and_j(motion, BSCAN, lags * DT)
    for lag, g, j in zip(lags, np.atleast_1d(g1_th), np.atleast_1d(j_th)):
        est, se_re, se_im = batch_means(g1_at_lag(int(lag)), E)
        assert_within_se(est.real, float(np.real(g)), se_re, what=f"Re g1 lag {lag}")
        assert_within_se(est.imag, float(np.imag(g)), se_im, what=f"Im g1 lag {lag}")
        cov, se, _ = batch_means(cov_at_lag(int(lag)), E)
        assert_within_se(cov.real, float(abs(g) ** 2 + j / ne), se, what=f"cov lag {lag}")


@pytest.mark.parametrize(
    "motion",
    [td.Diffusion(diffusion_um2_per_s=15.0), td.Flow(speed_um_per_s=3.0, polar_angle_deg=70.0, azimuth_deg=90.0)],
    ids=["diffusion", "flow-y"],
)
def test_fused_float32_agrees_with_float64_when_anisotropic(motion):
    """The fused kernel's anisotropic exponent follows the same scatterers as the float64 torch code."""
    sc = _scene((motion,), systems=(BSCAN, HIGH))
    a = td.simulate(sc, trials=64, seed=4, dtype="float32", threads=1).signals.to(torch.complex128)
    b = td.simulate(sc, trials=64, seed=4, dtype="float64", threads=1).signals
    assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max())


def test_equal_y_width_is_bit_identical_to_none():
    motions = (td.Diffusion(diffusion_um2_per_s=2.0), td.Flow(speed_um_per_s=2.0, polar_angle_deg=30.0))
    same = td.OCTSystem(
        name="840-high",
        wavelength_um=0.84,
        lateral_resolution_um=4.9,
        axial_resolution_um=3.8,
        lateral_resolution_y_um=4.9,
    )
    for m in motions:
        for dt in ("float32", "float64"):
            a = td.simulate(_scene((m,), systems=(HIGH,)), trials=70, seed=2, dtype=dt, threads=1).signals
            b = td.simulate(_scene((m,), systems=(same,)), trials=70, seed=2, dtype=dt, threads=1).signals
            assert torch.equal(a, b)


# ------------------------------------------------------------------------------------------------
# the fused kernel and its torch twin


@needs_compiled
@pytest.mark.parametrize("taper", [False, True])
def test_anisotropic_walk_and_paths_are_bit_identical_on_both_backends(taper):
    g = torch.Generator().manual_seed(15)
    counts = torch.randint(0, 60, (7,), generator=g)
    M = int(counts.sum())
    pos = ((torch.rand(3, M, generator=g) * 2 - 1) * torch.tensor([9.0, 4.0, 5.0]).view(3, 1)).contiguous()
    args = dict(
        counts=counts,
        key=777,
        sigmas=[0.8, 1.3, 0.2, 2.5],
        L=(18.0, 8.0, 10.0),
        groups=[(0.1, 0.2, 7.3), (0.03, 0.25)],
        group_of=[0, 1, 0],
        q_turns=[2.38, 1.53, 2.0],
        log_tol=math.log(1e-2),
        taper=taper,
    )
    p1, p2 = pos.clone(), pos.clone()
    a = kernel.walk_periodic(p1, **args)
    b = kernel.walk_periodic(p2, **args, force_torch=True)
    assert torch.equal(p1, p2) and torch.equal(a, b)
    assert bool((a != 0).any())
    # straight paths through an anisotropic PSF (float64 coefficients, float32 evaluation)
    n, c = 70, 40
    u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    p = (u(3, n, c) * 2 - 1) * torch.tensor([12.0, 4.0, 5.0], dtype=torch.float64).view(3, 1, 1)
    v = (u(3, n, c) * 2 - 1) * 3.0
    t_ref = u(n, c) * 6.0
    times = torch.linspace(0.0, 6.2, 31, dtype=torch.float64)
    kw = dict(
        q_turns=[2.38, 1.53],
        a_lat=[0.0247, 0.0833],
        a_ax=[0.213, 0.213],
        ry=[13.5, 1.0],
        log_tol=math.log(1e-2),
        taper=taper,
    )
    pa = kernel.path_fields(p, v, t_ref, times=times, **kw)
    pb = kernel.path_fields(p, v, t_ref, times=times, **kw, force_torch=True)
    assert torch.equal(pa, pb) and bool((pa != 0).any())


# ------------------------------------------------------------------------------------------------
# the renderer


def test_render_uses_the_y_width():
    """B-scan: mean intensity ρ·π^{3/2}·s_x·s_y·s_z; volume: the intensity correlation of neighbouring
    pixels is exp(−Δ²/(2s²)) with s_x along x and s_y along y (physics.md §5.4 across pixels)."""
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render

    system = {
        "name": "b",
        "wavelength_um": 0.84,
        "lateral_resolution_um": 9.0,
        "axial_resolution_um": 3.8,
        "lateral_resolution_y_um": 3.0,
    }

    def phantom(grid):
        return phantom_from_dict(
            {
                "name": "t",
                "system": [system],
                "protocol": {"n_frames": 2, "frame_interval_s": DT},
                "grid": grid,
                "analysis": {"metrics": ["liv"]},
                "background": {"density_per_um3": RHO},
            }
        )

    bscan = phantom({"n_x": 40, "n_z": 40, "pitch_x_um": 12.0, "pitch_z_um": 6.0})
    vals = torch.cat([render(bscan, seed=s, dtype="float64").intensity()[..., 0].reshape(-1) for s in range(4)])
    assert_within_se(
        float(vals.mean()),
        cv.mean_intensity(RHO, 9.0, 3.8, lateral_resolution_y_um=3.0),
        float(vals.std() / math.sqrt(vals.numel())),
        what="<I>",
    )
    vol = phantom(
        {"kind": "volume", "n_x": 24, "n_y": 24, "n_z": 8, "pitch_x_um": 1.5, "pitch_y_um": 1.5, "pitch_z_um": 4.0}
    )
    sx, sy = cv.amplitude_sigma_lateral_um(9.0), cv.amplitude_sigma_lateral_um(3.0)
    est = {("x", 1): [], ("x", 3): [], ("y", 1): [], ("y", 2): []}
    for seed in range(6):
        i = render(vol, seed=seed, dtype="float64").intensity()[..., 0]  # [Y, Z, X]
        for axis, lag in est:
            dim = 2 if axis == "x" else 0
            a = i.narrow(dim, 0, i.shape[dim] - lag).reshape(-1)
            b = i.narrow(dim, lag, i.shape[dim] - lag).reshape(-1)
            a, b = a - a.mean(), b - b.mean()
            est[(axis, lag)].append(float((a * b).sum() / torch.sqrt((a * a).sum() * (b * b).sum())))
    for (axis, lag), v in est.items():
        s = sx if axis == "x" else sy
        v = np.asarray(v)
        assert_within_se(
            v.mean(),
            math.exp(-((1.5 * lag) ** 2) / (2 * s * s)),
            v.std(ddof=1) / math.sqrt(len(v)),
            what=f"{axis} lag {lag}",
        )

"""Truncation of the PSF, hard or tapered (physics.md §5.9): the window and its closed-form moments,
bit identity of the fused kernel's taper and its torch twin, continuity of a scatterer's amplitude as
it enters the PSF, the mean intensity of every sampler against the closed form, and "hard" unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _stats import assert_within_se, batch_means, mean_intensity
from scipy import integrate, stats

import torchdoct as td
from torchdoct import conventions as cv
from torchdoct.sim import kernel

needs_compiled = pytest.mark.skipif(not kernel.compiled(), reason="the compiled kernel was not built")
HIGH = td.OCTSystem(name="840-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
RHO = 0.055


def _window_vec(s: np.ndarray) -> np.ndarray:
    return np.array([cv.taper_window(float(x)) for x in np.atleast_1d(s)])


def test_window_is_one_inside_zero_outside_and_smooth():
    a = cv.TAPER_START
    assert cv.taper_window(0.0) == cv.taper_window(a) == 1.0
    assert cv.taper_window(1.0) == cv.taper_window(1.5) == 0.0
    s = np.linspace(a, 1.0, 20001)
    w = _window_vec(s)
    assert np.all(np.diff(w) <= 0)  # monotone
    h = s[1] - s[0]
    d1 = np.diff(w) / h
    d2 = np.diff(w, 2) / h**2
    # first and second derivatives vanish at both ends (C²): the finite differences go to 0 there
    assert abs(d1[0]) < 1e-3 and abs(d1[-1]) < 1e-3
    assert abs(d2[0]) < 1e-1 and abs(d2[-1]) < 1e-1
    assert abs(d1).max() == pytest.approx(1.875 / (1 - a), rel=1e-3)  # 15/8 of the slope of t


@pytest.mark.parametrize("tol", [0.3, 0.1, 1e-2, 1e-3, 1e-5])
def test_closed_form_moments_match_quadrature(tol):
    """E[(1 − w)²] and E[w²] over X ~ Gamma(3/2) (the |h|²-weighted squared scaled radius) by quadrature."""
    c2 = cv.truncation_radius_factor(tol) ** 2
    g = stats.gamma(1.5)

    def w(x):
        return cv.taper_window(x / c2)

    pts = [cv.TAPER_START * c2, c2]
    err = integrate.quad(lambda x: (1 - w(x)) ** 2 * g.pdf(x), 0, c2, points=pts, limit=400, epsabs=1e-15)[0] + g.sf(c2)
    inten = integrate.quad(lambda x: w(x) ** 2 * g.pdf(x), 0, c2, points=pts, limit=400, epsabs=1e-15)[0]
    assert cv.truncation_field_error(tol, "taper") == pytest.approx(err, rel=1e-9)
    assert cv.truncation_intensity_factor(tol, "taper") == pytest.approx(inten, rel=1e-9)
    assert cv.truncation_field_error(tol, "hard") == cv.truncation_error_bound(tol) == pytest.approx(g.sf(c2), rel=1e-9)
    assert cv.truncation_intensity_factor(tol, "hard") == pytest.approx(g.cdf(c2), rel=1e-12)
    # the taper only ever removes amplitude
    assert cv.truncation_field_error(tol, "taper") > cv.truncation_field_error(tol, "hard")
    assert cv.truncation_intensity_factor(tol, "taper") < cv.truncation_intensity_factor(tol, "hard")
    with pytest.raises(ValueError, match="truncation mode"):
        cv.truncation_field_error(tol, "soft")


def test_documented_numbers():
    assert cv.truncation_field_error(1e-2, "taper") == pytest.approx(9.0e-4, rel=0.01)
    assert cv.truncation_field_error(1e-3, "taper") == pytest.approx(1.8e-5, rel=0.02)
    assert cv.truncation_intensity_factor(1e-2, "taper") == pytest.approx(0.99857, abs=1e-5)
    assert cv.truncation_intensity_factor(1e-3, "taper") == pytest.approx(0.999963, abs=1e-6)


@pytest.mark.parametrize("force_torch", [False, True])
def test_float32_window_matches_the_definition(force_torch):
    log_tol = math.log(1e-2)
    e0, tk = kernel.taper_constants(log_tol, True)
    assert kernel.taper_constants(log_tol, False) == (0.0, 0.0)
    ex = torch.linspace(log_tol, 0.0, 100_001)
    got = kernel.taper_weights(ex, e0, tk, force_torch=force_torch).double()
    ref = torch.tensor(_window_vec(ex.double().numpy() / log_tol))
    assert float((got - ref).abs().max()) < 2e-6
    assert float(got[0]) == 0.0 and float(got[-1]) == 1.0


@needs_compiled
def test_window_and_tapered_kernels_are_bit_identical_on_both_backends():
    g = torch.Generator().manual_seed(8)
    log_tol = math.log(1e-2)
    e0, tk = kernel.taper_constants(log_tol, True)
    ex = -torch.rand(200_003, generator=g) * 5.0
    assert torch.equal(kernel.taper_weights(ex, e0, tk), kernel.taper_weights(ex, e0, tk, force_torch=True))
    n, c, T = 70, 33, 40
    u = lambda: torch.rand(n, c, generator=g)  # noqa: E731
    e, a2 = -5.0 * u(), -3.0 * u() * (u() > 0.1)
    t_star, phi, omega = 8.0 * u() - 1.0, u(), 10.0 * (u() - 0.5)
    times = torch.linspace(0.0, 6.0, T)
    a = kernel.eval_straight(e, a2, t_star, phi, omega, times, log_tol, taper=True)
    b = kernel.eval_straight(e, a2, t_star, phi, omega, times, log_tol, taper=True, force_torch=True)
    assert torch.equal(a, b)
    assert not torch.equal(a, kernel.eval_straight(e, a2, t_star, phi, omega, times, log_tol))


@needs_compiled
def test_a_tapered_simulation_is_bit_identical_on_both_backends(monkeypatch):
    sc = td.Scene(
        systems=(
            HIGH,
            td.OCTSystem(
                name="b",
                wavelength_um=0.84,
                lateral_resolution_um=18.0,
                axial_resolution_um=3.8,
                lateral_resolution_y_um=4.9,
            ),
        ),
        protocol=td.Protocol(n_frames=12, frame_interval_s=0.2048),
        populations=(
            td.Population(density_per_um3=0.03, motion=(td.Diffusion(diffusion_um2_per_s=15.0),)),
            td.Population(density_per_um3=0.02, motion=(td.RandomBallistic(speed_um_per_s=6.0),)),
            td.Population(density_per_um3=0.02, motion=(td.Flow(speed_um_per_s=4.0, polar_angle_deg=45.0),)),
        ),
        simulation=td.SimulationSettings(truncation="taper"),
    )
    a = td.simulate(sc, trials=70, seed=3, threads=1).signals
    monkeypatch.setenv("TORCHDOCT_KERNEL", "torch")
    kernel._library.cache_clear()
    try:
        b = td.simulate(sc, trials=70, seed=3, threads=1).signals
    finally:
        monkeypatch.delenv("TORCHDOCT_KERNEL")
        kernel._library.cache_clear()
    assert torch.equal(a, b)
    hard = td.simulate(sc, trials=70, seed=3, threads=1, truncation="hard").signals
    assert not torch.equal(a, hard)
    # the same scatterers: the taper changes only the amplitudes near the edge of the PSF
    assert float((a - hard).abs().pow(2).mean()) < 0.01 * float(hard.abs().pow(2).mean())


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_scatterer_enters_continuously_with_the_taper(dtype):
    """One path through the PSF, sampled finely: the hard truncation jumps by the tolerance times the
    peak amplitude where it enters and leaves; the taper does not jump."""
    tol = 1e-2
    times = torch.linspace(0.0, 6.0, 60_001, dtype=torch.float64)
    coef = [torch.tensor([[x]], dtype=torch.float64) for x in (0.0, -1.0, 3.0, 0.0, 0.0)]  # e*, a2, t*, φ, ω
    sim = __import__("importlib").import_module("torchdoct.sim.samplers")
    jumps = {}
    for taper in (False, True):
        amp = sim._eval_straight(*coef, times, math.log(tol), 1.0, getattr(torch, dtype), taper)[0].abs().double()
        jumps[taper] = float(amp.diff().abs().max())
        assert float(amp.max()) == pytest.approx(1.0, abs=1e-6)
    assert jumps[False] == pytest.approx(tol, rel=0.02)
    assert jumps[True] < 1e-3  # the steepest slope of the smooth amplitude over one time step (1e-4 s)


def _scene(motion, **sim):
    return td.Scene(
        systems=(HIGH,),
        protocol=td.Protocol(n_frames=4, frame_interval_s=0.2048),
        populations=(td.Population(density_per_um3=RHO, motion=motion),),
        analysis=td.Analysis(metrics=("liv",)),
        simulation=td.SimulationSettings(**sim),
    )


@pytest.mark.parametrize(
    "motion, hard_ellipsoid",
    [
        ((), False),  # static: the box, untruncated inside it when hard
        ((td.Diffusion(diffusion_um2_per_s=1.0),), True),  # periodic walk
        ((td.Flow(speed_um_per_s=2.0, polar_angle_deg=30.0),), True),  # straight paths
        (
            (td.Diffusion(diffusion_um2_per_s=0.5), td.Flow(speed_um_per_s=1.0, polar_angle_deg=60.0)),
            False,
        ),  # walk with drift
    ],
    ids=["static", "diffusion", "flow", "diffusion-and-flow"],
)
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_mean_intensity_is_the_closed_form_of_the_window(motion, hard_ellipsoid, dtype):
    """⟨I⟩ = E[w²]·ρπ^{3/2}s_x²s_z at a coarse tolerance (0.3) where the window's share is resolved."""
    tol = 0.3
    full = cv.mean_intensity(RHO, 4.9, 3.8)
    for mode in ("hard", "taper"):
        if mode == "hard" and not hard_ellipsoid:
            continue
        res = td.simulate(_scene(motion, truncation=mode, truncation_tolerance=tol), trials=4096, seed=12, dtype=dtype)
        mi, se, _ = batch_means(mean_intensity, res.signals[:, 0, :])
        assert_within_se(mi.real, cv.truncation_intensity_factor(tol, mode) * full, se, what=f"<I> {mode}")


def test_taper_is_the_default():
    sc = _scene((td.Flow(speed_um_per_s=2.0, polar_angle_deg=30.0),))
    assert sc.simulation.truncation == "taper"
    a = td.simulate(sc, trials=64, seed=1, threads=1).signals
    assert torch.equal(a, td.simulate(sc, trials=64, seed=1, threads=1, truncation="taper").signals)
    assert not torch.equal(a, td.simulate(sc, trials=64, seed=1, threads=1, truncation="hard").signals)
    with pytest.raises(ValueError, match="truncation must be one of"):
        td.simulate(sc, trials=64, truncation="soft")
    plan = td.make_plan(sc)
    assert plan.truncation == "taper"
    assert plan.truncation_error_bound == cv.truncation_field_error(1e-2, "taper")
    assert "tapered to 0" in plan.describe()
    hard = td.make_plan(sc.replace(simulation=td.SimulationSettings(truncation="hard")))
    assert hard.truncation_error_bound == cv.truncation_error_bound(1e-2)


def test_scene_setting_round_trips():
    from torchdoct.sim.config import scene_from_dict

    sc = _scene((), truncation="hard")
    d = sc.to_dict()
    assert d["simulation"]["truncation"] == "hard"
    assert scene_from_dict(d) == sc
    assert "truncation" not in _scene(()).to_dict()["simulation"]  # the default (taper) is left out
    assert scene_from_dict(_scene((), truncation="taper").to_dict()) == _scene(())


@pytest.mark.parametrize("mode", ["hard", "taper"])
def test_rendered_mean_intensity_is_the_product_of_the_axis_windows(mode):
    """The renderer truncates each axis's window separately (a box): ⟨I⟩ = ρπ^{3/2}s_x s_y s_z·Π_a f,
    f = ∫_{−c}^{c} e^{−u²}·w(u²/c²)² du/√π (w = 1 when hard), at a coarse tolerance (0.5) where the
    window's share is resolved (0.739 hard, 0.669 taper of the full ⟨I⟩; SE ≈ 1 %); pixels 20 µm apart are independent."""
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render

    tol = 0.5
    c = cv.truncation_radius_factor(tol)
    w = (lambda u: cv.taper_window(u * u / (c * c))) if mode == "taper" else (lambda u: 1.0)
    f = integrate.quad(
        lambda u: math.exp(-u * u) * w(u) ** 2,
        -c,
        c,
        points=[-c * math.sqrt(cv.TAPER_START), c * math.sqrt(cv.TAPER_START)],
    )[0]
    f /= math.sqrt(math.pi)
    system = {
        "name": "b",
        "wavelength_um": 0.84,
        "lateral_resolution_um": 4.9,
        "axial_resolution_um": 3.8,
        "lateral_resolution_y_um": 9.0,
    }
    ph = phantom_from_dict(
        {
            "name": "t",
            "system": [system],
            "protocol": {"n_frames": 2, "frame_interval_s": 0.2048},
            "grid": {"n_x": 50, "n_z": 50, "pitch_x_um": 20.0, "pitch_z_um": 20.0},
            "analysis": {"metrics": ["liv"]},
            "background": {"density_per_um3": RHO},
            "simulation": {"truncation": mode, "truncation_tolerance": tol},
        }
    )
    vals = torch.cat([render(ph, seed=s, dtype="float64").intensity()[..., 0].reshape(-1) for s in range(6)])
    ref = f**3 * cv.mean_intensity(RHO, 4.9, 3.8, lateral_resolution_y_um=9.0)
    assert_within_se(float(vals.mean()), ref, float(vals.std() / math.sqrt(vals.numel())), what=f"<I> {mode}")

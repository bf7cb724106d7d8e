"""Simulator kernel: the straight-path evaluation against the closed form, the component-major draws
and compaction against their stacked definitions, and bit-identical results whatever the chunk
(the straight-path sampler computes only the slots below the chunk's largest count)."""

from __future__ import annotations

import importlib
import math

import pytest
import torch

import torchdoct as td
from torchdoct.sim.plan import BLOCK_TRIALS

sim = importlib.import_module("torchdoct.sim.samplers")
streams = importlib.import_module("torchdoct.sim.streams")

HIGH = td.OCTSystem(name="840-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
AX14 = td.OCTSystem(name="840-ax14", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=14.0)
LAT18 = td.OCTSystem(name="840-lat18", wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8)


def _random_paths(n: int, c: int, seed: int):
    """Coefficients (e*, a2, t*, φ*, ω) of random straight paths, float64 [n, c]; about a third never
    reach the tolerance 1e-2 (e* < ln 1e-2) and some stand still (a2 = 0)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda: torch.rand(n, c, generator=g, dtype=torch.float64)  # noqa: E731
    e = -7.0 * u()
    a2 = -3.0 * u() * (u() > 0.1)
    t_star = 8.0 * u() - 1.0
    phi = 2.0 * math.pi * u()
    omega = 40.0 * (u() - 0.5)
    return e, a2, t_star, phi, omega


def _direct(e, a2, t_star, phi, omega, times, tol):
    """Σ_paths exp(e* + a2·τ²)·exp(i(φ* + ω·τ)), terms with exponent below ln tol set to 0 (float64)."""
    tau = times[None, None, :] - t_star[..., None]
    ex = e[..., None] + a2[..., None] * tau * tau
    amp = torch.where(ex >= math.log(tol), torch.exp(ex), torch.zeros_like(ex))
    ph = phi[..., None] + omega[..., None] * tau
    return torch.complex((amp * torch.cos(ph)).sum(1), (amp * torch.sin(ph)).sum(1))


@pytest.mark.parametrize("n_frames", [32, 150])  # one tile, and tiles of 64 frames with per-tile packing
def test_straight_paths_match_the_closed_form_with_truncation(n_frames):
    tol = 1e-2
    coef = _random_paths(BLOCK_TRIALS + 6, 40, seed=n_frames)  # a full block and a partial one
    times = torch.linspace(0.0, 6.0, n_frames, dtype=torch.float64)
    ref = _direct(*coef, times, tol)
    scale = float(ref.abs().max())
    got64 = sim._eval_straight(*coef, times, math.log(tol), 1.0, torch.float64)
    assert got64.dtype == torch.complex128
    assert float((got64 - ref).abs().max()) <= 1e-12 * scale
    # float32: the time offset τ is rounded to float32 (|τ| ≤ 7 s, ω ≤ 20 rad/s): phase error ≲ 1e-5
    got32 = sim._eval_straight(*coef, times, math.log(tol), 1.0, torch.float32)
    assert got32.dtype == torch.complex64
    assert float((got32.to(torch.complex128) - ref).abs().max()) <= 1e-4 * scale
    # reflectivity scales the field
    half = sim._eval_straight(*coef, times, math.log(tol), 0.5, torch.float64)
    torch.testing.assert_close(half, 0.5 * got64, rtol=1e-12, atol=1e-12 * scale)


def test_truncation_keeps_terms_at_the_tolerance_and_drops_them_below():
    """One path per trial with exponent e* + a2·τ² crossing ln tol: frames above it carry exactly the
    term, frames below it exactly 0."""
    tol = 1e-2
    times = torch.arange(16, dtype=torch.float64) * 0.25
    t_star = torch.full((BLOCK_TRIALS, 1), 2.0, dtype=torch.float64)
    a2 = torch.full_like(t_star, -2.0)
    e = torch.full_like(t_star, -1.0)
    zero = torch.zeros_like(t_star)
    out = sim._eval_straight(e, a2, t_star, zero, zero, times, math.log(tol), 1.0, torch.float64)
    ex = -1.0 - 2.0 * (times - 2.0) ** 2
    above = ex >= math.log(tol)
    assert 0 < int(above.sum()) < times.numel()
    assert torch.equal(out[0].real[~above], torch.zeros(int((~above).sum()), dtype=torch.float64))
    torch.testing.assert_close(out[0].real[above], torch.exp(ex[above]), rtol=1e-14, atol=0.0)
    assert torch.equal(out, out[:1].expand_as(out))  # every trial the same


def _reference_compact(mask, cap, t):
    """The definition: a stable sort of the True entries of each row to its front."""
    order = torch.argsort((~mask).to(torch.int8), dim=1, stable=True)[:, :cap]
    return t.gather(-1, order.expand(*t.shape[:-2], *order.shape))


def test_compact_moves_entries_to_the_front_in_order():
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(70, 90, generator=g) < 0.4
    comps = torch.randn(3, 70, 90, generator=g, dtype=torch.float64)
    times = torch.rand(70, 90, generator=g, dtype=torch.float64)
    cap = int(mask.sum(1).max()) + 5
    valid, (c_out, t_out) = sim._compact(mask, cap, "test", comps, times, fill=(7.0, -1.0))
    assert torch.equal(valid.sum(1), mask.sum(1))
    assert torch.equal(valid, torch.arange(cap)[None, :] < mask.sum(1)[:, None])
    ref_c, ref_t = _reference_compact(mask, cap, comps), _reference_compact(mask, cap, times)
    assert torch.equal(c_out[:, valid], ref_c[:, valid]) and torch.equal(t_out[valid], ref_t[valid])
    assert bool((c_out[:, ~valid] == 7.0).all()) and bool((t_out[~valid] == -1.0).all())
    # keep: only as many slots as the largest count
    valid_k, (c_k,) = sim._compact(mask, cap, "test", comps, keep=True)
    assert valid_k.shape[1] == int(mask.sum(1).max()) and torch.equal(c_k[:, valid_k], ref_c[:, valid])
    with pytest.raises(streams.CapacityError, match="exceed the 3 reserved slots"):
        sim._compact(mask, 3, "test", comps)


def _draws(seed: int, blocks: int = 2):
    return streams.Draws([streams.block_generator(seed, b) for b in range(blocks)], torch.device("cpu"))


def test_drift_paths_follow_their_laws():
    """Initial paths fill the ellipsoid uniformly (|p/H|³ uniform on [0, 1]); entrants start on its
    surface moving inward, at times uniform on [0, T]; velocities have the law's speed and directions
    (isotropic: ⟨cos²θ⟩ = 1/3; uniform angles: ⟨cos²θ⟩ = 1/2)."""
    from scipy import stats

    from torchdoct.sim import kernel

    H, T, N = (9.0, 8.0, 11.0), 6.5, 64 * 40
    n0 = torch.full((N,), 30)
    n_prop = torch.full((N,), 20)
    for law, mean_mu2 in ((0, 1.0 / 3.0), (1, 0.5)):
        w_max = 6.0 / min(H)
        p, v, t_ref, count = kernel.drift_paths(
            list(range(7, 47)), n0, n_prop, H, (0.0, 0.0, 0.0), [(6.0, law)], w_max, T, 20
        )
        x = [p[i] / H[i] for i in range(3)]
        r3 = (x[0] ** 2 + x[1] ** 2 + x[2] ** 2) ** 1.5
        slot = torch.arange(p.shape[2])[None, :].expand(N, -1)
        first = slot < 30
        assert stats.kstest(r3[first].numpy(), "uniform").pvalue > 1e-4
        speed = torch.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)[first]
        # the azimuth's sin/cos are float32 polynomials (kernel.sincos_turns): unit length to 2 float32 ulp
        torch.testing.assert_close(speed, torch.full_like(speed, 6.0), rtol=2.0**-22, atol=0.0)
        mu2 = (v[2][first] / 6.0) ** 2
        n = mu2.numel()
        assert abs(float(mu2.mean()) - mean_mu2) < 5 * float(mu2.std()) / math.sqrt(n)
        # entrants: on the surface, inward, uniform times
        later = (slot >= 30) & (slot < count[:, None])
        assert int(later.sum()) > 1000
        torch.testing.assert_close(r3[later], torch.ones_like(r3[later]), rtol=2.0**-20, atol=0.0)  # float32 sin/cos
        inward = sum(x[i][later] * v[i][later] / H[i] for i in range(3))
        assert bool((inward < 0).all())
        assert stats.kstest(t_ref[later].numpy() / T, "uniform").pvalue > 1e-4
        assert bool((p[0][~(first | later)] == 1e6).all()) and bool((v[:, ~(first | later)] == 0).all())


@pytest.mark.parametrize(
    "motion",
    [
        (td.RandomBallistic(speed_um_per_s=4.0, directions="uniform-angles"),),
        (td.Flow(speed_um_per_s=5.0, polar_angle_deg=45.0),),
        (td.Diffusion(diffusion_um2_per_s=3.0),),
    ],
)
def test_bit_identical_whatever_the_chunk_with_systems_of_different_boxes(motion):
    """Three PSF boxes (each system group evaluates its own culled paths), a second static population
    of another reflectivity; the slots computed follow each chunk's largest count, the numbers do not."""
    sc = td.Scene(
        systems=(HIGH, AX14, LAT18),
        protocol=td.Protocol(n_frames=12, frame_interval_s=0.25),
        populations=(
            td.Population(density_per_um3=0.04, motion=motion),
            td.Population(density_per_um3=0.01, reflectivity=0.6, motion=()),
        ),
        analysis=td.Analysis(metrics=("liv",)),
    )
    ref = td.simulate(sc, trials=200, seed=11, threads=1, chunk_trials=64).signals
    for chunk, threads in ((256, 1), (128, 2), (None, 2)):
        out = td.simulate(sc, trials=200, seed=11, threads=threads, chunk_trials=chunk).signals
        assert torch.equal(out, ref), (chunk, threads)
    # fewer trials: the same first trials
    assert torch.equal(td.simulate(sc, trials=70, seed=11, threads=1).signals, ref[:70])
    assert bool(torch.isfinite(ref.real).all()) and float(ref.abs().max()) > 0.0

"""The reference simulator against the closed forms of physics.md §5 (slow): is it trustworthy?

Pooled ensemble estimators over all trials and frame pairs (physics.md §6):
``ĝ1(m) = ⟨E_i E*_{i+m}⟩/⟨I⟩`` (complex; §5.3 sign convention) and
``ĉ(m) = ⟨I_i I_{i+m}⟩/⟨I⟩² − 1 = |g1|² + j/N_eff`` (§5.4), and ``⟨I⟩`` against ρ·π^{3/2}·s_x·s_y·s_z
(§5.2). Standard errors by 64 batch means of trials; the |z| bound is Bonferroni over the test's
comparisons (refcompare.z_bound, family-wise 1e-3). The isotropic-lateral closed forms are those of
:mod:`torchdoct.sim.theory`; for an anisotropic lateral PSF (s_x ≠ s_y, a B-scan's x-only reduction)
they are written here from §5.3/§5.4, which factor per axis:

* flow: ``g1 = exp(−i·2kn·v_z·τ − Σ_a v_a²τ²/(4 s_a²))``, ``j = |g1|²``;
* diffusion: ``g1 = exp(−4(kn)²Dτ/(1 + Dτ/s_z²)) / √(Π_a (1 + Dτ/s_a²))``,
  ``j = 1/√(Π_a (1 + 2Dτ/s_a²))``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import refcompare as rc
import refsim

from torchdoct.sim import theory

pytestmark = pytest.mark.slow

LAGS = (1, 2, 4, 8, 16, 31)
DT = 0.2048
RHO = 0.05


def _theory_isotropic(motion: refsim.Motion, cfg: int, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    _, wl, lat, ax, _ = rc.CONFIGS[cfg]
    res = dict(lateral_resolution_um=lat, axial_resolution_um=ax)
    if motion.kind == "diffusion":
        g1 = theory.g1_diffusion(taus, diffusion_um2_per_s=motion.diffusion_um2_per_s, wavelength_um=wl, **res)
        j = theory.j_diffusion(taus, diffusion_um2_per_s=motion.diffusion_um2_per_s, **res)
    elif motion.kind == "ballistic":
        g1 = theory.g1_ballistic(
            taus, speed_um_per_s=motion.speed_um_per_s, wavelength_um=wl, directions=motion.directions, **res
        )
        j = theory.j_ballistic(taus, speed_um_per_s=motion.speed_um_per_s, directions=motion.directions, **res)
    else:
        g1 = theory.g1_flow(
            taus, speed_um_per_s=motion.speed_um_per_s, polar_angle_deg=motion.polar_angle_deg, wavelength_um=wl, **res
        )
        j = theory.j_flow(taus, speed_um_per_s=motion.speed_um_per_s, polar_angle_deg=motion.polar_angle_deg, **res)
    return np.asarray(g1, dtype=np.complex128), np.asarray(j, dtype=np.float64)


def _theory_anisotropic(motion: refsim.Motion, optics: refsim.Optics, taus: np.ndarray):
    s = np.array(optics.sigmas_um)
    kn = optics.kn
    if motion.kind == "flow":
        v = motion.flow_velocity
        g1 = np.exp(-2j * kn * v[2] * taus - (taus[:, None] ** 2 * v**2 / (4 * s**2)).sum(1))
        return g1, np.abs(g1) ** 2
    d = motion.diffusion_um2_per_s * taus
    r = 1.0 + d[:, None] / s**2
    g1 = np.exp(-4 * kn**2 * d / r[:, 2]) / np.sqrt(r.prod(1))
    j = 1.0 / np.sqrt((1.0 + 2.0 * d[:, None] / s**2).prod(1))
    return g1.astype(np.complex128), j


def _check(e: np.ndarray, optics: refsim.Optics, g1: np.ndarray, j: np.ndarray) -> None:
    """⟨I⟩, ĝ1 (Re, Im) and ĉ at LAGS against theory, SE from 64 batch means of trials."""
    sx, sy, sz = optics.sigmas_um
    n_eff = RHO * (2 * math.pi) ** 1.5 * sx * sy * sz
    i_theory = refsim.mean_intensity(optics, RHO)
    inten = np.abs(e) ** 2

    def stats(ee: np.ndarray, ii: np.ndarray) -> np.ndarray:
        mi = ii.mean()
        out = [mi / i_theory - 1.0]
        for m in LAGS:
            g = (ee[:, :-m] * np.conj(ee[:, m:])).mean() / mi
            c = (ii[:, :-m] * ii[:, m:]).mean() / mi**2 - 1.0
            out += [g.real, g.imag, c]
        return np.array(out)

    full = stats(e, inten)
    batches = np.array([stats(a, b) for a, b in zip(np.array_split(e, 64), np.array_split(inten, 64))])
    se = batches.std(0, ddof=1) / 8.0
    expect = [0.0]
    for k in range(len(LAGS)):
        expect += [g1[k].real, g1[k].imag, abs(g1[k]) ** 2 + j[k] / n_eff]
    expect = np.array(expect)
    labels = ["<I> rel"] + [f"{w}({m})" for m in LAGS for w in ("Re g1", "Im g1", "cov")]
    z = (full - expect) / se
    bound = rc.z_bound(len(z))
    bad = [
        f"{lab}: {f:.5f} vs {x:.5f} (SE {s:.5f}, z {zz:+.1f})"
        for lab, f, x, s, zz in zip(labels, full, expect, se, z)
        if abs(zz) > bound
    ]
    assert not bad, f"|z| > {bound:.2f}: " + "; ".join(bad)


_ISO_CASES = [
    ("diffusion D=0.005", refsim.Motion("diffusion", diffusion_um2_per_s=0.005), 0, 1536),
    ("diffusion D=0.05", refsim.Motion("diffusion", diffusion_um2_per_s=0.05), 0, 1536),
    ("ballistic iso v=0.1", refsim.Motion("ballistic", speed_um_per_s=0.1), 0, 1536),
    (
        "ballistic uniform-angles v=0.1",
        refsim.Motion("ballistic", speed_um_per_s=0.1, directions="uniform-angles"),
        0,
        1536,
    ),
    ("flow v=0.5 θ=0°", refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=0.0), 0, 1536),
    ("flow v=0.5 θ=20°", refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=20.0, azimuth_deg=30.0), 0, 1536),
    ("flow v=1 θ=45°", refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=45.0, azimuth_deg=200.0), 0, 1536),
    ("flow v=0.5 θ=90°", refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=90.0), 0, 1536),
    ("flow v=0.5 θ=20° axial=14", refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=20.0), 1, 1024),
    ("diffusion D=0.002 axial=14", refsim.Motion("diffusion", diffusion_um2_per_s=0.002), 1, 1024),
    ("flow v=1 θ=70° lateral=18", refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=70.0), 2, 512),
    ("ballistic iso v=0.3 lateral=18", refsim.Motion("ballistic", speed_um_per_s=0.3), 2, 512),
]


@pytest.mark.parametrize("name,motion,cfg,trials", _ISO_CASES, ids=[c[0] for c in _ISO_CASES])
def test_reference_matches_closed_forms(name, motion, cfg, trials):
    _, wl, lat, ax, _ = rc.CONFIGS[cfg]
    optics = refsim.Optics(wl, lat, ax)
    e = refsim.simulate(
        optics, motion, density_per_um3=RHO, n_frames=32, frame_interval_s=DT, trials=trials, seed=101 + cfg
    )[:, 0]
    g1, j = _theory_isotropic(motion, cfg, np.array(LAGS) * DT)
    _check(e, optics, g1, j)


_ANISO_CASES = [
    (
        "flow v=1 θ=60° az=30° x=18 y=4.9",
        refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=60.0, azimuth_deg=30.0),
    ),
    (
        "flow v=1 θ=60° az=120° x=18 y=4.9",
        refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=60.0, azimuth_deg=120.0),
    ),
    ("diffusion D=0.05 x=18 y=4.9", refsim.Motion("diffusion", diffusion_um2_per_s=0.05)),
    ("diffusion D=0.5 x=18 y=4.9", refsim.Motion("diffusion", diffusion_um2_per_s=0.5)),
]


@pytest.mark.parametrize("name,motion", _ANISO_CASES, ids=[c[0] for c in _ANISO_CASES])
def test_reference_anisotropic_lateral_psf(name, motion):
    """A B-scan's x-only lateral reduction: Δx = 18 µm, Δy = 4.9 µm, Δz = 3.8 µm at 840 nm."""
    optics = refsim.Optics(0.84, 18.0, 3.8, lateral_y_um=4.9)
    e = refsim.simulate(optics, motion, density_per_um3=RHO, n_frames=32, frame_interval_s=DT, trials=1024, seed=202)[
        :, 0
    ]
    g1, j = _theory_anisotropic(motion, optics, np.array(LAGS) * DT)
    _check(e, optics, g1, j)

"""Simulator properties: reproducibility, plan = work, hard cases, noise, float32 vs float64."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch
from _stats import assert_within_se, batch_means, g1_at_lag

import torchdoct as td
from torchdoct.conventions import mean_intensity as mean_intensity_theory
from torchdoct.conventions import n_eff
from torchdoct.sim import theory as th
from torchdoct.sim.plan import make_plan

sim = importlib.import_module("torchdoct.sim.samplers")
streams = importlib.import_module("torchdoct.sim.streams")

DT = 0.2048
HIGH = td.OCTSystem(name="840-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
W1310 = td.OCTSystem(name="1310-high", wavelength_um=1.31, lateral_resolution_um=4.9, axial_resolution_um=3.8)
AX14 = td.OCTSystem(name="840-ax14", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=14.0)


def scene(
    motion=(),
    *,
    systems=(HIGH,),
    rho=0.055,
    n_frames=32,
    noise=None,
    metrics=("liv", "ocds"),
    delay=(0.2048, 1.2288),
    populations=None,
    times=None,
):
    protocol = (
        td.Protocol(n_frames=n_frames, frame_interval_s=DT)
        if times is None
        else td.Protocol(n_frames=len(times), frame_times_s=tuple(times))
    )
    pops = populations or (td.Population(density_per_um3=rho, motion=tuple(motion)),)
    return td.Scene(
        systems=tuple(systems),
        protocol=protocol,
        populations=pops,
        noise=noise,
        analysis=td.Analysis(metrics=metrics, ocds_delay_range_s=delay),
    )


MOTIONS = {
    "static": (),
    "diffusion": (td.Diffusion(diffusion_um2_per_s=0.2),),
    "ballistic": (td.RandomBallistic(speed_um_per_s=1.0),),
    "flow": (td.Flow(speed_um_per_s=1.0, polar_angle_deg=45.0),),
    "diffusion+flow": (td.Diffusion(diffusion_um2_per_s=0.05), td.Flow(speed_um_per_s=0.5, polar_angle_deg=90.0)),
}


# ------------------------------------------------------------------------------------------------
# reproducibility


@pytest.mark.parametrize("kind", list(MOTIONS))
def test_same_seed_bit_identical_whatever_chunking(kind):
    sc = scene(MOTIONS[kind], systems=(HIGH, AX14), n_frames=8, noise=td.Noise(snr_db=25.0), delay=(0.2048, 0.6144))
    a = td.simulate(sc, trials=150, seed=3, chunk_trials=64)
    b = td.simulate(sc, trials=150, seed=3, chunk_trials=1000)
    c = td.simulate(sc, trials=300, seed=3, chunk_trials=128)
    assert torch.equal(a.signals, b.signals)
    assert torch.equal(a.signals, c.signals[:150])
    d = td.simulate(sc, trials=150, seed=4)
    assert not torch.equal(a.signals, d.signals)


def test_systems_share_one_realization():
    """Two identical systems under different names see exactly the same scatterers."""
    twin = td.OCTSystem(name="twin", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    for motion in MOTIONS.values():
        res = td.simulate(
            scene(motion, systems=(HIGH, AX14, twin), n_frames=8, delay=(0.2048, 0.6144)), trials=64, seed=1
        )
        assert torch.equal(res.signals[:, 0], res.signals[:, 2])


def test_does_not_touch_global_rng_or_default_dtype():
    state = torch.get_rng_state()
    td.simulate(scene(MOTIONS["diffusion"], n_frames=4, metrics=("liv",)), trials=64, seed=0, dtype="float64")
    assert torch.equal(state, torch.get_rng_state())
    assert torch.get_default_dtype() == torch.float32


# ------------------------------------------------------------------------------------------------
# the plan names exactly the work that runs


class _Counter:
    def __init__(self, monkeypatch):
        self.calls: list[tuple[str, tuple]] = []
        self.summed = 0
        orig_draw = streams.Draws._draw
        orig_sum = sim._sum_field
        orig_sparse = sim._eval_straight

        def draw(this, fn, shape):
            self.calls.append((fn.__name__, tuple(shape)))
            return orig_draw(this, fn, shape)

        def sum_field(amp, phase, dim):
            self.summed += amp.numel()
            return orig_sum(amp, phase, dim)

        def sparse(*args, **kw):
            out = orig_sparse(*args, **kw)
            self.summed += int((out != 0).sum())
            return out

        monkeypatch.setattr(streams.Draws, "_draw", draw)
        monkeypatch.setattr(sim, "_sum_field", sum_field)
        monkeypatch.setattr(sim, "_eval_straight", sparse)

    def normals(self):
        return [c for c in self.calls if c[0] == "randn"]


@pytest.mark.parametrize("kind", ["static", "ballistic", "flow"])
def test_no_per_frame_draws_and_no_noise_unless_asked(kind, monkeypatch):
    counts = {}
    duration = 7 * DT
    for n_frames in (8, 32):
        ctr = _Counter(monkeypatch)
        sc = td.Scene(
            systems=(HIGH,),
            protocol=td.Protocol(n_frames=n_frames, frame_interval_s=duration / (n_frames - 1)),
            populations=(td.Population(density_per_um3=0.055, motion=MOTIONS[kind]),),
            analysis=td.Analysis(metrics=("liv",)),
        )
        plan = make_plan(sc)
        assert "noise" not in plan.stages and "random walk (per-frame draws)" not in plan.stages
        assert all(not p.per_frame_random_draws for p in plan.populations)
        td.simulate(sc, trials=64, seed=0)
        assert ctr.normals() == []  # no noise stage, no random walk
        counts[n_frames] = (sum(math.prod(s) for _, s in ctr.calls), ctr.summed)
    # over the same duration, the random numbers drawn do not grow with the number of frames
    assert counts[8][0] == counts[32][0]
    if kind == "static":
        # one evaluation per scatterer, whatever the number of frames
        assert counts[8][1] == counts[32][1]
        assert make_plan(scene((), n_frames=32)).stages == (
            "seed scatterers",
            "signal (one evaluation, constant over frames)",
            "metrics",
        )


def test_noise_stage_draws_once_per_frame_and_system(monkeypatch):
    ctr = _Counter(monkeypatch)
    sc = scene((), systems=(HIGH, W1310), n_frames=8, noise=td.Noise(snr_db=20.0), delay=(0.2048, 0.6144))
    assert "noise" in make_plan(sc).stages
    td.simulate(sc, trials=64, seed=0)
    assert ctr.normals() == [("randn", (2, 8)), ("randn", (2, 8))]


def test_zero_parameter_motion_is_static():
    motion = (td.Diffusion(diffusion_um2_per_s=0.0), td.Flow(speed_um_per_s=0.0, polar_angle_deg=30.0))
    sc = scene(motion, n_frames=8, delay=(0.2048, 0.6144))
    assert make_plan(sc).populations[0].sampler == "static"
    a = td.simulate(sc, trials=64, seed=2)
    b = td.simulate(scene((), n_frames=8, delay=(0.2048, 0.6144)), trials=64, seed=2)
    assert torch.equal(a.signals, b.signals)


def test_plan_counts_match_the_work(monkeypatch):
    """Expected scatterers per trial (plan) against the mean number the simulator actually used."""
    seen = []
    real = sim._eval_culled

    def spy(pp, pop, p_ref, *args):
        seen.append((p_ref[0] < 0.5 * sim._FAR).sum(1).double())  # [3, N, C]
        return real(pp, pop, p_ref, *args)

    monkeypatch.setattr(sim, "_eval_culled", spy)
    for kind in ("static", "ballistic", "flow"):
        seen.clear()
        sc = scene(MOTIONS[kind], n_frames=8, delay=(0.2048, 0.6144))
        mean = make_plan(sc).populations[0].expected_scatterers_per_trial
        td.simulate(sc, trials=512, seed=0)
        n = torch.cat(seen)
        assert abs(float(n.mean()) - mean) <= 4 * math.sqrt(mean / n.numel()), kind  # Poisson counts
    # the random walk draws one Poisson count per trial for its periodic cell
    pp = make_plan(scene(MOTIONS["diffusion"], n_frames=8, delay=(0.2048, 0.6144))).populations[0]
    draws = streams.Draws([streams.block_generator(0, b) for b in range(8)], torch.device("cpu"))
    n = draws.poisson(pp.expected_scatterers_per_trial, pp.capacity, "test")
    mean = pp.expected_scatterers_per_trial
    assert abs(float(n.double().mean()) - mean) <= 4 * math.sqrt(mean / n.numel())


# ------------------------------------------------------------------------------------------------
# hard cases


def test_zero_motion_gives_exact_zeros():
    res = td.simulate(scene((), n_frames=32), trials=256, seed=1)
    m = res.metrics()
    assert not bool(m["zero_intensity"].any())
    assert torch.equal(m["liv"], torch.zeros_like(m["liv"]))
    assert torch.equal(m["ocds"], torch.zeros_like(m["ocds"]))


@pytest.mark.parametrize("truncation", ["hard", "taper"])
def test_sparse_volume_policy(truncation):
    """Trials with no scatterer in the truncated PSF have I = 0: counted, NaN metrics, excluded.

    The hard cut keeps every scatterer of the PSF box (amplitudes below the tolerance in its corners
    included); the taper reaches exactly 0 on the tolerance ellipsoid inscribed in the box, whose
    volume is π/6 of the box's: P(empty) = exp(−ρ·V) with V the box or the ellipsoid."""
    plan = make_plan(scene((), n_frames=4, metrics=("liv",)))
    box = 8 * math.prod(plan.populations[0].domain_half_widths_um)
    rho = 1.5 / box  # 1.5 scatterers expected in the box
    sc = scene((), rho=rho, n_frames=4, metrics=("liv",))
    res = td.simulate(sc, trials=8192, seed=6, truncation=truncation)
    m = res.metrics()
    zero = m["zero_intensity"][:, 0]
    p = math.exp(-1.5 * (1.0 if truncation == "hard" else math.pi / 6.0))
    assert_within_se(float(zero.double().mean()), p, math.sqrt(p * (1 - p) / zero.numel()), what="P(empty)")
    assert torch.isnan(m["liv"][zero, 0]).all()
    assert torch.isfinite(m["liv"][~zero, 0]).all()
    s = res.summary()["840-high"]
    assert s["zero_intensity_trials"] == int(zero.sum())
    assert s["liv"]["n"] == int((~zero).sum())
    assert math.isfinite(s["liv"]["mean"])


@pytest.mark.slow  # longer than the default suite allows one test (CONTRIBUTING.md, markers)
def test_crowded_volume_is_gaussian_speckle():
    """ENS 1e4: bounded chunks, C² → 1 and P(I > ⟨I⟩) → e^-1 (circular Gaussian field)."""
    rho = 1e4 / HIGH.lateral_resolution_um**2 / HIGH.axial_resolution_um
    sc = scene((), rho=rho, n_frames=2, metrics=("liv",))
    plan = make_plan(sc)
    assert plan.systems[0].ens_paper == pytest.approx(1e4)
    res = td.simulate(sc, trials=256, seed=8, dtype="float64")
    I = res.intensity[:, 0, 0]
    mi = mean_intensity_theory(rho, 4.9, 3.8)
    assert_within_se(float(I.mean()), mi, float(I.std() / math.sqrt(I.numel())), what="<I>")
    frac = float((I > I.mean()).double().mean())
    assert_within_se(frac, math.exp(-1), math.sqrt(0.2325 / I.numel()), what="P(I > <I>)")
    c2 = float(I.var() / I.mean() ** 2)
    assert_within_se(c2, 1.0 + 1.0 / n_eff(rho, 4.9, 3.8), 2.0 / math.sqrt(I.numel()), what="C^2")


@pytest.mark.parametrize("kind, factor", [("diffusion", 2.0), ("ballistic", 4.0), ("flow", 4.0)])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_tiny_motion_follows_small_motion_asymptote(kind, factor, dtype):
    """Per realization, LIV ∝ v² (ballistic, flow) and ∝ D (diffusion) at v = 1e-4 µm/s, D = 1e-6 µm²/s.

    Doubling the parameter with the same seed keeps the scatterers; the median over trials of
    LIV(2p)/LIV(p) must be within 5 % of 2 or 4, in float32 as in float64.
    """

    def motion(x):
        return {
            "diffusion": (td.Diffusion(diffusion_um2_per_s=1e-6 * x),),
            "ballistic": (td.RandomBallistic(speed_um_per_s=1e-4 * x),),
            "flow": (td.Flow(speed_um_per_s=1e-4 * x, polar_angle_deg=45.0),),
        }[kind]

    a = td.simulate(scene(motion(1)), trials=256, seed=1, dtype=dtype).metrics()["liv"][:, 0].double()
    b = td.simulate(scene(motion(2)), trials=256, seed=1, dtype=dtype).metrics()["liv"][:, 0].double()
    assert bool(torch.isfinite(a).all()) and bool((a > 0).all())
    ratio = float((b / a).median())
    assert abs(ratio / factor - 1) < 0.05, ratio


@pytest.mark.parametrize("kind", ["diffusion", "ballistic", "flow"])
def test_float32_matches_float64(kind):
    sc = scene(MOTIONS[kind] if kind != "flow" else (td.Flow(speed_um_per_s=3.0, polar_angle_deg=45.0),), n_frames=32)
    a = td.simulate(sc, trials=128, seed=5, dtype="float32")
    b = td.simulate(sc, trials=128, seed=5, dtype="float64")
    assert a.signals.dtype == torch.complex64 and b.signals.dtype == torch.complex128
    scale = math.sqrt(mean_intensity_theory(0.055, 4.9, 3.8))
    err = (a.signals.to(torch.complex128) - b.signals).abs().max().item()
    assert err < 1e-4 * scale, err
    la, lb = a.metrics()["liv"].double(), b.metrics()["liv"]
    assert float((la - lb).abs().median()) < 1e-3


def test_huge_motion_saturates():
    """Flow at 300 µm/s decorrelates every frame: LIV at its plateau, OCDS at the estimator's floor."""
    res = td.simulate(scene((td.Flow(speed_um_per_s=300.0, polar_angle_deg=45.0),)), trials=256, seed=2)
    m = res.metrics()
    liv = m["liv"][:, 0].double()
    ocds = m["ocds"][:, 0].double()
    # plateau: (31/32)·Var(10 log10 I) at N_eff 5.93 = (31/32)·33.0 dB² (physics.md §5.6, MC SE 0.2)
    se = float(liv.std() / math.sqrt(liv.numel()))
    assert abs(float(liv.mean()) - 31 / 32 * 33.0) <= 4 * math.hypot(se, 31 / 32 * 0.2)
    # independent frames: E[ρ_m] ≈ −1/(N−m) for the Pearson estimator, hence OCDS ≈ 0.006 1/s
    delays = torch.arange(1, 32, dtype=torch.float64) * DT
    ref = float(td.sim.metrics.ocds_from_correlations(-1.0 / (32 - torch.arange(1, 32, dtype=torch.float64)), delays))
    assert abs(ref) < 0.01
    assert_within_se(float(ocds.mean()), ref, float(ocds.std() / math.sqrt(ocds.numel())), what="OCDS")


@pytest.mark.parametrize("wavelength", [0.4, 2.0])
def test_extreme_wavelengths(wavelength):
    system = td.OCTSystem(name="w", wavelength_um=wavelength, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    motion = td.Diffusion(diffusion_um2_per_s=0.002)
    res = td.simulate(
        scene((motion,), systems=(system,), n_frames=4, metrics=("liv",)), trials=2048, seed=3, dtype="float64"
    )
    E = res.signals[:, 0]
    g_th = th.g1_diffusion(
        DT, diffusion_um2_per_s=0.002, wavelength_um=wavelength, lateral_resolution_um=4.9, axial_resolution_um=3.8
    )
    est, se_re, _ = batch_means(g1_at_lag(1), E)
    assert_within_se(est.real, float(g_th), se_re, what=f"g1 at {wavelength} µm")


def test_thousand_frame_protocol():
    motion = td.Diffusion(diffusion_um2_per_s=0.01)
    sc = scene((motion,), n_frames=1000, metrics=("liv", "ocds"))
    res = td.simulate(sc, trials=128, seed=4, dtype="float32")
    I = res.intensity[:, 0]
    assert bool(torch.isfinite(I).all())
    # stationary: the first and last 100 frames have the theoretical mean intensity
    mi = mean_intensity_theory(0.055, 4.9, 3.8)
    for part in (I[:, :100], I[:, -100:]):
        per_trial = part.double().mean(1)
        assert_within_se(float(per_trial.mean()), mi, float(per_trial.std() / math.sqrt(per_trial.numel())))
    est, se_re, _ = batch_means(g1_at_lag(1), res.signals[:, 0].to(torch.complex128), n_batches=16)
    g_th = th.g1_diffusion(
        DT, diffusion_um2_per_s=0.01, wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8
    )
    assert_within_se(est.real, float(g_th), se_re)
    assert bool(torch.isfinite(res.metrics()["ocds"]).all())


def test_explicit_frame_times():
    """Non-uniform protocol: per-frame diffusion steps follow each interval (g1 at delay 0.2048 s)."""
    times = [0.0, 0.2048, 0.4096, 1.2288, 1.4336, 3.0]
    motion = td.Diffusion(diffusion_um2_per_s=0.005)
    res = td.simulate(scene((motion,), times=times, metrics=("liv",)), trials=2048, seed=1, dtype="float64")
    E = res.signals[:, 0]
    pairs = [(0, 1), (1, 2), (3, 4)]

    def g1(x):
        num = sum((x[:, i] * x[:, j].conj()).mean() for i, j in pairs) / len(pairs)
        return complex(num) / float((x.real**2 + x.imag**2).mean())

    est, se_re, _ = batch_means(g1, E)
    g_th = th.g1_diffusion(
        0.2048, diffusion_um2_per_s=0.005, wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8
    )
    assert_within_se(est.real, float(g_th), se_re)


# ------------------------------------------------------------------------------------------------
# noise


def test_noise_power_and_low_snr_liv():
    """Static signal + noise at 10 dB: temporal complex variance = N0·(N−1)/N with N0 = ⟨I⟩/10."""
    sc = scene((), n_frames=16, noise=td.Noise(snr_db=10.0), metrics=("liv", "complex_variance"))
    res = td.simulate(sc, trials=2048, seed=3, dtype="float64")
    cv = res.metrics()["complex_variance"][:, 0]
    n0 = mean_intensity_theory(0.055, 4.9, 3.8) / 10.0
    assert_within_se(float(cv.mean()), n0 * 15 / 16, float(cv.std() / math.sqrt(cv.numel())), what="noise power")
    # noise-dominated: LIV → (N−1)/N·31.03 dB²
    low = td.simulate(scene((), n_frames=16, noise=td.Noise(snr_db=-40.0), metrics=("liv",)), trials=2048, seed=3)
    liv = low.metrics()["liv"][:, 0].double()
    assert_within_se(
        float(liv.mean()),
        15 / 16 * th.db_variance_gaussian_speckle(),
        float(liv.std() / math.sqrt(liv.numel())),
        what="noise LIV",
    )


def test_two_populations_add_intensities():
    """70 % static + 30 % diffusing: ⟨I⟩ adds up, and the static part stays correlated forever."""
    pops = (
        td.Population(density_per_um3=0.0385, name="static"),
        td.Population(density_per_um3=0.0165, name="diffusing", motion=(td.Diffusion(diffusion_um2_per_s=0.5),)),
    )
    res = td.simulate(scene(populations=pops, n_frames=8, metrics=("liv",)), trials=4096, seed=2, dtype="float64")
    E = res.signals[:, 0]
    mi, se, _ = batch_means(lambda x: float((x.real**2 + x.imag**2).mean()), E)
    assert_within_se(mi.real, mean_intensity_theory(0.055, 4.9, 3.8), se, what="<I>")
    est, se_re, _ = batch_means(g1_at_lag(7), E)
    # g1 = 0.7·1 + 0.3·g1_diffusion(7Δt) (≈ 0)
    assert_within_se(est.real, 0.7, se_re, what="g1 of the mixture")


# ------------------------------------------------------------------------------------------------
# the periodic cell of pure diffusion


def _axis_terms_by_quadrature(s, L, v, q, k):
    """One axis of the periodic-image terms by direct 2-D quadrature over (x, displacement d).

    Intensity: ∫∫ w(x)·w(x + d − kL)·N(d; 0, v) with w the normalized intensity PSF |a|²/∫|a|²;
    field: |∫∫ a(x)·a(x + d − kL)·e^{iqd}·N(d; 0, v)| / ∫a², a(x) = exp(−x²/(2s²)).
    """
    x = np.linspace(-12 * s, 12 * s, 1201)
    sd = math.sqrt(v)
    d = np.linspace(k * L - 12 * math.hypot(sd, s), k * L + 12 * math.hypot(sd, s), 1201)
    dx, dd = x[1] - x[0], d[1] - d[0]
    X, Dd = np.meshgrid(x, d, indexing="ij")
    nd = np.exp(-(Dd**2) / (2 * v)) / math.sqrt(2 * math.pi * v)
    a = lambda u: np.exp(-(u**2) / (2 * s * s))  # noqa: E731
    w_norm = math.sqrt(math.pi) * s  # ∫|a|² = ∫ exp(−x²/s²)
    inten = float((a(X) ** 2 * a(X + Dd - k * L) ** 2 * nd).sum() * dx * dd) / w_norm**2
    field = abs(complex((a(X) * a(X + Dd - k * L) * np.exp(1j * q * Dd) * nd).sum() * dx * dd)) / w_norm
    return inten, field


def test_periodic_image_bound_matches_quadrature():
    """The closed-form image terms of plan.periodic_image_bound against brute-force quadrature."""
    from torchdoct.sim.plan import periodic_image_bound

    s_x, s_z, q = 1.73, 2.28, 14.96
    half = (4.0, 4.0, 5.0)
    D, tau, rho = 6.0, 0.4, 0.055
    v = 2 * D * tau
    terms = []
    for a, s in enumerate((s_x, s_x, s_z)):
        terms.append(
            {k: _axis_terms_by_quadrature(s, 2 * half[a], v, q if a == 2 else 0.0, k) for k in (-2, -1, 0, 1, 2)}
        )
    prod_all_i = math.prod(sum(t[k][0] for k in t) for t in terms)
    prod_0_i = math.prod(t[0][0] for t in terms)
    prod_all_f = math.prod(sum(t[k][1] for k in t) for t in terms)
    prod_0_f = math.prod(t[0][1] for t in terms)
    expect_i = (prod_all_i - prod_0_i) / rho
    expect_f = prod_all_f - prod_0_f
    got_i = periodic_image_bound(half, [(s_x, s_z, q)], D, [tau], 1.0 / rho, 0.0)
    got_f = periodic_image_bound(half, [(s_x, s_z, q)], D, [tau], 0.0, 1.0)
    assert got_i == pytest.approx(expect_i, rel=1e-3)
    assert got_f == pytest.approx(expect_f, rel=1e-3, abs=1e-12)
    assert got_i > 1e-3  # a cell this small wraps visibly: the test compares real numbers


@pytest.mark.parametrize("D", [1e-6, 0.005, 1.2, 15.0, 1e4])
def test_periodic_cell_holds_the_psf_and_meets_the_wrap_tolerance(D):
    from torchdoct.conventions import truncation_half_widths_um
    from torchdoct.sim.plan import wrap_tolerance

    for tol in (1e-2, 1e-3):
        pp = make_plan(scene((td.Diffusion(diffusion_um2_per_s=D),)), truncation_tolerance=tol).populations[0]
        assert pp.sampler == "diffusive" and pp.immigrant_method == "periodic"
        assert 0.0 < pp.wrap_error_bound <= wrap_tolerance(tol) * (1 + 1e-9)
        box = truncation_half_widths_um(4.9, 3.8, tol)
        assert all(c >= h for c, h in zip(pp.domain_half_widths_um, box))
        # fully mixed walks wrap as independent draws of a fixed count: 1/N of the cell bounds it
        assert pp.expected_scatterers_per_trial <= 1.2 / wrap_tolerance(tol) + 0.055 * 8 * math.prod(box)


def test_periodic_cell_keeps_poisson_statistics_under_huge_diffusion():
    """D = 1e4 µm²/s (σ_step = 64 µm ≫ the cell): every frame is a fresh Poisson speckle, so the
    LIV sits at its plateau (31/32)·33.0 dB² for N_eff 5.93 (physics.md §5.6) and ⟨I⟩ is exact,
    with a cell of about 1,000 scatterers instead of one 64-µm step's reach around the PSF."""
    res = td.simulate(scene((td.Diffusion(diffusion_um2_per_s=1e4),)), trials=512, seed=5)
    assert res.plan.populations[0].expected_scatterers_per_trial < 1500
    liv = res.metrics()["liv"][:, 0].double()
    se = float(liv.std() / math.sqrt(liv.numel()))
    assert abs(float(liv.mean()) - 31 / 32 * 33.0) <= 4 * math.hypot(se, 31 / 32 * 0.2)
    I = res.intensity[:, 0].double().mean(1)
    assert_within_se(float(I.mean()), mean_intensity_theory(0.055, 4.9, 3.8), float(I.std() / math.sqrt(I.numel())))

"""The labelled dataset: prior draws, ground-truth identifiability, field combination, cache."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import torchdoct as td
from classifier.dataset import make_dataset
from classifier.features import Configuration, FeatureSpec, load_spec
from classifier.nuisance import combine_fields
from classifier.prior import CLASSES, Draw, Prior, draw_parameters
from classifier.simulation import scene_for, simulate_draw
from classifier.truth import identifiability, transit_decay

TINY = FeatureSpec(
    name="tiny",
    configurations=(Configuration(name="o", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8),),
)


def _draw(
    label: int, magnitude: float, density: float = 0.06, nuisance=((0.0, math.nan),), polar: float = 45.0
) -> Draw:
    return Draw(
        label=label,
        magnitude=magnitude,
        polar_angle_deg=polar,
        azimuth_deg=0.0,
        density_per_um3=density,
        sim_seed=11,
        nuisance=tuple(nuisance),
    )


def test_draws_are_stratified_reproducible_and_prefix_stable():
    prior = Prior()
    draws = [draw_parameters(prior, 3, "train", k, replicates=4) for k in range(60)]
    assert [d.label for d in draws] == [k % 3 for k in range(60)]
    again = draw_parameters(prior, 3, "train", 17, replicates=2)
    assert again.magnitude == draws[17].magnitude and again.sim_seed == draws[17].sim_seed
    assert again.nuisance == draws[17].nuisance[:2]  # replicate r does not depend on the number of replicates
    other = draw_parameters(prior, 3, "test", 17)
    assert other.sim_seed != draws[17].sim_seed and other.magnitude != draws[17].magnitude
    for label, (lo, hi) in enumerate((prior.diffusion_um2_per_s, prior.speed_um_per_s, prior.speed_um_per_s)):
        mags = np.array([d.magnitude for d in draws if d.label == label])
        assert np.all((mags >= lo) & (mags <= hi))
        q = np.sort((np.log(mags) - math.log(lo)) / (math.log(hi) - math.log(lo)))
        # golden-ratio stratification: 20 points leave no gap wider than 2/20 of the log range
        assert np.diff(np.concatenate([[q[-1] - 1], q])).max() < 0.1
    for d in draws:
        assert 0.02 <= d.density_per_um3 <= 0.1 and 0.0 <= d.polar_angle_deg <= 180.0
        for f, snr in d.nuisance:
            assert 0.0 <= f <= 0.8 and (math.isnan(snr) or 10.0 <= snr <= 40.0)


def test_prior_validation_and_round_trip():
    p = Prior()
    assert Prior.from_dict(p.to_dict()) == p
    with pytest.raises(ValueError, match="unknown"):
        Prior.from_dict({"speed": [1, 2]})
    with pytest.raises(ValueError, match="diffusion_um2_per_s"):
        Prior(diffusion_um2_per_s=(0.0, 15.0))
    with pytest.raises(ValueError, match="static_fraction"):
        Prior(static_fraction=(0.0, 1.0))
    with pytest.raises(ValueError, match="probability"):
        Prior(noise_probability=1.5)


def test_identifiability_regimes_follow_the_physics():
    spec = load_spec("single-acquisition")
    prior = Prior()
    # flow decorrelates by transit only (|g1|^2 = j, physics.md §5.4): never 'decorrelated' in the prior's range
    for v in np.geomspace(*prior.speed_um_per_s, 12):
        s, g1sq, rho_last = identifiability(spec, _draw(2, v), prior)
        assert s != "decorrelated"
    assert identifiability(spec, _draw(2, 1e-3), prior)[0] == "static"
    assert identifiability(spec, _draw(0, 15.0), prior)[0] == "decorrelated"
    assert identifiability(spec, _draw(1, 6.0), prior)[0] == "decorrelated"
    assert identifiability(spec, _draw(0, 1e-3), prior)[0] == "identifiable"
    # monotone in the motion magnitude: static -> identifiable -> decorrelated, never back
    for label, rng in ((0, prior.diffusion_um2_per_s), (1, prior.speed_um_per_s)):
        order = {"static": 0, "identifiable": 1, "decorrelated": 2}
        seq = [order[identifiability(spec, _draw(label, m), prior)[0]] for m in np.geomspace(*rng, 30)]
        assert seq == sorted(seq)
    # the status is exactly the stated criteria
    eps = prior.identifiability_epsilon
    for label, m in ((0, 0.04), (1, 0.9), (2, 0.09), (1, 0.004)):
        s, g1sq, rho_last = identifiability(spec, _draw(label, m), prior)
        assert (s == "static") == bool(np.all(rho_last >= 1 - eps))
        assert (s == "decorrelated") == (not np.all(rho_last >= 1 - eps) and bool(np.all(g1sq <= eps)))
        assert np.all((g1sq >= 0) & (g1sq <= 1)) and np.all(rho_last <= 1 + 1e-12)


def test_transit_decay_is_the_closed_form_and_the_definition_is_the_same_for_signature_specs():
    """rho_I(dt) - rho_I(T) from the closed forms; signature specs share the ground-truth definition."""
    from torchdoct.conventions import n_eff
    from torchdoct.sim import theory

    sig, liv = load_spec("signature"), load_spec("single-acquisition")
    prior = Prior()
    taus = np.array([sig.frame_interval_s, (sig.n_frames - 1) * sig.frame_interval_s])
    for m in (1e-3, 1.0, 15.0):
        d = _draw(0, m)
        want = []
        for c in sig.configurations:
            res = dict(lateral_resolution_um=c.lateral_resolution_um, axial_resolution_um=c.axial_resolution_um)
            g1 = theory.g1_diffusion(
                taus, diffusion_um2_per_s=m, wavelength_um=c.wavelength_um, refractive_index=sig.refractive_index, **res
            )
            j = theory.j_diffusion(taus, diffusion_um2_per_s=m, **res)
            rho = theory.intensity_correlation_coefficient(g1, j, n_eff(d.density_per_um3, **res))
            want.append(rho[0] - rho[1])
        np.testing.assert_allclose(transit_decay(sig, d, prior), want, rtol=1e-12)
        assert identifiability(sig, d, prior)[0] == identifiability(liv, d, prior)[0]
    # D = 1 µm²/s: the field decorrelates within a frame while the transit term still decays
    eps = prior.identifiability_epsilon
    s, g1sq, _ = identifiability(sig, _draw(0, 1.0), prior)
    assert s == "decorrelated" and np.all(g1sq <= eps) and np.any(transit_decay(sig, _draw(0, 1.0), prior) > eps)
    # D = 15 µm²/s: the transit is over within a frame too
    assert np.all(transit_decay(sig, _draw(0, 15.0), prior) <= eps)


def test_combine_fields_intensity_and_noise_power():
    gen = torch.Generator().manual_seed(5)
    shape = (4000, 2, 8)
    e_m = torch.complex(torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)) * math.sqrt(0.5)
    e_s = torch.complex(torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)) * math.sqrt(0.5) * 1.3
    assert torch.equal(combine_fields(e_m, None, 0.0, math.nan, [1.0, 1.0], gen), e_m)
    f = 0.6
    out = combine_fields(e_m, e_s, f, math.nan, [1.0, 1.0], gen)
    a2 = f / (1 - f)
    i = (out.real**2 + out.imag**2).double()
    ref = (e_m.real**2 + e_m.imag**2).double().mean() + a2 * (e_s.real**2 + e_s.imag**2).double().mean()
    se = float(i.mean(dim=(1, 2)).std() / math.sqrt(shape[0]))
    assert abs(float(i.mean()) - float(ref)) <= 4 * se
    # noise alone (zero moving field): power (1 + a^2)·<I>/10^(snr/10) per system, circular
    zero = torch.zeros(shape, dtype=torch.complex64)
    mean_i = [2.0, 0.5]
    noise = combine_fields(zero, zero, f, 10.0, mean_i, gen)
    p = (noise.real**2 + noise.imag**2).double()
    for s_idx, m in enumerate(mean_i):
        want = (1 + a2) * m / 10.0
        got = p[:, s_idx].mean()
        se = float(p[:, s_idx].std() / math.sqrt(p[:, s_idx].numel()))
        assert abs(float(got) - want) <= 4 * se
        assert abs(float((noise[:, s_idx].real ** 2 - noise[:, s_idx].imag ** 2).mean())) <= 4 * se
    with pytest.raises(ValueError, match="static_fraction"):
        combine_fields(e_m, e_s, 1.0, math.nan, [1.0, 1.0], gen)
    with pytest.raises(ValueError, match="static scatterers"):
        combine_fields(e_m, None, 0.5, math.nan, [1.0, 1.0], gen)


def test_noise_matches_torchdoct_noise_model():
    """A static sample with 10-dB noise: LIV from simulate_draw's noise equals torchdoct.Noise's (within SE)."""
    prior = Prior()
    draw = _draw(2, 1e-4, nuisance=((0.0, 10.0),))  # flow at 1e-4 µm/s: static for every purpose (float32 resolves it)
    x, zero = simulate_draw(TINY, draw, prior, trials=1024, truncation_tolerance=1e-2)
    assert not zero.any()
    liv_ours = x[0, :, 0].astype(np.float64)
    scene = scene_for(TINY, draw, prior, "static").replace(noise=td.Noise(snr_db=10.0))
    ref = td.simulate(scene, trials=1024, seed=99, truncation_tolerance=1e-2).metrics()["liv"][:, 0].double().numpy()
    se = math.sqrt(liv_ours.var(ddof=1) / liv_ours.size + ref.var(ddof=1) / ref.size)
    assert abs(liv_ours.mean() - ref.mean()) <= 4 * se


def test_make_dataset_caches_by_key_and_is_reproducible(tmp_path):
    kw = dict(seed=4, split="validation", draws=3, trials_per_draw=64, replicates=2, cache_dir=tmp_path)
    a = make_dataset(TINY, **kw)
    assert not a.meta["from_cache"] and len(a) == 3 * 2 * 64 - a.meta["dropped_empty"]
    assert a.x.shape == (len(a), 2) and a.x.dtype == np.float32
    assert set(np.unique(a.y)) == {0, 1, 2} and len(np.unique(a.group)) == 6
    b = make_dataset(TINY, **kw)
    assert b.meta["from_cache"]
    for k, v in a.arrays().items():
        np.testing.assert_array_equal(v, getattr(b, k))
    c = make_dataset(TINY, **{**kw, "cache_dir": None}, use_cache=False)
    np.testing.assert_array_equal(a.x, c.x)
    d = make_dataset(TINY, **{**kw, "seed": 5})
    assert not d.meta["from_cache"] and not np.array_equal(a.magnitude, d.magnitude)
    assert len(list(tmp_path.iterdir())) == 2
    with pytest.raises(ValueError, match="split"):
        make_dataset(TINY, split="dev", draws=3, cache_dir=tmp_path)
    with pytest.raises(ValueError, match="draws"):
        make_dataset(TINY, draws=0, cache_dir=tmp_path)


def test_classes_are_the_three_motion_types():
    assert CLASSES == ("diffusion", "ballistic", "flow")


def test_dataset_does_not_depend_on_threads():
    """Draws run side by side (torchdoct.runtime.threads); each has its own seeds, so the split is bit-identical."""
    from torchdoct.runtime.threads import using_threads

    with using_threads(1):
        one = make_dataset(TINY, split="test", draws=3, trials_per_draw=64, replicates=2, use_cache=False)
    with using_threads(3):
        three = make_dataset(TINY, split="test", draws=3, trials_per_draw=64, replicates=2, use_cache=False)
    assert np.array_equal(one.x, three.x) and np.array_equal(one.y, three.y)
    assert np.array_equal(one.group, three.group)


def test_prior_direction_laws_and_flow_angle_range_are_validated():
    assert Prior().ballistic_directions == "both" and Prior().flow_polar_angle_deg == (0.0, 180.0)
    for law in ("both", "isotropic", "uniform-angles"):
        assert Prior.from_dict(Prior(ballistic_directions=law).to_dict()).ballistic_directions == law
    with pytest.raises(
        ValueError, match=r"ballistic_directions must be one of \['both', 'isotropic', 'uniform-angles'\]"
    ):
        Prior(ballistic_directions="cog")
    with pytest.raises(ValueError, match="ballistic_directions"):
        Prior(ballistic_directions=None)
    with pytest.raises(ValueError, match=r"flow_polar_angle_deg must lie in \[0, 180\]"):
        Prior(flow_polar_angle_deg=(10.0, 190.0))
    with pytest.raises(ValueError, match="flow_polar_angle_deg"):
        Prior(flow_polar_angle_deg=(80.0, 10.0))
    with pytest.raises(ValueError, match="Draw.ballistic_directions"):
        _draw(1, 0.1).__class__(
            label=1,
            magnitude=0.1,
            polar_angle_deg=0.0,
            azimuth_deg=0.0,
            density_per_um3=0.05,
            sim_seed=1,
            ballistic_directions="both",
        )


def test_stored_priors_still_load():
    """Priors stored in models (the shipped ones, and one written before the laws were mixed and the flow
    angle had a range) load: a missing key takes its default, which reproduces the old draws."""
    from classifier.infer import load_model, shipped_models

    old = {
        "diffusion_um2_per_s": [0.0001, 15.0],
        "speed_um_per_s": [0.001, 6.0],
        "ballistic_directions": "isotropic",
        "density_per_um3": [0.02, 0.1],
        "static_probability": 0.5,
        "static_fraction": [0.0, 0.8],
        "noise_probability": 0.5,
        "snr_db": [20.0, 40.0],
        "identifiability_epsilon": 0.05,
    }
    stored = [old] + [load_model(name, threads=1).metadata["prior"] for name in shipped_models()]
    for data in stored:
        p = Prior.from_dict(data)
        assert p.ballistic_directions == data["ballistic_directions"]
        assert p.flow_polar_angle_deg == tuple(data.get("flow_polar_angle_deg", (0.0, 180.0)))
        if p.ballistic_directions != "both":
            assert draw_parameters(p, 0, "train", 1).ballistic_directions == p.ballistic_directions
    assert Prior.from_dict(old) == Prior(ballistic_directions="isotropic", snr_db=(20.0, 40.0))


def test_both_direction_laws_are_drawn_half_each_and_leave_the_rest_of_the_draw_unchanged():
    both, iso, cog = Prior(), Prior(ballistic_directions="isotropic"), Prior(ballistic_directions="uniform-angles")
    n_ballistic = 0
    laws = []
    for k in range(480):  # 160 ballistic draws
        d = draw_parameters(both, 7, "train", k, replicates=2)
        ref = draw_parameters(iso, 7, "train", k, replicates=2)
        # the law comes from a stream of its own: every other parameter is the single-law prior's
        assert dataclasses.replace(d, ballistic_directions="isotropic") == ref
        assert draw_parameters(cog, 7, "train", k).ballistic_directions == "uniform-angles"
        if d.label == 1:
            n_ballistic += 1
            laws.append(d.ballistic_directions)
        else:
            assert d.ballistic_directions == "isotropic"
    assert n_ballistic == 160 and set(laws) == {"isotropic", "uniform-angles"}
    share = laws.count("uniform-angles") / n_ballistic
    assert abs(share - 0.5) <= 4 * math.sqrt(0.25 / n_ballistic)
    # reproducible, and not a function of the draw's place in the golden-ratio sequence alone
    assert [draw_parameters(both, 7, "train", k).ballistic_directions for k in range(1, 480, 3)] == laws
    assert [draw_parameters(both, 8, "train", k).ballistic_directions for k in range(1, 480, 3)] != laws


def test_each_ballistic_draw_is_simulated_and_judged_with_its_own_law():
    spec = load_spec("single-acquisition")
    prior = Prior()
    iso = _draw(1, 0.3)
    cog = dataclasses.replace(iso, ballistic_directions="uniform-angles")
    assert scene_for(spec, iso, prior).populations[0].motion[0].directions == "isotropic"
    assert scene_for(spec, cog, prior).populations[0].motion[0].directions == "uniform-angles"
    # the laws' closed forms differ (physics.md §5.3: sinc vs J0 tail), and so do the criteria
    _, g1_iso, rho_iso = identifiability(spec, iso, prior)
    _, g1_cog, rho_cog = identifiability(spec, cog, prior)
    assert not np.allclose(g1_iso, g1_cog, rtol=1e-3) and not np.allclose(rho_iso, rho_cog, rtol=1e-6)


def test_flow_angle_range_is_isotropic_within_it():
    wide = Prior()
    u = [draw_parameters(wide, 2, "test", k) for k in range(2, 3000, 3)]
    # default: the historical law, cos(polar) = 2u - 1 bit for bit
    for k, d in zip(range(2, 3000, 3), u[:20]):
        from classifier.prior import _seed_sequence

        u0 = np.random.default_rng(_seed_sequence(2, "test", k)).random(4)[0]
        assert d.polar_angle_deg == math.degrees(math.acos(2.0 * u0 - 1.0))
    narrow = Prior(flow_polar_angle_deg=(10.0, 80.0))
    draws = [draw_parameters(narrow, 2, "test", k) for k in range(2, 3000, 3)]
    polar = np.array([d.polar_angle_deg for d in draws])
    assert np.all((polar >= 10.0) & (polar <= 80.0))
    # cos(polar) ~ U[cos 80°, cos 10°]: mean and variance of a uniform, within 4 SE
    c = np.cos(np.radians(polar))
    lo, hi = math.cos(math.radians(80.0)), math.cos(math.radians(10.0))
    assert abs(c.mean() - (lo + hi) / 2) <= 4 * (hi - lo) / math.sqrt(12 * c.size)
    assert abs(c.var() - (hi - lo) ** 2 / 12) <= 4 * (hi - lo) ** 2 / math.sqrt(180 * c.size)
    # the angle range changes nothing else
    for d, w in zip(draws[:50], u[:50]):
        assert dataclasses.replace(d, polar_angle_deg=w.polar_angle_deg) == w


# ----------------------------------------------------------------------------------------------------------
# the edge of a moving region: a static share per configuration (physics.md §14)


def test_edge_static_fractions_closed_form():
    from classifier.nuisance import edge_static_fractions

    spec = load_spec("signature")  # original 4.9/3.8, axial=14, lateral=18 (isotropic)
    names = [c.name for c in spec.configurations]
    assert edge_static_fractions(spec.configurations, (0.0, 1.0, 0.0, 0.0)) == [0.5] * 3  # on the edge
    # normal along x: σ_c = Δx/4; the widest (lateral 18 µm) at d = 1 of its SDs holds ½·erfc(1/√2)
    f = dict(zip(names, edge_static_fractions(spec.configurations, (1.0, 1.0, 0.0, 0.0))))
    by_name = {c.name: c for c in spec.configurations}
    assert f[names[2]] == pytest.approx(0.5 * math.erfc(1 / math.sqrt(2)), rel=1e-12)
    d_um = by_name[names[2]].lateral_resolution_um / 4
    assert f[names[0]] == pytest.approx(0.5 * math.erfc(d_um / (math.sqrt(2) * 4.9 / 4)), rel=1e-12)
    assert f[names[1]] == f[names[0]]  # the axial reduction does not widen the PSF along x
    # normal along z: the axial-reduced configuration reaches furthest; the sign of the normal does not matter
    up = edge_static_fractions(spec.configurations, (0.7, 0.0, 0.0, 1.0))
    assert up == edge_static_fractions(spec.configurations, (0.7, 0.0, 0.0, -1.0))
    assert up[1] > up[0] == up[2]
    far = edge_static_fractions(spec.configurations, (3.0, 0.6, 0.0, 0.8))
    assert max(far) == pytest.approx(0.5 * math.erfc(3 / math.sqrt(2)), rel=1e-12) and min(far) < max(far)


def test_combine_fields_takes_a_static_share_per_system():
    gen = torch.Generator().manual_seed(6)
    shape = (6000, 2, 4)
    e_m = torch.complex(torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)) * math.sqrt(0.5)
    e_s = torch.complex(torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)) * math.sqrt(0.5)
    shares = [0.1, 0.7]
    out = combine_fields(e_m, e_s, shares, math.nan, [1.0, 1.0], gen)
    static_part = out - e_m  # a_c·E_s
    for c, f in enumerate(shares):
        p_static = (static_part[:, c].abs() ** 2).double()
        p_total = (out[:, c].abs() ** 2).double()
        share = float(p_static.mean() / p_total.mean())
        se = float(p_static.std() / math.sqrt(p_static.numel())) / float(p_total.mean())
        assert abs(share - f) <= 5 * se + 0.01, (c, share, f)  # 0.01: the ratio's own spread
    assert torch.equal(
        combine_fields(e_m, e_s, [0.3, 0.3], math.nan, [1.0, 1.0], gen),
        combine_fields(e_m, e_s, 0.3, math.nan, [1.0, 1.0], gen),
    )
    with pytest.raises(ValueError, match="2 systems"):
        combine_fields(e_m, e_s, [0.1, 0.2, 0.3], math.nan, [1.0, 1.0], gen)


def test_edge_replicates_leave_the_other_draws_unchanged():
    base = Prior()
    edged = dataclasses.replace(base, static_edge_probability=0.3)
    assert "static_edge_probability" not in base.to_dict() and edged.to_dict()["static_edge_probability"] == 0.3
    n_edge = n_rep = 0
    for k in range(200):
        a, b = draw_parameters(base, 1, "train", k, 8), draw_parameters(edged, 1, "train", k, 8)
        assert (a.magnitude, a.sim_seed, a.polar_angle_deg) == (b.magnitude, b.sim_seed, b.polar_angle_deg)
        assert a.static_edges == ()
        edges = b.static_edges or (None,) * 8
        for (fa, sa), (fb, sb), e in zip(a.nuisance, b.nuisance, edges):
            assert sa == sb or (math.isnan(sa) and math.isnan(sb))
            if e is None:
                assert fa == fb
            else:
                assert fb == 0.0 and 0.0 <= e[0] <= 3.0 and math.isclose(math.hypot(*e[1:]), 1.0, rel_tol=1e-12)
                n_edge += 1
            n_rep += 1
    se = math.sqrt(0.3 * 0.7 / n_rep)
    assert abs(n_edge / n_rep - 0.3) <= 4 * se


def test_flow_near_a_static_edge_beats_at_its_doppler_period():
    """Axial flow beside static tissue: the intensity correlation of the configuration that reaches the static
    side oscillates at the Doppler period λ/(2 n v_z) (here 8 frames), so ρ at 8 frames exceeds ρ at 4; without
    the edge it decays monotonically."""
    spec = load_spec("signature")
    prior = Prior()
    v = 0.84 / (2 * 1.0 * 8 * 0.2048)  # Doppler period of 8 frames
    i4, i8 = spec.metrics.index("rho_lin_4"), spec.metrics.index("rho_lin_8")
    lat = 2  # lateral=18: reaches the static side first along x
    nm = len(spec.metrics)
    out = {}
    for name, edges in (("none", ()), ("edge", ((0.5, 1.0, 0.0, 0.0),))):
        d = Draw(
            label=2,
            magnitude=v,
            polar_angle_deg=0.0,
            azimuth_deg=0.0,
            density_per_um3=0.05,
            sim_seed=21,
            nuisance=((0.0, math.nan),),
            static_edges=edges,
        )
        x = simulate_draw(spec, d, prior, trials=256, truncation_tolerance=1e-2)[0][0]
        r4, r8 = x[:, lat * nm + i4], x[:, lat * nm + i8]
        diff = r8 - r4
        out[name] = (float(diff.mean()), float(diff.std() / math.sqrt(len(diff))))
    assert out["none"][0] < -3 * out["none"][1]  # decays: ρ_8 < ρ_4
    assert out["edge"][0] > 3 * out["edge"][1]  # beats: ρ_8 > ρ_4

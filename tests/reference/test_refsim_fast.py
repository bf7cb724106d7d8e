"""The reference simulator (refsim): fast checks in the default suite.

* its numpy features equal torchdoct's extractors on the same fields (so the feature comparison of the
  slow tests compares simulators, not extractors);
* its one-time statistics equal the closed forms of physics.md §5.2/§5.4 (⟨I⟩ = ρ·π^{3/2}·s_x·s_y·s_z,
  C² = 1 + 1/N_eff with N_eff = ρ·(2π)^{3/2}·s_x·s_y·s_z), also for an anisotropic lateral PSF;
* torchdoct at tolerance 1e-4 agrees with it on every feature of one fast flow cell at the original
  resolution (the slow tests cover every configuration, slow motions and the default tolerance).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import refcompare as rc
import refsim
import torch

from torchdoct.sim.config import Analysis
from torchdoct.sim.metrics import compute_metrics
from torchdoct.sim.signature import signature


def test_numpy_features_equal_torchdoct_extractors():
    """refsim.features (numpy, from the definitions) == torchdoct.sim.signature / metrics, float64."""
    optics = [refsim.Optics(0.84, 4.9, 3.8), refsim.Optics(0.84, 18.0, 3.8, lateral_y_um=4.9)]
    e = refsim.simulate(
        optics,
        refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=30.0),
        density_per_um3=0.05,
        n_frames=32,
        frame_interval_s=0.2048,
        trials=40,
        seed=3,
        snr_db=20.0,
    )
    ours = refsim.features(e, 0.2048, rc.NAMES)
    times = [i * 0.2048 for i in range(32)]
    x = torch.from_numpy(e)
    _, sig = signature(x, times, names=rc.SIGNATURE_NAMES)
    met = compute_metrics(x, times, Analysis(metrics=("liv", "ocds")))
    theirs = {n: sig[..., i].numpy() for i, n in enumerate(rc.SIGNATURE_NAMES)}
    theirs.update(liv=met["liv"].numpy(), ocds=met["ocds"].numpy())
    for n in rc.NAMES:
        a, b = ours[n], theirs[n]
        if n.startswith("g1_phase_"):  # angles: compare on the circle
            a, b = np.exp(1j * a), np.exp(1j * b)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-10, err_msg=n)


def test_reproducible_and_independent_of_trial_count():
    m = refsim.Motion("diffusion", diffusion_um2_per_s=0.01)
    kw = dict(density_per_um3=0.05, n_frames=8, frame_interval_s=0.2048, seed=11)
    a = refsim.simulate(refsim.Optics(0.84, 4.9, 3.8), m, trials=100, **kw)
    b = refsim.simulate(refsim.Optics(0.84, 4.9, 3.8), m, trials=70, **kw)
    assert np.array_equal(a[:70], b)
    assert not np.array_equal(
        a[:, 0, 0], refsim.simulate(refsim.Optics(0.84, 4.9, 3.8), m, trials=100, **{**kw, "seed": 12})[:, 0, 0]
    )


def test_box_and_neglected_fraction():
    """The box holds ±6 amplitude sigmas plus the motion margin; 1 − erf(6)³ of ∫|h|² is left out."""
    o = refsim.Optics(0.84, 4.9, 3.8)
    sx, sy, sz = o.sigmas_um
    assert sx == pytest.approx(4.9 / (2 * math.sqrt(2))) and sz == pytest.approx(3.8 / (2 * math.sqrt(math.log(2))))
    L = refsim.box_lengths_um(o, refsim.Motion("flow", speed_um_per_s=1.0, polar_angle_deg=90.0), 6.35)
    np.testing.assert_allclose(L, [12 * sx + 6.35, 12 * sy, 12 * sz])
    assert refsim.neglected_field_fraction(6.0) == pytest.approx(3 * math.erfc(6.0), rel=1e-6)
    assert refsim.neglected_field_fraction(6.0) < 1e-16


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("lateral_y", [None, 14.0])
def test_one_time_statistics_match_closed_forms(lateral_y):
    """⟨I⟩ and C² of static scatterers against physics.md §5.2/§5.4 (per-axis sigmas), z from batch means."""
    o = refsim.Optics(0.84, 4.9, 3.8, lateral_y_um=lateral_y)
    rho = 0.05
    e = refsim.simulate(
        o, refsim.Motion("static"), density_per_um3=rho, n_frames=2, frame_interval_s=0.2, trials=6400, seed=5
    )[:, 0, 0]
    inten = np.abs(e) ** 2
    sx, sy, sz = o.sigmas_um
    i_theory = rho * math.pi**1.5 * sx * sy * sz
    n_eff = rho * (2 * math.pi) ** 1.5 * sx * sy * sz
    batches = inten.reshape(64, -1)
    m = batches.mean(1)
    c2 = (batches**2).mean(1) / m**2 - 1
    z_i = (inten.mean() - i_theory) / (m.std(ddof=1) / 8)
    z_c = ((inten**2).mean() / inten.mean() ** 2 - 1 - (1 + 1 / n_eff)) / (c2.std(ddof=1) / 8)
    bound = rc.z_bound(2)
    assert abs(z_i) <= bound, f"<I> {inten.mean():.4f} vs {i_theory:.4f} (z {z_i:+.2f})"
    assert abs(z_c) <= bound, f"C² vs 1 + 1/N_eff = {1 + 1 / n_eff:.4f} (z {z_c:+.2f})"


def test_torchdoct_matches_reference_fast_flow():
    """Every feature (signature, field group, LIV, OCDS) of flow 2 µm/s at 45°, original resolution:
    torchdoct (tolerance 1e-4, float32) against the reference, |z| within the Bonferroni bound."""
    cell = "flow v=2 θ=45°"
    ref = rc.reference_features(cell, 384, configs=(0,))
    td = rc.torchdoct_features(cell, 2048, truncation_tolerance=1e-4, configs=(0,), threads=1)
    rows = rc.compare(td, ref, configs=(0,))
    bound = rc.z_bound(len(rows))
    assert max(abs(r["z"]) for r in rows) <= bound, rc.format_failures(rows, bound)
    assert all(r["nan_a"] == 0 and r["nan_b"] == 0 for r in rows)


def test_the_reference_record_holds_every_run_the_comparisons_read():
    """tests/reference/data/reference-features.json: every run of ``refcompare.record_runs`` at the trials and
    seed the comparisons use, every feature at each of its configurations, finite and NaN trials adding to the
    run's trials, and the command that wrote it."""
    import json

    record = json.loads(rc.RECORD.read_text(encoding="utf-8"))
    assert record["command"] == rc.RECORD_COMMAND
    assert (record["trials"], record["seed"]) == (rc.REF_TRIALS, rc.REF_SEED)
    runs = rc.record_runs()
    assert set(record["runs"]) == {rc.record_key(c, rc.REF_TRIALS, rc.REF_SEED, k) for c, k in runs}
    for cell, configs in runs:
        run = rc.recorded_reference(cell, rc.REF_TRIALS, rc.REF_SEED, configs)
        assert set(run) == set(rc.NAMES), cell
        for name, rows in run.items():
            assert len(rows) == len(configs), (cell, name)
            for _mean, sd, n, nan in rows:
                assert n + nan == rc.REF_TRIALS and n > 1 and sd >= 0, (cell, name)
    with pytest.raises(KeyError, match="--record"):
        rc.recorded_reference("flow v=2 θ=45°", 17)


def test_compare_reads_trials_and_their_summary_alike():
    rng = np.random.default_rng(5)
    a = {"x": rng.normal(size=(200, 3)), "y": rng.normal(size=(200, 3))}
    b = {"x": rng.normal(0.1, 1.0, size=(300, 3)), "y": rng.normal(size=(300, 3))}
    b["x"][:7, 1] = np.nan
    direct = rc.compare(a, b)
    assert rc.compare(a, rc.summarize(b)) == direct
    assert rc.compare(rc.summarize(a), rc.summarize(b)) == direct
    row = next(r for r in direct if r["feature"] == "x" and r["config"] == rc.CONFIGS[1][0])
    fb = b["x"][7:, 1]
    se = np.hypot(a["x"][:, 1].std(ddof=1) / np.sqrt(200), fb.std(ddof=1) / np.sqrt(293))
    assert row["nan_b"] == 7 and row["z"] == pytest.approx((a["x"][:, 1].mean() - fb.mean()) / se, rel=1e-12)

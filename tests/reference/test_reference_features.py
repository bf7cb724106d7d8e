"""torchdoct's simulator against the independent reference simulator, on every feature a model reads (slow).

Per cell (refcompare.CELLS: slow flow at 0-90° from the beam axis, faster flow, slow and moderate
diffusion, random-ballistic motion under both direction laws) and the three configurations of the
shipped signature models, the mean of every feature — ``rho_lin_m`` at the spec's lags,
``lin_contrast``, ``db_variance``, the field group ``g1_m``, ``g1_phase_m``, ``phase_ramp``, LIV and
OCDS — agrees between torchdoct and the reference within the Bonferroni |z| bound of
refcompare (Monte Carlo SEs of both sides; 1024 reference trials; torchdoct 4096 trials at the scene
default, 8192 at the hard 1e-3 cut, 2048 in float64).

Trials: a feature's z is its bias over the combined standard error, ``SE² = σ_ref²/n_ref + σ_td²/n_td``,
computed from each side's own sample, so the bound follows the sample sizes. With per-trial SDs alike
on both sides, ``SE² ∝ 1/1024 + 1/n_td``: 8192 torchdoct trials give 1.125/1024, 4096 give 1.25/1024 and
2048 give 1.5/1024, so the smallest bias the bound resolves is sqrt(1.25/1.125) = 1.05 times the one at
8192 with 4096 trials and 1.15 times with 2048: the reference's sample dominates. The hard 1e-3 cut keeps
8192, since its strict xfail needs the power; the scene default (the smooth taper) has no xfail and takes
4096. The float64 setting runs the simulator's torch path (the compiled kernel is float32), many times
slower per trial: it takes 2048 trials and the ``extended`` marker (a check of the truncation-free limit,
not of what the models read; not in ``.ci/run``; ``python -m pytest -m extended``).

The reference side: the reference simulator is deterministic for a seed, and its 1024-trial runs cost a
minute per cell on one core, so each run's summary (mean, SD and counts of every feature per configuration:
what the z-test reads) is recorded in ``tests/reference/data/reference-features.json`` by
``python tests/reference/refcompare.py --record`` and the comparisons read it; the record is checked against
the simulator by running the reference again (one run here, every run with ``-m extended``).

Settings of torchdoct: the scene default (``simulation.truncation_tolerance`` and, where the
simulator has it, ``simulation.truncation``; float32 as the training data use), a hard cut at 1e-3 in
float32 and at 1e-4 in float64. A hard truncation at 1e-2 lets scatterers pop in at 1 % of the peak
amplitude, which decorrelates slow motion at short lags (flow 0.5 µm/s at 20°: ``rho_lin_1`` at
axial=14 0.990 against 0.998, z ≈ −14): while that is the default, the cells it biases are marked
``xfail(strict=True)`` (:data:`BIASED_AT_HARD_1E2`), so the mark must go when the default changes.
"""

from __future__ import annotations

import dataclasses
import inspect

import pytest
import refcompare as rc

from torchdoct.sim.config import OCTSystem, SimulationSettings
from torchdoct.sim.simulate import simulate

pytestmark = pytest.mark.slow

REF_TRIALS = rc.REF_TRIALS
TD_TRIALS = 8192
#: torchdoct trials per setting (module docstring: the float64 setting's smaller sample).
TD_TRIALS_OF = {"default": 4096, "1e-3 float32": TD_TRIALS, "1e-4 float64": 2048}
_DEFAULTS = SimulationSettings()
_HAS_TRUNCATION_MODE = "truncation" in inspect.signature(simulate).parameters
DEFAULT_IS_HARD_1E2 = _DEFAULTS.truncation_tolerance == 1e-2 and getattr(_DEFAULTS, "truncation", "hard") == "hard"
#: Cells whose features a hard truncation at 1e-2 biases beyond the bound, measured (``--runxfail``
#: shows the worst features): slow flow at every angle, worst |z| 19 (20°, rho_lin_1@axial=14
#: 0.9896 vs 0.9973), 29 (0°, rho_lin_1@axial=14 0.9843 vs 0.9985), 13 (45°), 19 (70°) and 26
#: (90°, rho_lin_1@lateral=18 0.9872 vs 0.9984); OCDS is biased too at 0° and 90° (z ≈ +7). Slow
#: diffusion and slow random-ballistic motion stay within the bound at 1e-2.
BIASED_AT_HARD_1E2 = {
    "flow v=0.5 θ=20°",
    "flow v=0.5 θ=0°",
    "flow v=0.5 θ=45°",
    "flow v=0.5 θ=70°",
    "flow v=0.5 θ=90°",
    "flow v=0.2 θ=0°",
}
#: A hard cut at 1e-3 still biases slower axial flow: flow 0.2 µm/s along the beam axis, rho_lin_1 at
#: axial=14 −0.0020 ± 0.0002 against torchdoct at 1e-6 (``torchdoct bench tradeoffs --part fidelity``);
#: kept as a strict xfail, the measured reason a hard 1e-3 is not the cure.
BIASED_AT_HARD_1E3 = {"flow v=0.2 θ=0°"}

#: The scene default, and hard cuts at two finer tolerances (named hard explicitly: the scene default
#: is now the taper, which the hard-cut settings must not inherit).
_HARD = {"truncation": "hard"} if _HAS_TRUNCATION_MODE else {}
SETTINGS = {
    "default": {},
    "1e-3 float32": {"truncation_tolerance": 1e-3, "dtype": "float32", **_HARD},
    "1e-4 float64": {"truncation_tolerance": 1e-4, "dtype": "float64", **_HARD},
}


def _params():
    out = []
    for cell in rc.CELLS:
        for label in SETTINGS:
            marks = []
            if label == "default" and DEFAULT_IS_HARD_1E2 and cell in BIASED_AT_HARD_1E2:
                marks.append(
                    pytest.mark.xfail(
                        strict=True,
                        reason="the default hard PSF truncation at 1e-2 biases slow motion at short lags (issue 24)",
                    )
                )
            if label == "1e-3 float32" and cell in BIASED_AT_HARD_1E3:
                marks.append(
                    pytest.mark.xfail(
                        strict=True,
                        reason="a hard PSF truncation at 1e-3 still biases the "
                        "short-lag intensity correlation of slow axial flow",
                    )
                )
            if label == "1e-4 float64":
                marks.append(pytest.mark.extended)
            out.append(pytest.param(cell, label, marks=marks, id=f"{cell}-{label}"))
    return out


@pytest.mark.parametrize("cell,setting", _params())
def test_every_feature_matches_reference(cell, setting):
    ref = rc.recorded_reference(cell, REF_TRIALS)
    td = rc.torchdoct_features(cell, TD_TRIALS_OF[setting], **SETTINGS[setting])
    rows = rc.compare(td, ref)
    bound = rc.z_bound(len(rows))
    assert all(r["nan_a"] == 0 and r["nan_b"] == 0 for r in rows), "empty resolution volumes (NaN features)"
    assert max(abs(r["z"]) for r in rows) <= bound, rc.format_failures(rows, bound)


@pytest.mark.skipif(not _HAS_TRUNCATION_MODE, reason="the simulator has no smooth PSF taper")
@pytest.mark.parametrize("tolerance", [1e-2, 1e-3])
@pytest.mark.parametrize("cell", ["flow v=0.5 θ=20°", "flow v=0.2 θ=0°", "diffusion D=0.002", "ballistic v=0.03 iso"])
def test_taper_matches_reference(cell, tolerance):
    """The smooth taper, float32, on the cells the hard cut biases. (At 1e-2 the taper's narrower PSF
    biases slow axial flow at lateral=18 by about −0.011 in ``rho_lin_8``: resolvable with 32,768
    trials per side, below this test's resolution; README, "Fidelity on what the models read".)"""
    ref = rc.recorded_reference(cell, REF_TRIALS)
    td = rc.torchdoct_features(cell, TD_TRIALS, truncation="taper", truncation_tolerance=tolerance)
    rows = rc.compare(td, ref)
    bound = rc.z_bound(len(rows))
    assert max(abs(r["z"]) for r in rows) <= bound, rc.format_failures(rows, bound)


_HAS_Y_WIDTH = any(f.name == "lateral_resolution_y_um" for f in dataclasses.fields(OCTSystem))


@pytest.mark.skipif(not _HAS_Y_WIDTH, reason="the simulator has no separate lateral width along y")
@pytest.mark.parametrize("setting", ["1e-3 float32", pytest.param("1e-4 float64", marks=pytest.mark.extended)])
@pytest.mark.parametrize("cell", list(rc.BSCAN_CELLS))
def test_bscan_lateral_reduction_matches_reference(cell, setting):
    """A B-scan's x-only lateral reduction (18 µm along x, 4.9 µm along y, 3.8 µm axial): every feature."""
    ref = rc.recorded_reference(cell, REF_TRIALS, configs=(3,))
    td = rc.torchdoct_features(cell, TD_TRIALS_OF[setting], configs=(3,), **SETTINGS[setting])
    rows = rc.compare(td, ref, configs=(3,))
    bound = rc.z_bound(len(rows))
    assert max(abs(r["z"]) for r in rows) <= bound, rc.format_failures(rows, bound)


def _assert_record_is_run(cell, configs):
    fresh = rc.summarize(rc.reference_features(cell, REF_TRIALS, rc.REF_SEED, configs))
    recorded = rc.recorded_reference(cell, REF_TRIALS, rc.REF_SEED, configs)
    assert fresh.keys() == recorded.keys()
    for name in fresh:
        for (m, sd, n, nan), (rm, rsd, rn, rnan) in zip(fresh[name], recorded[name]):
            assert (n, nan) == (rn, rnan), name
            # the same trials: equal up to the summation order of another machine's libraries
            assert m == pytest.approx(rm, rel=1e-9, abs=1e-12) and sd == pytest.approx(rsd, rel=1e-9, abs=1e-12), name


def test_the_recorded_reference_is_the_reference_simulators_run():
    """The cheapest recorded run (one configuration), run again by the reference simulator, gives the record."""
    _assert_record_is_run("flow v=2 θ=60° along x", (3,))


@pytest.mark.extended
@pytest.mark.parametrize("cell,configs", rc.record_runs(), ids=lambda v: str(v))
def test_every_recorded_reference_run_is_the_reference_simulators_run(cell, configs):
    _assert_record_is_run(cell, configs)

"""Training for a system of one's own (``doct-train --like``): identifiable ranges, the prior scaled to a
system, the speeds the simulator can hold, and the expected time of a run (docs/physics.md §13).

* :func:`identifiable_range`: the magnitudes at which a motion type is identifiable on a spec's system and
  protocol (the ground truth of :func:`classifier.truth.identifiability`, closed forms);
* :func:`prior_for_spec`: a :class:`classifier.prior.Prior` whose magnitude ranges are those ranges
  widened by half a decade, whose density keeps the scatterers per resolution volume of the shipped
  prior, and whose speeds stop at :func:`speed_cap`;
* :func:`estimate_seconds`: the expected time of :func:`classifier.train.train`, from a pilot.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .features import FeatureSpec
from .prior import BALLISTIC_LAWS, CLASSES, Draw, Prior
from .simulation import DEFAULT_TRUNCATION, scene_for
from .truth import identifiability, lateral_y

__all__ = [
    "identifiable_range",
    "prior_for_spec",
    "speed_cap",
    "estimate_seconds",
    "PRIOR_MARGIN_DECADES",
    "REFERENCE_RESOLUTIONS_UM",
    "MAX_SCATTERERS_PER_TRIAL",
    "FIT_SECONDS_PER_SAMPLE_EPOCH",
]

#: Nuisances over which :func:`identifiable_range` takes the widest range: flow at every polar angle
#: (degrees from the depth axis; azimuth 0, the lateral widths along x and y both enter through the
#: configurations), both random-ballistic direction laws, the prior's density extremes.
_RANGE_POLAR_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
#: Log-magnitude grid of :func:`identifiable_range`: 1e-9 to 1e5 at 24 points per decade (±5 %).
_RANGE_GRID = np.logspace(-9.0, 5.0, 14 * 24 + 1)
#: Half a decade beyond each end of the identifiable range (:func:`prior_for_spec`): the indeterminate
#: class is trained on the draws that are static or decorrelated, and the network must see the transition.
PRIOR_MARGIN_DECADES = 0.5
#: Lateral 1/e² width and axial FWHM (µm) of the system the shipped prior's density range refers to
#: (the reference paper's 840-nm system; :func:`prior_for_spec`).
REFERENCE_RESOLUTIONS_UM = (4.9, 3.8)


def identifiable_range(spec: FeatureSpec, label: int, prior: Prior | None = None) -> tuple[float, float]:
    """The magnitudes (D in µm²/s for diffusion, the speed in µm/s otherwise) at which motion type
    ``label`` is identifiable (:func:`identifiability`) at the spec's configurations and protocol for some
    direction (flow: polar angle 0-90°; random-ballistic: either direction law) and density of ``prior``.

    Below it every configuration sees a static sample over the acquisition (``ρ_I(T) ≥ 1 − ε``), above
    it every configuration decorrelates within one frame interval (``|g1(Δt)|² ≤ ε``): the closed forms
    of physics.md §5.3-5.4 on a log grid (:data:`_RANGE_GRID`, 5 % steps). ``ValueError`` when no
    magnitude of the grid is identifiable (a protocol that cannot see this motion)."""
    prior = prior or Prior()
    variants: list[dict[str, Any]]  # Draw's keyword arguments that vary
    if label == 2:
        variants = [dict(polar_angle_deg=a) for a in _RANGE_POLAR_DEG]
    elif label == 1:
        variants = [dict(ballistic_directions=law) for law in BALLISTIC_LAWS]
    else:
        variants = [{}]
    ok = np.zeros(_RANGE_GRID.size, bool)
    for i, mag in enumerate(_RANGE_GRID):
        for v in variants:
            for dens in sorted(set(prior.density_per_um3)):
                d = Draw(
                    label=label,
                    magnitude=float(mag),
                    polar_angle_deg=v.get("polar_angle_deg", 0.0),
                    azimuth_deg=0.0,
                    density_per_um3=dens,
                    sim_seed=0,
                    ballistic_directions=v.get("ballistic_directions", "isotropic"),
                )
                if identifiability(spec, d, prior)[0] == "identifiable":
                    ok[i] = True
                    break
            if ok[i]:
                break
    if not ok.any():
        raise ValueError(
            f"spec {spec.name!r}: {CLASSES[label]} is identifiable at no magnitude from "
            f"{_RANGE_GRID[0]:g} to {_RANGE_GRID[-1]:g} with {spec.n_frames} frames "
            f"{spec.frame_interval_s:g} s apart"
        )
    idx = np.flatnonzero(ok)
    return float(_RANGE_GRID[idx[0]]), float(_RANGE_GRID[idx[-1]])


def prior_for_spec(
    spec: FeatureSpec, base: Prior | None = None, margin_decades: float = PRIOR_MARGIN_DECADES
) -> tuple[Prior, dict[str, list[float]]]:
    """``base`` (default :class:`Prior`) with its magnitude ranges and density scaled to the spec's system
    and protocol.

    The density range keeps the number of scatterers per resolution volume, ``N_eff`` (physics.md §5.4),
    that ``base`` gives the reference system (:data:`REFERENCE_RESOLUTIONS_UM`, the paper's 4.9/3.8 µm)
    at the spec's finest configuration: the speckle statistics the shipped models were trained on, at a
    cost that does not grow with the resolution volume (a 10/8 µm system would otherwise simulate 9×
    more scatterers per trial). Each motion type's range is its :func:`identifiable_range` widened by
    ``margin_decades`` at both ends (the indeterminate class is trained on what lies beyond); flow gets
    its own speed range (:attr:`Prior.flow_speed_um_per_s`). Speeds are capped where the simulation would
    need more than :data:`MAX_SCATTERERS_PER_TRIAL` scatterers per trial (:func:`speed_cap`): faster
    motions are outside the trained range. Returns the prior and the identifiable ranges it came from
    (``{"diffusion": [lo, hi], ...}``, µm²/s or µm/s; ``"flow_simulated_max"`` etc. when capped)."""
    import dataclasses as _dc

    from torchdoct.conventions import n_eff

    base = base or Prior()
    ref = n_eff(1.0, *REFERENCE_RESOLUTIONS_UM)
    finest = min(
        n_eff(1.0, c.lateral_resolution_um, c.axial_resolution_um, **lateral_y(c)) for c in spec.configurations
    )
    d_lo, d_hi = (float(f"{d * ref / finest:.3g}") for d in base.density_per_um3)
    density = (d_lo, d_hi)
    base = _dc.replace(base, density_per_um3=density)
    ranges = {CLASSES[label]: list(identifiable_range(spec, label, base)) for label in range(len(CLASSES))}
    k = 10.0 ** float(margin_decades)

    def widen(r):
        return (float(f"{r[0] / k:.3g}"), float(f"{r[1] * k:.3g}"))

    speed = {}
    for label, name in ((1, "ballistic"), (2, "flow")):
        lo, hi = widen(ranges[name])
        cap = speed_cap(spec, base, label)
        if cap < hi:
            ranges[f"{name}_simulated_max"] = [float(f"{cap:.3g}")]
            hi = float(f"{cap:.3g}")
        speed[name] = (lo, max(hi, lo))
    prior = _dc.replace(
        base,
        diffusion_um2_per_s=widen(ranges["diffusion"]),
        speed_um_per_s=speed["ballistic"],
        flow_speed_um_per_s=speed["flow"],
    )
    return prior, ranges


#: Most scatterers per simulated trial a scaled prior asks of the simulator (:func:`speed_cap`): the
#: shipped prior's costliest draw (flow at 6 µm/s, 0.1 µm⁻³, the reference configurations: ~1e4). A
#: faster motion sweeps a longer box over the acquisition, and its memory (about 0.4 MB per scatterer per
#: 64 trials) and time grow with it: flow at 100 µm/s over 32 frames of 0.2048 s holds 1e5 scatterers
#: per trial, 38 GB per chunk.
MAX_SCATTERERS_PER_TRIAL = 1.0e4


def speed_cap(spec: FeatureSpec, prior: Prior, label: int) -> float:
    """The fastest speed (µm/s) of motion type ``label`` (1 ballistic, 2 flow) whose simulation at the prior's
    highest density holds at most :data:`MAX_SCATTERERS_PER_TRIAL` scatterers per trial at every direction
    (:meth:`torchdoct.sim.plan.Plan.expected_scatterers_per_trial`; bisection to 2 %)."""
    from torchdoct.sim.plan import make_plan

    def count(v: float) -> float:
        worst = 0.0
        angles = (0.0, 45.0, 90.0) if label == 2 else (0.0,)
        laws = BALLISTIC_LAWS if label == 1 else ("isotropic",)
        for a in angles:
            for law in laws:
                d = Draw(
                    label=label,
                    magnitude=v,
                    polar_angle_deg=a,
                    azimuth_deg=0.0,
                    density_per_um3=prior.density_per_um3[1],
                    sim_seed=0,
                    ballistic_directions=law,
                )
                plan = make_plan(scene_for(spec, d, prior), truncation_tolerance=1e-2, truncation=DEFAULT_TRUNCATION)
                worst = max(worst, plan.expected_scatterers_per_trial)
        return worst

    from torchdoct.sim.config import MAX_SPEED_UM_PER_S

    lo, hi = 1e-6, float(MAX_SPEED_UM_PER_S)
    if count(hi) <= MAX_SCATTERERS_PER_TRIAL:
        return hi
    if count(lo) > MAX_SCATTERERS_PER_TRIAL:
        return lo
    while hi / lo > 1.02:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if count(mid) <= MAX_SCATTERERS_PER_TRIAL else (lo, mid)
    return lo


def estimate_seconds(
    spec: FeatureSpec,
    prior: Prior,
    cfg: Any,
    *,
    pilot_draws: int = 6,
    threads: int | None = None,
    calibration_draws: int = 0,
    calibration_trials: int = 0,
) -> dict[str, float]:
    """Expected time of :func:`classifier.train.train` with the recipe ``cfg`` (a
    :class:`classifier.train.TrainConfig`), in s, from a pilot: the first ``pilot_draws`` draws of the training split
    simulated and timed (their numbers are not kept). Simulation: the mean time per draw × the draws of
    every split (train, validation, test, and the test-sized shifted-prior and bulk-phase splits when the
    recipe makes them) / the cores; the network's fit: :data:`FIT_SECONDS_PER_SAMPLE_EPOCH` × samples
    per epoch × the epoch cap (an upper bound: early stopping often ends sooner); the calibration split
    (``calibration_draws`` draws of ``calibration_trials`` trials, after training) at the same time per
    trial."""
    from torchdoct.runtime.threads import resolve_threads, single_torch_thread

    from .prior import draw_parameters
    from .simulation import simulate_draw

    t0 = time.perf_counter()
    with single_torch_thread():
        for k in range(int(pilot_draws)):
            d = draw_parameters(prior, cfg.seed, "train", k, cfg.replicates)
            simulate_draw(
                spec,
                d,
                prior,
                trials=cfg.trials_per_draw,
                truncation_tolerance=cfg.truncation_tolerance,
                truncation=cfg.truncation,
            )
    per_draw = (time.perf_counter() - t0) / max(int(pilot_draws), 1)
    extra = 0
    if spec.is_signature if cfg.shifted_test is None else cfg.shifted_test:
        extra += cfg.draws_test
    if spec.needs_field if cfg.bulk_phase_test is None else cfg.bulk_phase_test:
        extra += cfg.draws_test
    draws = cfg.draws_train + cfg.draws_validation + cfg.draws_test + extra
    simulation = per_draw * draws / resolve_threads(threads)
    calibration = per_draw * calibration_draws * calibration_trials / cfg.trials_per_draw / resolve_threads(threads)
    samples = cfg.draws_train * cfg.replicates * (cfg.singles_per_group + cfg.pooled_per_group)
    fit = FIT_SECONDS_PER_SAMPLE_EPOCH * samples * cfg.max_epochs * (spec.n_features / 36.0) ** 0.5
    baselines = BASELINE_SECONDS_PER_SAMPLE * samples if cfg.baselines else 0.0
    return {
        "pilot_s_per_draw": per_draw,
        "draws": draws,
        "simulation_s": simulation,
        "fit_s": fit,
        "baselines_s": baselines,
        "calibration_s": calibration,
        "total_s": simulation + fit + baselines + calibration + REPORT_SECONDS,
    }


#: Seconds per training sample and epoch of the network's fit on one thread: the mean of three
#: ``doct-train --like`` runs on an idle 2-core machine (64-64 hidden, 60 epochs of 737,280 samples);
#: :func:`estimate_seconds` scales it with the square root of the feature count.
FIT_SECONDS_PER_SAMPLE_EPOCH = 504.0 / (60 * 737_280)
#: Seconds per training sample of the scikit-learn baselines (logistic regression and gradient boosting;
#: the same runs), skipped with ``--no-baselines``.
BASELINE_SECONDS_PER_SAMPLE = 131.0 / 737_280
#: Seconds of the test sets' evaluation, the ONNX export and the report (the middle of the same runs).
REPORT_SECONDS = 30.0

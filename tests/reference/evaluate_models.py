"""Evaluation of a trained motion-type classifier on data it never saw: the reference simulator and a
prior the models were not trained on.

Run (from the repository root)::

    python -m tests.reference.evaluate_models --model signature [--draws 300] [--trials 32] [--seed 0] --out DIR

``--model``: a shipped model name, an ``.onnx`` file, or a ``doct-train --out`` directory holding one.
Writes ``<out>/<model>-independent.json`` and ``.md`` (never over existing files without ``--force``)
and prints a summary.

**Data** (:func:`draw_independent`, :data:`PRIOR_TEXT`). Draw ``k`` of seed ``S`` takes its numbers
from ``numpy.random.SeedSequence(S, spawn_key=(0, k))`` (so a draw does not depend on how many are
made):

* motion type ``k mod 3``: diffusion, random-ballistic motion and flow in equal thirds;
* magnitude log-uniform (independent draws, not the training's stratified sequence) over sub-ranges
  inside each type's identifiable range (ground truth of :func:`classifier.truth.identifiability`
  for the signature spec at this density: diffusion 2e-5 to 0.025 µm²/s, random-ballistic motion
  0.005-0.7 µm/s (isotropic law; 0.003-2.3 for the uniform-angles law), flow above 0.09-0.14 µm/s):
  D ∈ [3e-4, 2e-2] µm²/s, ballistic v ∈ [1e-2, 0.5] µm/s, flow v ∈ [0.2, 3] µm/s (training: one
  range [1e-4, 15] µm²/s and one [1e-3, 6] µm/s for both speeds);
* flow direction: polar angle from the depth axis uniform in [0°, 90°] (every band 0-30°, 30-60°,
  60-90° holds a third of the flow draws; training: isotropic over the sphere, 13 % within 30° of the
  axis), azimuth uniform in [0°, 360°);
* random-ballistic direction law: isotropic or the paper's uniform-angles law, 1:1 per draw;
* moving-scatterer density fixed at 0.04 µm⁻³ (training: U[0.02, 0.1]); no static scatterers
  (training: a static fraction U[0, 0.8] with probability 1/2);
* noise always on, SNR ~ U[20, 30] dB per draw (training: with probability 1/2, U[10, 40] dB).

**Simulation** (:func:`simulate_joint`): the brute-force model of :mod:`refsim` (physics.md §5.1:
Gaussian PSF, round-trip phase ``exp(i·2·k·n·z)``; exact Brownian and straight paths at the frame
times; float64; its :class:`refsim.Optics`, :class:`refsim.Motion`, direction laws and
:func:`refsim.mean_intensity`), with one difference: **every configuration of the model sees the same
scatterers on the same paths**, as one dataset and its computational resolution reductions do (and a
co-registered dual-band acquisition of one sample). The scatterers are a Poisson process in a box
that holds every starting point from which a path can reach any configuration's window
``|x_a| < c·s_a`` (``c`` = :data:`refsim.BOX_SIGMAS` = 6 amplitude sigmas) within the acquisition
(:func:`source_box_um`; for flow the volume of :func:`refsim.box_lengths_um`'s box, no wrapping
needed); a configuration sums, at every frame, every scatterer whose path can enter its window (the
others stay below ``exp(−c²/2) = 1.5e-8`` of its peak amplitude, the level :mod:`refsim`'s box
neglects; torchdoct's default truncation enters scatterers at 1e-2), so no scatterer enters or leaves
a sum during the acquisition. Configurations come from the model's spec: wavelength,
lateral 1/e² width along x and y (``lateral_resolution_y_um`` where a configuration gives it, else
isotropic), axial FWHM, refractive index, frame count and interval.

**Noise**: circular complex Gaussian, independent per frame, of power ``⟨I⟩/10^(SNR/10)`` with
``⟨I⟩`` the configuration's own mean intensity (physics.md §5.2, §8), drawn **independently per
configuration**. A measured dataset's resolution reductions are computed from one noisy field (their
noise is filtered and correlated between configurations); independent noise at the same SNR per
configuration is the approximation made here (it is also the training data's noise model).

**Randomness**: trials come in blocks of :data:`BLOCK_TRIALS`; block ``b`` of a draw uses
``SeedSequence(sim_seed, spawn_key=(b,))``: a trial's numbers do not depend on the number of trials.

**Features**: :func:`torchdoct.sim.signature.signature` (the extractor ``torchdoct maps --signature``
and the training data use) on the float64 fields, in the model's feature order, stored as float32 as
in training. **Ground truth**: :func:`classifier.truth.identifiability` of a
:class:`classifier.prior.Draw` with the model's ε, so "identifiable" means what it means in training.

**Metrics** (per pool 1 and 25; pool ``n`` = the mean of ``n`` trials of one draw, ``pool_pixels = n``,
8 random subsets per draw, :func:`classifier.train.pooled_samples`, as in the training reports and as
``doct-classify --pool`` feeds independent pixels), decided by the model's own rule:
the metrics block of every test set of the training reports, :func:`classifier.evaluation.evaluate_set`:
balanced accuracy and coverage on identifiable pixels, per-class recall, ECE, flow recall by polar band
and speed decade, the accuracy-coverage table, accuracy against magnitude, the magnitude head's median
|log10 error| and 68 %/95 % interval coverage (head of the true class, identifiable pixels). Standard
errors: bootstrap over draws (the independent unit), :data:`N_BOOT` resamples. Beside every number its target
(:data:`TARGETS`, issue 24).

**Prediction sets** (models with a calibration, ``conformal`` of each pool): ``doct-classify``'s sets at its
default error level, per motion the share decided, decided as another motion and whose set misses it, alone
(``--decide-ballistic``) and after rule 1, which ``doct-classify`` applies to one pixel's time series
(:func:`conformal_scores`). These data are not drawn like the calibration set (another prior and simulator):
they measure what the guarantee is worth off it.

**Cost**: the reference simulator's draws (300 × 32 trials by default); diffusion draws cost the most, their
Brownian steps and phases being drawn and evaluated at every frame. The report records the seconds, and
its bootstrap standard errors beside every number.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

try:  # run as `python -m tests.reference.evaluate_models`
    from . import refsim
except ImportError:  # imported by the tests (tests/reference on sys.path)
    import refsim

__all__ = [
    "DEFAULT_DRAWS",
    "DEFAULT_TRIALS",
    "BLOCK_TRIALS",
    "DENSITY",
    "RANGES",
    "SNR_DB",
    "POLAR_DEG",
    "POOLS",
    "TARGETS",
    "IndependentDraw",
    "draw_independent",
    "independent_prior",
    "dataset_draw",
    "optics_for",
    "motion_for",
    "source_box_um",
    "simulate_joint",
    "draw_features",
    "evaluate_model",
    "format_markdown",
    "main",
]

DEFAULT_DRAWS = 300
DEFAULT_TRIALS = 32
#: Trials per random block of the simulation.
BLOCK_TRIALS = 8
#: Moving-scatterer density (µm⁻³).
DENSITY = 0.04
#: Log-uniform magnitude range per motion type: D (µm²/s), ballistic v, flow v (µm/s).
RANGES = {"diffusion": (3e-4, 2e-2), "ballistic": (1e-2, 0.5), "flow": (0.2, 3.0)}
#: SNR range (dB), noise always on.
SNR_DB = (20.0, 30.0)
#: Flow polar angle range (degrees from the depth axis), uniform in the angle.
POLAR_DEG = (0.0, 90.0)
#: Pool sizes evaluated (capped at the number of trials), subsets per draw for pools > 1.
POOLS = (1, 25)
POOLED_PER_DRAW = 8
#: Bootstrap resamples over draws for the standard errors.
N_BOOT = 200
#: The goals of issue 24 on independent data (measured, not test thresholds).
TARGETS = {
    "pool_1": {"balanced_accuracy_identifiable": 0.88, "coverage_identifiable": 0.80, "ece": 0.05},
    "pool_25": {"balanced_accuracy_identifiable": 0.98, "coverage_identifiable": 0.90},
    "flow_recall_every_polar_band": 0.80,
    "magnitude_pool_1": {"median_abs_log10_error": 0.06, "coverage_68": (0.65, 0.71), "coverage_95": (0.93, 0.97)},
}
PRIOR_TEXT = (
    f"motion type in equal thirds (draw k: type k mod 3); magnitude log-uniform (independent draws): "
    f"D in [{RANGES['diffusion'][0]:g}, {RANGES['diffusion'][1]:g}] µm²/s, random-ballistic v in "
    f"[{RANGES['ballistic'][0]:g}, {RANGES['ballistic'][1]:g}] µm/s, flow v in [{RANGES['flow'][0]:g}, "
    f"{RANGES['flow'][1]:g}] µm/s (inside each type's identifiable range); flow polar angle uniform in "
    f"[{POLAR_DEG[0]:g}°, {POLAR_DEG[1]:g}°] from the depth axis, azimuth uniform; random-ballistic "
    f"direction law isotropic or uniform-angles, 1:1; moving-scatterer density {DENSITY:g} µm⁻³; no static "
    f"scatterers; noise always on at SNR U[{SNR_DB[0]:g}, {SNR_DB[1]:g}] dB relative to each "
    f"configuration's mean intensity, independent per configuration, frame and trial"
)
SIM_TEXT = (
    "reference simulator (brute force, float64, exact paths; physics.md §5.1), every configuration of the "
    "model seeing the same scatterers on the same paths (one Poisson set in a box that reaches every "
    "configuration's window of ±6 amplitude sigmas); features by torchdoct.sim.signature; ground truth by classifier.truth.identifiability with the model's epsilon"
)
_CLASSES = ("diffusion", "ballistic", "flow")
_LAWS = ("isotropic", "uniform-angles")


# ------------------------------------------------------------------------------------------------
# the prior


@dataclass(frozen=True)
class IndependentDraw:
    """One draw of the independent prior: motion ``label`` (index of diffusion, ballistic, flow),
    ``magnitude`` (µm²/s or µm/s), flow direction (degrees; drawn for every type, used by flow), the
    random-ballistic direction law, the SNR (dB) and the simulator seed."""

    k: int
    label: int
    magnitude: float
    polar_angle_deg: float
    azimuth_deg: float
    ballistic_directions: str
    snr_db: float
    sim_seed: int

    @property
    def motion(self) -> str:
        return _CLASSES[self.label]


def draw_independent(seed: int, k: int) -> IndependentDraw:
    """Draw ``k`` of the independent prior (module docstring) from ``SeedSequence(seed, spawn_key=(0, k))``."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(0, int(k)))
    u = np.random.default_rng(ss).random(5)
    label = int(k) % 3
    lo, hi = RANGES[_CLASSES[label]]
    magnitude = float(math.exp(math.log(lo) + u[0] * (math.log(hi) - math.log(lo))))
    polar = POLAR_DEG[0] + u[1] * (POLAR_DEG[1] - POLAR_DEG[0])
    law = _LAWS[int(u[3] >= 0.5)]
    snr = SNR_DB[0] + u[4] * (SNR_DB[1] - SNR_DB[0])
    sim_seed = int(ss.generate_state(2, np.uint64)[1] >> np.uint64(2))
    return IndependentDraw(
        k=int(k),
        label=label,
        magnitude=magnitude,
        polar_angle_deg=float(polar),
        azimuth_deg=float(360.0 * u[2]),
        ballistic_directions=law,
        snr_db=float(snr),
        sim_seed=sim_seed,
    )


def independent_prior(epsilon: float):
    """The prior as a :class:`classifier.prior.Prior` (for the ground truth and the report; one speed
    range spans both speed types, whose own ranges are :data:`RANGES`)."""
    from classifier.prior import Prior

    return Prior(
        diffusion_um2_per_s=RANGES["diffusion"],
        speed_um_per_s=(min(RANGES["ballistic"][0], RANGES["flow"][0]), max(RANGES["ballistic"][1], RANGES["flow"][1])),
        ballistic_directions="both",
        flow_polar_angle_deg=POLAR_DEG,
        flow_polar_law="uniform-angle",
        density_per_um3=(DENSITY, DENSITY),
        static_probability=0.0,
        noise_probability=1.0,
        snr_db=SNR_DB,
        identifiability_epsilon=float(epsilon),
    )


def dataset_draw(d: IndependentDraw):
    """The :class:`classifier.prior.Draw` of an independent draw (for :func:`classifier.truth.identifiability`)."""
    from classifier.prior import Draw

    return Draw(
        label=d.label,
        magnitude=d.magnitude,
        polar_angle_deg=d.polar_angle_deg,
        azimuth_deg=d.azimuth_deg,
        density_per_um3=DENSITY,
        sim_seed=d.sim_seed,
        nuisance=((0.0, d.snr_db),),
        ballistic_directions=d.ballistic_directions,
    )


def optics_for(spec) -> list[refsim.Optics]:
    """:class:`refsim.Optics` of every configuration of a :class:`classifier.features.FeatureSpec`."""
    out = []
    for c in spec.configurations:
        ly = getattr(c, "lateral_resolution_y_um", None)
        out.append(
            refsim.Optics(
                float(c.wavelength_um),
                float(c.lateral_resolution_um),
                float(c.axial_resolution_um),
                lateral_y_um=None if ly is None else float(ly),
                refractive_index=float(spec.refractive_index),
            )
        )
    return out


def motion_for(d: IndependentDraw) -> refsim.Motion:
    if d.label == 0:
        return refsim.Motion("diffusion", diffusion_um2_per_s=d.magnitude)
    if d.label == 1:
        return refsim.Motion("ballistic", speed_um_per_s=d.magnitude, directions=d.ballistic_directions)
    return refsim.Motion(
        "flow", speed_um_per_s=d.magnitude, polar_angle_deg=d.polar_angle_deg, azimuth_deg=d.azimuth_deg
    )


# ------------------------------------------------------------------------------------------------
# simulation: one set of scatterers for every configuration


def source_box_um(
    optics: Sequence[refsim.Optics], motion: refsim.Motion, duration_s: float, box_sigmas: float = refsim.BOX_SIGMAS
) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (µm) of the box the scatterers are drawn from (module docstring).

    The windows ``|x_a| ≤ c·s_a`` of every configuration (``c`` = ``box_sigmas``) have the bounding box
    ``±H_a``, ``H_a = c·max s_a``; the box holds every starting point from which a path can reach it
    within ``duration_s``: flow ``[−H_a − max(v_a·T, 0), H_a + max(−v_a·T, 0)]`` (the volume of
    :func:`refsim.box_lengths_um`'s box), random-ballistic motion ``±(H_a + v·T)``, diffusion
    ``±(H_a + 6·√(2·D·T))``, static ``±H_a``.
    """
    H = box_sigmas * np.max([o.sigmas_um for o in optics], axis=0)
    T = float(duration_s)
    if motion.kind == "flow":
        vt = motion.flow_velocity * T
        return -H - np.maximum(vt, 0.0), H + np.maximum(-vt, 0.0)
    if motion.kind == "ballistic":
        r = np.full(3, motion.speed_um_per_s * T)
    elif motion.kind == "diffusion":
        r = np.full(3, 6.0 * math.sqrt(2.0 * motion.diffusion_um2_per_s * T))
    else:
        r = np.zeros(3)
    return -H - r, H + r


def _joint_block(
    optics: Sequence[refsim.Optics],
    motion: refsim.Motion,
    density: float,
    times: np.ndarray,
    trials: int,
    rng: np.random.Generator,
    snr_db: float | None,
    box_sigmas: float,
) -> np.ndarray:
    """Fields ``[trials, C, T]`` of one block: one Poisson set of scatterers and paths for all configurations.

    Per configuration, only the scatterers whose path can enter its window ``|x_a| < c·s_a`` (``c`` =
    ``box_sigmas``) during the acquisition are summed, over every frame (straight paths: the bounding
    box of the path meets the window; diffusion: the start lies within the window widened by 6 SDs
    of the whole acquisition's displacement); the others stay below ``exp(−c²/2)`` of the peak amplitude.
    """
    duration = float(times[-1] - times[0])
    lo, hi = source_box_um(optics, motion, duration, box_sigmas)
    counts = rng.poisson(density * float(np.prod(hi - lo)), size=trials)
    m = int(counts.sum())
    owner = np.repeat(np.arange(trials), counts)
    pos0 = (lo + rng.random((m, 3)) * (hi - lo)).T.copy()  # [3, m]: one contiguous row per axis
    if motion.kind == "ballistic":
        vel = (motion.speed_um_per_s * refsim._directions(rng, m, motion.directions)).T.copy()
    elif motion.kind == "flow":
        vel = np.repeat(motion.flow_velocity[:, None], m, axis=1)
    else:
        vel = np.zeros((3, m))
    sig = [np.array(o.sigmas_um) for o in optics]
    half = [box_sigmas * s for s in sig]
    if motion.kind == "diffusion":
        reach = 6.0 * math.sqrt(2.0 * motion.diffusion_um2_per_s * duration)
        near = [np.all(np.abs(pos0) < (h + reach)[:, None], axis=0) for h in half]
    else:  # the bounding box of the straight path [p0, p0 + v·T] meets the window
        end = pos0 + vel * duration
        near = [
            np.all((np.minimum(pos0, end) < h[:, None]) & (np.maximum(pos0, end) > -h[:, None]), axis=0) for h in half
        ]
    used = np.flatnonzero(np.any(near, axis=0))  # scatterers some configuration sees
    p0, v, who_all = pos0[:, used], vel[:, used], owner[used]
    sel = [np.flatnonzero(n[used]) for n in near]  # per configuration, into `used`
    who = [who_all[s] for s in sel]
    w = [0.5 / s**2 for s in sig]
    two_kn = [2.0 * o.kn for o in optics]
    sums = [_TrialSums(k, trials) for k in who]
    out = np.empty((trials, len(optics), len(times)), dtype=np.complex128)
    t_rel = times - times[0]
    if motion.kind == "diffusion":
        dt = np.diff(times)
        if len(times) > 2 and np.ptp(dt) > 1e-12 * times[-1]:
            raise ValueError("diffusion needs uniform frame times")
        step_sd = math.sqrt(2.0 * motion.diffusion_um2_per_s * float(dt[0])) if len(times) > 1 else 0.0
        pos = p0.copy()
        for i in range(len(times)):
            if i > 0:  # exact Brownian path at the frame times
                pos += rng.standard_normal((pos.shape[1], 3)).T * step_sd
            phasor = {}
            for c in range(len(optics)):
                if two_kn[c] not in phasor:  # exp(i·2kn·z) of every used scatterer, once per wavelength
                    phasor[two_kn[c]] = _cis(two_kn[c] * pos[2])
                q = pos[:, sel[c]]
                amp = np.exp(-(w[c][0] * q[0] ** 2 + w[c][1] * q[1] ** 2 + w[c][2] * q[2] ** 2))
                out[:, c, i] = sums[c](amp * phasor[two_kn[c]][sel[c]])
        return _add_noise(out, optics, density, snr_db, rng)
    # straight paths r(t) = r0 + v·t: the Gaussian exponent is A + B·t + C·t² per scatterer, and the
    # phase 2kn·(z0 + v_z·t) turns by a fixed factor per frame interval (uniform frames)
    for c in range(len(optics)):
        x0, vv = p0[:, sel[c]], v[:, sel[c]]
        wc = w[c][:, None]
        A = np.sum(wc * x0 * x0, axis=0)
        B = 2.0 * np.sum(wc * x0 * vv, axis=0)
        C = np.sum(wc * vv * vv, axis=0)
        phasor = _cis(two_kn[c] * x0[2])
        if motion.kind == "ballistic" and len(times) > 1:
            turn = _cis(two_kn[c] * vv[2] * (times[1] - times[0]))
        for i, t in enumerate(t_rel):
            if motion.kind == "ballistic" and i > 0:
                phasor *= turn
            e = sums[c](np.exp(-(A + t * (B + t * C))) * phasor)
            if motion.kind == "flow":  # the common Doppler phase of flow
                e *= np.exp(1j * two_kn[c] * motion.flow_velocity[2] * t)
            out[:, c, i] = e
    return _add_noise(out, optics, density, snr_db, rng)


def _cis(phase: np.ndarray) -> np.ndarray:
    """``exp(i·phase)`` (complex128) from float64 cosine and sine (torch's vectorised ones: 5x numpy's speed,
    within 1 ulp of numpy's)."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(phase, dtype=np.float64))
    out = np.empty(t.shape, np.complex128)
    out.real, out.imag = torch.cos(t).numpy(), torch.sin(t).numpy()
    return out


class _TrialSums:
    """Sums of per-scatterer values over the scatterers of each trial (``owner`` sorted ascending)."""

    def __init__(self, owner: np.ndarray, trials: int):
        counts = np.bincount(owner, minlength=trials)
        self.trials = trials
        self.nonempty = counts > 0
        self.starts = (np.cumsum(counts) - counts)[self.nonempty]

    def __call__(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros(self.trials, dtype=values.dtype)
        if self.starts.size:
            out[self.nonempty] = np.add.reduceat(values, self.starts)
        return out


def _add_noise(
    out: np.ndarray, optics: Sequence[refsim.Optics], density: float, snr_db: float | None, rng: np.random.Generator
) -> np.ndarray:
    """Circular complex Gaussian noise, independent per configuration, trial and frame, of power
    ``⟨I⟩/10^(SNR/10)`` with ``⟨I⟩`` the configuration's mean intensity (physics.md §5.2, §8)."""
    if snr_db is None:
        return out
    trials, _, frames = out.shape
    for c, o in enumerate(optics):
        sd = math.sqrt(refsim.mean_intensity(o, density) / 10.0 ** (snr_db / 10.0) / 2.0)
        out[:, c] += sd * (rng.standard_normal((trials, frames)) + 1j * rng.standard_normal((trials, frames)))
    return out


def simulate_joint(
    optics: Sequence[refsim.Optics],
    motion: refsim.Motion,
    *,
    density_per_um3: float,
    n_frames: int,
    frame_interval_s: float,
    trials: int,
    seed: int,
    snr_db: float | None = None,
    box_sigmas: float = refsim.BOX_SIGMAS,
) -> np.ndarray:
    """Complex fields ``[trials, configurations, frames]`` (complex128), every configuration seeing the
    same scatterers (module docstring); noise (``snr_db``, None = none) independent per configuration.
    Frames at ``t_i = i·frame_interval_s``; block ``b`` of :data:`BLOCK_TRIALS` trials draws from
    ``SeedSequence(seed, spawn_key=(b,))``."""
    times = np.arange(int(n_frames), dtype=np.float64) * float(frame_interval_s)
    out = np.empty((int(trials), len(optics), int(n_frames)), dtype=np.complex128)
    for b in range(-(-int(trials) // BLOCK_TRIALS)):
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(b,)))
        e = _joint_block(optics, motion, float(density_per_um3), times, BLOCK_TRIALS, rng, snr_db, box_sigmas)
        lo = b * BLOCK_TRIALS
        out[lo : lo + BLOCK_TRIALS] = e[: int(trials) - lo]
    return out


def draw_features(spec, d: IndependentDraw, trials: int) -> np.ndarray:
    """Model features ``[trials, F]`` (float32, the spec's order) of one draw, by torchdoct's extractor."""
    import torch

    from torchdoct.sim.signature import signature

    e = simulate_joint(
        optics_for(spec),
        motion_for(d),
        density_per_um3=DENSITY,
        n_frames=spec.n_frames,
        frame_interval_s=spec.frame_interval_s,
        trials=trials,
        seed=d.sim_seed,
        snr_db=d.snr_db,
    )
    _, sig = signature(torch.from_numpy(e), spec.frame_times_s, names=spec.metrics)  # [trials, C, metrics]
    return sig.reshape(sig.shape[0], -1).numpy().astype(np.float32)


# ------------------------------------------------------------------------------------------------
# evaluation


def _bootstrap(fn, draw: np.ndarray, n_boot: int, seed: int) -> dict[str, float]:
    """SD over ``n_boot`` resamples of the draws of the scalars ``fn(index) -> {name: value}`` (NaN dropped):
    :func:`classifier.evaluation.bootstrap_draws` (the resampling of every standard error here)."""
    from classifier.evaluation import bootstrap_draws

    return bootstrap_draws(fn, draw, n_boot=n_boot, seed=seed)


def _resolve_model(model: str):
    """``(ClassifierModel, name)`` of a shipped name, an ``.onnx`` file or a directory holding one."""
    from classifier.infer import load_model

    p = Path(model)
    if p.is_dir():
        found = sorted(p.glob("*.onnx"))
        if len(found) != 1:
            raise ValueError(
                f"--model {model}: a directory must hold exactly one .onnx model (doct-train --out); "
                f"found {[f.name for f in found] or 'none'}. Fix: give the .onnx file itself"
            )
        p = found[0]
        return load_model(str(p), threads=1), p.stem
    mdl = load_model(model, threads=1)
    return mdl, (mdl.path.stem if p.suffix == ".onnx" else str(model))


def conformal_scores(
    probabilities: np.ndarray,
    pool_pixels: np.ndarray,
    truth: np.ndarray,
    identifiable: np.ndarray,
    classes: Sequence[str],
    calibration: dict[str, Any],
    alpha: float,
) -> dict[str, Any]:
    """``doct-classify``'s prediction sets (:mod:`classifier.conformal`, the model's calibration at error level
    ``alpha``) scored per motion over its identifiable samples (``truth`` indexes :data:`_CLASSES`): the share
    decided as the motion (a set of that motion alone), decided as another motion (a set of one other motion:
    the wrong share), whose set misses the motion (the share the split-conformal guarantee bounds by ``alpha``
    on data drawn like the calibration set, not on these), and the mean number of motions in the set. With
    ``rule_1`` the same after rule 1 of :mod:`classifier.ambiguity`, which ``doct-classify`` applies wherever
    the maps cannot see an axis (always, for one pixel's time series): a ``ballistic`` set becomes
    ``ballistic-or-flow``."""
    from classifier.conformal import MODES, prediction_sets, set_label_names, set_labels, thresholds_for

    mode = calibration.get("mode", MODES[0])
    members = prediction_sets(probabilities, thresholds_for(calibration, pool_pixels, alpha, mode))
    labels = set_labels(members, classes)
    ballistic = list(classes).index("ballistic")
    either = len(classes) + set_label_names(classes).index("ballistic-or-flow")
    ruled = np.where(labels == ballistic, either, labels)
    motion_idx = [list(classes).index(m) for m in _CLASSES]
    out: dict[str, Any] = {"alpha": float(alpha), "mode": mode, "per_class": {}, "rule_1": {}}
    for k, name in enumerate(_CLASSES):
        sel = identifiable & (truth == k)
        n = int(sel.sum())
        own, others = motion_idx[k], [motion_idx[j] for j in range(len(_CLASSES)) if j != k]

        def share(mask: np.ndarray) -> float | None:
            return float(mask.mean()) if n else None

        out["per_class"][name] = {
            "samples": n,
            "decided": share(labels[sel] == own),
            "wrong_share": share(np.isin(labels[sel], others)),
            "set_miss_share": share(~members[sel, own]),
            "mean_set_size": share(members[sel][:, motion_idx].sum(axis=1)),
        }
        out["rule_1"][name] = {"decided": share(ruled[sel] == own), "wrong_share": share(np.isin(ruled[sel], others))}
    return out


def evaluate_model(
    model: str,
    *,
    draws: int = DEFAULT_DRAWS,
    trials: int = DEFAULT_TRIALS,
    seed: int = 0,
    n_boot: int = N_BOOT,
    progress: bool = True,
) -> dict[str, Any]:
    """Simulate ``draws`` independent draws × ``trials`` pixels, classify them with ``model`` and return
    the report (JSON-able dict; module docstring)."""
    from classifier.dataset import Dataset
    from classifier.evaluation import evaluate_set
    from classifier.train import pooled_samples
    from classifier.truth import STATUS, identifiability

    for name, v, low in (("draws", draws, 1), ("trials", trials, 1), ("seed", seed, 0), ("n_boot", n_boot, 2)):
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise ValueError(f"{name} must be an integer >= {low}; got {v!r}")
    t0 = time.perf_counter()
    mdl, name = _resolve_model(model)
    spec = mdl.spec
    if not spec.is_signature:
        raise ValueError(
            f"model {name}: its features are {list(spec.metrics)}; this evaluation computes the "
            "signature features (torchdoct.sim.signature) and needs a signature model"
        )
    names = [col["name"] for col in mdl.columns[:-1]]
    if names != list(spec.feature_names) or mdl.columns[-1]["metric"] != "pool_pixels":
        raise ValueError(
            f"model {name}: its input columns {names + [mdl.columns[-1]['name']]} are not its spec's "
            f"features {list(spec.feature_names)} followed by pool_pixels; re-export it with doct-train"
        )
    classes = mdl.classes
    rule = mdl.rule
    prior = independent_prior(float(rule["epsilon"]))
    cols: dict[str, list] = {k: [] for k in ("x", "y", "draw", "status", "magnitude", "snr_db", "polar_angle_deg")}
    per_draw = []
    status_counts = dict.fromkeys(STATUS, 0)
    dropped = 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=draws, unit="draw", desc=f"independent data for {name}")
    t_sim = time.perf_counter()
    for k in range(draws):
        d = draw_independent(seed, k)
        status, _, _ = identifiability(spec, dataset_draw(d), prior)
        status_counts[status] += 1
        x = draw_features(spec, d, trials)
        keep = np.all(np.isfinite(x), axis=1)
        dropped += int((~keep).sum())
        n = int(keep.sum())
        cols["x"].append(x[keep])
        cols["y"].append(np.full(n, d.label, np.int64))
        cols["draw"].append(np.full(n, k, np.int64))
        cols["status"].append(np.full(n, STATUS.index(status), np.int64))
        cols["magnitude"].append(np.full(n, d.magnitude))
        cols["snr_db"].append(np.full(n, d.snr_db))
        cols["polar_angle_deg"].append(np.full(n, d.polar_angle_deg if d.label == 2 else math.nan))
        per_draw.append({**asdict(d), "motion": d.motion, "status": status})
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    sim_s = time.perf_counter() - t_sim
    a = {k: np.concatenate(v) for k, v in cols.items()}
    ds = Dataset(
        x=a["x"].reshape(-1, spec.n_features),
        y=a["y"],
        draw=a["draw"],
        group=a["draw"],
        status=a["status"],
        magnitude=a["magnitude"],
        density=np.full(a["y"].shape, DENSITY),
        static_fraction=np.zeros(a["y"].shape),
        snr_db=a["snr_db"],
        polar_angle_deg=a["polar_angle_deg"],
    )
    pools = sorted({min(int(p), trials) for p in POOLS})
    ranges = [RANGES[c] for c in _CLASSES]
    results: dict[str, Any] = {}
    for pool in pools:
        if pool == 1:
            s = {
                "x": np.concatenate([ds.x, np.ones((len(ds), 1), np.float32)], axis=1),
                "y": ds.y,
                "status": ds.status,
                "draw": ds.draw,
                "magnitude": ds.magnitude,
                "polar_angle_deg": ds.polar_angle_deg,
            }
        else:
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(1, pool)))
            groups = np.unique(ds.group)
            s = pooled_samples(ds, [np.full(POOLED_PER_DRAW, pool) for _ in groups], rng)
        probs, mean, sd = mdl.predict_all(s["x"])
        results[str(pool)] = evaluate_set(
            probs,
            s,
            rule,
            class_names=classes,
            ranges=ranges,
            magnitude=None if mean is None else (mean, sd),
            resampled_errors=True,
            n_boot=n_boot,
            seed=seed,
        )
        if mdl.calibration is not None:
            from classifier.conformal import DEFAULT_ALPHA

            results[str(pool)]["conformal"] = conformal_scores(
                probs,
                s["x"][:, -1],
                np.asarray(s["y"]),
                np.asarray(s["status"]) == STATUS.index("identifiable"),
                classes,
                mdl.calibration,
                DEFAULT_ALPHA,
            )
    import classifier
    import torchdoct

    report = {
        "versions": {"classifier": classifier.__version__, "torchdoct": torchdoct.__version__},
        "model": name,
        "model_path": mdl.path.name,
        "spec": spec.to_dict(),
        "classes": classes,
        "rule": rule,
        "seed": int(seed),
        "draws": int(draws),
        "trials_per_draw": int(trials),
        "pools": [str(p) for p in pools],
        "pooled_subsets_per_draw": POOLED_PER_DRAW,
        "n_boot": int(n_boot),
        "prior": {
            "text": PRIOR_TEXT,
            "ranges": {k: list(v) for k, v in RANGES.items()},
            "density_per_um3": DENSITY,
            "snr_db": list(SNR_DB),
            "flow_polar_angle_deg": list(POLAR_DEG),
            "as_classifier_prior": prior.to_dict(),
        },
        "simulation": {
            "text": SIM_TEXT,
            "box_sigmas": refsim.BOX_SIGMAS,
            "block_trials": BLOCK_TRIALS,
            "noise": "independent per configuration at the draw's SNR relative to the configuration's "
            "mean intensity (measured reductions share one noisy field: an approximation)",
        },
        "draw_status_counts": status_counts,
        "dropped_nonfinite": dropped,
        "per_draw": per_draw,
        "results": results,
        "targets": _targets(results),
        "seconds": {"simulation_and_features": sim_s, "total": time.perf_counter() - t0, "per_draw": sim_s / draws},
    }
    return report


def _targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Each goal of :data:`TARGETS` beside its measured value."""
    rows = []

    def add(what: str, value: Any, goal: str, met: bool | None) -> None:
        rows.append({"what": what, "value": value, "goal": goal, "met": met})

    def ok(v: Any, test) -> bool | None:
        return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else bool(test(v))

    for pool, key in (("1", "pool_1"), ("25", "pool_25")):
        if pool not in results:
            continue
        m = results[pool]["metrics"]
        t = TARGETS[key]
        bal, cov = m["balanced_accuracy_identifiable"], m["coverage_identifiable"]
        add(
            f"pool {pool}: balanced accuracy (identifiable, decided)",
            bal,
            f">= {t['balanced_accuracy_identifiable']:g}",
            ok(bal, lambda v: v >= t["balanced_accuracy_identifiable"]),
        )
        add(
            f"pool {pool}: coverage (identifiable)",
            cov,
            f">= {t['coverage_identifiable']:g}",
            ok(cov, lambda v: v >= t["coverage_identifiable"]),
        )
        if "ece" in t:
            add(f"pool {pool}: ECE", m["ece"], f"<= {t['ece']:g}", ok(m["ece"], lambda v: v <= t["ece"]))
    if "1" in results:
        goal = TARGETS["flow_recall_every_polar_band"]
        for band, r in results["1"]["flow_bands"]["polar_bands"].items():
            add(
                f"pool 1: flow recall, polar band {band}°",
                r["recall"],
                f">= {goal:g}",
                ok(r["recall"], lambda v: v >= goal),
            )
        mg = results["1"].get("magnitude")
        if mg and mg.get("samples"):
            t = TARGETS["magnitude_pool_1"]
            add(
                "pool 1: median |log10 magnitude error|",
                mg["median_abs_log10_error"],
                f"<= {t['median_abs_log10_error']:g}",
                ok(mg["median_abs_log10_error"], lambda v: v <= t["median_abs_log10_error"]),
            )
            for lvl in ("68", "95"):
                lo, hi = t[f"coverage_{lvl}"]
                v = mg[f"coverage_{lvl}"]
                add(f"pool 1: {lvl} % interval coverage", v, f"{lo:g}-{hi:g}", ok(v, lambda x: lo <= x <= hi))
    return rows


# ------------------------------------------------------------------------------------------------
# report


def _f(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _pm(v: Any, se: Any) -> str:
    if se is None or (isinstance(se, float) and not math.isfinite(se)) or _f(v) == "n/a":
        return _f(v)
    return f"{_f(v)} ± {se:.3f}"


def format_markdown(r: dict[str, Any]) -> str:
    """The report as a short Markdown text."""
    L = [
        f"# `{r['model']}` on independent data",
        "",
        f"{r['draws']} draws × {r['trials_per_draw']} trials, seed {r['seed']}; {r['simulation']['text']}.",
        "",
        f"Prior (not the training prior): {r['prior']['text']}.",
        "",
        "Ground truth per draw: "
        + ", ".join(f"{k} {v}" for k, v in r["draw_status_counts"].items())
        + f"; non-finite feature vectors dropped: {r['dropped_nonfinite']}. Decisions by the model's rule "
        f"(min_probability {r['rule']['min_probability']:g}); ± = bootstrap SE over draws ({r['n_boot']} resamples).",
        "",
        "## Targets",
        "",
        "| goal | measured | target | met |",
        "|---|---:|---:|---|",
    ]
    for t in r["targets"]:
        L.append(
            f"| {t['what']} | {_f(t['value'])} | {t['goal']} | "
            f"{'n/a' if t['met'] is None else ('yes' if t['met'] else '**no**')} |"
        )
    L += [
        "",
        "## By pool",
        "",
        "| pool | samples | coverage | bal. acc. | accuracy | recall diffusion / ballistic / flow | ECE | "
        "indeterminate |",
        "|---:|---:|---:|---:|---:|---|---:|---:|",
    ]
    for pool, res in r["results"].items():
        m, se, rse = res["metrics"], res["standard_errors"], res["recall_se"]
        rec = " / ".join(_pm(m["recall_identifiable"][c], rse.get(c)) for c in _CLASSES)
        L.append(
            f"| {pool} | {res['samples']} | {_pm(m['coverage_identifiable'], se.get('coverage_identifiable'))} | "
            f"{_pm(m['balanced_accuracy_identifiable'], se.get('balanced_accuracy_identifiable'))} | "
            f"{_pm(m['accuracy_identifiable'], se.get('accuracy_identifiable'))} | {rec} | "
            f"{_pm(m['ece'], se.get('ece'))} | {_f(m['indeterminate_fraction'])} |"
        )
    if any("conformal" in res for res in r["results"].values()):
        L += [
            "",
            "## `doct-classify`'s prediction sets (identifiable pixels)",
            "",
            "Per motion: decided as it, decided as another motion (the wrong share), its set misses it, the mean "
            "number of motions in its set; then the first two after rule 1 (a `ballistic` set becomes "
            "`ballistic-or-flow`, as `doct-classify` does for one pixel's time series).",
            "",
            "| pool | α | motion | samples | decided | wrong | set misses | set size | rule 1: decided | "
            "rule 1: wrong |",
            "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for pool, res in r["results"].items():
            c = res.get("conformal")
            if not c:
                continue
            for name, q in c["per_class"].items():
                q1 = c["rule_1"][name]
                L.append(
                    f"| {pool} | {c['alpha']:g} | {name} | {q['samples']} | {_f(q['decided'])} | "
                    f"{_f(q['wrong_share'])} | {_f(q['set_miss_share'])} | {_f(q['mean_set_size'], 2)} | "
                    f"{_f(q1['decided'])} | {_f(q1['wrong_share'])} |"
                )
    L += [
        "",
        "## Flow recall by polar band and speed decade (identifiable flow)",
        "",
        "| pool | band | samples | coverage | flow recall | as ballistic | as diffusion |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for pool, res in r["results"].items():
        fb, fse = res["flow_bands"], res["flow_bands_se"]
        for kind, unit in (("polar_bands", "°"), ("speed_decades", " µm/s")):
            for band, b in fb[kind].items():
                L.append(
                    f"| {pool} | {band}{unit} | {b['samples']} | {_f(b['coverage'])} | "
                    f"{_pm(b['recall'], fse.get(f'{kind}:{band}'))} | {_f(b['as'].get('ballistic'))} | "
                    f"{_f(b['as'].get('diffusion'))} |"
                )
    L += [
        "",
        "## Accuracy against coverage (`--min-probability`)",
        "",
        "| pool | min_probability | coverage | accuracy | bal. accuracy | non-identifiable decided |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for pool, res in r["results"].items():
        for c in res["coverage_curve"]:
            L.append(
                f"| {pool} | {c['min_probability']:g} | {_f(c['coverage_identifiable'])} | "
                f"{_f(c['accuracy_identifiable'])} | {_f(c['balanced_accuracy_identifiable'])} | "
                f"{_f(c['non_identifiable_decided'])} |"
            )
    if any("magnitude" in res for res in r["results"].values()):
        L += [
            "",
            "## Magnitude (identifiable pixels, head of the true class)",
            "",
            "| pool | samples | median abs. log10 error | 68 % coverage | 95 % coverage | median error diffusion / "
            "ballistic / flow |",
            "|---:|---:|---:|---:|---:|---|",
        ]
        for pool, res in r["results"].items():
            mg, mse = res.get("magnitude"), res.get("magnitude_se", {})
            if not mg or not mg.get("samples"):
                continue
            L.append(
                f"| {pool} | {mg['samples']} | {_pm(mg['median_abs_log10_error'], mse.get('median_abs_log10_error'))}"
                f" | {_pm(mg['coverage_68'], mse.get('coverage_68'))} | {_pm(mg['coverage_95'], mse.get('coverage_95'))}"
                f" | "
                + " / ".join(_f(mg["by_class"].get(c, {}).get("median_abs_log10_error")) for c in _CLASSES)
                + " |"
            )
    L += [
        "",
        "## Accuracy against magnitude (pool 1)",
        "",
        "| class | magnitude | samples | truth indeterminate | decided indeterminate | coverage | accuracy |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for row in r["results"][r["pools"][0]]["by_magnitude"]:
        L.append(
            f"| {row['class']} | {row['low']:.2g}–{row['high']:.2g} | {row['samples']} | "
            f"{_f(row['truth_indeterminate'], 2)} | {_f(row['predicted_indeterminate'], 2)} | "
            f"{_f(row['coverage'], 2)} | {_f(row['accuracy_decided'], 2)} |"
        )
    s = r["seconds"]
    L += [
        "",
        f"Time: simulation and features {s['simulation_and_features']:.0f} s ({s['per_draw']:.2f} s per draw), "
        f"{s['total']:.0f} s in all.",
        "",
    ]
    return "\n".join(L)


def _summary(r: dict[str, Any]) -> str:
    lines = [
        f"{r['model']} on independent data ({r['draws']} draws × {r['trials_per_draw']} trials, seed {r['seed']}; "
        + ", ".join(f"{k} {v}" for k, v in r["draw_status_counts"].items())
        + f"; {r['seconds']['total']:.0f} s)"
    ]
    for pool, res in r["results"].items():
        m, se = res["metrics"], res["standard_errors"]
        rec = ", ".join(f"{c} {_f(m['recall_identifiable'][c])}" for c in _CLASSES)
        bands = ", ".join(f"{b} {_f(v['recall'])}" for b, v in res["flow_bands"]["polar_bands"].items())
        lines.append(
            f"  pool {pool}: balanced accuracy {_pm(m['balanced_accuracy_identifiable'], se.get('balanced_accuracy_identifiable'))}"
            f" at coverage {_pm(m['coverage_identifiable'], se.get('coverage_identifiable'))}, ECE "
            f"{_pm(m['ece'], se.get('ece'))}; recall {rec}; flow by polar band {bands}"
        )
        mg = res.get("magnitude")
        if mg and mg.get("samples"):
            lines.append(
                f"          magnitude: median |log10 error| {_f(mg['median_abs_log10_error'])}, 68 % / 95 % "
                f"coverage {_f(mg['coverage_68'])} / {_f(mg['coverage_95'])}"
            )
    missed = [t["what"] for t in r["targets"] if t["met"] is False]
    lines.append(
        f"  targets met: {sum(t['met'] is True for t in r['targets'])} of {len(r['targets'])}"
        + (f"; not met: {'; '.join(missed)}" if missed else "")
    )
    return "\n".join(lines)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_report(report: dict[str, Any], out: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """``<out>/<model>-independent.json`` and ``.md``; existing files are kept unless ``force``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    paths = [out / f"{report['model']}-independent{s}" for s in (".json", ".md")]
    if not force:
        for p in paths:
            if p.exists():
                raise FileExistsError(f"{p} exists; pass --force to overwrite it, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    for p, text in zip(paths, (json.dumps(report, indent=1, default=_json_default), format_markdown(report))):
        tmp = p.with_name(f".{p.name}.tmp")
        tmp.write_text(text + "\n", encoding="utf-8")
        os.replace(tmp, p)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tests.reference.evaluate_models",
        description="Evaluate a signature classifier on data it never saw: the reference "
        "simulator (shared scatterers per model configuration) and an independent "
        "prior. Writes <out>/<model>-independent.json and .md.",
    )
    ap.add_argument("--model", required=True, help="shipped model name, .onnx file, or directory holding one .onnx")
    ap.add_argument("--draws", type=int, default=DEFAULT_DRAWS, help=f"parameter draws (default {DEFAULT_DRAWS})")
    ap.add_argument(
        "--trials", type=int, default=DEFAULT_TRIALS, help=f"independent pixels per draw (default {DEFAULT_TRIALS})"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the draws, the simulation and the pools (default 0)")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--boot", type=int, default=N_BOOT, help=f"bootstrap resamples over draws (default {N_BOOT})")
    ap.add_argument("--force", action="store_true", help="overwrite existing report files")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    try:
        report = evaluate_model(
            args.model,
            draws=args.draws,
            trials=args.trials,
            seed=args.seed,
            n_boot=args.boot,
            progress=not args.no_progress,
        )
        paths = write_report(report, args.out, force=args.force)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(_summary(report))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Labelled feature vectors simulated with :func:`torchdoct.simulate` from a documented prior.

**The prior** (:class:`Prior`, stored in every model):

* motion type: diffusion, random-ballistic motion, mono-directional flow, in equal numbers;
* random-ballistic direction law (``ballistic_directions``, the laws of
  :class:`torchdoct.RandomBallistic`, physics.md §10.2): ``"both"`` (default) gives each ballistic
  draw, with probability 1/2, either the isotropic law (cos of the polar angle ~ U[−1, 1]) or the
  paper's ``"uniform-angles"`` law (polar angle ~ U[0, π], concentrated at the depth axis, ⟨n_z²⟩ = 1/2),
  from a stream of its own (:attr:`Draw.ballistic_directions`); ``"isotropic"`` or
  ``"uniform-angles"`` gives every ballistic draw that law (the prior of the models trained before
  the two laws were mixed: ``"isotropic"``);
* motion magnitude, log-uniform: D ∈ [1e-4, 15] µm²/s, v ∈ [1e-3, 6] µm/s (the shipped models; a
  prior scaled to another system, :func:`classifier.own_system.prior_for_spec`, spans each motion type's
  identifiable range and keeps the scatterers per resolution volume). The paper's ranges
  (§3.2) end at 15 µm²/s and 6 µm/s and start at 0, which a log scale cannot hold; their lower ends
  are taken as 1e-3 µm²/s and 1e-2 µm/s, where the 840-nm LIV of diffusion and random-ballistic
  motion is already a sizeable part of its plateau (physics.md §5.7), and extended a decade below
  as the issue asks;
* flow direction within ``flow_polar_angle_deg`` = [θ₁, θ₂] (default [0, 180°]), azimuth ~ U[0, 360°);
  ``flow_polar_law`` ``"isotropic"`` (default): cos of the polar angle from the depth axis
  ~ U[cos θ₂, cos θ₁] (U[−1, 1] by default); ``"uniform-angle"``: the polar angle ~ U[θ₁, θ₂], which
  gives near-axial flow (the hardest to tell from random-ballistic motion by intensity, physics.md
  §5.3) as many draws per degree as any other direction: within 30° of the axis 1/3 of the flow draws
  over [0, 90°], against 0.13 for the isotropic law;
* density of the moving scatterers ~ U[0.02, 0.1] µm⁻³;
* with probability 1/2 a static fraction ~ U[0, 0.8] of the mean intensity (static scatterers at the
  moving ones' density, reflectivity set to give that fraction);
* ``static_edge_probability`` (default 0; ``doct-train --like`` 0.25): the pixel near the edge of its moving
  region instead, each configuration with its own static share (below, physics.md §14);
* with probability 1/2 additive noise at SNR ~ U[10, 40] dB (torchdoct's noise model: circular
  complex Gaussian, independent per frame and per system, relative to each system's mean intensity).
  ``doct-classify`` decides every pixel down to 30 dB below the image's 99th percentile (its
  background mask), which on a system with 40-50 dB of peak SNR reaches 10-20 dB: the prior covers
  the pixels the model is asked about (with U[20, 40] dB the model was over-confident at 15-20 dB:
  expected calibration error 0.11 there, classifier/README.md);
* ``bulk_residual_step_rad`` (default (0, 0): phase-stable data): for models that read the field's
  phase on bulk-phase-corrected maps (``torchdoct maps --bulk-phase``), what the correction leaves: a
  random walk of the phase over the frames, common to the configurations, with a step SD ~ U[low, high]
  rad per replicate (the correction estimates one phase step per frame pair; docs/physics.md gives
  its residual against SNR);
* the configurations' optics from the spec, an anisotropic lateral PSF included
  (``lateral_resolution_y_um``: a B-scan's x-only lateral reduction keeps the original width along y);
* refractive index, protocol and OCDS analysis from the feature spec (the paper's: n = 1, 32 frames
  at 0.2048 s, OCDS over [0.2048, 1.2288] s on dB intensity, Pearson estimator).

**Sampling** (stratified): a split holds ``draws`` parameter draws × ``replicates`` (static
fraction, SNR) settings × ``trials_per_draw`` trials. Draw ``k`` has motion type ``k mod 3``; the
``i``-th draw of a type takes its log-magnitude at the quantile ``frac(u₀ + i·(√5 − 1)/2)``
(golden-ratio sequence, ``u₀`` from the split's seed), so any prefix of draws covers the magnitude
range evenly; density and flow direction are drawn independently per draw, static fraction and SNR
per replicate, the ballistic direction law (prior ``"both"``) per ballistic draw. Two
:func:`torchdoct.simulate` calls per draw (moving and static scatterers) run its trials (all systems
of a scene see the same scatterers, as one dataset and its resolution reductions do); 64 trials per
draw is one random block of the simulator, and fewer would cost the same. Trials of one (draw,
replicate) group share every parameter: they are the pixels that pooling may average, and draws are
the independent unit of the parameter space.

**Seeds and splits**: everything of draw ``k`` of split ``s`` (train 0, validation 1, test 2) comes
from ``numpy.random.SeedSequence(seed, spawn_key=(s, k))`` (replicate ``r``: ``(s, k, 1 + r)``; the
ballistic direction law: ``(s, k, 2³⁰)``, so choosing it leaves every other parameter of the draw
as it is); the splits never share a draw, and a split's draws do not depend on how many draws are
made.

**Ground-truth identifiability** (physics.md §5.3-5.4, via :mod:`torchdoct.sim.theory`): a draw is
*indeterminate* when its moving scatterers

* do not decorrelate: the intensity correlation coefficient ``ρ_I(T) = (|g1|² + j/N_eff)/(1 + 1/N_eff)``
  at the first-to-last frame delay ``T`` is ``≥ 1 − ε`` at every configuration (``"static"``): LIV and
  OCDS are those of a static sample whatever the motion; or
* decorrelate completely within one frame interval: ``|g1(Δt)|² ≤ ε`` at every configuration
  (``"decorrelated"``): every frame has a new speckle phase pattern, and all that is left of the
  intensity correlation is the incoherent term ``j/N_eff ≤ 1/(1 + N_eff)``, which only measures how
  fast scatterers cross the PSF (a transit time that diffusion and random-ballistic motion both have;
  flow never gets here in the prior, because for flow ``|g1|² = j`` decays by transit alone),

with ``ε = 0.05``, for every spec: for the signature the definition was re-measured (a transit term
that still decays after the field has decorrelated does not tell the motion types apart per pixel:
:func:`identifiability`). The classifier's ``indeterminate`` class is trained on these draws
(:mod:`classifier.rule`).

**Static fraction and noise** are applied per *replicate*: each draw's moving and static fields are
simulated once and combined ``replicates`` times with different static fractions and SNRs
(:func:`simulate_draw`); this multiplies the nuisance variety per (costly) simulation. The static
fraction is the static scatterers' share of the mean intensity, the same at every configuration (static
scatterers mixed among the moving ones). A replicate may instead lie near the **edge of its moving
region** (:attr:`Prior.static_edge_probability`; a vessel wall, a cell's border): static tissue fills the
half-space beyond a plane at distance ``d`` from the pixel, and each configuration's static share is the
part of its own intensity PSF beyond the plane, ``f_c = ½·erfc(d / (√2·σ_c))`` with ``σ_c`` the SD of the
configuration's intensity PSF along the plane's normal (:func:`edge_static_fractions`; physics.md §14). A
reduced configuration reaches further into the static tissue than the original one, so near an edge the
moving field beats against a static field at its Doppler frequency in the reduced configurations only
(measured on the rendered flow phantoms: the intensity correlation of a flow region oscillates at
``2 n v_z / λ`` within one reduced PSF of its edge). The moving scatterers fill the whole space in the
simulation (the half-space restriction enters only through the shares).

**Cache**: a split is stored as ``.npz`` under a key (SHA-256) of the spec, the prior, the seed, the
split, the numbers of draws, replicates and trials, the PSF truncation, the ground-truth definition
and the torchdoct version, and is reused when the key matches.

**Cost** (a 2-core machine, one thread, single-acquisition spec): about 0.53 s per draw, i.e. 8 ms per
simulated trial of the three systems, 1 ms per feature vector after the 8 replicates; the
two-wavelength spec costs about a tenth of that (:attr:`Dataset.meta` records it per split).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .nuisance import combine_fields, edge_static_fractions  # noqa: F401  (public names of this module too)
from .features import FeatureSpec, load_spec

__all__ = [
    "CLASSES",
    "STATUS",
    "combine_fields",
    "edge_static_fractions",
    "SPLITS",
    "Prior",
    "Draw",
    "Dataset",
    "default_cache_dir",
    "draw_parameters",
    "scene_for",
    "simulate_draw",
    "identifiability",
    "transit_decay",
    "make_dataset",
]

#: Motion types, in label order.
CLASSES = ("diffusion", "ballistic", "flow")
#: Split names and their index in the seed's spawn key.
SPLITS = {"train": 0, "validation": 1, "test": 2}
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
#: Direction laws of :class:`torchdoct.RandomBallistic` (physics.md §10.2).
BALLISTIC_LAWS = ("isotropic", "uniform-angles")
#: Values of :attr:`Prior.ballistic_directions`: ``"both"`` mixes the two laws 1:1.
BALLISTIC_PRIORS = ("both", *BALLISTIC_LAWS)
#: Laws of the flow's polar angle within :attr:`Prior.flow_polar_angle_deg` (module docstring).
FLOW_POLAR_LAWS = ("isotropic", "uniform-angle")
#: PSF truncation mode of the training data (:func:`make_dataset`): the smooth taper, which lets
#: scatterers enter the PSF continuously (a hard cut at 1e-2 biases the short-lag correlations of slow
#: motion that the signature models read; the taper at 1e-2 matches the reference simulator at the cost
#: of the hard cut, ``torchdoct bench tradeoffs --part fidelity``).
DEFAULT_TRUNCATION = "taper"
#: Spawn-key element of the stream that picks a ballistic draw's direction law.
_LAW_STREAM = 1 << 30
#: the stream of a replicate's static edge (:attr:`Prior.static_edge_probability`)
_EDGE_STREAM = (1 << 30) + 1


def _range(path: str, value: Any, *, positive: bool = False) -> tuple[float, float]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise TypeError(f"prior.{path} must be a pair [low, high]; got {value!r}")
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo or (positive and lo <= 0):
        raise ValueError(f"prior.{path} must be finite with {'0 < ' if positive else ''}low <= high; got {value!r}")
    return (lo, hi)


@dataclass(frozen=True, kw_only=True)
class Prior:
    """Distribution of the simulated samples (module docstring; units in the field names)."""

    diffusion_um2_per_s: tuple[float, float] = (1e-4, 15.0)
    speed_um_per_s: tuple[float, float] = (1e-3, 6.0)
    #: flow speeds (µm/s) when they differ from the random-ballistic ones; None (the shipped priors): as
    #: ``speed_um_per_s``. A prior scaled to a system (:func:`classifier.own_system.prior_for_spec`) gives
    #: each motion type its own identifiable range: flow decorrelates by transit alone, identifiable faster.
    flow_speed_um_per_s: tuple[float, float] | None = None
    ballistic_directions: str = "both"
    flow_polar_angle_deg: tuple[float, float] = (0.0, 180.0)
    flow_polar_law: str = "isotropic"
    density_per_um3: tuple[float, float] = (0.02, 0.1)
    static_probability: float = 0.5
    static_fraction: tuple[float, float] = (0.0, 0.8)
    noise_probability: float = 0.5
    snr_db: tuple[float, float] = (10.0, 40.0)
    identifiability_epsilon: float = 0.05
    #: residual of a bulk-phase correction (``torchdoct maps --bulk-phase``): a random walk of the
    #: phase over the frames, common to the configurations, with a step SD (rad) ~ U[low, high] per
    #: replicate; (0, 0) = phase-stable data (the default)
    bulk_residual_step_rad: tuple[float, float] = (0.0, 0.0)
    #: probability per replicate that the pixel lies near the edge of its moving region, with static tissue
    #: beyond a plane (module docstring): that replicate's static share is then each configuration's own
    #: (:func:`edge_static_fractions`) instead of a common static fraction; 0 (the shipped priors): never
    static_edge_probability: float = 0.0
    #: the distance from the pixel to that plane, uniform in this range, in units of the SD of the largest
    #: configuration's intensity PSF along the plane's normal (0: on the edge, every share 1/2)
    static_edge_distance: tuple[float, float] = (0.0, 3.0)

    def __post_init__(self) -> None:
        for key, pos in (("diffusion_um2_per_s", True), ("speed_um_per_s", True), ("density_per_um3", True),
                         ("static_fraction", False), ("snr_db", False), ("flow_polar_angle_deg", False),
                         ("bulk_residual_step_rad", False), ("static_edge_distance", False)):
            object.__setattr__(self, key, _range(key, getattr(self, key), positive=pos))
        if self.flow_speed_um_per_s is not None:
            object.__setattr__(self, "flow_speed_um_per_s",
                               _range("flow_speed_um_per_s", self.flow_speed_um_per_s, positive=True))
        if self.static_fraction[0] < 0 or self.static_fraction[1] >= 1:
            raise ValueError(f"prior.static_fraction must lie in [0, 1); got {self.static_fraction}")
        if self.static_edge_distance[0] < 0:
            raise ValueError(f"prior.static_edge_distance must be >= 0 (PSF SDs from the edge); "
                             f"got {list(self.static_edge_distance)}")
        for key in ("static_probability", "noise_probability", "static_edge_probability"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"prior.{key} must be a probability in [0, 1]; got {v!r}")
        if self.flow_polar_angle_deg[0] < 0 or self.flow_polar_angle_deg[1] > 180:
            raise ValueError(f"prior.flow_polar_angle_deg must lie in [0, 180] (degrees from the depth axis); "
                             f"got {list(self.flow_polar_angle_deg)}")
        if not isinstance(self.flow_polar_law, str) or self.flow_polar_law not in FLOW_POLAR_LAWS:
            raise ValueError(f"prior.flow_polar_law must be one of {list(FLOW_POLAR_LAWS)} ('isotropic': cos of the "
                             f"polar angle uniform, 'uniform-angle': the polar angle itself uniform, which puts "
                             f"three times more draws within 30° of the beam axis); got {self.flow_polar_law!r}")
        if not isinstance(self.ballistic_directions, str) or self.ballistic_directions not in BALLISTIC_PRIORS:
            raise ValueError(f"prior.ballistic_directions must be one of {list(BALLISTIC_PRIORS)} ('both': each "
                             f"ballistic draw takes one of torchdoct.RandomBallistic's two direction laws with "
                             f"probability 1/2); got {self.ballistic_directions!r}")
        if self.bulk_residual_step_rad[0] < 0 or self.bulk_residual_step_rad[1] > math.pi:
            raise ValueError(f"prior.bulk_residual_step_rad must lie in [0, π] (rad per frame); "
                             f"got {list(self.bulk_residual_step_rad)}")
        if not 0.0 < float(self.identifiability_epsilon) < 0.5:
            raise ValueError(f"prior.identifiability_epsilon must be in (0, 0.5); got {self.identifiability_epsilon!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-able fields; ``flow_polar_law`` only when it is not ``"isotropic"`` (the law of every
        prior stored before the key existed, so their dicts and cache keys stay what they were)."""
        d = dataclasses.asdict(self)
        if d["flow_polar_law"] == "isotropic":
            del d["flow_polar_law"]
        if tuple(d["bulk_residual_step_rad"]) == (0.0, 0.0):
            del d["bulk_residual_step_rad"]
        if d["flow_speed_um_per_s"] is None:
            del d["flow_speed_um_per_s"]
        if d["static_edge_probability"] == 0:  # priors without edges keep their dicts and cache keys
            del d["static_edge_probability"], d["static_edge_distance"]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def magnitude_range(self, label: int) -> tuple[float, float]:
        """The log-uniform range of the motion magnitude of class ``label`` (:data:`CLASSES`): D (µm²/s)
        for diffusion, the speed (µm/s) for random-ballistic motion and flow."""
        if label == 0:
            return self.diffusion_um2_per_s
        if label == 2 and self.flow_speed_um_per_s is not None:
            return self.flow_speed_um_per_s
        return self.speed_um_per_s

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Prior":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"prior: unknown key(s) {unknown} (allowed: {sorted(known)})")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


@dataclass(frozen=True)
class Draw:
    """One parameter draw: motion type ``label`` and ``magnitude`` (µm²/s for diffusion, µm/s
    otherwise), flow direction (deg), density of the moving scatterers (µm⁻³), the simulator seed,
    per replicate ``(static_fraction, snr_db)`` (``snr_db`` NaN = no noise), and
    ``ballistic_directions``, the direction law of a random-ballistic draw (:data:`BALLISTIC_LAWS`).
    A draw of another motion type carries the prior's law when the prior has one, else
    ``"isotropic"``; it is not used for them."""

    label: int
    magnitude: float
    polar_angle_deg: float
    azimuth_deg: float
    density_per_um3: float
    sim_seed: int
    nuisance: tuple[tuple[float, float], ...] = ()
    ballistic_directions: str = "isotropic"
    #: per replicate, ``None`` or the static edge ``(d, n_x, n_y, n_z)`` of :func:`edge_static_fractions`
    #: (its static shares replace the replicate's static fraction); empty: no edges
    static_edges: tuple[tuple[float, float, float, float] | None, ...] = ()

    def __post_init__(self) -> None:
        if self.ballistic_directions not in BALLISTIC_LAWS:
            raise ValueError(f"Draw.ballistic_directions must be one of {list(BALLISTIC_LAWS)}; "
                             f"got {self.ballistic_directions!r}")

    @property
    def motion(self) -> str:
        return CLASSES[self.label]


def _seed_sequence(seed: int, split: str, *key: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(int(seed), spawn_key=(SPLITS[split], *(int(k) for k in key)))


def draw_parameters(prior: Prior, seed: int, split: str, k: int, replicates: int = 1) -> Draw:
    """Draw ``k`` of ``split`` (module docstring: stratified type and magnitude, the rest i.i.d.).

    Replicate ``r``'s static fraction and SNR come from their own stream, so they do not depend on
    the number of replicates; so does the direction law of a ballistic draw under the prior
    ``"both"`` (``isotropic`` if its uniform is < 1/2, else ``uniform-angles``).
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}; got {split!r}")
    label = k % len(CLASSES)
    i = k // len(CLASSES)
    # offset of the magnitude sequence: one per (seed, split, type), independent of k
    u0 = np.random.default_rng(_seed_sequence(seed, split, 1 << 30, label)).random()
    q = (u0 + i * _GOLDEN) % 1.0
    lo, hi = prior.magnitude_range(label)
    magnitude = float(math.exp(math.log(lo) + q * (math.log(hi) - math.log(lo))))
    ss = _seed_sequence(seed, split, k)
    u = np.random.default_rng(ss).random(4)
    th1, th2 = prior.flow_polar_angle_deg
    if prior.flow_polar_law == "uniform-angle":  # the polar angle itself uniform in [th1, th2]
        polar = th1 + u[0] * (th2 - th1)
    elif (th1, th2) == (0.0, 180.0):
        polar = math.degrees(math.acos(2.0 * u[0] - 1.0))
    else:  # isotropic within [th1, th2]: cos(polar) ~ U[cos th2, cos th1]
        c1, c2 = math.cos(math.radians(th1)), math.cos(math.radians(th2))
        polar = min(max(math.degrees(math.acos(min(max(c2 + u[0] * (c1 - c2), -1.0), 1.0))), th1), th2)
    azimuth = 360.0 * u[1]
    density = prior.density_per_um3[0] + u[2] * (prior.density_per_um3[1] - prior.density_per_um3[0])
    nuisance = []
    edges: list = []
    for r in range(replicates):
        v = np.random.default_rng(_seed_sequence(seed, split, k, 1 + r)).random(4)
        static = 0.0
        if v[0] < prior.static_probability:
            static = prior.static_fraction[0] + v[1] * (prior.static_fraction[1] - prior.static_fraction[0])
        snr = math.nan
        if v[2] < prior.noise_probability:
            snr = prior.snr_db[0] + v[3] * (prior.snr_db[1] - prior.snr_db[0])
        nuisance.append((float(static), float(snr)))
        if prior.static_edge_probability > 0:  # its own stream: the draws above are those of a prior without edges
            w = np.random.default_rng(_seed_sequence(seed, split, k, 1 + r, _EDGE_STREAM)).random(4)
            edge = None
            if w[0] < prior.static_edge_probability:
                cos_t, phi = 2.0 * w[1] - 1.0, 2.0 * math.pi * w[2]
                sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
                lo_d, hi_d = prior.static_edge_distance
                edge = (float(lo_d + w[3] * (hi_d - lo_d)), sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t)
                nuisance[-1] = (0.0, nuisance[-1][1])
            edges.append(edge)
    sim_seed = int(ss.generate_state(2, np.uint64)[1] >> np.uint64(2))
    law = prior.ballistic_directions
    if law == "both":
        law = "isotropic"
        if label == 1 and np.random.default_rng(_seed_sequence(seed, split, k, _LAW_STREAM)).random() >= 0.5:
            law = "uniform-angles"
    return Draw(label=label, magnitude=magnitude, polar_angle_deg=polar, azimuth_deg=azimuth,
                density_per_um3=float(density), sim_seed=sim_seed, nuisance=tuple(nuisance),
                ballistic_directions=law, static_edges=tuple(edges) if any(e is not None for e in edges) else ())


def _lateral_y(c) -> dict[str, float]:
    """``{"lateral_resolution_y_um": Δy}`` for a configuration with an anisotropic lateral PSF (a B-scan's
    x-only lateral reduction keeps the original width along y), else ``{}`` (isotropic)."""
    return {} if c.lateral_resolution_y_um is None else {"lateral_resolution_y_um": c.lateral_resolution_y_um}


def scene_for(spec: FeatureSpec, draw: Draw, prior: Prior, population: str = "moving"):
    """The noise-free :class:`torchdoct.Scene` of one draw's ``"moving"`` or ``"static"`` scatterers.

    Both have the draw's density and reflectivity 1; the spec's systems, protocol and analysis.
    """
    import torchdoct as td

    systems = tuple(td.OCTSystem(name=c.name, wavelength_um=c.wavelength_um,
                                 lateral_resolution_um=c.lateral_resolution_um,
                                 axial_resolution_um=c.axial_resolution_um,
                                 refractive_index=spec.refractive_index, **_lateral_y(c))
                    for c in spec.configurations)
    if population == "static":
        motion: tuple = ()
    elif population != "moving":
        raise ValueError(f"population must be 'moving' or 'static'; got {population!r}")
    elif draw.label == 0:
        motion = (td.Diffusion(diffusion_um2_per_s=draw.magnitude),)
    elif draw.label == 1:
        motion = (td.RandomBallistic(speed_um_per_s=draw.magnitude, directions=draw.ballistic_directions),)
    else:
        motion = (td.Flow(speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg,
                          azimuth_deg=draw.azimuth_deg),)
    return td.Scene(name=f"{spec.name}-{draw.motion}-{population}", systems=systems,
                    protocol=td.Protocol(n_frames=spec.n_frames, frame_interval_s=spec.frame_interval_s),
                    populations=(td.Population(name=population, density_per_um3=draw.density_per_um3,
                                               motion=motion),),
                    analysis=td.Analysis(metrics=("liv", "ocds"), ocds_delay_range_s=spec.ocds_delay_range_s,
                                         ocds_scale=spec.ocds_scale, ocds_estimator=spec.ocds_estimator))


def simulate_draw(spec: FeatureSpec, draw: Draw, prior: Prior, *, trials: int,
                  truncation_tolerance: float, bulk_phase: bool = False, truncation: str = DEFAULT_TRUNCATION):
    """Feature vectors ``[R, trials, F]`` (float32, spec order) and the empty-volume mask ``[R, trials]``.

    For a signature spec (:attr:`FeatureSpec.is_signature`) the features come from
    :func:`torchdoct.sim.signature.pixel_features` (the extractor of ``torchdoct maps --signature``), and a
    third array ``[R, trials, 2·C]`` holds LIV and OCDS of the same pixels at the same
    configurations (for the LIV/OCDS baseline on the same test pixels). ``bulk_phase``: multiply
    every frame by a uniform random phase (one per trial and frame, common to the configurations,
    as bulk motion of a sample is to one dataset and its resolution reductions).

    Two :func:`torchdoct.simulate` calls per draw: the moving scatterers ``E_m`` and, independently,
    static scatterers ``E_s`` at the same density (reflectivity 1). Replicate ``r`` with static
    fraction ``f`` and SNR is ``E = E_m + a·E_s + n`` with ``a = √(f/(1−f))`` (a static population of
    reflectivity ``a``, exactly: the field is linear in the reflectivity; ``f`` is the static share of
    the mean intensity) and ``n`` circular complex Gaussian noise, independent per frame and system,
    of power ``⟨I⟩/10^(SNR/10)`` with ``⟨I⟩ = (1 + a²)·ρ·π^{3/2}·s_x²·s_z`` the mean noise-free
    intensity (physics.md §5.2, §8; the model of :class:`torchdoct.Noise`).
    """
    import torch
    import torchdoct as td
    from torchdoct.conventions import mean_intensity
    from torchdoct.sim.metrics import compute_metrics

    # one thread per draw: draws run side by side (make_dataset)
    moving = td.simulate(scene_for(spec, draw, prior, "moving"), trials=trials, seed=draw.sim_seed,
                         dtype="float32", truncation_tolerance=truncation_tolerance, truncation=truncation,
                         threads=1, progress=False)
    nuisance = draw.nuisance or ((0.0, math.nan),)
    edges = draw.static_edges or (None,) * len(nuisance)
    shares = [f if e is None else edge_static_fractions(spec.configurations, e) for (f, _), e in zip(nuisance, edges)]
    static = None
    if any(f > 0 for f, _ in nuisance) or any(e is not None for e in edges):
        static = td.simulate(scene_for(spec, draw, prior, "static"), trials=trials, seed=draw.sim_seed ^ 0x5A5A5A5A,
                             dtype="float32", truncation_tolerance=truncation_tolerance, truncation=truncation,
                             threads=1, progress=False).signals
    mean_i = [mean_intensity(draw.density_per_um3, c.lateral_resolution_um, c.axial_resolution_um, **_lateral_y(c))
              for c in spec.configurations]
    gen = torch.Generator().manual_seed(draw.sim_seed ^ 0x3C3C3C3C)
    signals = torch.cat([combine_fields(moving.signals, static, f, snr, mean_i, gen)
                         for f, (_, snr) in zip(shares, nuisance)])
    lo, hi = prior.bulk_residual_step_rad
    if hi > 0:  # the residual of a bulk-phase correction: a random walk per trial, common to the configurations
        rgen = torch.Generator().manual_seed(draw.sim_seed ^ 0x1E1E1E1E)
        n_rep, n_t = len(nuisance), signals.shape[-1]
        step_sd = lo + torch.rand(n_rep, 1, 1, generator=rgen, dtype=torch.float64) * (hi - lo)
        steps = torch.randn(n_rep, trials, n_t - 1, generator=rgen, dtype=torch.float64) * step_sd
        walk = torch.cat([torch.zeros(n_rep, trials, 1, dtype=torch.float64), steps.cumsum(-1)], dim=-1)
        walk = walk.reshape(n_rep * trials, 1, n_t)
        signals = signals * torch.polar(torch.ones_like(walk), walk).to(signals.dtype)
    if bulk_phase:  # one uniform random phase per trial and frame, common to all configurations
        bgen = torch.Generator().manual_seed(draw.sim_seed ^ 0x0F0F0F0F)
        phi = torch.rand(signals.shape[0], 1, signals.shape[-1], generator=bgen, dtype=torch.float64) * (2 * math.pi)
        signals = signals * torch.polar(torch.ones_like(phi), phi).to(signals.dtype)
    met = compute_metrics(signals, moving.frame_times_s, moving.scene.analysis)
    zero = met["zero_intensity"].any(-1).numpy().reshape(len(nuisance), trials)
    if spec.is_signature:
        from torchdoct.sim.signature import pixel_features  # the function of the maps' slab loop too

        _, sig = pixel_features(signals, moving.frame_times_s, spec)  # [N, systems, F]
        x = sig.reshape(sig.shape[0], -1).numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
        ref = torch.stack([met[m][:, s] for s in range(len(spec.configurations)) for m in ("liv", "ocds")], dim=-1)
        return x, zero, ref.numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
    cols = [met[m][:, s] for s in range(len(spec.configurations)) for m in spec.metrics]
    x = torch.stack(cols, dim=-1).numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
    return x, zero


def identifiability(spec: FeatureSpec, draw: Draw, prior: Prior) -> tuple[str, np.ndarray, np.ndarray]:
    """Ground-truth identifiability of a draw (module docstring), with its two criteria per configuration.

    Returns ``(status, g1sq_first [C], rho_last [C])``: status ``"identifiable"``, ``"static"`` or
    ``"decorrelated"``; ``|g1(Δt)|²`` and ``ρ_I(T)`` of the moving scatterers. Formulas: physics.md
    §5.3 (g1), §5.4 (j, N_eff, ``ρ_I = (|g1|² + j/N_eff)/(1 + 1/N_eff)``), via :mod:`torchdoct.sim.theory`.

    The same definition holds for signature specs: a transit term ``j/N_eff`` that still decays over
    the acquisition after the field has decorrelated (:func:`transit_decay`) was measured not to tell
    diffusion from random-ballistic motion per pixel (``python -m classifier.ablation --indeterminate``,
    ``classifier/README.md``), so "decorrelated" stays as wide as it is.
    """
    status, first_a, last_a, _ = _criteria(spec, draw, prior)
    return status, first_a, last_a


def transit_decay(spec: FeatureSpec, draw: Draw, prior: Prior) -> np.ndarray:
    """``ρ_I(Δt) − ρ_I(T)`` per configuration [C]: how much of the moving scatterers' intensity correlation
    still decays between the first and the last frame delay (physics.md §5.4; after the field has
    decorrelated, ``|g1|² ≈ 0``, this is the incoherent transit term ``j/N_eff`` alone)."""
    return _criteria(spec, draw, prior)[3]


def _criteria(spec: FeatureSpec, draw: Draw, prior: Prior) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """Status, ``|g1(Δt)|²``, ``ρ_I(T)`` and ``ρ_I(Δt) − ρ_I(T)`` per configuration (:func:`identifiability`)."""
    from torchdoct.sim import theory
    from torchdoct.conventions import n_eff

    taus = np.array([spec.frame_interval_s, (spec.n_frames - 1) * spec.frame_interval_s])
    first, last, drop = [], [], []
    for c in spec.configurations:
        res = dict(lateral_resolution_um=c.lateral_resolution_um, axial_resolution_um=c.axial_resolution_um,
                   **_lateral_y(c))
        if draw.label == 0:
            g1 = theory.g1_diffusion(taus, diffusion_um2_per_s=draw.magnitude, wavelength_um=c.wavelength_um,
                                     refractive_index=spec.refractive_index, **res)
            j = theory.j_diffusion(taus, diffusion_um2_per_s=draw.magnitude, **res)
        elif draw.label == 1:
            g1 = theory.g1_ballistic(taus, speed_um_per_s=draw.magnitude, wavelength_um=c.wavelength_um,
                                     refractive_index=spec.refractive_index,
                                     directions=draw.ballistic_directions, **res)
            j = theory.j_ballistic(taus, speed_um_per_s=draw.magnitude, directions=draw.ballistic_directions,
                                   **res)
        else:
            g1 = theory.g1_flow(taus, speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg,
                                azimuth_deg=draw.azimuth_deg, wavelength_um=c.wavelength_um,
                                refractive_index=spec.refractive_index, **res)
            j = theory.j_flow(taus, speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg,
                              azimuth_deg=draw.azimuth_deg, **res)
        rho = theory.intensity_correlation_coefficient(
            g1, j, n_eff(draw.density_per_um3, c.lateral_resolution_um, c.axial_resolution_um, **_lateral_y(c)))
        first.append(float(np.abs(g1[0]) ** 2))
        last.append(float(rho[1]))
        drop.append(float(rho[0] - rho[1]))
    first_a, last_a = np.array(first), np.array(last)
    eps = prior.identifiability_epsilon
    if np.all(last_a >= 1.0 - eps):
        status = "static"
    elif np.all(first_a <= eps):
        status = "decorrelated"
    else:
        status = "identifiable"
    return status, first_a, last_a, np.array(drop)


#: Version of the ground-truth definition (part of the cache key).
_IDENTIFIABILITY_VERSION = "static: rho_I(T) >= 1-eps; decorrelated: |g1(dt)|^2 <= eps; all configurations"
#: Identifiability status codes stored in a dataset.
STATUS = ("identifiable", "static", "decorrelated")


_ARRAYS = ("x", "y", "draw", "group", "status", "magnitude", "density", "static_fraction", "snr_db",
           "polar_angle_deg")


@dataclass
class Dataset:
    """One split: features ``x [N, F]`` (float32), motion labels ``y [N]`` and per-sample truth.

    ``draw [N]`` is the draw index and ``group [N]`` the (draw, replicate) index: trials of a group
    share every parameter and are the units that may be pooled. ``status [N]`` indexes
    :data:`STATUS`; ``magnitude``, ``density`` (moving scatterers), ``static_fraction``, ``snr_db``
    (NaN = no noise) and ``polar_angle_deg`` (flow only, from the depth axis; NaN otherwise) describe
    the sample. Samples with an empty resolution volume at some frame
    (NaN features) are dropped and counted in ``meta["dropped_empty"]``.
    """

    x: np.ndarray
    y: np.ndarray
    draw: np.ndarray
    group: np.ndarray
    status: np.ndarray
    magnitude: np.ndarray
    density: np.ndarray
    static_fraction: np.ndarray
    snr_db: np.ndarray
    #: polar angle of a flow sample's velocity from the depth (beam) axis, degrees; NaN for other
    #: motions (and ``None`` given: unknown, NaN)
    polar_angle_deg: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    #: LIV and OCDS of the same samples at the spec's configurations (signature specs only), ``[N, 2·C]``.
    x_ref: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.polar_angle_deg is None:
            self.polar_angle_deg = np.full(self.y.shape, math.nan)

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def identifiable(self) -> np.ndarray:
        return self.status == 0

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in _ARRAYS}

    def save(self, path: str | os.PathLike) -> None:
        with open(path, "wb") as fh:
            extra = {} if self.x_ref is None else {"x_ref": self.x_ref}
            np.savez(fh, meta_json=np.asarray(json.dumps(self.meta)), **self.arrays(), **extra)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Dataset":
        with np.load(path, allow_pickle=False) as z:
            # splits stored before the polar angle was recorded have none: NaN (unknown)
            arrays = {k: z[k] if k in z.files else np.full(z["y"].shape, math.nan) for k in _ARRAYS}
            meta = json.loads(str(z["meta_json"]))
            x_ref = z["x_ref"] if "x_ref" in z.files else None
        return cls(**arrays, meta=meta, x_ref=x_ref)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/torchdoct/classifier`` (or ``~/.cache/...``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchdoct" / "classifier"


def dataset_key(spec: FeatureSpec, prior: Prior, seed: int, split: str, draws: int, trials_per_draw: int,
                replicates: int, truncation_tolerance: float, bulk_phase: bool = False,
                truncation: str = "hard") -> tuple[str, dict[str, Any]]:
    """Cache key (hex SHA-256) and the JSON-able description it hashes."""
    import torchdoct

    desc = {"spec": spec.to_dict(), "prior": prior.to_dict(), "seed": int(seed), "split": split,
            "draws": int(draws), "trials_per_draw": int(trials_per_draw), "replicates": int(replicates),
            "truncation_tolerance": float(truncation_tolerance), "torchdoct_version": torchdoct.__version__,
            "identifiability": _IDENTIFIABILITY_VERSION, "format": 3}
    if spec.is_signature:
        desc["signature_extractor"] = _signature_version()
    if bulk_phase:
        desc["bulk_phase"] = "uniform random phase per trial and frame"
    if truncation != "hard":  # (a hard cut: the only mode of the splits stored before there were two)
        desc["truncation"] = truncation
    blob = json.dumps(desc, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest(), desc


def _signature_version() -> str:
    """Hash of the extractor's source: a change of the signature invalidates cached signature splits."""
    import torchdoct.sim.signature as sig

    return hashlib.sha256(Path(sig.__file__).read_bytes()).hexdigest()[:16]


def _positive_int(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive integer; got {v!r}")
    return v


def _check_resources(spec: FeatureSpec, split: str, draws: int, trials_per_draw: int, replicates: int,
                     path: Path | None) -> None:
    """The split's arrays fit in memory twice (the pieces of every draw and their concatenation) and once in
    the cache's folder: :func:`torchdoct.resources.check_resources`, before any draw is simulated."""
    from torchdoct.resources import check_resources

    n = draws * replicates * trials_per_draw
    per_sample = 4 * spec.n_features + 8 * (len(_ARRAYS) - 1) + (8 * len(spec.configurations) if spec.is_signature
                                                                   else 0)
    check_resources(  # on disk: the finished draws until the split is written, then the split
        f"the {split} split of {spec.name!r}", 2 * n * per_sample,
        "lower the draws (doct-train --draws-train, --draws-validation, --draws-test), --trials-per-draw or "
        "--replicates",
        detail=f"{n} samples = {draws} draws × {replicates} replicates × {trials_per_draw} trials, "
               f"{per_sample} bytes each, twice while gathered",
        out_path=None if path is None else path.parent, out_bytes=2 * n * per_sample,
        out_fix="free disk space there, give another --cache directory, or --no-cache")


def make_dataset(spec: FeatureSpec | str, prior: Prior | None = None, *, seed: int = 0, split: str = "train",
                 draws: int = 300, trials_per_draw: int = 64, replicates: int = 8,
                 truncation_tolerance: float = 1e-2, cache_dir: str | os.PathLike | None = None,
                 use_cache: bool = True, progress: bool = False, bulk_phase: bool = False,
                 truncation: str = DEFAULT_TRUNCATION) -> Dataset:
    """Simulate (or load from the cache) one split of labelled feature vectors.

    ``draws`` parameter draws × ``replicates`` (static fraction, SNR) settings × ``trials_per_draw``
    trials (:func:`simulate_draw`). ``truncation_tolerance`` is the simulator's PSF truncation
    (relative amplitude); 1e-2 bounds the relative mean-square field error at 3.6e-4
    (:func:`torchdoct.conventions.truncation_error_bound`) and halves the cost against 1e-3.
    ``bulk_phase``: a random bulk phase per frame (:func:`simulate_draw`; a separate cache entry).
    ``truncation``: ``"hard"`` (the amplitude cut to 0 below the tolerance) or ``"taper"`` (a smooth
    window that reaches 0 at the tolerance, so scatterers enter the PSF continuously;
    :func:`torchdoct.conventions.taper_window`): the hard cut at 1e-2 biases the short-lag correlations
    of slow motion, which the signature models read (``torchdoct bench tradeoffs --part fidelity``).
    """
    spec = load_spec(spec)
    prior = prior or Prior()
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}; got {split!r}")
    _positive_int("draws", draws)
    _positive_int("trials_per_draw", trials_per_draw)
    _positive_int("replicates", replicates)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer; got {seed!r}")
    key, desc = dataset_key(spec, prior, seed, split, draws, trials_per_draw, replicates, truncation_tolerance,
                            bulk_phase, truncation)
    path = None
    if use_cache:
        cdir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        path = cdir / f"{spec.name}-{split}{'-bulk' if bulk_phase else ''}-{key[:16]}.npz"
        if path.exists():
            ds = Dataset.load(path)
            if ds.meta.get("key") == key:
                ds.meta["from_cache"] = True
                return ds
    _check_resources(spec, split, draws, trials_per_draw, replicates, path)
    cols: dict[str, list] = {k: [] for k in _ARRAYS}
    refs: list[np.ndarray] = []
    dropped = 0
    status_counts = {s: 0 for s in STATUS}
    t0 = time.perf_counter()
    from torchdoct.study.cells import CellCache, CellJob, run_cached, run_cells
    from torchdoct.threads import resolve_threads

    def one(k: int):
        d = draw_parameters(prior, seed, split, k, replicates)
        return simulate_draw(spec, d, prior, trials=trials_per_draw, truncation_tolerance=truncation_tolerance,
                             bulk_phase=bulk_phase, truncation=truncation)

    # draws side by side on the usable cores, in threads (the cell runner, torchdoct.study.cells: one
    # torch thread each; every draw has its own seeds, so the dataset does not depend on the number of
    # threads); each finished draw is kept beside the split's cache file until the split is written, so
    # an interrupted run resumes from the draws it finished
    draw_cache = CellCache(None if path is None else path.with_name(f".{path.stem}.draws"))
    jobs = [CellJob(key=f"draw-{k}-{hashlib.sha256(f'{key}:{k}'.encode()).hexdigest()[:24]}", payload=k)
            for k in range(draws)]

    def execute(payloads: list, done) -> None:
        run_cells(one, payloads, done=done, workers=resolve_threads(None), one_torch_thread=True)

    results, _ = run_cached(
        jobs, cache=draw_cache, execute=execute, encode=_encode_draw, decode=_decode_draw, progress=progress,
        desc=f"simulate {spec.name}/{split}", unit="draw", what="draws of this split", final_note=False)
    for k, res in enumerate(results):  # gathered in draw order
        d = draw_parameters(prior, seed, split, k, replicates)
        x, zero = res[0], res[1]
        status, _, _ = identifiability(spec, d, prior)
        status_counts[status] += 1
        edges = d.static_edges or (None,) * len(d.nuisance)
        for r, ((f, snr), e) in enumerate(zip(d.nuisance, edges)):
            if e is not None:  # a static edge: the mean of the configurations' static shares
                f = float(np.mean(edge_static_fractions(spec.configurations, e)))
            keep = ~zero[r] & np.all(np.isfinite(x[r]), axis=1)
            dropped += int((~keep).sum())
            n = int(keep.sum())
            cols["x"].append(x[r][keep])
            if len(res) == 3:
                refs.append(res[2][r][keep])
            cols["y"].append(np.full(n, d.label, np.int64))
            cols["draw"].append(np.full(n, k, np.int64))
            cols["group"].append(np.full(n, k * replicates + r, np.int64))
            cols["status"].append(np.full(n, STATUS.index(status), np.int64))
            cols["magnitude"].append(np.full(n, d.magnitude))
            cols["density"].append(np.full(n, d.density_per_um3))
            cols["static_fraction"].append(np.full(n, f))
            cols["snr_db"].append(np.full(n, snr))
            cols["polar_angle_deg"].append(np.full(n, d.polar_angle_deg if d.label == 2 else math.nan))
    elapsed = time.perf_counter() - t0
    arrays = {k: np.concatenate(v) for k, v in cols.items()}
    arrays["x"] = arrays["x"].astype(np.float32).reshape(-1, spec.n_features)
    meta = {"key": key, **desc, "feature_names": list(spec.feature_names), "classes": list(CLASSES),
            "status_names": list(STATUS), "draw_status_counts": status_counts, "dropped_empty": dropped,
            "elapsed_s": elapsed, "seconds_per_draw": elapsed / draws,
            "seconds_per_trial": elapsed / (draws * trials_per_draw), "from_cache": False}
    x_ref = np.concatenate(refs).astype(np.float32) if refs else None
    ds = Dataset(**arrays, meta=meta, x_ref=x_ref)
    if path is not None:
        from torchdoct.files import atomic_write

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, ds.save)
        if draw_cache.dir is not None and draw_cache.dir.is_dir():  # the split holds them now
            for k in range(draws):
                draw_cache.path(jobs[k].key).unlink(missing_ok=True)
            try:
                draw_cache.dir.rmdir()
            except OSError:
                pass  # another run's draws are there too
    return ds


def _encode_draw(job, res) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A finished draw's cache entry: its features, empty-volume mask and (signature specs) LIV/OCDS."""
    return {f"a{i}": a for i, a in enumerate(res)}, {"arrays": len(res)}


def _decode_draw(job, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> tuple[np.ndarray, ...]:
    return tuple(arrays[f"a{i}"] for i in range(int(meta["arrays"])))

"""The prior of the classifier's training data and its parameter draws: what a simulated sample may be, and
draw ``k`` of a split (:func:`draw_parameters`).

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
  motion is already a sizeable part of its plateau (physics.md §5.7), and extended a decade below them;
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
  expected calibration error 0.11 there, research/classifier-history.md);
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
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "CLASSES",
    "SPLITS",
    "BALLISTIC_LAWS",
    "BALLISTIC_PRIORS",
    "FLOW_POLAR_LAWS",
    "Prior",
    "Draw",
    "draw_parameters",
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
    #: (:func:`classifier.nuisance.edge_static_fractions`) instead of a common static fraction; 0 (the shipped priors): never
    static_edge_probability: float = 0.0
    #: the distance from the pixel to that plane, uniform in this range, in units of the SD of the largest
    #: configuration's intensity PSF along the plane's normal (0: on the edge, every share 1/2)
    static_edge_distance: tuple[float, float] = (0.0, 3.0)

    def __post_init__(self) -> None:
        for key, pos in (
            ("diffusion_um2_per_s", True),
            ("speed_um_per_s", True),
            ("density_per_um3", True),
            ("static_fraction", False),
            ("snr_db", False),
            ("flow_polar_angle_deg", False),
            ("bulk_residual_step_rad", False),
            ("static_edge_distance", False),
        ):
            object.__setattr__(self, key, _range(key, getattr(self, key), positive=pos))
        if self.flow_speed_um_per_s is not None:
            object.__setattr__(
                self, "flow_speed_um_per_s", _range("flow_speed_um_per_s", self.flow_speed_um_per_s, positive=True)
            )
        if self.static_fraction[0] < 0 or self.static_fraction[1] >= 1:
            raise ValueError(f"prior.static_fraction must lie in [0, 1); got {self.static_fraction}")
        if self.static_edge_distance[0] < 0:
            raise ValueError(
                f"prior.static_edge_distance must be >= 0 (PSF SDs from the edge); "
                f"got {list(self.static_edge_distance)}"
            )
        for key in ("static_probability", "noise_probability", "static_edge_probability"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"prior.{key} must be a probability in [0, 1]; got {v!r}")
        if self.flow_polar_angle_deg[0] < 0 or self.flow_polar_angle_deg[1] > 180:
            raise ValueError(
                f"prior.flow_polar_angle_deg must lie in [0, 180] (degrees from the depth axis); "
                f"got {list(self.flow_polar_angle_deg)}"
            )
        if not isinstance(self.flow_polar_law, str) or self.flow_polar_law not in FLOW_POLAR_LAWS:
            raise ValueError(
                f"prior.flow_polar_law must be one of {list(FLOW_POLAR_LAWS)} ('isotropic': cos of the "
                f"polar angle uniform, 'uniform-angle': the polar angle itself uniform, which puts "
                f"three times more draws within 30° of the beam axis); got {self.flow_polar_law!r}"
            )
        if not isinstance(self.ballistic_directions, str) or self.ballistic_directions not in BALLISTIC_PRIORS:
            raise ValueError(
                f"prior.ballistic_directions must be one of {list(BALLISTIC_PRIORS)} ('both': each "
                f"ballistic draw takes one of torchdoct.RandomBallistic's two direction laws with "
                f"probability 1/2); got {self.ballistic_directions!r}"
            )
        if self.bulk_residual_step_rad[0] < 0 or self.bulk_residual_step_rad[1] > math.pi:
            raise ValueError(
                f"prior.bulk_residual_step_rad must lie in [0, π] (rad per frame); "
                f"got {list(self.bulk_residual_step_rad)}"
            )
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
    def from_dict(cls, data: dict[str, Any]) -> Prior:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"prior: unknown key(s) {unknown} (allowed: {sorted(known)})")
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)  # each field's type is checked by __post_init__


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
    #: per replicate, ``None`` or the static edge ``(d, n_x, n_y, n_z)`` of :func:`classifier.nuisance.edge_static_fractions`
    #: (its static shares replace the replicate's static fraction); empty: no edges
    static_edges: tuple[tuple[float, float, float, float] | None, ...] = ()

    def __post_init__(self) -> None:
        if self.ballistic_directions not in BALLISTIC_LAWS:
            raise ValueError(
                f"Draw.ballistic_directions must be one of {list(BALLISTIC_LAWS)}; got {self.ballistic_directions!r}"
            )

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
    return Draw(
        label=label,
        magnitude=magnitude,
        polar_angle_deg=polar,
        azimuth_deg=azimuth,
        density_per_um3=float(density),
        sim_seed=sim_seed,
        nuisance=tuple(nuisance),
        ballistic_directions=law,
        static_edges=tuple(edges) if any(e is not None for e in edges) else (),
    )

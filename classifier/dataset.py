"""Labelled feature vectors simulated with :func:`torchdoct.simulate` from a documented prior.

**The prior** (:class:`Prior`, stored in every model):

* motion type: diffusion, random-ballistic motion (isotropic directions), mono-directional flow,
  in equal numbers;
* motion magnitude, log-uniform: D ∈ [1e-4, 15] µm²/s, v ∈ [1e-3, 6] µm/s. The paper's ranges
  (§3.2) end at 15 µm²/s and 6 µm/s and start at 0, which a log scale cannot hold; their lower ends
  are taken as 1e-3 µm²/s and 1e-2 µm/s, where the 840-nm LIV of diffusion and random-ballistic
  motion is already a sizeable part of its plateau (physics.md §5.7), and extended a decade below
  as the issue asks;
* flow direction isotropic (cos of the polar angle from the depth axis ~ U[−1, 1], azimuth ~ U[0, 360°));
* total scatterer density ~ U[0.02, 0.1] µm⁻³;
* with probability 1/2 a static fraction ~ U[0, 0.8] of the density (same reflectivity);
* with probability 1/2 additive noise at SNR ~ U[20, 40] dB (torchdoct's noise model: circular
  complex Gaussian, independent per frame and per system, relative to each system's mean intensity);
* refractive index, protocol and OCDS analysis from the feature spec (the paper's: n = 1, 32 frames
  at 0.2048 s, OCDS over [0.2048, 1.2288] s on dB intensity, Pearson estimator).

**Sampling** (stratified): a split holds ``draws`` parameter draws × ``trials_per_draw`` trials.
Draw ``k`` has motion type ``k mod 3``; the ``i``-th draw of a type takes its log-magnitude at the
quantile ``frac(u₀ + i·(√5 − 1)/2)`` (golden-ratio sequence, ``u₀`` from the split's seed), so any
prefix of draws covers the magnitude range evenly; the other parameters are drawn independently per
draw. One :func:`torchdoct.simulate` call per draw runs its trials (all systems of the scene see the
same scatterers, as one dataset and its resolution reductions do); 64 trials per draw is one random
block of the simulator, and fewer would cost the same. Trials of one draw share their parameters, so
statistics are computed with draws as the independent unit where it matters.

**Seeds and splits**: everything of draw ``k`` of split ``s`` (train 0, validation 1, test 2) comes
from ``numpy.random.SeedSequence(seed, spawn_key=(s, k))``; the splits never share a draw, and a
split's draws do not depend on how many draws are made.

**Ground-truth identifiability** (physics.md §5.3-5.4, via :mod:`torchdoct.theory`): with the
intensity correlation coefficient of the moving scatterers ``ρ_I(τ) = (|g1|² + j/N_eff)/(1 + 1/N_eff)``
at each configuration of the spec, a draw is *indeterminate* when its motion

* does not decorrelate: ``ρ_I(T) ≥ 1 − ε`` at every configuration, ``T`` the first-to-last frame
  delay (``"static"``), or
* decorrelates completely within one frame interval: ``ρ_I(Δt) ≤ ε`` at every configuration
  (``"decorrelated"``),

with ``ε = 0.05``. In both regimes LIV and OCDS are those of a static sample or of independent
speckle whatever the motion type, so no classifier can tell the types apart.

**Cache**: a split is stored as ``.npz`` under a key (SHA-256) of the spec, the prior, the seed, the
split, the number of draws and trials, and the torchdoct version, and is reused when the key matches.
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

from .features import FeatureSpec, load_spec

__all__ = [
    "CLASSES",
    "SPLITS",
    "Prior",
    "Draw",
    "Dataset",
    "default_cache_dir",
    "draw_parameters",
    "scene_for",
    "simulate_draw",
    "identifiability",
    "make_dataset",
]

#: Motion types, in label order.
CLASSES = ("diffusion", "ballistic", "flow")
#: Split names and their index in the seed's spawn key.
SPLITS = {"train": 0, "validation": 1, "test": 2}
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


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
    ballistic_directions: str = "isotropic"
    density_per_um3: tuple[float, float] = (0.02, 0.1)
    static_probability: float = 0.5
    static_fraction: tuple[float, float] = (0.0, 0.8)
    noise_probability: float = 0.5
    snr_db: tuple[float, float] = (20.0, 40.0)
    identifiability_epsilon: float = 0.05

    def __post_init__(self) -> None:
        for key, pos in (("diffusion_um2_per_s", True), ("speed_um_per_s", True), ("density_per_um3", True),
                         ("static_fraction", False), ("snr_db", False)):
            object.__setattr__(self, key, _range(key, getattr(self, key), positive=pos))
        if self.static_fraction[0] < 0 or self.static_fraction[1] >= 1:
            raise ValueError(f"prior.static_fraction must lie in [0, 1); got {self.static_fraction}")
        for key in ("static_probability", "noise_probability"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"prior.{key} must be a probability in [0, 1]; got {v!r}")
        if self.ballistic_directions not in ("isotropic", "uniform-angles"):
            raise ValueError(f"prior.ballistic_directions must be 'isotropic' or 'uniform-angles'; "
                             f"got {self.ballistic_directions!r}")
        if not 0.0 < float(self.identifiability_epsilon) < 0.5:
            raise ValueError(f"prior.identifiability_epsilon must be in (0, 0.5); got {self.identifiability_epsilon!r}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Prior":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"prior: unknown key(s) {unknown} (allowed: {sorted(known)})")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


@dataclass(frozen=True)
class Draw:
    """One parameter draw: motion type and magnitude (µm²/s for diffusion, µm/s otherwise), flow
    direction (deg), total density (µm⁻³), static fraction, SNR (dB; NaN = no noise)."""

    label: int
    magnitude: float
    polar_angle_deg: float
    azimuth_deg: float
    density_per_um3: float
    static_fraction: float
    snr_db: float
    sim_seed: int

    @property
    def motion(self) -> str:
        return CLASSES[self.label]


def _seed_sequence(seed: int, split: str, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(int(seed), spawn_key=(SPLITS[split], int(index)))


def draw_parameters(prior: Prior, seed: int, split: str, k: int) -> Draw:
    """Draw ``k`` of ``split`` (module docstring: stratified type and magnitude, the rest i.i.d.)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}; got {split!r}")
    label = k % len(CLASSES)
    i = k // len(CLASSES)
    # offset of the magnitude sequence: one per (seed, split, type), independent of k
    u0 = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(SPLITS[split], 1 << 30, label))).random()
    q = (u0 + i * _GOLDEN) % 1.0
    lo, hi = prior.diffusion_um2_per_s if label == 0 else prior.speed_um_per_s
    magnitude = float(math.exp(math.log(lo) + q * (math.log(hi) - math.log(lo))))
    ss = _seed_sequence(seed, split, k)
    rng = np.random.default_rng(ss)
    u = rng.random(8)
    polar = math.degrees(math.acos(2.0 * u[0] - 1.0))
    azimuth = 360.0 * u[1]
    density = prior.density_per_um3[0] + u[2] * (prior.density_per_um3[1] - prior.density_per_um3[0])
    static = 0.0
    if u[3] < prior.static_probability:
        static = prior.static_fraction[0] + u[4] * (prior.static_fraction[1] - prior.static_fraction[0])
    snr = math.nan
    if u[5] < prior.noise_probability:
        snr = prior.snr_db[0] + u[6] * (prior.snr_db[1] - prior.snr_db[0])
    sim_seed = int(ss.generate_state(2, np.uint64)[1] >> np.uint64(2))
    return Draw(label=label, magnitude=magnitude, polar_angle_deg=polar, azimuth_deg=azimuth,
                density_per_um3=float(density), static_fraction=float(static), snr_db=float(snr),
                sim_seed=sim_seed)


def scene_for(spec: FeatureSpec, draw: Draw, prior: Prior):
    """The :class:`torchdoct.Scene` of one draw: the spec's systems, protocol and analysis."""
    import torchdoct as td

    systems = tuple(td.OCTSystem(name=c.name, wavelength_um=c.wavelength_um,
                                 lateral_resolution_um=c.lateral_resolution_um,
                                 axial_resolution_um=c.axial_resolution_um,
                                 refractive_index=spec.refractive_index) for c in spec.configurations)
    if draw.label == 0:
        motion = td.Diffusion(diffusion_um2_per_s=draw.magnitude)
    elif draw.label == 1:
        motion = td.RandomBallistic(speed_um_per_s=draw.magnitude, directions=prior.ballistic_directions)
    else:
        motion = td.Flow(speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg,
                         azimuth_deg=draw.azimuth_deg)
    moving = draw.density_per_um3 * (1.0 - draw.static_fraction)
    pops = [td.Population(name="moving", density_per_um3=moving, motion=(motion,))]
    if draw.static_fraction > 0:
        pops.append(td.Population(name="static", density_per_um3=draw.density_per_um3 * draw.static_fraction))
    noise = None if math.isnan(draw.snr_db) else td.Noise(snr_db=draw.snr_db)
    return td.Scene(name=f"{spec.name}-{draw.motion}", systems=systems,
                    protocol=td.Protocol(n_frames=spec.n_frames, frame_interval_s=spec.frame_interval_s),
                    populations=tuple(pops), noise=noise,
                    analysis=td.Analysis(metrics=("liv", "ocds"), ocds_delay_range_s=spec.ocds_delay_range_s,
                                         ocds_scale=spec.ocds_scale, ocds_estimator=spec.ocds_estimator))


def simulate_draw(spec: FeatureSpec, draw: Draw, prior: Prior, *, trials: int,
                  truncation_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Feature vectors ``[trials, F]`` (float32, spec order) and the empty-volume mask ``[trials]``."""
    import torchdoct as td

    scene = scene_for(spec, draw, prior)
    res = td.simulate(scene, trials=trials, seed=draw.sim_seed, dtype="float32",
                      truncation_tolerance=truncation_tolerance, progress=False)
    met = res.metrics()
    cols = [met[m][:, s] for s in range(len(spec.configurations)) for m in spec.metrics]
    import torch

    x = torch.stack(cols, dim=-1).cpu().numpy().astype(np.float32)
    zero = met["zero_intensity"].any(-1).cpu().numpy()
    return x, zero


def identifiability(spec: FeatureSpec, draw: Draw, prior: Prior) -> tuple[str, np.ndarray, np.ndarray]:
    """Ground-truth identifiability of a draw (module docstring) and ``ρ_I(Δt)``, ``ρ_I(T)`` per configuration.

    Returns ``(status, rho_first [C], rho_last [C])`` with status ``"identifiable"``, ``"static"`` or
    ``"decorrelated"``. Formulas: physics.md §5.3 (g1), §5.4 (j, N_eff, ρ_I); N_eff of the moving
    scatterers (:func:`torchdoct.conventions.n_eff`).
    """
    from torchdoct import theory
    from torchdoct.conventions import n_eff

    taus = np.array([spec.frame_interval_s, (spec.n_frames - 1) * spec.frame_interval_s])
    moving = draw.density_per_um3 * (1.0 - draw.static_fraction)
    first, last = [], []
    for c in spec.configurations:
        res = dict(lateral_resolution_um=c.lateral_resolution_um, axial_resolution_um=c.axial_resolution_um)
        if draw.label == 0:
            g1 = theory.g1_diffusion(taus, diffusion_um2_per_s=draw.magnitude, wavelength_um=c.wavelength_um,
                                     refractive_index=spec.refractive_index, **res)
            j = theory.j_diffusion(taus, diffusion_um2_per_s=draw.magnitude, **res)
        elif draw.label == 1:
            g1 = theory.g1_ballistic(taus, speed_um_per_s=draw.magnitude, wavelength_um=c.wavelength_um,
                                     refractive_index=spec.refractive_index,
                                     directions=prior.ballistic_directions, **res)
            j = theory.j_ballistic(taus, speed_um_per_s=draw.magnitude, directions=prior.ballistic_directions,
                                   **res)
        else:
            g1 = theory.g1_flow(taus, speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg,
                                wavelength_um=c.wavelength_um, refractive_index=spec.refractive_index, **res)
            j = theory.j_flow(taus, speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg, **res)
        rho = theory.intensity_correlation_coefficient(
            g1, j, n_eff(moving, c.lateral_resolution_um, c.axial_resolution_um))
        first.append(float(rho[0]))
        last.append(float(rho[1]))
    first_a, last_a = np.array(first), np.array(last)
    eps = prior.identifiability_epsilon
    if np.all(last_a >= 1.0 - eps):
        status = "static"
    elif np.all(first_a <= eps):
        status = "decorrelated"
    else:
        status = "identifiable"
    return status, first_a, last_a


#: Identifiability status codes stored in a dataset.
STATUS = ("identifiable", "static", "decorrelated")


@dataclass
class Dataset:
    """One split: features ``x [N, F]`` (float32), motion labels ``y [N]`` and per-sample truth.

    ``draw [N]`` is the draw index (trials of one draw share their parameters); ``status [N]``
    indexes :data:`STATUS`; ``magnitude``, ``density``, ``static_fraction``, ``snr_db`` (NaN = no
    noise) describe the draw. Samples with an empty resolution volume at some frame (NaN features)
    are dropped and counted in ``meta["dropped_empty"]``.
    """

    x: np.ndarray
    y: np.ndarray
    draw: np.ndarray
    status: np.ndarray
    magnitude: np.ndarray
    density: np.ndarray
    static_fraction: np.ndarray
    snr_db: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def identifiable(self) -> np.ndarray:
        return self.status == 0

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("x", "y", "draw", "status", "magnitude", "density",
                                              "static_fraction", "snr_db")}

    def save(self, path: str | os.PathLike) -> None:
        with open(path, "wb") as fh:
            np.savez(fh, meta_json=np.asarray(json.dumps(self.meta)), **self.arrays())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Dataset":
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("x", "y", "draw", "status", "magnitude", "density", "static_fraction",
                                        "snr_db")}
            meta = json.loads(str(z["meta_json"]))
        return cls(**arrays, meta=meta)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/torchdoct/classifier`` (or ``~/.cache/...``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchdoct" / "classifier"


def dataset_key(spec: FeatureSpec, prior: Prior, seed: int, split: str, draws: int, trials_per_draw: int,
                truncation_tolerance: float) -> tuple[str, dict[str, Any]]:
    """Cache key (hex SHA-256) and the JSON-able description it hashes."""
    import torchdoct

    desc = {"spec": spec.to_dict(), "prior": prior.to_dict(), "seed": int(seed), "split": split,
            "draws": int(draws), "trials_per_draw": int(trials_per_draw),
            "truncation_tolerance": float(truncation_tolerance), "torchdoct_version": torchdoct.__version__,
            "format": 1}
    blob = json.dumps(desc, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest(), desc


def make_dataset(spec: FeatureSpec | str, prior: Prior | None = None, *, seed: int = 0, split: str = "train",
                 draws: int = 300, trials_per_draw: int = 64, truncation_tolerance: float = 1e-2,
                 cache_dir: str | os.PathLike | None = None, use_cache: bool = True,
                 progress: bool = False) -> Dataset:
    """Simulate (or load from the cache) one split of labelled feature vectors.

    ``truncation_tolerance`` is the simulator's PSF truncation (relative amplitude); 1e-2 bounds the
    relative mean-square field error at 3.6e-4 (:func:`torchdoct.conventions.truncation_error_bound`)
    and halves the cost against the default 1e-3.
    """
    spec = load_spec(spec)
    prior = prior or Prior()
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}; got {split!r}")
    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ValueError(f"draws must be a positive integer; got {draws!r}")
    if isinstance(trials_per_draw, bool) or not isinstance(trials_per_draw, int) or trials_per_draw < 1:
        raise ValueError(f"trials_per_draw must be a positive integer; got {trials_per_draw!r}")
    key, desc = dataset_key(spec, prior, seed, split, draws, trials_per_draw, truncation_tolerance)
    path = None
    if use_cache:
        cdir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        path = cdir / f"{spec.name}-{split}-{key[:16]}.npz"
        if path.exists():
            ds = Dataset.load(path)
            if ds.meta.get("key") == key:
                ds.meta["from_cache"] = True
                return ds
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=draws, unit="draw", desc=f"simulate {spec.name}/{split}")
    cols: dict[str, list] = {k: [] for k in ("x", "y", "draw", "status", "magnitude", "density",
                                             "static_fraction", "snr_db")}
    dropped = 0
    status_counts = {s: 0 for s in STATUS}
    t0 = time.perf_counter()
    for k in range(draws):
        d = draw_parameters(prior, seed, split, k)
        x, zero = simulate_draw(spec, d, prior, trials=trials_per_draw, truncation_tolerance=truncation_tolerance)
        status, _, _ = identifiability(spec, d, prior)
        status_counts[status] += 1
        keep = ~zero & np.all(np.isfinite(x), axis=1)
        dropped += int((~keep).sum())
        n = int(keep.sum())
        cols["x"].append(x[keep])
        cols["y"].append(np.full(n, d.label, np.int64))
        cols["draw"].append(np.full(n, k, np.int64))
        cols["status"].append(np.full(n, STATUS.index(status), np.int64))
        cols["magnitude"].append(np.full(n, d.magnitude))
        cols["density"].append(np.full(n, d.density_per_um3))
        cols["static_fraction"].append(np.full(n, d.static_fraction))
        cols["snr_db"].append(np.full(n, d.snr_db))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - t0
    arrays = {k: np.concatenate(v) for k, v in cols.items()}
    arrays["x"] = arrays["x"].astype(np.float32).reshape(-1, spec.n_features)
    meta = {"key": key, **desc, "feature_names": list(spec.feature_names), "classes": list(CLASSES),
            "status_names": list(STATUS), "draw_status_counts": status_counts, "dropped_empty": dropped,
            "elapsed_s": elapsed, "seconds_per_sample": elapsed / (draws * trials_per_draw),
            "from_cache": False}
    ds = Dataset(**arrays, meta=meta)
    if path is not None:
        from torchdoct._files import atomic_write

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, ds.save)
    return ds

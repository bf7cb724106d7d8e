"""Scenes: validated, frozen descriptions of systems, protocol, scatterers, noise and analysis.

A scene is what a TOML scene file holds (schema in the README); :func:`load_scene` reads one,
:func:`scene_from_dict` builds one from plain Python data, and :meth:`Scene.to_dict` writes it back.
Every value is checked on construction; a bad value raises :class:`SceneError` (a ``ValueError``)
or ``TypeError`` naming the key path (``population[1].motion[0].speed_um_per_s``), the value and
the fix.

Units follow :mod:`torchdoct.conventions`: lengths µm, times s, wavelength in vacuum µm, lateral
resolution = 1/e² full width of the intensity PSF, axial resolution = intensity FWHM.

Kept whole (over 800 lines): the scene's frozen dataclasses share one set of checkers (``_number``,
``_integer``, ``_string``, ``_check_keys``) that name every key path the same way; splitting the classes
from their checkers would make every error message a cross-module contract.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ..conventions import delay_groups, delay_range_tolerance_s, uniform_frame_interval_s

__all__ = [
    "SceneError",
    "OCTSystem",
    "Protocol",
    "Diffusion",
    "RandomBallistic",
    "Flow",
    "Motion",
    "Population",
    "Noise",
    "Analysis",
    "SimulationSettings",
    "Scene",
    "METRICS",
    "load_scene",
    "scene_from_dict",
]

METRICS = ("liv", "ocds", "complex_variance", "autocorrelation")
#: Upper limits that keep a scene physically meaningful and the plan finite.
MAX_FRAMES = 100_000
#: Largest motion parameters (far beyond biology: 1 cm/s, 1 mm²/s); they keep plans finite.
MAX_SPEED_UM_PER_S = 1e4
MAX_DIFFUSION_UM2_PER_S = 1e6
#: Longest protocol (s): one day.
MAX_DURATION_S = 86_400.0
#: Most tables of one kind in a scene or phantom file, checked before any is read (a 10 MB file of
#: 100,000 systems would otherwise run for minutes): systems, populations (and phantom regions and
#: backgrounds), motions per population. The paper's study uses 4 systems; more: split the scene.
MAX_TABLES = {"system": 64, "population": 1024, "region": 1024, "background": 1024, "motion": 16}


class SceneError(ValueError):
    """A scene value is invalid; the message names the key, the value and the fix."""


# ----------------------------------------------------------------------------------------------
# value checks


def _fail(path: str, msg: str, fix: str | None = None) -> None:
    text = f"{path}: {msg}"
    if fix:
        text += f" (fix: {fix})"
    raise SceneError(text)


def _number(
    path: str,
    value: Any,
    *,
    positive: bool = False,
    nonneg: bool = False,
    lo: float | None = None,
    hi: float | None = None,
    unit: str = "",
) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(
            f"{path} must be a number{(' in ' + unit) if unit else ''}; got {type(value).__name__} {value!r}"
        )
    u = f" {unit}" if unit else ""
    try:
        v = float(value)
    except OverflowError:  # an integer of hundreds of digits
        _fail(
            path,
            f"must be a finite number{u}; got an integer of {len(str(abs(value)))} digits, beyond any float",
            "give a finite value",
        )
    if not math.isfinite(v):
        _fail(path, f"must be a finite number{u}; got {value!r}", "give a finite value")
    if positive and v <= 0:
        _fail(path, f"must be > 0{u}; got {value!r}", "give a positive value")
    if nonneg and v < 0:
        _fail(path, f"must be >= 0{u}; got {value!r}", "give a non-negative value")
    if lo is not None and v < lo:
        _fail(path, f"must be >= {lo}{u}; got {value!r}")
    if hi is not None and v > hi:
        _fail(path, f"must be <= {hi}{u}; got {value!r}")
    return v


def _integer(path: str, value: Any, *, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise TypeError(f"{path} must be an integer; got {type(value).__name__} {value!r}")
    if lo is not None and value < lo:
        _fail(path, f"must be >= {lo}; got {value}")
    if hi is not None and value > hi:
        _fail(path, f"must be <= {hi}; got {value}")
    return int(value)


def _string(path: str, value: Any, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{path} must be a string; got {type(value).__name__} {value!r}")
    if choices is not None and value not in choices:
        _fail(path, f"must be one of {', '.join(map(repr, choices))}; got {value!r}")
    return value


# ----------------------------------------------------------------------------------------------
# dataclasses


@dataclass(frozen=True, kw_only=True)
class OCTSystem:
    """One OCT system: probe wavelength and resolutions (see :mod:`torchdoct.conventions`).

    ``wavelength_um``: vacuum centre wavelength (µm). ``lateral_resolution_um``: 1/e² full width of
    the intensity PSF (µm), along x, and along y too unless ``lateral_resolution_y_um`` is given.
    ``lateral_resolution_y_um``: 1/e² full width along y (µm; default ``None`` = the same as x): B-scan
    data after a computational lateral reduction along x only keep the system's width along y.
    ``axial_resolution_um``: FWHM of the intensity PSF in the medium (µm).
    ``refractive_index``: phase index ``n`` of the medium (round-trip phase ``2·k·n·z``; 1.0 matches
    the reference paper).
    """

    name: str
    wavelength_um: float
    lateral_resolution_um: float
    axial_resolution_um: float
    refractive_index: float = 1.0
    lateral_resolution_y_um: float | None = None

    def __post_init__(self) -> None:
        p = f"system[{self.name!r}]"
        _string(f"{p}.name", self.name)
        if not self.name:
            _fail(f"{p}.name", "must not be empty", "give each system a short unique name")
        _number(f"{p}.wavelength_um", self.wavelength_um, positive=True, unit="µm")
        if not (0.1 <= self.wavelength_um <= 20.0):
            _fail(
                f"{p}.wavelength_um",
                f"{self.wavelength_um} µm is outside 0.1-20 µm",
                "wavelengths are in micrometres: 840 nm is 0.84",
            )
        _number(f"{p}.lateral_resolution_um", self.lateral_resolution_um, positive=True, unit="µm")
        _number(f"{p}.axial_resolution_um", self.axial_resolution_um, positive=True, unit="µm")
        if self.lateral_resolution_y_um is not None:
            _number(f"{p}.lateral_resolution_y_um", self.lateral_resolution_y_um, positive=True, unit="µm")
        for key in ("lateral_resolution_um", "lateral_resolution_y_um", "axial_resolution_um"):
            if getattr(self, key) is not None and getattr(self, key) > 1e4:
                _fail(f"{p}.{key}", f"{getattr(self, key)} µm is larger than 1 cm", "resolutions are in micrometres")
        from ..conventions import REFRACTIVE_INDEX_RANGE

        _number(
            f"{p}.refractive_index", self.refractive_index, lo=REFRACTIVE_INDEX_RANGE[0], hi=REFRACTIVE_INDEX_RANGE[1]
        )

    @property
    def lateral_widths_um(self) -> tuple[float, float]:
        """1/e² full widths (x, y) of the intensity PSF (µm); y is ``lateral_resolution_um`` unless
        ``lateral_resolution_y_um`` is given."""
        y = self.lateral_resolution_um if self.lateral_resolution_y_um is None else self.lateral_resolution_y_um
        return (self.lateral_resolution_um, y)

    @property
    def is_isotropic(self) -> bool:
        """Whether the lateral PSF has one width (x and y)."""
        return self.lateral_resolution_y_um is None or self.lateral_resolution_y_um == self.lateral_resolution_um


@dataclass(frozen=True, kw_only=True)
class Protocol:
    """Frame timing: ``n_frames`` frames ``frame_interval_s`` apart, or explicit ``frame_times_s`` (s)."""

    n_frames: int
    frame_interval_s: float | None = None
    frame_times_s: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        _integer("protocol.n_frames", self.n_frames, lo=2, hi=MAX_FRAMES)
        if (self.frame_interval_s is None) == (self.frame_times_s is None):
            _fail(
                "protocol", "give exactly one of frame_interval_s and frame_times_s", "e.g. frame_interval_s = 0.2048"
            )
        if self.frame_interval_s is not None:
            _number("protocol.frame_interval_s", self.frame_interval_s, positive=True, unit="s")
            if self.frame_interval_s * (self.n_frames - 1) > MAX_DURATION_S:
                _fail(
                    "protocol.frame_interval_s",
                    f"{self.frame_interval_s} s × {self.n_frames - 1} intervals exceeds {MAX_DURATION_S:g} s",
                    "times are in seconds: 204.8 ms is 0.2048",
                )
        else:
            times = self.frame_times_s
            if not isinstance(times, (list, tuple)):
                raise TypeError(f"protocol.frame_times_s must be a list of times in s; got {times!r}")
            times = tuple(_number(f"protocol.frame_times_s[{i}]", t, unit="s") for i, t in enumerate(times))
            object.__setattr__(self, "frame_times_s", times)
            if len(times) != self.n_frames:
                _fail(
                    "protocol.frame_times_s",
                    f"has {len(times)} entries but n_frames = {self.n_frames}",
                    "make n_frames equal to the number of frame times",
                )
            if any(b <= a for a, b in zip(times, times[1:])):
                _fail("protocol.frame_times_s", "must be strictly increasing")
            if times[-1] - times[0] > MAX_DURATION_S:
                _fail(
                    "protocol.frame_times_s",
                    f"span {times[-1] - times[0]:g} s exceeds {MAX_DURATION_S:g} s",
                    "times are in seconds",
                )

    @property
    def times_s(self) -> tuple[float, ...]:
        """Frame times relative to the first frame (s)."""
        if self.frame_times_s is not None:
            t0 = self.frame_times_s[0]
            return tuple(t - t0 for t in self.frame_times_s)
        assert self.frame_interval_s is not None  # __post_init__: exactly one of the two is given
        return tuple(i * self.frame_interval_s for i in range(self.n_frames))

    @property
    def duration_s(self) -> float:
        """First-to-last frame separation (s)."""
        return self.times_s[-1]

    @property
    def max_interval_s(self) -> float:
        t = self.times_s
        return max(b - a for a, b in zip(t, t[1:]))

    @property
    def is_uniform(self) -> bool:
        return uniform_frame_interval_s(self.times_s) is not None


@dataclass(frozen=True, kw_only=True)
class Diffusion:
    """Brownian motion: each coordinate moves by ``N(0, 2·D·Δt)`` over Δt (paper Eq. 9)."""

    diffusion_um2_per_s: float
    kind: Literal["diffusion"] = "diffusion"

    def validate(self, path: str) -> None:
        _number(
            f"{path}.diffusion_um2_per_s",
            self.diffusion_um2_per_s,
            nonneg=True,
            hi=MAX_DIFFUSION_UM2_PER_S,
            unit="µm²/s",
        )

    @property
    def is_zero(self) -> bool:
        return self.diffusion_um2_per_s == 0.0


@dataclass(frozen=True, kw_only=True)
class RandomBallistic:
    """Random ballistic motion: every scatterer moves at ``speed_um_per_s`` along its own direction.

    ``directions = "isotropic"``: uniform on the sphere (cos of the polar angle ~ U[-1, 1]).
    ``directions = "uniform-angles"``: polar angle ~ U[0, π] as in the paper's text and the COG
    reference code (not isotropic: ⟨n_z²⟩ = 1/2, physics.md §10.2). Azimuth ~ U[0, 2π) in both.
    """

    speed_um_per_s: float
    directions: Literal["isotropic", "uniform-angles"] = "isotropic"
    kind: Literal["ballistic"] = "ballistic"

    def validate(self, path: str) -> None:
        _number(f"{path}.speed_um_per_s", self.speed_um_per_s, nonneg=True, hi=MAX_SPEED_UM_PER_S, unit="µm/s")
        _string(f"{path}.directions", self.directions, ("isotropic", "uniform-angles"))

    @property
    def is_zero(self) -> bool:
        return self.speed_um_per_s == 0.0


@dataclass(frozen=True, kw_only=True)
class Flow:
    """Mono-directional flow: all scatterers move with one velocity.

    ``polar_angle_deg`` is measured from the depth axis (+z, deeper), ``azimuth_deg`` from +x.
    """

    speed_um_per_s: float
    polar_angle_deg: float = 45.0
    azimuth_deg: float = 0.0
    kind: Literal["flow"] = "flow"

    def validate(self, path: str) -> None:
        _number(f"{path}.speed_um_per_s", self.speed_um_per_s, nonneg=True, hi=MAX_SPEED_UM_PER_S, unit="µm/s")
        _number(f"{path}.polar_angle_deg", self.polar_angle_deg, lo=0.0, hi=180.0, unit="deg")
        _number(f"{path}.azimuth_deg", self.azimuth_deg, lo=-360.0, hi=360.0, unit="deg")

    @property
    def is_zero(self) -> bool:
        return self.speed_um_per_s == 0.0

    @property
    def velocity_um_per_s(self) -> tuple[float, float, float]:
        th = math.radians(self.polar_angle_deg)
        ph = math.radians(self.azimuth_deg)
        v = self.speed_um_per_s
        return (v * math.sin(th) * math.cos(ph), v * math.sin(th) * math.sin(ph), v * math.cos(th))


Motion = Diffusion | RandomBallistic | Flow
_MOTION_TYPES = {"diffusion": Diffusion, "ballistic": RandomBallistic, "flow": Flow}


@dataclass(frozen=True, kw_only=True)
class Population:
    """Scatterers of one kind: Poisson density (µm⁻³), field reflectivity ``b`` and motions.

    The displacements of all ``motion`` entries add up; no entry means static scatterers.
    """

    density_per_um3: float
    reflectivity: float = 1.0
    motion: tuple[Motion, ...] = ()
    name: str = ""

    def __post_init__(self) -> None:
        p = f"population[{self.name!r}]" if self.name else "population"
        _number(f"{p}.density_per_um3", self.density_per_um3, positive=True, unit="µm⁻³")
        if self.density_per_um3 > 1e3:
            _fail(
                f"{p}.density_per_um3",
                f"{self.density_per_um3} per µm³ is beyond 1000",
                "density is per cubic micrometre: 0.055 means 5.5e7 per mm³",
            )
        _number(f"{p}.reflectivity", self.reflectivity, positive=True)
        if self.reflectivity > 1e6:
            _fail(
                f"{p}.reflectivity",
                f"{self.reflectivity} is beyond 1e6",
                "reflectivity is a relative field amplitude (1 = the reference scatterer); use relative values",
            )
        object.__setattr__(self, "motion", tuple(self.motion))
        for i, m in enumerate(self.motion):
            if not isinstance(m, (Diffusion, RandomBallistic, Flow)):
                raise TypeError(f"{p}.motion[{i}] must be Diffusion, RandomBallistic or Flow; got {m!r}")
            m.validate(f"{p}.motion[{i}]")

    @property
    def active_motion(self) -> tuple[Motion, ...]:
        """Motion entries with a non-zero parameter (zero-speed entries do nothing)."""
        return tuple(m for m in self.motion if not m.is_zero)

    @property
    def diffusion_um2_per_s(self) -> float:
        return sum(m.diffusion_um2_per_s for m in self.active_motion if isinstance(m, Diffusion))

    @property
    def flow_velocity_um_per_s(self) -> tuple[float, float, float]:
        v = [0.0, 0.0, 0.0]
        for m in self.active_motion:
            if isinstance(m, Flow):
                for a, c in enumerate(m.velocity_um_per_s):
                    v[a] += c
        return (v[0], v[1], v[2])

    @property
    def ballistic(self) -> tuple[RandomBallistic, ...]:
        return tuple(m for m in self.active_motion if isinstance(m, RandomBallistic))

    @property
    def max_speed_um_per_s(self) -> float:
        """Upper bound on the drift speed |v_flow + Σ v_b n_b| (µm/s)."""
        vf = math.sqrt(sum(c * c for c in self.flow_velocity_um_per_s))
        return vf + sum(m.speed_um_per_s for m in self.ballistic)

    @property
    def motion_class(self) -> str:
        """``static``, ``drift`` (ballistic and/or flow only) or ``diffusive``."""
        if not self.active_motion:
            return "static"
        if self.diffusion_um2_per_s > 0:
            return "diffusive"
        return "drift"


@dataclass(frozen=True, kw_only=True)
class Noise:
    """Additive circular complex Gaussian noise, independent per frame, at ``snr_db`` (dB).

    The noise power per system is ``⟨I⟩ / 10^(snr_db/10)`` with ``⟨I⟩`` the mean noise-free intensity
    of the scene for that system (physics.md §5.2, summed over populations).
    """

    snr_db: float

    def __post_init__(self) -> None:
        _number("noise.snr_db", self.snr_db, lo=-60.0, hi=200.0, unit="dB")


@dataclass(frozen=True, kw_only=True)
class Analysis:
    """Which metrics to compute and how (physics.md §1, §2.4).

    ``ocds_delay_range_s``: delay range [s] of the OCDS slope fit (default [0.2048, 1.2288]).
    ``ocds_scale``: ``"db"`` (default) or ``"linear"`` intensity. ``ocds_estimator``: ``"pearson"``
    (per-lag Pearson correlation, default) or ``"biased"`` (lagged products over N / zero-lag).
    """

    metrics: tuple[str, ...] = ("liv", "ocds")
    ocds_delay_range_s: tuple[float, float] = (0.2048, 1.2288)
    ocds_scale: Literal["db", "linear"] = "db"
    ocds_estimator: Literal["pearson", "biased"] = "pearson"

    def __post_init__(self) -> None:
        if isinstance(self.metrics, str) or not isinstance(self.metrics, (list, tuple)):
            raise TypeError(f"analysis.metrics must be a list of metric names; got {self.metrics!r}")
        object.__setattr__(self, "metrics", tuple(self.metrics))
        for i, m in enumerate(self.metrics):
            _string(f"analysis.metrics[{i}]", m, METRICS)
        if len(set(self.metrics)) != len(self.metrics):
            _fail("analysis.metrics", f"lists a metric twice: {list(self.metrics)}")
        r = self.ocds_delay_range_s
        if not isinstance(r, (list, tuple)) or len(r) != 2:
            raise TypeError(f"analysis.ocds_delay_range_s must be [min_s, max_s]; got {r!r}")
        r = (
            _number("analysis.ocds_delay_range_s[0]", r[0], positive=True, unit="s"),
            _number("analysis.ocds_delay_range_s[1]", r[1], positive=True, unit="s"),
        )
        if r[1] <= r[0]:
            _fail("analysis.ocds_delay_range_s", f"max must exceed min; got {list(r)}")
        object.__setattr__(self, "ocds_delay_range_s", r)
        _string("analysis.ocds_scale", self.ocds_scale, ("db", "linear"))
        _string("analysis.ocds_estimator", self.ocds_estimator, ("pearson", "biased"))


@dataclass(frozen=True, kw_only=True)
class SimulationSettings:
    """Defaults of a run: ``trials``, ``seed``, PSF ``truncation_tolerance``, ``truncation`` and ``dtype``.

    ``truncation_tolerance`` is the amplitude (relative to the PSF peak) below which scatterers are
    left out; it bounds the relative mean-square field error (see
    :func:`torchdoct.conventions.truncation_error_bound`). ``truncation``: ``"taper"`` (default: the
    amplitude is multiplied by a smooth window that reaches 0 at the tolerance, so moving scatterers
    enter the PSF continuously; :func:`torchdoct.conventions.taper_window`, physics.md §5.9) or
    ``"hard"`` (the amplitude is cut to 0 below the tolerance, so they enter with a step, which at
    1e-2 biases the short-lag correlations of slow motion: ``rho_lin_1`` of flow 0.5 µm/s along the
    beam at axial=14, 0.984 against 0.998 for the reference simulator). The default is the cheapest
    setting whose model features show no bias at the resolution of the fidelity benchmark
    (``torchdoct bench tradeoffs --part fidelity``, README "Fidelity on what the models read"), at
    the cost of the hard cut.
    """

    trials: int = 500
    seed: int = 0
    truncation_tolerance: float = 1e-2
    dtype: Literal["float32", "float64"] = "float32"
    truncation: Literal["hard", "taper"] = "taper"

    def __post_init__(self) -> None:
        _integer("simulation.trials", self.trials, lo=1, hi=10**9)
        _integer("simulation.seed", self.seed, lo=0, hi=2**63 - 1)
        _number("simulation.truncation_tolerance", self.truncation_tolerance, lo=1e-12, hi=0.5)
        _string("simulation.dtype", self.dtype, ("float32", "float64"))
        _string("simulation.truncation", self.truncation, ("hard", "taper"))


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A sample (scatterer populations) seen by one or more OCT systems over one protocol."""

    systems: tuple[OCTSystem, ...]
    protocol: Protocol
    populations: tuple[Population, ...]
    noise: Noise | None = None
    analysis: Analysis = field(default_factory=Analysis)
    simulation: SimulationSettings = field(default_factory=SimulationSettings)
    name: str = ""
    description: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "systems", tuple(self.systems))
        object.__setattr__(self, "populations", tuple(self.populations))
        if not self.systems:
            _fail("system", "a scene needs at least one [[system]]", "add a [[system]] table")
        if not self.populations:
            _fail("population", "a scene needs at least one [[population]]", "add a [[population]] table")
        names = [s.name for s in self.systems]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            _fail("system.name", f"duplicate system names {dup}", "give each system a unique name")
        lo, hi = self.analysis.ocds_delay_range_s
        if "ocds" in self.analysis.metrics:
            delays = self.delays_s
            tol = delay_range_tolerance_s(self.protocol.times_s, (lo, hi))
            inside = [d for d in delays if lo - tol <= d <= hi + tol]
            if len(inside) >= 2:
                try:
                    check_ocds_pairs(
                        self.protocol.times_s,
                        (lo, hi),
                        "analysis.ocds_delay_range_s",
                        "narrow ocds_delay_range_s or raise protocol.n_frames",
                    )
                except ValueError as err:
                    raise SceneError(str(err)) from None
            if len(inside) < 2:
                _fail(
                    "analysis.ocds_delay_range_s",
                    f"[{lo}, {hi}] s holds {len(inside)} frame delay(s) of the protocol "
                    f"(delays {delays[0]:.6g} ... {delays[-1]:.6g} s); OCDS needs at least 2",
                    "widen the range or lengthen the protocol",
                )

    @property
    def delays_s(self) -> tuple[float, ...]:
        """Distinct frame-pair delays of the protocol (s), :func:`torchdoct.conventions.delay_groups`."""
        return tuple(d for d, _ in delay_groups(self.protocol.times_s))

    def replace(self, **changes: Any) -> Scene:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the scene-file schema (round-trips through :func:`scene_from_dict`)."""
        out: dict[str, Any] = {}
        if self.name:
            out["name"] = self.name
        if self.description:
            out["description"] = self.description
        out["system"] = [
            {k: v for k, v in dataclasses.asdict(s).items() if not (k == "lateral_resolution_y_um" and v is None)}
            for s in self.systems
        ]
        pr: dict[str, Any] = {"n_frames": self.protocol.n_frames}
        if self.protocol.frame_interval_s is not None:
            pr["frame_interval_s"] = self.protocol.frame_interval_s
        else:
            assert self.protocol.frame_times_s is not None  # Protocol: exactly one of the two is given
            pr["frame_times_s"] = list(self.protocol.frame_times_s)
        out["protocol"] = pr
        pops = []
        for p in self.populations:
            d: dict[str, Any] = {"density_per_um3": p.density_per_um3, "reflectivity": p.reflectivity}
            if p.name:
                d["name"] = p.name
            d["motion"] = [dataclasses.asdict(m) for m in p.motion]
            pops.append(d)
        out["population"] = pops
        if self.noise is not None:
            out["noise"] = {"snr_db": self.noise.snr_db}
        a = dataclasses.asdict(self.analysis)
        a["metrics"] = list(a["metrics"])
        a["ocds_delay_range_s"] = list(a["ocds_delay_range_s"])
        out["analysis"] = a
        sim = dataclasses.asdict(self.simulation)
        if sim["truncation"] == "taper":  # the default, left out
            del sim["truncation"]
        out["simulation"] = sim
        return out


# ----------------------------------------------------------------------------------------------
# parsing


def _check_keys(path: str, table: Any, allowed: AbstractSet[str], required: AbstractSet[str] = frozenset()) -> dict:
    if not isinstance(table, dict):
        raise TypeError(f"{path} must be a table; got {type(table).__name__} {table!r}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        _fail(path, f"unknown key(s) {unknown}", f"allowed keys are {sorted(allowed)}")
    missing = sorted(required - set(table))
    if missing:
        _fail(path, f"missing required key(s) {missing}")
    return table


def _list_of_tables(path: str, value: Any) -> list:
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list):
        raise TypeError(f"{path} must be an array of tables ([[{path}]]); got {value!r}")
    check_count(path, len(value))
    return value


#: Fewest frame pairs a delay of the OCDS fit may rest on (docs/reliability.md, "Degenerate estimators").
#: Without correlation, the Pearson coefficient of N pairs has the variance 1/(N − 1): finite from N = 2
#: on, undefined for one pair, whose correlation is the convention ρ = 1 (both sides constant), not an
#: estimate: a fit through it returns a number set by the protocol alone (−2/Δt over 3 frames).
MIN_PAIRS_PER_DELAY = 2


def delay_pair_counts(frame_times_s: Any) -> list[tuple[float, int]]:
    """``(delay_s, frame pairs)`` of every distinct delay of the frame times (s): ``(m·Δt, N − m)`` for a
    uniform protocol, else the pairs ``i < j`` grouped by ``t_j − t_i``, both as
    :func:`torchdoct.conventions.delay_groups` (and so :func:`torchdoct.sim.metrics.ocds`) group them. A uniform
    protocol's counts are computed, not its N·(N − 1)/2 pairs listed (the maps check every slab's OCDS: listing
    the pairs made each check grow as N², gigabytes and minutes for thousands of frames)."""
    times = [float(v) for v in frame_times_s]
    dt = uniform_frame_interval_s(times)
    if dt is not None:
        return [(m * dt, len(times) - m) for m in range(1, len(times))]
    return [(d, len(ij)) for d, ij in delay_groups(times)]


def check_ocds_pairs(
    frame_times_s: Any,
    delay_range_s: Any,
    where: str = "ocds_delay_range_s",
    fix: str = "narrow the delay range or record more frames",
) -> None:
    """Refuse (``ValueError``) an OCDS whose delay range includes a delay resting on fewer than
    :data:`MIN_PAIRS_PER_DELAY` frame pairs, naming ``where``, the delay, its pairs, the largest delay
    that has enough and the ``fix``."""
    lo, hi = (float(v) for v in delay_range_s)
    counts = delay_pair_counts(frame_times_s)
    tol = delay_range_tolerance_s(frame_times_s, (lo, hi))
    inside = [(d, c) for d, c in counts if lo - tol <= d <= hi + tol]
    if len(inside) < 2:
        return  # fewer than 2 delays: the slope's own check names it
    thin = [(d, c) for d, c in inside if c < MIN_PAIRS_PER_DELAY]
    if not thin:
        return
    enough = [d for d, c in inside if c >= MIN_PAIRS_PER_DELAY]
    d, c = thin[0]
    more = f" (and {len(thin) - 1} more delay(s) above it)" if len(thin) > 1 else ""
    upto = f"; the delays up to {max(enough):.6g} s have enough" if enough else ""
    raise ValueError(
        f"{where}: [{lo:g}, {hi:g}] s includes the delay {d:.6g} s, which rests on {c} frame pair(s)"
        f"{more}; a lag correlation of fewer than {MIN_PAIRS_PER_DELAY} pairs is no estimate (one pair "
        f"has nothing to correlate: its ρ = 1 is a convention, whatever the data){upto}: {fix}"
    )


def whole_argument(name: str, value: Any) -> int:
    """``value`` as an ``int`` when it is one (a Python or NumPy integer); a ``bool``, a float (even
    ``2.0``) or anything else is a ``TypeError`` naming the argument ``name``: Python callers get no
    silent truncation (``trials=2.5`` is not 2 trials)."""
    import operator

    if isinstance(value, bool) or isinstance(value, float) or not hasattr(type(value), "__index__"):
        raise TypeError(
            f"{name} must be an integer; got {type(value).__name__} {value!r}"
            + (" (pass int(...) if truncation is meant)" if isinstance(value, float) else "")
        )
    return operator.index(value)


def check_scene_argument(func: str, value: Any, cls: type | None = None, loader: str = "td.load_scene") -> None:
    """A ``TypeError`` when ``value`` (the first argument of ``func``) is not a ``cls`` (default
    :class:`Scene`): a name or a path says to load it first with ``loader``."""
    cls = Scene if cls is None else cls
    if isinstance(value, cls):
        return
    if isinstance(value, (str, os.PathLike)):
        raise TypeError(
            f"{func} takes a {cls.__name__}, not the name or path {str(value)!r}: load it first, "
            f"{func.split('(')[0]}({loader}({str(value)!r}))"
        )
    raise TypeError(f"{func} takes a {cls.__name__} (from {loader}); got {type(value).__name__}")


def check_path_argument(func: str, value: Any, what: str) -> None:
    """A ``TypeError`` naming ``func`` when ``value`` is neither a path (``str``, ``os.PathLike``) nor a name:
    ``td.load_scene(42)`` says what it takes instead of an internal message."""
    if not isinstance(value, (str, os.PathLike)) or (isinstance(value, str) and not value.strip()):
        raise TypeError(
            f"{func} takes the path of a {what} file or the name of a shipped {what}; got "
            f"{type(value).__name__} {str(value)[:40]!r}"
        )


def check_count(path: str, n: int) -> None:
    """Refuse more than :data:`MAX_TABLES` tables of one kind (``path``: ``system``, ``population[0].motion``,
    ``region``, ...) before any of them is read or validated."""
    kind = path.rsplit(".", 1)[-1]
    limit = MAX_TABLES.get(kind)
    if limit is not None and n > limit:
        _fail(
            path,
            f"{n} [[{kind}]] tables; at most {limit} are accepted (each is validated and planned)",
            f"split the file into several with at most {limit} each",
        )


def _build(path: str, cls: type, kwargs: dict[str, Any]) -> Any:
    """Construct a dataclass, re-labelling its errors with the file's key path."""
    try:
        return cls(**kwargs)
    except (SceneError, TypeError) as err:
        msg = str(err)
        prefixes = []
        if cls is OCTSystem:
            prefixes.append(f"system[{kwargs.get('name')!r}]")
        if cls is Population:
            prefixes.append(f"population[{kwargs.get('name')!r}]" if kwargs.get("name") else "population")
        for pre in prefixes:
            if msg.startswith(pre + "."):
                msg = path + msg[len(pre) :]
                break
        raise type(err)(msg) from None


_SYSTEM_KEYS = {
    "name",
    "wavelength_um",
    "lateral_resolution_um",
    "axial_resolution_um",
    "refractive_index",
    "lateral_resolution_y_um",
}
_MOTION_KEYS = {
    "diffusion": {"kind", "diffusion_um2_per_s"},
    "ballistic": {"kind", "speed_um_per_s", "directions"},
    "flow": {"kind", "speed_um_per_s", "polar_angle_deg", "azimuth_deg"},
}
_MOTION_REQUIRED = {
    "diffusion": {"diffusion_um2_per_s"},
    "ballistic": {"speed_um_per_s"},
    "flow": {"speed_um_per_s"},
}


def scene_from_dict(data: dict[str, Any]) -> Scene:
    """Build a validated :class:`Scene` from the scene-file schema (see the README)."""
    _check_keys(
        "scene",
        data,
        {"name", "description", "system", "protocol", "population", "noise", "analysis", "simulation"},
        {"system", "protocol", "population"},
    )
    systems = []
    for i, s in enumerate(_list_of_tables("system", data["system"])):
        p = f"system[{i}]"
        _check_keys(p, s, _SYSTEM_KEYS, _SYSTEM_KEYS - {"refractive_index", "lateral_resolution_y_um"})
        systems.append(_build(p, OCTSystem, dict(s)))
    pr = _check_keys("protocol", data["protocol"], {"n_frames", "frame_interval_s", "frame_times_s"}, {"n_frames"})
    protocol = Protocol(**pr)
    populations = []
    for i, pop in enumerate(_list_of_tables("population", data["population"])):
        p = f"population[{i}]"
        _check_keys(p, pop, {"name", "density_per_um3", "reflectivity", "motion"}, {"density_per_um3"})
        motions = []
        for j, m in enumerate(_list_of_tables(f"{p}.motion", pop.get("motion", []))):
            mp = f"{p}.motion[{j}]"
            if not isinstance(m, dict):
                raise TypeError(f"{mp} must be a table; got {m!r}")
            if "kind" not in m:
                _fail(mp, "missing key 'kind'", 'set kind = "diffusion", "ballistic" or "flow"')
            kind = _string(f"{mp}.kind", m["kind"], tuple(_MOTION_TYPES))
            _check_keys(mp, m, _MOTION_KEYS[kind], _MOTION_REQUIRED[kind])
            kw = {k: v for k, v in m.items() if k != "kind"}
            try:
                motion = _MOTION_TYPES[kind](**kw)
            except TypeError as err:
                raise TypeError(f"{mp}: {err}") from None
            motion.validate(mp)
            motions.append(motion)
        kw = {k: v for k, v in pop.items() if k != "motion"}
        populations.append(_build(p, Population, {**kw, "motion": tuple(motions)}))
    noise = None
    if "noise" in data:
        n = _check_keys("noise", data["noise"], {"snr_db"}, {"snr_db"})
        noise = Noise(**n)
    analysis = Analysis(
        **_check_keys(
            "analysis", data.get("analysis", {}), {"metrics", "ocds_delay_range_s", "ocds_scale", "ocds_estimator"}
        )
    )
    simulation = SimulationSettings(
        **_check_keys(
            "simulation", data.get("simulation", {}), {"trials", "seed", "truncation_tolerance", "dtype", "truncation"}
        )
    )
    name = data.get("name", "")
    desc = data.get("description", "")
    _string("name", name)
    _string("description", desc)
    return Scene(
        systems=tuple(systems),
        protocol=protocol,
        populations=tuple(populations),
        noise=noise,
        analysis=analysis,
        simulation=simulation,
        name=name,
        description=desc,
    )


def read_toml(path: str | Path, what: str = "TOML file") -> dict[str, Any]:
    """The tables of a TOML file; a syntax error or a file that is not UTF-8 text (an image or data
    file given by mistake) is a :class:`SceneError` naming the file; a path that is not a regular file
    or a file over :data:`torchdoct.files.MAX_TEXT_BYTES` is a ``ValueError`` naming ``what``
    (:func:`torchdoct.files.read_capped`)."""
    from ..files import check_nesting, read_capped, toml_loads

    try:
        text = read_capped(path, what).decode("utf-8")
        check_nesting(text, str(path), toml=True)  # before the parser's recursion
        data = toml_loads(text)
        check_nesting(data, str(path))  # dotted keys nest tables without brackets
        return data
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{path}: not valid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise SceneError(
            f"{path}: not a TOML text file (byte {err.start} is not UTF-8 text); give the scene, "
            "phantom or study file (TOML, UTF-8), not a data or image file"
        ) from None


def load_scene(path: str | Path) -> Scene:
    """Read and validate a TOML scene file, or a shipped scene by name (see :func:`torchdoct.sim.scenes`)."""
    from .scenes import resolve_scene_path

    check_path_argument("td.load_scene(path)", path, "scene")
    p = resolve_scene_path(path)
    data = read_toml(p)
    try:
        scene = scene_from_dict(data)
    except (SceneError, TypeError) as err:
        raise type(err)(f"{p.name}: {err}") from None
    if not scene.name:
        scene = scene.replace(name=p.stem)
    return scene

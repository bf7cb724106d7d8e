"""The plan of a point simulation: which stages run, on which domain, at what cost.

:func:`make_plan` turns a :class:`~torchdoct.sim.config.Scene` into a :class:`Plan`; the simulator
executes exactly that plan, and ``torchdoct plan SCENE.toml`` prints it. Effects a scene does not ask
for have no stage: no noise stage without ``[noise]``, no motion stage for static scatterers, no
per-frame random draws for ballistic or flow motion (straight paths are drawn once).

Domains (lengths µm, times s; PSF truncation as in :mod:`torchdoct.conventions`):

* ``B``: the box of half-widths ``H = c·(s_x, s_y, s_z)``, ``c = √(2 ln(1/tolerance))``, the union
  over the scene's systems (all systems see the same scatterers); ``s_y = s_x`` unless a system gives
  ``lateral_resolution_y_um``.
* static populations: Poisson scatterers in ``B``, one evaluation per scatterer (the signal is
  constant over frames).
* drift populations (ballistic and/or flow, no diffusion): every straight path that meets the
  tolerance ellipsoid ``E`` (semi-axes ``H``, inscribed in ``B``: the region where the amplitude PSF
  exceeds the tolerance) during the protocol: the scatterers inside ``E`` at the first frame plus
  those entering it. In coordinates scaled by ``H`` the ellipsoid is the unit ball, a velocity ``v``
  becomes ``w = v/H`` and the Poisson density ``ρ·Hx·Hy·Hz``, so paths of velocity ``v`` enter at
  the rate ``ρ·Hx·Hy·Hz·π·|w|`` with a uniform impact point on the disk across ``w``. Exact: a path
  that never meets ``E`` never exceeds the tolerance, and every path sampled does.
* pure diffusion: scatterers walk on a periodic cell ``Ω ⊇ B`` (a scatterer leaving one face
  re-enters through the opposite one), so the count and the uniform Poisson law hold exactly at every
  frame and nothing is drawn but the steps. The only approximation is that a scatterer that travels
  once around the cell meets its own earlier contribution; :func:`periodic_image_bound` gives the
  largest such spurious share of any two-frame correlation of the field (relative to ⟨I⟩) or of
  the intensity (relative to ⟨I⟩²), and :func:`periodic_cell` grows ``Ω`` beyond ``B`` until it is
  below :func:`wrap_tolerance` (``max(tolerance/10, 1e-5)``: 1e-3 at the default tolerance).
* diffusion with drift: scatterers are tracked frame by frame in the region ``R = B ⊕ M``,
  ``M = c·σ_step + v_max·Δt`` (``σ_step = √(2·D·Δt_max)``), which a scatterer outside ``R`` cannot
  cross into ``B`` within one frame except with probability below the tolerance; at each frame
  immigrants from the shell around ``R`` are drawn from the Poisson medium outside it. A scatterer
  that leaves ``R`` and later comes back returns as a new one: its contributions before and after
  are not correlated, which drops part of the same-scatterer correlation at long delays.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..conventions import (
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    ens_paper,
    mean_intensity,
    n_eff,
    noise_power,
    truncation_field_error,
    truncation_half_widths_um,
    truncation_radius_factor,
    wavenumber_per_um,
)
from .config import Population, Scene

__all__ = [
    "PopulationPlan",
    "SystemPlan",
    "Plan",
    "make_plan",
    "capacity",
    "periodic_cell",
    "periodic_image_bound",
    "wrap_tolerance",
    "ellipsoid_entry_rate",
    "ellipsoid_entry_bound",
    "expected_entry_flux",
]

#: Trials per reproducibility block: trial ``i`` draws its randomness from the stream of block
#: ``i // BLOCK_TRIALS``, seeded from (seed, block index), so results never depend on chunking.
BLOCK_TRIALS = 64


def capacity(mean: float) -> int:
    """Slots reserved for a Poisson count of the given mean: mean + 10 SD + 16, a multiple of 8.

    The chance that a Poisson count exceeds it is below 1e-20; the simulator checks and raises.
    """
    c = mean + 10.0 * math.sqrt(max(mean, 0.0)) + 16.0
    return int(math.ceil(c / 8.0) * 8)


def _grown(h: tuple[float, float, float], g: float) -> tuple[float, float, float]:
    """The half-widths ``h`` with ``g`` added to each."""
    return (h[0] + g, h[1] + g, h[2] + g)


def _box_volume(h: tuple[float, float, float]) -> float:
    return 8.0 * h[0] * h[1] * h[2]


def _face_areas(h: tuple[float, float, float]) -> list[tuple[int, float]]:
    """(axis, area) of the two faces normal to each axis of the box of half-widths h."""
    out = []
    for a in range(3):
        b, c = [i for i in range(3) if i != a]
        out.append((a, 4.0 * h[b] * h[c]))
    return out


@functools.lru_cache(maxsize=16)
def _velocity_sample_of(
    flow: tuple[float, ...], ballistic: tuple[tuple[float, str], ...], n_samples: int = 200_000
) -> np.ndarray:
    """Cached by the velocity law: a plan asks for it once per group of systems."""
    rng = np.random.default_rng(12345)
    v = np.tile(np.asarray(flow, dtype=float), (n_samples, 1))
    for speed, directions in ballistic:
        u1, u2 = rng.random(n_samples), rng.random(n_samples)
        mu = 2 * u1 - 1 if directions == "isotropic" else np.cos(np.pi * u1)
        st = np.sqrt(np.clip(1 - mu * mu, 0, None))
        phi = 2 * np.pi * u2
        v += speed * np.stack([st * np.cos(phi), st * np.sin(phi), mu], axis=1)
    v.setflags(write=False)
    return v


def _mean_abs_components(v: np.ndarray, h: tuple[float, float, float]) -> np.ndarray:
    """E|v_a| per axis (µm/s) over the velocity rows ``v``."""
    return np.array([np.mean(np.abs(v[:, a])) for a in range(3)])


def _mean_scaled_speed(v: np.ndarray, h: tuple[float, float, float]) -> float:
    """E|v/h| over the velocity rows ``v`` (1/s)."""
    return float(np.mean(np.linalg.norm(v / np.asarray(h, dtype=float), axis=1)))


@functools.lru_cache(maxsize=256)
def _sample_mean(
    stat, flow: tuple[float, ...], ballistic: tuple[tuple[float, str], ...], h: tuple[float, float, float]
):
    """``stat`` over the fixed-seed sample of a velocity law (cached: sweeps ask for it per cell)."""
    return stat(_velocity_sample_of(flow, ballistic), h)


def _law_mean(pop: Population, stat, h: tuple[float, float, float] = (1.0, 1.0, 1.0)):
    """``stat`` (homogeneous of degree 1 in v) over the population's velocity law: exact for one
    velocity; ``speed·stat(d)`` for one ballistic law alone (one sample per direction law); else over
    the fixed-seed sample."""
    flow = tuple(pop.flow_velocity_um_per_s)
    ballistic = tuple((b.speed_um_per_s, b.directions) for b in pop.ballistic)
    if not ballistic:
        return stat(np.asarray([flow], dtype=float), h)
    if len(ballistic) == 1 and not any(flow):
        return ballistic[0][0] * _sample_mean(stat, (0.0, 0.0, 0.0), ((1.0, ballistic[0][1]),), tuple(h))
    return _sample_mean(stat, flow, ballistic, tuple(h))


def expected_entry_flux(pop: Population, h: tuple[float, float, float]) -> float:
    """Expected number of paths entering box ``h`` per unit time: ``ρ Σ_f A_f E[(−v·m_f)₊]``
    (expectation over the velocity law, :func:`_law_mean`; a plan figure)."""
    # both faces normal to axis a: E[(v_a)_-] + E[(v_a)_+] = E|v_a|
    m = _law_mean(pop, _mean_abs_components)
    return pop.density_per_um3 * sum(area * float(m[a]) for a, area in _face_areas(h))


def ellipsoid_entry_rate(pop: Population, h: tuple[float, float, float]) -> float:
    """Expected number of paths entering the ellipsoid of semi-axes ``h`` per unit time:
    ``ρ·π·hx·hy·hz·E|v/h|`` (see the module docstring; expectation over the velocity law, :func:`_law_mean`)."""
    return pop.density_per_um3 * math.pi * math.prod(h) * _law_mean(pop, _mean_scaled_speed, h)


def ellipsoid_entry_bound(pop: Population, h: tuple[float, float, float]) -> float:
    """Upper bound on ``|v/h|`` over the velocity law (µm/s over µm): the proposal rate of entrants."""
    flow = math.sqrt(sum((f / x) ** 2 for f, x in zip(pop.flow_velocity_um_per_s, h)))
    return flow + sum(b.speed_um_per_s for b in pop.ballistic) / min(h)


def _groups(halfs: list[tuple[float, float, float]]) -> list[tuple[tuple[float, float, float], tuple[int, ...]]]:
    """Systems grouped by identical PSF truncation boxes (in first-seen order)."""
    out: dict[tuple[float, float, float], list[int]] = {}
    for i, h in enumerate(halfs):
        out.setdefault(h, []).append(i)
    return [(h, tuple(idx)) for h, idx in out.items()]


def wrap_tolerance(tolerance: float) -> float:
    """Largest spurious share of a two-frame correlation the periodic cell may add: ``max(tol/10, 1e-5)``."""
    return max(tolerance / 10.0, 1e-5)


def _bound_lags(times_s: tuple[float, ...]) -> np.ndarray:
    """Delays (s) at which the periodic-image bound is evaluated: a dense grid over [shortest, longest]
    delay of the protocol (the bound is smooth in the delay, so its maximum over the grid is its
    maximum over the protocol's delays to within the grid spacing)."""
    t = np.asarray(times_s, dtype=float)
    d_min = float(np.min(np.diff(t)))
    d_max = float(t[-1] - t[0])
    return np.unique(np.concatenate([np.geomspace(d_min, d_max, 256), np.linspace(d_min, d_max, 256)]))


def periodic_image_bound(
    half_widths_um, optics, diffusion_um2_per_s: float, lags_s, w_intensity: float, w_field: float
) -> float:
    """Largest spurious share of a two-frame correlation from a periodic cell (pure diffusion).

    A scatterer displaced by ``Δ`` (Gaussian, variance ``2·D·τ`` per axis after delay τ) is evaluated
    at ``Δ`` wrapped into the cell of side ``L = 2·half_widths``; the wrong images ``Δ − n·L``
    (``n ≠ 0``) add to the same-scatterer terms of the two-frame moments (physics.md §5). With the
    untruncated Gaussian PSF of amplitude widths ``s_a`` (:mod:`torchdoct.conventions`):

    * intensity, relative to ⟨I⟩²: ``w_I·[Π_a Σ_k N(k·L_a; 0, s_a² + 2Dτ) − Π_a N(0; 0, s_a² + 2Dτ)]``,
      ``w_I = ρ_p·b_p⁴/(Σ_i ρ_i·b_i²)²`` (``1/ρ`` for one population);
    * field, relative to ⟨I⟩: ``w_F·[Π_a Σ_k |F_a(k)| − Π_a F_a(0)]`` with
      ``F_a(k) = √(2s_a²/W_a)·exp(−(k·L_a)²/(2·W_a))``, ``W_a = 2s_a² + 2Dτ``, times
      ``exp(−q²·v_p/2)``, ``v_p = 2Dτ·2s_z²/W_z``, on the depth axis (``q = 2kn``, the phase
      decorrelation); ``w_F = ρ_p·b_p²/Σ_i ρ_i·b_i²``.

    ``optics``: one ``(s_x, s_z, q)`` or ``(s_x, s_z, q, s_y)`` per system (µm, µm, rad/µm, µm; ``s_y = s_x``
    when left out). Returns the maximum over the systems, the delays ``lags_s`` (s) and both terms.
    """
    L = 2.0 * np.asarray(half_widths_um, dtype=float)
    v = 2.0 * diffusion_um2_per_s * np.asarray(lags_s, dtype=float)
    worst = 0.0
    for opt in optics:
        s_x, s_z, q = opt[:3]
        s_y = opt[3] if len(opt) > 3 else s_x
        i_all = np.ones_like(v)
        i_0 = np.ones_like(v)
        f_all = np.ones_like(v)
        f_0 = np.ones_like(v)
        for a, s in enumerate((s_x, s_y, s_z)):
            s2 = s * s + v
            w = 2.0 * s * s + v
            kmax = int(math.ceil(12.0 * math.sqrt(float(w.max())) / L[a])) + 1
            k = np.arange(-kmax, kmax + 1, dtype=float)[None, :]
            g = np.exp(-((k * L[a]) ** 2) / (2.0 * s2[:, None])) / np.sqrt(2.0 * np.pi * s2[:, None])
            i_all *= g.sum(1)
            i_0 *= g[:, kmax]
            f = np.sqrt(2.0 * s * s / w)[:, None] * np.exp(-((k * L[a]) ** 2) / (2.0 * w[:, None]))
            if a == 2:
                f = f * np.exp(-0.5 * q * q * v * 2.0 * s * s / w)[:, None]
            f_all *= f.sum(1)
            f_0 *= f[:, kmax]
        worst = max(worst, float(np.max(w_intensity * (i_all - i_0))), float(np.max(w_field * (f_all - f_0))))
    return worst


def periodic_cell(
    psf_half_widths_um, optics, diffusion_um2_per_s: float, times_s, w_intensity: float, w_field: float, target: float
) -> tuple[tuple[float, float, float], float]:
    """The smallest cell ``B + g`` (``g ≥ 0`` µm added to every half-width) whose
    :func:`periodic_image_bound` over the protocol's delays is at most ``target``; returns the cell's
    half-widths (µm) and its bound."""
    lags = _bound_lags(times_s)
    hx, hy, hz = (float(h) for h in psf_half_widths_um)
    H = (hx, hy, hz)

    def bound(g: float) -> float:
        return periodic_image_bound([h + g for h in H], optics, diffusion_um2_per_s, lags, w_intensity, w_field)

    b = bound(0.0)
    if b <= target:
        return H, b
    lo, hi = 0.0, max(H)
    b = bound(hi)
    while b > target:
        lo, hi = hi, 2.0 * hi
        if hi > 1e7:
            raise ValueError("no periodic cell reaches the wrap tolerance (raise the truncation tolerance)")
        b = bound(hi)
    for _ in range(40):  # bisection on g; ``b`` stays the bound at ``hi``
        if hi - lo < 1e-3 * hi:
            break
        mid = 0.5 * (lo + hi)
        b_mid = bound(mid)
        if b_mid > target:
            lo = mid
        else:
            hi, b = mid, b_mid
    return _grown(H, hi), b


@functools.lru_cache(maxsize=256)
def _periodic_cell_cached(psf_half_widths_um, optics, diffusion_um2_per_s, times_s, w_intensity, w_field, target):
    """:func:`periodic_cell` remembered per argument set (a bisection of a dozen bound evaluations, several ms:
    repeated simulations of one scene, and sweeps that revisit a value, pay it once)."""
    return periodic_cell(psf_half_widths_um, optics, diffusion_um2_per_s, times_s, w_intensity, w_field, target)


@dataclass(frozen=True)
class PopulationPlan:
    """How one population is simulated (lengths µm, times s)."""

    index: int
    name: str
    sampler: str  # "static" | "drift" | "diffusive"
    motions: tuple[str, ...]
    density_per_um3: float
    domain_half_widths_um: tuple[float, float, float]
    expected_scatterers_per_trial: float
    capacity: int
    per_frame_random_draws: bool
    evaluations_per_trial: float  # scatterer-frame evaluations, all systems
    # drift
    entry_proposal_rate_per_s: float = 0.0
    entry_proposal_capacity: int = 0
    entry_capacity: int = 0
    # per-system culling (static, drift): one entry per group of systems sharing a PSF box:
    # (half-widths µm, system indices, expected scatterers per trial, capacity)
    system_groups: tuple = ()
    # diffusive: "periodic" (pure diffusion) or "shell" (diffusion with drift)
    immigrant_method: str = ""
    wrap_error_bound: float = 0.0
    step_margin_um: float = 0.0
    immigrant_shell_half_widths_um: tuple[float, float, float] = (0.0, 0.0, 0.0)
    immigrant_proposal_capacity: int = 0


@dataclass(frozen=True)
class SystemPlan:
    name: str
    truncation_half_widths_um: tuple[float, float, float]
    ens_paper: float
    n_eff: float
    mean_intensity: float
    noise_power: float | None


@dataclass(frozen=True)
class Plan:
    """What a simulation of a scene will run; see the module docstring."""

    scene_name: str
    stages: tuple[str, ...]
    truncation_tolerance: float
    truncation_error_bound: float
    domain_half_widths_um: tuple[float, float, float]
    systems: tuple[SystemPlan, ...]
    populations: tuple[PopulationPlan, ...]
    n_frames: int
    duration_s: float
    has_noise: bool
    block_trials: int = BLOCK_TRIALS
    notes: tuple[str, ...] = field(default_factory=tuple)
    truncation: str = "hard"

    @property
    def expected_scatterers_per_trial(self) -> float:
        return sum(p.expected_scatterers_per_trial for p in self.populations)

    @property
    def evaluations_per_trial(self) -> float:
        return sum(p.evaluations_per_trial for p in self.populations)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["expected_scatterers_per_trial"] = self.expected_scatterers_per_trial
        d["evaluations_per_trial"] = self.evaluations_per_trial
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def describe(self, trials: int | None = None) -> str:
        """Human-readable plan."""
        lines = [f"plan for scene {self.scene_name!r}: {self.n_frames} frames over {self.duration_s:g} s"]
        lines.append("stages: " + " -> ".join(self.stages))
        mode = "tapered to 0 at" if self.truncation == "taper" else "cut at"
        lines.append(
            f"PSF amplitude {mode} tolerance {self.truncation_tolerance:g} "
            f"(relative mean-square field change {self.truncation_error_bound:.2g})"
        )
        lines.append("systems (all see the same scatterers):")
        for s in self.systems:
            h = s.truncation_half_widths_um
            noise = "" if s.noise_power is None else f", noise power {s.noise_power:.4g}"
            ens = "ρΔx²Δz" if h[0] == h[1] else "ρΔxΔyΔz"
            lines.append(
                f"  {s.name:>14}: ENS(paper, {ens}) {s.ens_paper:8.3f}   N_eff {s.n_eff:8.3f}   "
                f"<I> {s.mean_intensity:.4g}   PSF box ±({h[0]:.2f}, {h[1]:.2f}, {h[2]:.2f}) µm{noise}"
            )
        lines.append("populations:")
        for p in self.populations:
            h = p.domain_half_widths_um
            lines.append(
                f"  [{p.index}] {p.name or '-'}: {p.sampler} ({', '.join(p.motions) or 'no motion'}), "
                f"ρ = {p.density_per_um3:g} µm⁻³"
            )
            if p.immigrant_method == "periodic":
                lines.append(
                    f"      random walk on a periodic cell = PSF box + {p.step_margin_um:.2f} µm per side "
                    f"(wrap-around adds <= {p.wrap_error_bound:.2g} to any two-frame correlation)"
                )
            elif p.sampler == "diffusive":
                lines.append(
                    f"      random walk, tracked region = PSF box + {p.step_margin_um:.2f} µm per side, "
                    f"immigrants drawn from the surrounding shell"
                )
            if p.sampler == "drift":
                lines.append(
                    "      straight paths that meet the tolerance ellipsoid (semi-axes = the PSF box "
                    "half-widths) during the protocol"
                )
            if len(p.system_groups) > 1:
                lines.append("      each system evaluates only the scatterers that reach its own PSF box")
            lines.append(
                f"      domain ±({h[0]:.2f}, {h[1]:.2f}, {h[2]:.2f}) µm, "
                f"{p.expected_scatterers_per_trial:.1f} scatterers/trial expected, "
                f"{p.evaluations_per_trial:.4g} scatterer-frame evaluations/trial, "
                f"per-frame random draws: {'yes' if p.per_frame_random_draws else 'no'}"
            )
        lines.append(
            f"total: {self.expected_scatterers_per_trial:.1f} scatterers/trial, "
            f"{self.evaluations_per_trial:.4g} scatterer-frame evaluations/trial"
        )
        if trials is not None:
            lines.append(f"for {trials} trials: {self.evaluations_per_trial * trials:.4g} evaluations")
        for n in self.notes:
            lines.append(f"note: {n}")
        return "\n".join(lines)


def make_plan(scene: Scene, *, truncation_tolerance: float | None = None, truncation: str | None = None) -> Plan:
    """Decide stages, domains and costs for simulating ``scene`` (see the module docstring).

    ``truncation_tolerance`` and ``truncation`` (``"hard"`` or ``"taper"``) default to the scene's
    ``[simulation]`` values; the taper changes no domain (it reaches 0 on the same ellipsoid)."""
    from .config import check_count, check_scene_argument

    check_scene_argument("td.make_plan(scene)", scene)
    check_count("system", len(scene.systems))  # a scene built in Python: the file's limits, before the work
    check_count("population", len(scene.populations))
    for i, p in enumerate(scene.populations):
        check_count(f"population[{i}].motion", len(p.motion))
    tol = scene.simulation.truncation_tolerance if truncation_tolerance is None else truncation_tolerance
    mode = scene.simulation.truncation if truncation is None else truncation
    c = truncation_radius_factor(tol)
    protocol = scene.protocol
    T = protocol.duration_s
    n_frames = protocol.n_frames
    S = len(scene.systems)
    halfs = [
        truncation_half_widths_um(
            s.lateral_resolution_um, s.axial_resolution_um, tol, lateral_resolution_y_um=s.lateral_resolution_y_um
        )
        for s in scene.systems
    ]
    H = (max(h[0] for h in halfs), max(h[1] for h in halfs), max(h[2] for h in halfs))
    rho_total = sum(p.density_per_um3 for p in scene.populations)

    systems = []
    for s, h in zip(scene.systems, halfs):
        mi = sum(
            mean_intensity(
                p.density_per_um3,
                s.lateral_resolution_um,
                s.axial_resolution_um,
                p.reflectivity,
                lateral_resolution_y_um=s.lateral_resolution_y_um,
            )
            for p in scene.populations
        )
        noise = None if scene.noise is None else noise_power(mi, scene.noise.snr_db)
        systems.append(
            SystemPlan(
                name=s.name,
                truncation_half_widths_um=h,
                ens_paper=ens_paper(
                    rho_total,
                    s.lateral_resolution_um,
                    s.axial_resolution_um,
                    lateral_resolution_y_um=s.lateral_resolution_y_um,
                ),
                n_eff=n_eff(
                    rho_total,
                    s.lateral_resolution_um,
                    s.axial_resolution_um,
                    lateral_resolution_y_um=s.lateral_resolution_y_um,
                ),
                mean_intensity=mi,
                noise_power=noise,
            )
        )

    pops = []
    notes = []
    stages = []
    for i, p in enumerate(scene.populations):
        kind = p.motion_class
        motions = tuple(m.kind + ("" if m.kind != "ballistic" else f" ({m.directions})") for m in p.active_motion)
        zero = [m.kind for m in p.motion if m.is_zero]
        if zero:
            notes.append(f"population {i}: motion entries with zero parameter ({', '.join(zero)}) do nothing")
        rho = p.density_per_um3
        if kind == "static":
            n = rho * _box_volume(H)
            groups = tuple((h, idx, rho * _box_volume(h), capacity(rho * _box_volume(h))) for h, idx in _groups(halfs))
            evals = sum(g[2] * len(g[1]) for g in groups)
            pops.append(
                PopulationPlan(i, p.name, "static", motions, rho, H, n, capacity(n), False, evals, system_groups=groups)
            )
        elif kind == "drift":
            n0 = rho * 4.0 * math.pi / 3.0 * math.prod(H)
            flux = ellipsoid_entry_rate(p, H)
            prop_rate = rho * math.pi * math.prod(H) * ellipsoid_entry_bound(p, H)
            n = n0 + flux * T
            moving = p.max_speed_um_per_s > 0 and T > 0
            drift_groups: list[tuple[tuple[float, float, float], tuple[int, ...], float, int]] = []
            for h, idx in _groups(halfs):
                ng = n if h == H else rho * _box_volume(h) + expected_entry_flux(p, h) * T
                drift_groups.append((h, idx, ng, capacity(ng)))
            # every sampled path is evaluated at every frame of its group's systems (amplitudes below
            # the tolerance are set to 0)
            evals = sum(g[2] * len(g[1]) for g in drift_groups) * n_frames
            pops.append(
                PopulationPlan(
                    i,
                    p.name,
                    "drift",
                    motions,
                    rho,
                    H,
                    n,
                    capacity(n0),
                    False,
                    evals,
                    system_groups=tuple(drift_groups),
                    entry_proposal_rate_per_s=prop_rate,
                    entry_proposal_capacity=capacity(prop_rate * T) if moving else 0,
                    entry_capacity=capacity(flux * T) if moving else 0,
                )
            )
        elif p.max_speed_um_per_s == 0:
            D = p.diffusion_um2_per_s
            # the weights are scale-free: reflectivities divided by the power of two just above the largest (exact,
            # so the weights are those of the unscaled ones), so that 1e-160 neither underflows nor divides by 0
            unit = 2.0 ** math.frexp(max(q.reflectivity for q in scene.populations))[1]
            b = p.reflectivity / unit
            mean_b2 = sum(q.density_per_um3 * (q.reflectivity / unit) ** 2 for q in scene.populations)
            w_int = rho * b**4 / mean_b2**2
            w_field = rho * b**2 / mean_b2
            optics = [
                (
                    amplitude_sigma_lateral_um(s.lateral_resolution_um),
                    amplitude_sigma_axial_um(s.axial_resolution_um),
                    2.0 * wavenumber_per_um(s.wavelength_um, s.refractive_index),
                )
                + (
                    ()
                    if s.lateral_resolution_y_um is None
                    else (amplitude_sigma_lateral_um(s.lateral_resolution_y_um),)
                )
                for s in scene.systems
            ]
            cell, bound = _periodic_cell_cached(
                tuple(H), tuple(optics), D, tuple(protocol.times_s), w_int, w_field, wrap_tolerance(tol)
            )
            n = rho * _box_volume(cell)
            evals = n * n_frames * S  # every scatterer of the cell, every frame, every system
            pops.append(
                PopulationPlan(
                    i,
                    p.name,
                    "diffusive",
                    motions,
                    rho,
                    cell,
                    n,
                    capacity(n),
                    True,
                    evals,
                    immigrant_method="periodic",
                    step_margin_um=cell[0] - H[0],
                    wrap_error_bound=bound,
                )
            )
        else:
            D = p.diffusion_um2_per_s
            dtm = protocol.max_interval_s
            sigma = math.sqrt(2.0 * D * dtm)
            margin = c * sigma + p.max_speed_um_per_s * dtm
            R = _grown(H, margin)
            outer = _grown(R, margin)
            n = rho * _box_volume(R)
            n_prop = rho * (_box_volume(outer) - _box_volume(R))
            pops.append(
                PopulationPlan(
                    i,
                    p.name,
                    "diffusive",
                    motions,
                    rho,
                    R,
                    n,
                    capacity(n),
                    True,
                    n * n_frames * S,
                    immigrant_method="shell",
                    step_margin_um=margin,
                    immigrant_shell_half_widths_um=outer,
                    immigrant_proposal_capacity=capacity(n_prop),
                )
            )
    kinds = {p.sampler for p in pops}
    stages.append("seed scatterers")
    if "drift" in kinds:
        stages.append("straight paths (drawn once)")
    if "diffusive" in kinds:
        stages.append("random walk (per-frame draws)")
    if kinds == {"static"}:
        stages.append("signal (one evaluation, constant over frames)")
    else:
        stages.append("signal")
    if scene.noise is not None:
        stages.append("noise")
    stages.append("metrics")
    return Plan(
        scene_name=scene.name,
        stages=tuple(stages),
        truncation_tolerance=tol,
        truncation_error_bound=truncation_field_error(tol, mode),
        domain_half_widths_um=H,
        systems=tuple(systems),
        populations=tuple(pops),
        n_frames=n_frames,
        duration_s=T,
        has_noise=scene.noise is not None,
        notes=tuple(notes),
        truncation=mode,
    )

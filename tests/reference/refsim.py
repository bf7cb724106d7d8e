"""An independent brute-force point simulator of the DOCT pixel signal, for tests only.

Written from ``docs/physics.md`` alone (§5.1 model and conventions, §5.3 motion laws, §8 noise,
§10.2 direction laws) in numpy, float64, and sharing no code with torchdoct's simulator: no
truncation ellipsoid, no plan, no kernel, no conventions module. The features are computed twice: by
:func:`torchdoct.sim.signature.signature` (the extractor the models read) and by the numpy
definitions of this module (:func:`features`, written from physics.md §1, §2.4 and the signature's
documented definitions), which the fast tests hold equal.

**Model** (physics.md §5.1). The complex signal of the pixel at the origin::

    E(t) = b Σ_j exp(−x_j²/(2 s_x²) − y_j²/(2 s_y²) − z_j²/(2 s_z²)) · exp(i·2·k·n·z_j(t)),   k = 2π/λ

with ``s_x = Δx/(2√2)``, ``s_y = Δy/(2√2)`` (Δx, Δy the 1/e² full widths of the intensity PSF along
x and y; an isotropic system has Δy = Δx, a B-scan's x-only lateral reduction has Δx reduced and Δy
original) and ``s_z = Δz/(2√ln2)`` (Δz the intensity FWHM).

**Scatterers**: a homogeneous Poisson process of density ρ (µm⁻³) in the box
``|x_a| ≤ L_a/2`` centred on the PSF, ``L_a = 2·c·s_a + m_a`` with ``c`` = :data:`BOX_SIGMAS` amplitude
sigmas (default 6) and ``m_a`` the margin of the motion: ``|v_a|·T`` for flow, ``v·T`` for random
ballistic motion, ``6·√(2·D·T)`` for diffusion (T the first-to-last frame time). Positions are wrapped
periodically into the box at every frame, so the process stays homogeneous Poisson at all times
(stationarity), and with this margin no scatterer comes back through the ``±c·s_a`` window within
the protocol (flow, ballistic: exactly; diffusion: a displacement of 6 standard deviations would be
needed). What the box leaves out: the share of ``∫|h|²`` outside ``±c·s_a`` on some axis,
``1 − erf(c)³`` (4.6e-12 at c = 5, 6.5e-17 at c = 6: :func:`neglected_field_fraction`); a scatterer
wrapped across a face enters at a relative amplitude ``≤ exp(−c²/2)`` (1.5e-8 at c = 6), against
1e-2 for torchdoct's default truncation ellipsoid.

**Exact paths** at the frame times ``t_i = i·Δt``: diffusion, the sum of independent Gaussian steps of
variance ``2·D·Δt`` per axis per frame (exact for Brownian motion sampled at the frames); random
ballistic, ``r_j(t) = r_j(0) + v·n̂_j·t`` with ``n̂_j`` isotropic (cos of the polar angle ~ U[−1, 1]) or
the paper's ``"uniform-angles"`` law (polar angle ~ U[0, π]), azimuth ~ U[0, 2π) (physics.md
§10.2); flow, ``r_j(t) = r_j(0) + v·t`` with ``v = v·(sinθ cosφ, sinθ sinφ, cosθ)``, θ the polar angle
from the depth axis +z and φ the azimuth from +x.

**Noise** (physics.md §8): additive circular complex Gaussian, independent per frame, of power
``N₀ = ⟨I⟩/10^(SNR/10)`` with ``⟨I⟩ = ρ·b²·π^{3/2}·s_x·s_y·s_z`` (physics.md §5.2).

**Randomness**: trials come in blocks of :data:`BLOCK` trials; block ``k`` of system ``s`` draws
from ``numpy.random.SeedSequence(seed, spawn_key=(s, k))``, so a trial's numbers do not depend on
how many trials are asked for. Different systems see independent scatterers (the tests compare
per-system means, which do not depend on whether systems share scatterers).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import special

__all__ = [
    "BOX_SIGMAS",
    "BLOCK",
    "Optics",
    "Motion",
    "box_lengths_um",
    "neglected_field_fraction",
    "mean_intensity",
    "simulate",
    "features",
    "feature_names",
]

#: Half-width of the scatterer box beyond the motion margin, in amplitude-PSF sigmas per axis.
BOX_SIGMAS = 6.0
#: Trials per random block.
BLOCK = 64


@dataclass(frozen=True)
class Optics:
    """One OCT system (physics.md §5.1): vacuum wavelength (µm), lateral resolution = 1/e² full width
    of the intensity PSF along x (and y; ``lateral_y_um=None`` means the same as x), axial
    resolution = intensity FWHM (µm), phase index n."""

    wavelength_um: float
    lateral_resolution_um: float
    axial_resolution_um: float
    lateral_y_um: float | None = None
    refractive_index: float = 1.0

    @property
    def sigmas_um(self) -> tuple[float, float, float]:
        """Amplitude-PSF sigmas (s_x, s_y, s_z): Δx/(2√2), Δy/(2√2), Δz/(2√ln2) (physics.md §5.1)."""
        dy = self.lateral_resolution_um if self.lateral_y_um is None else self.lateral_y_um
        return (
            self.lateral_resolution_um / (2.0 * math.sqrt(2.0)),
            dy / (2.0 * math.sqrt(2.0)),
            self.axial_resolution_um / (2.0 * math.sqrt(math.log(2.0))),
        )

    @property
    def kn(self) -> float:
        """k·n = 2π·n/λ (rad/µm); the round-trip phase is exp(i·2·k·n·z)."""
        return 2.0 * math.pi * self.refractive_index / self.wavelength_um


@dataclass(frozen=True)
class Motion:
    """``kind``: ``"static"``, ``"diffusion"`` (``diffusion_um2_per_s``), ``"ballistic"``
    (``speed_um_per_s``, ``directions`` ``"isotropic"`` or ``"uniform-angles"``) or ``"flow"``
    (``speed_um_per_s``, ``polar_angle_deg`` from +z, ``azimuth_deg`` from +x)."""

    kind: str
    diffusion_um2_per_s: float = 0.0
    speed_um_per_s: float = 0.0
    directions: str = "isotropic"
    polar_angle_deg: float = 0.0
    azimuth_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("static", "diffusion", "ballistic", "flow"):
            raise ValueError(f"Motion.kind must be static, diffusion, ballistic or flow; got {self.kind!r}")
        if self.directions not in ("isotropic", "uniform-angles"):
            raise ValueError(f"Motion.directions must be isotropic or uniform-angles; got {self.directions!r}")

    @property
    def flow_velocity(self) -> np.ndarray:
        th, ph = math.radians(self.polar_angle_deg), math.radians(self.azimuth_deg)
        v = self.speed_um_per_s
        return np.array([v * math.sin(th) * math.cos(ph), v * math.sin(th) * math.sin(ph), v * math.cos(th)])


def box_lengths_um(optics: Optics, motion: Motion, duration_s: float, box_sigmas: float = BOX_SIGMAS) -> np.ndarray:
    """Box side lengths (L_x, L_y, L_z) in µm (module docstring)."""
    s = np.array(optics.sigmas_um)
    if motion.kind == "flow":
        margin = np.abs(motion.flow_velocity) * duration_s
    elif motion.kind == "ballistic":
        margin = np.full(3, motion.speed_um_per_s * duration_s)
    elif motion.kind == "diffusion":
        margin = np.full(3, 6.0 * math.sqrt(2.0 * motion.diffusion_um2_per_s * duration_s))
    else:
        margin = np.zeros(3)
    return 2.0 * box_sigmas * s + margin


def neglected_field_fraction(box_sigmas: float = BOX_SIGMAS) -> float:
    """Share of ``∫|h|²`` outside ``±c·s_a`` on some axis: ``1 − erf(c)³`` (|h|² has sigma s_a/√2)."""
    return float(-np.expm1(3.0 * np.log1p(-special.erfc(box_sigmas))))


def mean_intensity(optics: Optics, density_per_um3: float, reflectivity: float = 1.0) -> float:
    """``⟨I⟩ = ρ·b²·∫|h|² = ρ·b²·π^{3/2}·s_x·s_y·s_z`` (physics.md §5.2)."""
    sx, sy, sz = optics.sigmas_um
    return density_per_um3 * reflectivity**2 * math.pi**1.5 * sx * sy * sz


def _directions(rng: np.random.Generator, n: int, law: str) -> np.ndarray:
    u0, u1 = rng.random(n), rng.random(n)
    mu = 2.0 * u0 - 1.0 if law == "isotropic" else np.cos(math.pi * u0)
    st = np.sqrt(np.clip(1.0 - mu * mu, 0.0, None))
    phi = 2.0 * math.pi * u1
    return np.stack([st * np.cos(phi), st * np.sin(phi), mu], axis=1)


def _block(
    optics: Optics,
    motion: Motion,
    density: float,
    times: np.ndarray,
    trials: int,
    rng: np.random.Generator,
    reflectivity: float,
    snr_db: float | None,
    box_sigmas: float,
) -> np.ndarray:
    L = box_lengths_um(optics, motion, float(times[-1] - times[0]), box_sigmas)
    counts = rng.poisson(density * float(np.prod(L)), size=trials)
    m = int(counts.sum())
    owner = np.repeat(np.arange(trials), counts)
    pos0 = (rng.random((m, 3)) - 0.5) * L
    sx, sy, sz = optics.sigmas_um
    w = np.array([0.5 / sx**2, 0.5 / sy**2, 0.5 / sz**2])
    two_kn = 2.0 * optics.kn
    if motion.kind == "ballistic":
        vel = motion.speed_um_per_s * _directions(rng, m, motion.directions)
    elif motion.kind == "flow":
        vel = np.broadcast_to(motion.flow_velocity, (m, 3))
    else:
        vel = None
    step_sd = math.sqrt(2.0 * motion.diffusion_um2_per_s * (times[1] - times[0])) if motion.kind == "diffusion" else 0.0
    if motion.kind == "diffusion" and len(times) > 2 and np.ptp(np.diff(times)) > 1e-12 * times[-1]:
        raise ValueError("the reference simulator's diffusion needs uniform frame times")
    out = np.empty((trials, len(times)), dtype=np.complex128)
    pos = pos0.copy()
    for i, t in enumerate(times):
        if vel is not None:
            pos = pos0 + vel * (t - times[0])
        elif motion.kind == "diffusion" and i > 0:
            pos0 += rng.standard_normal((m, 3)) * step_sd  # unwrapped Brownian path
            pos = pos0
        p = pos - L * np.floor(pos / L + 0.5)  # periodic wrap into [−L/2, L/2)
        amp = np.exp(-(p * p) @ w) * reflectivity
        ph = two_kn * p[:, 2]
        out[:, i] = np.bincount(owner, weights=amp * np.cos(ph), minlength=trials) + 1j * np.bincount(
            owner, weights=amp * np.sin(ph), minlength=trials
        )
    if snr_db is not None:
        n0 = mean_intensity(optics, density, reflectivity) / 10.0 ** (snr_db / 10.0)
        sd = math.sqrt(n0 / 2.0)
        out += sd * (rng.standard_normal(out.shape) + 1j * rng.standard_normal(out.shape))
    return out


def simulate(
    optics: Optics | Sequence[Optics],
    motion: Motion,
    *,
    density_per_um3: float,
    n_frames: int,
    frame_interval_s: float,
    trials: int,
    seed: int,
    reflectivity: float = 1.0,
    snr_db: float | None = None,
    box_sigmas: float = BOX_SIGMAS,
) -> np.ndarray:
    """Complex signals ``[trials, systems, frames]`` (complex128) of the module's model.

    ``optics``: one system or a sequence (each with its own, independent scatterers). Frames at
    ``t_i = i·frame_interval_s``. ``snr_db=None``: no noise.
    """
    systems = [optics] if isinstance(optics, Optics) else list(optics)
    times = np.arange(n_frames, dtype=np.float64) * float(frame_interval_s)
    out = np.empty((trials, len(systems), n_frames), dtype=np.complex128)
    for s, opt in enumerate(systems):
        for k in range(-(-trials // BLOCK)):
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(s, k)))
            e = _block(opt, motion, density_per_um3, times, BLOCK, rng, reflectivity, snr_db, box_sigmas)
            lo = k * BLOCK
            out[lo : lo + BLOCK, s] = e[: trials - lo]
    return out


# ------------------------------------------------------------------------------------------------------
# features, in numpy, from their definitions (physics.md §1, §2.4; torchdoct.sim.signature's docstring)


def feature_names(rho_lin_lags: Sequence[int], field_lags: Sequence[int]) -> tuple[str, ...]:
    """Every feature a shipped model reads or the field group offers, plus LIV and OCDS."""
    return (
        tuple(f"rho_lin_{m}" for m in rho_lin_lags)
        + ("lin_contrast", "db_variance")
        + tuple(f"g1_{m}" for m in field_lags)
        + tuple(f"g1_phase_{m}" for m in field_lags)
        + ("phase_ramp", "liv", "ocds")
    )


def _pearson(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a - a.mean(-1, keepdims=True)
    b = b - b.mean(-1, keepdims=True)
    return (a * b).mean(-1) / np.sqrt((a * a).mean(-1) * (b * b).mean(-1))


def features(
    e: np.ndarray, frame_interval_s: float, names: Sequence[str], ocds_lags: Sequence[int] = (1, 2, 3, 4, 5, 6)
) -> dict[str, np.ndarray]:
    """Features of complex signals ``e [..., T]`` by name (numpy, float64).

    ``rho_lin_m``: Pearson correlation of I = |E|² between frames i and i+m (the T − m pairs);
    ``lin_contrast``: Var_t I/(mean_t I)² (ddof 0); ``db_variance`` and ``liv``: ddof-0 variance of
    10·log10 I (physics.md §1); ``g1_m``: |Σ E_i E*_{i+m}|/√(Σ I_i · Σ I_{i+m}); ``g1_phase_m``: the
    argument of that sum in (−π, π]; ``phase_ramp``: cos(arg G(2) − 2·arg G(1)); ``ocds``: minus the
    least-squares slope against τ = m·Δt of the Pearson correlation of the dB intensity at
    ``ocds_lags`` (physics.md §2.4).
    """
    inten = e.real**2 + e.imag**2
    db = 10.0 * np.log10(inten)
    n = e.shape[-1]

    def g(m: int) -> np.ndarray:
        return (e[..., : n - m] * np.conj(e[..., m:])).sum(-1)

    out: dict[str, np.ndarray] = {}
    for name in names:
        if name.startswith("rho_lin_"):
            m = int(name.rsplit("_", 1)[1])
            out[name] = _pearson(inten[..., : n - m], inten[..., m:])
        elif name == "lin_contrast":
            out[name] = inten.var(-1) / inten.mean(-1) ** 2
        elif name in ("db_variance", "liv"):
            out[name] = db.var(-1)
        elif name.startswith("g1_phase_"):
            ang = np.angle(g(int(name.rsplit("_", 1)[1])))
            out[name] = np.where(ang <= -math.pi, ang + 2.0 * math.pi, ang)
        elif name.startswith("g1_"):
            m = int(name.rsplit("_", 1)[1])
            out[name] = np.abs(g(m)) / np.sqrt(inten[..., : n - m].sum(-1) * inten[..., m:].sum(-1))
        elif name == "phase_ramp":
            z = g(2) * np.conj(g(1)) ** 2
            out[name] = z.real / np.abs(z)
        elif name == "ocds":
            lags = np.asarray(ocds_lags, dtype=np.float64)
            rho = np.stack([_pearson(db[..., : n - int(m)], db[..., int(m) :]) for m in ocds_lags], -1)
            x = (lags - lags.mean()) * frame_interval_s
            out[name] = -(rho * x).sum(-1) / (x * x).sum()
        else:
            raise ValueError(f"unknown feature {name!r}")
    return out

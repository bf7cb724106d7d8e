"""The dynamic-light-scattering baseline: a per-pixel least-squares fit of the complex ĝ1 curve.

DLS-OCT (physics.md §4, §5.3) classifies and sizes motion by fitting the normalised field
autocorrelation ``g1(τ) = Ms + Mf·g1_motion(τ)`` of each pixel: a static term ``Ms`` (static
scatterers, real) plus the moving scatterers' term. This module fits it to the measured
``ĝ1(m·Δt) = g1_m·exp(i·g1_phase_m)`` (:mod:`torchdoct.sim.signature`) at lags ``m`` of every
configuration of a feature spec jointly, with the closed forms of :mod:`torchdoct.sim.theory` for
the three motion types of the classifier's prior (:mod:`classifier.dataset`):

* diffusion: :func:`~torchdoct.sim.theory.g1_diffusion` (``exp(−q²Dτ)`` with its transit factors,
  ``q = 2·k·n``), real;
* random-ballistic motion: :func:`~torchdoct.sim.theory.g1_ballistic` with the prior's direction
  law (both laws, the better one, when the prior mixes them), real;
* flow: :func:`~torchdoct.sim.theory.g1_flow`, the transit Gaussian ``exp(−v²τ²[sin²θ/(4s_x²) +
  cos²θ/(4s_z²)])`` times the Doppler phase ``exp(−i·q·v·cosθ·τ)``, speed and polar angle free.

**The fit** (vectorised over pixels, numpy). Per candidate on a log grid of the magnitude
(:data:`GRID_PER_DECADE` points per decade over the prior's range widened a decade each way; for
flow times :data:`COS_POLAR_STEPS` values of ``|cos θ|``) and per configuration, the amplitudes
``Ms, Mf ≥ 0`` are solved in closed form (two-parameter non-negative least squares: the
unconstrained solution or the better face), weighted by ``T − m`` (the frame pairs behind ĝ1 at
lag ``m``: its inverse variance for decorrelated speckle). Magnitude and angle are shared by the
configurations (one set of scatterers), the amplitudes are not (the static scatterers' speckle
intensity differs between the resolutions of one pixel). Flow's phase turns by ``q·v_z·Δt`` per
frame, up to ~18 rad for the prior's speeds, too fast for a shared grid: the pixel's phase step
``φ`` is found first (``Ms + A·exp(−(m/m_e)²)·e^{imφ}`` over :data:`PHASE_STEPS` steps and the
envelopes :data:`ENVELOPES_LAGS`, refined by a parabola); the flow model then uses ``e^{imφ}`` and
only the candidates whose own Doppler step ``∓q·v·cosθ·Δt`` equals ``φ`` modulo 2π (any alias)
within half the step between neighbouring ``|cos θ|`` (at least :data:`PHASE_TOLERANCE_RAD`).

**The class** is the model of the lowest Bayesian information criterion ``n·ln(RSS/n) + p·ln n``
(``n = 2·C·L`` real values; ``p = 2C + 1`` for diffusion and ballistic motion, ``2C + 3`` for flow:
speed, polar angle and the phase step, :data:`FLOW_EXTRA_PARAMETERS`), against a null model
``ĝ1 = Ms`` (``p = C``: no moving term, or one decorrelated within a frame). **Its magnitude** is
the fitted D (µm²/s) or v (µm/s), to the grid's 1/20 dex.

**Indeterminate** (the analogue of :mod:`classifier.rule`, with the prior's ``ε``): a pixel is left
undecided when its input is not finite; when the chosen model has no moving term (``Mf = 0`` at
every configuration) or does not beat the null model; or when the fitted curve lies in a regime
where the field cannot tell the motion types apart: it does not decorrelate over the acquisition
(``|g1_fit(T)|² ≥ 1 − ε`` at every configuration, ``T`` the first-to-last frame delay) or it
decorrelates completely within one frame interval (``|g1_fit(Δt)|² ≤ ε`` at every configuration):
the ground truth's criteria (:func:`classifier.truth.identifiability`) on the fitted curve, with
``|g1|²`` for ``ρ_I`` (the field carries no transit term ``j/N_eff``, which the signature network
reads from the intensity; the ground truth counts pixels whose phase is lost in a frame but whose
transit is visible as identifiable, so those count against the fit's coverage).

**Lags** (:data:`DEFAULT_LAGS`): the signature's linear-intensity lags 1, 2, 3, 4, 6, 8, 11, 16, 22,
28, log-spaced like the prior's magnitudes, so every decade of decorrelation time gets a few
points. On the validation split (45 draws, seed 0; balanced accuracy on identifiable pixels at
pool 1 / pool 25) they beat every lag 1-8 (0.45 / 0.70), 1-16 (0.46 / 0.79) and 1-29 (0.43 / 0.85)
with 0.54 / 0.88: the estimator ĝ1 of a single 32-frame pixel is biased at long lags (few pairs; a
slowly varying speckle stays coherent within them), and its lags are strongly correlated.

``python -m research.g1fit --out PATH.json`` compares the fit with the shipped ``signature``
network on the very test pixels of its report (:func:`evaluate_against_network`). The module stays
whole (over 600 lines): the comparison is the fit's only caller and reads its grid and outcome codes.

Kept whole (over 800 lines): the fit, its evaluation against the network and its report are one
experiment, run by :func:`main`; it is research code, outside the installed packages.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from types import SimpleNamespace
from typing import Any

import numpy as np

from classifier.report import bootstrap_draws

__all__ = [
    "GRID_PER_DECADE",
    "DEFAULT_LAGS",
    "FLOW_EXTRA_PARAMETERS",
    "REASONS",
    "G1Fit",
    "fit_g1",
    "g1_columns",
    "complex_g1",
    "superset_spec",
    "evaluate_against_network",
    "format_markdown",
    "main",
]

#: Candidate magnitudes per decade (log grid step 1/20 dex).
GRID_PER_DECADE = 20
#: |cos θ| values of the flow grid (uniform in [0, 1]).
COS_POLAR_STEPS = 11
#: Phase steps per frame tried by the flow phase search (uniform in (−π, π]).
PHASE_STEPS = 256
#: Envelopes ``exp(−(m/m_e)²)`` of the phase search (lags; ``inf`` = flat).
ENVELOPES_LAGS = (2.0, 6.0, 20.0, math.inf)
#: Smallest accepted mismatch (rad per frame) between a flow candidate's Doppler step and the pixel's.
PHASE_TOLERANCE_RAD = 2 * 2 * math.pi / PHASE_STEPS
#: Nonlinear parameters flow has beyond the others' one magnitude (the BIC's count): the polar angle and
#: the pixel's phase step.
FLOW_EXTRA_PARAMETERS = 2
#: Default lags (frames): the signature's linear-intensity lags, log-spaced (module docstring).
DEFAULT_LAGS = (1, 2, 3, 4, 6, 8, 11, 16, 22, 28)
#: Outcome of every pixel.
REASONS = ("decided", "invalid input", "no moving term", "static", "decorrelated")
_MOTIONS = ("diffusion", "ballistic", "flow")
_CHUNK = 512


@dataclass
class G1Fit:
    """Result of :func:`fit_g1` for ``N`` pixels (``C`` configurations).

    ``label [N]``: 0 diffusion, 1 ballistic, 2 flow, 3 indeterminate (the classifier's class order);
    ``reason [N]`` indexes :data:`REASONS`; ``model [N]``: the model of the lowest BIC (also for
    undecided pixels; −1 for invalid input); ``magnitude [N]``: its D (µm²/s) or v (µm/s), NaN for
    invalid input; ``magnitude_by_model [N, 3]``: the best magnitude under each model;
    ``polar_angle_deg [N]``: flow's fitted angle from the depth axis; ``static, moving [N, C]``: the
    amplitudes ``Ms``, ``Mf`` of the chosen model; ``rss, bic [N, 3]`` per model;
    ``phase_step_rad [N]``: the pixel's fitted Doppler phase step per frame.
    """

    label: np.ndarray
    reason: np.ndarray
    model: np.ndarray
    magnitude: np.ndarray
    magnitude_by_model: np.ndarray
    polar_angle_deg: np.ndarray
    static: np.ndarray
    moving: np.ndarray
    rss: np.ndarray
    bic: np.ndarray
    phase_step_rad: np.ndarray

    def one_hot(self) -> np.ndarray:
        """``[N, 4]`` probabilities (1 for the decision) for :func:`classifier.report.evaluate`."""
        return np.eye(4)[self.label]


# ----------------------------------------------------------------------------------------------------------
# candidate tables
# ----------------------------------------------------------------------------------------------------------
def _log_grid(lo: float, hi: float) -> np.ndarray:
    """Points ``10^(k/GRID_PER_DECADE)`` from a decade below ``lo`` to a decade above ``hi``."""
    a = math.floor(math.log10(lo / 10.0) * GRID_PER_DECADE + 1e-9)
    b = math.ceil(math.log10(hi * 10.0) * GRID_PER_DECADE - 1e-9)
    return 10.0 ** (np.arange(a, b + 1) / GRID_PER_DECADE)


@lru_cache(maxsize=8)
def _tables(
    configs: tuple, lags: tuple, dt: float, n_frames: int, n: float, laws: tuple, d_range: tuple, v_range: tuple
) -> dict[str, Any]:
    """Candidate curves of the three models: real ``g [K, C, L]`` (flow: the transit decay only),
    ``|g1|`` at Δt and at T ``[K, C]``, magnitudes ``[K]`` and, for flow, ``|cos θ|`` and the Doppler
    step ``q·v·|cos θ|·Δt`` (rad)."""
    from torchdoct.sim import theory

    tau = np.asarray(lags, np.float64) * dt
    ends = np.array([dt, (n_frames - 1) * dt])
    out: dict[str, Any] = {}
    for name in _MOTIONS:
        mag = _log_grid(*(d_range if name == "diffusion" else v_range))
        cos = np.zeros(1)
        law = np.zeros(mag.size, np.int64)
        if name == "flow":
            c = np.linspace(0.0, 1.0, COS_POLAR_STEPS)
            mag, cos = np.repeat(mag, c.size), np.tile(c, mag.size)
            law = np.zeros(mag.size, np.int64)
        elif name == "ballistic":  # one candidate set per direction law of the prior
            law = np.repeat(np.arange(len(laws)), mag.size)
            mag = np.tile(mag, len(laws))
        curves, first, last = [], [], []
        for wl, lat, ax in configs:
            kw = dict(wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax, refractive_index=n)
            t = np.concatenate([tau, ends])[None, :]
            if name == "diffusion":
                g = theory.g1_diffusion(t, diffusion_um2_per_s=mag[:, None], **kw)
            elif name == "ballistic":
                g = np.concatenate(
                    [
                        theory.g1_ballistic(t, speed_um_per_s=mag[law == i, None], directions=d, **kw)
                        for i, d in enumerate(laws)
                    ]
                )
            else:
                g = np.abs(
                    theory.g1_flow(
                        t, speed_um_per_s=mag[:, None], polar_angle_deg=np.degrees(np.arccos(cos))[:, None], **kw
                    )
                )
            curves.append(g[:, :-2])
            first.append(np.abs(g[:, -2]))
            last.append(np.abs(g[:, -1]))
        g = np.stack(curves, axis=1)
        w = np.asarray([n_frames - m for m in lags], np.float64)
        keep = ((g * g) @ w).min(axis=1) > 1e-12 * w.sum()  # a curve that is 0 at every lag explains nothing
        q = 2.0 * (2.0 * math.pi * n / configs[0][0])
        out[name] = {
            "g": g[keep],
            "first": np.stack(first, 1)[keep],
            "last": np.stack(last, 1)[keep],
            "magnitude": mag[keep],
            "cos": cos[keep] if name == "flow" else None,
            "law": law[keep],
            "step": (q * mag * cos * dt)[keep] if name == "flow" else None,
            # half the Doppler-step spacing of neighbouring |cos θ| at the same speed (rad per frame)
            "tol": np.maximum(0.5 * q * mag * dt / (COS_POLAR_STEPS - 1), PHASE_TOLERANCE_RAD)[keep]
            if name == "flow"
            else None,
        }
    return out


# ----------------------------------------------------------------------------------------------------------
# the fit
# ----------------------------------------------------------------------------------------------------------
def _nnls2(b1, b2, a11, a12, a22):
    """Reduction of the residual ``R = S_yy − RSS`` of ``y ≈ Ms + Mf·g`` with ``Ms, Mf ≥ 0`` (normal
    equations ``[[a11, a12], [a12, a22]]·[Ms, Mf] = [b1, b2]``; every argument broadcasts), with
    ``Ms`` and ``Mf``."""
    det = a11 * a22 - a12 * a12
    ok = det > 1e-9 * a11 * a22
    sdet = np.where(ok, det, 1.0)
    ms = (a22 * b1 - a12 * b2) / sdet
    mf = (a11 * b2 - a12 * b1) / sdet
    inner = ok & (ms >= 0) & (mf >= 0)
    r_in = ms * b1 + mf * b2
    b1p, b2p = np.maximum(b1, 0.0), np.maximum(b2, 0.0)
    r_s = b1p * b1p / a11  # Mf = 0
    r_f = b2p * b2p / a22  # Ms = 0
    face = r_f > r_s
    r = np.where(inner, r_in, np.where(face, r_f, r_s))
    ms_out = np.where(inner, ms, np.where(face, 0.0, b1p / a11))
    mf_out = np.where(inner, mf, np.where(face, b2p / a22, 0.0))
    return r, ms_out, mf_out


def _reduction(b1, b2, a11, a12, a22):
    """``R`` of :func:`_nnls2` only, in few passes (the candidate search): the interior optimum where
    it is feasible (then it beats both faces), else the better face."""
    inv_a22 = 1.0 / a22
    det = a11 * a22 - a12 * a12
    inv_det = np.where(det > 1e-9 * a11 * a22, 1.0 / np.where(det > 0, det, 1.0), 0.0).astype(b2.dtype)
    t1 = a22 * b1 - a12 * b2  # ∝ Ms of the interior solution
    t2 = a11 * b2
    t2 -= a12 * b1  # ∝ Mf
    r_in = t1 * b1
    r_in += t2 * b2
    r_in *= inv_det
    np.minimum(t1, t2, out=t1)
    r_in[t1 < 0] = 0.0
    face = np.maximum(b2, 0.0)
    face *= face
    face *= inv_a22
    np.maximum(r_in, face, out=r_in)
    b1p = np.maximum(b1, 0.0)
    np.maximum(r_in, (b1p * b1p / a11).astype(b2.dtype), out=r_in)
    return r_in


def _phase_search(y: np.ndarray, w: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Doppler phase step per frame ``φ [N]`` (rad, (−π, π]) of ``y [N, C, L]``: the best
    ``Ms + A·r_m·e^{imφ}`` (module docstring) over the phase grid and envelopes, refined by a parabola."""
    n, c, L = y.shape
    phis = -math.pi + 2.0 * math.pi * (np.arange(PHASE_STEPS) + 1) / PHASE_STEPS
    env = np.stack([np.exp(-((lags / m) ** 2)) if math.isfinite(m) else np.ones(L) for m in ENVELOPES_LAGS])  # [E, L]
    rot = np.exp(-1j * lags[:, None] * phis[None, :])  # [L, J]
    kern = (w * env)[:, :, None] * rot[None]  # [E, L, J]
    a11 = w.sum()
    a12 = (kern.real).sum(axis=1)  # Σ w r cos(mφ) [E, J]
    a22 = ((w * env * env).sum(axis=1))[:, None]  # [E, 1]
    yr = y.reshape(n * c, L).astype(np.complex64)
    b1 = (yr.real @ w.astype(np.float32)).reshape(n, c, 1, 1)
    kr = kern.transpose(1, 0, 2).reshape(L, -1).astype(np.complex64)
    b2 = (yr.real @ kr.real - yr.imag @ kr.imag).reshape(n, c, *a12.shape)
    r = _reduction(b1, b2, np.float32(a11), a12[None, None].astype(np.float32), a22[None, None].astype(np.float32))
    crit = r.sum(axis=1, dtype=np.float64)  # [N, E, J]
    flat = crit.reshape(n, -1).argmax(axis=1)
    e, j = np.divmod(flat, PHASE_STEPS)
    rows = np.arange(n)
    c0 = crit[rows, e, j]
    cm = crit[rows, e, (j - 1) % PHASE_STEPS]
    cp = crit[rows, e, (j + 1) % PHASE_STEPS]
    den = cm - 2.0 * c0 + cp
    shift = np.where(den < 0, 0.5 * (cm - cp) / np.where(den < 0, den, -1.0), 0.0)
    phi = phis[j] + np.clip(shift, -0.5, 0.5) * (2.0 * math.pi / PHASE_STEPS)
    return np.where(phi > math.pi, phi - 2.0 * math.pi, np.where(phi <= -math.pi, phi + 2.0 * math.pi, phi))


def _wrap(x: np.ndarray) -> np.ndarray:
    return np.abs(np.remainder(x + math.pi, 2.0 * math.pi) - math.pi)


def _fit_chunk(y: np.ndarray, tab: dict, w: np.ndarray, lags: np.ndarray, use_phase: bool) -> dict[str, np.ndarray]:
    n, c, L = y.shape
    a11 = w.sum()
    if not use_phase:  # |ĝ1| against |g1|: flow's Doppler term and the pixel's phase drift both dropped
        y = np.abs(y).astype(np.complex128)
    b1 = (y.real @ w)[:, None, :]  # [N, 1, C]
    syy = ((y.real**2 + y.imag**2) @ w).sum(axis=1)  # [N]
    phi = _phase_search(y, w, lags) if use_phase else np.zeros(n)
    b1p = np.maximum(b1[:, 0], 0.0)
    res: dict[str, np.ndarray] = {"syy": syy, "phi": phi, "rss0": np.maximum(syy - (b1p * b1p / a11).sum(axis=1), 0.0)}
    for name in _MOTIONS:
        t = tab[name]
        g = t["g"]  # [K, C, L]
        a22 = (g * g) @ w  # [K, C]
        if name == "flow":  # the pixel's phase ramp; amplitudes against e^{imφ}·decay
            rot = np.exp(-1j * phi[:, None] * lags[None, :])  # [N, L]
            u = (y * rot[:, None, :]).real
            cw = np.cos(phi[:, None] * lags[None, :]) * w  # [N, L]
            b2 = np.stack([u[:, k] * w @ g[:, k].T for k in range(c)], axis=-1)  # [N, K, C]
            a12 = np.stack([cw @ g[:, k].T for k in range(c)], axis=-1)
        else:
            b2 = np.stack([y.real[:, k] * w @ g[:, k].T for k in range(c)], axis=-1)
            a12 = ((g * w).sum(axis=2))[None]  # [1, K, C]
        # candidate search in float32 (R of every candidate), the chosen one again in float64 below
        r = _reduction(b1, b2, a11, a12, a22[None])
        tot = r.sum(axis=2, dtype=np.float64)  # [N, K]
        sign = None
        if name == "flow" and use_phase:  # candidates whose Doppler step agrees with φ (either direction, mod 2π)
            tol = t["tol"]
            deeper = _wrap(phi[:, None] + t["step"][None, :])  # θ < 90°: g1 ∝ e^{−i q v_z τ}
            higher = _wrap(phi[:, None] - t["step"][None, :])
            tot = np.where(np.minimum(deeper, higher) <= tol[None, :], tot, -np.inf)
            sign = deeper <= higher
        elif name == "flow":
            sign = np.ones(tot.shape, bool)
        k = tot.argmax(axis=1)
        rows = np.arange(n)
        rk, ms, mf = _nnls2(b1[:, 0], b2[rows, k], a11, a12[0 if a12.shape[0] == 1 else rows, k], a22[k])
        res[name] = {
            "k": k,
            "rss": np.maximum(syy - rk.sum(axis=1), 0.0),
            "ms": ms,
            "mf": mf,
            "deeper": None if sign is None else sign[rows, k],
        }
    return res


def fit_g1(
    y: np.ndarray,
    configurations: Sequence[tuple[float, float, float]],
    lags: Sequence[int],
    *,
    frame_interval_s: float,
    n_frames: int,
    refractive_index: float = 1.0,
    ballistic_directions: str = "both",
    diffusion_range_um2_per_s: tuple[float, float] = (1e-4, 15.0),
    speed_range_um_per_s: tuple[float, float] = (1e-3, 6.0),
    epsilon: float = 0.05,
    use_phase: bool = True,
) -> G1Fit:
    """Fit every pixel of ``y [N, C, L]`` (complex ĝ1 at ``lags`` of the ``C`` configurations
    ``(wavelength_um, lateral_resolution_um, axial_resolution_um)``; module docstring).

    ``frame_interval_s`` Δt (s) and ``n_frames`` T of the protocol; ``refractive_index`` n (phase
    ``2·k·n·z``); the ranges are the prior's (the grid extends a decade beyond each end); ``epsilon``
    the identifiability threshold of the indeterminate outcome. Pixels with a non-finite value are
    undecided (reason ``"invalid input"``).
    """
    y = np.asarray(y)
    lags_t = tuple(int(m) for m in lags)
    confs = tuple((float(a), float(b), float(c)) for a, b, c in configurations)
    if y.ndim != 3 or y.shape[1:] != (len(confs), len(lags_t)):
        raise ValueError(f"y must be [N, {len(confs)} configurations, {len(lags_t)} lags]; got shape {y.shape}")
    if not lags_t or min(lags_t) < 1 or max(lags_t) > n_frames - 1 or len(set(lags_t)) != len(lags_t):
        raise ValueError(f"lags must be distinct integers in [1, n_frames - 1 = {n_frames - 1}]; got {list(lags_t)}")
    if len({round(w, 9) for w, _, _ in confs}) != 1:
        raise ValueError(
            "the configurations must share one wavelength (one Doppler step per pixel); got "
            f"{sorted({w for w, _, _ in confs})} µm"
        )
    laws = ("isotropic", "uniform-angles") if ballistic_directions == "both" else (ballistic_directions,)
    if not set(laws) <= {"isotropic", "uniform-angles"}:
        raise ValueError(
            f"ballistic_directions must be 'isotropic', 'uniform-angles' or 'both'; got {ballistic_directions!r}"
        )
    tab = _tables(
        confs,
        lags_t,
        float(frame_interval_s),
        int(n_frames),
        float(refractive_index),
        laws,
        tuple(diffusion_range_um2_per_s),
        tuple(speed_range_um_per_s),
    )
    n, c, L = y.shape
    valid = np.isfinite(y.real).all(axis=(1, 2)) & np.isfinite(y.imag).all(axis=(1, 2))
    yc = np.where(valid[:, None, None], y, 0.0).astype(np.complex128)
    lags_a = np.asarray(lags_t, np.float64)
    w = (n_frames - lags_a) / (n_frames - lags_a).mean()
    n_obs = 2 * c * L
    params = np.array([2 * c + 1, 2 * c + 1, 2 * c + 1 + FLOW_EXTRA_PARAMETERS], np.float64)
    out = {k: [] for k in ("k", "rss", "ms", "mf", "deeper", "phi", "rss0", "syy")}
    for s in range(0, n, _CHUNK):
        r = _fit_chunk(yc[s : s + _CHUNK], tab, w, lags_a, use_phase)
        out["phi"].append(r["phi"])
        out["rss0"].append(r["rss0"])
        out["syy"].append(r["syy"])
        for key in ("k", "rss", "ms", "mf"):
            out[key].append(np.stack([r[m][key] for m in _MOTIONS], axis=1))  # [n, 3(, C)]
        out["deeper"].append(r["flow"]["deeper"])
    cat = {k: (np.concatenate(v) if v else np.zeros((0,))) for k, v in out.items()}
    if n == 0:
        e = np.zeros(0)
        return G1Fit(
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            e,
            np.zeros((0, 3)),
            e,
            np.zeros((0, c)),
            np.zeros((0, c)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            e,
        )
    rss = cat["rss"]
    floor = 1e-12 * cat["syy"] + 1e-300  # residuals below this are rounding: a perfect fit of any model
    ratio = np.maximum(rss, floor[:, None]) / np.maximum(cat["rss0"], floor)[:, None]
    bic = n_obs * np.log(ratio) + params * math.log(n_obs)
    bic0 = c * math.log(n_obs)  # the null model: static term only (no moving term, or one decorrelated at lag 1)
    model = bic.argmin(axis=1)
    rows = np.arange(n)
    kk = cat["k"]
    mags = np.stack([tab[m]["magnitude"][kk[:, i]] for i, m in enumerate(_MOTIONS)], axis=1)
    first = np.stack([tab[m]["first"][kk[:, i]] for i, m in enumerate(_MOTIONS)], axis=1)  # [N, 3, C]
    last = np.stack([tab[m]["last"][kk[:, i]] for i, m in enumerate(_MOTIONS)], axis=1)
    ms, mf = cat["ms"][rows, model], cat["mf"][rows, model]
    reason = np.zeros(n, np.int64)
    f1, fT = first[rows, model], last[rows, model]
    reason[np.all(f1 * f1 <= epsilon, axis=1)] = 4
    reason[np.all(fT * fT >= 1.0 - epsilon, axis=1)] = 3
    reason[np.all(mf <= 0.0, axis=1) | (bic[rows, model] >= bic0)] = 2
    reason[~valid] = 1
    label = np.where(reason == 0, model, 3)
    cosf = tab["flow"]["cos"][kk[:, 2]]
    polar = np.degrees(np.arccos(np.where(cat["deeper"], cosf, -cosf)))
    mag = mags[rows, model]
    nanv = np.where(valid, 1.0, np.nan)
    return G1Fit(
        label=label.astype(np.int64),
        reason=reason,
        model=np.where(valid, model, -1).astype(np.int64),
        magnitude=mag * nanv,
        magnitude_by_model=mags * nanv[:, None],
        polar_angle_deg=polar * nanv,
        static=ms * nanv[:, None],
        moving=mf * nanv[:, None],
        rss=rss * nanv[:, None],
        bic=bic * nanv[:, None],
        phase_step_rad=cat["phi"] * nanv,
    )


# ----------------------------------------------------------------------------------------------------------
# the comparison with the network on the test pixels of its report
# ----------------------------------------------------------------------------------------------------------
def superset_spec(spec, lags: Sequence[int]):
    """``spec`` (a signature spec) with ``g1_m`` and ``g1_phase_m`` at ``lags`` appended to its metrics
    (the same configurations and protocol, hence the same simulated pixels)."""
    from classifier.features import spec_from_dict

    d = spec.to_dict()
    extra = [f"{k}_{m}" for k in ("g1", "g1_phase") for m in lags]
    d["metrics"] = list(spec.metrics) + [e for e in extra if e not in spec.metrics]
    d["name"] = f"{spec.name}-g1fit"
    d["description"] = f"{spec.description}; plus g1 and g1_phase at lags {min(lags)}-{max(lags)}"
    return spec_from_dict(d)


def g1_columns(feature_names: Sequence[str], spec, lags: Sequence[int]) -> tuple[list[int], list[int]]:
    """Column indices of ``g1_m@conf`` and ``g1_phase_m@conf`` in configuration-major, lag-minor order."""
    index = {n: i for i, n in enumerate(feature_names)}
    try:
        mag = [index[f"g1_{m}@{c.name}"] for c in spec.configurations for m in lags]
        ph = [index[f"g1_phase_{m}@{c.name}"] for c in spec.configurations for m in lags]
    except KeyError as err:
        raise ValueError(f"the features lack {err.args[0]!r}: build the data with superset_spec") from None
    return mag, ph


def complex_g1(x: np.ndarray, mag_cols: Sequence[int], phase_cols: Sequence[int], n_conf: int) -> np.ndarray:
    """``ĝ1 = g1_m·exp(i·g1_phase_m)`` ``[N, C, L]`` from feature rows."""
    y = x[:, mag_cols].astype(np.float64) * np.exp(1j * x[:, phase_cols].astype(np.float64))
    return y.reshape(len(x), n_conf, -1)


def _fit_kwargs(spec, prior, lags) -> dict[str, Any]:
    return dict(
        configurations=[(c.wavelength_um, c.lateral_resolution_um, c.axial_resolution_um) for c in spec.configurations],
        lags=tuple(lags),
        frame_interval_s=spec.frame_interval_s,
        n_frames=spec.n_frames,
        refractive_index=spec.refractive_index,
        ballistic_directions=prior.ballistic_directions,
        diffusion_range_um2_per_s=prior.diffusion_um2_per_s,
        speed_range_um_per_s=prior.speed_um_per_s,
        epsilon=prior.identifiability_epsilon,
    )


def _magnitude_errors(est_log10: np.ndarray, s: dict[str, np.ndarray], decided_correct: np.ndarray) -> dict:
    """Median |log10 error| on identifiable samples: (a) decided with the true class, (b) every
    identifiable sample with the true class's estimate (the training report's definition)."""
    from classifier.prior import CLASSES

    ident = s["status"] == 0
    rows = np.arange(len(s["y"]))
    err = np.abs(est_log10[rows, s["y"]] - np.log10(s["magnitude"]))
    out: dict[str, Any] = {}
    for key, m in (("decided_correct", ident & decided_correct), ("identifiable_true_class", ident)):
        e = err[m & np.isfinite(err)]
        out[key] = {
            "samples": int(e.size),
            "median_abs_log10_error": float(np.median(e)) if e.size else math.nan,
            "by_class": {
                CLASSES[c]: float(np.median(err[m & (s["y"] == c) & np.isfinite(err)]))
                if np.any(m & (s["y"] == c) & np.isfinite(err))
                else math.nan
                for c in range(len(CLASSES))
            },
        }
    return out


def _abs_log10_error(est_log10: np.ndarray, s: dict[str, np.ndarray]) -> np.ndarray:
    """|log10 estimate − log10 truth| of the true class's estimate, per sample."""
    return np.abs(est_log10[np.arange(len(s["y"])), s["y"]] - np.log10(s["magnitude"]))


def _headline(pred: np.ndarray, y: np.ndarray, status: np.ndarray, err: np.ndarray) -> dict[str, float]:
    """Balanced accuracy and coverage on identifiable samples (:func:`classifier.report.evaluate`'s
    definitions) and the median magnitude error (a), from decisions: the bootstrap's fast path."""
    ident = status == 0
    dec = ident & (pred != 3)
    rec = [float((pred[dec & (y == c)] == c).mean()) for c in range(3) if np.any(dec & (y == c))]
    ok = dec & (pred == y) & np.isfinite(err)
    return {
        "balanced_accuracy_identifiable": float(np.mean(rec)) if rec else math.nan,
        "coverage_identifiable": float(dec.sum() / max(ident.sum(), 1)),
        "median_abs_log10_error": float(np.median(err[ok])) if ok.any() else math.nan,
    }


def _timed(fn, *args, repeats: int = 2) -> tuple[Any, float]:
    import time

    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return out, best


def evaluate_against_network(
    model: str = "signature",
    *,
    draws: int | None = None,
    lags: Sequence[int] | None = None,
    cache_dir=None,
    timing_pixels: int = 4096,
    log=print,
) -> dict[str, Any]:
    """The fit and the shipped network on the same test pixels (pool 1 and 25, with and without a
    random bulk phase per frame): balanced accuracy, coverage, accuracy, confusion, magnitude error,
    µs per pixel (one thread). ``draws``: test draws (default the model's, which reproduces the
    pixels of its report); ``lags`` default :data:`DEFAULT_LAGS` (those ≤ T − 3)."""
    from threadpoolctl import threadpool_limits

    from classifier.dataset import make_dataset
    from classifier.infer import load_model
    from classifier.prior import Prior
    from classifier.report import evaluate
    from classifier.rule import apply_rule
    from classifier.train import CLASS_NAMES, eval_samples

    say = log or (lambda *a, **k: None)
    net = load_model(model, threads=1)
    spec = net.spec
    if not spec.is_signature or "train_config" not in net.metadata or "prior" not in net.metadata:
        raise ValueError(
            f"model {net.path.name}: the comparison needs a signature model written by doct-train "
            f"(spec {spec.name!r} reads {', '.join(spec.metrics)}); use --model signature"
        )
    prior = Prior.from_dict(net.metadata["prior"])
    tc = net.metadata["train_config"]
    cfg = SimpleNamespace(
        **{
            k: tc[k]
            for k in ("seed", "draws_test", "trials_per_draw", "replicates", "truncation_tolerance", "eval_pools")
        }
    )
    rule = net.rule
    lags = tuple(lags or (m for m in DEFAULT_LAGS if m <= spec.n_frames - 3))
    n_draws = int(draws or cfg.draws_test)
    sup = superset_spec(spec, lags)
    kw = _fit_kwargs(spec, prior, lags)
    names = sup.feature_names
    net_cols = [names.index(n) for n in spec.feature_names]
    mag_cols, ph_cols = g1_columns(names, sup, lags)
    n_conf = len(spec.configurations)
    report: dict[str, Any] = {
        "model": str(net.path.name),
        "spec": spec.name,
        "configurations": [c.describe() for c in spec.configurations],
        "seed": cfg.seed,
        "draws_test": n_draws,
        "trials_per_draw": cfg.trials_per_draw,
        "replicates": cfg.replicates,
        "truncation_tolerance": cfg.truncation_tolerance,
        "prior": prior.to_dict(),
        "lags": list(lags),
        "rule": rule["definition"],
        "fit": {
            "grid_per_decade": GRID_PER_DECADE,
            "cos_polar_steps": COS_POLAR_STEPS,
            "phase_steps": PHASE_STEPS,
            "envelopes_lags": [m if math.isfinite(m) else "flat" for m in ENVELOPES_LAGS],
            "selection": f"lowest BIC n ln(RSS/n) + p ln n, n = 2 C L, p = 2C+1 (diffusion, ballistic), "
            f"2C+{1 + FLOW_EXTRA_PARAMETERS} (flow: speed, polar angle, phase step), against the null "
            "model g1 = Ms (p = C)",
            "indeterminate": "non-finite input; no moving term (Mf = 0 at every configuration, or the null model "
            "wins); |g1_fit(T)|^2 >= 1 - eps at every configuration (static); |g1_fit(dt)|^2 <= eps "
            "at every configuration (decorrelated)",
        },
        "network_reads_field": bool(spec.needs_field),
        "sets": {},
    }
    for bulk in (False, True):
        label = "random bulk phase per frame" if bulk else "phase-stable"
        ds = make_dataset(
            sup,
            prior,
            seed=cfg.seed,
            split="test",
            draws=n_draws,
            trials_per_draw=cfg.trials_per_draw,
            replicates=cfg.replicates,
            truncation_tolerance=cfg.truncation_tolerance,
            truncation=cfg.truncation,
            cache_dir=cache_dir,
            bulk_phase=bulk,
        )
        src = "cache" if ds.meta["from_cache"] else "simulated"
        say(f"{label}: {len(ds)} test pixels from {n_draws} draws ({src})")
        y = complex_g1(ds.x, mag_cols, ph_cols, n_conf)
        joint = dataclasses.replace(
            ds,
            x=np.concatenate([ds.x[:, net_cols], y.real.reshape(len(ds), -1), y.imag.reshape(len(ds), -1)], axis=1),
            x_ref=None,
        )
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(9,)))  # the report's pools
        pools = {}
        for n in cfg.eval_pools:
            s = eval_samples(joint, n, rng)
            if str(n) in ("1", "25"):
                pools[str(n)] = s
        out: dict[str, Any] = {}
        f = len(net_cols)
        cl = n_conf * len(lags)
        for pool, s in pools.items():
            x_net = np.concatenate([s["x"][:, :f], s["x"][:, -1:]], axis=1).astype(np.float32)
            yy = (s["x"][:, f : f + cl] + 1j * s["x"][:, f + cl : f + 2 * cl]).reshape(-1, n_conf, len(lags))
            p_net = net.predict(x_net)
            mu, _ = net.predict_magnitude(x_net)
            with threadpool_limits(1):
                fit = fit_g1(yy, **kw)
            m_net = evaluate(p_net, s["y"], s["status"], CLASS_NAMES, rule)
            m_fit = evaluate(fit.one_hot(), s["y"], s["status"], CLASS_NAMES, rule)
            dec_net, _ = apply_rule(p_net, CLASS_NAMES, rule)  # the rule's decision
            with np.errstate(divide="ignore", invalid="ignore"):
                fit_log = np.log10(fit.magnitude_by_model)
            row = {"samples": int(len(s["y"])), "identifiable": int((s["status"] == 0).sum())}
            for name, m, est, dec in (
                ("network", m_net, mu.astype(np.float64), dec_net),
                ("g1 fit", m_fit, fit_log, fit.label),
            ):
                row[name] = {
                    k: m[k]
                    for k in (
                        "balanced_accuracy_identifiable",
                        "coverage_identifiable",
                        "accuracy_identifiable",
                        "strict_accuracy_identifiable",
                        "accuracy_all",
                        "balanced_accuracy_all",
                        "recall_identifiable",
                        "confusion",
                    )
                }
                row[name]["magnitude"] = _magnitude_errors(est, s, dec == s["y"])
            row["g1 fit"]["reasons"] = {r: int((fit.reason == i).sum()) for i, r in enumerate(REASONS)}
            if pool == "1" and not bulk:
                if n_draws == cfg.draws_test:
                    ref = net.metadata.get("test_summary_by_pool", {}).get("1", {})
                    row["network"]["matches_model_report"] = {
                        k: (ref.get(k), m_net[k]) for k in ("balanced_accuracy_identifiable", "coverage_identifiable")
                    }
                sub = slice(0, min(timing_pixels, len(yy)))
                with threadpool_limits(1):
                    _, t_fit = _timed(lambda: fit_g1(yy[sub], **kw))
                _, t_net = _timed(lambda: net.predict(x_net[sub]), repeats=5)
                n_t = len(yy[sub])
                row["us_per_pixel"] = {"network": t_net / n_t * 1e6, "g1 fit": t_fit / n_t * 1e6, "pixels": n_t}
            if not bulk:
                err_net = _abs_log10_error(mu.astype(np.float64), s)
                err_fit = _abs_log10_error(fit_log, s)

                def diffs(ix):
                    y_, st_ = s["y"][ix], s["status"][ix]
                    a, b = _headline(dec_net[ix], y_, st_, err_net[ix]), _headline(fit.label[ix], y_, st_, err_fit[ix])
                    return {k: a[k] - b[k] for k in a}

                row["difference_se"] = bootstrap_draws(diffs, s["draw"], seed=cfg.seed)  # paired: one resample, both
            out[pool] = row
            say(
                f"  pool {pool}: network bal. acc. {m_net['balanced_accuracy_identifiable']:.3f} coverage "
                f"{m_net['coverage_identifiable']:.3f}; g1 fit {m_fit['balanced_accuracy_identifiable']:.3f} / "
                f"{m_fit['coverage_identifiable']:.3f}"
            )
        report["sets"][label] = out
    return report


def _f(v: Any, digits: int = 3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def format_markdown(r: dict[str, Any]) -> str:
    """The comparison as Markdown: the tables of the JSON and how much the network beats the fit by."""
    L = ["# The signature network against a per-pixel least-squares g1 fit (DLS-OCT baseline)", ""]
    L.append(
        f"Model `{r['model']}` (spec `{r['spec']}`: {'; '.join(r['configurations'])}). Test split of its report: "
        f"seed {r['seed']}, {r['draws_test']} draws × {r['replicates']} (static fraction, SNR) replicates × "
        f"{r['trials_per_draw']} trials, PSF truncation {r['truncation_tolerance']}; the same pixels for both "
        "methods. The network reads its signature features; the fit reads the complex "
        f"ĝ1 = g1_m·exp(i·g1_phase_m) at lags {', '.join(map(str, r['lags']))} (frames) of every configuration "
        "(`research/g1fit.py`: closed forms of "
        "torchdoct.sim.theory, grid of "
        f"{r['fit']['grid_per_decade']} magnitudes per decade, {r['fit']['cos_polar_steps']} |cos θ| for flow; "
        f"class by {r['fit']['selection']}; indeterminate: {r['fit']['indeterminate']}).  "
    )
    L.append(
        "Identifiable = the ground truth of `classifier.truth.identifiability`; coverage = decided share of "
        "them; accuracy over the decided ones. Magnitude error: median |log10 error| of D (µm²/s) or v (µm/s), "
        "(a) on identifiable pixels decided with the true class, (b) on every identifiable pixel with the true "
        "class's estimate (the training report's definition)."
    )
    L.append("")
    for label, per in r["sets"].items():
        L += [f"## {label}", ""]
        if label != "phase-stable":
            L.append(
                "A uniform random phase per frame (bulk motion) scrambles every field sum G(m), hence ĝ1 and its "
                "phase: the fit has nothing left to fit. "
                + (
                    "The network reads intensity features only, which the bulk phase leaves unchanged: its "
                    "numbers are those of the phase-stable data."
                    if not r.get("network_reads_field")
                    else ""
                )
            )
            L.append("")
        L.append(
            "| pool | method | bal. acc. identifiable | coverage | acc. identifiable | strict acc. | acc. all "
            "| magnitude error (a) | (b) | (a) diffusion / ballistic / flow |"
        )
        L.append("|---:|---|---:|---:|---:|---:|---:|---:|---:|---|")
        for pool, row in per.items():
            for name in ("network", "g1 fit"):
                m = row[name]
                a, b = m["magnitude"]["decided_correct"], m["magnitude"]["identifiable_true_class"]
                L.append(
                    f"| {pool} | {name} | {_f(m['balanced_accuracy_identifiable'])} | "
                    f"{_f(m['coverage_identifiable'])} | {_f(m['accuracy_identifiable'])} | "
                    f"{_f(m['strict_accuracy_identifiable'])} | {_f(m['accuracy_all'])} | "
                    f"{_f(a['median_abs_log10_error'])} | {_f(b['median_abs_log10_error'])} | "
                    + " / ".join(_f(v) for v in a["by_class"].values())
                    + " |"
                )
        L.append("")
        for pool, row in per.items():
            fit = row["g1 fit"]
            L.append(
                f"Pool {pool}: {row['samples']} samples, {row['identifiable']} identifiable; the fit's outcomes: "
                + ", ".join(f"{k} {v}" for k, v in fit["reasons"].items())
                + ".  "
            )
            if "us_per_pixel" in row:
                t = row["us_per_pixel"]
                L.append(
                    f"Cost per pixel (one thread, {t['pixels']} pixels, features given): network "
                    f"{t['network']:.2f} µs, g1 fit {t['g1 fit']:.0f} µs "
                    f"({t['g1 fit'] / t['network']:.0f}×).  "
                )
            if "matches_model_report" in row["network"]:
                chk = row["network"]["matches_model_report"]
                L.append(
                    "Network against its own report on these pixels (balanced accuracy, coverage): "
                    + "; ".join(f"{k}: report {_f(v[0], 4)}, here {_f(v[1], 4)}" for k, v in chk.items())
                    + ".  "
                )
        L.append("")
        for pool, row in per.items():
            for name in ("network", "g1 fit"):
                cm = row[name]["confusion"]
                cls = ["diffusion", "ballistic", "flow", "indeterminate"]
                L.append(
                    f"Confusion, {name}, pool {pool} (rows truth, columns decision; {', '.join(cls)}): "
                    + "; ".join(f"{c}: {' '.join(str(v) for v in rr)}" for c, rr in zip(cls, cm))
                    + ".  "
                )
        L.append("")
    L += ["## By how much the network beats the fit", ""]
    L.append(
        "Differences network − fit on the same samples; SE = standard error from a paired bootstrap over test "
        "draws (phase-stable data). Magnitude error (a) compares different pixel sets (each method's own "
        "correctly decided ones), (b) the same identifiable pixels."
    )
    L.append("")
    for label, per in r["sets"].items():
        for pool, row in per.items():
            a, b = row["network"], row["g1 fit"]
            d_ba = a["balanced_accuracy_identifiable"] - b["balanced_accuracy_identifiable"]
            d_cov = a["coverage_identifiable"] - b["coverage_identifiable"]
            ea, eb = (m["magnitude"]["decided_correct"]["median_abs_log10_error"] for m in (a, b))
            fa, fb = (m["magnitude"]["identifiable_true_class"]["median_abs_log10_error"] for m in (a, b))
            se = row.get("difference_se", {})

            def sed(k: str) -> str:
                return f" (SE {se[k]:.3f})" if k in se and math.isfinite(se[k]) else ""

            better = [
                n
                for n, ok in (
                    ("balanced accuracy", d_ba > 0),
                    ("coverage", d_cov > 0),
                    ("magnitude error (a)", ea < eb),
                    ("magnitude error (b)", fa < fb),
                )
                if ok
            ]
            worse = [
                n
                for n in ("balanced accuracy", "coverage", "magnitude error (a)", "magnitude error (b)")
                if n not in better
            ]
            cost = (
                f"; cost per pixel {row['us_per_pixel']['g1 fit'] / row['us_per_pixel']['network']:.0f}× lower"
                if "us_per_pixel" in row
                else ""
            )
            L.append(
                f"- {label}, pool {pool}: balanced accuracy {d_ba:+.3f}{sed('balanced_accuracy_identifiable')}, "
                f"coverage {d_cov:+.3f}{sed('coverage_identifiable')}; magnitude error (a) {_f(ea)} against "
                f"{_f(eb)} ({ea - eb:+.3f} dex{sed('median_abs_log10_error')}), (b) {_f(fa)} against {_f(fb)} "
                f"({fa - fb:+.3f} dex){cost}. The network is better in "
                f"{', '.join(better) or 'nothing'}" + (f"; not in {', '.join(worse)}" if worse else "") + "."
            )
    L.append("")
    return "\n".join(L)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m research.g1fit --out PATH.json``: run :func:`evaluate_against_network`, write
    ``PATH.json`` and ``PATH.md`` (refuses to overwrite either)."""
    import argparse
    import json
    from pathlib import Path

    from torchdoct.files import atomic_write

    p = argparse.ArgumentParser(prog="python -m research.g1fit", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="JSON output file; the Markdown is written beside it (.md)")
    p.add_argument("--model", default="signature", help="shipped model name or .onnx path (default signature)")
    p.add_argument(
        "--draws",
        type=int,
        default=None,
        help="test draws (default: the model's, which reproduces the pixels of its report)",
    )
    p.add_argument(
        "--lags",
        default=None,
        help="fit lags in frames, comma-separated (default " + ",".join(map(str, DEFAULT_LAGS)) + ")",
    )
    p.add_argument("--cache", default=None, help="dataset cache directory (default ~/.cache/torchdoct/classifier)")
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.suffix != ".json":
        print(f"error: --out {out}: give a .json file name (the Markdown goes beside it)", flush=True)
        return 2
    md = out.with_suffix(".md")
    for path in (out, md):
        if path.exists():
            print(f"error: {path} exists; choose another --out (nothing was overwritten)", flush=True)
            return 2
    if args.draws is not None and args.draws < 1:
        print(f"error: --draws must be >= 1; got {args.draws}", flush=True)
        return 2
    lags = None
    if args.lags is not None:
        try:
            lags = tuple(int(v) for v in args.lags.split(","))
        except ValueError:
            print(f"error: --lags {args.lags!r}: give lags in frames, e.g. 1,2,4,8", flush=True)
            return 2
    try:
        res = evaluate_against_network(args.model, draws=args.draws, lags=lags, cache_dir=args.cache)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", flush=True)
        return 2
    atomic_write(out, lambda tmp: Path(tmp).write_text(json.dumps(res, indent=1), encoding="utf-8"))
    atomic_write(md, lambda tmp: Path(tmp).write_text(format_markdown(res), encoding="utf-8"))
    print(f"wrote {out} and {md}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

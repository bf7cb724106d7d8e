"""Closed-form ensemble statistics of the point model (physics.md §5, §1, §2.4).

Everything here is numpy/scipy in float64; there is no torch and no randomness. The functions give the
"ideal" (ensemble) values that the simulator and the DOCT metrics are tested against.

Conventions (see :mod:`torchdoct.conventions`, physics.md §5.1):

* lengths in µm, times in s, speeds in µm/s, diffusion coefficients in µm²/s;
* ``lateral_resolution_um`` is the 1/e² full width of the intensity PSF, ``axial_resolution_um`` its FWHM;
  both are turned into amplitude-PSF sigmas ``s_x``, ``s_z`` only by the conventions module;
* the round-trip phase of a scatterer at depth ``z`` is ``e^{+i·2·k·n·z}`` with ``k·n`` given by
  :func:`torchdoct.conventions.wavenumber_per_um`, so for a displacement ``Δ`` over the lag ``τ``

      g1(τ) = E_Δ[ exp(−i·2kn·Δz − (Δx²+Δy²)/(4 s_x²) − Δz²/(4 s_z²)) ]        (physics.md §5.3)
      j(τ)  = E_Δ[ exp(−(Δx²+Δy²)/(2 s_x²) − Δz²/(2 s_z²)) ]                   (physics.md §5.4)

  and flow moving deeper (``polar_angle_deg = 0``) gives ``g1 ∝ exp(−i·2kn·v·τ)``.

Shorthand used in the ballistic formulas (``u = v·τ`` the path length in µm):
``Q = 2·kn·u``, ``A = u²/(4 s_x²)``, ``B = u²/(4 s_z²)``, ``β = A − B``.

Separate lateral widths (physics.md §5.8): every function also takes ``lateral_resolution_y_um`` (1/e²
full width along y, µm; ``None``: the same as ``lateral_resolution_um``, which is then the width along
x), so ``s_y ≠ s_x``. Diffusion and flow keep closed forms (one factor per axis; flow then depends on its
azimuth, ``azimuth_deg`` from x towards y). Random-ballistic motion averages over the azimuth first,
``⟨exp(−sin²θ·(A_x cos²φ + A_y sin²φ))⟩_φ = e^{−sin²θ·min(A_x, A_y)}·ive(0, sin²θ·|A_x − A_y|/2)``, which
leaves one smooth integral over the polar angle, evaluated by Gauss–Legendre quadrature with enough
nodes for the oscillation and the peaks (agrees with the isotropic closed forms to ~1e-12 when
``s_y = s_x``; tested). With ``s_y = s_x`` every function takes its isotropic code path.

Every function accepts scalars or arrays, broadcasts its numeric arguments against each other and returns
float64 (complex128 for :func:`g1_flow`) numpy arrays (0-d for scalar input), except the scalar reductions
documented as such.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import cast

import numpy as np
from scipy import special

from torchdoct import conventions
from torchdoct.conventions import DB_PER_NEPER_INTENSITY

__all__ = [
    "g1_diffusion",
    "g1_ballistic",
    "g1_flow",
    "j_diffusion",
    "j_ballistic",
    "j_flow",
    "g1_and_j",
    "intensity_autocovariance",
    "intensity_correlation_coefficient",
    "dilog",
    "db_variance_gaussian_speckle",
    "liv_gaussian_limit",
    "ocds_from_correlations",
    "rho_db_gaussian_limit",
]

_DIRECTIONS = ("isotropic", "uniform-angles")
_SQRT_PI = math.sqrt(math.pi)
#: |β| below which the isotropic ballistic g1 uses its β = 0 limit ``e^{−A} sin Q / Q``.
_BETA_ZERO = 1e-12
#: Gauss–Legendre rule on [0, 1] for the small-(Q, β) corner where the Faddeeva forms cancel.
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(40)
_GL_NODES = 0.5 * (_GL_NODES + 1.0)
_GL_WEIGHTS = 0.5 * _GL_WEIGHTS
#: Elements x Bessel-orders evaluated at once in the uniform-angles series (memory bound).
_BESSEL_BLOCK = 2_000_000
#: |A − B| above which the uniform-angles g1 uses its Laplace (large-|A − B|) form instead of the series.
_LAPLACE_MIN_DIFF = 2e8


# ----------------------------------------------------------------------------------------------------------
# validation helpers
# ----------------------------------------------------------------------------------------------------------
def _f64(name: str, value) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"`{name}` must be real numeric (scalar or array); got {value!r}") from exc
    if np.any(np.isnan(arr)):
        raise ValueError(f"`{name}` must not contain NaN")
    return arr


def _nonneg(name: str, value, unit: str) -> np.ndarray:
    arr = _f64(name, value)
    if np.any(arr < 0):
        raise ValueError(f"`{name}` must be >= 0 {unit}; got min {arr.min()!r}")
    return arr


def _positive(name: str, value, unit: str) -> np.ndarray:
    arr = _f64(name, value)
    if np.any(~(arr > 0)):
        raise ValueError(f"`{name}` must be > 0 {unit}; got min {arr.min()!r}")
    return arr


def _elementwise(formula: Callable[..., float]) -> Callable[..., np.ndarray]:
    """A scalar formula of :mod:`torchdoct.conventions` applied to arrays: each is plain arithmetic, so it is
    elementwise on numpy arrays (the conventions are typed for the scalar case)."""
    return cast("Callable[..., np.ndarray]", formula)


_amplitude_sigma_lateral_um = _elementwise(conventions.amplitude_sigma_lateral_um)
_amplitude_sigma_axial_um = _elementwise(conventions.amplitude_sigma_axial_um)
_wavenumber_per_um = _elementwise(conventions.wavenumber_per_um)


def _check_directions(directions: str) -> None:
    if directions not in _DIRECTIONS:
        raise ValueError(f"`directions` must be one of {_DIRECTIONS}; got {directions!r}")


def _psf_widths(lateral_resolution_um, axial_resolution_um) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude-PSF sigmas (s_x, s_z) in µm, via :mod:`torchdoct.conventions` only."""
    lat = _positive("lateral_resolution_um", lateral_resolution_um, "µm")
    ax = _positive("axial_resolution_um", axial_resolution_um, "µm")
    return _amplitude_sigma_lateral_um(lat), _amplitude_sigma_axial_um(ax)


def _sigma_y(lateral_resolution_um, lateral_resolution_y_um) -> np.ndarray | None:
    """Amplitude sigma s_y (µm) when the lateral PSF has a separate y width, else ``None`` (isotropic:
    ``lateral_resolution_y_um`` is ``None`` or equal to ``lateral_resolution_um`` everywhere)."""
    if lateral_resolution_y_um is None:
        return None
    lat_y = _positive("lateral_resolution_y_um", lateral_resolution_y_um, "µm")
    lat = _positive("lateral_resolution_um", lateral_resolution_um, "µm")
    if np.all(np.broadcast_to(lat_y, np.broadcast_shapes(lat.shape, lat_y.shape)) == lat):
        return None
    return _amplitude_sigma_lateral_um(lat_y)


def _kn(wavelength_um, refractive_index) -> np.ndarray:
    """Wavenumber in the medium k·n (rad/µm), via :func:`torchdoct.conventions.wavenumber_per_um`."""
    wl = _positive("wavelength_um", wavelength_um, "µm")
    n = _positive("refractive_index", refractive_index, "")
    return np.asarray(_wavenumber_per_um(wl, n), dtype=np.float64)


# ----------------------------------------------------------------------------------------------------------
# field autocorrelation g1 (physics.md §5.3)
# ----------------------------------------------------------------------------------------------------------
def g1_diffusion(
    tau_s,
    *,
    diffusion_um2_per_s,
    wavelength_um,
    lateral_resolution_um,
    axial_resolution_um,
    refractive_index=1.0,
    lateral_resolution_y_um=None,
) -> np.ndarray:
    """Normalized field autocorrelation g1(τ) for Brownian diffusion (physics.md §5.3 (a), §5.8).

    ``g1 = exp(−4(kn)²Dτ / (1 + Dτ/s_z²)) / [(1 + Dτ/s_x²) √(1 + Dτ/s_z²)]``, real and in (0, 1];
    with a separate y width the factor ``(1 + Dτ/s_x²)`` becomes ``√((1 + Dτ/s_x²)(1 + Dτ/s_y²))``.

    Parameters: ``tau_s`` lag τ ≥ 0 (s); ``diffusion_um2_per_s`` D ≥ 0 (µm²/s; each coordinate increment is
    N(0, 2Dτ)); ``wavelength_um`` vacuum wavelength λ₀ (µm); resolutions (µm) as in
    :mod:`torchdoct.conventions`; ``refractive_index`` n (phase ``2·k·n·z``). Returns float64, broadcast shape.
    """
    tau = _nonneg("tau_s", tau_s, "s")
    diff = _nonneg("diffusion_um2_per_s", diffusion_um2_per_s, "µm²/s")
    sx, sz = _psf_widths(lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    kn = _kn(wavelength_um, refractive_index)
    dt = diff * tau  # µm²
    rx = 1.0 + dt / sx**2
    if sy is not None:
        rx = np.sqrt(rx * (1.0 + dt / sy**2))
    rz = 1.0 + dt / sz**2
    out = np.exp(-4.0 * kn**2 * dt / rz) / (rx * np.sqrt(rz))
    return np.asarray(out, dtype=np.float64)


def _ballistic_terms(tau_s, speed_um_per_s, lateral_resolution_um, axial_resolution_um):
    tau = _nonneg("tau_s", tau_s, "s")
    speed = _nonneg("speed_um_per_s", speed_um_per_s, "µm/s")
    sx, sz = _psf_widths(lateral_resolution_um, axial_resolution_um)
    u = speed * tau  # path length (µm)
    inv_x = 1.0 / (4.0 * sx**2)
    inv_z = 1.0 / (4.0 * sz**2)
    a_lat = u**2 * inv_x
    b_ax = u**2 * inv_z
    beta = u**2 * (inv_x - inv_z)  # exactly 0 when s_x == s_z
    return u, a_lat, b_ax, beta


def _g1_iso(q: np.ndarray, a_lat: np.ndarray, b_ax: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """``e^{−A} ∫₀¹ e^{βμ²} cos(Qμ) dμ`` elementwise for 1-D float64 arrays (physics.md §5.3 (b))."""
    out = np.empty_like(q)
    tiny = np.abs(beta) < _BETA_ZERO
    small = ~tiny & (q <= 1.0) & (np.abs(beta) <= 1.0)
    pos = ~tiny & ~small & (beta > 0)
    neg = ~tiny & ~small & (beta < 0)

    # β ≈ 0: e^{−A} sin Q / Q (np.sinc handles Q = 0); error O(|β|) < 1e-12.
    if np.any(tiny):
        out[tiny] = np.exp(-a_lat[tiny]) * np.sinc(q[tiny] / np.pi)

    # Q ≤ 1 and |β| ≤ 1: the two Faddeeva terms are O(1/max(Q, √|β|)) and cancel to an O(1) result, so use
    # a 40-node Gauss–Legendre rule instead (the integrand is entire and slowly varying here: exact to eps).
    if np.any(small):
        mu = _GL_NODES[None, :]
        expo = beta[small, None] * mu**2 - a_lat[small, None]
        vals = np.exp(expo) * np.cos(q[small, None] * mu)
        out[small] = vals @ _GL_WEIGHTS

    # β > 0: g1 = √π/(2√β) · Re{ i [e^{−B−iQ} w(−√β + iQ/(2√β)) − e^{−A} w(iQ/(2√β))] }.
    if np.any(pos):
        rb = np.sqrt(beta[pos])
        y = q[pos] / (2.0 * rb)
        t1 = np.exp(-b_ax[pos] - 1j * q[pos]) * special.wofz(-rb + 1j * y)
        t0 = np.exp(-a_lat[pos]) * special.wofz(1j * y)
        out[pos] = (_SQRT_PI / (2.0 * rb)) * np.real(1j * (t1 - t0))

    # β < 0, a = −β: g1 = √π/(2√a) · Re{ e^{−A−Q²/(4a)} − e^{−B−iQ} w(i√a − Q/(2√a)) }.
    if np.any(neg):
        ra = np.sqrt(-beta[neg])
        y = q[neg] / (2.0 * ra)
        t0 = np.exp(-a_lat[neg] - y**2)
        t1 = np.exp(-b_ax[neg] - 1j * q[neg]) * special.wofz(1j * ra - y)
        out[neg] = (_SQRT_PI / (2.0 * ra)) * np.real(t0 - t1)
    return out


def _bessel_orders(q: np.ndarray, c_abs: np.ndarray) -> np.ndarray:
    """Number of terms m = 0..M-1 that make the series of physics.md §5.3 (b′) converge to ~1e-17.

    |J_2m(Q)| is negligible for 2m > Q + 12 Q^{1/3} + 40 (Airy tail) and e^{−c} I_m(c) for
    m > 9.5 √c + 20 (Gaussian tail e^{−m²/(2c)}); the series is cut at the smaller of the two.
    """
    m_j = np.ceil(0.5 * (q + 12.0 * np.cbrt(q) + 40.0))
    m_i = np.ceil(9.5 * np.sqrt(c_abs) + 20.0)
    return np.minimum(m_j, m_i).astype(np.int64) + 1


def _bessel_series(q: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``Σ_m (−1)^m e^{−|c|} I_m(c) J_2m(Q)`` over all integers m (1-D arrays)."""
    c_abs = np.abs(c)
    sign = np.where(c < 0, -1.0, 1.0)  # I_m(−c) = (−1)^m I_m(c): flips the alternating sign
    n_terms = _bessel_orders(q, c_abs)
    out = np.empty_like(q)
    order = np.argsort(n_terms, kind="stable")
    sorted_terms = n_terms[order]
    start = 0
    while start < order.size:
        # largest block whose (count x its largest M) fits the budget; M is ascending within `order`
        window = sorted_terms[start : start + _BESSEL_BLOCK]
        cost = np.arange(1, window.size + 1) * window
        stop = start + max(1, int(np.searchsorted(cost, _BESSEL_BLOCK, side="right")))
        idx = order[start:stop]
        m_cnt = int(sorted_terms[stop - 1])
        m = np.arange(m_cnt, dtype=np.float64)[None, :]
        alt = (-sign[idx, None]) ** m
        weight = np.where(m == 0, 1.0, 2.0)
        terms = weight * alt * special.ive(m, c_abs[idx, None]) * special.jv(2.0 * m, q[idx, None])
        out[idx] = terms.sum(axis=1)
        start = stop
    return out


def _g1_uniform_angles(q: np.ndarray, a_lat: np.ndarray, b_ax: np.ndarray) -> np.ndarray:
    """``(1/π)∫₀^π exp(−iQcosφ − A sin²φ − B cos²φ) dφ`` (physics.md §5.3 (b′)), 1-D arrays.

    ``= e^{−(A+B)/2} Σ_m (−1)^m I_m((A−B)/2) J_2m(Q) = e^{−min(A,B)} Σ_m (−1)^m ive(m, (A−B)/2) J_2m(Q)``.

    For |A − B| > 2e8 (beyond scipy's ``ive`` range and the practical series length; only reachable when the
    two PSF widths differ by orders of magnitude) the Laplace form of the integral is used instead:
    A > B: ``e^{−B} Re[e^{iQ} (A − B + iQ/2)^{−1/2}]/√π``; B > A: ``e^{−A} e^{−Q²/(4(B−A))}/√(π(B−A))``,
    relative error O(1/|A − B|) of a value O(|A − B|^{−1/2}), i.e. < 1e-12 absolute.
    """
    out = np.zeros_like(q)
    floor = np.minimum(a_lat, b_ax)
    diff = a_lat - b_ax
    live = floor < 746.0  # e^{−746} underflows to 0: those entries stay exactly 0
    huge = live & (np.abs(diff) > _LAPLACE_MIN_DIFF)
    series = live & ~huge
    if np.any(series):
        out[series] = np.exp(-floor[series]) * _bessel_series(q[series], 0.5 * diff[series])
    lat_wide = huge & (diff > 0)  # weight peaks at φ = 0, π (moving along z)
    if np.any(lat_wide):
        d = diff[lat_wide]
        z = np.exp(1j * q[lat_wide]) / np.sqrt(d + 0.5j * q[lat_wide])
        out[lat_wide] = np.exp(-b_ax[lat_wide]) * z.real / _SQRT_PI
    ax_wide = huge & (diff < 0)  # weight peaks at φ = π/2 (moving laterally)
    if np.any(ax_wide):
        d = -diff[ax_wide]
        out[ax_wide] = np.exp(-a_lat[ax_wide] - q[ax_wide] ** 2 / (4.0 * d)) / np.sqrt(np.pi * d)
    return out


def _ive0_abs(x: np.ndarray) -> np.ndarray:
    """``e^{−|x|} I₀(|x|)``; Hankel expansion above 1e8 where scipy's ``ive`` returns NaN."""
    x = np.abs(x)
    out = np.empty_like(x)
    big = x > 1e8
    out[~big] = special.ive(0, x[~big])
    xb = x[big]
    out[big] = (1.0 + 1.0 / (8.0 * xb) + 9.0 / (128.0 * xb**2)) / np.sqrt(2.0 * np.pi * xb)
    return out


#: Largest Gauss–Legendre rule of the anisotropic ballistic quadrature (nodes per element).
_ANISO_MAX_NODES = 8192


@functools.lru_cache(maxsize=64)
def _gl_unit(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [0, 1] (scipy's banded eigen-solver: fast for thousands of nodes)."""
    x, w = special.roots_legendre(n)
    return 0.5 * (x + 1.0), 0.5 * w


def _ballistic_anisotropic(
    q: np.ndarray, a_x: np.ndarray, a_y: np.ndarray, b_ax: np.ndarray, directions: str
) -> np.ndarray:
    """``E_n[cos(Q n_z) exp(−A_x n_x² − A_y n_y² − B n_z²)]`` over the direction law (1-D arrays).

    The azimuth average is exact: ``⟨e^{−s²(A_x cos²φ + A_y sin²φ)}⟩_φ = e^{−s²·m}·ive(0, s²·|A_x − A_y|/2)``
    (``s = sin θ``, ``m = min(A_x, A_y)``). What remains is an integral over the polar angle:
    isotropic ``∫₀¹ cos(Qμ)·e^{−Bμ²}·F(1 − μ²) dμ``; uniform angles ``(2/π)∫₀^{π/2} cos(Q cos θ)·e^{−B cos²θ}·
    F(sin²θ) dθ``, with ``F(s²) = e^{−s²·m}·ive(0, s²|Δ|/2)``. Gauss–Legendre with ``60 + Q + 8√max(A, B)``
    nodes (up to :data:`_ANISO_MAX_NODES`): the oscillation and the peaks at the ends of the interval, where
    the rule's nodes cluster, are resolved. With ``Q = 0`` and ``(A, B)`` doubled it is ``j``.
    """
    out = np.empty_like(q)
    m = np.minimum(a_x, a_y)
    half_d = 0.5 * np.abs(a_x - a_y)
    big = np.maximum(np.maximum(a_x, a_y), b_ax)
    nodes = np.minimum(60.0 + q + 8.0 * np.sqrt(big), _ANISO_MAX_NODES)
    # bucket the rules by powers of 2^(1/4) so each bucket is one vectorized evaluation
    bucket = np.ceil(4.0 * np.log2(nodes)).astype(np.int64)
    for bkt in np.unique(bucket):
        idx = np.nonzero(bucket == bkt)[0]
        n = int(min(_ANISO_MAX_NODES, math.ceil(2.0 ** (bkt / 4.0))))
        x, w = _gl_unit(n)
        for lo in range(0, idx.size, max(1, 4_000_000 // n)):
            sl = idx[lo : lo + max(1, 4_000_000 // n)]
            if directions == "isotropic":
                mu = x[None, :]
                s2 = 1.0 - mu * mu
                osc = np.cos(q[sl, None] * mu)
            else:
                th = 0.5 * np.pi * x[None, :]
                mu = np.cos(th)
                s2 = np.sin(th) ** 2
                osc = np.cos(q[sl, None] * mu)
            f = np.exp(-b_ax[sl, None] * mu * mu - s2 * m[sl, None]) * _ive0_abs(s2 * half_d[sl, None])
            out[sl] = (osc * f) @ w
    return out


def g1_ballistic(
    tau_s,
    *,
    speed_um_per_s,
    wavelength_um,
    lateral_resolution_um,
    axial_resolution_um,
    refractive_index=1.0,
    directions="isotropic",
    lateral_resolution_y_um=None,
) -> np.ndarray:
    """Normalized field autocorrelation g1(τ) for random-ballistic motion (physics.md §5.3 (b), (b′)).

    Every scatterer moves the distance ``u = vτ`` (µm) along its own random direction. With
    ``Q = 2·kn·u``, ``A = u²/(4s_x²)``, ``B = u²/(4s_z²)``, ``β = A − B``:

    * ``directions="isotropic"`` (uniform on the sphere, §5.3 (b)):
      ``g1 = e^{−A} ∫₀¹ e^{βμ²} cos(Qμ) dμ``, evaluated with the Faddeeva closed forms (``scipy.special.wofz``)
      for β > 0 and β < 0, the limit ``e^{−A} sin Q/Q`` for |β| < 1e-12, and a Gauss–Legendre rule for
      Q ≤ 1, |β| ≤ 1 where the Faddeeva terms cancel.
    * ``directions="uniform-angles"`` (COG/paper law: polar angle φ ~ U[0, π], azimuth uniform, §5.3 (b′)):
      ``g1 = e^{−(A+B)/2} Σ_m (−1)^m I_m((A−B)/2) J_2m(Q)`` with scaled ``ive``; the series is truncated
      adaptively per element (converges for Q up to ~1e4 and any A − B).
    * ``lateral_resolution_y_um`` different from ``lateral_resolution_um`` (§5.8): ``A_y = u²/(4s_y²)`` and
      the polar-angle quadrature of :func:`_ballistic_anisotropic`.

    Parameters: ``tau_s`` lag τ ≥ 0 (s); ``speed_um_per_s`` v ≥ 0 (µm/s); ``wavelength_um`` λ₀ (µm);
    resolutions (µm) per :mod:`torchdoct.conventions`; ``refractive_index`` n. Returns real float64 in [−1, 1]
    with the broadcast shape; g1 = 1 at τ = 0 or v = 0.
    """
    _check_directions(directions)
    kn = _kn(wavelength_um, refractive_index)
    u, a_lat, b_ax, beta = _ballistic_terms(tau_s, speed_um_per_s, lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    a_y = a_lat if sy is None else u**2 / (4.0 * sy**2)
    u, a_lat, b_ax, beta, kn, a_y = np.broadcast_arrays(u, a_lat, b_ax, beta, kn, a_y)
    shape = u.shape
    q = (2.0 * kn * u).ravel()
    a_lat, b_ax, beta = a_lat.ravel(), b_ax.ravel(), beta.ravel()
    if sy is not None:
        out = _ballistic_anisotropic(q, a_lat, np.ascontiguousarray(a_y).ravel(), b_ax, directions)
    elif directions == "isotropic":
        out = _g1_iso(q, a_lat, b_ax, beta)
    else:
        out = _g1_uniform_angles(q, a_lat, b_ax)
    out[u.ravel() == 0.0] = 1.0
    return out.reshape(shape)


def _flow_lateral(sin_t, sx, sy, azimuth_deg):
    """``sin²θ/s_x²`` (isotropic lateral PSF) or ``sin²θ·(cos²φ/s_x² + sin²φ/s_y²)`` (µm⁻²)."""
    if sy is None:
        return sin_t**2 / sx**2
    phi = np.deg2rad(_f64("azimuth_deg", azimuth_deg))
    return sin_t**2 * (np.cos(phi) ** 2 / sx**2 + np.sin(phi) ** 2 / sy**2)


def g1_flow(
    tau_s,
    *,
    speed_um_per_s,
    polar_angle_deg,
    wavelength_um,
    lateral_resolution_um,
    axial_resolution_um,
    refractive_index=1.0,
    lateral_resolution_y_um=None,
    azimuth_deg=0.0,
) -> np.ndarray:
    """Complex g1(τ) for mono-directional flow (physics.md §5.3 (c), §5.8).

    ``g1 = exp(−i·2kn·vτ·cosθ − v²τ²[sin²θ/(4s_x²) + cos²θ/(4s_z²)])`` with θ = ``polar_angle_deg`` (degrees)
    from the depth axis (θ = 0: moving deeper). With an isotropic lateral PSF the azimuth does not matter;
    with a separate y width ``sin²θ/s_x²`` becomes ``sin²θ·(cos²φ/s_x² + sin²φ/s_y²)``, φ = ``azimuth_deg``
    (degrees from x towards y). ``|g1|`` does not depend on the wavelength. Units: τ (s), v (µm/s), λ₀ and
    resolutions (µm). Returns complex128, broadcast shape.
    """
    tau = _nonneg("tau_s", tau_s, "s")
    speed = _nonneg("speed_um_per_s", speed_um_per_s, "µm/s")
    theta = np.deg2rad(_f64("polar_angle_deg", polar_angle_deg))
    sx, sz = _psf_widths(lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    kn = _kn(wavelength_um, refractive_index)
    u = speed * tau
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    if sy is None:
        decay = u**2 * (sin_t**2 / (4.0 * sx**2) + cos_t**2 / (4.0 * sz**2))
    else:
        decay = u**2 * (_flow_lateral(sin_t, sx, sy, azimuth_deg) / 4.0 + cos_t**2 / (4.0 * sz**2))
    phase = 2.0 * kn * u * cos_t
    out = np.exp(-decay) * (np.cos(phase) - 1j * np.sin(phase))
    return np.asarray(out, dtype=np.complex128)


# ----------------------------------------------------------------------------------------------------------
# incoherent (Poisson) term j (physics.md §5.4)
# ----------------------------------------------------------------------------------------------------------
def j_diffusion(
    tau_s, *, diffusion_um2_per_s, lateral_resolution_um, axial_resolution_um, lateral_resolution_y_um=None
) -> np.ndarray:
    """Poisson-term overlap j(τ) for diffusion (physics.md §5.4 (a), §5.8).

    ``j = 1 / [(1 + 2Dτ/s_x²) √(1 + 2Dτ/s_z²)]``; j(0) = 1 (with a separate y width the first factor is
    ``√((1 + 2Dτ/s_x²)(1 + 2Dτ/s_y²))``). Units: τ (s), D (µm²/s), resolutions (µm).
    Returns float64, broadcast shape.
    """
    tau = _nonneg("tau_s", tau_s, "s")
    diff = _nonneg("diffusion_um2_per_s", diffusion_um2_per_s, "µm²/s")
    sx, sz = _psf_widths(lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    dt = diff * tau
    rx = 1.0 + 2.0 * dt / sx**2
    if sy is not None:
        rx = np.sqrt(rx * (1.0 + 2.0 * dt / sy**2))
    out = 1.0 / (rx * np.sqrt(1.0 + 2.0 * dt / sz**2))
    return np.asarray(out, dtype=np.float64)


def _dawson_ratio(x: np.ndarray) -> np.ndarray:
    """F(x)/x (F the Dawson function), → 1 at x = 0."""
    out = np.ones_like(x)
    big = x > 1e-4
    out[big] = special.dawsn(x[big]) / x[big]
    sm = ~big
    out[sm] = 1.0 - 2.0 * x[sm] ** 2 / 3.0 + 4.0 * x[sm] ** 4 / 15.0
    return out


def _erf_ratio(x: np.ndarray) -> np.ndarray:
    """√π erf(x)/(2x), → 1 at x = 0."""
    out = np.ones_like(x)
    big = x > 1e-4
    out[big] = _SQRT_PI * special.erf(x[big]) / (2.0 * x[big])
    sm = ~big
    out[sm] = 1.0 - x[sm] ** 2 / 3.0 + x[sm] ** 4 / 10.0
    return out


def j_ballistic(
    tau_s,
    *,
    speed_um_per_s,
    lateral_resolution_um,
    axial_resolution_um,
    directions="isotropic",
    lateral_resolution_y_um=None,
) -> np.ndarray:
    """Poisson-term overlap j(τ) for random-ballistic motion (physics.md §5.4 (b), (b′)).

    With ``A′ = u²/(2s_x²)``, ``B′ = u²/(2s_z²)`` (u = vτ in µm), ``β′ = A′ − B′``:

    * ``"isotropic"``: ``j = e^{−A′} ∫₀¹ e^{β′μ²} dμ`` = ``e^{−B′} F(√β′)/√β′`` (β′ > 0, Dawson F) or
      ``e^{−A′} √π erf(√a′)/(2√a′)`` (a′ = −β′ ≥ 0);
    * ``"uniform-angles"`` (φ ~ U[0, π]): ``j = e^{−(A′+B′)/2} I₀((A′−B′)/2)``, evaluated with ``ive``.

    With a separate y width (§5.8) the polar-angle quadrature of :func:`_ballistic_anisotropic` at Q = 0.

    j does not depend on the wavelength. Units: τ (s), v (µm/s), resolutions (µm). Returns float64 in [0, 1],
    broadcast shape; j = 1 at τ = 0 or v = 0.
    """
    _check_directions(directions)
    u, a_lat, b_ax, beta = _ballistic_terms(tau_s, speed_um_per_s, lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    a_y = a_lat if sy is None else u**2 / (4.0 * sy**2)
    a2, b2, beta2, ay2 = np.broadcast_arrays(2.0 * a_lat, 2.0 * b_ax, 2.0 * beta, 2.0 * a_y)
    shape = a2.shape
    a2, b2, beta2 = a2.ravel(), b2.ravel(), beta2.ravel()
    out = np.empty_like(a2)
    if sy is not None:
        out[:] = _ballistic_anisotropic(np.zeros_like(a2), a2, np.ascontiguousarray(ay2).ravel(), b2, directions)
        out[np.ascontiguousarray(np.broadcast_to(u, shape)).ravel() == 0.0] = 1.0
    elif directions == "isotropic":
        pos = beta2 > 0
        neg = ~pos
        out[pos] = np.exp(-b2[pos]) * _dawson_ratio(np.sqrt(beta2[pos]))
        out[neg] = np.exp(-a2[neg]) * _erf_ratio(np.sqrt(-beta2[neg]))
    else:
        out[:] = np.exp(-np.minimum(a2, b2)) * _ive0_abs(0.5 * (a2 - b2))
    return out.reshape(shape)


def j_flow(
    tau_s,
    *,
    speed_um_per_s,
    polar_angle_deg,
    lateral_resolution_um,
    axial_resolution_um,
    lateral_resolution_y_um=None,
    azimuth_deg=0.0,
) -> np.ndarray:
    """Poisson-term overlap j(τ) for mono-directional flow (physics.md §5.4 (c)): ``j = |g1_flow|²``.

    ``j = exp(−v²τ²[sin²θ/(2s_x²) + cos²θ/(2s_z²)])``, wavelength independent (with a separate y width,
    ``sin²θ/s_x²`` as in :func:`g1_flow`). Units: τ (s), v (µm/s), θ = ``polar_angle_deg`` (degrees from the
    depth axis), φ = ``azimuth_deg``, resolutions (µm). Returns float64, broadcast shape.
    """
    tau = _nonneg("tau_s", tau_s, "s")
    speed = _nonneg("speed_um_per_s", speed_um_per_s, "µm/s")
    theta = np.deg2rad(_f64("polar_angle_deg", polar_angle_deg))
    sx, sz = _psf_widths(lateral_resolution_um, axial_resolution_um)
    sy = _sigma_y(lateral_resolution_um, lateral_resolution_y_um)
    u = speed * tau
    if sy is None:
        out = np.exp(-(u**2) * (np.sin(theta) ** 2 / (2.0 * sx**2) + np.cos(theta) ** 2 / (2.0 * sz**2)))
    else:
        out = np.exp(
            -(u**2) * (_flow_lateral(np.sin(theta), sx, sy, azimuth_deg) / 2.0 + np.cos(theta) ** 2 / (2.0 * sz**2))
        )
    return np.asarray(out, dtype=np.float64)


# ----------------------------------------------------------------------------------------------------------
# intensity correlations (physics.md §5.4, §2.4)
# ----------------------------------------------------------------------------------------------------------
def g1_and_j(motion, system, tau_s) -> tuple[np.ndarray, np.ndarray]:
    """``(g1(τ), j(τ))`` of one motion model seen by one system (physics.md §5.3-5.4): ``motion`` a
    ``Diffusion``, ``RandomBallistic`` or ``Flow`` and ``system`` an ``OCTSystem`` of
    :mod:`torchdoct.sim.config` (read by their fields: µm, µm²/s, µm/s, degrees); ``tau_s`` in s."""
    kw = dict(
        lateral_resolution_um=system.lateral_resolution_um,
        axial_resolution_um=system.axial_resolution_um,
        lateral_resolution_y_um=getattr(system, "lateral_resolution_y_um", None),
    )
    if hasattr(motion, "diffusion_um2_per_s"):
        D = motion.diffusion_um2_per_s
        return (
            g1_diffusion(tau_s, diffusion_um2_per_s=D, wavelength_um=system.wavelength_um, **kw),
            j_diffusion(tau_s, diffusion_um2_per_s=D, **kw),
        )
    if hasattr(motion, "directions"):
        v, d = motion.speed_um_per_s, motion.directions
        return (
            g1_ballistic(tau_s, speed_um_per_s=v, wavelength_um=system.wavelength_um, directions=d, **kw),
            j_ballistic(tau_s, speed_um_per_s=v, directions=d, **kw),
        )
    v, a = motion.speed_um_per_s, motion.polar_angle_deg
    kw["azimuth_deg"] = getattr(motion, "azimuth_deg", 0.0)
    return (
        g1_flow(tau_s, speed_um_per_s=v, polar_angle_deg=a, wavelength_um=system.wavelength_um, **kw),
        j_flow(tau_s, speed_um_per_s=v, polar_angle_deg=a, **kw),
    )


def _n_eff_arr(n_eff_value) -> np.ndarray:
    return _positive("n_eff_value", n_eff_value, "(scatterers)")


def intensity_autocovariance(g1, j, n_eff_value) -> np.ndarray:
    """Normalized intensity autocovariance ``G2/⟨I⟩² − 1 = |g1|² + j/N_eff`` (physics.md §5.4).

    ``g1`` real or complex, ``j`` real (both dimensionless, broadcast), ``n_eff_value`` the speckle-governing
    scatterer count N_eff (``torchdoct.conventions.n_eff``; ``np.inf`` gives the Siegert limit). Float64.
    At τ = 0 this is the squared contrast ``C² = 1 + 1/N_eff``.
    """
    g1 = np.asarray(g1)
    j_arr = _f64("j", j)
    ne = _n_eff_arr(n_eff_value)
    return np.asarray(np.abs(g1) ** 2 + j_arr / ne, dtype=np.float64)


def intensity_correlation_coefficient(g1, j, n_eff_value) -> np.ndarray:
    """Correlation coefficient of linear intensity ``ρ_I = (|g1|² + j/N_eff)/(1 + 1/N_eff)`` (§5.4, §2.4).

    Dimensionless, float64, broadcast shape; ρ_I(0) = 1.
    """
    ne = _n_eff_arr(n_eff_value)
    return np.asarray(intensity_autocovariance(g1, j, ne) / (1.0 + 1.0 / ne), dtype=np.float64)


def dilog(x) -> np.ndarray:
    """Dilogarithm ``Li₂(x) = −∫₀^x ln(1−t)/t dt`` for x ≤ 1 (physics.md §1), via ``scipy.special.spence(1−x)``.

    Values in (1, 1 + 1e-12] (rounding of |g1|²) are clipped to 1; Li₂(1) = π²/6. Float64, same shape.
    """
    arr = _f64("x", x)
    if np.any(arr > 1.0 + 1e-12):
        raise ValueError(f"`x` must be <= 1 for the real dilogarithm; got max {arr.max()!r}")
    arr = np.minimum(arr, 1.0)
    return np.asarray(special.spence(1.0 - arr), dtype=np.float64)


def db_variance_gaussian_speckle() -> float:
    """Variance of ``10·log10 I`` for fully developed Gaussian speckle, (10/ln10)²·π²/6 = 31.03 dB² (§1)."""
    return DB_PER_NEPER_INTENSITY**2 * math.pi**2 / 6.0


def liv_gaussian_limit(g1_abs_at_lags, n_frames):
    """Expected LIV (dB², ddof 0) of N Gaussian-speckle frames (physics.md §1, exact as N_eff → ∞).

    ``E[LIV] = (10/ln10)² [ (π²/6)(1 − 1/N) − (2/N²) Σ_{m=1}^{N−1} (N − m) Li₂(|g1(mΔt)|²) ]``

    ``g1_abs_at_lags`` has shape ``[..., N−1]``: |g1| (or complex g1) at lags m·Δt, m = 1..N−1 (uniform frame
    interval). ``n_frames`` = N ≥ 2. Returns a float for 1-D input, else a float64 array of shape ``[...]``.
    """
    n = int(n_frames)
    if n != n_frames or n < 2:
        raise ValueError(f"`n_frames` must be an integer >= 2; got {n_frames!r}")
    g = np.abs(np.asarray(g1_abs_at_lags))
    if g.ndim == 0 or g.shape[-1] != n - 1:
        raise ValueError(f"`g1_abs_at_lags` must have last dimension n_frames - 1 = {n - 1}; got shape {g.shape}")
    m = np.arange(1, n, dtype=np.float64)
    acc = (dilog(g**2) * (n - m)).sum(axis=-1)
    out = DB_PER_NEPER_INTENSITY**2 * ((math.pi**2 / 6.0) * (1.0 - 1.0 / n) - 2.0 * acc / n**2)
    out = np.asarray(out, dtype=np.float64)
    return float(out) if out.ndim == 0 else out


def ocds_from_correlations(rho, delays_s):
    """OCDS (s⁻¹) = minus the ordinary-least-squares slope of ρ versus delay (physics.md §2.4).

    ``rho`` has shape ``[..., M]`` (correlation coefficients at the M delays, dimensionless), ``delays_s`` shape
    ``[M]`` (s), M ≥ 2 distinct delays; for OCDS_l use m = 1..6 frames of 0.2048 s. Positive for a decaying
    curve. Returns a float for 1-D ``rho``, else a float64 array of shape ``[...]``.
    """
    r = _f64("rho", rho)
    t = _f64("delays_s", delays_s)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"`delays_s` must be 1-D with >= 2 delays (s); got shape {t.shape}")
    if r.ndim == 0 or r.shape[-1] != t.size:
        raise ValueError(f"`rho` must have last dimension {t.size} (= len(delays_s)); got shape {r.shape}")
    tc = t - t.mean()
    sxx = float(np.dot(tc, tc))
    if sxx == 0.0:
        raise ValueError("`delays_s` must not all be equal")
    slope = (r - r.mean(axis=-1, keepdims=True)) @ tc / sxx
    out = np.asarray(-slope, dtype=np.float64)
    return float(out) if out.ndim == 0 else out


def rho_db_gaussian_limit(g1) -> np.ndarray:
    """Correlation coefficient of dB intensity, Gaussian-speckle limit: ``(6/π²) Li₂(|g1|²)`` (§2.4).

    ``g1`` real or complex (dimensionless). Returns float64, same shape; 1 at |g1| = 1, 0 at g1 = 0.
    """
    g = np.abs(np.asarray(g1))
    return np.asarray(6.0 / math.pi**2 * dilog(g**2), dtype=np.float64)

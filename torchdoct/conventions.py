"""Physical conventions of torchdoct: the one place where resolutions become PSF widths.

Every other module imports its conversions from here.

=======================  =====================================================================
Quantity                 Convention
=======================  =====================================================================
lengths                  micrometres (``_um``)
times                    seconds (``_s``)
wavelength               vacuum centre wavelength λ₀ in µm
refractive index ``n``   phase index of the medium; the round-trip phase of a scatterer at depth
                         z is ``2·k·n·z`` with ``k = 2π/λ₀`` (the paper's equation is ``n = 1``)
depth axis               ``z`` (positive = deeper); lateral axes ``x``, ``y``
lateral resolution Δx    1/e² full width of the *intensity* PSF (in the medium) along x; along y
                         ``Δy`` (``lateral_resolution_y_um``), equal to Δx unless given
axial resolution Δz      FWHM of the *intensity* PSF (in the medium)
amplitude PSF            ``h(r) = exp(-x²/(2 s_x²) - y²/(2 s_y²) - z²/(2 s_z²))``
                         with ``s_x = Δx/(2√2)``, ``s_y = Δy/(2√2)`` and ``s_z = Δz/(2√ln2)``
                         (physics.md §5.1, §5.8)
intensity                ``I = |E|²`` (linear); dB means ``10·log10 I``
=======================  =====================================================================

Effective numbers of scatterers (physics.md §5.5):

* ``ens_paper = ρ·Δx·Δy·Δz``: the count the reference paper quotes (5.02 / 18.5 / 67.7, with Δy = Δx).
* ``n_eff = ρ·(2π)^{3/2}·s_x·s_y·s_z = 1.18233·ρ·Δx·Δy·Δz``: the count that governs speckle statistics,
  ``C_I² = Var I/⟨I⟩² = 1 + 1/N_eff`` exactly for a Poisson medium (physics.md §5.4).

A lateral PSF with separate widths (``Δy ≠ Δx``) is what B-scan data look like after a computational
lateral reduction along x only (x reduced, y keeps the system's width). Every function below that
takes ``lateral_resolution_um`` also takes ``lateral_resolution_y_um`` (keyword; ``None``: equal to
``lateral_resolution_um``, the isotropic PSF).

PSF truncation (the simulator's domain): the amplitude PSF is below ``tolerance`` (relative to its
peak) outside the ellipsoid ``x²/s_x² + y²/s_y² + z²/s_z² = 2·ln(1/tolerance)``; the simulator
evaluates every scatterer inside the bounding box of that ellipsoid (half-widths
:func:`truncation_half_widths_um`). Scatterers left out carry less than the fraction
:func:`truncation_error_bound` of the mean intensity, which bounds the relative mean-square error
of the simulated field: ``E|E - E_trunc|² / E|E|² ≤ Q(3/2, 2·ln(1/tolerance))``
(``Q`` the regularized upper incomplete gamma function).

Truncation modes (``[simulation] truncation``, physics.md §5.9): ``"hard"`` cuts the amplitude to
exactly 0 below the tolerance, so a moving scatterer enters the PSF at ``tolerance`` times the peak (a
step, which decorrelates slow motion at short lags); ``"taper"`` multiplies the amplitude by the
window :func:`taper_window` of the exponent, which falls smoothly (C²) from 1 at ``TAPER_START·ln tol``
to 0 at ``ln tol``, so scatterers enter continuously. The taper changes the PSF near its edge; its
cost in mean-square field and mean intensity is :func:`truncation_field_error` and
:func:`truncation_intensity_factor` (moments of the window over the |h|²-weighted radius).

Noise (``[noise] snr_db``, :class:`torchdoct.sim.config.Noise`; physics.md §8): additive circular complex
Gaussian noise, independent per frame (and per pixel and system), of power ``N₀ = ⟨I⟩/10^(SNR/10)``
relative to the mean noise-free intensity ``⟨I⟩`` (physics.md §5.2); its real and imaginary parts each
have the standard deviation ``√(N₀/2)``. :func:`noise_power` and :func:`noise_sigma` are the only
conversions of an SNR in dB to a noise level: the point simulator, the image renderer and the
classifier's training data call them.
"""

from __future__ import annotations

import functools
import math
import struct

__all__ = [
    "LENGTH_UNIT",
    "TIME_UNIT",
    "DB_PER_NEPER_INTENSITY",
    "REFRACTIVE_INDEX_RANGE",
    "amplitude_sigma_lateral_um",
    "amplitude_sigma_axial_um",
    "lateral_resolution_from_sigma_um",
    "axial_resolution_from_sigma_um",
    "wavenumber_per_um",
    "ens_paper",
    "n_eff",
    "mean_intensity",
    "psf_integral_um3",
    "truncation_radius_factor",
    "truncation_half_widths_um",
    "truncation_error_bound",
    "TRUNCATION_MODES",
    "TAPER_START",
    "taper_window",
    "truncation_field_error",
    "truncation_intensity_factor",
    "noise_power",
    "noise_sigma",
    "FLOAT32_SPACING",
    "FLOAT64_SPACING",
    "time_tolerance_s",
    "uniform_frame_interval_s",
    "delay_groups",
    "delay_range_tolerance_s",
]

LENGTH_UNIT = "um"
TIME_UNIT = "s"
#: ``10/ln(10)``: dB per neper of intensity; ``10·log10 I = DB_PER_NEPER_INTENSITY · ln I``.
DB_PER_NEPER_INTENSITY = 10.0 / math.log(10.0)

#: Phase refractive index a system's medium may have, in scene files, sidecars and maps alike (air 1,
#: tissue about 1.35-1.4, the densest optical glasses below 2; 5 leaves room and refuses typing errors).
REFRACTIVE_INDEX_RANGE = (1.0, 5.0)

#: Single precision's relative spacing, 2⁻²³: frame times stored as float32 (by an HDF5 attribute, a MATLAB
#: ``single`` or a float32 tensor) are exact to half of it times their magnitude.
FLOAT32_SPACING = 2.0**-23
#: Double precision's relative spacing, 2⁻⁵².
FLOAT64_SPACING = 2.0**-52


def _is_single(v: float) -> bool:
    """Whether ``v`` is a single-precision number (float32 rounds it to itself)."""
    try:
        return struct.unpack("f", struct.pack("f", v))[0] == v
    except OverflowError:
        return False


def time_tolerance_s(times_s) -> float:
    """The resolution (s) of frame times: two steps or delays closer than this are one. At least 1e-9 of the
    span (what times written with 9 digits resolve) and 8 double-precision spacings of the largest time;
    when every time is a single-precision number (stored as float32), 4 single-precision spacings of the
    largest time."""
    t = [float(v) for v in times_s]
    if not t:
        return 0.0
    top = max(abs(v) for v in t)
    tol = max(1e-9 * (max(t) - min(t)), 8 * FLOAT64_SPACING * top)
    if all(_is_single(v) for v in t):
        tol = max(tol, 4 * FLOAT32_SPACING * top)
    return tol


def uniform_frame_interval_s(times_s) -> float | None:
    """The frame interval (s) of a uniform protocol (every step equal within :func:`time_tolerance_s`),
    else ``None``."""
    t = [float(v) for v in times_s]
    d = [b - a for a, b in zip(t, t[1:])]
    if d and max(d) - min(d) <= time_tolerance_s(t):
        return (t[-1] - t[0]) / (len(t) - 1)
    return None


def delay_range_tolerance_s(times_s, delay_range_s) -> float:
    """How far (s) a delay of the frame times may lie outside ``delay_range_s = (lo, hi)`` and still count
    as inside: the times' resolution (:func:`time_tolerance_s`), at least 1e-9 of the range's ends."""
    lo, hi = (float(v) for v in delay_range_s)
    return max(time_tolerance_s(times_s), 1e-9 * max(abs(lo), abs(hi)))


def delay_groups(times_s) -> list[tuple[float, list[tuple[int, int]]]]:
    """Every distinct delay ``t_j − t_i`` (s) of the frame times, ascending, with its frame index pairs
    ``(i, j > i)`` in index order. Delays within :func:`time_tolerance_s` of a group's shortest are one delay, their mean;
    a uniform protocol's delays are ``m·Δt`` exactly."""
    t = [float(v) for v in times_s]
    n = len(t)
    dt = uniform_frame_interval_s(t)
    if dt is not None:
        return [(m * dt, [(i, i + m) for i in range(n - m)]) for m in range(1, n)]
    tol = time_tolerance_s(t)
    pairs = sorted((t[j] - t[i], i, j) for i in range(n) for j in range(i + 1, n))
    groups: list[tuple[float, list[float], list[tuple[int, int]]]] = []
    for d, i, j in pairs:
        if not groups or d - groups[-1][0] > tol:
            groups.append((d, [], []))
        groups[-1][1].append(d)
        groups[-1][2].append((i, j))
    return [(ds[0] + math.fsum(d - ds[0] for d in ds) / len(ds), sorted(ij)) for _, ds, ij in groups]


_SQRT2 = math.sqrt(2.0)
_SQRT_LN2 = math.sqrt(math.log(2.0))


def amplitude_sigma_lateral_um(lateral_resolution_um: float) -> float:
    """Lateral amplitude-PSF sigma ``s_x = Δx/(2√2)`` from the 1/e² intensity full width Δx (µm)."""
    return lateral_resolution_um / (2.0 * _SQRT2)


def amplitude_sigma_axial_um(axial_resolution_um: float) -> float:
    """Axial amplitude-PSF sigma ``s_z = Δz/(2√ln2)`` from the intensity FWHM Δz (µm)."""
    return axial_resolution_um / (2.0 * _SQRT_LN2)


def lateral_resolution_from_sigma_um(sigma_um: float) -> float:
    """Inverse of :func:`amplitude_sigma_lateral_um`: ``Δx = 2√2·s_x`` (µm)."""
    return 2.0 * _SQRT2 * sigma_um


def axial_resolution_from_sigma_um(sigma_um: float) -> float:
    """Inverse of :func:`amplitude_sigma_axial_um`: ``Δz = 2√ln2·s_z`` (µm)."""
    return 2.0 * _SQRT_LN2 * sigma_um


def wavenumber_per_um(wavelength_um: float, refractive_index: float = 1.0) -> float:
    """Wavenumber in the medium ``k·n = 2π·n/λ₀`` (rad/µm); the round-trip phase is ``2·k·n·z``."""
    return 2.0 * math.pi * refractive_index / wavelength_um


def _lateral_y(lateral_resolution_um: float, lateral_resolution_y_um: float | None) -> float:
    return lateral_resolution_um if lateral_resolution_y_um is None else lateral_resolution_y_um


def psf_integral_um3(
    lateral_resolution_um: float, axial_resolution_um: float, *, lateral_resolution_y_um: float | None = None
) -> float:
    """``∫|h|² d³r = π^{3/2}·s_x·s_y·s_z`` (µm³), the intensity-PSF volume (physics.md §5.2)."""
    sx = amplitude_sigma_lateral_um(lateral_resolution_um)
    sy = amplitude_sigma_lateral_um(_lateral_y(lateral_resolution_um, lateral_resolution_y_um))
    sz = amplitude_sigma_axial_um(axial_resolution_um)
    return math.pi**1.5 * sx * sy * sz


def mean_intensity(
    density_per_um3: float,
    lateral_resolution_um: float,
    axial_resolution_um: float,
    reflectivity: float = 1.0,
    *,
    lateral_resolution_y_um: float | None = None,
) -> float:
    """Mean intensity ``⟨I⟩ = ρ·b²·π^{3/2}·s_x·s_y·s_z`` of a Poisson medium (physics.md §5.2).

    ``reflectivity`` is the field amplitude ``b`` of one scatterer; intensities scale as ``b²``.
    """
    return (
        density_per_um3
        * reflectivity**2
        * psf_integral_um3(lateral_resolution_um, axial_resolution_um, lateral_resolution_y_um=lateral_resolution_y_um)
    )


def ens_paper(
    density_per_um3: float,
    lateral_resolution_um: float,
    axial_resolution_um: float,
    *,
    lateral_resolution_y_um: float | None = None,
) -> float:
    """Effective number of scatterers as the reference paper counts it: ``ρ·Δx·Δy·Δz`` (``ρ·Δx²·Δz``)."""
    lat_y = _lateral_y(lateral_resolution_um, lateral_resolution_y_um)
    if lat_y == lateral_resolution_um:
        return density_per_um3 * lateral_resolution_um**2 * axial_resolution_um
    return density_per_um3 * lateral_resolution_um * lat_y * axial_resolution_um


def n_eff(
    density_per_um3: float,
    lateral_resolution_um: float,
    axial_resolution_um: float,
    *,
    lateral_resolution_y_um: float | None = None,
) -> float:
    """Speckle-governing scatterer count ``N_eff = ρ·(2π)^{3/2}·s_x·s_y·s_z`` (physics.md §5.4-5.5).

    ``N_eff = ρ (∫|h|²)² / ∫|h|⁴`` and ``C_I² = 1 + 1/N_eff``.
    """
    sx = amplitude_sigma_lateral_um(lateral_resolution_um)
    sy = amplitude_sigma_lateral_um(_lateral_y(lateral_resolution_um, lateral_resolution_y_um))
    sz = amplitude_sigma_axial_um(axial_resolution_um)
    return density_per_um3 * (2.0 * math.pi) ** 1.5 * sx * sy * sz


def truncation_radius_factor(tolerance: float) -> float:
    """``c = √(2·ln(1/tolerance))``: the amplitude PSF ``exp(-u²/2)`` drops below ``tolerance`` at ``u = c``."""
    if isinstance(tolerance, bool) or (not isinstance(tolerance, (int, float)) and not hasattr(tolerance, "__float__")):
        raise TypeError(
            f"truncation tolerance must be a number in (0, 1); got {type(tolerance).__name__} {str(tolerance)[:40]!r}"
        )
    if not (0.0 < tolerance < 1.0):
        raise ValueError(f"truncation tolerance must be in (0, 1); got {tolerance!r}")
    return math.sqrt(2.0 * math.log(1.0 / tolerance))


def truncation_half_widths_um(
    lateral_resolution_um: float,
    axial_resolution_um: float,
    tolerance: float,
    *,
    lateral_resolution_y_um: float | None = None,
) -> tuple[float, float, float]:
    """Half-widths (x, y, z) in µm of the box outside which the amplitude PSF is below ``tolerance``
    (the semi-axes ``c·(s_x, s_y, s_z)`` of the tolerance ellipsoid)."""
    c = truncation_radius_factor(tolerance)
    sx = amplitude_sigma_lateral_um(lateral_resolution_um)
    sy = amplitude_sigma_lateral_um(_lateral_y(lateral_resolution_um, lateral_resolution_y_um))
    sz = amplitude_sigma_axial_um(axial_resolution_um)
    return (c * sx, c * sy, c * sz)


def truncation_error_bound(tolerance: float) -> float:
    """Upper bound on ``E|E - E_trunc|² / E|E|²`` for a PSF truncated at amplitude ``tolerance``.

    The left-out scatterers lie outside the ellipsoid ``Σ x_a²/s_a² = 2 ln(1/tol)``; their share of
    ``∫|h|²`` is ``P(χ²₃ > 4·ln(1/tol)) = Q(3/2, 2·ln(1/tol))``. Cross terms between scatterers
    average to zero (independent phases), so this is the relative mean-square field error; its square
    root bounds the relative RMS error of the signal. Tolerance 1e-2 (the default) gives 3.6e-4 (RMS
    1.9 %), 1e-3 gives 4.3e-6 (RMS 0.21 %); the box that is actually kept loses less (5e-5 and 4e-7
    of the mean intensity).
    """
    c = truncation_radius_factor(tolerance)
    x = c * c  # = 2 ln(1/tol); Q(3/2, x) = erfc(√x) + 2√(x/π)·e^{-x}
    return math.erfc(math.sqrt(x)) + 2.0 * math.sqrt(x / math.pi) * math.exp(-x)


#: Truncation modes of the simulator (``[simulation] truncation``).
TRUNCATION_MODES = ("hard", "taper")
#: Where the taper starts, as a fraction of ``ln(tolerance)``: the window is 1 for exponents above
#: ``TAPER_START·ln tol`` (amplitude ``tol^0.75``: 0.032 at tolerance 1e-2) and falls to 0 at ``ln tol``.
#: 0.75 about minimizes the change of the short-lag transit rate at tolerance 1e-2 (physics.md §5.9).
TAPER_START = 0.75


def taper_window(s: float) -> float:
    """The taper as a function of ``s = exponent/ln(tol) ∈ [0, 1]`` (0 at the PSF centre, 1 on the
    tolerance ellipsoid): 1 for ``s ≤ a = TAPER_START``, ``1 − t³(10 − 15t + 6t²)`` with
    ``t = (s − a)/(1 − a)`` between, 0 for ``s ≥ 1``; its first and second derivatives vanish at both
    ends (C²). The simulator evaluates the same polynomial in float32 (:mod:`torchdoct.sim.kernel`)."""
    a = TAPER_START
    if s <= a:
        return 1.0
    if s >= 1.0:
        return 0.0
    t = (s - a) / (1.0 - a)
    return 1.0 - t**3 * (10.0 - 15.0 * t + 6.0 * t * t)


@functools.lru_cache(maxsize=1)
def _gauss_legendre_64():
    """Nodes and weights of the 64-node Gauss–Legendre rule (an eigenproblem: computed once)."""
    import numpy as np

    return np.polynomial.legendre.leggauss(64)


def _shell_moment(tolerance: float, integrand_of_w) -> float:
    """``E[f(w(X/c²)); a·c² < X < c²]`` over ``X ~ Gamma(3/2, 1)`` (``X = Σ x_a²/s_a²``, weighted by
    ``|h|²``; density ``2√(X/π)·e^{−X}``), ``c² = 2 ln(1/tol)``, on the taper shell. The integrand is a
    polynomial in ``X`` times ``√X·e^{−X}``, analytic on the shell (``X > 0``), so a 64-node
    Gauss–Legendre rule gives it to rounding (the expansion of the polynomial into incomplete gamma
    functions cancels to ~1e-6 and is not used)."""
    import numpy as np

    c2 = truncation_radius_factor(tolerance) ** 2
    x0, x1 = TAPER_START * c2, c2
    nodes, weights = _gauss_legendre_64()
    x = 0.5 * (x1 - x0) * nodes + 0.5 * (x1 + x0)
    t = (x / c2 - TAPER_START) / (1.0 - TAPER_START)
    w = 1.0 - t**3 * (10.0 - 15.0 * t + 6.0 * t * t)
    dens = 2.0 * np.sqrt(x / math.pi) * np.exp(-x)
    return float(0.5 * (x1 - x0) * np.dot(weights, integrand_of_w(w) * dens))


def _gamma32_cdf(x: float) -> float:
    """``P(3/2, x) = 1 − Q(3/2, x)``, the Gamma(3/2, 1) distribution function."""
    return 1.0 - (math.erfc(math.sqrt(x)) + 2.0 * math.sqrt(x / math.pi) * math.exp(-x))


def truncation_field_error(tolerance: float, mode: str = "hard") -> float:
    """``E|E − E_trunc|² / E|E|²``: the relative mean-square change of the field by the truncation.

    ``E|E − E_trunc|² = ρ·b²·∫|h|²(1 − w)²`` (cross terms average to zero), so the ratio is
    ``E[(1 − w(X/c²))²]`` over ``X ~ Gamma(3/2)``. Hard (``w`` = 1 inside the ellipsoid):
    ``Q(3/2, 2 ln(1/tol))`` = :func:`truncation_error_bound` (3.6e-4 at 1e-2, 4.3e-6 at 1e-3). Taper:
    that plus the shell where the window is below 1 (:func:`_shell_moment`), 9.0e-4 at 1e-2 and 1.8e-5
    at 1e-3 (RMS 3.0 % and 0.43 %); the window is smooth, so this is a slightly different smooth PSF, not a source of
    decorrelation (physics.md §5.9).
    """
    if mode not in TRUNCATION_MODES:
        raise ValueError(f"truncation mode must be one of {TRUNCATION_MODES}; got {mode!r}")
    hard = truncation_error_bound(tolerance)
    if mode == "hard":
        return hard
    return hard + _shell_moment(tolerance, lambda w: (1.0 - w) ** 2)


def truncation_intensity_factor(tolerance: float, mode: str = "hard") -> float:
    """Mean intensity of the truncated PSF over that of the full one: ``E[w(X/c²)²]``, ``X ~ Gamma(3/2)``.

    Hard: ``1 − Q(3/2, 2 ln(1/tol))`` (the box the simulator keeps loses less; physics.md §5.9).
    Taper: ``P(3/2, a·c²) + E[W(t)²; shell]`` = 0.99857 at 1e-2, 0.999963 at 1e-3 (the shell's share
    by :func:`_shell_moment`).
    """
    if mode not in TRUNCATION_MODES:
        raise ValueError(f"truncation mode must be one of {TRUNCATION_MODES}; got {mode!r}")
    if mode == "hard":
        return 1.0 - truncation_error_bound(tolerance)
    c2 = truncation_radius_factor(tolerance) ** 2
    return _gamma32_cdf(TAPER_START * c2) + _shell_moment(tolerance, lambda w: w * w)


def noise_power(mean_intensity, snr_db: float):
    """Noise power ``N₀ = ⟨I⟩ / 10^(snr_db/10)`` (intensity units, those of ``⟨I⟩ = |E|²``) of additive
    circular complex Gaussian noise at ``snr_db`` (dB) below the mean noise-free intensity
    ``mean_intensity`` (physics.md §5.2, §8; :class:`torchdoct.sim.config.Noise`).

    ``mean_intensity`` is a number or an array/tensor (one value per system); the result has its type.
    """
    return mean_intensity / 10.0 ** (snr_db / 10.0)


def noise_sigma(mean_intensity, snr_db: float):
    """Standard deviation ``√(N₀/2)`` (field units, ``√`` of intensity) of each of the real and the
    imaginary part of the noise at ``snr_db`` (dB) below ``mean_intensity``: ``N₀`` is
    :func:`noise_power`, split evenly between the two quadratures (physics.md §8).

    A number gives a float; a torch tensor or numpy array gives one of its type and dtype.
    """
    var = noise_power(mean_intensity, snr_db) / 2.0
    if isinstance(var, (int, float)):
        return math.sqrt(var)
    sqrt = getattr(var, "sqrt", None)
    if sqrt is not None:
        return sqrt()
    import numpy as np

    return np.sqrt(var)

"""Doppler phase against a static-tissue reference (``torchdoct maps --doppler``; docs/concepts/doppler-reference.md).

Channels ``doppler_phase_{m}`` (rad) at the original resolution, one per lag ``m`` (frames): for each pixel
``p``, with the lag-``m`` products ``C_t(p) = E_{t+m}(p)·E_t*(p)`` (``t = 0 … T−m−1``) and the reference sum
``R_t = Σ_{q ∈ ref} C_t(q)`` of its A-line (or, when the A-line has too few reference pixels, of its B-scan),

    doppler_phase_m(p) = arg Σ_t C_t*(p) · r_t(p)/|r_t(p)|,     r_t(p) = R_t − [p ∈ ref]·C_t(p)

(leave-one-out: a reference pixel is measured against the others). A phase ``φ_t`` common to the
reference and the pixel at each frame (bulk motion) cancels exactly. The sign is that of ``g1_phase_m``
(:mod:`torchdoct.sim.signature`): scatterers moving deeper at ``v_z`` give ``−2kn·v_z·m·Δt`` (wrapped to
(−π, π]); random-ballistic motion and diffusion give a phase symmetric about 0.

**Reference pixels** (per scope: the A-line, or the B-scan; docs/concepts/doppler-reference.md §4): a pixel
is a candidate when its intensity is *steady*, temporal contrast ``Var_t I/(mean_t I)²`` at most
:data:`REFERENCE_CONTRAST` (the bulk-invariant ``stable`` rule of :mod:`torchdoct.measured.bulkphase`; a
static pixel at pixel SNR ``s`` has ``(2s + 1)/(s + 1)²``, so a candidate has ``s ≳``
:func:`min_reference_snr` and lies above the noise floor), and *white*, its von Neumann ratio at least
:func:`min_whiteness` (noise, not a drift). Slow flow can pass both where its speckle sits near an
intensity extremum, so the candidates are then split by phase: their phases relative to the sum of all
candidates are histogrammed (bins of width ``h``, each weighted by ``1 − contrast/C``, the steadier the
heavier), the peak population (within ``1.5·h`` of the peak bin's centre) gives a sum, and the candidates
within ``h`` of it are the reference. ``h`` is 3.5 standard deviations of a static pixel's phase at the SNR
floor (:func:`phase_tolerance`). The population counts when significantly more than :data:`MIN_WHITE_SHARE`
of the steady pixels within ``h`` of it are white (:func:`white_population`): static tissue is white nearly
everywhere, slow flow mostly drifts. And the population must be steady as a whole: the mean over its pixels of
the lag-1 autocorrelation of their intensity fluctuations (:func:`drift_statistic`) is at most
:func:`max_population_drift` (a flow that is the steadiest population of a static-free sample hides its
drift under the noise pixel by pixel, not over hundreds of pixels), or its drift's contrast is at most
:data:`MAX_DRIFT_CONTRAST` (too small to move the phase). Last, its speckle pattern must have stayed in place:
not significantly more than :data:`MAX_MOVED_SHARE` of its pixels moved theirs (:func:`pattern_statistic`,
:func:`moved_population`). The product of axially neighbouring fields cancels the bulk phase and a flow's own
Doppler rotation, so a flow whose intensity drift hides under the noise, even over tens of pixels (at a low
SNR), still shows its pattern sliding.

**Scope and minimum**: an A-line with at least :data:`MIN_REFERENCE_PIXELS` reference pixels uses its
own reference; otherwise its B-scan's (the same rule on all the B-scan's pixels, which assumes a bulk
phase common to the B-scan at each frame; with ``--bulk-phase`` the per-A-line estimate is removed first);
otherwise the pixel is NaN. When no A-line or B-scan has a reference at a lag, that lag's channel is absent
and ``meta["doppler"]`` says why; intensity-only input gives no channel and a note.

**Memory**: the reference needs whole A-lines (every depth row and frame), so it is estimated first, in
lateral slabs of whole A-lines (:func:`estimate_doppler_reference`; the B-scan scope of a B-scan split
into several slabs takes four passes); only the reference sums ``[T−m, (Y), X]`` and a reference mask
``[(Y), Z, X]`` are kept, and the channel is computed per pixel in the maps' own slabs (any cut).

Kept whole (over 800 lines): the reference rule's seven steps, the constants they share, the slab and
four-pass streaming that evaluates them, the channel and the metadata that records the rule are one
definition; split, a change to a step would have to be mirrored across modules to keep the recorded rule
true.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence as _Seq
from typing import Any

import numpy as np
import torch

from ..conventions import uniform_frame_interval_s, wavenumber_per_um
from ..runtime.interrupt import progress_disabled
from .bulkphase import STABLE_CONTRAST
from .sequence import SequenceData

__all__ = [
    "DEFAULT_DOPPLER_LAGS",
    "REFERENCE_CONTRAST",
    "MIN_REFERENCE_PIXELS",
    "MIN_WHITE_SHARE",
    "MAX_POPULATION_DRIFT",
    "drift_statistic",
    "max_population_drift",
    "MAX_DRIFT_CONTRAST",
    "PATTERN_MOVED_MIN",
    "PATTERN_CHANGE_MIN",
    "MAX_MOVED_SHARE",
    "pattern_statistic",
    "moved_population",
    "WHITE_TEST_LEVEL",
    "MIN_BSCAN_COVERAGE",
    "PHASE_TOLERANCE_Z",
    "REFERENCE_RULE",
    "min_reference_snr",
    "min_whiteness",
    "white_population",
    "phase_tolerance",
    "doppler_lags",
    "DopplerReference",
    "estimate_doppler_reference",
    "doppler_absent",
    "doppler_channel_records",
    "doppler_slab",
    "doppler_name",
]

#: The lags (frames) of ``--doppler`` without ``--doppler-lags``: the shortest, the widest velocity range.
DEFAULT_DOPPLER_LAGS = (1,)
#: Largest temporal intensity contrast of a reference candidate (the ``stable`` rule of the bulk phase).
REFERENCE_CONTRAST = STABLE_CONTRAST
#: Fewest reference pixels of a scope: the reference's phase variance per frame pair is ``1/N`` of one of
#: its pixels' (to first order in the noise), so at ``N ≥ 10`` it adds at most 10 % to the variance of a
#: pixel at the reference's SNR.
MIN_REFERENCE_PIXELS = 10
#: A reference population's steady, in-phase pixels must be white significantly more often than this share
#: (a majority), at the level below (:func:`white_population`).
MIN_WHITE_SHARE = 0.5
WHITE_TEST_LEVEL = 0.01
#: Largest mean, over a reference population's pixels, of the lag-1 autocorrelation of their intensity
#: fluctuations (:func:`drift_statistic`): white fluctuations (static tissue and noise) give ``−1/T`` in
#: expectation, a constant intensity 0, a drift its share of the fluctuation (docs/concepts/doppler-reference.md
#: §4, step 6).
MAX_POPULATION_DRIFT = 0.05
#: Largest mean, over a reference population's pixels, of the lag-1 autocovariance of their intensity in units
#: of the squared mean intensity (the drift's contrast, :func:`drift_statistic`) that counts as no drift
#: whatever its share of the fluctuation: a 25th of :data:`REFERENCE_CONTRAST`, a drift of at most about
#: 4.5 % rms of the intensity. A moving share ``ε`` of a pixel's field drifts its intensity by about ``2ε`` rms
#: and its phase by at most about ``ε`` rad, so such a reference moves its phase by about 0.02 rad at most:
#: static tissue whose intensity follows a moving neighbour's PSF tail stays a reference.
MAX_DRIFT_CONTRAST = REFERENCE_CONTRAST / 25
#: Significance (:func:`pattern_statistic`, 0) above which a pixel's speckle pattern moved (step 7): for static
#: tissue in white noise each of a pixel's pairs is exponential with mean 1 and exceeds it with probability
#: ``e^{−2}``; a flow whose Doppler phase the reference would carry exceeds it in most of its pixels
#: (docs/concepts/doppler-reference.md §4).
PATTERN_MOVED_MIN = 2.0
#: Size (:func:`pattern_statistic`, 1) from which a significant change counts as moved: a moving share ``ε`` of
#: a pixel's field changes it by at most about ``2ε`` and turns the pixel's phase by at most about ``ε`` rad,
#: so static tissue that shares its PSF with a slowly moving neighbour (or slow random motion, whose phase is
#: symmetric about 0 anyway) stays a reference unless its moving share could turn its phase by a few
#: hundredths of a radian or more.
PATTERN_CHANGE_MIN = 0.1
#: A reference population counts unless significantly more than this share of its pixels moved their pattern
#: (one-sided binomial test at :data:`WHITE_TEST_LEVEL`): static tissue moves its pattern only by the noise's
#: chance and where the PSF shares it with a moving neighbour (a layer's edge).
MAX_MOVED_SHARE = 0.4
#: A B-scan's reference counts when at least this share of its A-lines with a candidate hold some of its
#: pixels: the bulk phase it removes is common to the B-scan.
MIN_BSCAN_COVERAGE = 0.5
#: Half width of the reference population, in standard deviations of a static pixel's phase.
PHASE_TOLERANCE_Z = 3.5
#: The rule, as the maps' metadata record it.
REFERENCE_RULE = (
    "reference pixels: temporal intensity contrast Var_t I/(mean_t I)^2 <= {c:g} (a static pixel at "
    "SNR >= {s:.1f}, above the noise floor) and white intensity fluctuations (von Neumann ratio "
    "sum (I_(t+1) - I_t)^2 / (2 sum (I_t - mean I)^2) >= {w:.3f}: noise, no drift); then the peak "
    "population of their phases relative to the sum of all of them (histogram of bin width h, weights "
    "1 - contrast/{c:g}); then those within h of that population's sum; the population counts when "
    "more than {ws:.0%} of the steady pixels within h of it are white (one-sided binomial test at "
    "{lv:g}) and the mean over its pixels of the lag-1 autocorrelation of their intensity fluctuations is at "
    "most {dr:g} plus 3.5 standard errors of a white population's, or the mean lag-1 autocovariance over the "
    "squared mean intensity is at most {dc:g} (steady as a population: no common drift); and not significantly more "
    "than {ms:.3g} of its pixels moved their speckle pattern (the product of axially neighbouring fields, which "
    "cancels a common phase, changed from the first half of the frames to the second by more than {pm:g} times its "
    "noise variance and by at least {pc:g} of the pair's intensity; one-sided binomial test at {lv:g}); scope: the "
    "A-line with >= {n} "
    "reference pixels, else its B-scan with >= {n} whose reference reaches >= {cov:.0%} of the A-lines "
    "with a candidate, else none (NaN); channel: arg sum_t conj(C_t(p)) "
    "r_t/|r_t|, C_t = E_(t+m) conj(E_t), r_t the reference sum without p"
)


def doppler_name(m: int) -> str:
    """The channel's metric name at lag ``m``."""
    return f"doppler_phase_{int(m)}"


def min_reference_snr(contrast: float = REFERENCE_CONTRAST) -> float:
    """The pixel SNR ``s`` (signal intensity over noise power) at which a static pixel's expected contrast
    ``(2s + 1)/(s + 1)²`` equals ``contrast``: ``((1 − C) + √(1 − C))/C``."""
    c = float(contrast)
    return ((1.0 - c) + math.sqrt(1.0 - c)) / c


def phase_tolerance(
    m: int,
    n_frames: int,
    *,
    contrast: float = REFERENCE_CONTRAST,
    min_pixels: int = MIN_REFERENCE_PIXELS,
    z: float = PHASE_TOLERANCE_Z,
) -> float:
    """``h`` (rad): ``z`` standard deviations of the lag-``m`` phase of a static pixel at the SNR floor ``s``
    relative to a reference of ``min_pixels`` such pixels, over ``T − m`` frame pairs. To first order in the
    noise the per-frame errors telescope, ``Var = (1 + 1/N)·m/(s(T − m)²)``; the noise-times-noise part adds
    ``(1 + 1/N)/(2s²(T − m))`` (docs/concepts/doppler-reference.md §3)."""
    s = min_reference_snr(contrast)
    n = n_frames - m
    var = (1.0 + 1.0 / min_pixels) * (m / (s * n * n) + 1.0 / (2.0 * s * s * n))
    return z * math.sqrt(var)


def doppler_lags(seq: SequenceData, lags: bool | _Seq[int] | None) -> tuple[int, ...]:
    """The lags asked (``True``: :data:`DEFAULT_DOPPLER_LAGS`), checked before any work: integers
    ``1 ≤ m < T``, a uniform frame interval, B-scans or a volume."""
    if lags is None or lags is False:
        return ()
    src = seq.source or "sequence"
    out = DEFAULT_DOPPLER_LAGS if lags is True else tuple(lags)
    if not out:
        raise ValueError("--doppler-lags: give at least one lag (frames)")
    t = seq.n_frames
    for m in out:
        if isinstance(m, bool) or not float(m).is_integer() or not 1 <= int(m) < t:
            raise ValueError(f"{src}: a Doppler lag must be a whole number of frames 1 <= m < {t}; got {m!r}")
    out = tuple(int(m) for m in out)
    if len(set(out)) != len(out):
        raise ValueError(f"--doppler-lags: lag given twice in {list(out)}")
    if seq.axes not in ("TZX", "TYZX"):
        raise ValueError(f"{src}: the Doppler channels need B-scans (TZX) or a volume (TYZX); got {seq.axes}")
    if uniform_frame_interval_s(seq.frame_times_s) is None:
        raise ValueError(
            f"{src}: the Doppler channels need a uniform frame interval (the phase per lag is a "
            "velocity only at one delay)"
        )
    for m in out:
        if t - m < 2:
            raise ValueError(f"{src}: Doppler lag {m} leaves {t - m} frame pair of {t} frames; give a lag <= {t - 2}")
    return out


@dataclasses.dataclass
class DopplerReference:
    """The reference of every lag: ``sums[m]`` the reference sum ``R_t`` each A-line uses (``[T−m, (Y), X]``,
    complex128, 0 where none), ``scope[m]`` per A-line (``[(Y), X]`` int8: 1 its own, 2 its B-scan's, 0
    none), ``mask[m]`` the pixels in the reference their A-line uses (``[(Y), Z, X]`` bool), and the counts
    of the metadata. ``lags``: the lags with a reference somewhere (their channels exist)."""

    asked: tuple[int, ...]
    lags: tuple[int, ...]
    sums: dict[int, np.ndarray]
    scope: dict[int, np.ndarray]
    mask: dict[int, np.ndarray]
    info: dict[int, dict[str, Any]]
    frame_interval_s: float
    wavelength_um: float | None
    refractive_index: float
    bulk_corrected: bool
    n_frames: int

    def meta(self) -> dict[str, Any]:
        """``meta["doppler"]`` of the maps."""
        per_lag = {}
        for m in self.asked:
            rec = dict(self.info[m])
            rec["channel"] = doppler_name(m) if m in self.lags else None
            rec["phase_tolerance_rad"] = rec.pop("h")
            if self.wavelength_um is not None:
                kn = wavenumber_per_um(self.wavelength_um, self.refractive_index)
                tau = m * self.frame_interval_s
                rec["vz_um_per_s_per_rad"] = -1.0 / (2.0 * kn * tau)
                rec["nyquist_vz_um_per_s"] = math.pi / (2.0 * kn * tau)
            per_lag[str(m)] = rec
        out: dict[str, Any] = {
            "lags": list(self.asked),
            "channels": [doppler_name(m) for m in self.lags],
            "unit": "rad",
            "sign": "g1_phase convention: scatterers moving deeper at v_z give -2kn*v_z*m*dt (wrapped)",
            "rule": REFERENCE_RULE.format(
                c=REFERENCE_CONTRAST,
                s=min_reference_snr(),
                n=MIN_REFERENCE_PIXELS,
                w=min_whiteness(self.n_frames),
                ws=MIN_WHITE_SHARE,
                lv=WHITE_TEST_LEVEL,
                cov=MIN_BSCAN_COVERAGE,
                dr=MAX_POPULATION_DRIFT,
                dc=MAX_DRIFT_CONTRAST,
                ms=MAX_MOVED_SHARE,
                pm=PATTERN_MOVED_MIN,
                pc=PATTERN_CHANGE_MIN,
            ),
            "min_bscan_coverage": MIN_BSCAN_COVERAGE,
            "max_population_drift": MAX_POPULATION_DRIFT,
            "max_drift_contrast": MAX_DRIFT_CONTRAST,
            "pattern_moved_min": PATTERN_MOVED_MIN,
            "pattern_change_min": PATTERN_CHANGE_MIN,
            "max_moved_share": MAX_MOVED_SHARE,
            "min_white_share": MIN_WHITE_SHARE,
            "min_whiteness": min_whiteness(self.n_frames),
            "reference_contrast": REFERENCE_CONTRAST,
            "min_reference_snr": min_reference_snr(),
            "min_reference_pixels": MIN_REFERENCE_PIXELS,
            "bulk_phase_removed_first": self.bulk_corrected,
            "per_lag": per_lag,
            "definition": "torchdoct.measured.doppler (docs/concepts/doppler-reference.md)",
        }
        if self.wavelength_um is not None:
            out["refractive_index"] = self.refractive_index
        if not self.lags:
            out["absent"] = (
                "no A-line and no B-scan holds the reference the rule needs (at least "
                f"{MIN_REFERENCE_PIXELS} steady, white, phase-consistent pixels whose population "
                "fluctuates as noise, not as a drift, and keeps its speckle pattern in place): no static "
                "tissue to measure the Doppler phase against, so no channel rather than a made-up value"
            )
        return out


def doppler_absent(seq: SequenceData, lags: _Seq[int]) -> dict[str, Any]:
    """``meta["doppler"]`` when the input holds intensity only: no channel, and why."""
    return {
        "lags": list(lags),
        "channels": [],
        "absent": f"{seq.source or 'the sequence'} holds intensity only: the Doppler phase needs the complex field",
        "definition": "torchdoct.measured.doppler",
    }


# ----------------------------------------------------------------------------------------------
# the pieces of the estimate (A-lines ``[T, L, Z]``; groups of pixels ``[G, S]``, below)


def min_whiteness(n_frames: int, z: float = PHASE_TOLERANCE_Z) -> float:
    """Smallest von Neumann ratio ``η = Σ_t (I_{t+1} − I_t)² / (2 Σ_t (I_t − Ī)²)`` of a reference candidate:
    ``z`` standard deviations below its mean 1 for white fluctuations (noise about a static field), with
    ``Var η = (T − 2)/((T − 1)(T + 1))``; a drift (slow flow) or a slow decorrelation gives ``η ≪ 1``."""
    t = int(n_frames)
    return 1.0 - z * math.sqrt((t - 2) / ((t - 1) * (t + 1)))


def max_population_drift(n_pixels: np.ndarray, n_frames: int, z: float = PHASE_TOLERANCE_Z) -> np.ndarray:
    """Largest mean :func:`drift_statistic` of a reference population of ``n_pixels`` pixels:
    :data:`MAX_POPULATION_DRIFT` plus ``z`` standard errors of the mean for white fluctuations (a pixel's
    lag-1 autocorrelation has about the variance of the von Neumann ratio, ``(T − 2)/((T − 1)(T + 1))``,
    :func:`min_whiteness`), so that a small static population is not rejected by chance."""
    t = int(n_frames)
    sd = math.sqrt((t - 2) / ((t - 1) * (t + 1)))
    return MAX_POPULATION_DRIFT + z * sd / np.sqrt(np.maximum(np.asarray(n_pixels, dtype=np.float64), 1.0))


def drift_statistic(inten: torch.Tensor) -> torch.Tensor:
    """Per pixel of intensities ``[T, ...]``, stacked ``[2, ...]``: the lag-1 autocorrelation of its
    fluctuations, ``Σ_t d_t·d_{t+1} / Σ_t d_t²`` with ``d_t = I_t − mean_t I`` (0 for a constant intensity),
    and the drift's contrast, ``Σ_t d_t·d_{t+1} / ((T − 1)·(mean_t I)²)`` (0 for a zero mean). White
    fluctuations give the first ``−1/T`` in expectation; a drift raises it towards 1 by its share of the
    variance, and the second by its own contrast."""
    mean = inten.mean(0)
    return _drift(inten - mean, mean)


def _drift(dev: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """:func:`drift_statistic` from the fluctuations ``dev [T, ...]`` about the temporal ``mean``."""
    num, den = (dev[1:] * dev[:-1]).sum(0), (dev * dev).sum(0)
    r1 = torch.where(den > 0, num / torch.where(den > 0, den, torch.ones_like(den)), torch.zeros_like(den))
    sq = (dev.shape[0] - 1) * mean * mean
    return torch.stack(
        [r1, torch.where(sq > 0, num / torch.where(sq > 0, sq, torch.ones_like(sq)), torch.zeros_like(sq))]
    )


def pattern_statistic(lines: torch.Tensor) -> torch.Tensor:
    """Per pixel of A-lines ``[T, L, Z]`` (complex), how far its speckle pattern moved over the sequence, read
    against its axial neighbours (``[2, L, Z]`` float64; docs/concepts/doppler-reference.md §4, step 7). For
    each pair of adjacent depths, the products ``P_t = E_t(z+1)·E_t*(z)``: a phase common to both pixels
    cancels (the bulk phase, and a flow's own Doppler rotation), so ``P_t`` changes only where the pattern
    changes. Of a pair, with ``ΔP = P̄_2 − P̄_1`` the change of the mean of ``P_t`` from the first ``⌊T/2⌋``
    frames to the last ``⌊T/2⌋``:

    0. its significance, ``|ΔP|²`` over its variance under white noise, ``2v/⌊T/2⌋`` with
       ``v = Σ_t |P_{t+1} − P_t|² / (2(T − 1))`` (from successive differences, which a slow change barely
       touches): static tissue in white noise gives an exponential statistic of mean 1 (0 without noise: a
       constant ``P_t``), a pattern that slides by a fair part of the PSF many times that;
    1. its size, ``|ΔP|`` over ``√(Ī(z)·Ī(z+1))`` (the largest ``|P̄|`` the two intensities allow): a moving
       share ``ε`` of the pixels' fields changes it by at most about ``2ε``.

    A pixel's values are the means over its pairs (one at either end of the A-line). NaN where a sample is not
    finite; 0 for an A-line of one pixel (no pair to read)."""
    n_t, n_z = lines.shape[0], lines.shape[-1]
    if n_z < 2 or n_t < 2:
        return torch.zeros((2,) + tuple(lines.shape[1:]), dtype=torch.float64)
    half = n_t // 2
    first = torch.zeros(lines.shape[1:-1] + (n_z - 1,), dtype=torch.complex128)
    last, v = torch.zeros_like(first), torch.zeros(first.shape, dtype=torch.float64)
    inten = torch.zeros(lines.shape[1:], dtype=torch.float64)
    prev = None
    for t in range(n_t):  # frame by frame: [L, Z−1] accumulators, not a [T, L, Z−1] array
        x = lines[t].to(_work_dtype(lines))
        inten += (x.real.double() ** 2 + x.imag.double() ** 2) / n_t
        p = (x[..., 1:] * x[..., :-1].conj()).to(torch.complex128)
        if t < half:
            first += p
        if t >= n_t - half:
            last += p
        if prev is not None:
            v += (p - prev).abs().square()
        prev = p
    delta = ((last - first) / half).abs()
    change = delta.square()
    v /= 2.0 * (n_t - 1)
    noise = 2.0 * v / half
    sig = torch.where(noise > 0, change / torch.where(noise > 0, noise, torch.ones_like(noise)), change * math.inf)
    sig = torch.where(change == 0, torch.zeros_like(sig), sig)  # a constant product (noise-free static): 0
    scale = torch.sqrt(inten[..., 1:] * inten[..., :-1])
    size = torch.where(
        scale > 0, delta / torch.where(scale > 0, scale, torch.ones_like(scale)), torch.zeros_like(delta)
    )
    out = torch.zeros((2,) + tuple(lines.shape[1:]), dtype=torch.float64)
    count = torch.zeros(lines.shape[1:], dtype=torch.float64)
    for k, pair in enumerate((sig, size)):
        out[k, ..., :-1] += pair
        out[k, ..., 1:] += pair
    count[..., :-1] += 1.0
    count[..., 1:] += 1.0
    return out / count


def _candidates(lines: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(candidate, steady [L, Z] bool, weight [L, Z], drift [3, L, Z] float64)`` of A-lines ``[T, L, Z]``: steady
    (contrast) and white (no drift: the von Neumann ratio; a constant intensity counts as white) intensity;
    the drift statistic of every pixel (:func:`drift_statistic`) and, third, 1 where its pattern moved
    (:func:`pattern_statistic`: significance above :data:`PATTERN_MOVED_MIN` and size at least
    :data:`PATTERN_CHANGE_MIN`, or not finite), else 0."""
    inten = (lines.real**2 + lines.imag**2).double()
    mean = inten.mean(0)
    dev = inten - mean
    dev2 = (dev * dev).sum(0)
    contrast = dev2 / inten.shape[0] / torch.where(mean > 0, mean * mean, torch.ones_like(mean))
    steps2 = ((inten[1:] - inten[:-1]) ** 2).sum(0)
    white = (steps2 >= 2.0 * min_whiteness(inten.shape[0]) * dev2) | (dev2 == 0)
    steady = (contrast <= REFERENCE_CONTRAST) & (mean > 0) & torch.isfinite(contrast)
    cand = steady & white
    w = torch.where(cand, 1.0 - contrast / REFERENCE_CONTRAST, torch.zeros_like(contrast))
    sig, size = pattern_statistic(lines)
    moved = (~((sig <= PATTERN_MOVED_MIN) | (size < PATTERN_CHANGE_MIN))).double()
    return cand, steady, w, torch.cat([_drift(dev, mean), moved[None]])


def white_population(n_white: np.ndarray, n_steady: np.ndarray) -> np.ndarray:
    """Whether a reference population is static tissue: of the ``n_steady`` steady pixels in phase with it
    (within ``h``), ``n_white`` fluctuate as white noise, significantly more than :data:`MIN_WHITE_SHARE`
    (one-sided binomial test at :data:`WHITE_TEST_LEVEL`). A static pixel fails the per-pixel test with the
    probability of a 3.5-sd excursion (only pixels that share the PSF with a moving neighbour drift); slow
    flow passes it only where its speckle sits near an intensity extremum, and as a population mostly drifts.
    The test is on a count, so a few drifting pixels at a layer's edge do not reject a large population, and
    a small one must be clearly white."""
    n = np.asarray(n_steady, dtype=np.int64)
    return (n > 0) & (np.asarray(n_white) >= _binomial_threshold(n, MIN_WHITE_SHARE, WHITE_TEST_LEVEL))


def moved_population(n_moved: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Whether a reference population's speckle pattern moved (step 7): of its ``n`` pixels, ``n_moved`` moved
    theirs (:func:`pattern_statistic`: significance above :data:`PATTERN_MOVED_MIN`, size at least
    :data:`PATTERN_CHANGE_MIN`), significantly more than
    :data:`MAX_MOVED_SHARE` (one-sided binomial test at :data:`WHITE_TEST_LEVEL`). A flow steadier than its
    noise passes the intensity tests (steps 2, 4 and 6) but carries its pattern along; the product of two
    neighbouring pixels' fields cancels its Doppler rotation and the bulk phase, so the pattern's motion shows
    even where the intensity barely changes."""
    n = np.asarray(n, dtype=np.int64)
    return (n > 0) & (np.asarray(n_moved) >= _binomial_threshold(n, MAX_MOVED_SHARE, WHITE_TEST_LEVEL))


def _binomial_threshold(n: np.ndarray, p: float, level: float) -> np.ndarray:
    """The smallest ``k`` with ``P(X ≥ k) ≤ level`` for ``X ~ Binomial(n, p)`` (elementwise; bisection on
    :func:`scipy.special.bdtr`)."""
    from scipy.special import bdtr

    lo, hi = np.zeros_like(n), n + 1
    while (lo < hi).any():
        mid = (lo + hi) // 2
        tail = np.where(mid > 0, 1.0 - bdtr(np.maximum(mid - 1, 0), n, p), 1.0)  # P(X >= mid)
        small = tail <= level
        hi = np.where((lo < hi) & small, mid, hi)
        lo = np.where((lo < hi) & ~small, mid + 1, lo)
    return lo


def _products(x: torch.Tensor, m: int) -> torch.Tensor:
    """``C_t = E_{t+m} E_t*`` (``[T−m, ...]``, complex128 for double-precision data, else complex64), 0 where
    not finite."""
    x = x.to(_work_dtype(x))
    c = x[m:] * x[:-m].conj()
    fin = torch.isfinite(c)
    return c if bool(fin.all()) else torch.where(fin, c, torch.zeros_like(c))


def _work_dtype(x: torch.Tensor) -> torch.dtype:
    return torch.complex128 if x.dtype in (torch.complex128, torch.float64) else torch.complex64


def _unit(r: torch.Tensor) -> torch.Tensor:
    a = r.abs()
    return torch.where(a > 0, r / torch.where(a > 0, a, torch.ones_like(a)), torch.zeros_like(r))


# The rule runs on groups of pixels (a scope each: an A-line, or a B-scan) held as ``[G, S]`` (``S`` pixels per
# group), the products as ``[K, G, S]`` and the reference sums as ``[K, G]`` (``K = T − m`` frame pairs).


def _group_sum(c: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    return torch.einsum("kgs,gs->kg", c, sel.to(c.dtype))


def _phase_to(c: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Each pixel's phase relative to its group's reference sum: ``arg Σ_t C_t · conj(R_t/|R_t|)`` ``[G, S]``."""
    return torch.angle(torch.einsum("kgs,kg->gs", c, _unit(ref).conj()))


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


def _n_bins(h: float) -> int:
    return max(8, int(math.ceil(2.0 * math.pi / h)))


def _histogram(psi: torch.Tensor, w: torch.Tensor, h: float) -> torch.Tensor:
    """``[G, bins]``: each group's ``w``-weighted histogram of ``psi`` over (−π, π]."""
    nb = _n_bins(h)
    g = psi.shape[0]
    b = torch.clamp(((psi + math.pi) / (2.0 * math.pi) * nb).long(), 0, nb - 1)
    b = b + torch.arange(g)[:, None] * nb
    return torch.zeros(g * nb, dtype=torch.float64).index_add_(0, b.reshape(-1), w.reshape(-1)).reshape(g, nb)


def _peak_centres(hist: torch.Tensor) -> torch.Tensor:
    """The centre (rad) of each group's peak bin of the histogram smoothed by three bins (circular)."""
    nb = hist.shape[1]
    sm = hist + torch.roll(hist, 1, 1) + torch.roll(hist, -1, 1)
    return (sm.argmax(1).double() + 0.5) * (2.0 * math.pi / nb) - math.pi


def _near_peak(psi: torch.Tensor, centre: torch.Tensor, h: float) -> torch.Tensor:
    """Within 1.5 bins of the peak bin's centre (``centre [G]``)."""
    return _wrap(psi - centre[:, None]).abs() <= 1.5 * 2.0 * math.pi / _n_bins(h)


def _last_step(
    c: torch.Tensor, cand: torch.Tensor, steady: torch.Tensor, drift: torch.Tensor, r1: torch.Tensor, h: float
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray, np.ndarray]:
    """The candidates within ``h`` of the population's sum ``r1``: ``(their sums [K, G], the pixels [G, S],
    their count [G], the steady pixels within h [G], the sums of their drift statistics and pattern-moved flags [3, G])``."""
    in_phase = _phase_to(c, r1).abs() <= h
    sel = cand & in_phase
    return (
        _group_sum(c, sel),
        sel,
        sel.sum(-1).numpy().astype(np.int64),
        (steady & in_phase).sum(-1).numpy().astype(np.int64),
        torch.where(sel, drift, torch.zeros_like(drift)).sum(-1).numpy(),
    )


def _select_complete(
    c: torch.Tensor, cand: torch.Tensor, steady: torch.Tensor, w: torch.Tensor, drift: torch.Tensor, h: float
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray, np.ndarray]:
    """The rule on groups whose pixels are all here (``c [K, G, S]``, the masks and weights ``[G, S]``): the
    candidates' sum, the peak of their phase histogram, the peak population's sum, then :func:`_last_step`."""
    psi = _phase_to(c, _group_sum(c, cand))
    sel = cand & _near_peak(psi, _peak_centres(_histogram(psi, w, h)), h)
    return _last_step(c, cand, steady, drift, _group_sum(c, sel), h)


def _slab_lines(block: torch.Tensor, volume: bool) -> torch.Tensor:
    """A-lines ``[T, L, Z]`` of a lateral slab (``[T, Z, Xs]`` or ``[T, Ys, Z, X]``)."""
    if volume:
        t, ys, z, x = block.shape
        return block.permute(0, 1, 3, 2).reshape(t, ys * x, z)
    return block.permute(0, 2, 1)


@torch.no_grad()
def estimate_doppler_reference(
    seq: SequenceData,
    lags: _Seq[int],
    *,
    bulk: np.ndarray | None = None,
    slab_elements: int = 1 << 23,
    progress: bool = False,
) -> DopplerReference:
    """The reference of every lag (module docstring), in lateral slabs of whole A-lines (X columns of a
    B-scan sequence, whole B-scans of a volume) of at most ``slab_elements`` samples. ``bulk``: the bulk-phase
    phasor ``[T, (Y), 1, X]`` of :func:`torchdoct.measured.maps.compute_maps`, applied first. A B-scan scope
    whole in its slab (every B-scan of a volume, a B-scan sequence in one slab) is decided there; a B-scan
    split across slabs takes four more passes (:func:`_bscan_passes`)."""
    data, axes = seq.data, seq.axes
    volume = axes == "TYZX"
    n_t = data.shape[0]
    zdim = axes.index("Z")
    cdim = 1 if volume else 2
    n_c, n_z = data.shape[cdim], data.shape[zdim]
    lat_shape = tuple(s for d, s in enumerate(data.shape) if d not in (0, zdim))  # (Y, X) or (X,)
    n_lines = int(np.prod(lat_shape))
    per = int(np.prod(data.shape)) // n_c
    step = max(1, min(n_c, int(slab_elements) // max(per, 1)))
    slabs = [(c0, min(n_c, c0 + step)) for c0 in range(0, n_c, step)]
    native = data.dtype.newbyteorder("=")
    n_bscans = data.shape[1] if volume else 1
    n_x = data.shape[-1]
    hs = {m: phase_tolerance(m, n_t) for m in lags}
    own = {m: _Scope(n_t - m, n_lines, n_z, n_t) for m in lags}
    bscan = {m: _Scope(n_t - m, n_bscans, n_lines // n_bscans * n_z, n_t) for m in lags}
    split = not volume and len(slabs) > 1  # the one B-scan of a sequence spans several slabs
    n_cand = 0
    line_cand = np.zeros(n_lines, dtype=bool)  # the A-lines with a candidate
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=len(slabs), desc="doppler reference", unit="slab")

    def read(c0: int, c1: int) -> tuple[torch.Tensor, slice, slice]:
        """The slab's A-lines ``[T, L, Z]``, their rows among all A-lines and their B-scans."""
        sel = [slice(None)] * data.ndim
        sel[cdim] = slice(c0, c1)
        raw = np.array(data[tuple(sel)], dtype=native, copy=True)
        if bulk is not None:
            raw = np.multiply(raw, bulk[tuple(sel)])
        lines = _slab_lines(torch.from_numpy(raw), volume)
        first = c0 * n_x if volume else c0
        return lines, slice(first, first + lines.shape[1]), slice(c0, c1) if volume else slice(0, 1)

    for c0, c1 in slabs:  # the A-line scope (whole in its slab), and the B-scan scope where it is whole too
        lines, rows, bs = read(c0, c1)
        cand, steady, w, drift = _candidates(lines)  # [L, Z]
        n_cand += int(cand.sum())
        line_cand[rows] = cand.any(1).numpy()
        n_g = bs.stop - bs.start
        for m in lags:
            c = _products(lines, m)  # [K, L, Z]
            r, sel, n_sel, n_steady, d_sum = _select_complete(c, cand, steady, w, drift, hs[m])
            own[m].put(rows, r, sel, n_sel, n_steady, d_sum)
            if not split and not own[m].ok(rows).all():  # some A-line needs its B-scan's reference
                g = lambda a, n_g=n_g: a.reshape(*a.shape[:-2], n_g, -1)  # noqa: E731 (pixels by B-scan)
                r, sel, n_sel, n_steady, d_sum = _select_complete(g(c), g(cand), g(steady), g(w), g(drift), hs[m])
                bscan[m].put(bs, r, sel, n_sel, n_steady, d_sum)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    if split:
        need = [m for m in lags if not own[m].ok(slice(None)).all()]
        if need:
            _bscan_passes(read, slabs, need, hs, bscan, n_lines=n_lines)
    scope, out_sums, out_mask, info, present = {}, {}, {}, {}, []
    line_b = np.repeat(np.arange(n_bscans), n_x) if volume else np.zeros(n_lines, dtype=np.int64)
    for m in lags:
        use_own = own[m].ok(slice(None))
        # a B-scan's reference must be common to its A-lines: of those with a candidate, at least half hold
        # some in phase with it (a bulk phase that differs between A-lines leaves only the few that share it)
        lines_in = bscan[m].pixels.reshape(n_bscans, -1, n_z).any(-1).sum(1)
        lines_cand = line_cand.reshape(n_bscans, -1).sum(1)
        coverage = lines_in / np.maximum(lines_cand, 1)
        b_ok = bscan[m].ok(slice(None)) & (coverage >= MIN_BSCAN_COVERAGE)
        fall = ~use_own & b_ok[line_b]
        sc = np.where(use_own, 1, np.where(fall, 2, 0)).astype(np.int8)
        s = np.where(use_own[None], own[m].sums, np.where(fall[None], bscan[m].sums[:, line_b], 0))
        pixels_b = bscan[m].pixels.reshape(n_lines, n_z)  # the B-scan scope's pixels, by A-line
        mk = np.where(use_own[:, None], own[m].pixels, fall[:, None] & pixels_b)  # [L, Z]
        scope[m] = sc.reshape(lat_shape)
        out_sums[m] = s.reshape(n_t - m, *lat_shape)
        out_mask[m] = np.moveaxis(mk.reshape(*lat_shape, n_z), -1, -2)  # [(Y), Z, X]
        line_share = mk.sum(1) / n_z  # each A-line's pixels in the reference it uses
        info[m] = {
            "h": hs[m],
            "reference_pixels": int(mk.sum()),
            "reference_share": float(mk.sum()) / (n_lines * n_z),
            "candidate_share": n_cand / (n_lines * n_z),
            "alines": n_lines,
            "alines_own_reference": int(use_own.sum()),
            "alines_bscan_reference": int(fall.sum()),
            "alines_without_reference": int((sc == 0).sum()),
            "aline_reference_share": {
                "min": float(line_share.min()),
                "median": float(np.median(line_share)),
                "max": float(line_share.max()),
            },
            "bscans_with_reference": int(b_ok.sum()),
            "bscan_reference_share": [
                float(v) / (n_lines // n_bscans * n_z) if e else None
                for v, e in zip(bscan[m].count, bscan[m].evaluated)
            ],
            "bscan_aline_coverage": [float(v) if e else None for v, e in zip(coverage, bscan[m].evaluated)],
        }
        if (sc > 0).any():
            present.append(m)
    system = dict(seq.meta.get("system") or {})
    wl = system.get("wavelength_um")
    return DopplerReference(
        asked=tuple(lags),
        lags=tuple(present),
        sums=out_sums,
        scope=scope,
        mask=out_mask,
        info=info,
        frame_interval_s=float(uniform_frame_interval_s(seq.frame_times_s) or 0.0),
        wavelength_um=None if wl is None else float(wl),
        refractive_index=float(system.get("refractive_index") or 1.0),
        bulk_corrected=bulk is not None,
        n_frames=n_t,
    )


class _Scope:
    """The reference of every group of one scope kind (A-lines, or B-scans): sums ``[K, G]``, pixels ``[G, S]``
    (``S`` pixels per group, A-line by A-line and depth by depth), the count and the steady pixels in phase,
    and which groups were evaluated (a B-scan only where some A-line needs it)."""

    def __init__(self, k: int, n_groups: int, per_group: int, n_frames: int) -> None:
        self.n_frames = int(n_frames)
        self.sums = np.zeros((k, n_groups), dtype=np.complex128)
        self.count = np.zeros(n_groups, dtype=np.int64)
        self.steady = np.zeros(n_groups, dtype=np.int64)
        self.drift = np.zeros((3, n_groups), dtype=np.float64)  # sums of r1, drift contrast, pattern moved
        self.pixels = np.zeros((n_groups, per_group), dtype=bool)
        self.evaluated = np.zeros(n_groups, dtype=bool)

    def put(
        self, rows: slice, r: torch.Tensor, sel: torch.Tensor, n_sel: np.ndarray, n_steady: np.ndarray, drift
    ) -> None:
        self.sums[:, rows] = r.numpy()
        self.count[rows] = n_sel
        self.steady[rows] = n_steady
        self.drift[:, rows] = drift
        self.pixels[rows] = sel.numpy().reshape(self.pixels[rows].shape)
        self.evaluated[rows] = True

    def ok(self, rows: slice) -> np.ndarray:
        """Groups with a reference: enough pixels, white as a population (:func:`white_population`), no
        common drift (the mean lag-1 autocorrelation of its pixels, :func:`drift_statistic`, at most
        :func:`max_population_drift`, or the mean drift contrast at most :data:`MAX_DRIFT_CONTRAST`), and a
        pattern that held (:func:`moved_population` false)."""
        n = self.count[rows]
        per = np.maximum(n, 1)
        r1, contrast = self.drift[0, rows] / per, self.drift[1, rows] / per
        steady = (r1 <= max_population_drift(n, self.n_frames)) | (contrast <= MAX_DRIFT_CONTRAST)
        held = ~moved_population(np.rint(self.drift[2, rows]).astype(np.int64), n)
        return (n >= MIN_REFERENCE_PIXELS) & white_population(n, self.steady[rows]) & steady & held


def _bscan_passes(read, slabs, lags, hs, bscan: dict[int, _Scope], *, n_lines: int) -> None:
    """The B-scan scope of a B-scan sequence split across slabs, in four passes (one group, every pixel): the
    candidates' sum, their phase histogram, the peak population's sum, then :func:`_last_step`; results into
    ``bscan``."""
    sums: dict[int, list[torch.Tensor]] = {m: [] for m in lags}
    hist: dict[int, torch.Tensor] = {}
    sel_parts: dict[int, list[np.ndarray]] = {m: [] for m in lags}
    count = {m: np.zeros(1, dtype=np.int64) for m in lags}
    steady_n = {m: np.zeros(1, dtype=np.int64) for m in lags}
    drift_n = {m: np.zeros((3, 1), dtype=np.float64) for m in lags}
    for step in range(4):
        acc: dict[int, Any] = dict.fromkeys(lags, 0)
        for c0, c1 in slabs:
            lines, _, _ = read(c0, c1)
            cand, steady, w, drift = (a.reshape(*a.shape[:-2], 1, -1) for a in _candidates(lines))
            for m in lags:
                c = _products(lines, m).reshape(lines.shape[0] - m, 1, -1)
                if step == 0:
                    acc[m] = acc[m] + _group_sum(c, cand)
                    continue
                psi = _phase_to(c, sums[m][0])
                if step == 1:
                    acc[m] = acc[m] + _histogram(psi, w, hs[m])
                elif step == 2:
                    acc[m] = acc[m] + _group_sum(c, cand & _near_peak(psi, _peak_centres(hist[m]), hs[m]))
                else:
                    r, sel, n_sel, n_steady, d_sum = _last_step(c, cand, steady, drift, sums[m][1], hs[m])
                    acc[m] = acc[m] + r
                    sel_parts[m].append(sel.numpy().reshape(-1))
                    count[m] += n_sel
                    steady_n[m] += n_steady
                    drift_n[m] += d_sum
        for m in lags:
            if step == 1:
                hist[m] = acc[m]
            else:
                sums[m].append(acc[m])
    for m in lags:
        sel_all = torch.from_numpy(np.concatenate(sel_parts[m]))
        bscan[m].put(slice(0, 1), sums[m][2], sel_all, count[m], steady_n[m], drift_n[m])


# ----------------------------------------------------------------------------------------------
# the channels in the maps' slab loop


def doppler_channel_records(
    ref: DopplerReference, label: str, optics: tuple[float | None, float | None], wavelength_um: float | None
) -> list[dict[str, Any]]:
    """One channel record per present lag (name, metric, unit rad, resolution, optics of the original)."""
    lat, ax = optics
    return [
        {
            "name": f"{doppler_name(m)}@{label}",
            "metric": doppler_name(m),
            "unit": "rad",
            "resolution": label,
            "wavelength_um": None if wavelength_um is None else float(wavelength_um),
            "lateral_resolution_um": lat,
            "axial_resolution_um": ax,
        }
        for m in ref.lags
    ]


def doppler_slab(
    x: torch.Tensor, ref: DopplerReference, cdim: int, c0: int, c1: int, *, chunk_pixels: int = 1 << 16
) -> np.ndarray:
    """The Doppler channels ``[len(ref.lags), (Y), Z, X]`` of the rows ``c0:c1`` (along data axis ``cdim``) of
    the field ``x`` (``[T, (Y), rows, X]``, those rows only, bulk-corrected as the reference was): NaN
    where the A-line has no reference or the pixel's sum is 0 or not finite."""
    n_t = x.shape[0]
    spatial = x.shape[1:]
    flat = x.reshape(n_t, -1)
    out = np.full((len(ref.lags), *spatial), np.nan)
    n_x = spatial[-1]
    ys = slice(c0, c1) if cdim == 1 and len(spatial) == 3 else slice(None)  # a volume cut in Y: its B-scans
    lead = spatial[:-2]  # (), or the B-scans of the slab
    first = np.arange(int(np.prod(lead, dtype=np.int64))).reshape(*lead, 1, 1) * n_x + np.arange(n_x)
    line_np = np.array(np.broadcast_to(first, spatial)).reshape(-1)  # each pixel's A-line
    line = torch.from_numpy(line_np)
    for li, m in enumerate(ref.lags):
        sums = torch.from_numpy(np.ascontiguousarray(ref.sums[m][:, ys]).reshape(n_t - m, -1)).to(
            _work_dtype(x)
        )  # [T−m, lines]
        none = (ref.scope[m][ys] == 0).reshape(-1)[line_np]
        sel = [slice(None)] * len(spatial)
        sel[cdim - 1] = slice(c0, c1)
        mk = torch.from_numpy(np.ascontiguousarray(ref.mask[m][tuple(sel)]).reshape(-1))
        val = np.empty(flat.shape[1])
        for p0 in range(0, flat.shape[1], chunk_pixels):
            p1 = min(flat.shape[1], p0 + chunk_pixels)
            c = _products(flat[:, p0:p1], m)
            r = sums[:, line[p0:p1]] - torch.where(mk[p0:p1][None], c, torch.zeros_like(c))
            d = (c.conj() * _unit(r)).sum(0)
            v = torch.angle(d).numpy()
            val[p0:p1] = np.where((d.abs() > 0).numpy() & np.isfinite(v), v, np.nan)
        val[none] = np.nan
        out[li] = val.reshape(spatial)
    return out

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
floor (:func:`phase_tolerance`). The population counts when at least :data:`MIN_WHITE_SHARE` of the steady
pixels within ``h`` of it are white (:func:`white_population`): static tissue is white nearly everywhere,
slow flow mostly drifts.

**Scope and minimum**: an A-line with at least :data:`MIN_REFERENCE_PIXELS` reference pixels uses its
own reference; otherwise its B-scan's (the same rule on all the B-scan's pixels, which assumes a bulk
phase common to the B-scan at each frame; with ``--bulk-phase`` the per-A-line estimate is removed first);
otherwise the pixel is NaN. When no A-line or B-scan has a reference at a lag, that lag's channel is absent
and ``meta["doppler"]`` says why; intensity-only input gives no channel and a note.

**Memory**: the reference needs whole A-lines (every depth row and frame), so it is estimated first, in
lateral slabs of whole A-lines (:func:`estimate_doppler_reference`; the B-scan scope of a B-scan split
into several slabs takes four passes); only the reference sums ``[T−m, (Y), X]`` and a reference mask
``[(Y), Z, X]`` are kept, and the channel is computed per pixel in the maps' own slabs (any cut).
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

__all__ = ["DEFAULT_DOPPLER_LAGS", "REFERENCE_CONTRAST", "MIN_REFERENCE_PIXELS", "MIN_WHITE_SHARE",
           "PHASE_TOLERANCE_Z", "REFERENCE_RULE", "min_reference_snr", "min_whiteness", "white_population",
           "phase_tolerance", "doppler_lags", "DopplerReference", "estimate_doppler_reference", "doppler_absent",
           "doppler_channel_records", "doppler_slab", "doppler_name"]

#: The lags (frames) of ``--doppler`` without ``--doppler-lags``: the shortest, the widest velocity range.
DEFAULT_DOPPLER_LAGS = (1,)
#: Largest temporal intensity contrast of a reference candidate (the ``stable`` rule of the bulk phase).
REFERENCE_CONTRAST = STABLE_CONTRAST
#: Fewest reference pixels of a scope: the reference's phase variance per frame pair is ``1/N`` of one of
#: its pixels' (to first order in the noise), so at ``N ≥ 10`` it adds at most 10 % to the variance of a
#: pixel at the reference's SNR.
MIN_REFERENCE_PIXELS = 10
#: Share of a reference population's steady, in-phase pixels that must fluctuate as white noise (a majority).
MIN_WHITE_SHARE = 0.5
#: Half width of the reference population, in standard deviations of a static pixel's phase.
PHASE_TOLERANCE_Z = 3.5
#: The rule, as the maps' metadata record it.
REFERENCE_RULE = ("reference pixels: temporal intensity contrast Var_t I/(mean_t I)^2 <= {c:g} (a static pixel at "
                  "SNR >= {s:.1f}, above the noise floor) and white intensity fluctuations (von Neumann ratio "
                  "sum (I_(t+1) - I_t)^2 / (2 sum (I_t - mean I)^2) >= {w:.3f}: noise, no drift); then the peak "
                  "population of their phases relative to the sum of all of them (histogram of bin width h, weights "
                  "1 - contrast/{c:g}); then those within h of that population's sum; the population counts when at "
                  "least {ws:.0%} of the steady pixels within h of it are white; scope: the A-line with >= {n} "
                  "reference pixels, else its B-scan with >= {n}, else none (NaN); channel: arg sum_t conj(C_t(p)) "
                  "r_t/|r_t|, C_t = E_(t+m) conj(E_t), r_t the reference sum without p")


def doppler_name(m: int) -> str:
    """The channel's metric name at lag ``m``."""
    return f"doppler_phase_{int(m)}"


def min_reference_snr(contrast: float = REFERENCE_CONTRAST) -> float:
    """The pixel SNR ``s`` (signal intensity over noise power) at which a static pixel's expected contrast
    ``(2s + 1)/(s + 1)²`` equals ``contrast``: ``((1 − C) + √(1 − C))/C``."""
    c = float(contrast)
    return ((1.0 - c) + math.sqrt(1.0 - c)) / c


def phase_tolerance(m: int, n_frames: int, *, contrast: float = REFERENCE_CONTRAST,
                    min_pixels: int = MIN_REFERENCE_PIXELS, z: float = PHASE_TOLERANCE_Z) -> float:
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
        raise ValueError(f"{src}: the Doppler channels need a uniform frame interval (the phase per lag is a "
                         "velocity only at one delay)")
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
            "rule": REFERENCE_RULE.format(c=REFERENCE_CONTRAST, s=min_reference_snr(), n=MIN_REFERENCE_PIXELS,
                                          w=min_whiteness(self.n_frames), ws=MIN_WHITE_SHARE),
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
            out["absent"] = ("no A-line and no B-scan holds the reference the rule needs (at least "
                             f"{MIN_REFERENCE_PIXELS} steady, phase-consistent pixels): no static tissue to measure "
                             "the Doppler phase against, so no channel rather than a made-up value")
        return out


def doppler_absent(seq: SequenceData, lags: _Seq[int]) -> dict[str, Any]:
    """``meta["doppler"]`` when the input holds intensity only: no channel, and why."""
    return {"lags": list(lags), "channels": [], "absent": f"{seq.source or 'the sequence'} holds intensity only: the "
            "Doppler phase needs the complex field", "definition": "torchdoct.measured.doppler"}


# ----------------------------------------------------------------------------------------------
# the pieces of the estimate (A-lines ``[T, L, Z]``, pixels flattened to ``[T, P]`` with a group id each)


def min_whiteness(n_frames: int, z: float = PHASE_TOLERANCE_Z) -> float:
    """Smallest von Neumann ratio ``η = Σ_t (I_{t+1} − I_t)² / (2 Σ_t (I_t − Ī)²)`` of a reference candidate:
    ``z`` standard deviations below its mean 1 for white fluctuations (noise about a static field), with
    ``Var η = (T − 2)/((T − 1)(T + 1))``; a drift (slow flow) or a slow decorrelation gives ``η ≪ 1``."""
    t = int(n_frames)
    return 1.0 - z * math.sqrt((t - 2) / ((t - 1) * (t + 1)))


def _candidates(lines: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(candidate, steady [L, Z] bool, weight [L, Z] float64)`` of A-lines ``[T, L, Z]``: steady (contrast)
    and white (no drift: the von Neumann ratio; a constant intensity counts as white) intensity."""
    inten = (lines.real ** 2 + lines.imag ** 2).double()
    mean = inten.mean(0)
    dev2 = ((inten - mean) ** 2).sum(0)
    contrast = dev2 / inten.shape[0] / torch.where(mean > 0, mean * mean, torch.ones_like(mean))
    steps2 = ((inten[1:] - inten[:-1]) ** 2).sum(0)
    white = (steps2 >= 2.0 * min_whiteness(inten.shape[0]) * dev2) | (dev2 == 0)
    steady = (contrast <= REFERENCE_CONTRAST) & (mean > 0) & torch.isfinite(contrast)
    cand = steady & white
    w = torch.where(cand, 1.0 - contrast / REFERENCE_CONTRAST, torch.zeros_like(contrast))
    return cand, steady, w


def white_population(n_white: np.ndarray, n_steady: np.ndarray) -> np.ndarray:
    """Whether a reference population is static tissue: of the steady pixels in phase with it (within ``h``),
    at least :data:`MIN_WHITE_SHARE` fluctuate as white noise. A static pixel fails the per-pixel test with
    the probability of a 3.5-sd excursion; slow flow passes it only where its speckle sits near an intensity
    extremum, and as a population mostly drifts."""
    return (n_steady > 0) & (n_white >= MIN_WHITE_SHARE * n_steady)


def _products(lines: torch.Tensor, m: int) -> torch.Tensor:
    """``C_t = E_{t+m} E_t*`` (complex128 ``[T−m, ...]``), 0 where not finite."""
    x = lines.to(torch.complex128)
    c = x[m:] * x[:-m].conj()
    return torch.where(torch.isfinite(c.real) & torch.isfinite(c.imag), c, torch.zeros_like(c))


def _unit(r: torch.Tensor) -> torch.Tensor:
    a = r.abs()
    return torch.where(a > 0, r / torch.where(a > 0, a, torch.ones_like(a)), torch.zeros_like(r))


def _group_sum(c: torch.Tensor, sel: torch.Tensor, gid: torch.Tensor, n_groups: int) -> torch.Tensor:
    """``Σ`` over the selected pixels of each group: ``c [K, P]``, ``sel [P]``, ``gid [P]`` → ``[K, G]``."""
    out = torch.zeros(c.shape[0], n_groups, dtype=c.dtype)
    return out.index_add_(1, gid, torch.where(sel[None], c, torch.zeros_like(c)))


def _phase_to(c: torch.Tensor, ref: torch.Tensor, gid: torch.Tensor) -> torch.Tensor:
    """Each pixel's phase relative to its group's reference sum: ``arg Σ_t C_t · conj(R_t/|R_t|)`` ``[P]``."""
    return torch.angle((c * _unit(ref)[:, gid].conj()).sum(0))


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


def _n_bins(h: float) -> int:
    return max(8, int(math.ceil(2.0 * math.pi / h)))


def _histogram(psi: torch.Tensor, w: torch.Tensor, gid: torch.Tensor, n_groups: int, h: float) -> torch.Tensor:
    nb = _n_bins(h)
    b = torch.clamp(((psi + math.pi) / (2.0 * math.pi) * nb).long(), 0, nb - 1)
    out = torch.zeros(n_groups * nb, dtype=torch.float64)
    return out.index_add_(0, gid * nb + b, w).reshape(n_groups, nb)


def _peak_centres(hist: torch.Tensor) -> torch.Tensor:
    """The centre (rad) of each group's peak bin of the histogram smoothed by three bins (circular)."""
    nb = hist.shape[1]
    sm = hist + torch.roll(hist, 1, 1) + torch.roll(hist, -1, 1)
    return (sm.argmax(1).double() + 0.5) * (2.0 * math.pi / nb) - math.pi


def _near(psi: torch.Tensor, centre: torch.Tensor, half: float) -> torch.Tensor:
    return _wrap(psi - centre).abs() <= half


def _select_complete(c: torch.Tensor, cand: torch.Tensor, steady: torch.Tensor, w: torch.Tensor, gid: torch.Tensor,
                     n_groups: int, h: float) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
    """The rule on groups whose pixels are all here: ``(reference sums [K, G], reference pixels [P], white and
    steady pixels in phase with each group's population [G])``."""
    r0 = _group_sum(c, cand, gid, n_groups)
    psi = _phase_to(c, r0, gid)
    centre = _peak_centres(_histogram(psi, w, gid, n_groups, h))
    sel = cand & _near(psi, centre[gid], 1.5 * 2.0 * math.pi / _n_bins(h))
    r1 = _group_sum(c, sel, gid, n_groups)
    in_phase = _phase_to(c, r1, gid).abs() <= h
    sel = cand & in_phase
    n_white, n_steady = _in_phase_counts(sel, steady & in_phase, gid, n_groups)
    return _group_sum(c, sel, gid, n_groups), sel, n_white, n_steady


def _in_phase_counts(sel: torch.Tensor, steady: torch.Tensor, gid: torch.Tensor, n_groups: int):
    return (np.bincount(gid[sel].numpy(), minlength=n_groups), np.bincount(gid[steady].numpy(), minlength=n_groups))


def _slab_lines(block: torch.Tensor, volume: bool) -> torch.Tensor:
    """A-lines ``[T, L, Z]`` of a lateral slab (``[T, Z, Xs]`` or ``[T, Ys, Z, X]``)."""
    if volume:
        t, ys, z, x = block.shape
        return block.permute(0, 1, 3, 2).reshape(t, ys * x, z)
    return block.permute(0, 2, 1)


@torch.no_grad()
def estimate_doppler_reference(seq: SequenceData, lags: _Seq[int], *, bulk: np.ndarray | None = None,
                               slab_elements: int = 1 << 23, device: torch.device | None = None,
                               progress: bool = False) -> DopplerReference:
    """The reference of every lag (module docstring), in lateral slabs of whole A-lines (X columns of a
    B-scan sequence, whole B-scans of a volume) of at most ``slab_elements`` samples. ``bulk``: the bulk-phase
    phasor ``[T, (Y), 1, X]`` of :func:`torchdoct.measured.maps.compute_maps`, applied first."""
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
    sums = {m: np.zeros((n_t - m, n_lines), dtype=np.complex128) for m in lags}
    own = {m: np.zeros(n_lines, dtype=np.int64) for m in lags}
    mask = {m: np.zeros((n_lines, n_z), dtype=bool) for m in lags}
    own_steady = {m: np.zeros(n_lines, dtype=np.int64) for m in lags}
    n_cand = np.zeros(n_lines, dtype=np.int64)
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=len(slabs), desc="doppler reference", unit="slab")

    def read(c0: int, c1: int) -> tuple[torch.Tensor, slice]:
        sel = [slice(None)] * data.ndim
        sel[cdim] = slice(c0, c1)
        raw = np.array(data[tuple(sel)], dtype=native, copy=True)
        if bulk is not None:
            raw = np.multiply(raw, bulk[tuple(sel)])
        lines = _slab_lines(torch.from_numpy(raw), volume)
        first = c0 * n_x if volume else c0
        return lines, slice(first, first + lines.shape[1])

    for c0, c1 in slabs:  # the A-line scope: every group is whole in its slab
        lines, rows = read(c0, c1)
        n_l = lines.shape[1]
        cand, steady, w = _candidates(lines)
        n_cand[rows] = cand.sum(1).numpy()
        gid = torch.arange(n_l).repeat_interleave(n_z)
        for m in lags:
            c = _products(lines, m).reshape(n_t - m, -1)
            r, sel, n_white, n_steady = _select_complete(c, cand.reshape(-1), steady.reshape(-1), w.reshape(-1), gid,
                                                         n_l, hs[m])
            sums[m][:, rows] = r.numpy()
            mask[m][rows] = sel.reshape(n_l, n_z).numpy()
            own[m][rows] = n_white
            own_steady[m][rows] = n_steady
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    # the B-scan scope, for the A-lines without their own reference
    own_ok = {m: (own[m] >= MIN_REFERENCE_PIXELS) & white_population(own[m], own_steady[m]) for m in lags}
    need = [m for m in lags if not own_ok[m].all()]
    bscan_sums: dict[int, np.ndarray] = {}
    bscan_n: dict[int, np.ndarray] = {}
    bscan_mask: dict[int, np.ndarray] = {}
    bscan_steady: dict[int, np.ndarray] = {}
    if need:
        bscan_sums, bscan_n, bscan_mask, bscan_steady = _bscan_scope(read, slabs, need, hs, n_t=n_t, n_z=n_z, n_lines=n_lines,
                                                       n_bscans=n_bscans, n_x=n_x, volume=volume)
    scope, out_sums, out_mask, info, present = {}, {}, {}, {}, []
    for m in lags:
        use_own = own_ok[m]
        sc = np.where(use_own, 1, 0).astype(np.int8)
        s = np.where(use_own[None], sums[m], 0)
        mk = np.where(use_own[:, None], mask[m], False)
        b_ok = np.zeros(n_bscans, dtype=bool)
        if m in bscan_sums:
            b_ok = (bscan_n[m] >= MIN_REFERENCE_PIXELS) & white_population(bscan_n[m], bscan_steady[m])
            line_b = np.repeat(np.arange(n_bscans), n_x) if volume else np.zeros(n_lines, dtype=np.int64)
            fall = ~use_own & b_ok[line_b]
            sc = np.where(fall, 2, sc).astype(np.int8)
            s = np.where(fall[None], bscan_sums[m][:, line_b], s)
            mk = np.where(fall[:, None], bscan_mask[m], mk)
        scope[m] = sc.reshape(lat_shape)
        out_sums[m] = s.reshape(n_t - m, *lat_shape)
        out_mask[m] = np.moveaxis(mk.reshape(*lat_shape, n_z), -1, -2)  # [(Y), Z, X]
        line_share = mk.sum(1) / n_z  # each A-line's pixels in the reference it uses
        info[m] = {
            "h": hs[m],
            "reference_pixels": int(mk.sum()),
            "reference_share": float(mk.sum()) / (n_lines * n_z),
            "candidate_share": float(n_cand.sum()) / (n_lines * n_z),
            "alines": n_lines,
            "alines_own_reference": int(use_own.sum()),
            "alines_bscan_reference": int((sc == 2).sum()),
            "alines_without_reference": int((sc == 0).sum()),
            "aline_reference_share": {"min": float(line_share.min()), "median": float(np.median(line_share)),
                                      "max": float(line_share.max())},
            "bscans_with_reference": int(b_ok.sum()) if m in bscan_sums else None,
            "bscan_reference_share": ([float(v) / (n_x * n_z) for v in bscan_n[m]] if m in bscan_n else None),
        }
        if (sc > 0).any():
            present.append(m)
    system = dict(seq.meta.get("system") or {})
    wl = system.get("wavelength_um")
    return DopplerReference(asked=tuple(lags), lags=tuple(present), sums=out_sums, scope=scope, mask=out_mask,
                            info=info, frame_interval_s=float(uniform_frame_interval_s(seq.frame_times_s)),
                            wavelength_um=None if wl is None else float(wl),
                            refractive_index=float(system.get("refractive_index") or 1.0),
                            bulk_corrected=bulk is not None, n_frames=n_t)


def _bscan_scope(read, slabs, lags, hs, *, n_t, n_z, n_lines, n_bscans, n_x, volume):
    """The rule with the B-scan as the scope, in four passes over the slabs (the B-scan of a ``[T, Z, X]``
    sequence may span several): the candidates' sum, their phase histogram, the peak population's sum, the
    final reference. Returns per lag the sums ``[T−m, B]``, the counts ``[B]``, the pixels ``[L, Z]`` and the
    steady pixels in phase with the population ``[B]``."""
    r0 = {m: torch.zeros(n_t - m, n_bscans, dtype=torch.complex128) for m in lags}
    hist = {m: torch.zeros(n_bscans, _n_bins(hs[m]), dtype=torch.float64) for m in lags}
    r1 = {m: torch.zeros(n_t - m, n_bscans, dtype=torch.complex128) for m in lags}
    r2 = {m: torch.zeros(n_t - m, n_bscans, dtype=torch.complex128) for m in lags}
    count = {m: np.zeros(n_bscans, dtype=np.int64) for m in lags}
    n_steady = {m: np.zeros(n_bscans, dtype=np.int64) for m in lags}
    pix = {m: np.zeros((n_lines, n_z), dtype=bool) for m in lags}
    centre: dict[int, torch.Tensor] = {}
    for step in range(4):
        for c0, c1 in slabs:
            lines, rows = read(c0, c1)
            n_l = lines.shape[1]
            cand, steady, w = _candidates(lines)
            cand, steady, w = cand.reshape(-1), steady.reshape(-1), w.reshape(-1)
            line_ids = torch.arange(rows.start, rows.stop)
            gid = (line_ids // n_x if volume else torch.zeros(n_l, dtype=torch.long)).repeat_interleave(n_z)
            for m in lags:
                c = _products(lines, m).reshape(n_t - m, -1)
                if step == 0:
                    r0[m] += _group_sum(c, cand, gid, n_bscans)
                    continue
                psi = _phase_to(c, r0[m], gid)
                if step == 1:
                    hist[m] += _histogram(psi, w, gid, n_bscans, hs[m])
                elif step == 2:
                    sel = cand & _near(psi, centre[m][gid], 1.5 * 2.0 * math.pi / _n_bins(hs[m]))
                    r1[m] += _group_sum(c, sel, gid, n_bscans)
                else:
                    in_phase = _phase_to(c, r1[m], gid).abs() <= hs[m]
                    sel = cand & in_phase
                    r2[m] += _group_sum(c, sel, gid, n_bscans)
                    n_w, n_s = _in_phase_counts(sel, steady & in_phase, gid, n_bscans)
                    count[m] += n_w
                    n_steady[m] += n_s
                    pix[m][rows] = sel.reshape(n_l, n_z).numpy()
        if step == 1:
            centre = {m: _peak_centres(hist[m]) for m in lags}
    return {m: r2[m].numpy() for m in lags}, count, pix, n_steady


# ----------------------------------------------------------------------------------------------
# the channels in the maps' slab loop


def doppler_channel_records(ref: DopplerReference, label: str, optics: tuple[float | None, float | None],
                            wavelength_um: float | None) -> list[dict[str, Any]]:
    """One channel record per present lag (name, metric, unit rad, resolution, optics of the original)."""
    lat, ax = optics
    return [{"name": f"{doppler_name(m)}@{label}", "metric": doppler_name(m), "unit": "rad", "resolution": label,
             "wavelength_um": None if wavelength_um is None else float(wavelength_um), "lateral_resolution_um": lat,
             "axial_resolution_um": ax} for m in ref.lags]


def doppler_slab(x: torch.Tensor, ref: DopplerReference, cdim: int, c0: int, c1: int, *,
                 chunk_pixels: int = 1 << 16) -> np.ndarray:
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
    line = (np.arange(int(np.prod(lead, dtype=np.int64))).reshape(*lead, 1, 1) * n_x + np.arange(n_x))
    line = torch.from_numpy(np.array(np.broadcast_to(line, spatial)).reshape(-1))  # each pixel's A-line
    for li, m in enumerate(ref.lags):
        sums = torch.from_numpy(np.ascontiguousarray(ref.sums[m][:, ys]).reshape(n_t - m, -1))  # [T−m, lines]
        none = (ref.scope[m][ys] == 0).reshape(-1)[line.numpy()]
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

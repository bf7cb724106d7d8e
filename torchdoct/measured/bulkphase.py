"""Bulk-phase correction of complex OCT sequences, per A-line and consecutive frame pair (physics.md §12).

Between two frames the whole sample under an A-line may move along the beam by a fraction of a
wavelength (breathing, heartbeat, stage drift, an unstable reference arm). Every scatterer of the
A-line then gains the same phase, ``E_i(z) → E_i(z)·exp(iφ_i)``: the intensity is unchanged, but the
field features (``g1_m``, ``g1_phase_m``, ``phase_ramp`` of :mod:`torchdoct.sim.signature`) measure
``φ_i`` instead of the pixel, and a lateral resolution reduction adds A-lines with different phases
(spurious decorrelation of the reduced intensity too). Phase-based OCT (Doppler OCT, OCT angiography)
estimates the bulk phase from the A-line itself and removes it; this module does the same.

**Estimate.** For each A-line (each ``x`` of a B-scan sequence ``[T, Z, X]``, each ``(y, x)`` of a
volume ``[T, Y, Z, X]``) and each consecutive frame pair ``(i, i+1)``, with the pixel products
``C_i(z) = E_{i+1}(z)·E_i*(z)`` over the depth rows used (``rows``, ``mask``):

* ``weighted-mean``: ``Δφ_i = arg Σ_z C_i(z)``. The argument of the summed products is the
  intensity-weighted mean phase difference (each pixel weighs ``|E_{i+1}||E_i|``); it is the
  maximum-likelihood step of one frame pair for an unknown static field in white Gaussian noise, but
  every pixel pulls on it, so a flowing layer with a Doppler step ``δ`` shifts it by about ``w_f·δ``
  (``w_f`` the layer's share of ``Σ|C|``; exactly ``arg(Σ_static |C| + Σ_flow C)``): the flow's ramp
  shrinks to ``δ − that`` and the static tissue acquires the opposite ramp.
* ``histogram``: the peak of the ``|C|``-weighted histogram of the pixel phase differences
  ``arg C_i(z)`` (``bins`` bins over (−π, π], smoothed circularly by [1, 2, 1]/4), refined to sub-bin
  precision: ``c₁ = arg Σ C`` over the pixels within 3 bins of the peak; the spread ``s`` of the
  static pixels is the ``|C|``-weighted median of ``|arg C − c₁|`` over the pixels within ``±π/4`` of
  ``c₁``, divided by 0.6745 (the Gaussian median absolute deviation; a median, so a flowing layer
  inside that range hardly moves it); then twice ``c ← arg Σ C`` over the pixels within
  ``±h = clamp(8·s, 2 bins, π/2)`` of the current ``c``. The peak belongs to the largest population
  of pixels that move together (the static tissue); pixels further than ``h`` from it do not enter,
  so the Doppler ramp of a flowing layer whose step exceeds ``h`` survives the correction. Measured on
  static speckle (64 rows, 64 bins), ``s`` is 0.25, 0.078, 0.025, 0.008 rad and ``h`` π/2, 0.62,
  0.20, 0.20 rad at 10, 20, 30, 40 dB SNR. When the Doppler step is within ``h`` the two populations
  cannot be told apart and the estimate is their weighted mean. The window is decided pair by pair,
  so the frame errors no longer cancel exactly between consecutive steps (below): on a static A-line
  the residual is 0-3 % above the weighted mean's (``torchdoct bench bulk-phase``).

The steps are accumulated, ``φ̂_0 = 0``, ``φ̂_i = Σ_{j<i} Δφ_j`` ("consecutive frames" reference: the
bulk phase relative to the first frame), and frame ``i`` of the A-line is multiplied by ``exp(−iφ̂_i)``
at every depth (:func:`apply_bulk_phase`). A-line pairs with no weight (every used pixel zero or
NaN) get ``Δφ_i = 0`` and are counted (``meta["bulk_phase"]["pairs_without_signal"]``).

**Which pixels** (``rows``, ``mask``): ``rows = (z0, z1)`` restricts the estimate to depth rows
``z0 ≤ z < z1`` (default all; the correction is applied to every row). ``mask``: ``"all"`` (default),
``"median"`` (only the pixels whose ``|C_i(z)|`` is at least the median over the A-line's used rows for
that pair: the brighter half, which skips the noise floor below the sample), ``"stable"`` /
``"stable:C"`` (only the pixels whose temporal intensity contrast ``Var_t I/(mean_t I)²`` over the whole
sequence is at most ``C``, default :data:`STABLE_CONTRAST` = 0.05: the static tissue, chosen from the
intensity, which the bulk phase does not touch; an A-line without such pixels uses all of them), or a
number, a dB threshold on ``10·log10|C_i(z)|`` (the dB scale of the data's intensity, as ``mean_db`` at
the original resolution). In a sample with moving scatterers every pixel of ``"all"`` also feeds the
A-line's own moving-speckle phase into the estimate (below); ``"stable"`` avoids it: on the rendered
vessel-slab phantom at 30 dB the residual falls from 0.09-0.10 rad to 0.006 rad (physics.md §12.3).
For a static sample at low SNR few pixels pass and ``"all"`` is better.

**Residual error** (physics.md §12, derived there): for an A-line of static scatterers ``S(z)`` in
white circular Gaussian noise of power ``σ²`` per pixel, with ``A = Σ_z |S(z)|²`` over the ``N_z``
used pixels and ``SNR = A/(N_z σ²)`` (mean signal intensity over noise power), the corrected phase
differs from the truth by a constant (a phase common to all frames of the A-line, which no temporal
feature sees) plus a residual ``r_i`` whose RMS over the ``T`` frames is, to first order in the noise,

    ⟨r²⟩ = (1 − 1/T)·σ²/(2A) + (T² − 1)/(6T)·N_z σ⁴/(2A²)
         ≈ 1/(2 N_z SNR) + (T/6)/(2 N_z SNR²)

The first term is the phase noise of each frame projected on the static field (the step errors
telescope: frame ``i+1``'s error enters step ``i`` with + and step ``i+1`` with −); the second, the
noise-times-noise part of each step, is a random walk over the frames and matters only at low SNR.
At high SNR the residual is ``≈ 1/√(2·N_z·SNR)``. For fully developed speckle ``A`` is a Gamma
variable and the mean over A-lines uses ``E[1/A] = 1/((N_z−1)P)``, ``E[1/A²] = 1/((N_z−1)(N_z−2)P²)``
(:func:`predicted_residual_rms`). :func:`torchdoct.bench.bulkphase.bench_bulk_phase` (``torchdoct bench bulk-phase``) measures it
against SNR. Moving scatterers in the A-line add to it: the estimate cannot tell the bulk phase from
the phase that the A-line's own decorrelating speckle shares across its pixels, and removes that too
(physics.md §12.3: a term of variance ``≈ f_s f_m/(2 N_z a²)`` and a random walk of ``≈ (1 − g²)
f_m²/(2 N_z a²)`` per step for a moving power fraction ``f_m`` with lag-1 correlation ``g``,
``a = f_s + g f_m``; ``predicted_residual_rms(moving_fraction=, moving_g=)``).

**Memory.** The correction of an A-line needs its whole depth (rows used) and all its frames, so the
estimate runs in lateral slabs of whole A-lines (X columns of a B-scan sequence, whole B-scans of a
volume), at most ``slab_elements`` complex samples each; the result is only ``[T, (Y), X]`` phases,
applied per depth slab inside :func:`torchdoct.measured.maps.compute_maps`. :func:`corrected_sequence`
makes a corrected copy of the whole sequence (the signature features read the whole field).

Intensity-only data (no phase) are refused with the file's name.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence as _Seq
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..conventions import noise_power
from ..runtime.interrupt import progress_disabled
from ..runtime.threads import one_torch_thread
from .io import SequenceData

__all__ = [
    "CORRECTION_AXIS_NEEDS",
    "METHODS",
    "MASKS",
    "STABLE_CONTRAST",
    "REFERENCE",
    "BulkPhase",
    "parse_mask",
    "parse_rows",
    "phase_steps",
    "estimate_bulk_phase",
    "phasor",
    "apply_bulk_phase",
    "corrected_sequence",
    "predicted_residual_rms",
]

METHODS = ("weighted-mean", "histogram")
#: How the steps are chained: each frame against the previous one, accumulated from the first frame.
REFERENCE = "consecutive frames"
DEFAULT_BINS = 64
#: Pixel masks: all pixels, the brighter half per pair, or the temporally stable pixels.
MASKS = ("all", "median", "stable")
#: ``mask="stable"``: largest temporal intensity contrast ``Var_t I/(mean_t I)²`` of a pixel used (a static
#: pixel at pixel SNR s has ≈ 2/s; moving fully developed speckle approaches 1).
STABLE_CONTRAST = 0.05
#: Histogram method: the range (rad, half width) of the spread estimate, the half width (bins) of the window
#: of the first refinement around the peak, the final window's half width in units of the spread, and its
#: upper bound (rad); its lower bound is 2 bins.
_WINDOW0 = math.pi / 4
_PEAK_BINS = 3
_SPREADS = 8.0
_WINDOW_MAX = math.pi / 2


def parse_mask(mask: str | float | None) -> str | float:
    """``"all"``, ``"median"``, ``"stable:C"`` (``"stable"``: ``C =`` :data:`STABLE_CONTRAST`) or a dB threshold
    (float); a clear error otherwise."""
    if mask is None:
        return "all"
    if isinstance(mask, (int, float)) and not isinstance(mask, bool):
        if not math.isfinite(float(mask)):
            raise ValueError(f"--bulk-phase-mask: a dB threshold must be finite; got {mask!r}")
        return float(mask)
    text = str(mask).strip().lower().replace(" ", "")
    if text in MASKS:
        return f"stable:{STABLE_CONTRAST:g}" if text == "stable" else text
    if text.startswith("stable:"):
        try:
            thr = float(text[7:])
        except ValueError:
            thr = math.nan
        if not (math.isfinite(thr) and thr > 0):
            raise ValueError(f"--bulk-phase-mask stable:C needs a contrast C > 0 (e.g. stable:0.05); got {mask!r}")
        return f"stable:{thr:g}"
    try:
        v = float(text)
    except ValueError:
        raise ValueError(
            f"--bulk-phase-mask must be all, median, stable[:C] or a dB threshold (e.g. -30); got {mask!r}"
        ) from None
    if not math.isfinite(v):
        raise ValueError(f"--bulk-phase-mask: a dB threshold must be finite; got {mask!r}")
    return v


def parse_rows(rows: str | _Seq[int] | None, n_z: int | None = None) -> tuple[int, int] | None:
    """``"Z0:Z1"`` or ``(z0, z1)`` → ``(z0, z1)`` (depth rows ``z0 ≤ z < z1``; an empty side means the
    start / end); checked against ``n_z`` when given."""
    if rows is None:
        return None
    if isinstance(rows, str):
        a, sep, b = rows.replace(" ", "").partition(":")
        if not sep:
            raise ValueError(f"--bulk-phase-rows must be Z0:Z1 (depth rows Z0 <= z < Z1, e.g. 40:200); got {rows!r}")
        try:
            z0 = int(a) if a else 0
            z1 = int(b) if b else (n_z if n_z is not None else -1)
        except ValueError:
            raise ValueError(f"--bulk-phase-rows must be two integers Z0:Z1; got {rows!r}") from None
    else:
        if len(rows) != 2:
            raise ValueError(f"bulk-phase rows must be (z0, z1); got {rows!r}")
        z0, z1 = (int(v) for v in rows)
    if n_z is not None:
        if z1 == -1:
            z1 = n_z
        if not 0 <= z0 < z1 <= n_z:
            raise ValueError(
                f"--bulk-phase-rows {z0}:{z1} must satisfy 0 <= Z0 < Z1 <= {n_z} (the depth rows of the data)"
            )
    return (z0, z1)


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


def phase_steps(
    lines: torch.Tensor, method: str = "weighted-mean", *, mask: str | float = "all", bins: int = DEFAULT_BINS
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bulk phase steps of A-lines ``lines [T, L, Z]`` (complex; ``L`` A-lines of ``Z`` depth pixels).

    Returns ``(steps [T−1, L] float64 rad, no_signal [T−1, L] bool)``: ``steps[i]`` is the estimate of
    ``φ_{i+1} − φ_i`` by ``method`` (module docstring); pairs without weight get 0 and ``no_signal``.
    """
    if method not in METHODS:
        raise ValueError(f"bulk-phase method must be one of {', '.join(METHODS)}; got {method!r}")
    mask = parse_mask(mask)
    if not lines.is_complex():
        raise ValueError("bulk-phase correction needs the complex field (phase); got a real array")
    c = lines[1:] * lines[:-1].conj()  # [T-1, L, Z]
    c = torch.where(torch.isfinite(c.real) & torch.isfinite(c.imag), c, torch.zeros_like(c))
    w = c.abs()
    if mask == "median":
        keep = w >= w.median(-1, keepdim=True).values
    elif mask == "all":
        keep = None
    elif isinstance(mask, str) and mask.startswith("stable:"):  # intensity steady over the sequence (bulk-invariant)
        inten = (lines.real**2 + lines.imag**2).double()
        mean = inten.mean(0)
        contrast = inten.var(0, unbiased=False) / torch.where(mean > 0, mean * mean, torch.ones_like(mean))
        keep = ((contrast <= float(mask[7:])) & (mean > 0))[None].expand_as(w)
        none = ~keep.any(-1, keepdim=True)  # an A-line without stable pixels: all its pixels
        keep = keep | none
    else:
        keep = w >= 10.0 ** (float(mask) / 10.0)
    if keep is not None:
        c = torch.where(keep, c, torch.zeros_like(c))
        w = torch.where(keep, w, torch.zeros_like(w))
    c = c.to(torch.complex128)
    w = w.to(torch.float64)
    total = c.sum(-1)
    no_signal = ~(w.sum(-1) > 0)
    if method == "weighted-mean":
        step = torch.angle(total)
    else:
        step = _histogram_steps(c, w, int(bins))
    step = torch.where(no_signal, torch.zeros_like(step), step)
    return step, no_signal


def _histogram_steps(c: torch.Tensor, w: torch.Tensor, bins: int) -> torch.Tensor:
    if bins < 8:
        raise ValueError(f"the histogram needs at least 8 bins; got {bins}")
    ang = torch.angle(c)  # (−π, π]
    width = 2.0 * math.pi / bins
    idx = torch.floor((ang + math.pi) / width).long().clamp(0, bins - 1)
    hist = torch.zeros(*c.shape[:-1], bins, dtype=torch.float64, device=c.device)
    hist.scatter_add_(-1, idx, w)
    hist = 0.25 * torch.roll(hist, 1, -1) + 0.5 * hist + 0.25 * torch.roll(hist, -1, -1)
    peak = -math.pi + (hist.argmax(-1).to(torch.float64) + 0.5) * width

    def windowed(center: torch.Tensor, half: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
        d = _wrap(ang - center[..., None])
        inside = d.abs() <= (half[..., None] if torch.is_tensor(half) else half)
        s = torch.where(inside, c, torch.zeros_like(c)).sum(-1)
        ok = s.abs() > 0
        return torch.where(ok, torch.angle(s), center), inside

    c1, _ = windowed(peak, _PEAK_BINS * width)
    # robust spread of the pixels within ±π/4 of c1: the |C|-weighted median of |d| / 0.6745 (an RMS would be
    # inflated by a flowing layer inside that range)
    d1 = _wrap(ang - c1[..., None])
    inside = d1.abs() <= _WINDOW0
    ad = torch.where(inside, d1.abs(), torch.full_like(ang, math.inf))
    ad, order = ad.sort(-1)
    cw = torch.where(inside, w, torch.zeros_like(w)).gather(-1, order).cumsum(-1)
    k = (cw < 0.5 * cw[..., -1:]).sum(-1, keepdim=True).clamp_max(ad.shape[-1] - 1)
    med = ad.gather(-1, k)[..., 0]
    spread = torch.where(torch.isfinite(med), med, torch.zeros_like(med)) / 0.6745
    half = (_SPREADS * spread).clamp(2.0 * width, _WINDOW_MAX)
    c2, _ = windowed(c1, half)
    c3, _ = windowed(c2, half)  # re-centred: the truncation of the static pixels' tails is symmetric about c3
    return c3


@dataclass(frozen=True, eq=False)
class BulkPhase:
    """Estimated bulk phase of a sequence: ``phase`` float64 ``[T, X]`` or ``[T, Y, X]`` (rad,
    ``φ̂_0 = 0``, accumulated steps, not wrapped), the settings, and ``pairs_without_signal``."""

    phase: np.ndarray
    method: str
    mask: str | float = "all"
    rows: tuple[int, int] | None = None
    bins: int | None = None
    pairs_without_signal: int = 0
    source: str | None = None
    seconds: float = field(default=0.0, compare=False)

    def meta(self) -> dict[str, Any]:
        """The record written to the maps' ``meta["bulk_phase"]`` (the classifier reads ``method``)."""
        steps = np.diff(self.phase, axis=0)
        wrapped = (steps + math.pi) % (2 * math.pi) - math.pi
        out: dict[str, Any] = {
            "method": self.method,
            "reference": REFERENCE,
            "per": "A-line ((y, x) of a volume, x of a B-scan sequence) and consecutive frame pair",
            "mask": self.mask if isinstance(self.mask, str) else f"{float(self.mask):g} dB",
            "rows": None if self.rows is None else [int(self.rows[0]), int(self.rows[1])],
            "applied": "to the complex field before the resolution reduction and the signature features",
            "pairs_without_signal": int(self.pairs_without_signal),
            "step_rms_rad": float(np.sqrt(np.mean(wrapped**2))) if wrapped.size else 0.0,
            "definition": "torchdoct.measured.bulkphase (physics.md §12)",
        }
        if self.method == "histogram":
            out["bins"] = int(self.bins or DEFAULT_BINS)
        return out


def _check_sequence(seq: SequenceData) -> str:
    src = seq.source or "sequence"
    if not seq.is_complex:
        raise ValueError(
            f"{src} holds intensity only (dtype {seq.data.dtype}): bulk-phase correction needs the complex "
            "field (the phase of every pixel); give the complex sequence (.npy/.npz/.h5, complex64 or "
            "complex128), or drop --bulk-phase"
        )
    if seq.n_frames < 2:
        raise ValueError(f"{src}: {seq.n_frames} frame along T; bulk-phase correction needs at least 2 frames")
    return src


@one_torch_thread
def estimate_bulk_phase(
    seq: SequenceData,
    method: str = "weighted-mean",
    *,
    mask: str | float = "all",
    rows: str | _Seq[int] | None = None,
    bins: int = DEFAULT_BINS,
    slab_elements: int = 1 << 23,
    device: str | torch.device | None = None,
    progress: bool = False,
) -> BulkPhase:
    """The bulk phase of every A-line and frame of ``seq`` (module docstring), slab by slab.

    Each slab holds whole A-lines (all frames, the depth rows used): X columns of a ``[T, Z, X]``
    sequence, whole B-scans of a ``[T, Y, Z, X]`` volume, at most ``slab_elements`` complex samples
    (at least one B-scan of a volume). The result does not depend on the slab size.
    """
    src = _check_sequence(seq)
    if method not in METHODS:
        raise ValueError(f"--bulk-phase must be one of {', '.join(METHODS)}; got {method!r}")
    mask = parse_mask(mask)
    data = seq.data
    axes = seq.axes
    zdim = axes.index("Z")
    n_z = data.shape[zdim]
    rows_t = parse_rows(rows, n_z)
    z0, z1 = rows_t if rows_t is not None else (0, n_z)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    native = data.dtype.newbyteorder("=")
    n_t = data.shape[0]
    volume = data.ndim == 4
    cdim = 1 if volume else 2  # Y of a volume, X of a B-scan sequence
    n_c = data.shape[cdim]
    per = int(np.prod(data.shape)) // n_c // n_z * (z1 - z0)
    step_c = max(1, min(n_c, int(slab_elements) // max(per, 1)))
    phase = np.zeros((n_t, *[s for d, s in enumerate(data.shape) if d not in (0, zdim)]), dtype=np.float64)
    missing = 0
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=math.ceil(n_c / step_c), desc="bulk phase", unit="slab")
    t0 = time.perf_counter()
    for c0 in range(0, n_c, step_c):
        c1 = min(n_c, c0 + step_c)
        sel = [slice(None)] * data.ndim
        sel[cdim] = slice(c0, c1)
        sel[zdim] = slice(z0, z1)
        block = torch.from_numpy(np.array(data[tuple(sel)], dtype=native, copy=True)).to(dev)
        lines = block.movedim(zdim, -1)  # [T, (Y), X, Z]
        spatial = lines.shape[1:-1]
        steps, none = phase_steps(lines.reshape(n_t, -1, z1 - z0), method, mask=mask, bins=bins)
        missing += int(none.sum())
        cum = torch.cat([torch.zeros_like(steps[:1]), steps.cumsum(0)], 0)
        idx = [slice(None)] * phase.ndim
        idx[1] = slice(c0, c1)  # Y of [T, Y, X], X of [T, X]
        phase[tuple(idx)] = cum.reshape(n_t, *spatial).cpu().numpy()
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return BulkPhase(
        phase=phase,
        method=method,
        mask=mask,
        rows=rows_t,
        bins=int(bins) if method == "histogram" else None,
        pairs_without_signal=missing,
        source=src,
        seconds=time.perf_counter() - t0,
    )


def _phasor_shape(bp: BulkPhase, seq_shape: tuple[int, ...], axes: str) -> tuple[int, ...]:
    zdim = axes.index("Z")
    want = tuple(s for d, s in enumerate(seq_shape) if d != zdim)
    if tuple(bp.phase.shape) != want:
        raise ValueError(
            f"bulk phase of shape {list(bp.phase.shape)} does not match the sequence "
            f"{list(seq_shape)} ({axes}): estimate it from this sequence"
        )
    return tuple(1 if d == zdim else s for d, s in enumerate(seq_shape))


def phasor(bp: BulkPhase, seq: SequenceData) -> np.ndarray:
    """``exp(−iφ̂)`` with the sequence's dimensions and a depth dimension of 1 (broadcasts over depth),
    in the data's complex dtype."""
    shape = _phasor_shape(bp, tuple(seq.data.shape), seq.axes)
    dtype = seq.data.dtype.newbyteorder("=")
    return np.exp(-1j * bp.phase).reshape(shape).astype(dtype)


def apply_bulk_phase(field: np.ndarray | torch.Tensor, bp: BulkPhase, axes: str) -> np.ndarray | torch.Tensor:
    """``field [T, (Y), Z, X]`` (the whole sequence) times ``exp(−iφ̂)`` of every A-line and frame; same
    type and dtype as ``field``."""
    shape = _phasor_shape(bp, tuple(field.shape), axes)
    p = np.exp(-1j * bp.phase).reshape(shape)
    if torch.is_tensor(field):
        return field * torch.from_numpy(p).to(field.dtype).to(field.device)
    return field * p.astype(field.dtype.newbyteorder("="))


#: What the correction (not the estimate) needs of each spatial axis when it runs on a piece of the field
#: (read by the slab planner of :func:`torchdoct.measured.maps.compute_maps`, as
#: :func:`torchdoct.measured.resolution.reduction_axis_needs`): nothing, since it multiplies each A-line's
#: frames by their own phasor, so any cut is exact. The estimate needs whole A-lines and every frame; it runs
#: before, over lateral slabs of its own (:func:`estimate_bulk_phase`), and keeps only the ``[T, (Y), X]`` phases.
CORRECTION_AXIS_NEEDS: dict[str, int | None] = {}


def corrected_sequence(seq: SequenceData, bp: BulkPhase) -> SequenceData:
    """A corrected copy of ``seq`` (the whole field in memory, the data's dtype) whose metadata record
    the correction (``meta["bulk_phase"]``)."""
    _check_sequence(seq)
    ph = phasor(bp, seq)
    data = np.empty(seq.data.shape, dtype=seq.data.dtype.newbyteorder("="))
    for k in range(seq.n_frames):  # frame by frame: no second temporary of the whole field
        np.multiply(seq.data[k], ph[k], out=data[k])
    meta = dict(seq.meta)
    meta["bulk_phase"] = bp.meta()
    return SequenceData(data=data, meta=meta, labels=seq.labels, label_params=seq.label_params, source=seq.source)


# ----------------------------------------------------------------------------------------------
# residual error: theory and measurement


def predicted_residual_rms(
    snr_db: float,
    n_z: int,
    n_frames: int,
    *,
    speckle: bool = True,
    noise_only: int = 0,
    moving_fraction: float = 0.0,
    moving_g: float = 1.0,
) -> float:
    """First-order RMS residual phase (rad) over the frames of an A-line (module docstring; physics.md §12),
    about its frame mean, with the signal power per pixel 1 and white noise at ``snr_db``.

    Static A-line: ``√((1 − 1/T)·σ²/2·E[1/A] + (T² − 1)/(6T)·N σ⁴/2·E[1/A²])`` with ``A = Σ|S|²`` over
    the ``N_z`` signal pixels and ``N = N_z + noise_only`` the pixels used (``noise_only`` of them hold
    noise only, e.g. below the sample). ``speckle``: ``A`` Gamma distributed (fully developed speckle,
    mean over A-lines: ``E[1/A] = 1/(N_z − 1)``, ``E[1/A²] = 1/((N_z − 1)(N_z − 2))``); otherwise
    ``A = N_z`` fixed. ``moving_fraction`` ``f_m`` of the power decorrelating as AR(1) with lag-1
    correlation ``moving_g`` ``g`` (physics.md §12.3): ``A`` becomes ``N_z·a``, ``a = 1 − f_m + g·f_m``, and two
    terms add: the moving part's projection on the static field, ``Im Σ S*M_i / A`` (variance
    ``N_z f_s f_m/2·E[1/A²]``, times ``1 − (1/T²)Σ_ij g^|i−j|`` about the frame mean), and the random
    walk of ``Im Σ M_{i+1}M_i* / A`` (``N_z (1 − g²) f_m²/2·E[1/A²]`` per step). Noise and moving
    speckle are taken to first order; cross terms of the two are neglected (O(1 − g))."""
    n, t = int(n_z), int(n_frames)
    n_used = n + int(noise_only)
    fm = float(moving_fraction)
    g = float(moving_g)
    if not 0.0 <= fm <= 1.0 or not 0.0 < g <= 1.0:
        raise ValueError("moving_fraction must be in [0, 1] and moving_g in (0, 1]")
    fs = 1.0 - fm
    a = fs + g * fm
    if speckle:
        if n < 3:
            raise ValueError("the speckle average needs N_z >= 3")
        inv_a, inv_a2 = 1.0 / ((n - 1) * a), 1.0 / ((n - 1) * (n - 2) * a * a)
    else:
        inv_a, inv_a2 = 1.0 / (n * a), 1.0 / (n * n * a * a)
    sigma2 = noise_power(1.0, float(snr_db))  # signal power 1
    walk = (t * t - 1.0) / (6.0 * t)
    ms = (1.0 - 1.0 / t) * sigma2 / 2.0 * inv_a / a + walk * n_used * sigma2**2 / 2.0 * inv_a2
    if fm > 0:
        lags = np.abs(np.arange(t)[:, None] - np.arange(t)[None, :])
        about_mean = 1.0 - float(np.mean(g**lags))
        ms += n * fs * fm / 2.0 * inv_a2 * about_mean + walk * n * (1.0 - g * g) * fm * fm / 2.0 * inv_a2
    return math.sqrt(ms)

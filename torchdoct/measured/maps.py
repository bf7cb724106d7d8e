"""DOCT maps of complex (or intensity) OCT sequences at one or more resolutions.

Kept whole (over 800 lines): one request is checked, planned, reduced, measured and written in the eight
named stages below, which share the request's checked state; splitting them would pass that state
across modules without making a stage shorter.

For every requested resolution (:func:`torchdoct.measured.resolution.parse_resolution`: ``original``,
``axial=14``, ``lateral=18``, ``axial=14,lateral=18``) the complex field is reduced
(:func:`torchdoct.measured.resolution.reduce_resolution`, paper Eqs. 1-8), ``I = |E|²`` is formed, and per
pixel (time last, ``[..., T]``) the channels below are computed:

* ``liv`` (dB²): :func:`torchdoct.sim.metrics.liv`, ddof-0 variance of ``10·log10 I`` (physics.md §1);
* ``ocds`` (1/s): −OLS slope of the lag correlation over ``ocds_delay_range_s`` (physics.md §2.4;
  :func:`torchdoct.sim.metrics.ocds`; the default Pearson/dB path evaluates only the lags inside the
  range, with the same definition, see :func:`ocds_map`);
* ``mean_db`` (dB): ``10·log10(mean_t I)``, the dB of the time-averaged linear intensity (the
  structural OCT image; with the default ``normalization="power"`` of the reduction it stays
  comparable across resolutions);
* on request ``aliv`` (dB²) and ``swiftness`` (1/s): physics.md §3, as the COG contrast library
  defines them: the LIV curve ``LIV(T_w)`` (ddof-0 variance of the dB intensity over every run of
  consecutive frames spanning exactly ``T_w``, averaged over start positions, for every ``T_w`` that
  is a difference of frame times; :func:`liv_curve`), smoothed by a 3×3 box over each (Z, X) image
  (``cv2.blur``, border reflect-101; ``aliv_smoothing=False`` turns it off) over the *defined*
  neighbours only (an undefined pixel's curve does not enter its neighbours' mean; with every pixel
  defined this is exactly ``cv2.blur``), then the saturation model
  ``LIV(T_w) = a·(1 − exp(−T_w/τ))`` fitted by unweighted least squares with ``a, τ ≥ 0``
  (:func:`fit_saturation`); ``aliv = a``, ``swiftness = 1/τ``.

Non-finite samples (NaN or inf in some frame) are masked per pixel instead of reaching the reduction's FFT
(where one NaN would make every reduced pixel NaN). At the original resolution the pixel itself is NaN in
every channel. A reduction is a normalised convolution (:func:`_normalized`): a pixel with a non-finite
sample enters with weight 0 at every frame (so the weights do not change in time), and each reduced pixel
is divided by the share of its window that fell on finite pixels, written as the ``valid_weight@RES``
channel (1 where no non-finite sample is within reach); a reduced pixel is NaN only where that share is
below :data:`MIN_VALID_WEIGHT` (plus the 3×3 smoothing for aLIV/Swiftness). A missing sample costs its
neighbourhood a share of its window, not its pixels. ``meta["nonfinite"]`` counts the samples and the
masked pixels per resolution. Undefined values are NaN: pixels with ``I = 0`` have no dB value (LIV, OCDS, aLIV,
Swiftness NaN; ``mean_db`` NaN only if ``I = 0`` at every frame), and Swiftness is NaN where the fit
gives ``a = 0`` (no fluctuation, τ undefined). After a resolution reduction the same rule holds with a
floor: ``I ≤ (64·ε)²·max I`` (ε the machine epsilon of the data type, ``max I`` the largest finite
intensity of the input: −102 dB for complex64, −277 dB for complex128) counts as ``I = 0``, because
exactly empty pixels acquire FFT round-off of the reduction there, not signal (:data:`EMPTY_RULE`,
recorded as ``meta["empty_rule"]``). At the original resolution only exact zeros are empty. An input
with no finite nonzero sample, or with fewer than 2 frames, is refused.

aLIV/Swiftness fits that end on a τ bound (:func:`tau_bound_code`) are flagged in the ``aliv_fit``
channel written with them (0 inside, 1 lower bound, 2 upper bound, NaN undefined); their counts per
resolution are in ``meta["aliv"]["flagged_pixels"]`` and :func:`write_pngs` draws them in magenta.

Optics: only a resolution change needs the pitch and the original resolutions (``system``); maps at
the original resolution record them when known (``None`` otherwise).

Bulk phase (``bulk_phase``, ``torchdoct maps --bulk-phase METHOD``): the phase common to an A-line's
pixels at each frame is estimated per A-line and consecutive frame pair and removed
(:mod:`torchdoct.measured.bulkphase`, physics.md §12) before the field is reduced, so a lateral
reduction adds A-lines with their bulk motion removed; the estimate runs first, in lateral slabs of
whole A-lines (it needs every depth row used and every frame of an A-line), and only the
``[T, (Y), X]`` phases are kept. The maps record it in ``meta["bulk_phase"]`` (method, reference
``"consecutive frames"``, mask, rows).

Block raster volumes (:class:`torchdoct.measured.io.BlockRaster` in the sequence metadata): maps are
computed on the whole volume (the lateral Gaussian runs across block boundaries, as in the paper),
then the B-scans next to the boundaries are dropped; ``meta["y_indices"]`` lists the kept positions.

Work is done in slabs, so memory stays bounded and a progress bar shows: each stage says which axes it
needs whole or with a halo (the lateral reduction the en-face axes, the axial window a halo of 5σ' + 1
pixels along depth, the aLIV smoothing one pixel along Z and X, the bulk-phase correction and the per-pixel
metrics and features nothing), and :func:`~torchdoct.measured.slabs.slab_cut` cuts the axis they need least (depth slabs with their
halo, or whole B-scans of a volume); results do not depend on the slab size beyond the window truncation at 5σ'.

Signature channels (``signature``, ``torchdoct maps --signature``): the decorrelation-signature features of
:func:`torchdoct.sim.signature.pixel_features` (the extractor of the training data) of every resolution's
field, computed in the same slab loop from the same reduced field as the other channels, pixel by pixel;
channels ``f"{feature}@{resolution}"`` after the DOCT channels. With ``bulk_phase`` they read the
corrected field at every resolution (the original one included: the field features read the phase).
Pixels that non-finite samples leave without a value (above) are NaN, as in the other channels; otherwise the signature's own
rule holds (NaN where ``I = 0`` at some frame, :mod:`torchdoct.sim.signature`), without the floor of
:data:`EMPTY_RULE`.

Doppler channels (``doppler``, ``torchdoct maps --doppler``): ``doppler_phase_{m}`` at the original resolution,
the phase of each pixel's lag-``m`` field correlation relative to a static-tissue reference of its A-line or
B-scan (:mod:`torchdoct.measured.doppler`, docs/concepts/doppler-reference.md), last. The reference needs whole
A-lines, so it is estimated before the slab loop over lateral slabs of its own; the loop then computes the
channel per pixel. No reference anywhere, or intensity-only input: no channel, and ``meta["doppler"]`` says why.

The module runs the slab loop; the per-pixel metrics are in :mod:`torchdoct.measured.mapmetrics` and the
figures in :mod:`torchdoct.measured.mapfigures` (their public names are importable from here too).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Iterable, Mapping
from collections.abc import Sequence as _Seq
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..files import atomic_write, check_out
from ..runtime.interrupt import progress_disabled
from ..runtime.threads import one_torch_thread
from ..sim.signature import available_features, default_features, feature_unit, pixel_features
from ..sim.speckle import halo_pixels
from .bulkphase import CORRECTION_AXIS_NEEDS, BulkPhase, estimate_bulk_phase
from .bulkphase import phasor as _bulk_phasor
from .doppler import (
    DopplerReference,
    doppler_absent,
    doppler_channel_records,
    doppler_lags,
    doppler_name,
    doppler_slab,
    estimate_doppler_reference,
)
from .io import Maps, SequenceData
from .mapfigures import DEFAULT_HUE_RANGE, FLAG_RGB, map_figure, percentile_range, png_name, pseudo_color  # noqa: F401 (FLAG_RGB re-exported)
from .mapmetrics import (
    DEFAULT_OCDS_DELAY_RANGE_S,
    FIT_FLAG,
    METRICS,
    SMOOTHING_AXIS_NEEDS,
    TAU_BOUND_LOG_TOL,  # noqa: F401 (re-exported)
    UNITS,
    VALID_WEIGHT,
    box_smooth_zx,
    fit_saturation,
    liv_curve,
    ocds_map,
    pixel_metrics,
    tau_bound_code,
)
from .mapspeckle import (
    SPECKLE_MAX_OFFSET,
    SPECKLE_WINDOW,
    speckle_channel_records,
    speckle_channels,
    speckle_meta,
    speckle_slab,
    speckle_target,
)
from .resolution import (
    EDGE_MODES,
    NORMALIZATIONS,
    ResolutionTarget,
    axial_filter_sigma_um,
    check_target_in_view,
    check_target_sampled,
    depth_spectrum_center,
    lateral_filter_sigma_um,
    parse_resolution,
    reduce_resolution,
    reduction_axis_needs,
)
from .slabs import nonfinite_reach, nonfinite_reach_px, slab_cut

__all__ = [
    "METRICS",
    "FIT_FLAG",
    "UNITS",
    "DEFAULT_OCDS_DELAY_RANGE_S",
    "ocds_map",
    "liv_curve",
    "fit_saturation",
    "tau_bound_code",
    "box_smooth_zx",
    "MapsRequest",
    "check_maps_request",
    "compute_maps",
    "signature_channels",
    "speckle_channels",
    "speckle_target",
    "signature_maps",
    "pseudo_color",
    "map_figure",
    "write_pngs",
    "png_name",
]


# ----------------------------------------------------------------------------------------------
# maps of a sequence

#: The leakage floor of a resolution reduction is ``(EMPTY_FLOOR_EPS_FACTOR·ε)²·max I`` (ε of the data type).
EMPTY_FLOOR_EPS_FACTOR = 64
EMPTY_RULE = (
    "a pixel has no dB value where I = 0 or NaN at some frame; after a resolution reduction I <= "
    "(64·eps)²·max I (eps of the data type, max I over the input; -102 dB for complex64, -277 dB for "
    "complex128) counts as I = 0: FFT round-off of the reduction, not signal"
)


#: Decades the largest intensity of the data must keep above the smallest normal number of its data type:
#: speckle falls this far below its peak in fewer than 1 sample in 10¹⁴ (as
#: :data:`torchdoct.sim.simulate.INTENSITY_MARGIN`).
INTENSITY_MARGIN = 1e14


def _peak_intensity(data: np.ndarray, src: str) -> float:
    """Largest finite ``|E|²`` (or intensity) of ``data``, frame by frame; refuses data without any
    finite nonzero sample (every map would be NaN), and data whose intensities overflow or underflow their
    data type (within :data:`INTENSITY_MARGIN` of its smallest normal number), naming the fix."""
    peak = top = 0.0
    for k in range(data.shape[0]):
        f = np.asarray(data[k])
        with np.errstate(over="ignore", invalid="ignore"):
            v = f.real * f.real + f.imag * f.imag if np.iscomplexobj(f) else np.abs(f)
        overflow = ~np.isfinite(v) & np.isfinite(f)  # |E|² beyond the data type of finite samples
        if overflow.any():
            top = float(np.max(np.abs(f[overflow])))
            raise ValueError(
                f"{src}: |E|² overflows {v.dtype} (|E| up to {top:.3g}, the largest {v.dtype} |E|² is "
                f"{float(np.finfo(v.dtype).max):.3g}); scale the field down (e.g. divide it by "
                f"{10 ** math.ceil(math.log10(top) - 15):.0e}) or store it as complex128"
            )
        peak = max(peak, float(np.max(v, where=np.isfinite(v), initial=0.0)))
        top = max(top, float(np.max(np.abs(f), where=np.isfinite(f), initial=0.0)))
    dtype = np.dtype(np.float64) if data.dtype in (np.complex128, np.float64) else np.dtype(np.float32)
    if top > 0 and not peak >= float(np.finfo(dtype).tiny) * INTENSITY_MARGIN:
        sq = "|E|²" if np.iscomplexobj(data) else "the intensity"
        raise ValueError(
            f"{src}: {sq} underflows {dtype} (the largest sample is {top:.3g}; {dtype} holds intensities "
            f"down to {float(np.finfo(dtype).tiny):.3g}, and speckle falls decades below its peak): no "
            f"pixel would have a dB value; LIV and OCDS do not depend on the scale: scale the data up (e.g. "
            f"multiply it by {10 ** -math.floor(math.log10(top)):.0e}) or store it as "
            f"{'complex128' if np.iscomplexobj(data) else 'float64'}"
        )
    if not peak > 0:
        raise ValueError(
            f"{src}: holds no finite nonzero sample (every value is NaN, infinite or 0), so no pixel "
            "has a dB value; check the file (and --dataset / --axes)"
        )
    return peak


def _as_targets(resolutions: Iterable[str | ResolutionTarget]) -> list[ResolutionTarget]:
    targets: list[ResolutionTarget] = []
    for r in resolutions:
        t = r if isinstance(r, ResolutionTarget) else parse_resolution(r)
        if t.label in [x.label for x in targets]:
            raise ValueError(f"resolution {t.label!r} requested twice")
        targets.append(t)
    if not targets:
        raise ValueError("give at least one --resolution (e.g. original)")
    return targets


@dataclasses.dataclass(frozen=True)
class MapsRequest:
    """What :func:`compute_maps` was asked for, checked against the sequence (:func:`check_maps_request`).

    ``metrics``: the DOCT metrics in :data:`METRICS` order; ``features``: the signature channels (empty:
    none); ``targets``: the resolutions in the order asked; ``system``: the optics the maps record (every
    field when a target changes the resolution); ``signature_system``: the optics the signature channels
    record; ``lateral_um`` / ``axial_um``: the original resolutions (``None`` when unknown);
    ``changes``: the targets that change the resolution; ``source``: the name in messages;
    ``speckle``: the speckle-motion channels (:mod:`torchdoct.sim.speckle`, at the first target that keeps
    the original resolution; empty: none) and ``speckle_window`` their window (pixels per axis);
    ``doppler``: the lags of the Doppler channels asked (:mod:`torchdoct.measured.doppler`; empty: none)."""

    metrics: tuple[str, ...]
    features: tuple[str, ...]
    targets: tuple[ResolutionTarget, ...]
    system: dict[str, Any]
    signature_system: dict[str, Any] | None
    lateral_um: float | None
    axial_um: float | None
    changes: tuple[ResolutionTarget, ...]
    source: str
    speckle: tuple[str, ...] = ()
    speckle_window: int = 0
    doppler: tuple[int, ...] = ()

    def optics(self, t: ResolutionTarget) -> tuple[float | None, float | None]:
        """``(lateral, axial)`` resolution (µm) of target ``t``; ``(None, None)`` when the optics are unknown."""
        return t.resolved(self.system) if self.lateral_um is not None else (None, None)


#: Time windows the saturation fit of aLIV and Swiftness needs: more than its two parameters, so that it is
#: a fit (two windows would give ``a`` and ``τ`` exactly through any two values, noise and all).
MIN_ALIV_WINDOWS = 3


def _check_aliv_windows(times: _Seq[float], max_window_s: float | None, src: str) -> None:
    """Refuse aLIV/Swiftness over fewer than :data:`MIN_ALIV_WINDOWS` distinct time windows, naming the file,
    the count and the fix."""
    from ..conventions import delay_groups, delay_range_tolerance_s

    spans = [d for d, _ in delay_groups(times)]
    if max_window_s is not None:
        tol = delay_range_tolerance_s(times, (0.0, max_window_s))
        spans = [d for d in spans if d <= max_window_s + tol]
    if len(spans) < MIN_ALIV_WINDOWS:
        limit = "" if max_window_s is None else f" up to --aliv-max-window-s {max_window_s:g} s"
        raise ValueError(
            f"{src}: aLIV and Swiftness fit a·(1 − exp(−T/τ)) to the LIV curve, two parameters, so they "
            f"need at least {MIN_ALIV_WINDOWS} time windows; the {len(times)} frames give {len(spans)}"
            f"{limit}; record more frames{', raise --aliv-max-window-s' if limit else ''}, or leave aliv "
            "and swiftness out of --metrics"
        )


def check_maps_request(
    seq: SequenceData,
    resolutions: Iterable[str | ResolutionTarget] = ("original",),
    *,
    metrics: Iterable[str] = ("liv", "ocds", "mean_db"),
    signature: bool | _Seq[str] | None = None,
    ocds_delay_range_s: tuple[float, float] = DEFAULT_OCDS_DELAY_RANGE_S,
    ocds_scale: str = "db",
    ocds_estimator: str = "pearson",
    edge_mode: str = "reflect",
    normalization: str = "power",
    slab_elements: int = 1 << 23,
    speckle: bool | _Seq[str] | None = None,
    speckle_window: int = SPECKLE_WINDOW,
    doppler: bool | _Seq[int] | None = None,
    aliv_max_window_s: float | None = None,
) -> MapsRequest:
    """Stage 1 of :func:`compute_maps`, before any work: the metric and feature names, the options, the
    resources (:func:`torchdoct.runtime.resources.check_maps`), the frames, the optics that each resolution target
    needs and the pixel grid that must hold it, intensity-only data against a resolution change, and the
    OCDS delay range. Raises ``ValueError`` (``TypeError``) naming the option and the fix; the arguments
    are those of :func:`compute_maps`. A command calls it before its own costly steps (a bulk-phase
    estimate)."""
    wanted = [m for m in METRICS if m in set(metrics)]
    unknown = sorted(set(metrics) - set(METRICS))
    feats: tuple[str, ...] = ()
    sig_system = None
    if signature is not None and signature is not False:  # before any work: the names, the optics, the protocol
        feats, _ = signature_channels(seq, None if signature is True else signature)
        sig_system = seq.system  # the signature channels record the optics of every resolution
    spk: tuple[str, ...] = ()
    if speckle is not None and speckle is not False:
        spk = speckle_channels(seq, None if speckle is True else speckle, window=speckle_window)
    dop = doppler_lags(seq, doppler)
    if unknown or not (wanted or feats or spk or dop):
        raise ValueError(f"unknown metrics {unknown}; choose from {', '.join(METRICS)}")
    if edge_mode not in EDGE_MODES:
        raise ValueError(f"edge_mode must be one of {', '.join(EDGE_MODES)}; got {edge_mode!r}")
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {', '.join(NORMALIZATIONS)}; got {normalization!r}")
    targets = _as_targets(resolutions)
    src = seq.source or "sequence"
    from ..runtime.resources import check_maps  # the one resource check of every command, before any work

    check_maps(
        src,
        seq.data.shape,
        seq.data.dtype.itemsize,
        complex_samples=seq.is_complex,
        n_resolutions=len(targets),
        metrics=wanted + list(feats) + list(spk) + [doppler_name(m) for m in dop],
        slab_elements=slab_elements,
    )
    if seq.n_frames < 2:
        raise ValueError(
            f"{src}: {seq.n_frames} frame along T; DOCT maps need at least 2 frames (LIV is a variance "
            "over frames); check the file or --axes"
        )
    recorded = {k: v for k, v in dict(seq.meta.get("system") or {}).items() if v is not None}
    asked = [t for t in targets if t.lateral_resolution_um is not None or t.axial_resolution_um is not None]
    if asked and not seq.is_complex and not ("lateral_resolution_um" in recorded and "axial_resolution_um" in recorded):
        # no optics option can help intensity-only data: say so before asking for the optics
        raise _intensity_only(seq, asked)
    if asked:
        system = seq.system  # a resolution target needs the original optics (a clear error names the options)
    else:  # original resolution only: the optics are recorded when known, never required
        system = recorded
    known = "lateral_resolution_um" in system and "axial_resolution_um" in system
    lat0 = float(system["lateral_resolution_um"]) if known else None
    ax0 = float(system["axial_resolution_um"]) if known else None
    req = MapsRequest(
        metrics=tuple(wanted),
        features=feats,
        targets=tuple(targets),
        system=system,
        signature_system=sig_system,
        lateral_um=lat0,
        axial_um=ax0,
        changes=(),
        source=src,
        speckle=spk,
        speckle_window=int(speckle_window) if spk else 0,
        doppler=dop,
    )
    changes = tuple(t for t in targets if req.optics(t) != (lat0, ax0))
    for t in targets:  # validate every target before any work
        # a target asked: system is seq.system, which holds both original resolutions (or raised above)
        if t.lateral_resolution_um is not None:
            assert lat0 is not None
            lateral_filter_sigma_um(lat0, t.lateral_resolution_um)
            if t in changes:  # the grid must hold the target PSF (two pixels at least)
                check_target_sampled("lateral", lat0, t.lateral_resolution_um, seq.pitch_um, seq.axes)
                check_target_in_view("lateral", lat0, t.lateral_resolution_um, seq.pitch_um, seq.axes, seq.data.shape)
        if t.axial_resolution_um is not None:
            assert ax0 is not None
            axial_filter_sigma_um(ax0, t.axial_resolution_um)
            if t in changes:
                check_target_sampled("axial", ax0, t.axial_resolution_um, seq.pitch_um, seq.axes)
                check_target_in_view("axial", ax0, t.axial_resolution_um, seq.pitch_um, seq.axes, seq.data.shape)
    if changes and not seq.is_complex:
        raise _intensity_only(seq, changes)
    if spk and all(t in changes for t in targets):
        raise ValueError(
            f"{src}: the speckle-motion channels are computed at the original resolution (the finest "
            "speckle: the most independent grains per window); add --resolution original"
        )
    if dop and all(t in changes for t in targets):
        raise ValueError(
            f"{src}: the Doppler channels are computed at the original resolution; add --resolution original"
        )
    times = seq.frame_times_s
    if "aliv" in wanted or "swiftness" in wanted:
        _check_aliv_windows(times, aliv_max_window_s, src)
    if "ocds" in wanted:
        lo, hi = ocds_delay_range_s
        if not (0 < lo < hi):
            raise ValueError(f"ocds_delay_range_s must be 0 < lo < hi (s); got {ocds_delay_range_s!r}")
        from ..sim.config import check_ocds_pairs

        check_ocds_pairs(
            times,
            (lo, hi),
            f"{seq.source or 'sequence'}: --ocds-delay-range-s",
            "narrow --ocds-delay-range-s, record more frames, or leave ocds out of --metrics",
        )
        probe = torch.rand(1, len(times), generator=torch.Generator().manual_seed(0)) + 1.0
        ocds_map(probe, times, delay_range_s=(lo, hi), scale=ocds_scale, estimator=ocds_estimator)
    return dataclasses.replace(req, changes=changes)


def _intensity_only(seq: SequenceData, changes: Iterable[ResolutionTarget]) -> ValueError:
    return ValueError(
        f"{seq.source or 'sequence'} holds intensity only (dtype {seq.data.dtype}): a resolution "
        f"change ({', '.join(t.label for t in changes)}) needs the complex field; use "
        "--resolution original only"
    )


def _bulk_phase_factor(
    seq: SequenceData,
    req: MapsRequest,
    bulk_phase: str | BulkPhase | None,
    *,
    slab_elements: int,
    device: torch.device,
    progress: bool,
) -> tuple[BulkPhase | None, np.ndarray | None]:
    """Stage 2 of :func:`compute_maps`: the bulk phase (estimated here for a method name) and the phasor
    that removes it, ``[T, (Y), 1, X]`` in the data's dtype, broadcast over depth (the multiplication of
    :func:`~torchdoct.measured.bulkphase.corrected_sequence`); ``(None, None)`` without ``bulk_phase``."""
    if isinstance(bulk_phase, str):
        bulk_phase = estimate_bulk_phase(seq, bulk_phase, slab_elements=slab_elements, device=device, progress=progress)
    elif bulk_phase is not None and not isinstance(bulk_phase, BulkPhase):
        raise TypeError(f"bulk_phase must be a method name or a BulkPhase; got {type(bulk_phase).__name__}")
    if bulk_phase is None:
        return None, None
    if not seq.is_complex:
        raise ValueError(
            f"{req.source} holds intensity only (dtype {seq.data.dtype}): bulk-phase correction needs the "
            "complex field; give the complex sequence, or drop --bulk-phase"
        )
    return bulk_phase, _bulk_phasor(bulk_phase, seq)


def _doppler_stage(
    seq: SequenceData, req: MapsRequest, bulk: np.ndarray | None, *, slab_elements: int, progress: bool
) -> tuple[DopplerReference | None, dict[str, Any] | None]:
    """Stage 2b of :func:`compute_maps`: the static-tissue reference of the Doppler channels, over whole A-lines
    before the slab loop (:func:`~torchdoct.measured.doppler.estimate_doppler_reference`), and
    ``meta["doppler"]``; ``(None, None)`` when not asked, ``(None, why)`` for intensity-only input."""
    if not req.doppler:
        return None, None
    if not seq.is_complex:
        return None, doppler_absent(seq, req.doppler)
    ref = estimate_doppler_reference(seq, req.doppler, bulk=bulk, slab_elements=slab_elements, progress=progress)
    return ref, ref.meta()


def _axial_center(seq: SequenceData, req: MapsRequest, axial_center: str | float) -> float | str:
    """Stage 3 of :func:`compute_maps`: the centre of the axial window (cycles/pixel), measured from the
    first frames' depth spectrum for ``"centroid"`` when an axial reduction needs it
    (:func:`~torchdoct.measured.resolution.depth_spectrum_center`), else as given."""
    if axial_center == "centroid" and seq.is_complex and any(t.axial_resolution_um is not None for t in req.changes):
        data = seq.data
        sub = torch.from_numpy(np.ascontiguousarray(data[: min(4, data.shape[0])], dtype=data.dtype.newbyteorder("=")))
        return depth_spectrum_center(sub, axes=seq.axes)
    if isinstance(axial_center, str) and axial_center not in ("zero", "centroid"):
        raise ValueError(f"axial_center must be 'zero', 'centroid' or a number (cycles/pixel); got {axial_center!r}")
    return axial_center


#: The share of a reduced pixel's window weight that must fall on finite samples for the pixel to have a
#: value (:func:`_normalized`): below half, the value would rest more on the missing samples' surroundings
#: than on the pixel's own neighbourhood.
MIN_VALID_WEIGHT = 0.5


def _normalized(
    red: torch.Tensor,
    bad: np.ndarray,
    seq: SequenceData,
    req: MapsRequest,
    t: ResolutionTarget,
    axes: str,
    edge_mode: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised convolution of a reduced slab whose pixels ``bad`` (``[(Y), Z, X]``, a non-finite sample at
    some frame) entered with weight 0 at every frame: the window's weight on the finite pixels,
    ``W = (g ∗ w) / (g ∗ 1)`` with ``g`` the reduction's envelope (unit sum, no carrier; the same padding), and
    the reduced field ``red / W`` where ``W >= MIN_VALID_WEIGHT`` (else left as it is: those pixels are NaN in
    the maps). A missing sample costs its neighbourhood a share of its window, not its value."""
    kw: dict[str, Any] = dict(
        pitch_um=seq.pitch_um,
        system=req.system,
        lateral_resolution_um=t.lateral_resolution_um,
        axial_resolution_um=t.axial_resolution_um,
        axes=axes,
        axial_center=0.0,
        edge_mode=edge_mode,
        normalization="sum",
    )
    w = torch.from_numpy(~bad).to(red.device, torch.complex128).unsqueeze(0)
    weight = reduce_resolution(w, **kw).real[0] / reduce_resolution(torch.ones_like(w), **kw).real[0]
    use = weight >= MIN_VALID_WEIGHT
    scale = torch.where(use, weight, torch.ones_like(weight)).to(red.real.dtype)
    return red / scale, weight.clamp(0.0, 1.0)


def _empty_floor(seq: SequenceData, req: MapsRequest) -> tuple[float, float]:
    """Stage 4 of :func:`compute_maps`: the largest finite intensity of the input and the floor below which a
    reduced pixel counts as empty, ``(64·ε)²·max I`` (:data:`EMPTY_RULE`); refuses data without a finite
    nonzero sample."""
    peak = _peak_intensity(seq.data, req.source)
    eps = float(np.finfo(_real_dtype(seq)).eps)
    return peak, peak * (EMPTY_FLOOR_EPS_FACTOR * eps) ** 2


def _real_dtype(seq: SequenceData) -> type:
    """The dtype of the maps' computation: float64 for complex128/float64 input, else float32."""
    return np.float64 if seq.data.dtype in (np.complex128, np.float64) else np.float32


@dataclasses.dataclass(frozen=True)
class _SlabPlan:
    """How one resolution's work is cut: along ``axis`` (index into the data), ``length`` rows in slabs of
    ``rows`` with a ``halo`` each side and a ``margin`` for the map stages; ``reach``: how far a non-finite
    sample reaches (:func:`~torchdoct.measured.slabs.nonfinite_reach_px`)."""

    target: ResolutionTarget
    axis: int
    length: int
    halo: int
    margin: int
    rows: int
    reach: dict[str, int]


def _slab_plans(
    seq: SequenceData, req: MapsRequest, *, bulk: bool, smoothing_margin: bool, edge_mode: str, slab_elements: int
) -> list[_SlabPlan]:
    """Stage 5 of :func:`compute_maps`: each resolution's cut, from what its stages need of the axes
    (:func:`~torchdoct.measured.slabs.slab_cut`): the bulk-phase correction (``bulk``), the reduction of a target that changes the
    resolution, the aLIV smoothing (``smoothing_margin``)."""
    data, axes = seq.data, seq.axes
    plans = []
    for t in req.targets:
        lat, ax = req.optics(t)
        ax0 = req.axial_um  # None with ax: the optics are unknown
        sig = (
            axial_filter_sigma_um(ax0, ax) / seq.pitch_um["z"]
            if ax0 is not None and ax is not None and ax != ax0
            else 0.0
        )
        field_needs = [CORRECTION_AXIS_NEEDS] if bulk else []
        if t in req.changes:
            field_needs.append(
                reduction_axis_needs(axes, lateral=lat != req.lateral_um, axial_sigma_px=sig, edge_mode=edge_mode)
            )
        if req.speckle and t is speckle_target(req):  # the window and its offsets beyond each slab
            h = halo_pixels(req.speckle_window, SPECKLE_MAX_OFFSET)
            field_needs.append({"Z": h, "Y": h})
        cut, halo, mrg = slab_cut(axes, field_needs, [SMOOTHING_AXIS_NEEDS] if smoothing_margin else [])
        cdim = axes.index(cut)
        n_c = data.shape[cdim]
        rows = max(1, min(n_c, int(slab_elements) // max(int(np.prod(data.shape)) // n_c, 1)))
        if halo is None:  # every axis it could cut is needed whole: one slab
            halo, rows = 0, n_c
        elif halo:  # a slab at least as deep as its halo on both sides
            rows = min(n_c, max(rows, 2 * halo))
        reach = nonfinite_reach_px(seq, t) if t in req.changes else {}
        plans.append(_SlabPlan(target=t, axis=cdim, length=n_c, halo=halo, margin=mrg, rows=rows, reach=reach))
    return plans


def _channel_records(req: MapsRequest, outputs: _Seq[str]) -> list[dict[str, Any]]:
    """Stage 6 of :func:`compute_maps`: one record per output channel (name, metric, unit, resolution, optics):
    the DOCT channels of every resolution, then the signature channels of every resolution."""
    channels: list[dict[str, Any]] = []
    sig_channels: list[dict[str, Any]] = []
    wl = req.system.get("wavelength_um")
    for t in req.targets:
        lat, ax = req.optics(t)
        for m in outputs:
            channels.append(
                {
                    "name": f"{m}@{t.label}",
                    "metric": m,
                    "unit": UNITS[m],
                    "resolution": t.label,
                    "wavelength_um": None if wl is None else float(wl),
                    "lateral_resolution_um": lat,
                    "axial_resolution_um": ax,
                }
            )
        if req.features:
            sig_system = req.signature_system
            assert sig_system is not None  # check_maps_request sets it with the signature channels
            s_lat, s_ax = t.resolved(sig_system)
            sig_channels += [
                {
                    "name": f"{f}@{t.label}",
                    "metric": f,
                    "unit": feature_unit(f),
                    "resolution": t.label,
                    "wavelength_um": float(sig_system["wavelength_um"]),
                    "lateral_resolution_um": s_lat,
                    "axial_resolution_um": s_ax,
                }
                for f in req.features
            ]
    spk_channels = speckle_channel_records(req, wl) if req.speckle else []
    return channels + sig_channels + spk_channels


@dataclasses.dataclass
class _SlabWork:
    """What every slab of :func:`_fill_maps` shares: the sequence and request, the output array and what the
    field stages need (the bulk phasor, the reduction's options, the empty floor, the metric options), and
    the counts of non-finite samples and masked pixels it gathers."""

    seq: SequenceData
    req: MapsRequest
    out: np.ndarray
    outputs: list[str]
    n_doct: int
    keep_y: np.ndarray | None
    bulk: np.ndarray | None
    device: torch.device
    axial_center: float | str
    edge_mode: str
    normalization: str
    floor: float
    smoothing_margin: int
    metric_options: dict[str, Any]
    chunk_pixels: int
    n_nonfinite: int = 0
    nonfinite_pixels: dict[str, int] = dataclasses.field(default_factory=dict)
    doppler: DopplerReference | None = None
    doppler_meta: dict[str, Any] | None = None
    slab_elements: int = 0


def _fill_maps(work: _SlabWork, plans: list[_SlabPlan], *, progress: bool, timings: dict[str, float] | None) -> None:
    """Stage 7 of :func:`compute_maps`: the slab loop, resolution by resolution (:func:`_map_slab` per slab),
    with a progress bar over the slabs and the seconds per resolution in ``timings``."""
    total = sum(math.ceil(p.length / p.rows) for p in plans)
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc="maps", unit="slab")
    for ti, plan in enumerate(plans):
        t0 = time.perf_counter()
        for c0 in range(0, plan.length, plan.rows):
            c1 = min(plan.length, c0 + plan.rows)
            for cols in _column_chunks(work, plan, c1 - c0):
                _map_slab(work, ti, plan, c0, c1, cols)
            if bar is not None:
                bar.update(1)
        if timings is not None:
            timings[plan.target.label] = time.perf_counter() - t0
    if bar is not None:
        bar.close()


def _column_chunks(work: _SlabWork, plan: _SlabPlan, rows: int) -> list[slice | None]:
    """The X ranges a slab of ``rows`` rows is computed in: the whole width (``[None]``), or, when the slab
    (every frame of even one row) holds more than ``work.slab_elements`` samples and its work is per pixel
    alone (the original resolution, no bulk phase, signature, speckle, Doppler or map smoothing), columns
    that fit: a long sequence then stays within ``--max-memory-gb`` (the per-pixel metrics do not depend
    on which pixels are computed together)."""
    data = work.seq.data
    per_row = int(np.prod(data.shape, dtype=np.int64)) // data.shape[plan.axis]
    n_x = data.shape[-1]
    per_pixel = (
        plan.target not in work.req.changes
        and work.bulk is None
        and not work.req.features
        and not work.req.speckle
        and work.doppler is None
        and plan.halo == 0
        and plan.margin == 0
        and work.smoothing_margin == 0
    )
    if not work.slab_elements or not per_pixel or rows * per_row <= work.slab_elements:
        return [None]
    width = max(1, int(work.slab_elements) // max(rows * per_row // n_x, 1))
    return [slice(x0, min(n_x, x0 + width)) for x0 in range(0, n_x, width)]


def _map_slab(work: _SlabWork, ti: int, plan: _SlabPlan, c0: int, c1: int, cols: slice | None = None) -> None:
    """The rows ``c0:c1`` of resolution ``ti`` along the plan's axis: read the slab with its halo, remove the
    bulk phase, mask the non-finite samples (they enter the reduction as 0), reduce the resolution, form
    the intensity (the empty floor after a reduction), compute the per-pixel metrics on the rows and the
    map stages' margin, NaN the pixels the non-finite samples reach, and write the DOCT channels; then the
    signature of the slab's own pixels from the same field."""
    seq, req, out = work.seq, work.req, work.out
    data, axes = seq.data, seq.axes
    t, cdim, halo, mrg = plan.target, plan.axis, plan.halo, plan.margin
    changed = t in req.changes
    outputs, feats = work.outputs, req.features
    real_dtype = _real_dtype(seq)
    a0, a1 = max(0, c0 - halo), min(plan.length, c1 + halo)
    sel = [slice(None)] * data.ndim
    sel[cdim] = slice(a0, a1)
    if cols is not None:  # a column range of a per-pixel slab (_column_chunks)
        sel[-1] = cols
    raw = np.array(data[tuple(sel)], dtype=data.dtype.newbyteorder("="), copy=True)  # native byte order
    corrected = None
    if work.bulk is not None and (changed or feats):  # bulk phase removed before the A-lines are mixed
        psel = list(sel)
        psel[axes.index("Z")] = slice(None)
        corrected = torch.from_numpy(np.multiply(raw, work.bulk[tuple(psel)])).to(work.device)
    # the intensity maps at the original resolution read no phase: the field as recorded
    block = corrected if changed and corrected is not None else torch.from_numpy(raw).to(work.device)
    bad = None
    fin = torch.isfinite(block)
    if not bool(fin.all()):  # masked per pixel: non-finite samples enter the reduction as 0
        bad = (~fin).any(dim=0).cpu().numpy()  # [(Y), Z, X] over a0:a1
        if ti == 0:
            work.n_nonfinite += int((~fin).narrow(cdim, c0 - a0, c1 - c0).sum())
        block = torch.where(fin, block, torch.zeros_like(block))
        if corrected is not None and not changed:
            corrected = torch.where(fin, corrected, torch.zeros_like(corrected))
        if changed:  # a pixel with a non-finite sample enters every frame with weight 0 (no change in time)
            block = torch.where(torch.from_numpy(bad).to(block.device), torch.zeros_like(block), block)
    del fin
    weight = None  # the share of the window's weight on finite samples, [(Y), Z, X] over a0:a1
    if changed:
        red = reduce_resolution(
            block,
            pitch_um=seq.pitch_um,
            system=req.system,
            lateral_resolution_um=t.lateral_resolution_um,
            axial_resolution_um=t.axial_resolution_um,
            axes=axes,
            axial_center=work.axial_center,
            edge_mode=work.edge_mode,
            normalization=work.normalization,
        )
        if bad is not None:
            red, weight = _normalized(red, bad, seq, req, t, axes, work.edge_mode)
    else:
        red = block
        if bad is not None:
            weight = torch.from_numpy((~bad).astype(np.float64))
    # the signature's field: the reduced one, or at the original resolution the bulk-corrected one
    field = corrected if corrected is not None and not changed else red
    m0, m1 = max(a0, c0 - mrg), min(a1, c1 + mrg)
    red = red.narrow(cdim, m0 - a0, m1 - m0)
    if red.is_complex():
        inten = red.real**2 + red.imag**2
    else:
        inten = red.to(torch.float64 if real_dtype == np.float64 else torch.float32)
    if changed:  # FFT round-off of the reduction is no signal: treated as I = 0 (module docstring)
        inten = torch.where(inten > work.floor, inten, torch.zeros_like(inten))
    wanted = list(req.metrics)
    vals = (
        pixel_metrics(inten, seq.frame_times_s, wanted, **work.metric_options, chunk_pixels=work.chunk_pixels)
        if wanted
        else {}
    )
    del inten
    masks = {}
    if weight is not None:
        vals[VALID_WEIGHT] = weight.narrow(cdim - 1, m0 - a0, m1 - m0).to(torch.float64)
    if bad is not None:
        sp = axes[1:]
        assert weight is not None  # set above whenever bad is
        lost = (weight < MIN_VALID_WEIGHT).cpu().numpy()
        masks["pixel"] = lost
        if work.smoothing_margin:
            grown = {c: work.smoothing_margin if c in "ZX" else 0 for c in "YZX"}
            masks["smoothed"] = nonfinite_reach(lost, sp, grown, work.edge_mode == "wrap")
        core = [slice(None)] * (data.ndim - 1)
        core[cdim - 1] = slice(c0 - a0, c1 - a0)
        masks = {k: v[tuple(core)] for k, v in masks.items()}
        work.nonfinite_pixels[t.label] = work.nonfinite_pixels.get(t.label, 0) + int(np.count_nonzero(masks["pixel"]))
    for mi, m in enumerate(outputs):
        v = vals[m].narrow(cdim - 1, c0 - m0, c1 - c0).cpu().numpy()
        if masks and m != VALID_WEIGHT:
            smoothed = m in ("aliv", "swiftness", FIT_FLAG) and "smoothed" in masks
            v = np.where(masks["smoothed" if smoothed else "pixel"], np.nan, v)
        idx: list[Any] = [ti * len(outputs) + mi] + [slice(None)] * (data.ndim - 1)
        idx[cdim] = slice(c0, c1)
        if cols is not None:
            idx[-1] = cols
        out[tuple(idx)] = v
    if feats:  # the signature of the slab's own pixels (no halo), from the same field
        x = field.narrow(cdim, c0 - a0, c1 - c0)
        if not x.is_complex():
            x = x.to(torch.float64 if real_dtype == np.float64 else torch.float32)
        x = x.movedim(0, -1)  # [*spatial, T]
        n_doct = work.n_doct
        idx = [slice(n_doct + ti * len(feats), n_doct + (ti + 1) * len(feats))] + [slice(None)] * (data.ndim - 1)
        idx[cdim] = slice(c0, c1)
        ys = None
        keep_y = work.keep_y
        if keep_y is not None:  # only the B-scans kept
            ys = np.flatnonzero(keep_y[c0:c1] if cdim == 1 else keep_y)
            x = x[torch.as_tensor(ys)]
            idx[1] = ys + (c0 if cdim == 1 else 0)
        feat = pixel_features(x, seq.frame_times_s, feats, chunk_pixels=work.chunk_pixels)[1]
        f = feat.movedim(-1, 0).cpu().numpy()  # [F, *spatial]
        if masks:  # the pixels that non-finite samples reach, as for the DOCT channels
            f = np.where(masks["pixel"] if ys is None else masks["pixel"][ys], np.nan, f)
        out[tuple(idx)] = f
    if req.speckle and t is speckle_target(req):  # the windows of the slab's own pixels, read with their halo
        idx, f = speckle_slab(
            field,
            seq,
            req,
            cdim,
            a0,
            c0,
            c1,
            base=work.n_doct + len(req.targets) * len(feats),
            keep_y=work.keep_y,
            mask=masks.get("pixel"),
        )
        out[tuple(idx)] = f
    if work.doppler is not None and work.doppler.lags and t is speckle_target(req):
        _doppler_channels(work, raw, sel, cdim, a0, c0, c1, masks.get("pixel"))
    del field


def _doppler_channels(
    work: _SlabWork, raw: np.ndarray, sel: list[slice], cdim: int, a0: int, c0: int, c1: int, mask: np.ndarray | None
) -> None:
    """The Doppler channels (the last ones) of the rows ``c0:c1`` from the slab ``raw`` as read (rows ``a0:``),
    bulk-corrected as the reference was (:func:`~torchdoct.measured.doppler.doppler_slab`): only the kept
    B-scans of a block raster, NaN where ``mask`` (the pixels non-finite samples reach) is set."""
    seq, out, ref = work.seq, work.out, work.doppler
    assert ref is not None  # called only with a Doppler reference (_map_slab)
    x = raw
    if work.bulk is not None:
        psel = list(sel)
        psel[seq.axes.index("Z")] = slice(None)
        x = np.multiply(raw, work.bulk[tuple(psel)])
    xt = torch.from_numpy(x).narrow(cdim, c0 - a0, c1 - c0)
    f = doppler_slab(xt, ref, cdim, c0, c1, chunk_pixels=work.chunk_pixels)
    n = len(ref.lags)
    idx: list[Any] = [slice(out.shape[0] - n, out.shape[0])] + [slice(None)] * (xt.dim() - 1)
    idx[cdim] = slice(c0, c1)
    if work.keep_y is not None:
        ys = np.flatnonzero(work.keep_y[c0:c1] if cdim == 1 else work.keep_y)
        f = f[:, ys]
        mask = None if mask is None else mask[ys]
        idx[1] = ys + (c0 if cdim == 1 else 0)
    if mask is not None:
        f = np.where(mask, np.nan, f)
    out[tuple(idx)] = f


def _maps_result(
    work: _SlabWork,
    channels: list[dict[str, Any]],
    *,
    bulk_phase: BulkPhase | None,
    peak: float,
    axial_center: str | float,
    options: dict[str, Any],
) -> Maps:
    """Stage 8 of :func:`compute_maps`: the metadata (channels, optics, the metric and reduction options, the
    empty rule, the bulk phase, the non-finite counts, the aLIV fit, the signature), the block raster's
    boundary B-scans dropped, and the :class:`Maps` in float32."""
    seq, req, out = work.seq, work.req, work.out
    axes, outputs = seq.axes, work.outputs
    fc = work.axial_center
    wanted = req.metrics
    meta: dict[str, Any] = {
        "channels": channels,
        "axes": "C" + axes[1:],
        "pitch_um": seq.meta.get("pitch_um"),
        "frame_times_s": seq.frame_times_s,
        "system": req.system,
        "ocds_delay_range_s": [float(v) for v in options["ocds_delay_range_s"]],
        "ocds_scale": options["ocds_scale"],
        "ocds_estimator": options["ocds_estimator"],
        "source": seq.source,
        "empty_rule": {
            "rule": EMPTY_RULE,
            "floor_relative_db": 10.0 * math.log10(work.floor / peak),
            "floor": work.floor,
            "max_intensity": peak,
        },
        "reduction": {
            "edge_mode": work.edge_mode,
            "normalization": work.normalization,
            "axial_center": axial_center if isinstance(axial_center, str) else float(axial_center),
            "axial_center_cycles_per_pixel": float(fc) if not isinstance(fc, str) else 0.0,
            "lateral_axes": "YX" if "Y" in axes else "X",
        },
    }
    if bulk_phase is not None:
        meta["bulk_phase"] = bulk_phase.meta()
    if work.n_nonfinite:
        meta["nonfinite"] = {
            "samples": work.n_nonfinite,
            "masked_pixels": {t.label: work.nonfinite_pixels.get(t.label, 0) for t in req.targets},
            "rule": "pixels a non-finite sample reaches (its own; within 5 sigma of the reduction "
            "window along each filtered axis) are NaN in every channel",
        }
    if "aliv" in wanted or "swiftness" in wanted:
        meta["aliv"] = {
            "smoothing": "box3x3" if options["aliv_smoothing"] else "none",
            "max_window_s": options["aliv_max_window_s"],
            "model": "a*(1-exp(-T/tau)); aliv=a, swiftness=1/tau",
        }
    raster = seq.block_raster
    if raster is not None:
        keep_y = work.keep_y
        assert keep_y is not None  # compute_maps sets it for a block raster
        meta["block_raster"] = raster.to_dict()
        out = out[:, keep_y]
        meta["y_indices"] = [int(i) for i in np.flatnonzero(keep_y)]
    if FIT_FLAG in outputs:
        meta["aliv"]["flag"] = (
            f"{FIT_FLAG} channel: 1 where the fit ended on the lower τ bound (curve flat over the "
            "windows), 2 on the upper bound (still rising at the longest window), 0 inside, NaN "
            "undefined; aLIV/Swiftness there are bounds of the model, not measurements"
        )
        meta["aliv"]["flagged_pixels"] = {
            c["resolution"]: {
                "tau_at_lower_bound": int(np.sum(out[i] == 1)),
                "tau_at_upper_bound": int(np.sum(out[i] == 2)),
            }
            for i, c in enumerate(channels)
            if c["metric"] == FIT_FLAG
        }
    if req.features:
        meta["signature"] = {
            "features": list(req.features),
            "intensity_only": not seq.is_complex,
            "definition": "torchdoct.sim.signature (lags in frames)",
        }
    if req.speckle:
        meta["speckle"] = speckle_meta(req)
    if work.doppler_meta is not None:
        meta["doppler"] = work.doppler_meta
    return Maps(maps=out.astype(np.float32, copy=False), channels=tuple(c["name"] for c in channels), meta=meta)


@one_torch_thread
def compute_maps(
    seq: SequenceData,
    resolutions: Iterable[str | ResolutionTarget] = ("original",),
    *,
    metrics: Iterable[str] = ("liv", "ocds", "mean_db"),
    ocds_delay_range_s: tuple[float, float] = DEFAULT_OCDS_DELAY_RANGE_S,
    ocds_scale: str = "db",
    ocds_estimator: str = "pearson",
    aliv_smoothing: bool = True,
    aliv_max_window_s: float | None = None,
    axial_center: str | float = "zero",
    edge_mode: str = "reflect",
    normalization: str = "power",
    drop_boundary: bool = True,
    device: str | torch.device | None = None,
    bulk_phase: str | BulkPhase | None = None,
    signature: bool | _Seq[str] | None = None,
    slab_elements: int = 1 << 23,
    chunk_pixels: int = 1 << 16,
    progress: bool = False,
    timings: dict[str, float] | None = None,
    speckle: bool | _Seq[str] | None = None,
    speckle_window: int = SPECKLE_WINDOW,
    doppler: bool | _Seq[int] | None = None,
) -> Maps:
    """DOCT maps of ``seq`` at every resolution in ``resolutions`` (see the module docstring).

    ``metrics``: any of ``liv``, ``ocds``, ``mean_db``, ``aliv``, ``swiftness``. ``axial_center``,
    ``edge_mode``, ``normalization``: :func:`torchdoct.measured.resolution.reduce_resolution`.
    ``drop_boundary``: drop the block-boundary B-scans of a block raster volume. ``bulk_phase``: a
    method of :mod:`torchdoct.measured.bulkphase` (estimated here with its defaults) or a
    :class:`~torchdoct.measured.bulkphase.BulkPhase` estimated from ``seq``: each A-line's frames are
    multiplied by ``exp(−iφ̂_i)`` before the resolution reduction, slab by slab, as
    :func:`~torchdoct.measured.bulkphase.corrected_sequence` does (the same numbers; the intensity maps at
    the original resolution do not read the phase and are unchanged bit for bit); recorded as
    ``meta["bulk_phase"]``; intensity-only input is refused. ``signature``: also the signature channels
    (module docstring) of every resolution, after the DOCT channels: ``True`` for
    :func:`signature_channels` of the sequence (the intensity part of intensity-only data), or the
    feature names; recorded as ``meta["signature"]`` (``metrics`` may then be empty). ``slab_elements``:
    complex samples per depth slab; ``chunk_pixels``: pixels per metric chunk (memory only).
    ``timings`` (optional dict) receives seconds per resolution label. ``speckle``: also the speckle-motion
    channels of :func:`speckle_channels` (``True`` for the defaults, or the names), after every other channel,
    from the field of the first target that keeps the original resolution (bulk-corrected with
    ``bulk_phase``), each pixel's ``speckle_window``-pixel window read across slab boundaries (a halo of
    :func:`torchdoct.sim.speckle.halo_pixels` rows); recorded as ``meta["speckle"]``. ``doppler``: also the
    Doppler phase against a static-tissue reference (:mod:`torchdoct.measured.doppler`; ``True`` for lag 1,
    or the lags in frames), last, at the original resolution; its reference is estimated first over whole
    A-lines (:func:`_doppler_stage`); recorded as ``meta["doppler"]`` with the reference share; a lag
    without any reference, or intensity-only input, gives no channel and says why there. Returns
    :class:`Maps` (float32 ``[C, (Y), Z, X]``, channels ``f"{metric}@{resolution}"``).

    The stages, in this order: :func:`check_maps_request` (everything that can be refused, before any
    work), :func:`_bulk_phase_factor` (the bulk phase and its phasor), :func:`_doppler_stage` (the Doppler
    channels' reference), :func:`_axial_center` (the axial
    window's centre), :func:`_empty_floor` (the largest intensity and the empty floor), :func:`_slab_plans`
    (each resolution's cut), :func:`_channel_records` (the channels' names and optics), :func:`_fill_maps`
    (the slab loop, :func:`_map_slab` per slab) and :func:`_maps_result` (metadata, block raster, float32).
    """
    req = check_maps_request(
        seq,
        resolutions,
        metrics=metrics,
        signature=signature,
        ocds_delay_range_s=ocds_delay_range_s,
        ocds_scale=ocds_scale,
        ocds_estimator=ocds_estimator,
        edge_mode=edge_mode,
        normalization=normalization,
        slab_elements=slab_elements,
        speckle=speckle,
        speckle_window=speckle_window,
        doppler=doppler,
        aliv_max_window_s=aliv_max_window_s,
    )
    dev = torch.device(device) if device is not None else torch.device("cpu")
    bulk_phase, bulk = _bulk_phase_factor(
        seq, req, bulk_phase, slab_elements=slab_elements, device=dev, progress=progress
    )
    dref, dmeta = _doppler_stage(seq, req, bulk, slab_elements=slab_elements, progress=progress)
    n_dop = len(dref.lags) if dref is not None else 0
    fc = _axial_center(seq, req, axial_center)
    fitted = "aliv" in req.metrics or "swiftness" in req.metrics
    margin = 1 if (aliv_smoothing and fitted) else 0
    peak, floor = _empty_floor(seq, req)
    outputs = list(req.metrics) + ([FIT_FLAG] if fitted else []) + ([VALID_WEIGHT] if seq.nonfinite_samples else [])
    n_doct = len(req.targets) * len(outputs)  # the DOCT channels, then the signature channels
    raster = seq.block_raster
    keep_y = None  # the B-scans a block raster volume keeps (its others are dropped at the end)
    if raster is not None:
        keep_y = raster.keep_y() if drop_boundary else np.ones(raster.n_y, dtype=bool)
    out = np.full(
        (n_doct + len(req.targets) * len(req.features) + len(req.speckle) + n_dop, *seq.data.shape[1:]),
        np.nan,
        dtype=_real_dtype(seq),
    )
    plans = _slab_plans(
        seq, req, bulk=bulk is not None, smoothing_margin=bool(margin), edge_mode=edge_mode, slab_elements=slab_elements
    )
    channels = _channel_records(req, outputs)
    if dref is not None and n_dop:
        t_dop = speckle_target(req)
        channels += doppler_channel_records(dref, t_dop.label, req.optics(t_dop), req.system.get("wavelength_um"))
    options = dict(
        ocds_delay_range_s=tuple(ocds_delay_range_s),
        ocds_scale=ocds_scale,
        ocds_estimator=ocds_estimator,
        aliv_smoothing=aliv_smoothing,
        aliv_max_window_s=aliv_max_window_s,
    )
    work = _SlabWork(
        seq=seq,
        req=req,
        out=out,
        outputs=outputs,
        n_doct=n_doct,
        keep_y=keep_y,
        bulk=bulk,
        device=dev,
        axial_center=fc,
        edge_mode=edge_mode,
        normalization=normalization,
        floor=floor,
        smoothing_margin=margin,
        metric_options=options,
        chunk_pixels=chunk_pixels,
        doppler=dref,
        doppler_meta=dmeta,
        slab_elements=slab_elements,
    )
    _fill_maps(work, plans, progress=progress, timings=timings)
    return _maps_result(work, channels, bulk_phase=bulk_phase, peak=peak, axial_center=axial_center, options=options)


def signature_channels(seq: SequenceData, names: _Seq[str] | None = None) -> tuple[tuple[str, ...], str | None]:
    """The signature features that maps of ``seq`` get, and a sentence for the user (or ``None``).

    ``names``: default :func:`torchdoct.sim.signature.default_features` of the sequence's frame count, of
    which intensity-only sequences get the intensity part (the sentence says so; a model that needs the
    phase refuses such maps); named features that need the phase are refused for intensity-only data.
    Unknown names, lags the protocol cannot hold and non-uniform frame intervals are refused here,
    before any work.
    """
    times = list(seq.frame_times_s)
    wanted = tuple(names) if names is not None else default_features(len(times))
    feats = available_features(wanted, seq.is_complex)
    note = None
    if len(feats) < len(wanted):
        if names is not None:
            missing = [n for n in wanted if n not in feats]
            raise ValueError(
                f"{seq.source or 'sequence'} holds intensity only: the signature features "
                f"{', '.join(missing)} need the complex field (phase)"
            )
        note = (
            f"{seq.source or 'sequence'} holds intensity only: the signature has only its intensity part "
            f"({len(feats)} of {len(wanted)} features per resolution; no g1/phase features); models that "
            "need the phase will refuse these maps"
        )
    probe = torch.ones(1, len(times), dtype=torch.complex64 if seq.is_complex else torch.float32)
    pixel_features(probe, times, feats)  # the names, lags and frame times, on one pixel
    return feats, note


def signature_maps(
    maps: Maps,
    seq: SequenceData,
    resolutions: _Seq[str | ResolutionTarget] = ("original",),
    *,
    names: _Seq[str] | None = None,
    chunk_pixels: int = 1 << 16,
) -> tuple[Maps, str | None]:
    """``maps`` (from :func:`compute_maps` of ``seq``) with the signature channels of every resolution
    appended: ``f"{feature}@{resolution}"``, metric = the feature name, its unit and the optics of the
    resolution; ``meta["signature"]`` records the features.

    The channels are those of ``compute_maps(..., signature=...)``: the field of each resolution reduced
    with the reduction settings recorded in ``maps.meta["reduction"]`` (paper Eqs. 1-8), slab by slab,
    then :func:`torchdoct.sim.signature.pixel_features` per pixel; the B-scans of ``maps.meta["y_indices"]``
    are kept. ``names``: :func:`signature_channels`. Returns ``(maps, note)`` with ``note`` a sentence
    for the user when only the intensity part could be computed, else ``None``.
    """
    red_meta = maps.meta.get("reduction") or {}
    feats, note = signature_channels(seq, names)
    keep = maps.meta.get("y_indices")
    raster = seq.block_raster
    sig = compute_maps(
        seq,
        resolutions,
        metrics=(),
        signature=feats,
        axial_center=red_meta.get("axial_center_cycles_per_pixel", 0.0) or "zero",
        edge_mode=red_meta.get("edge_mode", "reflect"),
        normalization=red_meta.get("normalization", "power"),
        drop_boundary=raster is not None and keep is not None and len(keep) < raster.n_y,
        chunk_pixels=chunk_pixels,
    )
    block = sig.maps
    if keep is not None and sig.meta.get("y_indices") != list(keep):
        raise ValueError(
            f"maps keep the B-scans {list(keep)}, but {seq.source or 'the sequence'} gives "
            f"{sig.meta.get('y_indices')}: give the sequence the maps were computed from"
        )
    meta = dict(maps.meta)
    meta["channels"] = list(maps.meta["channels"]) + list(sig.meta["channels"])
    meta["signature"] = sig.meta["signature"]
    arr = np.concatenate([maps.maps, block], axis=0).astype(np.float32, copy=False)
    return Maps(maps=arr, channels=tuple(c["name"] for c in meta["channels"]), meta=meta), note


# ----------------------------------------------------------------------------------------------
# the PNG set


def write_pngs(
    maps: Maps,
    out_path: str | Path,
    *,
    ranges: Mapping[str, tuple[float, float]] | None = None,
    db_range: tuple[float, float] | None = None,
    hue_range: tuple[float, float] = DEFAULT_HUE_RANGE,
    y_index: int | None = None,
    force: bool = False,
    check_only: bool = False,
) -> list[Path]:
    """One figure PNG per channel (:func:`map_figure`), named by :func:`png_name`; the ``aliv_fit``
    flags are drawn inside the aLIV/Swiftness images, not as images of their own.

    ``ranges``: ``{metric: (lo, hi)}``; a metric without one gets the 1st-99th percentile of its
    finite values pooled over all resolutions (so resolutions share one colour scale).
    ``db_range``: default the 5th-99.9th percentile of all ``mean_db`` values (the brightness of the
    DOCT images and the grey scale of ``mean_db``). Volumes ``[C, Y, Z, X]`` show the B-scan
    ``y_index`` (default the middle one). All paths are checked before writing; existing files need
    ``force``. ``check_only`` returns the paths without writing.
    """
    infos = [c for c in maps.meta["channels"] if c["metric"] != FIT_FLAG]
    paths = [png_name(out_path, c["name"]) for c in infos]
    for p in paths:
        check_out(p, force, ".png", what="PNG output")
    if check_only:
        return paths
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arr = maps.maps
    if arr.ndim == 4:
        y = arr.shape[1] // 2 if y_index is None else int(y_index)
        if not 0 <= y < arr.shape[1]:
            raise ValueError(f"--png-y {y_index} is outside 0..{arr.shape[1] - 1}")
        arr = arr[:, y]
    by_metric: dict[str, list[np.ndarray]] = {}
    for c in infos:
        by_metric.setdefault(c["metric"], []).append(arr[maps.index(c["name"])])
    ranges = dict(ranges or {})
    if db_range is None and "mean_db" in by_metric:
        db_range = percentile_range(by_metric["mean_db"], 5.0, 99.9)
    for info, path in zip(infos, paths):
        metric = info["metric"]
        vr = ranges.get(metric) or (
            db_range if metric == "mean_db" and db_range else percentile_range(by_metric[metric], 1.0, 99.0)
        )
        fig = map_figure(maps, info["name"], value_range=vr, db_range=db_range, hue_range=hue_range, y_index=y_index)
        try:
            atomic_write(path, functools.partial(fig.savefig, format="png", dpi=100))
        finally:
            plt.close(fig)
    return paths

"""How the slab loop of :func:`torchdoct.measured.maps.compute_maps` cuts its work, and how far a non-finite
sample reaches through it.

Every stage of the maps says what it needs of each spatial axis of a piece (the bulk-phase correction,
the resolution reduction, the aLIV smoothing); :func:`slab_cut` cuts the axis they need least. A
non-finite sample reaches the pixels within the window's truncation (``⌈5σ'⌉`` pixels along each
filtered axis), where the maps re-weight the finite samples (:func:`torchdoct.measured.maps._normalized`):
:func:`nonfinite_reach_px`, :func:`nonfinite_reach`, :func:`nonfinite_mask`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from .io import SequenceData
from .resolution import ResolutionTarget, axial_filter_sigma_um, lateral_filter_sigma_um, parse_resolution

__all__ = ["slab_cut", "nonfinite_reach", "nonfinite_reach_px", "nonfinite_mask"]


def nonfinite_reach(bad: np.ndarray, spatial_axes: str, widths: Mapping[str, int], wrap: bool) -> np.ndarray:
    """``bad`` (pixels with a non-finite sample, ``[(Y), Z, X]``) spread by ``±widths[c]`` pixels along each
    axis letter ``c`` (the reach of a filter truncated at 5σ'); periodic when the reduction wraps."""
    from scipy.ndimage import maximum_filter1d

    out = bad.astype(np.uint8)
    for c, w in widths.items():
        if w > 0 and c in spatial_axes:
            out = maximum_filter1d(out, size=2 * w + 1, axis=spatial_axes.index(c), mode="wrap" if wrap else "constant")
    return out.astype(bool)


def nonfinite_reach_px(seq: SequenceData, target: str | ResolutionTarget) -> dict[str, int]:
    """How far (pixels, per axis letter) a sample reaches through the reduction to ``target`` of ``seq``:
    ``⌈5σ'/pitch⌉`` along each filtered axis (the window's truncation), nothing at the original."""
    t = parse_resolution(target) if isinstance(target, str) else target
    if t.lateral_resolution_um is None and t.axial_resolution_um is None:
        return {}
    system = seq.system
    lat0, ax0 = float(system["lateral_resolution_um"]), float(system["axial_resolution_um"])
    lat, ax = t.resolved(system)
    reach = {}
    if ax != ax0:
        reach["Z"] = int(math.ceil(5.0 * axial_filter_sigma_um(ax0, ax) / seq.pitch_um["z"]))
    if lat != lat0:
        sl = lateral_filter_sigma_um(lat0, lat)
        for c in "YX":
            if c in seq.axes:
                reach[c] = int(math.ceil(5.0 * sl / seq.pitch_um[c.lower()]))
    return reach


def nonfinite_mask(
    seq: SequenceData, target: str | ResolutionTarget = "original", *, edge_mode: str = "reflect"
) -> np.ndarray | None:
    """The pixels (``[(Y), Z, X]``) that a non-finite sample of ``seq`` reaches at ``target``
    (:func:`~torchdoct.measured.maps.compute_maps` re-weights them after a reduction and makes them NaN at the
    original; its module docstring), or ``None`` when every sample is finite."""
    bad = None
    for frame in seq.data:
        fin = np.isfinite(frame)
        if not fin.all():
            bad = ~fin if bad is None else bad | ~fin
    if bad is None:
        return None
    return nonfinite_reach(bad, seq.axes[1:], nonfinite_reach_px(seq, target), edge_mode == "wrap")


def _add_halos(a: int | None, b: int | None) -> int | None:
    return None if a is None or b is None else a + b


def slab_cut(
    axes: str, field_needs: Iterable[Mapping[str, int | None]], map_needs: Iterable[Mapping[str, int | None]] = ()
) -> tuple[str, int | None, int]:
    """Where the slab loop of :func:`~torchdoct.measured.maps.compute_maps` cuts one resolution's work: ``(axis, halo, margin)``.

    Every stage says what it needs of each spatial axis of a piece (``None``: the axis whole; an integer:
    a halo of that many pixels each side; absent: nothing): the field stages, run in order before the
    per-pixel metrics and features (the bulk-phase correction, :data:`~torchdoct.measured.bulkphase.
    CORRECTION_AXIS_NEEDS`; the resolution reduction, :func:`~torchdoct.measured.resolution.
    reduction_axis_needs`), then the stages on the maps (the aLIV smoothing, :data:`~torchdoct.measured.
    mapmetrics.SMOOTHING_AXIS_NEEDS`). Halos of stages in sequence add up. The cut axis is the one of Z, Y
    (when the sequence has it) that no stage needs whole, with the smallest total ``halo`` (Z on a tie);
    ``margin`` is the part of it the map stages need (the metrics are computed that many pixels beyond
    each slab's own rows). When every candidate is needed whole, ``("Z", None, 0)``: one slab.
    """
    total: dict[str, int | None] = {}
    on_maps: dict[str, int | None] = {}
    for needs, into in ((field_needs, [total]), (map_needs, [total, on_maps])):
        for n in needs:
            for a, h in n.items():
                for d in into:
                    d[a] = _add_halos(d.get(a, 0), h)
    cuts = [a for a in "ZY" if a in axes and total.get(a, 0) is not None]
    if not cuts:
        return "Z", None, 0
    a = min(cuts, key=lambda c: (total.get(c, 0), "ZY".index(c)))
    return a, total.get(a, 0), on_maps.get(a, 0) or 0

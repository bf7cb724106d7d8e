"""The speckle-motion channels of :func:`torchdoct.measured.maps.compute_maps` (``torchdoct maps --speckle``):
which features a sequence gets (checked before any work), which resolution gives them, and one slab's
channels from its field read with the window's halo (:mod:`torchdoct.sim.speckle`;
docs/concepts/speckle-motion.md). ``req`` is the :class:`torchdoct.measured.maps.MapsRequest` of the maps
(not imported here: maps imports this module)."""

from __future__ import annotations

from collections.abc import Sequence as _Seq
from typing import Any

import numpy as np
import torch

from ..sim.speckle import DEFAULT_MAX_OFFSET as SPECKLE_MAX_OFFSET
from ..sim.speckle import DEFAULT_WINDOW as SPECKLE_WINDOW
from ..sim.speckle import (
    halo_pixels,
    is_dynamic_feature,
    map_speckle_features,
    speckle_feature_unit,
    speckle_motion,
)
from .sequence import SequenceData

__all__ = [
    "SPECKLE_MAX_OFFSET",
    "SPECKLE_WINDOW",
    "speckle_target",
    "speckle_channels",
    "speckle_channel_records",
    "speckle_meta",
    "speckle_slab",
]


def speckle_target(req: Any) -> Any:
    """The resolution whose field gives the speckle-motion channels: the first target that keeps the
    original resolution."""
    return next(t for t in req.targets if t not in req.changes)


def speckle_channels(
    seq: SequenceData, names: _Seq[str] | None = None, *, window: int = SPECKLE_WINDOW
) -> tuple[str, ...]:
    """The speckle-motion features that maps of ``seq`` get (default
    :func:`torchdoct.sim.speckle.map_speckle_features` of its B-scans or volume), checked before any
    work: the spatial axes (Z, X and Y), the pixel pitch of each, a uniform frame interval, the lags the
    protocol holds, the window (odd pixels)."""
    src = seq.source or "sequence"
    sp = seq.axes[1:]
    if sp not in ("ZX", "YZX"):
        raise ValueError(f"{src}: speckle-motion channels need B-scans (TZX) or a volume (TYZX); got axes {seq.axes}")
    ndim = len(sp)
    pitch = seq.meta.get("pitch_um") or {}
    missing = [c.lower() for c in sp if not pitch.get(c.lower())]
    if missing:
        raise ValueError(
            f"{src}: speckle-motion channels need the pixel pitch of {', '.join(missing)} (µm); give "
            "--pitch-um z=..,x=..[,y=..]"
        )
    times = [float(v) for v in seq.frame_times_s]
    d = np.diff(times)
    if d.size == 0 or d.min() <= 0 or d.max() - d.min() > 1e-6 * d.max():
        raise ValueError(
            f"{src}: speckle-motion channels need a uniform frame interval; got intervals "
            f"{d.min() if d.size else None}-{d.max() if d.size else None} s"
        )
    names = tuple(names) if names is not None else map_speckle_features(ndim, n_frames=len(times))
    dyn = [n for n in names if is_dynamic_feature(n)]
    if dyn and not np.iscomplexobj(seq.data):
        raise ValueError(
            f"{src}: the speckle channels of the dynamic field ({', '.join(dyn[:3])}{' …' if len(dyn) > 3 else ''}; "
            "--speckle-dynamic) need complex data: an intensity sequence has no field whose temporal mean the "
            "static tissue is; leave them out"
        )
    probe = torch.ones(
        len(times),
        *([2 * halo_pixels(window, SPECKLE_MAX_OFFSET) + 1] * ndim),
        dtype=torch.complex64 if dyn else torch.float32,
    )
    try:  # the names, lags and window, on one small block
        speckle_motion(
            probe,
            {c.lower(): 1.0 for c in sp},
            float(d[0]),
            names,
            window=window,
            max_offset=SPECKLE_MAX_OFFSET,
            ndim=ndim,
        )
    except ValueError as err:
        raise ValueError(f"{src}: speckle-motion channels (--speckle, --speckle-window): {err}") from None
    return names


def speckle_slab(
    field: torch.Tensor,
    seq: SequenceData,
    req: Any,
    cdim: int,
    a0: int,
    c0: int,
    c1: int,
    *,
    base: int,
    keep_y: np.ndarray | None,
    mask: np.ndarray | None,
) -> tuple[list[Any], np.ndarray]:
    """The speckle-motion channels of the rows ``c0:c1`` (along data axis ``cdim``) from ``field``
    (``[T, (Y), Z, X]`` over the rows ``a0:``, the slab with its halo), as ``(index into the maps array,
    values [F, ...])``: only the kept B-scans of a block raster (their windows read the dropped ones too),
    NaN where ``mask`` (the pixels non-finite samples reach) is set."""
    real = torch.float64 if field.dtype in (torch.complex128, torch.float64) else torch.float32
    x = field if field.is_complex() else field.to(real)
    times = seq.frame_times_s
    f = speckle_motion(
        x,
        seq.pitch_um,
        float(times[1] - times[0]),
        req.speckle,
        window=req.speckle_window,
        max_offset=SPECKLE_MAX_OFFSET,
        ndim=field.dim() - 1,
    )[1]  # [F, *spatial]
    f = f.narrow(cdim, c0 - a0, c1 - c0).cpu().numpy()
    idx: list[Any] = [slice(base, base + len(req.speckle))] + [slice(None)] * (field.dim() - 1)
    idx[cdim] = slice(c0, c1)
    if keep_y is not None:
        ys = np.flatnonzero(keep_y[c0:c1] if cdim == 1 else keep_y)
        f = f[:, ys]
        mask = None if mask is None else mask[ys]
        idx[1] = ys + (c0 if cdim == 1 else 0)
    if mask is not None:
        f = np.where(mask, np.nan, f)
    return idx, f


def speckle_channel_records(req: Any, wavelength_um: float | None) -> list[dict[str, Any]]:
    """One channel record per speckle feature (name, metric, unit, resolution, optics of the original)."""
    t = speckle_target(req)
    lat, ax = req.optics(t)
    return [
        {
            "name": f"{f}@{t.label}",
            "metric": f,
            "unit": speckle_feature_unit(f),
            "resolution": t.label,
            "wavelength_um": None if wavelength_um is None else float(wavelength_um),
            "lateral_resolution_um": lat,
            "axial_resolution_um": ax,
        }
        for f in req.speckle
    ]


def speckle_meta(req: Any) -> dict[str, Any]:
    """``meta["speckle"]`` of the maps: the features, the resolution, the window, the offset grid, the halo."""
    return {
        "features": list(req.speckle),
        "resolution": speckle_target(req).label,
        "window_px": req.speckle_window,
        "max_offset_px": SPECKLE_MAX_OFFSET,
        "halo_px": halo_pixels(req.speckle_window, SPECKLE_MAX_OFFSET),
        "definition": "torchdoct.sim.speckle (lags in frames; docs/concepts/speckle-motion.md)",
    }

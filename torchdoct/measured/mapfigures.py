"""Figures of DOCT maps: the pseudo-colour composition (colour = the metric on a perceptual,
colour-blind-safe colour map, brightness = the mean dB intensity), one quantitative figure per channel (:func:`map_figure`; the PNG set of ``torchdoct maps --png`` is
:func:`torchdoct.measured.maps.write_pngs`), with numpy and matplotlib; every public name is re-exported
by :mod:`torchdoct.measured.maps`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .mapmetrics import FIT_FLAG
from .mapsfile import Maps

__all__ = ["DEFAULT_HUE_RANGE", "FLAG_RGB", "pseudo_color", "map_figure", "png_name", "percentile_range"]

#: Default part of the colour map (:data:`torchdoct.figures.CONTINUOUS_CMAP`, viridis) the value range spans:
#: all of it, low values dark blue-purple (0), high values yellow (1).
DEFAULT_HUE_RANGE = (0.0, 1.0)
#: Colour of flagged pixels (aLIV/Swiftness fits on a τ bound) in the pseudo-colour images: Okabe–Ito
#: vermillion, which viridis does not hold.
FLAG_RGB = (213, 94, 0)


def _cmap_rgb(frac: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of the continuous colour map at ``frac`` ∈ [0, 1]."""
    import matplotlib

    from ..figures import CONTINUOUS_CMAP

    return np.asarray(matplotlib.colormaps[CONTINUOUS_CMAP](frac))[..., :3]


def pseudo_color(
    value: np.ndarray,
    intensity_db: np.ndarray | None,
    *,
    value_range: tuple[float, float],
    db_range: tuple[float, float] | None = None,
    hue_range: tuple[float, float] = DEFAULT_HUE_RANGE,
    flagged: np.ndarray | None = None,
) -> np.ndarray:
    """RGB uint8 ``[H, W, 3]``: colour = ``value`` over ``value_range``, brightness = dB intensity.

    The composition DOCT images use, on a perceptual colour map that colour-blind readers can use
    (:data:`torchdoct.figures.CONTINUOUS_CMAP`): colour at ``hue_range[0] + (hue_range[1] − hue_range[0])·
    clip((v − lo)/(hi − lo), 0, 1)`` along the map (by default all of it, dark for low, yellow for high),
    scaled by the brightness ``clip((dB − db_lo)/(db_hi − db_lo), 0, 1)`` (1 everywhere without an
    intensity image). NaN values are shown grey at their brightness; ``flagged`` pixels (bool, e.g. an
    aLIV fit on a τ bound) are shown in :data:`FLAG_RGB` (vermillion, outside the colour map) at full
    brightness.
    """
    v = np.asarray(value, dtype=np.float64)
    lo, hi = (float(x) for x in value_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"value range must be finite with hi > lo; got {value_range!r}")
    frac = np.clip((v - lo) / (hi - lo), 0.0, 1.0)
    hue = hue_range[0] + (hue_range[1] - hue_range[0]) * np.nan_to_num(frac)
    if intensity_db is None:
        bright = np.ones_like(v)
    else:
        if db_range is None:
            raise ValueError("db_range is needed with an intensity image")
        dlo, dhi = (float(x) for x in db_range)
        if not (math.isfinite(dlo) and math.isfinite(dhi) and dhi > dlo):
            raise ValueError(f"dB range must be finite with hi > lo; got {db_range!r}")
        bright = np.nan_to_num(np.clip((np.asarray(intensity_db, dtype=np.float64) - dlo) / (dhi - dlo), 0, 1))
    colour = np.where(np.isfinite(v)[..., None], _cmap_rgb(np.clip(hue, 0.0, 1.0)), 0.6)
    rgb = np.round(colour * bright[..., None] * 255.0).astype(np.uint8)
    if flagged is not None:
        rgb[np.asarray(flagged, dtype=bool)] = FLAG_RGB
    return rgb


def png_name(out_path: str | Path, channel: str) -> Path:
    """``OUT_STEM_metric_resolution.png`` beside ``out_path`` (``=`` and ``,`` removed from the label)."""
    out = Path(out_path)
    metric, _, res = channel.partition("@")
    label = res.replace("=", "").replace(",", "-").replace(".", "p")
    return out.with_name(f"{out.stem}_{metric}_{label}.png")


def percentile_range(values: list[np.ndarray], lo_pct: float, hi_pct: float) -> tuple[float, float]:
    """``(lo, hi)``: the ``lo_pct``-``hi_pct`` percentiles of the finite values pooled over ``values``
    (``(0, 1)`` without any, ``hi = lo + 1`` when they coincide)."""
    v = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in values])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (0.0, 1.0)
    lo, hi = np.percentile(v, [lo_pct, hi_pct])
    if not hi > lo:
        hi = lo + 1.0
    return float(lo), float(hi)


_TITLES = {
    "liv": "LIV",
    "ocds": "OCDS",
    "mean_db": "mean intensity",
    "aliv": "aLIV",
    "swiftness": "Swiftness",
    FIT_FLAG: "aLIV fit on a τ bound",
    "valid_weight": "share of the window on finite samples",
}


def _optics_text(info: Mapping[str, Any]) -> str:
    lat, ax, wl = (info.get(k) for k in ("lateral_resolution_um", "axial_resolution_um", "wavelength_um"))
    if lat is None or ax is None:
        return "original resolution (optics not given)"
    return f"lateral {float(lat):g} µm, axial {float(ax):g} µm" + (f", {float(wl) * 1000:g} nm" if wl else "")


def map_figure(
    maps: Maps,
    channel: str,
    *,
    value_range: tuple[float, float] | None = None,
    db_range: tuple[float, float] | None = None,
    hue_range: tuple[float, float] = DEFAULT_HUE_RANGE,
    y_index: int | None = None,
) -> Any:
    """A quantitative figure of one channel: the image on µm axes (:mod:`torchdoct.figures`), a colour
    bar with the unit and the value range, the channel name and its resolution in the title.

    DOCT channels are drawn by :func:`pseudo_color` (brightness from the ``mean_db`` channel of the
    same resolution over ``db_range``; aLIV/Swiftness pixels whose fit ended on a τ bound, from the
    ``aliv_fit`` channel, in :data:`FLAG_RGB`; undefined pixels grey), ``mean_db`` in grey scale.
    ``value_range`` defaults to the channel's 1st-99th percentile, ``db_range`` to the 5th-99.9th
    percentile of its ``mean_db``. Volumes show the B-scan ``y_index`` (default the middle one).
    Returns the matplotlib ``Figure`` (the caller saves and closes it).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, Normalize
    from matplotlib.patches import Patch

    from ..figures import show_bscan, unit_text

    info = maps.channel_info(channel)
    metric, res = info["metric"], info["resolution"]

    def plane(name: str) -> np.ndarray:
        a = maps[name]
        return a[y] if a.ndim == 3 else a

    y = None
    if maps.maps.ndim == 4:
        n_y = maps.maps.shape[1]
        y = n_y // 2 if y_index is None else int(y_index)
        if not 0 <= y < n_y:
            raise ValueError(f"--png-y {y_index} is outside 0..{n_y - 1}")
    v = plane(channel)
    vr = value_range or percentile_range([v], 1.0, 99.0)
    unit = unit_text(info.get("unit"))
    name = _TITLES.get(metric, metric)
    h, w = v.shape
    aspect = (w * float((maps.meta.get("pitch_um") or {}).get("x", 1.0) or 1.0)) / max(
        h * float((maps.meta.get("pitch_um") or {}).get("z", 1.0) or 1.0), 1e-9
    )
    fig_w = min(max(4.5 * aspect, 3.5), 11.0) + 2.6
    fig, ax = plt.subplots(figsize=(fig_w, 5.0))
    handles = []
    extra = ""
    n_nan = int(np.sum(~np.isfinite(v)))
    if metric == "mean_db":
        cmap = plt.get_cmap("gray").with_extremes(bad="#6f9fcf")
        show_bscan(ax, np.ma.masked_invalid(v), pitch_um=maps.meta.get("pitch_um"), cmap=cmap, vmin=vr[0], vmax=vr[1])
        sm = ScalarMappable(norm=Normalize(*vr), cmap=cmap)
        if n_nan:
            handles.append(Patch(color="#6f9fcf", label=f"no intensity ({n_nan} px)"))
    else:
        db_name = next(
            (c["name"] for c in maps.meta["channels"] if c["metric"] == "mean_db" and c["resolution"] == res), None
        )
        db = plane(db_name) if db_name else None
        dr = db_range or (percentile_range([db], 5.0, 99.9) if db is not None else None)
        flag_name = f"{FIT_FLAG}@{res}"
        flagged = None
        if metric in ("aliv", "swiftness") and flag_name in maps.channels:
            with np.errstate(invalid="ignore"):
                flagged = plane(flag_name) > 0
        rgb = pseudo_color(
            v, db, value_range=vr, db_range=dr if db is not None else None, hue_range=hue_range, flagged=flagged
        )
        show_bscan(ax, rgb, pitch_um=maps.meta.get("pitch_um"))
        cmap = ListedColormap(_cmap_rgb(np.linspace(hue_range[0], hue_range[1], 256)))
        sm = ScalarMappable(norm=Normalize(*vr), cmap=cmap)
        if n_nan:
            handles.append(
                Patch(color="0.6", label=f"undefined, no dB value: grey, black without intensity ({n_nan} px)")
            )
        if flagged is not None and flagged.any():
            handles.append(Patch(color=np.array(FLAG_RGB) / 255.0, label=f"fit on a τ bound ({int(flagged.sum())} px)"))
        if db is not None:
            extra = f"\nbrightness: mean intensity {dr[0]:.3g} … {dr[1]:.3g} dB"
    cb = fig.colorbar(sm, ax=ax, shrink=0.85)
    cb.set_label(f"{name} ({unit}): {vr[0]:.4g} … {vr[1]:.4g}")
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.8)
    where = "" if y is None else f", B-scan y = {y}"
    ax.set_title(f"{name} [{channel}]\n{_optics_text(info)}{where}{extra}", fontsize=9)
    fig.tight_layout()
    return fig

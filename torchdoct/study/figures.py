"""The study's figures, drawn from the tables of :mod:`torchdoct.study.stats`.

:func:`plot_comparison` is the paper's Fig. 6/7/8 for one comparison (rows diffusion, random
ballistic, flow; columns LIV and OCDS; mean ± SD of both systems; an inset at small motion);
:func:`plot_directions` compares the two ballistic direction laws. Figures are drawn on the Agg canvas
(no pyplot) and saved as PNG and SVG without dates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..files import atomic_write
from .spec import Comparison, Part, Study, _xsym, _xunit

__all__ = ["plot_comparison", "plot_directions"]

_METRIC_LABEL = {"liv": "LIV (dB²)", "ocds": "OCDS (s⁻¹)"}


def _system_label(study: Study, name: str) -> str:
    s = study.system(name)
    return (
        f"{name}: {1000 * s['wavelength_um']:.0f} nm, {s['lateral_resolution_um']:g} µm lat., "
        f"{s['axial_resolution_um']:g} µm ax."
    )


def _new_figure(width: float, height: float):
    """A figure on the Agg canvas (no pyplot, no global backend switch: safe inside notebooks)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _inset_bounds(ax, xs: Sequence[np.ndarray], ys: Sequence[np.ndarray]) -> list[float]:
    """Lower-right or upper-right inset box, whichever the plotted mean curves cross least."""
    candidates = [[0.50, 0.08, 0.47, 0.42], [0.50, 0.52, 0.47, 0.42]]
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    pts = []
    for x, y in zip(xs, ys):
        xx = np.linspace(float(np.min(x)), float(np.max(x)), 400)
        pts.append(((xx - x0) / (x1 - x0), (np.interp(xx, x, y) - y0) / (y1 - y0)))
    best, count = candidates[0], math.inf
    for b in candidates:
        n = sum(
            int(np.sum((u >= b[0] - 0.03) & (u <= b[0] + b[2] + 0.03) & (w >= b[1] - 0.05) & (w <= b[1] + b[3] + 0.05)))
            for u, w in pts
        )
        if n < count:
            best, count = b, n
    return best


def _draw_curves(ax, curves: list[tuple[np.ndarray, np.ndarray, np.ndarray, str, str]], *, small: bool = False) -> None:
    for x, m, sd, color, label in curves:
        ax.fill_between(x, m - sd, m + sd, color=color, alpha=0.13, linewidth=0)
        ax.plot(x, m, "-o", color=color, label=label, markersize=2.5 if small else 3.5, linewidth=1.0)


def _panel(ax, part: Part, curves, metric: str, letter: str, title: str) -> None:
    _draw_curves(ax, curves)
    xmax = max(float(np.max(c[0])) for c in curves)
    ax.set_xlim(-0.02 * xmax, 1.02 * xmax)
    ax.set_xlabel(part.label)
    ax.set_ylabel(_METRIC_LABEL.get(metric, metric))
    ax.set_title(f"({letter}) {title}", loc="left", fontsize=10)
    ax.grid(alpha=0.3)
    sel = [(x <= part.inset_max * (1 + 1e-9)) for x, *_ in curves]
    if sum(int(s.sum()) for s in sel) >= 4 and part.inset_max < xmax:
        bounds = _inset_bounds(ax, [c[0] for c in curves], [c[1] for c in curves])
        ins = ax.inset_axes(bounds)
        _draw_curves(ins, [(x[s], m[s], sd[s], col, lab) for (x, m, sd, col, lab), s in zip(curves, sel)], small=True)
        ins.set_xlim(0, part.inset_max)
        lo = min(float(np.min((m - sd)[s])) for (x, m, sd, *_), s in zip(curves, sel))
        hi = max(float(np.max((m + sd)[s])) for (x, m, sd, *_), s in zip(curves, sel))
        pad = 0.05 * (hi - lo if hi > lo else 1.0)
        ins.set_ylim(lo - pad, hi + pad)
        ins.tick_params(labelsize=7)
        ins.grid(alpha=0.3)
        ins.set_title(f"{_xsym(part)} ≤ {part.inset_max:g} {_xunit(part)}", fontsize=7, pad=2)


def plot_comparison(study: Study, comparison: Comparison, differences):
    """Figure (matplotlib ``Figure``) equivalent to the paper's Fig. 6/7/8 for one comparison.

    Rows: the study's ``figure_parts`` (diffusion, random ballistic, flow); columns: LIV, OCDS; each panel
    the mean ± SD (band) of the reference (blue) and other (orange) system against the motion
    parameter, with an inset at small motion (``inset_max`` of the part).
    """
    metrics = [m for m in ("liv", "ocds") if m in set(differences["metric"])]
    nrow, ncol = len(study.figure_parts), len(metrics)
    fig = _new_figure(5.2 * ncol, 3.6 * nrow)
    axes = fig.subplots(nrow, ncol, squeeze=False)
    letters = "abcdefghijklmnopqrstuvwxyz"
    d = differences[differences["comparison"] == comparison.name]
    for r, pname in enumerate(study.figure_parts):
        part = study.part(pname)
        for c, metric in enumerate(metrics):
            t = d[(d["part"] == pname) & (d["metric"] == metric)].sort_values("value")
            x = t["value"].to_numpy(float)
            curves = [
                (
                    x,
                    t["mean_reference"].to_numpy(float),
                    t["sd_reference"].to_numpy(float),
                    "tab:blue",
                    _system_label(study, comparison.reference),
                ),
                (
                    x,
                    t["mean_other"].to_numpy(float),
                    t["sd_other"].to_numpy(float),
                    "tab:orange",
                    _system_label(study, comparison.other),
                ),
            ]
            title = f"{pname}: {metric.upper()}"
            _panel(axes[r][c], part, curves, metric, letters[r * ncol + c], title)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=2, fontsize=9, frameon=False)
    fig.suptitle(comparison.title + " — mean ± SD", fontsize=11)
    return fig


def plot_directions(study: Study, directions):
    """LIV and OCDS against speed for both ballistic direction laws (solid: first part, dashed: second)."""
    metrics = [m for m in ("liv", "ocds") if m in set(directions["metric"])]
    fig = _new_figure(5.2 * len(metrics), 4.2)
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    pa, pb = study.direction_parts
    la = study.part(pa).motion.get("directions", "isotropic")
    lb = study.part(pb).motion.get("directions", "isotropic")
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
    for ax, metric in zip(axes, metrics):
        for k, system in enumerate(dict.fromkeys(directions["system"])):
            t = directions[(directions["system"] == system) & (directions["metric"] == metric)].sort_values("value")
            col = colors[k % len(colors)]
            ax.plot(t["value"], t["mean_a"], "-o", color=col, markersize=3, linewidth=1.0, label=f"{system}, {la}")
            ax.plot(t["value"], t["mean_b"], "--s", color=col, markersize=3, linewidth=1.0, label=f"{system}, {lb}")
        ax.set_xlabel("speed v (µm/s), random ballistic")
        ax.set_ylabel(_METRIC_LABEL.get(metric, metric))
        ax.set_xscale("symlog", linthresh=0.01)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2, loc="upper left")
    fig.suptitle(f"Random ballistic motion: direction law {la} (solid) vs {lb} (dashed), mean over trials", fontsize=10)
    return fig


def _save_figure(fig, stem: Path, force: bool) -> list[Path]:

    out = []
    for ext, kw in ((".png", {"dpi": 150, "metadata": {"Software": None}}), (".svg", {"metadata": {"Date": None}})):
        p = stem.with_suffix(ext)
        atomic_write(p, lambda tmp, kw=kw, ext=ext: fig.savefig(tmp, format=ext[1:], **kw))
        out.append(p)
    return out

"""The reference paper's numerical study: its sweeps, Figs. 6-8, and a claims report with numbers.

A *study file* (``torchdoct/data/studies/*.toml``; ``paper`` is the full study, ``paper-reduced`` a
small one for tests and the notebook) holds:

* ``[study]``: ``trials``, ``seed``, ``dtype``, ``grouping`` (``"pairs"``: one scene per comparison,
  so the two systems of a comparison see the same scatterers; ``"all"``: every system in one scene),
  ``figure_parts`` (the three parts whose curves are the rows of each figure: diffusion, random
  ballistic, flow), optional ``direction_parts`` (two ballistic parts that differ only by the
  direction law) and ``[[study.comparison]]`` tables (``name``, ``figure``, ``title``, ``reference``,
  ``other``: two system names);
* ``[scene]``: the scene every part shares (scene-file schema of the README); each part appends its
  motion to the first population;
* ``[[part]]``: ``name``, ``label`` (x axis), ``parameter`` (the swept key of the motion table),
  ``inset_max`` (x range of the small-motion inset), ``motion`` (a motion table) and the values as in a
  sweep field (``values`` / ``linear`` / ``log``, see :mod:`torchdoct.sweep`).

:func:`run_study` turns every part (× comparison when grouped in pairs) into a :class:`~torchdoct.sweep.Sweep`,
runs them (cached, resumable, locally or on Dask), and writes into the output directory:

* ``results.csv``/``.parquet``: the tidy table of :mod:`torchdoct.sweep` with the columns ``part``,
  ``comparison``, ``motion``, ``parameter`` and ``value`` (the motion parameter);
* ``differences.csv``/``.parquet``: per part, comparison, value and metric, both systems' mean and SD
  and the paired difference ``other − reference`` over the same trials (same scatterers) with its
  standard error and ``z = diff/SE``;
* ``directions.csv``/``.parquet``: isotropic minus uniform-angle ballistic motion per system
  (trials paired by seed, see below);
* one figure per comparison (PNG and SVG), equivalent to the paper's Figs. 6, 7, 8: rows diffusion,
  random ballistic, flow; columns LIV and OCDS; mean ± SD of both systems; an inset at small motion;
  and ``fig-directions`` comparing the two ballistic direction laws;
* ``claims.md``: every numerical finding of the paper's Sections 3.3 and 4 with this run's numbers and
  a verdict; ``study.json``: the resolved study, every cell's seed and cache key, wall times.

Metrics are those of :mod:`torchdoct.metrics` (LIV: physics.md §1; OCDS: physics.md §2.4); ENS and
N_eff come from :mod:`torchdoct.conventions` (physics.md §5.5).

Statistics: a difference is *significant* when ``|z| ≥ 4`` (``Z_SIGNIFICANT``; the project's bound
for Monte Carlo comparisons, conservative for the ~30 values of a curve). Cells of one motion value
share their seed across parts and comparisons (the seed depends on the base seed and the cell key
``{path: value}`` only, :func:`torchdoct.sweep.cell_seed`), so the two direction laws are compared with
common random numbers; every SE is computed from per-trial differences and is valid either way.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ._files import atomic_write, file_or_shipped, shipped_files
from .config import SceneError, _check_keys, _fail, read_toml, scene_from_dict
from .sweep import (
    SweepResult,
    _normalize_arrays,
    field_values,
    make_sweep,
    prepare_out_dir,
    run_sweeps,
    write_table,
)

__all__ = [
    "Z_SIGNIFICANT",
    "Comparison",
    "Part",
    "Study",
    "StudyResult",
    "shipped_studies",
    "load_study",
    "study_from_dict",
    "study_sweeps",
    "study_outputs",
    "paired_differences",
    "direction_differences",
    "plot_comparison",
    "plot_directions",
    "claims_report",
    "run_study",
    "bench_study",
    "format_bench_study",
]

#: |z| at or above which a difference counts as significant in the claims report.
Z_SIGNIFICANT = 4.0
#: A single value's difference that brackets a crossing (see :func:`_crossing`).
Z_BRACKET = 2.0
_METRIC_LABEL = {"liv": "LIV (dB²)", "ocds": "OCDS (s⁻¹)"}
_METRIC_UNIT = {"liv": "dB²", "ocds": "s⁻¹"}


def _tables(where: str, value: Any, empty: str) -> list:
    """An array of tables (a single table becomes one); none at all fails with ``empty``."""
    value = [value] if isinstance(value, dict) else value
    if not isinstance(value, list) or not value:
        _fail(where, empty)
    return value


def _str(where: str, v: Any) -> str:
    if not isinstance(v, str) or not v:
        raise TypeError(f"{where} must be a non-empty string; got {v!r}")
    return v


# ----------------------------------------------------------------------------------------------
# the study file


@dataclass(frozen=True)
class Comparison:
    """Two systems compared pairwise: ``other − reference`` (same scatterers)."""

    name: str
    figure: str
    title: str
    reference: str
    other: str
    paper_figure: str = ""


@dataclass(frozen=True)
class Part:
    """One motion model swept over its parameter (``parameter`` = key of the motion table)."""

    name: str
    label: str
    parameter: str
    inset_max: float
    motion: dict[str, Any]
    values: tuple[float, ...]

    @property
    def kind(self) -> str:
        return self.motion["kind"]


@dataclass(frozen=True)
class Study:
    """A validated study file (module docstring)."""

    name: str
    description: str
    trials: int
    seed: int
    dtype: str
    grouping: str
    comparisons: tuple[Comparison, ...]
    parts: tuple[Part, ...]
    figure_parts: tuple[str, ...]
    direction_parts: tuple[str, ...]
    scene_data: dict[str, Any] = field(repr=False)

    def part(self, name: str) -> Part:
        return next(p for p in self.parts if p.name == name)

    def system(self, name: str) -> dict[str, Any]:
        return next(s for s in self.scene_data["system"] if s["name"] == name)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "description": self.description,
                "study": {"trials": self.trials, "seed": self.seed, "dtype": self.dtype, "grouping": self.grouping,
                          "figure_parts": list(self.figure_parts), "direction_parts": list(self.direction_parts),
                          "comparison": [c.__dict__ for c in self.comparisons]},
                "scene": self.scene_data,
                "part": [{"name": p.name, "label": p.label, "parameter": p.parameter, "inset_max": p.inset_max,
                          "motion": p.motion, "values": list(p.values)} for p in self.parts]}


def shipped_studies() -> dict[str, Path]:
    """Name -> path of every study file shipped with torchdoct."""
    return shipped_files("torchdoct", "data/studies")


def _resolve(study: str | os.PathLike) -> Path:
    shipped = shipped_studies()
    found = file_or_shipped(study, shipped)
    if found is not None:
        return found
    raise FileNotFoundError(f"study {str(study)!r} not found; give a study .toml file or the name of a shipped "
                            f"study: {', '.join(shipped)}")


def load_study(study: str | os.PathLike) -> Study:
    """Read and validate a study file, or a shipped study by name (``paper``, ``paper-reduced``)."""
    p = _resolve(study)
    data = read_toml(p)
    try:
        return study_from_dict(data, default_name=p.stem)
    except (SceneError, TypeError) as err:
        raise type(err)(f"{p.name}: {err}") from None


def study_from_dict(data: dict[str, Any], *, default_name: str = "study") -> Study:
    """A validated :class:`Study` from the study-file schema (module docstring)."""
    _check_keys("study file", data, {"name", "description", "study", "scene", "part"}, {"study", "scene", "part"})
    st = _check_keys("study", data["study"], {"trials", "seed", "dtype", "grouping", "figure_parts", "direction_parts",
                                        "comparison"}, {"comparison", "figure_parts"})
    trials = st.get("trials", 500)
    seed = st.get("seed", 0)
    for k, v in (("trials", trials), ("seed", seed)):
        if isinstance(v, bool) or not isinstance(v, int) or v < (1 if k == "trials" else 0):
            raise TypeError(f"study.{k} must be an integer >= {1 if k == 'trials' else 0}; got {v!r}")
    dtype = st.get("dtype", "float32")
    if dtype not in ("float32", "float64"):
        _fail("study.dtype", f"must be 'float32' or 'float64'; got {dtype!r}")
    grouping = st.get("grouping", "pairs")
    if grouping not in ("pairs", "all"):
        _fail("study.grouping", f"must be 'pairs' or 'all'; got {grouping!r}")

    scene = copy.deepcopy(data["scene"])
    if not isinstance(scene, dict):
        raise TypeError(f"scene must be a table; got {scene!r}")
    _normalize_arrays(scene)
    if not isinstance(scene.get("population"), list) or not scene["population"]:
        _fail("scene.population", "the study needs a [[scene.population]] for the parts' motion")
    try:
        scene_from_dict(scene)
    except (SceneError, TypeError) as err:
        raise type(err)(f"scene: {err}") from None
    system_names = [s["name"] for s in scene["system"]]

    comps = _tables("study.comparison", st["comparison"], "needs at least one [[study.comparison]]")
    comparisons = []
    for i, c in enumerate(comps):
        w = f"study.comparison[{i}]"
        _check_keys(w, c, {"name", "figure", "title", "paper_figure", "reference", "other"}, {"name", "reference", "other"})
        for k in ("reference", "other"):
            if _str(f"{w}.{k}", c[k]) not in system_names:
                _fail(f"{w}.{k}", f"{c[k]!r} is not a system of [scene]", f"use one of {system_names}")
        if c["reference"] == c["other"]:
            _fail(w, "reference and other are the same system", "compare two different systems")
        name = _str(f"{w}.name", c["name"])
        comparisons.append(Comparison(name=name, figure=_str(f"{w}.figure", c.get("figure", f"fig-{name}")),
                                      title=_str(f"{w}.title", c.get("title", name)),
                                      reference=c["reference"], other=c["other"],
                                      paper_figure=_str(f"{w}.paper_figure", c.get("paper_figure", c.get("figure", name)))))
    names = [c.name for c in comparisons]
    if len(set(names)) != len(names) or "all" in names:
        _fail("study.comparison", f"names must be unique and not 'all'; got {names}")

    parts_data = _tables("part", data["part"], "a study needs at least one [[part]]")
    parts = []
    for i, p in enumerate(parts_data):
        w = f"part[{i}]"
        _check_keys(w, p, {"name", "label", "parameter", "inset_max", "motion", "values", "linear", "log"},
              {"name", "parameter", "motion"})
        motion = p["motion"]
        if not isinstance(motion, dict) or "kind" not in motion:
            raise TypeError(f"{w}.motion must be a motion table with a kind; got {motion!r}")
        param = _str(f"{w}.parameter", p["parameter"])
        if param not in motion:
            _fail(f"{w}.parameter", f"{param!r} is not a key of {w}.motion", f"add {param} = 0.0 to the motion table")
        test = copy.deepcopy(scene)
        test["population"][0].setdefault("motion", []).append(motion)
        try:
            scene_from_dict(test)
        except (SceneError, TypeError) as err:
            raise type(err)(f"{w}.motion: {err}") from None
        values = field_values({k: p[k] for k in ("values", "linear", "log") if k in p}, w)
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
                _fail(w, f"motion values must be numbers >= 0; got {v!r}")
        inset = p.get("inset_max", max(values) / 10 if max(values) > 0 else 1.0)
        if isinstance(inset, bool) or not isinstance(inset, (int, float)) or not inset > 0:
            raise TypeError(f"{w}.inset_max must be a number > 0; got {inset!r}")
        parts.append(Part(name=_str(f"{w}.name", p["name"]), label=_str(f"{w}.label", p.get("label", param)),
                          parameter=param, inset_max=float(inset), motion=dict(motion),
                          values=tuple(float(v) for v in values)))
    pnames = [p.name for p in parts]
    if len(set(pnames)) != len(pnames):
        _fail("part", f"part names must be unique; got {pnames}")
    fig_parts = st["figure_parts"]
    if not isinstance(fig_parts, list) or not fig_parts:
        raise TypeError(f"study.figure_parts must be a list of part names; got {fig_parts!r}")
    for n in fig_parts:
        if n not in pnames:
            _fail("study.figure_parts", f"{n!r} is not a part", f"use names of [[part]]: {pnames}")
    dir_parts = st.get("direction_parts", [])
    if dir_parts:
        if not isinstance(dir_parts, list) or len(dir_parts) != 2 or any(n not in pnames for n in dir_parts):
            _fail("study.direction_parts", f"must name two parts; got {dir_parts!r}", f"use names of [[part]]: {pnames}")
        a, b = (next(p for p in parts if p.name == n) for n in dir_parts)
        strip = lambda m: {k: v for k, v in m.items() if k != "directions"}  # noqa: E731
        if a.kind != "ballistic" or b.kind != "ballistic" or strip(a.motion) != strip(b.motion) \
                or a.values != b.values:
            _fail("study.direction_parts", f"{dir_parts} must be ballistic parts with the same values that differ "
                  "only in directions")
    return Study(name=_str("name", data.get("name", default_name)), description=data.get("description", ""),
                 trials=trials, seed=seed, dtype=dtype, grouping=grouping, comparisons=tuple(comparisons),
                 parts=tuple(parts), figure_parts=tuple(fig_parts), direction_parts=tuple(dir_parts),
                 scene_data=scene)


# ----------------------------------------------------------------------------------------------
# sweeps of a study


def _sweep_name(part: str, comparison: str) -> str:
    return part if comparison == "all" else f"{part}/{comparison}"


def _groups(study: Study) -> list[tuple[str, list[str]]]:
    """(comparison or "all", system names) of each scene of a part."""
    if study.grouping == "all":
        return [("all", [s["name"] for s in study.scene_data["system"]])]
    return [(c.name, [c.reference, c.other]) for c in study.comparisons]


def study_sweeps(study: Study):
    """The sweeps of a study: one per part, or per part × comparison (``grouping = "pairs"``)."""
    sweeps = []
    for part in study.parts:
        for comp, systems in _groups(study):
            data = copy.deepcopy(study.scene_data)
            data["system"] = [copy.deepcopy(study.system(n)) for n in systems]
            data["name"] = f"{study.name}-{part.name}"
            motions = data["population"][0].setdefault("motion", [])
            motions.append(copy.deepcopy(part.motion))
            data.setdefault("simulation", {}).update({"trials": study.trials, "seed": study.seed, "dtype": study.dtype})
            path = f"population.0.motion.{len(motions) - 1}.{part.parameter}"
            sweeps.append(make_sweep(data, [{"path": path, "name": "value", "values": list(part.values)}],
                                     name=_sweep_name(part.name, comp),
                                     tags={"part": part.name, "comparison": comp, "motion": part.kind,
                                           "parameter": part.parameter}))
    return sweeps


# ----------------------------------------------------------------------------------------------
# paired statistics


def _paired(a: np.ndarray, b: np.ndarray) -> tuple[float, float, int]:
    """Mean and SE of ``b − a`` over trials where both are finite."""
    ok = np.isfinite(a) & np.isfinite(b)
    d = (b[ok].astype(np.float64) - a[ok].astype(np.float64))
    n = int(d.size)
    mean = float(d.mean()) if n else math.nan
    se = float(d.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return mean, se, n


def _ms(a: np.ndarray) -> tuple[float, float]:
    v = a[np.isfinite(a)].astype(np.float64)
    return (float(v.mean()) if v.size else math.nan, float(v.std(ddof=1)) if v.size > 1 else math.nan)


def _z(diff: float, se: float) -> float:
    if se > 0:
        return diff / se
    return 0.0 if diff == 0 else math.copysign(math.inf, diff)


def paired_differences(study: Study, result: SweepResult):
    """Per part × comparison × value × metric: both systems' mean/SD and ``other − reference`` ± SE."""
    import pandas as pd

    rows = []
    for part in study.parts:
        for c in study.comparisons:
            comp = c.name if study.grouping == "pairs" else "all"
            for cr in result.of_sweep(_sweep_name(part.name, comp)):
                i_ref = cr.system_names.index(c.reference)
                i_oth = cr.system_names.index(c.other)
                for metric, arr in cr.metrics.items():
                    mr, sr = _ms(arr[:, i_ref])
                    mo, so = _ms(arr[:, i_oth])
                    d, se, n = _paired(arr[:, i_ref], arr[:, i_oth])
                    rows.append({"part": part.name, "comparison": c.name, "motion": part.kind,
                                 "parameter": part.parameter, "value": cr.cell.values["value"], "metric": metric,
                                 "reference": c.reference, "other": c.other, "mean_reference": mr, "sd_reference": sr,
                                 "mean_other": mo, "sd_other": so, "diff": d, "se": se, "z": _z(d, se), "n": n,
                                 "trials": cr.trials, "seed": cr.seed})
    return pd.DataFrame(rows)


def _system_sweeps(study: Study) -> dict[str, str]:
    """System name -> the comparison whose scenes hold it (first one), or "all"."""
    out: dict[str, str] = {}
    for comp, systems in _groups(study):
        for s in systems:
            out.setdefault(s, comp)
    return out


def direction_differences(study: Study, result: SweepResult):
    """Per system × value × metric: ``direction_parts[1] − direction_parts[0]`` (trials paired by seed)."""
    import pandas as pd

    if not study.direction_parts:
        return pd.DataFrame()
    pa, pb = study.direction_parts
    rows = []
    for system, comp in _system_sweeps(study).items():
        ca = result.of_sweep(_sweep_name(pa, comp))
        cb = {c.cell.values["value"]: c for c in result.of_sweep(_sweep_name(pb, comp))}
        for a in ca:
            v = a.cell.values["value"]
            b = cb[v]
            ia, ib = a.system_names.index(system), b.system_names.index(system)
            for metric in a.metrics:
                ma, sa = _ms(a.metrics[metric][:, ia])
                mb, sb = _ms(b.metrics[metric][:, ib])
                d, se, n = _paired(a.metrics[metric][:, ia], b.metrics[metric][:, ib])
                rows.append({"system": system, "value": v, "metric": metric, "part_a": pa, "part_b": pb,
                             "directions_a": study.part(pa).motion.get("directions", "isotropic"),
                             "directions_b": study.part(pb).motion.get("directions", "isotropic"),
                             "mean_a": ma, "sd_a": sa, "mean_b": mb, "sd_b": sb, "diff": d, "se": se,
                             "z": _z(d, se), "n": n})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------------
# figures


def _system_label(study: Study, name: str) -> str:
    s = study.system(name)
    return (f"{name}: {1000 * s['wavelength_um']:.0f} nm, {s['lateral_resolution_um']:g} µm lat., "
            f"{s['axial_resolution_um']:g} µm ax.")


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
        n = sum(int(np.sum((u >= b[0] - 0.03) & (u <= b[0] + b[2] + 0.03) & (w >= b[1] - 0.05)
                           & (w <= b[1] + b[3] + 0.05))) for u, w in pts)
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
            curves = [(x, t["mean_reference"].to_numpy(float), t["sd_reference"].to_numpy(float), "tab:blue",
                       _system_label(study, comparison.reference)),
                      (x, t["mean_other"].to_numpy(float), t["sd_other"].to_numpy(float), "tab:orange",
                       _system_label(study, comparison.other))]
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
    fig.suptitle(f"Random ballistic motion: direction law {la} (solid) vs {lb} (dashed), mean over trials",
                 fontsize=10)
    return fig


def _save_figure(fig, stem: Path, force: bool) -> list[Path]:

    out = []
    for ext, kw in ((".png", {"dpi": 150, "metadata": {"Software": None}}), (".svg", {"metadata": {"Date": None}})):
        p = stem.with_suffix(ext)
        atomic_write(p, lambda tmp, kw=kw, ext=ext: fig.savefig(tmp, format=ext[1:], **kw))
        out.append(p)
    return out


# ----------------------------------------------------------------------------------------------
# claims


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:+.{digits}g}" if abs(v) >= 1e-3 or v == 0 else f"{v:+.2e}"


def _dz(d: float, se: float, unit: str) -> str:
    """``+1.23 ± 0.45 dB² (z = +2.7)``."""
    z = _z(d, se)
    zs = "±∞" if math.isinf(z) else f"{z:+.1f}"
    return f"{_fmt(d)} ± {se:.2g} {unit} (z = {zs})"


@dataclass
class _Curve:
    """One comparison along the motion parameter: means, paired difference (other − reference), SE, z."""

    x: np.ndarray
    ref: np.ndarray
    other: np.ndarray
    diff: np.ndarray
    se: np.ndarray
    z: np.ndarray

    def where(self, mask: np.ndarray) -> "_Curve":
        return _Curve(*(a[mask] for a in (self.x, self.ref, self.other, self.diff, self.se, self.z)))

    def flip(self) -> "_Curve":
        """reference − other instead of other − reference."""
        return _Curve(self.x, self.other, self.ref, -self.diff, self.se, -self.z)

    @property
    def scale(self) -> float:
        """Largest |mean| of either curve (for relative sizes)."""
        return float(np.nanmax(np.abs(np.concatenate([self.ref, self.other])))) if self.x.size else 0.0


def _curve(diffs, part: str, comparison: str, metric: str) -> _Curve | None:
    t = diffs[(diffs["part"] == part) & (diffs["comparison"] == comparison) & (diffs["metric"] == metric)]
    if t.empty:
        return None
    t = t.sort_values("value")
    return _Curve(*(t[k].to_numpy(float) for k in ("value", "mean_reference", "mean_other", "diff", "se", "z")))


def _zfin(c: _Curve) -> np.ndarray:
    return np.where(np.isfinite(c.z), c.z, np.sign(c.diff) * 1e9)


def _maxabs(c: _Curve) -> int:
    """Index of the largest |z| (an exact nonzero difference with SE 0 counts as infinite)."""
    return int(np.argmax(np.abs(_zfin(c))))


def _pooled(c: _Curve) -> tuple[float, float, float, int]:
    """Mean of the differences over the values of ``c`` and its SE (cells are independent): (mean, SE, z, k)."""
    k = int(c.x.size)
    if k == 0:
        return math.nan, math.nan, math.nan, 0
    mean = float(np.mean(c.diff))
    se = float(math.sqrt(np.sum(c.se ** 2)) / k)
    return mean, se, _z(mean, se), k


def _crossing(c: _Curve) -> dict[str, Any] | None:
    """Where ``diff`` turns from positive (left) to negative (right).

    The split between two sampled values that maximizes Σz_left − Σz_right; it counts as found when
    the pooled difference is significantly positive on the left and significantly negative on the right.
    ``bracket``: where the crossing can lie, from the last value at or below the split whose own
    difference is positive at z ≥ 2 to the first value at or above it negative at z ≤ −2 (the range of
    the curve's ends when there is none): in between, single values cannot tell the sign.
    """
    c = c.where(c.x > 0)
    if c.x.size < 2:
        return None
    z = np.clip(_zfin(c), -50, 50)
    score = [z[: k + 1].sum() - z[k + 1:].sum() for k in range(c.x.size - 1)]
    k = int(np.argmax(score))
    left, right = c.where(np.arange(c.x.size) <= k), c.where(np.arange(c.x.size) > k)
    pl, pr = _pooled(left), _pooled(right)
    pos = [i for i in range(k + 1) if z[i] >= Z_BRACKET]
    neg = [i for i in range(k + 1, c.x.size) if z[i] <= -Z_BRACKET]
    bracket = (float(c.x[pos[-1]] if pos else c.x[0]), float(c.x[neg[0]] if neg else c.x[-1]))
    return {"x_lo": float(c.x[k]), "x_hi": float(c.x[k + 1]), "x": float(math.sqrt(c.x[k] * c.x[k + 1])),
            "bracket": bracket, "left": pl, "right": pr,
            "found": pl[2] >= Z_SIGNIFICANT and pr[2] <= -Z_SIGNIFICANT}


def _x_reach(x: np.ndarray, y: np.ndarray, frac: float = 0.9) -> float:
    """Smallest x where the mean curve first reaches ``frac`` of its value at the largest x (interpolated)."""
    target = frac * y[-1]
    for i in range(1, x.size):
        if y[i] >= target:
            y0, y1 = y[i - 1], y[i]
            return float(x[i - 1] + (x[i] - x[i - 1]) * ((target - y0) / (y1 - y0) if y1 != y0 else 1.0))
    return math.nan


def _count(c: _Curve, sign: int) -> tuple[int, int]:
    """(values significant in the direction ``sign``, values significant in the opposite direction)."""
    z = _zfin(c) * sign
    return int(np.sum(z >= Z_SIGNIFICANT)), int(np.sum(z <= -Z_SIGNIFICANT))


def _extremes(c: _Curve) -> tuple[int, int, int, float]:
    """(index of the largest |z|, values significant either way, index of the largest |difference|,
    that difference relative to the curve's maximum)."""
    k = int(np.nanargmax(np.abs(c.diff)))
    return _maxabs(c), sum(_count(c, +1)), k, (abs(c.diff[k]) / c.scale if c.scale > 0 else 0.0)


def _verdict_effect(n_exp: int, n_opp: int, trials: int) -> str:
    """A claimed difference of known sign."""
    if n_exp and not n_opp:
        return "supported"
    if n_exp and n_opp:
        return "mixed: significant in both directions"
    if n_opp:
        return "contradicted: significant in the opposite direction"
    return f"not resolved: no significant difference with {trials} trials"


def _region(c: _Curve, sign: int, trials: int, unit: str) -> tuple[str, str]:
    """(numbers, verdict) of a claimed difference of sign ``sign`` over the values of ``c``: the pooled
    difference decides; single values significantly the other way make it *mixed*."""
    mean, se, z, k = _pooled(c)
    n_exp, n_opp = _count(c, sign)
    text = (f"pooled over {k} values {_dz(mean, se, unit)}; single values significant as claimed at {n_exp}, "
            f"the other way at {n_opp}")
    zs = z * sign
    if zs >= Z_SIGNIFICANT:
        verdict = "mixed: significant the other way at some values" if n_opp else "supported"
    elif zs <= -Z_SIGNIFICANT:
        verdict = "contradicted: significant in the opposite direction"
    else:
        verdict = f"not resolved: no significant difference with {trials} trials"
    return text, verdict


def _verdict_null(n_sig: int, rel: float) -> str:
    """A claimed absence of difference: no single value may differ significantly."""
    if n_sig == 0:
        return "supported"
    if rel < 0.05:
        return f"partly: significant but small ({100 * rel:.1f} % of the curve)"
    return f"contradicted: significant at {n_sig} value(s), up to {100 * rel:.1f} % of the curve"


def _range_of(x: np.ndarray, unit: str) -> str:
    return f"{x.min():.3g}–{x.max():.3g} {unit}" if x.size else "none"


class _Claims:
    def __init__(self, trials: int):
        self.trials = trials
        self.rows: list[tuple[str, str, str, str, str]] = []

    def add(self, where: str, claim: str, result: str, verdict: str) -> None:
        self.rows.append((str(len(self.rows) + 1), where, claim, result, verdict))

    def table(self) -> str:
        out = ["| # | paper | claim | this run | verdict |", "|---|---|---|---|---|"]
        for r in self.rows:
            out.append("| " + " | ".join(x.replace("|", "\\|").replace("\n", " ") for x in r) + " |")
        return "\n".join(out)


def _xunit(part: Part) -> str:
    return "µm²/s" if "um2_per_s" in part.parameter else ("µm/s" if "um_per_s" in part.parameter else "")


def _xsym(part: Part) -> str:
    return "D" if part.kind == "diffusion" else "v"


def _figure_parts(study: Study) -> tuple[Part, Part, Part]:
    d, b, f = (study.part(n) for n in study.figure_parts[:3])
    return d, b, f


def _wavelength_claims(cl: _Claims, study: Study, diffs, comp: Comparison) -> None:
    dpart, bpart, fpart = _figure_parts(study)
    fig, ref, oth = comp.paper_figure, comp.reference, comp.other
    for part, letters in ((dpart, "ab"), (bpart, "cd")):
        xs, xu = _xsym(part), _xunit(part)
        for metric, letter in zip(("liv", "ocds"), letters):
            c = _curve(diffs, part.name, comp.name, metric)
            if c is None:
                continue
            c = c.flip()  # reference − other (840 − 1310)
            u = _METRIC_UNIT[metric]
            small = c.where((c.x > 0) & (c.x <= part.inset_max * (1 + 1e-9)))
            if small.x.size:
                i = _maxabs(small)
                hi, lo = _count(small, +1)
                res = (f"{ref} − {oth} for 0 < {xs} ≤ {part.inset_max:g} {xu}: largest "
                       f"{_dz(small.diff[i], small.se[i], u)} "
                       f"at {xs} = {small.x[i]:.3g} {xu}; significant at {hi + lo}/{small.x.size} values "
                       f"({hi} with {ref} higher, {lo} lower)")
                verdict = "supported" if hi + lo else f"not resolved: no significant difference with {cl.trials} trials"
            else:
                res, verdict = "no motion values in the inset range", "not tested"
            cl.add(f"§3.3.1, {fig}({letter})", f"{part.name}: {metric.upper()} depends on the wavelength at small "
                   f"{xs} (magnified insets)", res, verdict)
            large = c.where(c.x >= 0.5 * c.x.max())
            j = _maxabs(large)
            nsig = sum(_count(large, +1))
            rel = abs(large.diff[j]) / c.scale if c.scale > 0 else 0.0
            res = (f"{xs} ≥ {0.5 * c.x.max():.3g} {xu}: largest {ref} − {oth} {_dz(large.diff[j], large.se[j], u)} at "
                   f"{xs} = {large.x[j]:.3g} {xu} ({100 * rel:.1f} % of the curve's maximum); significant at "
                   f"{nsig}/{large.x.size} values")
            cl.add(f"§3.3.1, {fig}({letter})", f"{part.name}: the {metric.upper()} difference becomes negligible at "
                   f"large {xs}", res, _verdict_null(nsig, rel))
    xu = _xunit(fpart)
    for metric, letter in (("liv", "e"), ("ocds", "f")):
        c = _curve(diffs, fpart.name, comp.name, metric)
        if c is None:
            continue
        c = c.flip().where(c.x > 0)
        u = _METRIC_UNIT[metric]
        i, nsig, k, rel = _extremes(c)
        res = (f"over all {c.x.size} speeds v > 0 the largest {ref} − {oth} in units of its SE is "
               f"{_dz(c.diff[i], c.se[i], u)} at v = {c.x[i]:.3g} {xu}; |z| ≥ {Z_SIGNIFICANT:g} at {nsig} values; "
               f"largest |difference| {abs(c.diff[k]):.3g} {u} ({100 * rel:.1f} % of the curve's maximum)")
        cl.add(f"§3.3.1, {fig}({letter})", f"{fpart.name}: no marked wavelength dependency of {metric.upper()} "
               "over the whole speed range", res, _verdict_null(nsig, rel))
    for part in (dpart, bpart):
        c = _curve(diffs, part.name, comp.name, "liv")
        if c is None:
            continue
        c = c.flip().where(c.x > 0)
        hi, lo = _count(c, +1)
        xs, xu = _xsym(part), _xunit(part)
        zf = _zfin(c)
        res = (f"{ref} LIV significantly higher at {hi}/{c.x.size} values of {xs} > 0 ({xs} in "
               f"{_range_of(c.x[zf >= Z_SIGNIFICANT], xu)}), lower at {lo}")
        cl.add("§4.1", f"{part.name}: the shorter wavelength gives the larger LIV", res,
               _verdict_effect(hi, lo, cl.trials))
    for part in (dpart, bpart):
        c = _curve(diffs, part.name, comp.name, "ocds")
        if c is None:
            continue
        c = c.where(c.x > 0)  # other − reference = 1310 − 840
        hi, lo = _count(c, +1)
        xs, xu = _xsym(part), _xunit(part)
        zf = _zfin(c)
        res = (f"{oth} OCDS significantly higher at {hi} values ({xs} in {_range_of(c.x[zf >= Z_SIGNIFICANT], xu)}), "
               f"lower at {lo} ({xs} in {_range_of(c.x[zf <= -Z_SIGNIFICANT], xu)})")
        v = _verdict_effect(hi, lo, cl.trials)
        if v.startswith("mixed"):
            v = "partly: the sign depends on the motion value"
        cl.add("§2.2.1 via §4.1", f"{part.name}: the simulation is consistent with the experiment, where 1310 nm "
               "gave the higher OCDS (+0.22 s⁻¹)", res, v)


def _resolution_claims(cl: _Claims, study: Study, diffs, comp: Comparison, kind: str) -> None:
    dpart, bpart, fpart = _figure_parts(study)
    fig = comp.paper_figure
    as_axial = " (paper: as for the axial resolution)" if kind == "lateral" else ""
    for part, letters in ((dpart, "ab"), (bpart, "cd")):
        xs, xu = _xsym(part), _xunit(part)
        c = _curve(diffs, part.name, comp.name, "liv")
        if c is not None:
            cpos = c.where(c.x > 0)  # other − reference = low − high resolution
            cr = _crossing(c)
            found = bool(cr and cr["found"])
            small = cpos.where(cpos.x <= (cr["x_lo"] if found else part.inset_max * (1 + 1e-9)))
            if small.x.size:
                text, verdict = _region(small, +1, cl.trials, "dB²")
                res = (f"low − high resolution LIV for 0 < {xs} ≤ {small.x.max():.3g} {xu} "
                       + ("(below the inversion)" if found else "(the inset range)") + f": {text}")
            else:
                res, verdict = "no motion values below the inversion", "not tested"
            cl.add(f"§3.3.2, {fig}({letters[0]})", f"{part.name}: the low {kind} resolution gives a slightly higher "
                   f"LIV at small {xs}{as_axial}", res, verdict)
            paper_cross = part.kind == "diffusion" and kind == "axial"
            claim = (f"{part.name}: the order inverts at larger {xs}: the high resolution gives the higher LIV"
                     + (" above about 1.2 µm²/s" if paper_cross else as_axial))
            if cr:
                sides = (f"pooled low − high below {_dz(*cr['left'][:2], 'dB²')}, above {_dz(*cr['right'][:2], 'dB²')}")
                if found:
                    b0, b1 = cr["bracket"]
                    res = (f"the order inverts; best split between the sampled {xs} = {cr['x_lo']:.3g} and "
                           f"{cr['x_hi']:.3g} {xu} (≈ {cr['x']:.3g}), and single values place the crossing between "
                           f"{b0:.3g} and {b1:.3g} {xu} (the last significantly positive and first significantly "
                           f"negative difference, |z| ≥ {Z_BRACKET:g}); {sides}")
                    if paper_cross and not (b0 <= 1.2 <= b1):
                        verdict = f"partly: the order inverts, but between {b0:.3g} and {b1:.3g} µm²/s, not at about 1.2"
                    else:
                        verdict = "supported" + (f" (1.2 µm²/s lies within {b0:.3g}–{b1:.3g})" if paper_cross else "")
                else:
                    res = (f"no significant inversion; best split between {cr['x_lo']:.3g} and {cr['x_hi']:.3g} "
                           f"{xu}: {sides}")
                    verdict = f"not resolved with {cl.trials} trials"
            else:
                res, verdict = "too few motion values", "not tested"
            cl.add(f"§3.3.2, {fig}({letters[0]})", claim, res, verdict)
            large = cpos.where(cpos.x >= 0.5 * cpos.x.max())
            text, verdict = _region(large, -1, cl.trials, "dB²")
            j = int(np.argmax(large.x))
            res = (f"low − high resolution LIV for {xs} ≥ {0.5 * cpos.x.max():.3g} {xu}: {text}; at {xs} = "
                   f"{large.x[j]:.3g} {xu}: {large.ref[j]:.2f} (high) vs {large.other[j]:.2f} (low) dB²")
            cl.add(f"§4.2 (P7–P9), {fig}({letters[0]})", f"{part.name}: at large {xs} the high resolution gives the "
                   "higher LIV (the plateau set by the spatial speckle contrast)", res, verdict)
        c = _curve(diffs, part.name, comp.name, "ocds")
        if c is None:
            continue
        cpos = c.where(c.x > 0)
        if part is dpart:
            i, nsig, k, rel = _extremes(cpos)
            res = (f"low − high: largest |z| {_dz(cpos.diff[i], cpos.se[i], 's⁻¹')} at D = {cpos.x[i]:.3g} {xu}; "
                   f"|z| ≥ {Z_SIGNIFICANT:g} at {nsig}/{cpos.x.size} values; largest |difference| "
                   f"{abs(cpos.diff[k]):.3g} s⁻¹ "
                   f"({100 * rel:.1f} % of the curve's maximum)")
            cl.add(f"§3.3.2, {fig}({letters[1]})", f"diffusion: OCDS shows no {kind}-resolution dependency{as_axial}",
                   res, _verdict_null(nsig, rel))
        else:
            band = cpos.where((cpos.x >= 0.5) & (cpos.x <= 5.0))
            if band.x.size:
                text, verdict = _region(band, -1, cl.trials, "s⁻¹")
                res = f"low − high OCDS for v in [0.5, 5] µm/s: {text}"
            else:
                res, verdict = "no speeds in [0.5, 5] µm/s", "not tested"
            cl.add(f"§3.3.2, {fig}({letters[1]})", f"ballistic: the high {kind} resolution gives a slightly higher OCDS "
                   f"at v ≈ 0.5–5 µm/s{as_axial}", res, verdict)
    xu = _xunit(fpart)
    for metric, letter in (("liv", "e"), ("ocds", "f")):
        c = _curve(diffs, fpart.name, comp.name, metric)
        if c is None:
            continue
        cpos = c.where(c.x > 0)
        u = _METRIC_UNIT[metric]
        i, nsig, k, rel = _extremes(cpos)
        pm, pse, pz, pk = _pooled(cpos)
        res = (f"low − high: largest |z| {_dz(cpos.diff[i], cpos.se[i], u)} at v = {cpos.x[i]:.3g} {xu}; largest "
               f"|difference| {abs(cpos.diff[k]):.3g} {u} at v = {cpos.x[k]:.3g} {xu} ({100 * rel:.0f} % of the curve's "
               f"maximum); significant at {nsig}/{cpos.x.size} speeds; pooled over all speeds {_dz(pm, pse, u)}")
        sig = nsig > 0 or abs(pz) >= Z_SIGNIFICANT
        if sig and rel >= 0.05:
            verdict = "supported"
        elif sig:
            verdict = f"partly: significant but small ({100 * rel:.1f} % of the curve)"
        else:
            verdict = f"not resolved: no significant difference with {cl.trials} trials"
        cl.add(f"§3.3.2, {fig}({letter})", f"flow: marked {kind}-resolution dependency of {metric.upper()}{as_axial}",
               res, verdict)
    c = _curve(diffs, fpart.name, comp.name, "liv")
    if c is not None:
        cpos = c.where(c.x > 0)
        text, verdict = _region(cpos, -1, cl.trials, "dB²")
        res = (f"high-resolution LIV above the low-resolution LIV at {int(np.sum(cpos.diff < 0))}/{cpos.x.size} speeds; "
               f"low − high {text}")
        cl.add(f"§4.2, {fig}(e)", "flow: the high resolution gives the higher LIV at all speeds", res, verdict)


def _reach_claims(cl: _Claims, study: Study, diffs, comps: list[Comparison]) -> list[str]:
    """P12/P13 (diffusion, ballistic) and the flow argument of §4.2: which LIV curve saturates first."""
    rows = []
    dpart, bpart, fpart = _figure_parts(study)
    for part in (dpart, bpart, fpart):
        xs, xu = _xsym(part), _xunit(part)
        for comp in comps:
            c = _curve(diffs, part.name, comp.name, "liv")
            if c is None:
                continue
            xr, xo = _x_reach(c.x, c.ref), _x_reach(c.x, c.other)
            rows.append(f"| {part.name} | {comp.name} | {xr:.3g} ({comp.reference}) | {xo:.3g} ({comp.other}) | {xu} |")
            if part is fpart:
                claim = f"flow: the LIV saturates over speed more rapidly for the higher resolution ({comp.name})"
                ok = xr <= xo
            else:
                claim = f"{part.name}: the LIV reaches its flat top more quickly for the larger ENS ({comp.name})"
                ok = xo <= xr
            verdict = ("not tested: a curve does not rise" if math.isnan(xr) or math.isnan(xo) else
                       ("consistent" if ok else "inconsistent") + " (from the mean curves; no standard error)")
            cl.add("§4.2 (flow)" if part is fpart else "§4.2 (P12, P13)", claim,
                   f"{xs} where the mean LIV first reaches 90 % of its value at the largest {xs}: {xr:.3g} (high) vs "
                   f"{xo:.3g} {xu} (low resolution)", verdict)
    return rows


def _direction_rows(study: Study, directions) -> list[str]:
    pa = study.direction_parts[0]
    ins = study.part(pa).inset_max
    rows = []
    for system in dict.fromkeys(directions["system"]):
        for metric in ("liv", "ocds"):
            t = directions[(directions["system"] == system) & (directions["metric"] == metric)
                           & (directions["value"] > 0)].sort_values("value")
            if t.empty:
                continue
            u = _METRIC_UNIT[metric]
            k = int(np.nanargmax(np.abs(t["diff"].to_numpy(float))))
            big = t.iloc[k]
            sig = t[np.abs(t["z"].to_numpy(float)) >= Z_SIGNIFICANT]
            sm = t[t["value"] <= ins * (1 + 1e-9)]
            msm = float(sm["diff"].mean()) if len(sm) else math.nan
            sesm = float(math.sqrt((sm["se"] ** 2).sum()) / len(sm)) if len(sm) else math.nan
            last = t.iloc[-1]
            rows.append(f"| {system} | {metric.upper()} | {_dz(big['diff'], big['se'], u)} at v = "
                        f"{big['value']:.3g} µm/s | "
                        f"{len(sig)}/{len(t)} | {_dz(msm, sesm, u)} | {_dz(last['diff'], last['se'], u)} |")
    return rows


def claims_report(study: Study, result: SweepResult, differences, directions, *,
                  runtime: dict[str, Any] | None = None) -> str:
    """The Markdown claims report: every numerical finding of the paper's §3.3 and §4 with this run's numbers."""
    from .conventions import ens_paper, n_eff

    cl = _Claims(study.trials)
    comp = {c.name: c for c in study.comparisons}
    sc = study.scene_data
    pop = sc["population"][0]
    prot = sc["protocol"]
    an = sc.get("analysis", {})
    lines = [f"# The reference paper's numerical claims against study `{study.name}`", "",
             "Paper: Fujimura et al., *Experimental and numerical investigation of wavelength and resolution dependency "
             "of dynamic OCT signals*: §3.3 (numerical results, Figs. 6–8) and §4 (discussion).", "",
             "## Setup", "",
             f"- density {pop['density_per_um3']} µm⁻³; {prot['n_frames']} frames"
             + (f", {1000 * prot['frame_interval_s']:.1f} ms apart" if "frame_interval_s" in prot else "")
             + f"; OCDS over delays {list(an.get('ocds_delay_range_s', [0.2048, 1.2288]))} s "
             f"({an.get('ocds_estimator', 'pearson')} correlation of the {an.get('ocds_scale', 'db')} intensity); "
             "LIV = ddof-0 variance of 10·log10 I over the frames.",
             f"- {study.trials} trials per point, base seed {study.seed}, {study.dtype}; grouping `{study.grouping}`: "
             + ("each comparison's two systems in one scene" if study.grouping == "pairs" else "all systems in one scene")
             + ", so every difference below is paired over the same scatterers."]
    for p in study.parts:
        extra = (f" ({p.motion.get('directions', 'isotropic')} directions)" if p.kind == "ballistic" else
                 f" ({p.motion.get('polar_angle_deg', 45.0):g}° from the depth axis)" if p.kind == "flow" else "")
        lines.append(f"- part `{p.name}`: {p.kind}{extra}, {p.parameter} at {len(p.values)} values from "
                     f"{min(p.values):g} to {max(p.values):g}; inset up to {p.inset_max:g}")
    lines += ["", f"± is one standard error of the paired difference over trials; z = difference / SE; *significant* "
              f"means |z| ≥ {Z_SIGNIFICANT:g}. Small motion in the wavelength claims is the inset range of each part; "
              "large motion is the upper half of the range. A claimed difference over a range of motion values is judged "
              "on the difference pooled over that range (mean of the per-value differences; SE from the independent "
              "cells); a claimed absence of difference on every single value. Verdicts: *supported*; *contradicted* "
              "(significant the other way); *mixed*; *partly*; *not resolved* (no significant difference at this "
              "number of trials).", ""]
    if "wavelength" in comp:
        _wavelength_claims(cl, study, differences, comp["wavelength"])
    for kind in ("axial", "lateral"):
        if kind in comp:
            _resolution_claims(cl, study, differences, comp[kind], kind)
    reach = _reach_claims(cl, study, differences, [comp[k] for k in ("axial", "lateral") if k in comp])
    paper_ens = {(3.8, 4.9): 5.02, (14.0, 4.9): 18.5, (3.8, 18.0): 67.7}
    rho = pop["density_per_um3"]
    ens_rows, checks = [], []
    for s in sc["system"]:
        dx, dz = s["lateral_resolution_um"], s["axial_resolution_um"]
        e, ne = ens_paper(rho, dx, dz), n_eff(rho, dx, dz)
        ref = paper_ens.get((dz, dx)) if math.isclose(rho, 0.055) else None
        if ref is not None:  # the paper quotes 3 significant digits
            checks.append((f"(Δz, Δx) = ({dz:g}, {dx:g}) µm: {e:.3f} (paper {ref})",
                           abs(round(e, 2 if e < 10 else 1) - ref) < 1e-9))
        ens_rows.append(f"| {s['name']} | {dx:g} | {dz:g} | {e:.3f} | {ref if ref is not None else '–'} | {ne:.2f} | "
                        f"{1 + 1 / ne:.3f} |")
    if checks:
        cl.add("§4.2 (P2)", "ENS = 5.02 (high, high), 18.5 (low axial), 67.7 (low lateral)",
               "; ".join(dict.fromkeys(c[0] for c in checks)), "supported" if all(c[1] for c in checks) else "contradicted")
    lines += ["## Claims", "", cl.table(), ""]
    lines += ["## Effective number of scatterers (§4.2, P2–P3)", "",
              "| system | Δx (µm) | Δz (µm) | ENS = ρ·Δx²·Δz | paper | N_eff | C_I² = 1 + 1/N_eff |",
              "|---|---|---|---|---|---|---|", *ens_rows, "",
              "N_eff = ρ·(2π)^{3/2}·s_x²·s_z = 1.182·ENS is the count that sets the speckle statistics, and C_I² "
              "the intensity contrast of the Poisson medium (physics.md §5.4–5.5). Every configuration has ENS > 2, "
              "where the "
              "paper (after Hillman et al.) expects the speckle contrast to be nearly constant: hence the small "
              "plateau differences.", ""]
    if reach:
        lines += ["## How fast each LIV curve saturates (§4.2, P12–P13)", "",
                  "Motion value where the mean LIV first reaches 90 % of its value at the largest motion value (linear "
                  "interpolation between the sampled values).", "",
                  "| part | comparison | high resolution | low resolution | unit |", "|---|---|---|---|---|", *reach, ""]
    if directions is not None and len(directions):
        pa, pb = study.direction_parts
        la = study.part(pa).motion.get("directions", "isotropic")
        lb = study.part(pb).motion.get("directions", "isotropic")
        lines += [f"## Random ballistic motion: `{lb}` minus `{la}` directions", "",
                  f"Part `{pa}` draws directions `{la}` (the paper's law, physics.md §10.2; used in the figures), part "
                  f"`{pb}` `{lb}`; both use the same seeds. Differences `{lb}` − `{la}`, per system:", "",
                  f"| system | metric | largest difference | speeds with \\|z\\| ≥ {Z_SIGNIFICANT:g} | "
                  "mean for v ≤ inset | at the largest v |",
                  "|---|---|---|---|---|---|", *_direction_rows(study, directions), ""]
    lines += ["## Where this run disagrees with the paper or cannot tell", ""]
    bad = [r for r in cl.rows if not r[4].startswith(("supported", "consistent"))]
    lines += [f"- claim {r[0]} ({r[1]}): {r[2]}: **{r[4]}**." for r in bad] or \
             ["- nowhere: every claim tested is supported by this run."]
    lines.append("")
    if runtime:
        lines += ["## Run", "",
                  f"{runtime.get('cells')} cells ({runtime.get('computed')} computed, {runtime.get('cached')} from the "
                  f"cache), {runtime.get('system_trials')} system-trials; this run's simulation wall time "
                  f"{runtime.get('simulate_s', 0):.1f} s; the cells' simulation times summed over cells (as recorded "
                  f"when each was computed) {sum(c.elapsed_s for c in result.cells):.1f} s; torchdoct "
                  f"{runtime.get('version')}.", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# running a study


def study_outputs(study: Study, out_dir: str | os.PathLike) -> list[Path]:
    """Every file :func:`run_study` writes into ``out_dir``."""
    d = Path(out_dir)
    files = [d / "results.csv", d / "results.parquet", d / "differences.csv", d / "differences.parquet"]
    if study.direction_parts:
        files += [d / "directions.csv", d / "directions.parquet"]
    for c in study.comparisons:
        files += [d / f"{c.figure}.png", d / f"{c.figure}.svg"]
    if study.direction_parts:
        files += [d / "fig-directions.png", d / "fig-directions.svg"]
    files += [d / "claims.md", d / "study.json"]
    return files


@dataclass
class StudyResult:
    """What :func:`run_study` produced."""

    study: Study
    sweep_result: SweepResult
    table: Any
    differences: Any
    directions: Any
    report: str
    files: list[Path]
    timings: dict[str, float]


def run_study(study: Study | str | os.PathLike, out_dir: str | os.PathLike, *, trials: int | None = None,
              seed: int | None = None, cache_dir: str | os.PathLike | None = "default",
              scheduler: str | None = None, batch_cells: int = 1, workers: int = 1, force: bool = False,
              progress: bool = False) -> StudyResult:
    """Run a study and write its table, differences, figures, claims report and ``study.json``.

    ``cache_dir``: ``"default"`` is ``out_dir/cache``; ``None`` disables the cache. ``trials``/``seed``
    override the study's. Every output file is checked before any simulation: an existing one is an
    error unless ``force``. A rerun reuses the cached cells.
    """
    from . import __version__

    if not isinstance(study, Study):
        study = load_study(study)
    if trials is not None or seed is not None:
        study = Study(**{**study.__dict__, "trials": trials if trials is not None else study.trials,
                         "seed": seed if seed is not None else study.seed})
    files = study_outputs(study, out_dir)
    out = prepare_out_dir(out_dir, files, force)
    if cache_dir == "default":
        cache_dir = out / "cache"
    t0 = time.perf_counter()
    sweeps = study_sweeps(study)
    res = run_sweeps(sweeps, cache_dir=cache_dir, scheduler=scheduler, batch_cells=batch_cells, workers=workers,
                     progress=progress, desc=f"study {study.name}")
    t_sim = time.perf_counter() - t0
    table = res.table()
    diffs = paired_differences(study, res)
    dirs = direction_differences(study, res)
    written = write_table(table, out / "results", force=force)
    written += write_table(diffs, out / "differences", force=force)
    if study.direction_parts:
        written += write_table(dirs, out / "directions", force=force)
    t1 = time.perf_counter()
    for c in study.comparisons:
        written += _save_figure(plot_comparison(study, c, diffs), out / c.figure, force)
    if study.direction_parts:
        written += _save_figure(plot_directions(study, dirs), out / "fig-directions", force)
    t_fig = time.perf_counter() - t1
    timings = {"simulate_s": t_sim, "figures_s": t_fig}
    runtime = {"cells": len(res.cells), "computed": res.computed, "cached": res.cached,
               "system_trials": res.system_trials, "simulate_s": t_sim,
               "total_s": time.perf_counter() - t0, "version": __version__}
    report = claims_report(study, res, diffs, dirs, runtime=runtime)
    atomic_write(out / "claims.md", lambda tmp: Path(tmp).write_text(report, encoding="utf-8"))
    written.append(out / "claims.md")
    timings["total_s"] = time.perf_counter() - t0
    record = {"torchdoct_version": __version__, "study": study.to_dict(), "timings_s": timings,
              "cells": [{"sweep": c.cell.sweep, "cell": c.cell.index, "value": c.cell.values["value"],
                         "seed": c.seed, "trials": c.trials, "dtype": c.dtype, "cache_key": c.cache_key,
                         "cached": c.cached, "elapsed_s": c.elapsed_s} for c in res.cells],
              "computed": res.computed, "cached": res.cached, "system_trials": res.system_trials}
    atomic_write(out / "study.json", lambda tmp: Path(tmp).write_text(json.dumps(record, indent=2), encoding="utf-8"))
    written.append(out / "study.json")
    return StudyResult(study=study, sweep_result=res, table=table, differences=diffs, directions=dirs,
                       report=report, files=written, timings=timings)


# ----------------------------------------------------------------------------------------------
# benchmark


def _grouping_cells(study: Study, trials: int) -> list[dict[str, Any]]:
    """ms per cell of one motion value with all systems in one scene vs the comparisons' pairs."""
    from .simulate import simulate

    rows = []
    for pname in study.figure_parts:
        part = study.part(pname)
        pos = [v for v in part.values if v > 0]
        for v in sorted({pos[0], pos[len(pos) // 2], pos[-1]}):
            t = {}
            for grouping in ("all", "pairs"):
                s = Study(**{**study.__dict__, "grouping": grouping, "parts": (part,),
                             "figure_parts": (part.name,), "direction_parts": ()})
                total = 0.0
                for sw in study_sweeps(s):
                    cell = next(c for c in sw.cells if c.values["value"] == v)
                    simulate(cell.scene, trials=64, seed=1, dtype=study.dtype)  # warm-up
                    t0 = time.perf_counter()
                    simulate(cell.scene, trials=trials, seed=2, dtype=study.dtype)
                    total += time.perf_counter() - t0
                t[grouping] = total
            rows.append({"part": pname, "value": v, "trials": trials, "all_s": t["all"], "pairs_s": t["pairs"],
                         "all_ms_per_trial": 1e3 * t["all"] / trials, "pairs_ms_per_trial": 1e3 * t["pairs"] / trials})
    return rows


def bench_study(study: str | os.PathLike = "paper-reduced", *, trials: int | None = None, groupings: bool = False,
                grouping_trials: int = 128, study_out: str | os.PathLike | None = None, force: bool = False,
                workers: int = 1, progress: bool = False) -> dict[str, Any]:
    """Wall time of a whole study from an empty cache (tables, figures, report included) as JSON-ready data.

    ``study_out``: keep the study's outputs and cell cache there (default: a temporary directory, no
    cache); a later ``torchdoct study`` with ``--out`` study_out reuses the cells. ``groupings``: also
    time one cell per part at three motion values with all systems in one scene and as the comparisons'
    pairs (the choice of ``grouping``).
    """
    import tempfile

    import torch

    from .bench import machine_info

    st = load_study(study)
    out: dict[str, Any] = {"benchmark": "study", "study": st.name, "machine": machine_info(),
                           "omp_num_threads": os.environ.get("OMP_NUM_THREADS")}
    cache = None
    if study_out is not None:  # keep the cells too, so that ``torchdoct study`` on study_out resumes from them
        cache = Path(study_out) / "cache"
        if cache.is_dir() and any(cache.glob("*.npz")):
            raise ValueError(f"--study-out: {cache} holds cached cells; the benchmark times a run from an empty "
                             "cache: give a new directory")
    with tempfile.TemporaryDirectory(prefix="torchdoct-bench-study-") as tmp:
        t0 = time.perf_counter()
        r = run_study(st, study_out if study_out is not None else Path(tmp) / "out", trials=trials, cache_dir=cache,
                      force=force, workers=workers, progress=progress)
        wall = time.perf_counter() - t0
    per_part: dict[str, float] = {}
    for c in r.sweep_result.cells:
        per_part[c.cell.sweep.split("/")[0]] = per_part.get(c.cell.sweep.split("/")[0], 0.0) + c.elapsed_s
    out.update({"grouping": r.study.grouping, "trials_per_point": r.study.trials, "cells": len(r.sweep_result.cells),
                "motion_values": sum(len(p.values) for p in r.study.parts),
                "system_trials": r.sweep_result.system_trials, "wall_s": wall,
                "simulate_s": r.timings["simulate_s"], "figures_s": r.timings["figures_s"],
                "ms_per_system_trial": 1e3 * r.timings["simulate_s"] / r.sweep_result.system_trials,
                "simulate_s_per_part": per_part, "target_s_full_paper_study": 60.0, "workers": workers,
                "torch_threads": torch.get_num_threads()})
    if groupings:
        out["groupings"] = _grouping_cells(st, grouping_trials)
    return out


def format_bench_study(res: dict[str, Any]) -> str:
    lines = [f"study {res['study']}: {res['cells']} cells ({res['motion_values']} motion values, grouping "
             f"{res['grouping']}), {res['trials_per_point']} trials per point, {res['system_trials']} system-trials",
             f"wall time {res['wall_s']:.1f} s (simulation {res['simulate_s']:.1f} s, figures {res['figures_s']:.1f} s); "
             f"{res['ms_per_system_trial']:.3f} ms per system-trial (wall); {res['workers']} worker process(es)"
             + (" with one torch thread each" if res["workers"] > 1 else f" with {res['torch_threads']} torch threads"),
             "cell time per part (summed over workers): "
             + ", ".join(f"{k} {v:.1f} s" for k, v in res["simulate_s_per_part"].items())]
    if "groupings" in res:
        lines += ["", "| part | value | all systems in one scene (ms/trial) | comparisons' pairs (ms/trial) |",
                  "|---|---:|---:|---:|"]
        for g in res["groupings"]:
            lines.append(f"| {g['part']} | {g['value']:g} | {g['all_ms_per_trial']:.2f} | {g['pairs_ms_per_trial']:.2f} |")
        a = sum(g["all_s"] for g in res["groupings"])
        p = sum(g["pairs_s"] for g in res["groupings"])
        lines.append(f"\ntotal over these cells: all {a:.2f} s, pairs {p:.2f} s (pairs/all = {p / a:.2f})")
    return "\n".join(lines)

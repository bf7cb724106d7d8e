"""Per-sample mean DOCT values across configurations and the reference paper's statistical tests.

Paper Section 2.1.5: the mean LIV and OCDS over each sample's region (spheroid, without the
B-scans next to block boundaries) are computed per configuration; two configurations (the
wavelength comparison) are compared by a paired t-test (``scipy.stats.ttest_rel``); three or more
(the four axial or lateral resolutions) first by the Kruskal-Wallis test (``scipy.stats.kruskal``)
and, when it is significant, by paired t-tests between every pair. No multiple-comparison
correction is applied (as in the paper). Plots show the mean over samples ± SD (ddof 1) as the
paper's Figs. 3-5, with the individual samples as thin paired lines. The tests need at least 2
samples; one sample gets its per-configuration means without tests.

A **configuration** is a (wavelength, lateral resolution, axial resolution) triple: channels of
different maps files are matched by these values within 1e-6 relative, not by name, so the maps of
one sample taken with two systems (840 nm reduced to 18/14 µm vs 1310 nm original) pair up.

The region of a maps file is a boolean **mask** of its spatial shape, or the pixels whose ``mean_db``
(of ``threshold_resolution``, default the first ``mean_db`` channel of the file) is at least
``threshold_db``, or every pixel; NaN values (undefined DOCT values) are left out of each mean.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from collections.abc import Sequence as _Seq
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from ..files import atomic_write, check_out
from ..optics import ChannelOptics, same_value
from .mapsfile import Maps

__all__ = [
    "ComparedConfiguration",
    "ComparisonResult",
    "parse_config",
    "region_mask",
    "sample_means",
    "compare_samples",
    "plot_comparison",
    "significance_stars",
]

#: Columns of the tests table (one row per test).
TEST_COLUMNS = [
    "metric",
    "test",
    "config_a",
    "config_b",
    "n_samples",
    "mean_a",
    "sd_a",
    "mean_b",
    "sd_b",
    "mean_diff_b_minus_a",
    "statistic",
    "p_value",
    "significant",
    "posthoc",
]


@dataclass(frozen=True)
class ComparedConfiguration:
    """One configuration of a comparison: a channel's optics (µm) as a table key, and ``resolution``, the
    label of the first channel seen (not compared). Channels are grouped by their optics values; matching
    optics against a wanted value is :meth:`torchdoct.optics.ChannelOptics.matches`."""

    wavelength_um: float
    lateral_resolution_um: float
    axial_resolution_um: float
    resolution: str = field(compare=False, default="")

    @property
    def optics(self) -> ChannelOptics:
        return ChannelOptics(self.wavelength_um, self.lateral_resolution_um, self.axial_resolution_um)

    def label(self, with_wavelength: bool) -> str:
        res = self.resolution or f"lateral={self.lateral_resolution_um:g},axial={self.axial_resolution_um:g}"
        return f"{self.wavelength_um * 1000:g}nm {res}" if with_wavelength else res


def parse_config(text: str) -> tuple[float | None, str]:
    """``"RESOLUTION"`` or ``"WAVELENGTH_UM:RESOLUTION"`` (e.g. ``"axial=14"``, ``"0.84:axial=14,lateral=18"``)."""
    from .resolution import parse_resolution

    t = str(text).strip()
    wl = None
    if ":" in t:
        a, t = t.split(":", 1)
        try:
            wl = float(a)
        except ValueError:
            raise ValueError(f"--config {text!r}: {a!r} is not a wavelength in µm (e.g. 0.84:original)") from None
    return wl, parse_resolution(t).label


def _channel_config(info: Mapping[str, Any]) -> ComparedConfiguration:
    return ComparedConfiguration(
        float(info["wavelength_um"]),
        float(info["lateral_resolution_um"]),
        float(info["axial_resolution_um"]),
        str(info.get("resolution", "")),
    )


def region_mask(
    maps: Maps,
    *,
    mask: np.ndarray | None = None,
    threshold_db: float | None = None,
    threshold_resolution: str | None = None,
) -> np.ndarray:
    """Boolean region of ``maps`` (spatial shape) from a mask, an intensity threshold, or everything."""
    spatial = maps.maps.shape[1:]
    if mask is not None and threshold_db is not None:
        raise ValueError("give a mask or an intensity threshold, not both")
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != spatial:
            raise ValueError(
                f"mask has shape {list(m.shape)} but the maps are {list(spatial)} "
                f"({maps.meta.get('source') or 'maps'}); give a mask of the maps' spatial shape"
            )
        if m.dtype != bool:
            if not np.all(np.isin(m, (0, 1))):
                raise ValueError("mask must be boolean or 0/1")
            m = m.astype(bool)
        return m
    if threshold_db is not None:
        if not math.isfinite(float(threshold_db)):
            raise ValueError(f"threshold_db must be finite (dB); got {threshold_db!r}")
        cands = [
            c
            for c in maps.meta["channels"]
            if c["metric"] == "mean_db" and (threshold_resolution is None or c["resolution"] == threshold_resolution)
        ]
        if not cands:
            raise ValueError(
                f"an intensity threshold needs a mean_db channel"
                f"{'' if threshold_resolution is None else ' at ' + threshold_resolution!r} in "
                f"{maps.meta.get('source') or 'the maps'}; compute maps with mean_db or give --mask"
            )
        db = maps[cands[0]["name"]]
        with np.errstate(invalid="ignore"):
            return np.asarray(db >= float(threshold_db))
    return np.ones(spatial, dtype=bool)


def sample_means(
    maps: Maps, region: np.ndarray, metrics: Iterable[str] = ("liv", "ocds")
) -> dict[ComparedConfiguration, dict[str, tuple[float, int]]]:
    """``{configuration: {metric: (mean over finite region pixels, pixel count)}}`` of one maps file."""
    out: dict[ComparedConfiguration, dict[str, tuple[float, int]]] = {}
    wanted = set(metrics)
    for i, info in enumerate(maps.meta["channels"]):
        if info["metric"] not in wanted:
            continue
        if any(info.get(k) is None for k in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um")):
            raise ValueError(
                f"{maps.meta.get('source') or 'maps'}: channel {info['name']} has no optics (the maps were "
                "computed without them); configurations are matched by wavelength and resolutions: "
                "recompute the maps with --wavelength-um, --lateral-resolution-um and "
                "--axial-resolution-um"
            )
        v = maps.maps[i][region]
        v = v[np.isfinite(v)]
        mean = float(np.mean(v, dtype=np.float64)) if v.size else math.nan
        cfg = _channel_config(info)
        slot = out.setdefault(cfg, {})
        if info["metric"] in slot:
            raise ValueError(f"two {info['metric']} channels with the same optics in one maps file ({info['name']})")
        slot[info["metric"]] = (mean, int(v.size))
    return out


@dataclass
class ComparisonResult:
    """``per_sample`` (sample, configuration, metric, mean, n_pixels), ``tests`` (one row per test),
    ``configs`` (labels in order), ``metrics``, ``alpha``; tables are pandas DataFrames."""

    per_sample: Any
    tests: Any
    configs: list[str]
    metrics: list[str]
    alpha: float
    note: str = ""

    def values(self, metric: str) -> np.ndarray:
        """``[n_samples, n_configs]`` per-sample means of ``metric``."""
        t = self.per_sample[self.per_sample["metric"] == metric]
        piv = t.pivot(index="sample", columns="configuration", values="mean")
        samples = list(dict.fromkeys(self.per_sample["sample"]))
        return piv.loc[samples, self.configs].to_numpy(dtype=np.float64)

    def format(self) -> str:
        lines = []
        for metric in self.metrics:
            v = self.values(metric)
            if v.shape[0] > 1:
                lines.append(f"{metric}: mean ± SD over {v.shape[0]} samples")
            else:
                lines.append(f"{metric}: mean over the region of 1 sample")
            for j, c in enumerate(self.configs):
                sd = f" ± {np.std(v[:, j], ddof=1):.4f}" if v.shape[0] > 1 else ""
                lines.append(f"  {c:>28}  {np.mean(v[:, j]):10.4f}{sd}")
            for _, r in self.tests[self.tests["metric"] == metric].iterrows():
                pair = r["config_a"] if r["config_b"] == "" else f"{r['config_a']} vs {r['config_b']}"
                extra = (
                    ""
                    if r["test"] == "Kruskal-Wallis" or r["posthoc"] is None
                    else (" (post hoc)" if r["posthoc"] else " (Kruskal-Wallis not significant)")
                )
                if not math.isfinite(r["statistic"]):
                    lines.append(f"  {r['test']}: {pair}: no difference testable (the same in every sample)")
                    continue
                lines.append(
                    f"  {r['test']}: {pair}: statistic {r['statistic']:.4g}, p = {r['p_value']:.4g} "
                    f"{significance_stars(r['p_value'], self.alpha)}{extra}"
                )
        if self.note:
            lines.append(self.note)
        return "\n".join(lines)


def significance_stars(p: float, alpha: float = 0.05) -> str:
    """``***`` p < 0.001, ``**`` < 0.01, ``*`` < alpha, else ``n.s.`` (NaN: ``n/a``)."""
    if not math.isfinite(p):
        return "n/a"
    if p < 0.001:
        return "***"
    if p < 0.01:
        return "**"
    return "*" if p < alpha else "n.s."


def _quiet(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with np.errstate(all="ignore"):
            r = fn(*args)
    return float(r.statistic), float(r.pvalue)


def compare_samples(
    samples: Mapping[str, _Seq[tuple[Maps, np.ndarray]]],
    *,
    metrics: _Seq[str] = ("liv", "ocds"),
    configs: _Seq[str] | None = None,
    alpha: float = 0.05,
) -> ComparisonResult:
    """Paper statistics over samples. ``samples``: ``{name: [(maps, region), ...]}`` (one sample may
    hold the maps of several systems). ``configs``: ``"[WAVELENGTH_UM:]RESOLUTION"`` specs selecting
    and ordering configurations (default: every configuration present in all samples, in order of
    first appearance). Needs ≥ 2 configurations; the tests need ≥ 2 samples: with one sample the
    result holds its means and an empty tests table (``note`` says why)."""
    import pandas as pd
    from scipy import stats

    if not samples:
        raise ValueError("no samples given")
    if not (0 < alpha < 1):
        raise ValueError(f"alpha must be in (0, 1); got {alpha!r}")
    metrics = list(metrics)
    per: dict[str, dict[ComparedConfiguration, dict[str, tuple[float, int]]]] = {}
    order: list[ComparedConfiguration] = []
    for name, items in samples.items():
        merged: dict[ComparedConfiguration, dict[str, tuple[float, int]]] = {}
        for maps, region in items:
            for cfg, vals in sample_means(maps, region, metrics).items():
                if cfg in merged:
                    raise ValueError(f"sample {name!r}: configuration {cfg.label(True)} appears in two maps files")
                merged[cfg] = vals
                if cfg not in order:
                    order.append(cfg)
        per[name] = merged
    if configs:
        chosen = []
        for spec in configs:
            wl, label = parse_config(spec)
            hits = [c for c in order if c.resolution == label and (wl is None or same_value(c.wavelength_um, wl))]
            if len(hits) != 1:
                have = ", ".join(c.label(True) for c in order)
                raise ValueError(
                    f"--config {spec!r} matches {len(hits)} configurations (have: {have}); "
                    "add the wavelength as WAVELENGTH_UM:RESOLUTION"
                )
            chosen.append(hits[0])
    else:
        chosen = [c for c in order if all(c in per[s] for s in per)]
    for s, d in per.items():
        for c in chosen:
            if c not in d:
                raise ValueError(f"sample {s!r} has no channels for configuration {c.label(True)}")
            for m in metrics:
                if m not in d[c]:
                    raise ValueError(f"sample {s!r} has no {m} channel for configuration {c.label(True)}")
    if len(chosen) < 2:
        raise ValueError(f"need at least 2 configurations common to all samples; found {len(chosen)}")
    multi_wl = len({round(c.wavelength_um, 9) for c in chosen}) > 1
    labels = [c.label(multi_wl) for c in chosen]
    if len(set(labels)) != len(labels):
        labels = [c.label(True) + f" ({c.lateral_resolution_um:g}/{c.axial_resolution_um:g} µm)" for c in chosen]
    rows = [
        {"sample": s, "configuration": lab, "metric": m, "mean": per[s][c][m][0], "n_pixels": per[s][c][m][1]}
        for s in per
        for c, lab in zip(chosen, labels)
        for m in metrics
    ]
    per_sample = pd.DataFrame(rows)
    result = ComparisonResult(per_sample=per_sample, tests=None, configs=labels, metrics=metrics, alpha=alpha)
    tests = []
    untestable: list[str] = []
    if len(per) < 2:
        result.note = (
            f"1 sample ({next(iter(per))}): no tests; the paired tests need at least 2 samples "
            "(one mean per sample and configuration)"
        )
    for m in metrics:
        v = result.values(m)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{m}: some sample has no finite values in its region; check masks / thresholds")
        n = v.shape[0]
        if n < 2:
            continue

        def summary(j: int) -> tuple[float, float]:
            return float(np.mean(v[:, j])), float(np.std(v[:, j], ddof=1))

        def ttest(i: int, j: int, posthoc: bool | None) -> dict[str, Any]:
            d = v[:, j] - v[:, i]
            if np.ptp(d) <= 1e-12 * max(float(np.max(np.abs(v[:, [i, j]]))), 1e-300):
                # the same paired difference in every sample (identical samples, or one sample given twice):
                # its SD is 0 and the t statistic infinite; no difference is testable
                stat, p = math.nan, math.nan
                untestable.append(f"{m} {labels[i]} vs {labels[j]}")
            else:
                stat, p = _quiet(stats.ttest_rel, v[:, i], v[:, j])
            (ma, sa), (mb, sb) = summary(i), summary(j)
            return {
                "metric": m,
                "test": "paired t-test",
                "config_a": labels[i],
                "config_b": labels[j],
                "n_samples": n,
                "mean_a": ma,
                "sd_a": sa,
                "mean_b": mb,
                "sd_b": sb,
                "mean_diff_b_minus_a": mb - ma,
                "statistic": stat,
                "p_value": p,
                "significant": bool(p < alpha),
                "posthoc": posthoc,
            }

        if len(chosen) == 2:
            tests.append(ttest(0, 1, None))
        else:
            if np.ptp(v) <= 1e-12 * max(float(np.max(np.abs(v))), 1e-300):  # every value the same
                stat, p = math.nan, math.nan
                untestable.append(f"{m} (Kruskal-Wallis)")
            else:
                stat, p = _quiet(stats.kruskal, *[v[:, j] for j in range(v.shape[1])])
            sig = bool(p < alpha)
            tests.append(
                {
                    "metric": m,
                    "test": "Kruskal-Wallis",
                    "config_a": "all",
                    "config_b": "",
                    "n_samples": n,
                    "mean_a": math.nan,
                    "sd_a": math.nan,
                    "mean_b": math.nan,
                    "sd_b": math.nan,
                    "mean_diff_b_minus_a": math.nan,
                    "statistic": stat,
                    "p_value": p,
                    "significant": sig,
                    "posthoc": None,
                }
            )
            for i, j in combinations(range(len(chosen)), 2):
                tests.append(ttest(i, j, sig))
    result.tests = pd.DataFrame(tests, columns=TEST_COLUMNS)
    if untestable:
        result.note = "\n".join(
            filter(
                None,
                [
                    result.note,
                    (
                        f"no difference testable for {', '.join(untestable)}: the samples give the same paired difference "
                        "(statistic and p NaN; identical samples, or one maps file given as two samples?)"
                    ),
                ],
            )
        )
    return result


def plot_comparison(result: ComparisonResult, path: str | Path, *, force: bool = False) -> Path:
    """Means ± SD over samples per configuration, one panel per metric (paper Figs. 3-5)."""
    out = check_out(path, force, (".png", ".pdf", ".svg"), what="--plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    units = {"liv": "dB²", "ocds": "s⁻¹", "mean_db": "dB", "aliv": "dB²", "swiftness": "s⁻¹"}
    k = len(result.metrics)
    fig, axes = plt.subplots(1, k, figsize=(1.2 + 1.1 * len(result.configs) * k + 1.0 * k, 3.8), squeeze=False)
    xs = np.arange(len(result.configs))
    for ax, m in zip(axes[0], result.metrics):
        v = result.values(m)
        for row in v:
            ax.plot(xs, row, color="0.8", lw=0.8, zorder=1)
        mean = v.mean(0)
        sd = v.std(0, ddof=1) if v.shape[0] > 1 else np.zeros_like(mean)
        ax.errorbar(xs, mean, yerr=sd, fmt="o", color="k", capsize=4, zorder=3)
        ax.set_xticks(xs)
        ax.set_xticklabels(result.configs, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(f"mean {m.upper() if m in ('liv', 'ocds', 'aliv') else m} [{units.get(m, '')}]")
        t = result.tests[result.tests["metric"] == m]
        top = float(np.nanmax(v)) if v.size else 1.0
        span = (float(np.nanmax(v)) - float(np.nanmin(v))) or 1.0
        level = 0
        title = f"{m} (n = {v.shape[0]})"
        for _, r in t.iterrows():
            if r["test"] == "Kruskal-Wallis":
                title += f"\nKruskal-Wallis p = {r['p_value']:.3g}"
                continue
            if r["posthoc"] is False or not r["significant"]:
                if len(result.configs) > 2:
                    continue
            i, j = result.configs.index(r["config_a"]), result.configs.index(r["config_b"])
            y = top + span * (0.08 + 0.1 * level)
            ax.plot([i, i, j, j], [y - 0.02 * span, y, y, y - 0.02 * span], color="k", lw=0.8)
            ax.text((i + j) / 2, y, significance_stars(r["p_value"], result.alpha), ha="center", va="bottom")
            level += 1
        ax.set_title(title, fontsize=9)
        ax.set_xlim(-0.5, len(result.configs) - 0.5)
    fig.tight_layout()

    def write(tmp: str) -> None:
        fig.savefig(tmp, format=out.suffix.lstrip("."), dpi=150)

    try:
        atomic_write(out, write)
    finally:
        plt.close(fig)
    return out

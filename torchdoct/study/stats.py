"""Paired statistics of a study.

:func:`paired_differences` and :func:`direction_differences` turn a sweep result into tables: per
value and metric, both systems' (or both direction laws') mean and SD and the paired difference over
the same trials with its standard error and ``z = diff/SE``. The curve statistics below (pooled
difference over a range of values, counts of significant values, the crossing of a difference curve,
where a mean curve saturates) read only those tables; the claims report is built on them.

A difference is *significant* when ``|z| ≥ 4`` (:data:`Z_SIGNIFICANT`; the reasons are in
:mod:`torchdoct.study`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .spec import Study
from .sweep import SweepResult
from .sweeps import _groups, _sweep_name

__all__ = ["Z_SIGNIFICANT", "Z_BRACKET", "paired_differences", "direction_differences"]

#: |z| at or above which a difference counts as significant in the claims report.
Z_SIGNIFICANT = 4.0
#: A single value's difference that brackets a crossing (see :func:`_crossing`).
Z_BRACKET = 2.0


def _paired(a: np.ndarray, b: np.ndarray) -> tuple[float, float, int]:
    """Mean and SE of ``b − a`` over trials where both are finite."""
    ok = np.isfinite(a) & np.isfinite(b)
    d = b[ok].astype(np.float64) - a[ok].astype(np.float64)
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
                    rows.append(
                        {
                            "part": part.name,
                            "comparison": c.name,
                            "motion": part.kind,
                            "parameter": part.parameter,
                            "value": cr.cell.values["value"],
                            "metric": metric,
                            "reference": c.reference,
                            "other": c.other,
                            "mean_reference": mr,
                            "sd_reference": sr,
                            "mean_other": mo,
                            "sd_other": so,
                            "diff": d,
                            "se": se,
                            "z": _z(d, se),
                            "n": n,
                            "trials": cr.trials,
                            "seed": cr.seed,
                        }
                    )
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
                rows.append(
                    {
                        "system": system,
                        "value": v,
                        "metric": metric,
                        "part_a": pa,
                        "part_b": pb,
                        "directions_a": study.part(pa).motion.get("directions", "isotropic"),
                        "directions_b": study.part(pb).motion.get("directions", "isotropic"),
                        "mean_a": ma,
                        "sd_a": sa,
                        "mean_b": mb,
                        "sd_b": sb,
                        "diff": d,
                        "se": se,
                        "z": _z(d, se),
                        "n": n,
                    }
                )
    return pd.DataFrame(rows)


@dataclass
class _Curve:
    """One comparison along the motion parameter: means, paired difference (other − reference), SE, z."""

    x: np.ndarray
    ref: np.ndarray
    other: np.ndarray
    diff: np.ndarray
    se: np.ndarray
    z: np.ndarray

    def where(self, mask: np.ndarray) -> _Curve:
        return _Curve(*(a[mask] for a in (self.x, self.ref, self.other, self.diff, self.se, self.z)))

    def flip(self) -> _Curve:
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
    se = float(math.sqrt(np.sum(c.se**2)) / k)
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
    score = [z[: k + 1].sum() - z[k + 1 :].sum() for k in range(c.x.size - 1)]
    k = int(np.argmax(score))
    left, right = c.where(np.arange(c.x.size) <= k), c.where(np.arange(c.x.size) > k)
    pl, pr = _pooled(left), _pooled(right)
    pos = [i for i in range(k + 1) if z[i] >= Z_BRACKET]
    neg = [i for i in range(k + 1, c.x.size) if z[i] <= -Z_BRACKET]
    bracket = (float(c.x[pos[-1]] if pos else c.x[0]), float(c.x[neg[0]] if neg else c.x[-1]))
    return {
        "x_lo": float(c.x[k]),
        "x_hi": float(c.x[k + 1]),
        "x": float(math.sqrt(c.x[k] * c.x[k + 1])),
        "bracket": bracket,
        "left": pl,
        "right": pr,
        "found": pl[2] >= Z_SIGNIFICANT and pr[2] <= -Z_SIGNIFICANT,
    }


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

"""Pareto fronts of cost against error, the defaults' dominance and the one-standard-error recommendation."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .evaluate import _sd

#: Paired z above which a faster, more accurate point counts as significantly better.
_Z_DOMINATED = 2.0


def _pareto(
    axis: str,
    rows: list[dict[str, Any]],
    reps: dict[tuple[str, str], dict[str, np.ndarray]],
    time_key: str,
    pool: str,
    default_label: str | None,
    min_coverage: float,
    error_key: str = "error",
) -> dict[str, Any]:
    """Front, defaults and one-standard-error recommendation for one (axis, time key, pool, error).

    ``error_key``: ``"error"`` (1 − balanced accuracy of the decided samples) or ``"strict_error"``
    (1 − strict accuracy on the common identifiable draws, undecided = wrong: coverage included).
    For ``"error"``, settings that decide less than ``min_coverage`` of the identifiable samples are
    left out (their balanced accuracy rests on a handful of decisions) and a recommended setting must
    not decide significantly less than the best. ``reps[(label, pool)]`` holds the bootstrap
    replicates of the errors and the coverage (the same resamples for every setting).
    """
    from torchdoct.bench.tradeoffs import pareto_front

    pts, excluded = [], []
    for r in rows:
        m = r["pools"].get(pool)
        if m is None:
            continue
        t, e, c = r[time_key], m[error_key], m["coverage"]
        if t is None or e is None or not (math.isfinite(t) and math.isfinite(e)):
            excluded.append({"label": r["label"], "reason": "no decided identifiable sample"})
        elif error_key == "error" and (c is None or c < min_coverage):
            excluded.append({"label": r["label"], "reason": f"coverage {c:.3f} < {min_coverage:g}"})
        else:
            pts.append(
                {
                    "label": r["label"],
                    "time_s": float(t),
                    "error": float(e),
                    "error_se": m[f"{error_key}_se"],
                    "coverage": float(c),
                    "coverage_se": m["coverage_se"],
                }
            )
    front = [p["label"] for p in pareto_front(pts)]
    out: dict[str, Any] = {
        "axis": axis,
        "time_key": time_key,
        "pool": pool,
        "error_key": error_key,
        "min_coverage": min_coverage if error_key == "error" else None,
        "front": front,
        "excluded": excluded,
        "points": [
            {
                "label": p["label"],
                "time": p["time_s"],
                "error": p["error"],
                "error_se": p["error_se"],
                "coverage": p["coverage"],
            }
            for p in pts
        ],
        "defaults": default_label if any(r["label"] == default_label for r in rows) else None,
        "defaults_on_front": None,
        "defaults_dominated_by": [],
        "defaults_significantly_dominated": None,
        "best": None,
        "recommended": None,
    }
    if not pts:
        return out

    def paired_se(a: str, b: str, key: str) -> float:
        return 0.0 if a == b else _sd(reps[(a, pool)][key] - reps[(b, pool)][key])

    d = next((p for p in pts if p["label"] == default_label), None)
    if d is not None:
        out["defaults_on_front"] = d["label"] in front
        dom = []
        for q in pts:
            if q["time_s"] < d["time_s"] and q["error"] < d["error"]:
                se = paired_se(d["label"], q["label"], error_key)
                gain = d["error"] - q["error"]
                dom.append(
                    {"label": q["label"], "error_gain": gain, "paired_se": se, "z": gain / se if se > 0 else math.inf}
                )
        out["defaults_dominated_by"] = dom
        out["defaults_significantly_dominated"] = any(x["z"] > _Z_DOMINATED for x in dom)
    best = min(pts, key=lambda p: (p["error"], p["time_s"]))

    def within(p: dict[str, Any]) -> bool:
        se_e = paired_se(p["label"], best["label"], error_key)
        se_c = paired_se(p["label"], best["label"], "coverage")
        return p["error"] - best["error"] <= (se_e if math.isfinite(se_e) else 0.0) and (
            error_key != "error" or best["coverage"] - p["coverage"] <= (se_c if math.isfinite(se_c) else 0.0)
        )

    out["best"] = best["label"]
    out["recommended"] = min((p for p in pts if within(p)), key=lambda p: (p["time_s"], p["error"]))["label"]
    return out


def _error_keys(primary: bool) -> tuple[str, ...]:
    """Errors with a front: both for an axis's primary cost, the balanced one otherwise."""
    return ("error", "strict_error") if primary else ("error",)

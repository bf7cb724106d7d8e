"""The grid of a sweep: the values of one field (explicit, linear or log-spaced) and key paths into a scene
file's dict (:mod:`torchdoct.study.sweep`'s module docstring gives the schema).

Generated values are rounded to 12 significant digits so that cell keys (and seeds) do not depend on
the numpy version. Paths index arrays of tables by position (``system.1.axial_resolution_um``); a
missing table on the path is created. Every error names the field and the fix.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np

from ..sim.config import _fail

__all__ = ["field_values", "MAX_CELLS", "max_cells", "set_max_cells", "cells_over_cap"]

_ARRAY_TABLES = ("system", "population")
_SIG_DIGITS = 12

#: The most cells a sweep may have unless ``--max-cells`` (:func:`set_max_cells`) says otherwise: every
#: cell's scene is built and validated before the first is simulated, so the count is checked first.
MAX_CELLS = 10_000
_max_cells: int | None = None


def set_max_cells(n: int | None) -> None:
    """Set (``None``: clear) the cap on a sweep's cells over :data:`MAX_CELLS` (``--max-cells``)."""
    global _max_cells
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"--max-cells must be a positive integer; got {n!r}")
    _max_cells = n


def max_cells() -> int:
    """The cap on a sweep's cells: ``--max-cells``, else :data:`MAX_CELLS`."""
    return MAX_CELLS if _max_cells is None else _max_cells


def cells_over_cap(where: str, n: int, what: str, estimate=None) -> None:
    """Refuse ``n`` cells (or values of one field) over :func:`max_cells` before any is built, naming
    ``where``, ``what`` makes them, the count and the fix; ``estimate()`` (called only then) returns the
    seconds and bytes of building one cell, scaled to ``n`` in the message."""
    cap = max_cells()
    if n > cap:
        extra = ""
        if estimate is not None:
            sec, nbytes = estimate()
            extra = (
                f"; building them alone would take about {sec * n:,.0f} s and {nbytes * n / 2**30:,.2f} GB "
                "before the first is simulated"
            )
        _fail(
            where,
            f"{what} makes {n:,} cells, over the cap of {cap:,}{extra}",
            'sweep fewer values, use mode = "zip", or pass --max-cells N to run them all',
        )


# ----------------------------------------------------------------------------------------------
# values of one field


def _round(v: float) -> float:
    return float(f"{v:.{_SIG_DIGITS}g}")


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _range_spec(where: str, spec: Any, kind: str) -> list[float]:
    example = "{ start = 0.001, stop = 15.0, num = 31 }" if kind == "log" else "{ start = 0.0, stop = 15.0, num = 31 }"
    if not isinstance(spec, dict):
        raise TypeError(f"{where}.{kind} must be a table {example}; got {spec!r}")
    unknown = sorted(set(spec) - {"start", "stop", "num"})
    missing = sorted({"start", "stop", "num"} - set(spec))
    if unknown or missing:
        _fail(
            f"{where}.{kind}",
            f"needs exactly the keys start, stop, num; "
            f"{'unknown ' + str(unknown) if unknown else 'missing ' + str(missing)}",
            f"write {kind} = {example}",
        )
    start, stop, num = spec["start"], spec["stop"], spec["num"]
    for key, v in (("start", start), ("stop", stop)):
        if not _is_number(v):
            raise TypeError(f"{where}.{kind}.{key} must be a number; got {v!r}")
        if not math.isfinite(v):
            _fail(f"{where}.{kind}.{key}", f"must be finite; got {v!r}")
    if isinstance(num, bool) or not isinstance(num, int):
        raise TypeError(f"{where}.{kind}.num must be an integer; got {num!r}")
    if num < 1:
        _fail(f"{where}.{kind}.num", f"must be >= 1; got {num}")
    cells_over_cap(f"{where}.{kind}.num", num, f"num = {num:,}")
    if kind == "log":
        if start <= 0 or stop <= 0:
            _fail(
                f"{where}.log",
                f"start and stop must be > 0; got start = {start}, stop = {stop}",
                "add 0 with values = [0.0] and start the log range above 0",
            )
        vals = np.geomspace(float(start), float(stop), num) if num > 1 else np.array([float(start)])
    else:
        vals = np.linspace(float(start), float(stop), num) if num > 1 else np.array([float(start)])
    return [_round(float(v)) for v in vals]


def field_values(spec: dict[str, Any], where: str = "sweep.field") -> tuple[Any, ...]:
    """Values of one sweep field from its ``values`` / ``linear`` / ``log`` keys (module docstring)."""
    sources = [k for k in ("values", "linear", "log") if k in spec]
    if not sources:
        _fail(where, "gives no values", "add values = [...], linear = {start, stop, num} or log = {start, stop, num}")
    out: list[Any] = []
    if "values" in spec:
        vals = spec["values"]
        if not isinstance(vals, list) or not vals:
            raise TypeError(f"{where}.values must be a non-empty array; got {vals!r}")
        for i, v in enumerate(vals):
            if isinstance(v, float) and not math.isfinite(v):
                _fail(f"{where}.values[{i}]", f"must be finite; got {v!r}")
        out.extend(vals)
    for kind in ("linear", "log"):
        if kind in spec:
            out.extend(_range_spec(where, spec[kind], kind))
    if len(sources) > 1:
        bad = [v for v in out if not _is_number(v)]
        if bad:
            _fail(
                where,
                f"combines {', '.join(sources)} but has non-numeric values {bad[:3]}",
                "give non-numeric values alone in values = [...]",
            )
        uniq: list[float] = []
        for v in sorted(out):
            if not uniq or not math.isclose(v, uniq[-1], rel_tol=1e-12, abs_tol=0.0):
                uniq.append(v)
        out = uniq
    return tuple(out)


# ----------------------------------------------------------------------------------------------
# paths into the scene dict


def _split_path(path: str, where: str) -> list[str]:
    if not isinstance(path, str) or not path.strip():
        raise TypeError(
            f"{where}.path must be a dotted key path such as 'population.0.motion.0.diffusion_um2_per_s'; got {path!r}"
        )
    parts = path.split(".")
    if any(not p for p in parts):
        _fail(f"{where}.path", f"{path!r} has an empty segment", "separate keys by single dots")
    return parts


def _normalize_arrays(data: dict[str, Any]) -> dict[str, Any]:
    """Turn single-table ``[system]``/``[population]``/``[population.motion]`` into one-element arrays."""
    for key in _ARRAY_TABLES:
        if isinstance(data.get(key), dict):
            data[key] = [data[key]]
    for pop in data.get("population", []) if isinstance(data.get("population"), list) else []:
        if isinstance(pop, dict) and isinstance(pop.get("motion"), dict):
            pop["motion"] = [pop["motion"]]
    return data


def _set_path(data: dict[str, Any], parts: list[str], value: Any, where: str) -> None:
    """Set ``data[p0][p1]...`` = value; arrays by index, missing tables created."""
    node: Any = data
    path = ".".join(parts)
    for depth, key in enumerate(parts):
        last = depth == len(parts) - 1
        here = ".".join(parts[:depth]) or "the scene"
        if isinstance(node, list):
            if not key.isdigit():
                _fail(
                    f"{where}.path",
                    f"{path!r}: {here} is an array; {key!r} is not an index",
                    f"use a position 0..{len(node) - 1}, e.g. {'.'.join(parts[:depth] + ['0'] + parts[depth + 1 :])!r}",
                )
            i = int(key)
            if i >= len(node):
                _fail(
                    f"{where}.path",
                    f"{path!r}: {here} has {len(node)} entr{'y' if len(node) == 1 else 'ies'} "
                    f"(indices 0..{len(node) - 1}); index {i} is out of range",
                    f"add the entry to the scene or use an index below {len(node)}",
                )
            if last:
                node[i] = copy.deepcopy(value)
            else:
                node = node[i]
        elif isinstance(node, dict):
            if last:
                node[key] = copy.deepcopy(value)
            else:
                if key not in node:
                    node[key] = {}
                node = node[key]
        else:
            _fail(
                f"{where}.path",
                f"{path!r}: {here} is a value ({node!r}), not a table or array",
                "point the path at a key inside a table",
            )

"""What every sequence format module returns (:class:`Loaded`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .lazy import LazyArray

__all__ = ["Loaded", "regular_file", "to_unit", "LENGTH_UM", "TIME_S"]


@dataclass
class Loaded:
    """What a format module's ``load`` returns.

    ``data``: the stored array (any axis order; may be a read-only memory map, or a :class:`LazyArray`
    read on demand). ``labels`` / ``label_params``: optional arrays stored with it. ``meta``: the metadata
    the file carries (then the sidecar is not read), or None. ``default_axes``: the stored order assumed
    when neither the file nor the caller names one (a TIFF stack: ``TZX``), or None. ``integer_intensity``:
    integer samples are intensities to be read as float32 (a TIFF's 8/16-bit pages). ``sidecar_fills``: the
    JSON sidecar, when there is one, supplies the keys ``meta`` lacks (``meta`` wins).
    """

    data: np.ndarray | LazyArray
    labels: np.ndarray | None = None
    label_params: np.ndarray | None = None
    meta: dict[str, Any] | None = None
    default_axes: str | None = None
    integer_intensity: bool = False
    sidecar_fills: bool = False


def regular_file(path: Path, what: str = "sequence file") -> None:
    """``path`` must be a regular file (a FIFO, device or socket would block or read without end): else a
    ``ValueError`` naming it and the fix, before it is opened."""
    import stat

    mode = path.stat().st_mode
    if not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a special file (FIFO, device or socket)"
        raise ValueError(f"{path.name}: the {what} is {kind}, not a regular file; give the data file itself")


#: Length units of OME-XML (symbols) and OME-NGFF (UDUNITS names), in µm.
LENGTH_UM = {
    "m": 1e6,
    "meter": 1e6,
    "cm": 1e4,
    "centimeter": 1e4,
    "mm": 1e3,
    "millimeter": 1e3,
    "µm": 1.0,
    "μm": 1.0,
    "um": 1.0,
    "micrometer": 1.0,
    "micron": 1.0,
    "nm": 1e-3,
    "nanometer": 1e-3,
}
#: Time units of OME-XML (symbols) and OME-NGFF (UDUNITS names), in s.
TIME_S = {
    "s": 1.0,
    "second": 1.0,
    "ms": 1e-3,
    "millisecond": 1e-3,
    "µs": 1e-6,
    "μs": 1e-6,
    "us": 1e-6,
    "microsecond": 1e-6,
    "ns": 1e-9,
    "nanosecond": 1e-9,
    "min": 60.0,
    "minute": 60.0,
    "h": 3600.0,
    "hour": 3600.0,
}


def to_unit(value: Any, unit: str | None, table: dict[str, float], default: str, where: str) -> float:
    """``value`` in ``unit`` (``default`` when None) converted by ``table`` (to µm or s); an unknown unit or
    a value that is not a finite positive number is a ``ValueError`` naming ``where``."""
    import math

    u = default if unit in (None, "") else str(unit)
    if u not in table:
        raise ValueError(
            f"{where}: unit {u!r} is not one of {', '.join(sorted(set(table)))}; store the value in {default}"
        )
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{where}: {value!r} must be a finite number > 0")
    return v * table[u]

"""What every sequence format module returns (:class:`Loaded`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Loaded"]


@dataclass
class Loaded:
    """What a format module's ``load`` returns.

    ``data``: the stored array (any axis order; may be a read-only memory map). ``labels`` /
    ``label_params``: optional arrays stored with it. ``meta``: the metadata the file carries (then
    the sidecar is not read), or None. ``default_axes``: the stored order assumed when neither the file
    nor the caller names one (a TIFF stack: ``TZX``), or None. ``integer_intensity``: integer samples
    are intensities to be read as float32 (a TIFF's 8/16-bit pages).
    """

    data: np.ndarray
    labels: np.ndarray | None = None
    label_params: np.ndarray | None = None
    meta: dict[str, Any] | None = None
    default_axes: str | None = None
    integer_intensity: bool = False

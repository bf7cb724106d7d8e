"""One axes convention for the project's image figures: render preview, maps PNGs, classify overlay.

A B-scan ``[Z, X]`` is drawn with x (fast lateral) to the right and depth z downwards, both in µm
(:data:`X_LABEL`, :data:`Z_LABEL`). The image extent is at pixel *edges*: pixel ``(iz, ix)`` covers
``x ∈ [x0 + ix·Δx, x0 + (ix + 1)·Δx]`` and ``z ∈ [z0 + iz·Δz, z0 + (iz + 1)·Δz]``, so the axes run
from ``x0`` to ``x0 + n_x·Δx`` and from ``z0`` (top) to ``z0 + n_z·Δz`` (bottom); ``x0, z0`` are 0
in every figure of the project (render preview, maps, overlays), so one image shows the same
coordinates in all three: distances from the top-left pixel edge. Without a pitch
the same layout is drawn in pixels (labels :data:`X_LABEL_PX`, :data:`Z_LABEL_PX`). Colour bars
carry the quantity and its unit, ``"LIV (dB²)"``.

This module imports only the standard library and numpy (matplotlib inside the functions), so the
torch-free classify path imports it (``import torchdoct`` is light).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "OKABE_ITO",
    "CLASS_COLORS",
    "LABEL_COLORS",
    "CONTINUOUS_CMAP",
    "MAGNITUDE_CMAP",
    "X_LABEL",
    "Z_LABEL",
    "X_LABEL_PX",
    "Z_LABEL_PX",
    "UNIT_TEXT",
    "image_extent",
    "show_bscan",
    "unit_text",
]

X_LABEL = "x (µm)"
Z_LABEL = "z, depth (µm)"
X_LABEL_PX = "x (pixel)"
Z_LABEL_PX = "z, depth (pixel)"
#: Units as the maps files write them → as figures print them.
#: The Okabe–Ito palette (Okabe & Ito, "Color Universal Design"): eight colours told apart with the common
#: colour-vision deficiencies. Every categorical figure of the project takes its colours from here.
OKABE_ITO = {
    "black": "#000000",
    "orange": "#E69F00",
    "sky blue": "#56B4E9",
    "bluish green": "#009E73",
    "yellow": "#F0E442",
    "blue": "#0072B2",
    "vermillion": "#D55E00",
    "reddish purple": "#CC79A7",
}
#: Colour of each motion class, shared by the ground truth of rendered phantoms and the classifier's
#: output, so a correct classification looks like its ground truth. Static tissue takes the colour of
#: "indeterminate": it does not decorrelate over the acquisition, which is what the classifier calls it.
CLASS_COLORS = {
    "diffusion": OKABE_ITO["blue"],
    "ballistic": OKABE_ITO["orange"],
    "flow": OKABE_ITO["bluish green"],
    "indeterminate": OKABE_ITO["reddish purple"],
}
#: Ground-truth label colours of rendered phantoms (:data:`torchdoct.image.phantom.MOTION_CODES` names).
LABEL_COLORS = {
    "empty": OKABE_ITO["black"],
    "static": CLASS_COLORS["indeterminate"],
    "diffusion": CLASS_COLORS["diffusion"],
    "ballistic": CLASS_COLORS["ballistic"],
    "flow": CLASS_COLORS["flow"],
    "mixed": OKABE_ITO["vermillion"],
}
#: Perceptual, colour-blind-safe colour maps of continuous quantities (matplotlib names): DOCT metrics,
#: and the motion magnitude.
CONTINUOUS_CMAP = "viridis"
MAGNITUDE_CMAP = "cividis"

UNIT_TEXT = {"dB^2": "dB²", "1/s": "s⁻¹", "dB": "dB", "code": "code"}


def unit_text(unit: str | None) -> str:
    """A unit as figures print it (``"dB^2"`` → ``"dB²"``, ``"1/s"`` → ``"s⁻¹"``)."""
    return UNIT_TEXT.get(unit or "", unit or "")


def _pitch(pitch_um: Mapping[str, Any] | None, key: str) -> float | None:
    if not isinstance(pitch_um, Mapping):
        return None
    v: Any = pitch_um.get(key)
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def image_extent(
    shape_zx: tuple[int, int], pitch_um: Mapping[str, Any] | None = None, origin_um: tuple[float, float] = (0.0, 0.0)
) -> tuple[tuple[float, float, float, float], bool]:
    """``((left, right, bottom, top), in_um)`` for ``imshow`` of a ``[Z, X]`` image (pixel edges).

    ``pitch_um``: ``{"z": Δz, "x": Δx}`` (µm); ``origin_um``: ``(z0, x0)``, the top-left pixel edge.
    ``in_um`` is False (extent in pixels) when the pitch is missing.
    """
    nz, nx = int(shape_zx[0]), int(shape_zx[1])
    pz, px = _pitch(pitch_um, "z"), _pitch(pitch_um, "x")
    if pz is None or px is None:
        return (0.0, float(nx), float(nz), 0.0), False
    z0, x0 = (float(v) for v in origin_um)
    return (x0, x0 + nx * px, z0 + nz * pz, z0), True


def show_bscan(
    ax: Any,
    image: np.ndarray,
    *,
    pitch_um: Mapping[str, Any] | None = None,
    origin_um: tuple[float, float] = (0.0, 0.0),
    **imshow_kw: Any,
) -> Any:
    """``ax.imshow`` of a ``[Z, X]`` (or ``[Z, X, 3]``) image with the project's axes convention.

    Sets the extent (:func:`image_extent`), the axis labels and ``interpolation="nearest"`` (pixels
    stay pixels); returns the ``AxesImage``.
    """
    arr = np.asarray(image)
    extent, in_um = image_extent(arr.shape[:2], pitch_um, origin_um)
    imshow_kw.setdefault("interpolation", "nearest")
    im = ax.imshow(arr, extent=extent, **imshow_kw)
    ax.set_xlabel(X_LABEL if in_um else X_LABEL_PX)
    ax.set_ylabel(Z_LABEL if in_um else Z_LABEL_PX)
    return im

"""The optics of one channel (one system configuration) as one value, and the one rule that matches two.

A channel of DOCT maps, a configuration of a classifier's feature specification and a system of a
scene all carry the same three lengths (µm; docs/physics.md §1 and :mod:`torchdoct.conventions`):

* ``wavelength_um``: vacuum centre wavelength;
* ``lateral_resolution_um``: 1/e² full width of the intensity PSF along x (the B-scan's fast axis);
* ``axial_resolution_um``: FWHM of the intensity PSF along depth, in the medium;

and, for an anisotropic lateral PSF, ``lateral_resolution_y_um`` (1/e² full width along y; ``None``
means the same as x). Two optics match when every length agrees within :data:`REL_TOL` relative
(:func:`same_value`): channels are matched by their optics, never by their names.

A maps channel's optics come from the maps metadata (:meth:`ChannelOptics.of_channel`): a
computational lateral reduction of B-scan data (``reduction.lateral_axes == "X"``) widens the PSF along
x only, so such a channel keeps the original lateral width along y.

Standard library only (no numpy, no torch): the torch-free classify path imports it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["REL_TOL", "same_value", "ChannelOptics"]

#: Relative tolerance for matching physical values (wavelengths, resolutions, times).
REL_TOL = 1e-6


def same_value(a: float, b: float, rel: float = REL_TOL) -> bool:
    """``|a − b| ≤ rel·max(|a|, |b|)``: the project's rule for matching physical values."""
    return abs(float(a) - float(b)) <= rel * max(abs(float(a)), abs(float(b)))


def _number(value: Any) -> float | None:
    """A finite positive float, or None for anything else (missing optics of a channel)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        try:  # numpy scalars
            value = float(value)
        except (TypeError, ValueError):
            return None
    v = float(value)
    return v if math.isfinite(v) and v > 0 else None


@dataclass(frozen=True)
class ChannelOptics:
    """Wavelength and resolutions of one channel (µm).

    ``lateral_resolution_um``: 1/e² full width of the intensity PSF along x (the B-scan's fast axis);
    ``lateral_resolution_y_um``: the same along y, ``None`` = as along x (isotropic);
    ``axial_resolution_um``: intensity FWHM along depth.
    """

    wavelength_um: float
    lateral_resolution_um: float  # along x (the B-scan's fast axis)
    axial_resolution_um: float
    lateral_resolution_y_um: float | None = None  # None = same as x (isotropic)

    @property
    def lateral_y_um(self) -> float:
        """The lateral resolution along y (µm): ``lateral_resolution_y_um``, or the x value when isotropic."""
        return self.lateral_resolution_um if self.lateral_resolution_y_um is None else self.lateral_resolution_y_um

    @property
    def isotropic(self) -> bool:
        """True when the lateral PSF has the same width along x and y (within :data:`REL_TOL`)."""
        return same_value(self.lateral_y_um, self.lateral_resolution_um)

    def matches(self, other: ChannelOptics, *, rel_tol: float = REL_TOL, lateral_y: bool = True) -> bool:
        """True when wavelength, lateral (x) and axial resolution agree within ``rel_tol`` relative, and,
        when ``lateral_y``, the lateral resolution along y too (an isotropic value's y is its x)."""
        return (
            same_value(self.wavelength_um, other.wavelength_um, rel_tol)
            and same_value(self.lateral_resolution_um, other.lateral_resolution_um, rel_tol)
            and same_value(self.axial_resolution_um, other.axial_resolution_um, rel_tol)
            and (not lateral_y or same_value(self.lateral_y_um, other.lateral_y_um, rel_tol))
        )

    def describe(self) -> str:
        """``"840 nm, lateral 4.9 µm, axial 3.8 µm"`` (``lateral 18 × 4.9 µm (x × y)`` when anisotropic)."""
        lateral = (
            f"{self.lateral_resolution_um:g} µm"
            if self.isotropic
            else f"{self.lateral_resolution_um:g} × {self.lateral_y_um:g} µm (x × y)"
        )
        return f"{self.wavelength_um * 1000:g} nm, lateral {lateral}, axial {self.axial_resolution_um:g} µm"

    @classmethod
    def of_channel(cls, channel: Mapping[str, Any], meta: Mapping[str, Any] | None = None) -> ChannelOptics | None:
        """The optics of a maps channel (its metadata dict), or None when it records none.

        ``meta``: the maps metadata. When its ``reduction.lateral_axes`` is ``"X"`` (B-scan data reduced
        along x only) and the channel's lateral resolution differs from the system's
        (``system.lateral_resolution_um``, the unreduced value), the channel's y resolution is the
        unreduced one; otherwise y = x.
        """
        try:
            values = [
                _number(channel.get(k)) for k in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um")
            ]
        except AttributeError:
            return None
        wl, lat, ax = values
        if wl is None or lat is None or ax is None:
            return None
        lat_y = None
        if meta is not None:
            reduction = meta.get("reduction")
            system = meta.get("system")
            axes = reduction.get("lateral_axes") if isinstance(reduction, Mapping) else None
            original = _number(system.get("lateral_resolution_um")) if isinstance(system, Mapping) else None
            if axes == "X" and original is not None and not same_value(lat, original):
                lat_y = original
        return cls(wl, lat, ax, lat_y)

"""Computational reduction of the resolution of complex OCT data (paper Section 2.1.3, Eqs. 1-8).

Both reductions convolve the complex field with a Gaussian, so a Gaussian complex PSF of amplitude
sigma ``s`` becomes one of sigma ``√(s² + σ'²)`` (paper Eqs. 1 and 5). With the project's
resolution conventions (:mod:`torchdoct.conventions`, physics.md §5.1: lateral resolution = 1/e²
full width of the intensity PSF, ``s_x = Δx/(2√2)``; axial = intensity FWHM, ``s_z = Δz/(2√ln2)``)
the widths needed to go from ``Δ`` to a target ``Δ_t`` are

* lateral (paper Eq. 4): ``σ'_x = √(s_x(Δx_t)² − s_x(Δx)²) = ½·√((Δx_t² − Δx²)/2)``; applied to each
  en-face plane (along Y and X), or along X only when the data have no Y axis (B-scan sequences: the
  PSF then stays at the original width along y, which no computation can change);
* axial (paper Eq. 8): a Gaussian spectral window ``exp(−½ (k/σ_s)²)`` on the Fourier transform of the
  field along depth (``k`` the angular spatial frequency conjugate to z, rad/µm), with
  ``σ_s = 1/σ'_z = 2·√(ln2/(Δz_t² − Δz²))``, ``σ'_z = √(s_z(Δz_t)² − s_z(Δz)²)``.

Both are implemented the same way, along one axis at a time: pad, FFT, multiply by the exact
continuous-Gaussian transfer function ``g·exp(−2π² f² σ'²)`` (``f`` in cycles/µm, so ``2πf = k``),
inverse FFT, crop. Multiplying the depth spectrum by the window *is* the paper's spectral
apodization; along the lateral axes it equals the paper's ``scipy.ndimage.gaussian_filter`` without
the sampled-kernel error at small ``σ'`` (a point PSF ends at the target width for any pitch).

Decisions (all switchable):

* **Centre of the axial window** (``axial_center``). The paper centres the window on the interference
  spectrum ("its origin locates at the center of the spectrum"). Simulated data (common phase
  convention ``E = Σ b·h(r_j − r_p)·exp(i2knz_j)``: no carrier across pixels) have their depth
  spectrum centred at zero spatial frequency: ``"zero"`` (default). Measured complex OCT usually
  carries a carrier along depth (the source spectrum sits away from the zero bin of the depth FFT);
  ``"centroid"`` centres the window on the power-weighted circular mean frequency of the depth
  spectrum of the data (:func:`depth_spectrum_center`), which is the paper's choice for measured
  data; a float gives the centre in cycles per depth pixel. A window centred at ``f_c`` is a
  convolution with ``g(z)·exp(i2πf_c z)``; it is applied as demodulate → zero-centred window →
  remodulate, so the edge handling acts on the envelope.
* **Normalization** (``normalization``): the filter gain ``g`` per filtered axis, with
  ``r = s_target/s_original``: ``"power"`` (default) ``g = √r``: the mean intensity of a random
  (Poisson) medium, ``ρ·∫|h|²``, is unchanged exactly, so dB maps and intensity thresholds stay
  comparable across resolutions; ``"peak"`` ``g = r``: the PSF keeps its peak amplitude 1, so the
  result equals a simulation at the target resolution with the same scatterers (the mean intensity
  then grows as ``r`` per axis, like the resolution volume); ``"sum"`` ``g = 1``: a unit-sum kernel /
  unit window at the centre, as the paper's ``gaussian_filter`` and spectral window (mean intensity
  falls as ``1/r`` per axis). LIV and OCDS do not depend on this choice (a constant factor).
* **Edges** (``edge_mode``): ``"reflect"`` (default; half-sample symmetric, ``d c b a | a b c d``,
  scipy's default mode that the paper used), ``"constant"`` (zeros outside), ``"wrap"`` (periodic).
  Padding is ``⌈5σ'⌉ + 1`` pixels (kernel tail below e^{-12.5}).
* **Identity / finer targets**: a target equal to the original (within 1e-9 relative) or ``None``
  leaves that axis untouched (the input is returned as is when nothing changes); a target finer than
  the original is a ``ValueError``.
* **Targets the grid cannot hold** (:func:`check_target_sampled`): a reduction cannot sharpen, and a
  target PSF narrower than two pixels along a filtered axis (lateral 1/e² width or axial FWHM
  ``< 2·pitch``) is not represented by the samples (Nyquist); ``torchdoct maps`` refuses such a target
  naming the smallest one the data allow. At exactly two pixels the lateral target's sampled
  ``Σ|h|²`` differs from ``∫|h|²/pitch`` by ``2·exp(−π² s²/p²)`` = 1.4 % (Poisson summation,
  ``s = p/√2``), the axial one's by 1e-6.
* **Targets wider than the image** (:func:`check_target_in_view`): a target PSF wider than the field of
  view (pixels × pitch) of an axis it filters would reach past the image on both sides, so the edge
  extension, not the sample, would make the result; ``torchdoct maps`` refuses it naming the widest target
  the axis allows (one field of view, :data:`MAX_TARGET_FIELDS`) or the pitch to check.
  :func:`reduce_resolution` keeps its own, looser memory bound on the Gaussian (:data:`MAX_KERNEL_AXES`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um

__all__ = [
    "reduction_axis_needs",
    "ResolutionTarget",
    "parse_resolution",
    "lateral_filter_sigma_um",
    "axial_filter_sigma_um",
    "axial_window_sigma_per_um",
    "depth_spectrum_center",
    "gaussian_filter_axis",
    "reduce_resolution",
    "check_target_sampled",
    "check_target_in_view",
    "MIN_TARGET_PIXELS",
    "EDGE_MODES",
    "NORMALIZATIONS",
]

EDGE_MODES = ("reflect", "constant", "wrap")
NORMALIZATIONS = ("power", "peak", "sum")
_REL_SAME = 1e-9


@dataclass(frozen=True)
class ResolutionTarget:
    """A target resolution: ``None`` keeps the original along that direction (µm)."""

    lateral_resolution_um: float | None = None
    axial_resolution_um: float | None = None

    def __post_init__(self) -> None:
        for key in ("lateral_resolution_um", "axial_resolution_um"):
            v = getattr(self, key)
            if v is not None and (
                not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0
            ):
                raise ValueError(f"target {key} must be a finite number > 0 (µm); got {v!r}")

    @property
    def label(self) -> str:
        """``"original"``, ``"axial=14"``, ``"lateral=18"`` or ``"axial=14,lateral=18"``."""
        parts = []
        if self.axial_resolution_um is not None:
            parts.append(f"axial={self.axial_resolution_um:g}")
        if self.lateral_resolution_um is not None:
            parts.append(f"lateral={self.lateral_resolution_um:g}")
        return ",".join(parts) or "original"

    def resolved(self, system: Mapping[str, Any]) -> tuple[float, float]:
        """``(lateral, axial)`` resolutions in µm after the reduction for ``system``."""
        lat = self.lateral_resolution_um if self.lateral_resolution_um is not None else system["lateral_resolution_um"]
        ax = self.axial_resolution_um if self.axial_resolution_um is not None else system["axial_resolution_um"]
        return float(lat), float(ax)


#: Coarsest target resolution accepted (µm): 1 cm, the bound of a scene's system resolutions.
MAX_RESOLUTION_UM = 1e4


def parse_resolution(text: str) -> ResolutionTarget:
    """``"original"`` | ``"axial=14"`` | ``"lateral=18"`` | ``"axial=14,lateral=18"`` (µm)."""
    t = str(text).strip().lower().replace(" ", "")
    if t in ("original", "orig", ""):
        return ResolutionTarget()
    vals: dict[str, float] = {}
    for part in t.split(","):
        key, sep, val = part.partition("=")
        if not sep or key not in ("axial", "lateral") or key in vals:
            raise ValueError(
                f"--resolution must be 'original', 'axial=UM', 'lateral=UM' or 'axial=UM,lateral=UM'; got {text!r}"
            )
        try:
            vals[key] = float(val)
        except ValueError:
            raise ValueError(f"--resolution {text!r}: {val!r} is not a number (µm)") from None
        if not (math.isfinite(vals[key]) and 0 < vals[key] <= MAX_RESOLUTION_UM):  # 1e200 overflows its square
            raise ValueError(
                f"--resolution {text!r}: {key} must be a number of µm in (0, {MAX_RESOLUTION_UM:g}] "
                f"(resolutions are in micrometres; {MAX_RESOLUTION_UM:g} µm is 1 cm)"
            )
    return ResolutionTarget(lateral_resolution_um=vals.get("lateral"), axial_resolution_um=vals.get("axial"))


def _check_target(kind: str, original_um: float, target_um: float) -> float:
    """``target² − original²`` after checks; 0 means identity."""
    if not (math.isfinite(target_um) and target_um > 0):
        raise ValueError(f"target {kind} resolution must be a finite number > 0 (µm); got {target_um!r}")
    if abs(target_um - original_um) <= _REL_SAME * original_um:
        return 0.0
    if target_um < original_um:
        raise ValueError(
            f"target {kind} resolution {target_um:g} µm is finer than the original {original_um:g} µm; "
            "a resolution can only be reduced (give a target >= the original)"
        )
    return target_um * target_um - original_um * original_um


#: the narrowest target PSF (lateral 1/e² width, axial FWHM) in pixels of the filtered axis (Nyquist)
MIN_TARGET_PIXELS = 2.0


def check_target_sampled(
    kind: str,
    original_um: float,
    target_um: float,
    pitch_um: Mapping[str, float],
    axes: str,
    option: str = "--resolution",
) -> None:
    """Refuse a ``kind`` (``"lateral"`` / ``"axial"``) target that differs from the original but is narrower
    than :data:`MIN_TARGET_PIXELS` pixels along an axis it filters (lateral: X, and Y when ``axes`` has it;
    axial: Z), naming ``option`` and the smallest target the data allow. Axes without a pitch are left to
    :func:`reduce_resolution`'s own error."""
    if _check_target(kind, original_um, target_um) == 0.0:
        return
    pitch = {str(k).lower(): v for k, v in dict(pitch_um or {}).items()}
    letters = "z" if kind == "axial" else "".join(c.lower() for c in "YX" if c in axes)
    known = {
        c: float(pitch[c])
        for c in letters
        if c in pitch and isinstance(pitch[c], (int, float)) and math.isfinite(pitch[c]) and pitch[c] > 0
    }
    if not known:
        return
    c, p = max(known.items(), key=lambda kv: kv[1])
    smallest = max(MIN_TARGET_PIXELS * p, original_um)
    if target_um < MIN_TARGET_PIXELS * p:
        raise ValueError(
            f"{option}: a {kind} resolution of {target_um:g} µm is finer than the {c} pitch of {p:g} µm "
            f"allows (the grid holds no PSF narrower than {MIN_TARGET_PIXELS:g} pixels, and a reduction "
            f"cannot sharpen); the smallest {kind} target these data allow is {smallest:g} µm: give "
            f"{kind}={smallest:g} or more"
        )


#: The widest reduction target, in fields of view (pixels × pitch) of an axis it filters: one. A wider
#: target PSF reaches past the image on both sides, so the edge extension, not the sample, would make
#: the maps.
MAX_TARGET_FIELDS = 1.0

#: The widest Gaussian :func:`reduce_resolution` runs, σ′ in lengths of the axis it filters (a memory bound,
#: see :func:`_check_kernel_bound`).
MAX_KERNEL_AXES = 4.0


def check_target_in_view(
    kind: str,
    original_um: float,
    target_um: float,
    pitch_um: Mapping[str, float],
    axes: str,
    shape: Any,
    option: str = "--resolution",
) -> None:
    """Refuse a ``kind`` reduction along an axis it filters (lateral: Y and X; axial: Z) whose field of
    view (pixels × pitch) is narrower than the original PSF (the samples cannot be at that pitch: a pitch
    given 1000× too fine made a mean 10 dB off, constant over the image), or whose target is wider than
    the field of view (:data:`MAX_TARGET_FIELDS`: the reduced PSF would reach past the image on both sides
    and the edge extension, not the sample, would make the maps). A target of exactly one field of view is
    accepted. Names ``option``, the axis, its extent and the fix (the widest target allowed, or the pitch).
    ``shape``: the field's shape in ``axes`` order. Reads only the shape: nothing is allocated."""
    if _check_target(kind, original_um, target_um) == 0.0:
        return
    pitch = {str(k).lower(): v for k, v in dict(pitch_um or {}).items()}
    dims = dict(zip(axes, [int(n) for n in shape]))
    letters = "Z" if kind == "axial" else "".join(c for c in "YX" if c in axes)
    for c in letters:
        p = pitch.get(c.lower())
        if c not in dims or not isinstance(p, (int, float)) or not (math.isfinite(p) and p > 0):
            continue
        fov = dims[c] * float(p)
        if original_um > fov:
            raise ValueError(
                f"{option}: the field of view along {c.lower()} ({dims[c]} pixels × {p:g} µm = {fov:g} µm) is "
                f"narrower than the original {kind} resolution of {original_um:g} µm, so the samples cannot "
                f"be at that pitch and a reduction to {target_um:g} µm would be made by the image's edges; "
                "check the pitch (--pitch-um, µm per pixel)"
            )
        if target_um > MAX_TARGET_FIELDS * fov:
            article = "an" if kind == "axial" else "a"
            raise ValueError(
                f"{option}: {article} {kind} resolution of {target_um:g} µm is wider than the field of view along "
                f"{c.lower()} ({dims[c]} pixels × {p:g} µm = {fov:g} µm): the reduced PSF would reach past "
                f"the image on both sides and the edges, not the sample, would make the maps; give "
                f"{kind}={MAX_TARGET_FIELDS * fov:g} or less, or check the pitch (--pitch-um, µm per pixel)"
            )


def _check_kernel_bound(sigma_um: float, pitch: float, n: int, axis: str) -> None:
    """The bound of the reduction kernel, a memory guard of :func:`reduce_resolution` (which the Python API
    calls directly): its σ' at most :data:`MAX_KERNEL_AXES` axis lengths, so the padding (⌈5σ'⌉ + 1 pixels
    a side) keeps the padded axis within about 41 times the axis, one axis at a time.

    Why 4 and not 1: this is not the validity check. :func:`check_target_in_view` (``torchdoct maps`` and
    :func:`~torchdoct.measured.maps.compute_maps` call it before any work) refuses a target wider than one
    field of view, which bounds σ' below ``Δ_t/(2√2)`` (lateral) or ``Δ_t/(2√ln2)`` (axial), about 0.35 or
    0.60 axis lengths: behind it this guard never fires. Called on its own, ``reduce_resolution`` is a
    numerical routine whose wider kernels are well defined (``edge_mode="wrap"`` on a periodic field pads
    nothing), and a bound of 1 would refuse them only to bound memory by a smaller constant multiple (about
    11 axis lengths instead of 41); what this guard must stop is a target or a pitch orders of magnitude
    off, whose padding would otherwise grow without bound."""
    if sigma_um / pitch > MAX_KERNEL_AXES * n:
        raise ValueError(
            f"the reduction along {axis} needs a Gaussian of σ' = {sigma_um / pitch:.4g} pixels, wider "
            f"than {MAX_KERNEL_AXES:g} times the axis ({n} pixels × {pitch:g} µm); give "
            "a target no wider than the field of view, or check pitch_um (µm per pixel)"
        )


def lateral_filter_sigma_um(original_um: float, target_um: float) -> float:
    """σ'_x (µm) of the lateral Gaussian (paper Eq. 4): ``√(s_x(Δx_t)² − s_x(Δx)²)``."""
    if _check_target("lateral", original_um, target_um) == 0.0:
        return 0.0
    return math.sqrt(amplitude_sigma_lateral_um(target_um) ** 2 - amplitude_sigma_lateral_um(original_um) ** 2)


def axial_filter_sigma_um(original_um: float, target_um: float) -> float:
    """σ'_z (µm) of the depth convolution equivalent to the spectral window (paper Eqs. 5-8)."""
    if _check_target("axial", original_um, target_um) == 0.0:
        return 0.0
    return math.sqrt(amplitude_sigma_axial_um(target_um) ** 2 - amplitude_sigma_axial_um(original_um) ** 2)


def axial_window_sigma_per_um(original_um: float, target_um: float) -> float:
    """σ_s = 1/σ'_z (rad/µm), the width of the spectral window (paper Eq. 8); inf for the identity."""
    s = axial_filter_sigma_um(original_um, target_um)
    return math.inf if s == 0.0 else 1.0 / s


# ----------------------------------------------------------------------------------------------
# filtering


def _fast_len(n: int) -> int:
    """Smallest 5-smooth integer >= n (fast FFT length)."""
    m = max(int(n), 1)
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def _reflect_index(n: int, lo: int, hi: int, device: torch.device) -> torch.Tensor:
    """Indices of positions ``lo … hi-1`` in half-sample-symmetric extension of ``0 … n-1``."""
    i = torch.arange(lo, hi, device=device)
    m = torch.remainder(i, 2 * n)
    return torch.where(m < n, m, 2 * n - 1 - m)


def gaussian_filter_axis(
    x: torch.Tensor,
    dim: int,
    sigma_px: float,
    *,
    gain: float = 1.0,
    center_cycles_per_px: float = 0.0,
    edge_mode: str = "reflect",
) -> torch.Tensor:
    """Convolve complex ``x`` along ``dim`` with ``gain·N(0, σ²)·exp(i2π f_c j)`` (σ in pixels).

    Implemented as a window ``gain·exp(−2π² (f − f_c)² σ²)`` on the FFT of the padded axis (see the
    module docstring for padding and ``edge_mode``); ``σ = 0`` returns ``gain·x``.
    """
    if edge_mode not in EDGE_MODES:
        raise ValueError(f"edge_mode must be one of {', '.join(EDGE_MODES)}; got {edge_mode!r}")
    if sigma_px < 0 or not math.isfinite(sigma_px):
        raise ValueError(f"filter sigma must be a finite number >= 0 (pixels); got {sigma_px!r}")
    if sigma_px == 0.0:
        return x * gain if gain != 1.0 else x
    dim = dim % x.ndim
    n = x.shape[dim]
    real = x.real.dtype
    fc = float(center_cycles_per_px)
    if fc != 0.0:
        j = torch.arange(n, device=x.device, dtype=torch.float64)
        shape = [1] * x.ndim
        shape[dim] = n
        carrier = torch.polar(torch.ones_like(j), 2.0 * math.pi * fc * j).to(x.dtype).reshape(shape)
        x = x * carrier.conj()
    if edge_mode == "wrap":
        pad, length = 0, n
        xp = x
    else:
        pad = int(math.ceil(5.0 * sigma_px)) + 1
        length = _fast_len(n + 2 * pad)
        if edge_mode == "reflect":
            idx = _reflect_index(n, -pad, length - pad, x.device)
            xp = x.index_select(dim, idx)
        else:
            widths = [0, 0] * x.ndim
            # torch pad order: last dim first
            k = 2 * (x.ndim - 1 - dim)
            widths[k], widths[k + 1] = pad, length - n - pad
            xp = torch.nn.functional.pad(x, widths)
    f = torch.fft.fftfreq(length, device=x.device, dtype=torch.float64)
    h = (gain * torch.exp(-2.0 * math.pi**2 * sigma_px**2 * f * f)).to(real)
    shape = [1] * x.ndim
    shape[dim] = length
    y = torch.fft.ifft(torch.fft.fft(xp, dim=dim) * h.reshape(shape), dim=dim)
    if pad or length != n:
        y = y.narrow(dim, pad, n)
    if fc != 0.0:
        y = y * carrier
    return y


def depth_spectrum_center(field: Any, *, axes: str = "TZX", max_lines: int = 65536) -> float:
    """Centre (cycles per depth pixel, in [−0.5, 0.5)) of the depth power spectrum of ``field``.

    The power-weighted circular mean ``arg Σ_f P(f)·e^{i2πf}/(2π)`` of ``P(f) = Σ |FFT_z E|²`` over
    (up to ``max_lines`` evenly spaced) A-lines of all frames: the "center of the spectrum" of the
    paper's axial window for measured data (≈ 0 for simulated data).
    """
    x = _as_tensor(field)
    if not x.is_complex():
        raise TypeError("depth_spectrum_center needs complex OCT data")
    axes = _check_axes(axes, x.ndim)
    zdim = axes.index("Z")
    lines = x.movedim(zdim, -1).reshape(-1, x.shape[zdim])
    if lines.shape[0] > max_lines:
        step = lines.shape[0] // max_lines
        lines = lines[::step][:max_lines]
    p = (torch.fft.fft(lines.to(torch.complex128), dim=-1).abs() ** 2).sum(0)
    f = torch.fft.fftfreq(p.numel(), dtype=torch.float64)
    z = (p * torch.polar(torch.ones_like(f), 2.0 * math.pi * f)).sum()
    if float(z.abs()) == 0.0:
        return 0.0
    c = float(torch.angle(z)) / (2.0 * math.pi)
    return c - 1.0 if c >= 0.5 else c


# ----------------------------------------------------------------------------------------------
# public entry point


def _as_tensor(field: Any) -> torch.Tensor:
    if isinstance(field, torch.Tensor):
        return field
    arr = np.asarray(field)
    if not arr.flags.writeable or not arr.flags.c_contiguous:
        arr = np.ascontiguousarray(arr).copy() if not arr.flags.writeable else np.ascontiguousarray(arr)
    return torch.from_numpy(arr)


def _check_axes(axes: str, ndim: int) -> str:
    if not isinstance(axes, str):
        raise TypeError(f"axes must be a string such as 'TZX' or 'TYZX'; got {axes!r}")
    a = axes.upper()
    if len(a) != ndim or len(set(a)) != len(a) or "Z" not in a or "X" not in a:
        raise ValueError(
            f"axes {axes!r} must name each of the {ndim} dimensions once and include Z and X (e.g. 'TZX' or 'TYZX')"
        )
    return a


def _system_value(system: Any, key: str) -> float:
    v = system.get(key) if isinstance(system, Mapping) else getattr(system, key, None)
    if v is None:
        raise ValueError(f"system has no {key!r}; give the original resolutions of the data (µm)")
    return float(v)


def _gain(normalization: str, ratio: float) -> float:
    if normalization == "power":
        return math.sqrt(ratio)
    if normalization == "peak":
        return ratio
    if normalization == "sum":
        return 1.0
    raise ValueError(f"normalization must be one of {', '.join(NORMALIZATIONS)}; got {normalization!r}")


def reduction_axis_needs(
    axes: str, *, lateral: bool, axial_sigma_px: float, edge_mode: str = "reflect"
) -> dict[str, int | None]:
    """What :func:`reduce_resolution` needs of each spatial axis when it runs on a piece of the field (the
    slab planner of :func:`torchdoct.measured.maps.compute_maps` reads it): ``None`` = that axis whole (the
    lateral Gaussian runs along every en-face axis, Y and X, across the whole plane; the axial filter with
    ``edge_mode="wrap"`` is periodic over the whole depth), an integer = a halo of that many pixels on each
    side (the axial window of σ ``axial_sigma_px`` pixels, truncated at 5σ, plus one). An axis not named
    may be cut anywhere: the reduction of the piece equals that of the whole there."""
    needs: dict[str, int | None] = {}
    if axial_sigma_px:
        needs["Z"] = None if edge_mode == "wrap" else int(math.ceil(5.0 * axial_sigma_px)) + 1
    if lateral:
        needs.update({c: None for c in "YX" if c in axes})
    return needs


def reduce_resolution(
    field: Any,
    *,
    pitch_um: Mapping[str, float],
    system: Any,
    lateral_resolution_um: float | None = None,
    axial_resolution_um: float | None = None,
    axes: str = "TZX",
    axial_center: str | float = "zero",
    edge_mode: str = "reflect",
    normalization: str = "power",
) -> Any:
    """Reduce the resolution of complex OCT ``field`` to the target (paper Eqs. 1-8).

    ``field``: torch tensor or numpy array, complex64/complex128, any layout named by ``axes`` (one
    letter per dimension; ``Z`` depth and ``X`` required, ``Y`` optional, others such as ``T`` are
    batch). ``pitch_um``: ``{"z": .., "x": .., ["y": ..]}`` (µm per pixel, z in the medium).
    ``system``: an :class:`~torchdoct.sim.config.OCTSystem` or a dict with the original
    ``lateral_resolution_um`` (1/e² width) and ``axial_resolution_um`` (FWHM). Targets ``None`` keep
    the original. Lateral: Gaussian σ'_x on each en-face plane (Y and X; X only without Y); axial:
    spectral window σ_s along Z. ``axial_center``, ``edge_mode``, ``normalization``: see the module
    docstring. Returns the same type, dtype and device as the input (the input itself when nothing
    changes). Intensity (real) data raise ``TypeError``: a resolution change needs the complex field.
    """
    is_numpy = not isinstance(field, torch.Tensor)
    x = _as_tensor(field)
    if not x.is_complex():
        raise TypeError(
            "resolution reduction needs the complex OCT field (complex64/complex128); intensity-only "
            f"data (dtype {x.dtype}, e.g. a TIFF stack) allow only the original resolution"
        )
    axes = _check_axes(axes, x.ndim)
    if edge_mode not in EDGE_MODES:
        raise ValueError(f"edge_mode must be one of {', '.join(EDGE_MODES)}; got {edge_mode!r}")
    _gain(normalization, 1.0)
    lat0 = _system_value(system, "lateral_resolution_um")
    ax0 = _system_value(system, "axial_resolution_um")
    sig_lat = 0.0 if lateral_resolution_um is None else lateral_filter_sigma_um(lat0, float(lateral_resolution_um))
    sig_ax = 0.0 if axial_resolution_um is None else axial_filter_sigma_um(ax0, float(axial_resolution_um))
    if sig_lat == 0.0 and sig_ax == 0.0:
        return field
    pitch = {str(k).lower(): float(v) for k, v in dict(pitch_um).items()}
    need = (["z"] if sig_ax else []) + ([c.lower() for c in "YX" if c in axes] if sig_lat else [])
    for c in need:
        if c not in pitch or not (math.isfinite(pitch[c]) and pitch[c] > 0):
            raise ValueError(
                f"pitch_um needs a positive {c!r} entry (µm per pixel) for this reduction; got {pitch_um!r}"
            )
    for c in need:
        _check_kernel_bound(sig_ax if c == "z" else sig_lat, pitch[c], x.shape[axes.index(c.upper())], c)
    y = x
    if sig_ax:
        if isinstance(axial_center, str):
            if axial_center == "zero":
                fc = 0.0
            elif axial_center == "centroid":
                fc = depth_spectrum_center(x, axes=axes)
            else:
                raise ValueError(
                    f"axial_center must be 'zero', 'centroid' or a number (cycles/pixel); got {axial_center!r}"
                )
        else:
            fc = float(axial_center)
            if not (math.isfinite(fc) and -0.5 <= fc <= 0.5):
                raise ValueError(f"axial_center must be within [-0.5, 0.5] cycles/pixel; got {axial_center!r}")
        ratio = amplitude_sigma_axial_um(float(axial_resolution_um)) / amplitude_sigma_axial_um(ax0)
        y = gaussian_filter_axis(
            y,
            axes.index("Z"),
            sig_ax / pitch["z"],
            gain=_gain(normalization, ratio),
            center_cycles_per_px=fc,
            edge_mode=edge_mode,
        )
    if sig_lat:
        ratio = amplitude_sigma_lateral_um(float(lateral_resolution_um)) / amplitude_sigma_lateral_um(lat0)
        g = _gain(normalization, ratio)
        for c in "YX":
            if c in axes:
                y = gaussian_filter_axis(y, axes.index(c), sig_lat / pitch[c.lower()], gain=g, edge_mode=edge_mode)
    if is_numpy:
        return y.numpy()
    return y

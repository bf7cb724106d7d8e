"""Speckle-motion features: where the speckle pattern of a window goes between frames.

One pixel's intensity cannot tell slow flow from slow random-ballistic motion when no static tissue
shares the PSF; the speckle *pattern* can. A coherent translation by ``d = v·τ`` carries the pattern
along: for a uniform medium and any PSF, ``E(r, t + τ) = E(r − d, t)·exp(i·2kn·d_z)``, so the intensity
cross-correlation between a pixel at ``t`` and its neighbours at ``t + τ`` peaks at the in-plane offset
``d⊥ = v⊥·τ``; under direction-symmetric motion (random ballistic, diffusion) it stays centred
(symmetric under ``Δ → −Δ``) and only decays. The derivation, the expected value of every feature
and the estimator's variance over a window are in ``docs/concepts/speckle-motion.md``.

Estimator (one window ``W`` of ``w`` pixels per spatial axis, centred on each pixel; lags ``m``
frames, ``τ = m·Δt``; offsets ``Δ`` on the grid ``{−R..R}`` pixels per axis)::

    Ĉ(Δ, m)   = ⟨I(r, i)·I(r+Δ, i+m)⟩ / (⟨I(r, i)⟩·⟨I(r+Δ, i+m)⟩) − 1
    V̂         = ⟨I(r, i)²⟩ / ⟨I(r, i)⟩² − 1
    ρ̂(Δ, m)   = Ĉ(Δ, m) / V̂

where the average of the product runs over the ``T − m`` frame pairs ``(i, i + m)`` of every valid pixel
``r`` of the window whose partner ``r + Δ`` is valid, ``⟨I(r, i)⟩`` over the first ``T − m`` frames of the
window's valid pixels, ``⟨I(r+Δ, i+m)⟩`` over the last ``T − m`` frames of the valid pixels of the window
moved by ``Δ``, and those of V̂ over every frame of every valid pixel of the window. Ĉ is the normalised intensity cross-covariance ``g2(Δ, τ) − 1``, whose expectation is
``|g1(Δ, τ)|² + j(Δ, τ)/N_eff`` (physics.md §5.4 with the offset; V̂ → ``1 + 1/N_eff``). No per-pixel
temporal mean is removed: it would subtract the trajectory-averaged pattern and push the peak of a
slow translation outward (derivation, §5).

Features, named by a string (lag ``m`` in frames; axis letters ``z`` depth, positive deeper, ``x`` the
B-scan's lateral axis, ``y`` the slow axis of a volume, positive towards increasing index):

* ``xc_centre_{m}`` (1): ``ρ̂(0, m)``, the window's pooled autocorrelation at lag ``m`` (the centred decay).
* ``xc_peak_{m}`` (1): the largest ``ρ̂(Δ, m)`` over the offset grid (the correlation that the moving
  pattern keeps where it went; flow in the plane keeps 1).
* ``xc_share_{m}`` (1): the antisymmetric (moving) share ``Σ_Δ (ρ̂(Δ) − ρ̂(−Δ))² / (2·Σ_Δ ρ̂(Δ)²)`` over the
  offsets ``Δ ≠ 0`` of the grid, in [0, 1]; expectation 0 for any direction-symmetric motion.
* ``xc_asym_{m}`` (1): the size of that antisymmetric part in correlation units, the root mean square of
  ``(ρ̂(Δ) − ρ̂(−Δ))/2`` over the offsets ``Δ ≠ 0``: a flow keeps it of order ``ρ̂_peak·p·|d|/s²`` while its
  pattern stays correlated; under direction-symmetric motion it is the estimator's noise, which (unlike
  the share, a ratio that noise alone brings near 1/2 once the correlation has decayed) stays small.
* ``xc_shift_{c}_{m}`` (µm): the sub-pixel peak offset along axis ``c``: the grid maximum refined by a
  three-point Gaussian (log-parabola) fit along each axis (a parabola when a value is ≤ 0), times the
  pitch. Positive: the pattern moved towards increasing index.
* ``xc_shift_{m}`` (µm): the in-plane length ``|d̂⊥(m)|`` of that vector.
* ``xc_velocity_{c}`` (µm/s): the least-squares slope through the origin of ``d̂_c(m)`` against ``τ_m``
  over the lags (``Σ τ·d̂ / Σ τ²``; the offset is 0 at ``τ = 0`` exactly). The sign convention is that of
  the displacement of the scatterers: ``+z`` deeper (the Doppler phase ``−2kn·v_z·τ`` of
  :mod:`torchdoct.sim.signature`), ``+x``/``+y`` towards increasing column / B-scan index.
* ``xc_speed`` (µm/s): the length of the in-plane velocity vector.
* ``xcd_{kind}_{m}`` (``kind`` one of the per-lag kinds above): the same feature of the *dynamic field*, the
  complex field less its temporal mean at each pixel, ``D(r, i) = E(r, i) − (1/T)·Σ_j E(r, j)``. A static
  population's field is its temporal mean, so it leaves ``D`` whole: its centred, undecaying correlation no
  longer holds the peak at the centre, and a flow inside static tissue shows its offset
  (docs/concepts/speckle-motion.md §3 (f)). Complex input only (an intensity has no field to subtract).

Every feature is invariant to the scale of the field (a gain or a reflectivity common to the window;
a reflectivity that varies inside the window raises V̂ and Ĉ like extra speckle contrast). Pixels whose intensity is 0 or not finite at some frame
are invalid: they enter no sum and get NaN themselves; a window without a valid pair gives NaN. Windows are cut at the edges of
the array (the sums run over the pixels inside). The input is an intensity ``I`` (real, ≥ 0) or a complex
field (``I = |E|²``); frames come before the spatial axes: ``[..., T, Z, X]`` for B-scans,
``[..., T, Y, Z, X]`` for volumes (``ndim=3``).

The names, units and halo import only the standard library (the torch-free classify path reads them).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

__all__ = [
    "UNITS",
    "DEFAULT_LAGS",
    "DEFAULT_WINDOW",
    "DEFAULT_MAX_OFFSET",
    "SPATIAL_AXES",
    "parse_speckle_feature",
    "is_speckle_feature",
    "speckle_feature_unit",
    "speckle_features",
    "dynamic_speckle_features",
    "is_dynamic_feature",
    "default_lags",
    "default_speckle_features",
    "map_speckle_features",
    "halo_pixels",
    "speckle_motion",
]

#: Lags (frames) of the default features, for the paper's 32-frame protocol (delays 0.4-3.3 s at 204.8 ms).
DEFAULT_LAGS = (2, 4, 8, 16)
#: Default window (pixels per spatial axis, odd).
DEFAULT_WINDOW = 9
#: Default largest offset (pixels per axis) of the cross-correlation grid.
DEFAULT_MAX_OFFSET = 2
#: Spatial axis letters of B-scans (2) and volumes (3), in array order after the frames.
SPATIAL_AXES = {2: "zx", 3: "yzx"}

_PATTERN = re.compile(r"^xcd?_(centre|peak|share|asym|shift|shift_[xyz])_([1-9][0-9]*)$")
#: The name prefix of the features of the dynamic field (module docstring).
DYNAMIC_PREFIX = "xcd_"
_VEL = re.compile(r"^xc_velocity_([xyz])$")
#: Unit of every feature kind.
UNITS = {
    "centre": "1",
    "peak": "1",
    "share": "1",
    "asym": "1",
    "shift": "um",
    "shift_x": "um",
    "shift_y": "um",
    "shift_z": "um",
    "velocity": "um/s",
    "speed": "um/s",
}


def parse_speckle_feature(name: str) -> tuple[str, str | None, int]:
    """``(kind, axis, lag)`` of a speckle feature name (axis ``None`` when it has none, lag 0 for the
    velocity features); ``ValueError`` if it is not one (module docstring)."""
    name = str(name)
    if name == "xc_speed":
        return "speed", None, 0
    m = _VEL.match(name)
    if m:
        return "velocity", m.group(1), 0
    m = _PATTERN.match(name)
    if m is None:
        raise ValueError(
            f"unknown speckle feature {name!r}: use xc_centre_M, xc_peak_M, xc_share_M, xc_asym_M, xc_shift_M, "
            "xc_shift_{z,x,y}_M (M = lag in frames >= 1), xc_velocity_{z,x,y} or xc_speed, or a per-lag one "
            "of the dynamic field, xcd_centre_M ... xcd_shift_{z,x,y}_M"
        )
    kind = m.group(1)
    axis = kind[-1] if kind.startswith("shift_") else None
    return ("shift" if axis else kind), axis, int(m.group(2))


def is_speckle_feature(name: str) -> bool:
    """True when ``name`` is a speckle-motion feature (it needs a window of pixels, not one pixel)."""
    try:
        parse_speckle_feature(name)
    except ValueError:
        return False
    return True


def is_dynamic_feature(name: str) -> bool:
    """True when ``name`` is a speckle feature of the dynamic field (``xcd_…``, module docstring)."""
    return str(name).startswith(DYNAMIC_PREFIX) and is_speckle_feature(name)


def speckle_feature_unit(name: str) -> str:
    """Unit string of a speckle feature (``"1"``, ``"um"`` or ``"um/s"``)."""
    return UNITS[parse_speckle_feature(name)[0]]


def default_lags(n_frames: int = 32) -> tuple[int, ...]:
    """:data:`DEFAULT_LAGS` (chosen for 32 frames) placed on an acquisition of ``n_frames``: lag ``m`` becomes
    ``max(1, round(m·T/32))``, kept strictly increasing and at most ``T − 2`` (32 frames: the defaults)."""
    out: list[int] = []
    for m in DEFAULT_LAGS:
        lag = max(1, int(math.floor(m * int(n_frames) / 32 + 0.5)))
        if out and lag <= out[-1]:
            lag = out[-1] + 1
        if lag <= int(n_frames) - 2:
            out.append(lag)
    return tuple(out)


def default_speckle_features(
    ndim: int = 2, lags: Sequence[int] | None = None, *, n_frames: int = 32
) -> tuple[str, ...]:
    """The default features of a B-scan (``ndim = 2``) or a volume (``ndim = 3``): per lag the centred
    value, the peak, the moving share, the antisymmetric amplitude and the shift length; then the speed.
    ``lags``: default :func:`default_lags` of ``n_frames``."""
    lags = default_lags(n_frames) if lags is None else tuple(lags)
    if ndim not in SPATIAL_AXES:
        raise ValueError(f"speckle features need 2 (Z, X) or 3 (Y, Z, X) spatial axes; got {ndim}")
    per_lag = tuple(f"xc_{k}_{m}" for m in lags for k in ("centre", "peak", "share", "asym", "shift"))
    return per_lag + ("xc_speed",)


def map_speckle_features(
    ndim: int = 2, lags: Sequence[int] | None = None, *, n_frames: int = 32, dynamic: bool = False
) -> tuple[str, ...]:
    """The channels ``torchdoct maps --speckle`` writes: :func:`default_speckle_features`, then the signed
    shift per axis and lag (``xc_shift_{c}_m``, what the classifier's rule of a held pattern that moved reads:
    the offset's path, not only its length); with ``dynamic`` (``--speckle-dynamic``), then
    :func:`dynamic_speckle_features`."""
    lags = default_lags(n_frames) if lags is None else tuple(lags)
    out = default_speckle_features(ndim, lags) + tuple(f"xc_shift_{c}_{m}" for m in lags for c in SPATIAL_AXES[ndim])
    return out + (dynamic_speckle_features(ndim, lags) if dynamic else ())


def speckle_features(ndim: int = 2, lags: Sequence[int] | None = None, *, n_frames: int = 32) -> tuple[str, ...]:
    """Every feature of ``lags`` (default :func:`default_lags` of ``n_frames``) for ``ndim`` spatial axes: the
    defaults, the signed shift per axis and lag, and the velocity per axis."""
    lags = default_lags(n_frames) if lags is None else tuple(lags)
    axes = SPATIAL_AXES[ndim]
    return (
        default_speckle_features(ndim, lags)
        + tuple(f"xc_shift_{c}_{m}" for m in lags for c in axes)
        + tuple(f"xc_velocity_{c}" for c in axes)
    )


def dynamic_speckle_features(
    ndim: int = 2, lags: Sequence[int] | None = None, *, n_frames: int = 32
) -> tuple[str, ...]:
    """The features of the dynamic field that ``torchdoct maps --speckle-dynamic`` adds (module docstring): per
    lag the centred value, the peak and the signed shift per axis, what the classifier's rules of coherent
    motion and of a held pattern that moved read (docs/abstention.md, rules 0 and 5)."""
    lags = default_lags(n_frames) if lags is None else tuple(lags)
    if ndim not in SPATIAL_AXES:
        raise ValueError(f"speckle features need 2 (Z, X) or 3 (Y, Z, X) spatial axes; got {ndim}")
    return tuple(
        f"{DYNAMIC_PREFIX}{k}_{m}"
        for m in lags
        for k in ("centre", "peak", *(f"shift_{c}" for c in SPATIAL_AXES[ndim]))
    )


def halo_pixels(window: int = DEFAULT_WINDOW, max_offset: int = DEFAULT_MAX_OFFSET) -> int:
    """Pixels each side of a slab that its features read beyond it (per spatial axis): ``w//2 + R``."""
    return int(window) // 2 + int(max_offset)


def _check(window: int, max_offset: int, lags: Sequence[int], n_frames: int) -> None:
    if isinstance(window, bool) or int(window) != window or window < 1 or window % 2 == 0:
        raise ValueError(f"the speckle window must be an odd number of pixels >= 1; got {window!r}")
    if isinstance(max_offset, bool) or int(max_offset) != max_offset or max_offset < 1:
        raise ValueError(f"the speckle offset grid needs max_offset >= 1 pixel; got {max_offset!r}")
    for m in lags:
        if int(m) != m or m < 1 or m > n_frames - 2:
            raise ValueError(f"speckle lag {m!r} needs 1 <= lag <= T - 2 = {n_frames - 2} frames")


def _box_mean_sum(x: torch.Tensor, window: int) -> torch.Tensor:
    """Sum of ``x [B, *S]`` over the ``window``-wide box around every pixel (zeros outside the array): a
    difference of cumulative sums along each spatial axis (float64; cost independent of the window)."""
    import torch.nn.functional as F

    h = window // 2
    sizes = x.shape[1:]
    return _box_sums_of_padded(F.pad(x, [h + 1, h] * (x.dim() - 1)), window, sizes)


def _box_sums_of_padded(x: torch.Tensor, window: int, sizes: Sequence[int]) -> torch.Tensor:
    """:func:`_box_mean_sum` of an array already padded by ``window//2 + 1`` before and ``window//2`` after
    each spatial axis (``sizes`` the unpadded ones): a difference of cumulative sums per axis."""
    for ax, n in enumerate(sizes, start=1):
        c = x.cumsum(ax)
        x = c.narrow(ax, window, n) - c.narrow(ax, 0, n)
    return x


def _shifted(x: torch.Tensor, offset: Sequence[int]) -> torch.Tensor:
    """``y[..., r] = x[..., r + offset]`` over the trailing ``len(offset)`` axes, 0 outside the array."""
    import torch

    y = torch.zeros_like(x)
    nd = len(offset)
    dst = [slice(None)] * (x.dim() - nd)
    src = list(dst)
    for o, n in zip(offset, x.shape[-nd:]):
        dst.append(slice(max(0, -o), min(n, n - o)))
        src.append(slice(max(0, o), min(n, n + o)))
    y[tuple(dst)] = x[tuple(src)]
    return y


def _lagged_box_sum(
    head: torch.Tensor, tail: torch.Tensor, offset: Sequence[int], window: int, buf: torch.Tensor, weight=None
) -> torch.Tensor:
    """``Σ_{u in the window of r} Σ_i head[:, i, u]·tail[:, i, u + offset]`` (``[B, T', *S]`` → float64
    ``[B, *S]``), the pairs with ``u + offset`` outside the array left out, each product times ``weight[:, u]``
    when given. The frame sum runs frame by frame in the data's precision (one pass over each frame, no
    ``[T', ...]`` product), the box sum in float64 on ``buf``: a scratch ``[B, *(S + window)]`` float64
    array (zeroed here) that holds the products with the box sum's zeros around them
    (:func:`_box_mean_sum`'s sums, without its padded copies)."""
    nd = len(offset)
    h = window // 2
    dst: list = [slice(None)]
    src: list = [slice(None)]
    for o, n in zip(offset, head.shape[-nd:]):
        dst.append(slice(max(0, -o), min(n, n - o)))
        src.append(slice(max(0, o), min(n, n + o)))
    hd = head[(dst[0], slice(None), *dst[1:])]
    tl = tail[(src[0], slice(None), *src[1:])]
    acc = hd[:, 0] * tl[:, 0]
    for i in range(1, hd.shape[1]):
        acc.addcmul_(hd[:, i], tl[:, i])
    if weight is not None:
        acc = acc * weight[tuple(dst)]
    buf.zero_()
    buf[(slice(None), *(slice(h + 1 + d.start, h + 1 + d.stop) for d in dst[1:]))] = acc
    return _box_sums_of_padded(buf, window, head.shape[-nd:])


def _refine(lo: torch.Tensor, mid: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Vertex offset (in grid steps, [−1, 1]) of the peak through the three values at −1, 0, +1: the
    Gaussian (log-parabola) fit when all three are positive (exact for a Gaussian peak), else a parabola;
    0 where a neighbour is missing (NaN) or the three are equal."""
    import torch

    pos = (lo > 0) & (mid > 0) & (hi > 0)
    one = torch.ones_like(mid)
    la, lb, lc = (torch.log(torch.where(pos, v, one)) for v in (lo, mid, hi))
    a = torch.where(pos, la, lo)
    b = torch.where(pos, lb, mid)
    c = torch.where(pos, lc, hi)
    den = a - 2.0 * b + c
    ok = (den < 0) & torch.isfinite(den)
    d = torch.where(ok, (a - c) / (2.0 * torch.where(ok, den, -one)), torch.zeros_like(mid))
    return d.clamp(-1.0, 1.0)


def speckle_motion(
    x: torch.Tensor,
    pitch_um: Mapping[str, float],
    frame_interval_s: float,
    names: Sequence[str] | None = None,
    *,
    window: int = DEFAULT_WINDOW,
    max_offset: int = DEFAULT_MAX_OFFSET,
    ndim: int = 2,
    velocity_lags: Sequence[int] | None = None,
) -> tuple[tuple[str, ...], torch.Tensor]:
    """Speckle-motion features of every pixel's window (module docstring) → ``(names, [..., F, *S])``.

    ``x``: intensity (real, ≥ 0) or complex field, ``[..., T, Z, X]`` (``ndim = 2``) or
    ``[..., T, Y, Z, X]`` (``ndim = 3``), frames before the spatial axes. ``pitch_um``: the pixel pitch
    (µm) per axis letter (``z``, ``x``, and ``y`` for volumes). ``frame_interval_s``: the uniform frame
    interval (s). ``names``: the features in output order (default :func:`default_speckle_features`).
    ``window``: pixels per spatial axis (odd), centred on each pixel; ``max_offset``: ``R``, the offset grid
    ``{−R..R}`` per axis; ``velocity_lags``: the lags of the velocity fit (``xc_velocity_*``,
    ``xc_speed``; default :func:`default_lags` of the frame count). ``names`` default:
    :func:`default_speckle_features` of the frame count. A pixel that is itself invalid (``I = 0`` or not finite at some frame) gets NaN. Output in float64 for float64/complex128 input, else float32.
    """
    import torch

    if ndim not in SPATIAL_AXES:
        raise ValueError(f"speckle features need 2 (Z, X) or 3 (Y, Z, X) spatial axes; got ndim={ndim!r}")
    if x.dim() < ndim + 1:
        raise ValueError(
            f"speckle features need an array [..., T, {', '.join(SPATIAL_AXES[ndim].upper())}]; got "
            f"shape {tuple(x.shape)}"
        )
    axes = SPATIAL_AXES[ndim]
    n_t = x.shape[-ndim - 1]
    names = tuple(names) if names is not None else default_speckle_features(ndim, n_frames=n_t)
    if not names or len(set(names)) != len(names):
        raise ValueError(f"give each speckle feature once (at least one); got {list(names)}")
    parsed = [parse_speckle_feature(n) for n in names]
    for n, (_kind, ax, _) in zip(names, parsed):
        if ax is not None and ax not in axes:
            raise ValueError(
                f"speckle feature {n!r}: a {'volume' if ax == 'y' else 'B-scan'} has no axis {ax!r} "
                f"(axes {', '.join(axes)})"
            )
    dyn = [n for n in names if n.startswith(DYNAMIC_PREFIX)]
    if dyn:
        if not x.is_complex():
            raise ValueError(
                f"speckle features of the dynamic field ({', '.join(dyn)}) need the complex field: an intensity "
                "has no temporal mean field to subtract"
            )
        plain = [n for n in names if not n.startswith(DYNAMIC_PREFIX)]
        kw = dict(window=window, max_offset=max_offset, ndim=ndim, velocity_lags=velocity_lags)
        # the temporal mean summed in double precision, one copy of the field: a static pixel's dynamic field is
        # its rounding at most (exactly 0, an invalid pixel, when its field is constant), not a pattern
        d = x - x.mean(-ndim - 1, keepdim=True, dtype=torch.complex128).to(x.dtype)
        _, fd = speckle_motion(d, pitch_um, frame_interval_s, ["xc_" + n[len(DYNAMIC_PREFIX) :] for n in dyn], **kw)
        cols = dict(zip(dyn, fd.unbind(-ndim - 1)))
        if plain:
            _, fp = speckle_motion(x, pitch_um, frame_interval_s, plain, **kw)
            cols.update(zip(plain, fp.unbind(-ndim - 1)))
        return names, torch.stack([cols[n] for n in names], -ndim - 1)
    vlags = tuple(int(m) for m in (default_lags(n_t) if velocity_lags is None else velocity_lags))
    if not vlags:
        raise ValueError("velocity_lags needs at least one lag")
    lags = sorted(
        {m for _, _, m in parsed if m > 0}
        | (set(vlags) if any(k in ("velocity", "speed") for k, _, _ in parsed) else set())
    )
    _check(window, max_offset, lags, n_t)
    try:
        pitch = [float(pitch_um[c]) for c in axes]
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            f"speckle features need the pixel pitch (µm) of the axes {', '.join(axes)}; got {pitch_um!r}"
        ) from None
    if not all(p > 0 and math.isfinite(p) for p in pitch):
        raise ValueError(f"the pixel pitch must be positive and finite (µm); got {pitch_um!r}")
    dt = float(frame_interval_s)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"the frame interval must be positive and finite (s); got {frame_interval_s!r}")

    wide = x.dtype in (torch.complex128, torch.float64)
    real = torch.float64 if wide else torch.float32
    inten = (x.real**2 + x.imag**2) if x.is_complex() else x.to(real)
    lead = inten.shape[: -ndim - 1]
    sp = inten.shape[-ndim:]
    inten = inten.reshape(-1, n_t, *sp)
    valid = (torch.isfinite(inten) & (inten > 0)).all(1)  # [B, *S]
    # frame sums in the data's precision, window sums in float64 (the correlations of long windows)
    safe = torch.where(valid[:, None], inten, torch.zeros_like(inten))
    if safe.dtype != real:
        safe = safe.to(real)
    vw = valid.to(torch.float64)
    n_pix = _box_mean_sum(vw, window)
    ok = n_pix > 0
    den_pix = torch.where(ok, n_pix, torch.ones_like(n_pix))
    m1 = _box_mean_sum(safe.mean(1, dtype=torch.float64), window) / den_pix  # ⟨I⟩ over the window and frames
    m2 = _box_mean_sum((safe * safe).mean(1, dtype=torch.float64), window) / den_pix
    var = m2 / torch.where(m1 > 0, m1 * m1, torch.ones_like(m1)) - 1.0  # V̂ = ⟨I²⟩/⟨I⟩² − 1
    var = torch.where(ok & (m1 > 0), var, torch.full_like(var, math.nan))

    rng = range(-max_offset, max_offset + 1)
    grid = [tuple(o) for o in torch.cartesian_prod(*[torch.tensor(list(rng))] * ndim).tolist()]
    centre_idx = grid.index((0,) * ndim)
    nan = torch.tensor(math.nan, dtype=torch.float64)
    per_lag: dict[int, dict[str, torch.Tensor]] = {}
    all_valid = bool(valid.all())
    pad = [max_offset, max_offset] * ndim

    def padded_box(v: torch.Tensor) -> torch.Tensor:  # box sums on the array grown by R: shifts stay exact
        import torch.nn.functional as F

        return _box_mean_sum(F.pad(v, pad), window)

    def moved(v: torch.Tensor, off: Sequence[int]) -> torch.Tensor:  # padded map at r + Δ, on the array's grid
        return v[(slice(None), *(slice(max_offset + o, max_offset + o + n) for o, n in zip(off, sp)))]

    n_part = padded_box(vw)  # valid pixels of every (shifted) window
    pairs: dict[tuple[int, ...], tuple] = {}  # per offset, the same at every lag: the pixel pairs and partners

    def offset_counts(off: tuple[int, ...]) -> tuple:
        """``(w, pairs, none)``: the pairs' weights (None when every pixel is valid: the product is already 0
        where the partner is outside the array), the window's pixel pairs (r, r + Δ) with both valid (≥ 1),
        and where there is none (None when every window has one)."""
        if off not in pairs:
            w = None if all_valid else vw * _shifted(vw, off)
            if w is None and not any(off):
                cnt = moved(n_part, off)
            else:
                cnt = _box_mean_sum(vw * _shifted(vw, off) if w is None else w, window)
            none = cnt <= 0
            pairs[off] = (w, cnt.clamp_min(1.0), none if bool(none.any()) else None)
        return pairs[off]

    buf = torch.empty(safe.shape[:1] + tuple(n + window for n in sp), dtype=torch.float64, device=safe.device)
    for m in lags:
        head, tail = safe[:, : n_t - m], safe[:, m:]
        h_mean = _box_mean_sum(head.mean(1, dtype=torch.float64), window) / den_pix  # ⟨I(r, i)⟩, i < T − m
        t_mean = padded_box(tail.mean(1, dtype=torch.float64)).div_(n_part.clamp_min(1.0))  # ⟨I(r + Δ, i + m)⟩ at r + Δ
        h_mean.mul_(n_t - m)  # the frame pairs' count, folded into the normalisation
        r = torch.empty((len(grid),) + h_mean.shape, dtype=torch.float64, device=h_mean.device)  # [G, B, *S]
        for g, off in enumerate(grid):
            w, cnt, none = offset_counts(off)
            s_ii = _lagged_box_sum(head, tail, off, window, buf, w).div_(cnt)  # (T − m)·⟨I(r, i)·I(r + Δ, i + m)⟩
            norm = moved(t_mean, off) * h_mean  # (T − m)·⟨I(r, i)⟩·⟨I(r + Δ, i + m)⟩ (finite, ≥ 0)
            bad = norm <= 0 if none is None else (norm <= 0) | none
            torch.div(s_ii, norm, out=r[g]).sub_(1.0).masked_fill_(bad, math.nan)  # Ĉ(Δ, m)
        r.div_(var)  # ρ(Δ, m)
        feats: dict[str, torch.Tensor] = {"centre": r[centre_idx]}
        filled = r.nan_to_num(nan=-math.inf, posinf=math.inf, neginf=-math.inf)
        peak, arg = filled.max(0)
        feats["peak"] = torch.where(torch.isfinite(peak), peak, nan)
        flip = [grid.index(tuple(-o for o in off)) for off in grid]
        nz = [i for i in range(len(grid)) if i != centre_idx]
        anti = torch.zeros_like(r[0])
        energy = torch.zeros_like(r[0])
        for i in nz:  # in grid order, one offset at a time: the same sums whatever the batch shape
            d = r[i] - r[flip[i]]
            anti.addcmul_(d, d)
            energy.addcmul_(r[i], r[i], value=4.0)
        feats["asym"] = torch.sqrt(anti / (4.0 * len(nz)))
        feats["share"] = torch.where(energy > 0, anti / torch.where(energy > 0, energy, torch.ones_like(energy)), nan)
        coords = torch.tensor(grid, dtype=torch.long)  # [G, ndim]
        at = coords[arg]  # [B, *S, ndim] grid offset of the peak
        shift = []
        for k in range(len(axes)):
            val = []
            for step in (-1, 0, 1):
                if step == 0:  # the peak itself (where there is none, the shift is NaN below)
                    val.append(peak)
                    continue
                nb = at.clone()
                nb[..., k] = nb[..., k] + step
                inside = (nb[..., k] >= -max_offset) & (nb[..., k] <= max_offset)
                nbc = nb.clamp(-max_offset, max_offset) + max_offset
                flat = torch.zeros_like(arg)
                for j in range(ndim):
                    flat = flat * len(rng) + nbc[..., j]
                v = torch.gather(r, 0, flat[None])[0]
                val.append(torch.where(inside, v, nan))
            frac = _refine(*val)
            shift.append((at[..., k].to(torch.float64) + frac) * pitch[k])
        for k, c in enumerate(axes):
            feats[f"shift_{c}"] = torch.where(torch.isfinite(peak), shift[k], nan)
        feats["shift"] = torch.sqrt(sum(feats[f"shift_{c}"] ** 2 for c in axes))
        per_lag[m] = feats
    vel: dict[str, torch.Tensor] = {}
    if any(k in ("velocity", "speed") for k, _, _ in parsed):
        taus = [m * dt for m in vlags]
        den = sum(t * t for t in taus)
        vel = {c: sum(t * per_lag[m][f"shift_{c}"] for t, m in zip(taus, vlags)) / den for c in axes}
        speed = torch.sqrt(sum(v**2 for v in vel.values()))
    cols = []
    for kind, ax, m in parsed:
        if kind == "velocity":
            cols.append(vel[ax])
        elif kind == "speed":
            cols.append(speed)
        elif kind == "shift" and ax is not None:
            cols.append(per_lag[m][f"shift_{ax}"])
        else:
            cols.append(per_lag[m][kind])
    out = torch.stack(cols, 1)  # [B, F, *S]
    out = torch.where(valid[:, None], out, torch.full_like(out, math.nan))
    return names, out.to(real).reshape(*lead, len(names), *sp)

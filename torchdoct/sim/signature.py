"""The decorrelation signature of a pixel: one feature extractor for simulated and measured data.

A pixel's complex time series ``E(t_i)`` (frames last, ``[..., T]``, uniform frame interval) carries
its motion in *how* it decorrelates with the delay: diffusion decorrelates exponentially in the
delay, random-ballistic motion and flow as a Gaussian (in the PSF transit) and an oscillating
phase term, and flow also turns the field's phase (physics.md §4, §5.3-5.4, §11). LIV and OCDS are
two coarse summaries of that curve; the signature keeps the curve itself at a few lags. One function,
:func:`pixel_features`, computes the training features of :mod:`classifier.dataset` (simulated fields)
and the ``--signature`` channels of ``torchdoct maps`` (measured fields and their computational
resolution reductions, slab by slab in :func:`torchdoct.measured.maps.compute_maps`), so the two cannot
drift apart. This module reads no file and imports nothing of :mod:`torchdoct.measured`.

Features, named by a string (lags ``m`` in frames, delay ``τ = m·Δt``):

* ``rho_db_{m}``: Pearson correlation of the dB intensity ``10·log10 I`` between frames ``i`` and
  ``i + m`` (all ``T − m`` pairs, each sub-sequence with its own mean; the estimator of
  :func:`torchdoct.sim.metrics.lag_correlations` and OCDS, physics.md §2.4). Unitless.
* ``rho_lin_{m}``: the same on the linear intensity ``I = |E|²``; its expectation is
  ``ρ_I(τ) = (|g1|² + j/N_eff)/(1 + 1/N_eff)`` (physics.md §5.4). Unitless.
* ``g1_{m}``: magnitude of the normalised complex field autocorrelation,
  ``|Σ_i E_i E*_{i+m}| / √(Σ_i |E_i|² · Σ_i |E_{i+m}|²)`` (sums over the ``T − m`` pairs), the
  estimate of ``|g1(τ)|`` of physics.md §5.3 (its expectation for fully decorrelated speckle is
  ``≈ √(π/(4(T−m)))``, and ``E|ĝ1|² ≈ 1/(T − m)``). In [0, 1] by Cauchy-Schwarz.
* ``g1_phase_{m}`` (rad): the argument of the same sum, ``arg G(m)`` in (−π, π] with
  ``G(m) = Σ_i E_i E*_{i+m}``: with the round-trip phase ``e^{+i·2kn·z}`` a scatterer moving deeper at
  ``v_z`` gives ``G ∝ exp(−i·2kn·v_z·τ)`` (physics.md §5.3 (c), :func:`torchdoct.sim.theory.g1_flow`), so
  ``g1_phase_m = −2kn·v_z·m·Δt`` wrapped; a field ``E_i = exp(i·ω·t_i)`` gives ``−ω·m·Δt`` wrapped.
  ``g1_m·exp(i·g1_phase_m)`` is the complex ``ĝ1(m·Δt)``. NaN where ``G(m) = 0`` (no defined angle).
* ``phase_ramp``: ``cos(arg G(2) − 2·arg G(1))`` with ``G(m) = Σ_i E_i E*_{i+m}``: 1 when the field's
  phase turns at a constant rate (flow's Doppler term ``exp(−i·2k·v_z·τ)``, physics.md §5.3 (c)),
  random for diffusion and random-ballistic motion. Unitless.
* ``lin_contrast``: temporal intensity contrast ``Var_t I / (mean_t I)²`` (ddof 0; physics.md §5.4:
  ``1 + 1/N_eff`` for fully developed moving speckle). Unitless.
* ``db_variance`` (dB²): ddof-0 variance of the dB intensity over the frames (= LIV, physics.md §1).

Every feature is invariant to the scale of the field (a gain or a reflectivity factor), as the
physics says the shape of the decorrelation is. **Bulk phase**: a phase ``φ_i`` common to all
scatterers of the pixel at frame ``i`` (bulk motion of the sample between frames) leaves every
intensity feature (``rho_db``, ``rho_lin``, ``lin_contrast``, ``db_variance``) exactly unchanged;
``g1_m`` and ``phase_ramp`` are unchanged by a *linear* drift (``g1_phase_m`` shifts by ``−ω·m·Δt``) ``φ_i = ω·t_i`` (a constant bulk
velocity), but no per-pixel statistic of the field survives an arbitrary phase per frame: the
field group then measures the bulk phase, not the pixel (so models that use it need phase-stable
or bulk-phase-corrected data; ``research/classifier-history.md`` reports the accuracy with a random bulk
phase per frame). Intensity-only data (e.g. TIFF intensities) give only the intensity group
(:func:`available_features`).

The names, units and defaults import only the standard library (the torch-free classify path
reads them); :func:`signature` and :func:`pixel_features` import torch.

Undefined values are NaN: a pixel with ``I = 0`` (or NaN) at some frame has no dB value and gets
NaN in every feature; a lag whose two sub-sequences are both constant has correlation 1 and one
constant against a varying one 0 (the rules of :mod:`torchdoct.sim.metrics`).

:data:`DEFAULT_FEATURES` is the content chosen by the ablation in ``research/classifier-history.md``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names and units below are read without torch by the classify path
    import torch

__all__ = [
    "UNITS",
    "DEFAULT_DB_LAGS",
    "DEFAULT_LINEAR_LAGS",
    "DEFAULT_FIELD_LAGS",
    "DEFAULT_FEATURES",
    "FIELD_FEATURES",
    "feature_unit",
    "needs_field",
    "available_features",
    "default_features",
    "signature_lags",
    "REFERENCE_FRAMES",
    "parse_feature",
    "signature",
    "pixel_features",
]

_PATTERN = re.compile(r"^(rho_db|rho_lin|g1|g1_phase)_([1-9][0-9]*)$")
_SCALARS = {"phase_ramp": "1", "lin_contrast": "1", "db_variance": "dB^2"}
#: Unit of every feature kind (the maps format's unit strings).
UNITS = {"rho_db": "1", "rho_lin": "1", "g1": "1", "g1_phase": "rad", **_SCALARS}
#: Kinds that need the complex field (phase); the others need only the intensity.
FIELD_FEATURES = ("g1", "g1_phase", "phase_ramp")
#: Default lags (frames) of each group, chosen by the ablation in research/classifier-history.md: the linear
#: intensity correlation at roughly log-spaced lags plus the two one-time statistics carry all that
#: the dB correlations add (no dB lags), and ``|g1|`` at the first lags (the field part) adds a little
#: on phase-stable data but nothing under a bulk phase drift.
DEFAULT_DB_LAGS: tuple[int, ...] = ()
DEFAULT_LINEAR_LAGS = (1, 2, 3, 4, 6, 8, 11, 16, 22, 28)
DEFAULT_FIELD_LAGS = (1, 2, 3, 4, 6, 8)
#: The default signature for the paper's protocol (32 frames), as ``torchdoct maps --signature``
#: writes it: names, in order (intensity part first, then the field part).
DEFAULT_FEATURES = (
    tuple(f"rho_db_{m}" for m in DEFAULT_DB_LAGS)
    + tuple(f"rho_lin_{m}" for m in DEFAULT_LINEAR_LAGS)
    + ("lin_contrast", "db_variance")
    + tuple(f"g1_{m}" for m in DEFAULT_FIELD_LAGS)
)


def parse_feature(name: str) -> tuple[str, int]:
    """``(kind, lag)`` of a feature name (lag 0 for the scalar features); ``ValueError`` if unknown."""
    if name in _SCALARS:
        return name, 0
    m = _PATTERN.match(str(name))
    if m is None:
        raise ValueError(
            f"unknown signature feature {name!r}: use rho_db_M, rho_lin_M, g1_M, g1_phase_M (M = lag "
            f"in frames >= 1) or {', '.join(_SCALARS)}"
        )
    return m.group(1), int(m.group(2))


def feature_unit(name: str) -> str:
    """Unit string of a feature (``"1"``, ``"rad"`` or ``"dB^2"``)."""
    return UNITS[parse_feature(name)[0]]


def needs_field(name: str) -> bool:
    """True when the feature needs the complex field (its phase), not only the intensity."""
    return parse_feature(name)[0] in FIELD_FEATURES


def available_features(names: Sequence[str], is_complex: bool) -> tuple[str, ...]:
    """The features of ``names`` computable from complex (all) or intensity-only data."""
    return tuple(n for n in names if is_complex or not needs_field(n))


#: The protocol the default lags were chosen for (the paper's 32 frames); :func:`signature_lags` rescales them.
REFERENCE_FRAMES = 32


def signature_lags(lags: Sequence[int], n_frames: int) -> tuple[int, ...]:
    """``lags`` (frames, chosen for :data:`REFERENCE_FRAMES` frames) for a sequence of ``n_frames``.

    The lags keep their place on the acquisition: lag ``m`` becomes ``round(m·(T − 4)/28)`` for ``T``
    frames (the longest default lag, 28, stays ``T − 4``), bumped to stay strictly increasing, with lag 1
    always kept (the shortest delay the protocol resolves: the fastest identifiable motion, physics.md
    §5.3) and every lag ≤ T − 3. For 32 frames this is ``lags`` itself; for 64 frames the default
    intensity lags are 1, 2, 4, 6, 9, 13, 17, 24, 34, 47, 60; for 16 frames 1-9 and 12."""
    n = int(n_frames)
    scale = (n - 4) / (REFERENCE_FRAMES - 4)
    out: list[int] = []
    for m in lags:
        lag = max(1, int(math.floor(m * scale + 0.5)))
        if out and lag <= out[-1]:
            lag = out[-1] + 1
        if lag <= n - 3:
            out.append(lag)
    if lags and (not out or out[0] != 1) and n >= 4:
        out.insert(0, 1)
    return tuple(out)


def default_features(n_frames: int) -> tuple[str, ...]:
    """:data:`DEFAULT_FEATURES` for a sequence of ``n_frames``: every group's lags placed on the acquisition
    by :func:`signature_lags` (for 32 frames exactly :data:`DEFAULT_FEATURES`)."""
    groups = (
        (kind, signature_lags(lags, n_frames))
        for kind, lags in (("rho_db", DEFAULT_DB_LAGS), ("rho_lin", DEFAULT_LINEAR_LAGS))
    )
    intensity = tuple(f"{kind}_{m}" for kind, lags in groups for m in lags)
    return (
        intensity
        + ("lin_contrast", "db_variance")
        + tuple(f"g1_{m}" for m in signature_lags(DEFAULT_FIELD_LAGS, n_frames))
    )


def _uniform(frame_times_s: Sequence[float], n: int) -> None:
    t = [float(v) for v in frame_times_s]
    if len(t) != n:
        raise ValueError(f"signal has {n} frames but {len(t)} frame times were given")
    d = [b - a for a, b in zip(t, t[1:])]
    if not d or min(d) <= 0 or max(d) - min(d) > 1e-6 * max(d):
        raise ValueError(
            "the signature needs at least 2 frames at a uniform, increasing frame interval; "
            f"got intervals {min(d) if d else None}-{max(d) if d else None} s"
        )


def signature(
    x: torch.Tensor, frame_times_s: Sequence[float], names: Sequence[str] | None = None
) -> tuple[tuple[str, ...], torch.Tensor]:
    """Signature features of ``x [..., T]`` (module docstring) → ``(names, features [..., F])``.

    ``x``: complex field, or real non-negative intensity (then only intensity features can be
    asked for). ``frame_times_s``: the ``T`` frame times (s), uniform. ``names``: the features, in
    output order (default :func:`default_features`, limited to the intensity group for real
    input). The output has ``x``'s real dtype.
    """
    import torch

    from .metrics import _pearson, _variance_last, to_db

    n = x.shape[-1]
    _uniform(frame_times_s, n)
    is_complex = x.is_complex()
    if names is None:
        names = available_features(default_features(n), is_complex)
    names = tuple(names)
    if not names:
        raise ValueError("no signature features requested")
    parsed = [parse_feature(nm) for nm in names]
    if len(set(names)) != len(names):
        raise ValueError(f"a signature feature is requested twice: {list(names)}")
    for nm, (kind, lag) in zip(names, parsed):
        if lag > n - 3:
            raise ValueError(f"signature feature {nm!r}: lag {lag} needs at least {lag + 3} frames; got {n}")
        if kind in FIELD_FEATURES and not is_complex:
            raise ValueError(
                f"signature feature {nm!r} needs the complex field (phase); the data hold intensity "
                "only, which gives only rho_db_*, rho_lin_*, lin_contrast and db_variance"
            )
    if is_complex:
        inten = x.real**2 + x.imag**2
    else:
        inten = x
    bad = ~(inten > 0).all(-1)  # I = 0 or NaN at some frame: no dB value
    safe = torch.where(bad[..., None], torch.ones_like(inten), inten) if bool(bad.any()) else inten
    cols: dict[str, torch.Tensor] = {}
    db: torch.Tensor | None = None
    g_cache: dict[int, torch.Tensor] = {}

    def g(m: int) -> torch.Tensor:
        if m not in g_cache:
            g_cache[m] = (x[..., : n - m] * x[..., m:].conj()).sum(-1)
        return g_cache[m]

    for nm, (kind, m) in zip(names, parsed):
        if kind in ("rho_db", "db_variance") and db is None:
            db = to_db(safe)
        if kind == "rho_db":
            assert db is not None  # computed just above
            v = _pearson(db[..., : n - m], db[..., m:])
        elif kind == "rho_lin":
            v = _pearson(safe[..., : n - m], safe[..., m:])
        elif kind == "db_variance":
            assert db is not None  # computed just above
            v = _variance_last(db)
        elif kind == "lin_contrast":
            mean = safe.mean(-1)
            v = _variance_last(safe) / (mean * mean)
        elif kind == "g1":
            den = torch.sqrt(safe[..., : n - m].sum(-1) * safe[..., m:].sum(-1))
            v = g(m).abs() / den
        elif kind == "g1_phase":  # arg G(m) in (−π, π]; NaN where G(m) = 0
            gm = g(m)
            v = torch.angle(gm)
            v = torch.where(v <= -math.pi, v + 2.0 * math.pi, v)
            v = torch.where(gm.abs() > 0, v, torch.full_like(v, math.nan))
        else:  # phase_ramp
            z = g(2) * g(1).conj() ** 2
            v = torch.where(
                z.abs() > 0,
                z.real / torch.where(z.abs() > 0, z.abs(), torch.ones_like(z.real)),
                torch.zeros_like(z.real),
            )
        cols[nm] = v
    out = torch.stack([cols[nm] for nm in names], dim=-1)
    if bool(bad.any()):
        out = torch.where(bad[..., None], torch.full_like(out, math.nan), out)
    return names, out


def pixel_features(
    field: torch.Tensor, frame_times_s: Sequence[float], spec_or_names=None, *, chunk_pixels: int | None = None
) -> tuple[tuple[str, ...], torch.Tensor]:
    """The features a signature model reads from every pixel of ``field [..., T]`` → ``(names, [..., F])``.

    The one feature function of both sides: :func:`classifier.dataset.simulate_draw` (simulated fields
    ``[N, configurations, T]``) and :func:`torchdoct.measured.maps.compute_maps` (each slab of a measured
    or rendered field, after its resolution reduction and bulk-phase correction) call it, so a model
    sees the same definition in training and on maps. ``field``: complex field, or real non-negative
    intensity (intensity features only); ``frame_times_s``: the ``T`` frame times (s), uniform.
    ``spec_or_names``: the feature names (:func:`parse_feature`), or a feature specification naming them
    in its ``metrics`` (a signature spec of :mod:`classifier.features`), or ``None`` for
    :func:`default_features` (their intensity part for real input). ``chunk_pixels``: at most that many
    pixels per :func:`signature` call (the leading dimensions flattened; memory only), ``None`` for one
    call. The features (module docstring) are those of :func:`signature`, in the field's real dtype.
    """
    names = getattr(spec_or_names, "metrics", spec_or_names)
    if names is not None:
        names = tuple(names)
    if chunk_pixels is None:
        return signature(field, frame_times_s, names=names)
    import torch

    if int(chunk_pixels) < 1:
        raise ValueError(f"chunk_pixels must be a positive integer; got {chunk_pixels!r}")
    n = field.shape[-1]
    flat = field.reshape(-1, n)
    lead = field.shape[:-1]
    names, first = signature(flat[:chunk_pixels], frame_times_s, names=names)
    if flat.shape[0] <= chunk_pixels:
        return names, first.reshape(*lead, len(names))
    out = torch.empty(flat.shape[0], len(names), dtype=first.dtype, device=first.device)
    out[:chunk_pixels] = first
    for p0 in range(chunk_pixels, flat.shape[0], chunk_pixels):
        out[p0 : p0 + chunk_pixels] = signature(flat[p0 : p0 + chunk_pixels], frame_times_s, names=names)[1]
    return names, out.reshape(*lead, len(names))

"""DOCT metrics on any ``[..., frames]`` tensor: a point sequence or a whole map.

Definitions (physics.md §1, §2.4; intensity ``I = |E|²``, dB = ``10·log10 I``):

* **LIV** (dB²): population variance (ddof 0) over frames of ``10·log10 I``.
* **lag correlation** ``ρ(τ)``: for each distinct frame delay ``τ``, the Pearson correlation of
  the signal over all frame pairs ``(i, j)`` with ``t_j − t_i = τ`` (``{s_i}`` against ``{s_j}``, each
  with its own mean), on the dB (default) or linear intensity. ``estimator="biased"`` instead
  divides the lagged products of the mean-removed sequence by ``N`` times its variance (the
  ``scipy.signal.correlate`` form, which shrinks ``ρ_m`` by about ``1 − m/N``).
* **OCDS** (s⁻¹): minus the least-squares slope of ``ρ(τ)`` against ``τ`` over the delays in
  ``delay_range_s`` (default [0.2048, 1.2288] s, i.e. lags 1-6 at 204.8 ms); positive for a decaying
  correlation.
* **complex variance**: ``mean_t |E − mean_t E|²`` (ddof 0, linear intensity units).

Degenerate inputs are defined, never NaN: a constant sequence has LIV exactly 0; a lag whose two
sub-sequences are both constant has ``ρ = 1`` (nothing decorrelates), and ``ρ = 0`` if only one is
constant (the biased estimator also gives 1 for a constant sequence). Intensities of exactly 0 (an empty resolution volume) have no dB value: :func:`to_db`
maps them to −inf and :func:`compute_metrics` reports those trials (``zero_intensity``) and sets
their dB metrics to NaN explicitly, so summaries exclude and count them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from ..conventions import delay_groups, delay_range_tolerance_s
from ..conventions import uniform_frame_interval_s as _uniform_interval

__all__ = [
    "to_db",
    "liv",
    "lag_correlations",
    "ocds",
    "ocds_from_correlations",
    "uniform_frame_interval_s",
    "complex_variance",
    "compute_metrics",
    "summarize",
]


def to_db(intensity: torch.Tensor) -> torch.Tensor:
    """``10·log10 I`` (dB of linear intensity)."""
    return 10.0 * torch.log10(intensity)


def _variance_last(x: torch.Tensor) -> torch.Tensor:
    """ddof-0 variance along the last axis, shifted by the first sample (exact 0 for constants)."""
    d = x - x[..., :1]
    m = d.mean(-1, keepdim=True)
    return ((d - m) ** 2).mean(-1)


def _check_intensity(func: str, intensity: Any, min_frames: int = 1) -> None:
    """Refuse, naming the argument, what is not a real tensor of intensities ``[..., frames]``: a complex
    field (its dB would be complex "variances"; pass ``field.abs() ** 2``, i.e. ``|E|²``), a number or
    another type, a tensor without a frames axis or with fewer than ``min_frames`` frames."""
    if not isinstance(intensity, torch.Tensor):
        raise TypeError(
            f"{func}(intensity): intensity must be a torch.Tensor of linear intensities [..., frames]; "
            f"got {type(intensity).__name__}"
            + (" (one number has no frames)" if isinstance(intensity, (int, float)) else " (use torch.as_tensor)")
        )
    if intensity.is_complex():
        raise TypeError(
            f"{func}(intensity): intensity must be real linear intensity I = |E|²; got a complex "
            f"{intensity.dtype} field: pass field.abs() ** 2"
        )
    if intensity.dtype == torch.bool:
        raise TypeError(f"{func}(intensity): intensity must be linear intensities; got a bool tensor (a mask?)")
    if intensity.ndim == 0:
        raise ValueError(
            f"{func}(intensity): intensity is a 0-dimensional tensor; it needs a frames axis (the last) [..., frames]"
        )
    if intensity.shape[-1] < min_frames:
        raise ValueError(
            f"{func}(intensity): {intensity.shape[-1]} frame(s) on the last axis (shape "
            f"{list(intensity.shape)}); {func} needs at least {min_frames}"
        )


def liv(intensity: torch.Tensor) -> torch.Tensor:
    """LIV (dB²): ddof-0 variance over the last axis (frames) of ``10·log10 I`` (physics.md §1)."""
    _check_intensity("liv", intensity, min_frames=2)  # the variance of one frame is 0 whatever the data
    return _variance_last(to_db(intensity))


def _delays(frame_times_s: Sequence[float]) -> tuple[list[float], list[tuple[list[int], list[int]]]]:
    """Distinct delays (s, :func:`torchdoct.conventions.delay_groups`) and, for each, the frame index pairs
    (i, j>i)."""
    groups = delay_groups(frame_times_s)
    return [d for d, _ in groups], [([i for i, _ in ij], [j for _, j in ij]) for _, ij in groups]


def _pearson(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    ref = x[..., :1]
    xd = x - ref
    yd = y - ref
    xm = xd - xd.mean(-1, keepdim=True)
    ym = yd - yd.mean(-1, keepdim=True)
    vx = (xm * xm).mean(-1)
    vy = (ym * ym).mean(-1)
    cov = (xm * ym).mean(-1)
    den = torch.sqrt(vx * vy)
    both_const = (vx == 0) & (vy == 0)
    rho = torch.where(den > 0, cov / torch.where(den > 0, den, torch.ones_like(den)), torch.zeros_like(den))
    return torch.where(both_const, torch.ones_like(rho), rho)


def lag_correlations(
    signal: torch.Tensor, frame_times_s: Sequence[float], *, estimator: str = "pearson"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Correlation coefficient against delay for real sequences ``[..., frames]``.

    Returns ``(delays_s [L], rho [..., L])``; see the module docstring for the estimators.
    """
    if signal.shape[-1] != len(frame_times_s):
        raise ValueError(f"signal has {signal.shape[-1]} frames but {len(frame_times_s)} frame times were given")
    if signal.is_complex():
        raise TypeError("lag_correlations takes a real signal (dB or linear intensity)")
    delays, pairs = _delays(frame_times_s)
    cols = []
    if estimator == "pearson":
        for i, j in pairs:
            ii = torch.tensor(i, device=signal.device)
            jj = torch.tensor(j, device=signal.device)
            cols.append(_pearson(signal.index_select(-1, ii), signal.index_select(-1, jj)))
    elif estimator == "biased":
        d = signal - signal[..., :1]
        xm = d - d.mean(-1, keepdim=True)
        var = (xm * xm).sum(-1)
        for i, j in pairs:
            ii = torch.tensor(i, device=signal.device)
            jj = torch.tensor(j, device=signal.device)
            s = (xm.index_select(-1, ii) * xm.index_select(-1, jj)).sum(-1)
            cols.append(torch.where(var > 0, s / torch.where(var > 0, var, torch.ones_like(var)), torch.ones_like(var)))
    else:
        raise ValueError(f"estimator must be 'pearson' or 'biased'; got {estimator!r}")
    return torch.tensor(delays, dtype=signal.dtype, device=signal.device), torch.stack(cols, dim=-1)


def ocds_from_correlations(
    rho: torch.Tensor,
    delays_s: torch.Tensor,
    delay_range_s: tuple[float, float] = (0.2048, 1.2288),
    *,
    tolerance_s: float | None = None,
) -> torch.Tensor:
    """OCDS (s⁻¹) = − OLS slope of ``rho[..., L]`` against ``delays_s`` within ``delay_range_s``, its ends
    widened by ``tolerance_s`` (default: :func:`torchdoct.conventions.delay_range_tolerance_s` of the delays;
    :func:`ocds` passes the frame times' own)."""
    lo, hi = delay_range_s
    tol = delay_range_tolerance_s(delays_s.tolist(), delay_range_s) if tolerance_s is None else tolerance_s
    sel = (delays_s >= lo - tol) & (delays_s <= hi + tol)
    if int(sel.sum()) < 2:
        raise ValueError(
            f"delay range [{lo}, {hi}] s holds fewer than 2 delays of the protocol "
            f"(delays {delays_s.min().item():.6g} ... {delays_s.max().item():.6g} s)"
        )
    x = delays_s[sel]
    y = rho[..., sel]
    xc = x - x.mean()
    return -((y - y[..., :1]) * xc).sum(-1) / (xc * xc).sum()


def _time_value(v: Any) -> float:
    """``v`` as seconds when it is a real number (a Python, NumPy or 0-d torch number); a string, a bool or
    anything else is a ``TypeError`` (``"0.2"`` is not read as a time, as in the sidecars)."""
    if isinstance(v, (str, bytes, bool)) or (isinstance(v, torch.Tensor) and (v.ndim or v.is_complex())):
        raise TypeError(type(v).__name__)
    if isinstance(v, complex) or getattr(getattr(v, "dtype", None), "kind", "") == "c":
        raise TypeError(type(v).__name__)
    return float(v)


def _kinds(values: Any) -> str:
    """What ``values`` holds, for a message: its type, and the type of its first element that is no number."""
    try:
        bad = next(v for v in values if isinstance(v, (str, bytes, bool)) or not hasattr(v, "__float__"))
    except (TypeError, StopIteration):
        return type(values).__name__
    return f"{type(values).__name__} holding {type(bad).__name__} {str(bad)[:40]!r}"


def _check_delay_range(func: str, delay_range_s: Any) -> tuple[float, float]:
    """``delay_range_s`` as ``(lo, hi)``: two finite numbers of seconds, ``0 <= lo < hi``, else an error naming
    the argument."""
    try:
        lo, hi = (_time_value(v) for v in delay_range_s)
    except (TypeError, ValueError):
        raise TypeError(
            f"{func}(delay_range_s): delay_range_s must be two numbers (lo, hi) in s; got {delay_range_s!r}"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
        raise ValueError(
            f"{func}(delay_range_s): delay_range_s must be finite with 0 <= lo < hi (s); got ({lo!r}, {hi!r})"
        )
    return lo, hi


def _check_frame_times(func: str, frame_times_s: Any, n_frames: int) -> list[float]:
    """The frame times as floats (s); refuse, naming the argument, frame times that are not finite numbers
    in order (a dict or set is not), one per frame, strictly increasing."""
    from collections.abc import Mapping, Set

    try:
        if isinstance(frame_times_s, (Mapping, Set, str, bytes)):  # no order, or not numbers
            raise TypeError(type(frame_times_s).__name__)
        t = [_time_value(v) for v in frame_times_s]
    except (TypeError, ValueError):
        raise TypeError(
            f"{func}(frame_times_s): frame_times_s must be a sequence of numbers (s); got {_kinds(frame_times_s)}"
        ) from None
    if len(t) != n_frames:
        raise ValueError(
            f"{func}(frame_times_s): {len(t)} frame times for {n_frames} frames; give one time (s) per frame"
        )
    bad = next((i for i, v in enumerate(t) if not math.isfinite(v)), None)
    if bad is not None:
        raise ValueError(f"{func}(frame_times_s): frame_times_s[{bad}] = {t[bad]} is not finite")
    if t and not math.isfinite(t[-1] - t[0]):
        raise ValueError(
            f"{func}(frame_times_s): the times span {t[0]:g} to {t[-1]:g} s, beyond any float; give "
            "the times of the acquisition in s (e.g. from 0)"
        )
    back = next((i for i in range(1, len(t)) if not t[i] > t[i - 1]), None)
    if back is not None:
        raise ValueError(
            f"{func}(frame_times_s): frame times must increase strictly; frame_times_s[{back}] = "
            f"{t[back]} s is not after frame_times_s[{back - 1}] = {t[back - 1]} s"
        )
    return t


def uniform_frame_interval_s(frame_times_s: Sequence[float]) -> float | None:
    """The frame interval (s) of a uniform protocol (steps equal within the times' resolution,
    :func:`torchdoct.conventions.uniform_frame_interval_s`), else ``None``."""
    return _uniform_interval(frame_times_s)


def ocds(
    intensity: torch.Tensor,
    frame_times_s: Sequence[float],
    *,
    delay_range_s: tuple[float, float] = (0.2048, 1.2288),
    scale: str = "db",
    estimator: str = "pearson",
) -> torch.Tensor:
    """OCDS (s⁻¹) of intensities ``[..., frames]`` (physics.md §2.4; see the module docstring).

    The one OCDS of the project: the simulator's metrics (:func:`compute_metrics`) and the maps
    (:mod:`torchdoct.measured.mapmetrics`) both call it. For a uniform protocol only the lags inside
    ``delay_range_s`` are correlated (the others do not enter the slope); their values are those of
    :func:`lag_correlations`, and the slope is :func:`ocds_from_correlations`.
    """
    from .config import check_ocds_pairs

    _check_intensity("ocds", intensity, min_frames=3)
    frame_times_s = _check_frame_times("ocds", frame_times_s, intensity.shape[-1])  # a list of floats
    if scale == "db":
        s = to_db(intensity)
    elif scale == "linear":
        s = intensity
    else:
        raise ValueError(f"scale must be 'db' or 'linear'; got {scale!r}")
    delay_range_s = _check_delay_range("ocds", delay_range_s)
    check_ocds_pairs(frame_times_s, delay_range_s, "ocds(delay_range_s)")  # after the check of 2 delays
    dt = uniform_frame_interval_s(frame_times_s)
    tol = delay_range_tolerance_s(frame_times_s, delay_range_s)
    if dt is None or estimator not in ("pearson", "biased"):
        delays, rho = lag_correlations(s, frame_times_s, estimator=estimator)
        return ocds_from_correlations(rho, delays, delay_range_s, tolerance_s=tol)
    n = s.shape[-1]
    if n != len(frame_times_s):
        raise ValueError(f"signal has {n} frames but {len(frame_times_s)} frame times were given")
    lo, hi = delay_range_s
    lags = [m for m in range(1, n) if lo - tol <= m * dt <= hi + tol]
    if len(lags) < 2:
        raise ValueError(
            f"ocds(delay_range_s): delay range [{lo}, {hi}] s holds fewer than 2 delays of the protocol "
            f"(frame interval {dt:.6g} s, {n} frames); widen it to hold 2 multiples of the interval"
        )
    if estimator == "pearson":
        rho = torch.stack([_pearson(s[..., : n - m], s[..., m:]) for m in lags], dim=-1)
    else:  # biased: as lag_correlations, for the lags in the range only
        d = s - s[..., :1]
        xm = d - d.mean(-1, keepdim=True)
        var = (xm * xm).sum(-1)
        ok = var > 0
        den = torch.where(ok, var, torch.ones_like(var))
        rho = torch.stack(
            [torch.where(ok, (xm[..., : n - m] * xm[..., m:]).sum(-1) / den, torch.ones_like(var)) for m in lags],
            dim=-1,
        )
    delays = torch.tensor([m * dt for m in lags], dtype=s.dtype, device=s.device)
    return ocds_from_correlations(rho, delays, (lo, hi), tolerance_s=tol)


def complex_variance(field: torch.Tensor) -> torch.Tensor:
    """``mean_t |E − mean_t E|²`` over the last axis (ddof 0; linear intensity units)."""
    d = field - field[..., :1]
    m = d.mean(-1, keepdim=True)
    r = d - m
    return (r.real**2 + r.imag**2).mean(-1)


def compute_metrics(signals: torch.Tensor, frame_times_s: Sequence[float], analysis: Any) -> dict[str, Any]:
    """Metrics of complex signals ``[..., frames]`` as the scene's ``[analysis]`` asks.

    Returns a dict with one tensor per metric (``liv``, ``ocds`` ``[...]``; ``autocorrelation``
    ``[..., L]`` with ``autocorrelation_delays_s``), plus ``zero_intensity`` (bool ``[...]``: some
    frame has I = 0, i.e. an empty resolution volume; dB metrics of those entries are NaN).
    """
    intensity = signals.real**2 + signals.imag**2
    zero = (intensity <= 0).any(-1)
    out: dict[str, Any] = {"zero_intensity": zero}
    nan = torch.tensor(float("nan"), dtype=intensity.dtype, device=intensity.device)
    db_needed = "liv" in analysis.metrics or (
        analysis.ocds_scale == "db" and ("ocds" in analysis.metrics or "autocorrelation" in analysis.metrics)
    )
    safe = torch.where(zero[..., None], torch.ones_like(intensity), intensity) if db_needed else intensity
    for name in analysis.metrics:
        if name == "liv":
            out["liv"] = torch.where(zero, nan, liv(safe))
        elif name == "ocds":
            v = ocds(
                safe if analysis.ocds_scale == "db" else intensity,
                frame_times_s,
                delay_range_s=analysis.ocds_delay_range_s,
                scale=analysis.ocds_scale,
                estimator=analysis.ocds_estimator,
            )
            out["ocds"] = torch.where(zero, nan, v) if analysis.ocds_scale == "db" else v
        elif name == "complex_variance":
            out["complex_variance"] = complex_variance(signals)
        elif name == "autocorrelation":
            s = to_db(safe) if analysis.ocds_scale == "db" else intensity
            d, rho = lag_correlations(s, frame_times_s, estimator=analysis.ocds_estimator)
            if analysis.ocds_scale == "db":
                rho = torch.where(zero[..., None], nan, rho)
            out["autocorrelation"] = rho
            out["autocorrelation_delays_s"] = d
    return out


def summarize(metrics: dict[str, Any], system_names: Sequence[str]) -> dict[str, Any]:
    """Mean, SD, standard error and count per system of the scalar metrics ``[trials, systems]``."""
    zero = metrics["zero_intensity"]
    out: dict[str, Any] = {}
    for s, name in enumerate(system_names):
        row: dict[str, Any] = {"zero_intensity_trials": int(zero[:, s].sum())}
        for key in ("liv", "ocds", "complex_variance"):
            if key not in metrics:
                continue
            v = metrics[key][:, s].double()
            v = v[torch.isfinite(v)]
            n = v.numel()
            mean = float(v.mean()) if n else math.nan
            sd = float(v.std(unbiased=True)) if n > 1 else math.nan
            row[key] = {"mean": mean, "sd": sd, "se": sd / math.sqrt(n) if n > 1 else math.nan, "n": n}
        out[name] = row
    return out

"""The per-pixel metrics of the DOCT maps on ``[..., T]`` (time last): LIV, OCDS, mean dB, and the LIV
curve with its saturation fit for aLIV and Swiftness; their definitions are in the module docstring of
:mod:`torchdoct.measured.maps` (physics.md §1-3), which runs them slab by slab and re-exports every
public name here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence as _Seq

import torch

from ..conventions import delay_groups, delay_range_tolerance_s
from ..sim import metrics as _metrics

__all__ = [
    "SMOOTHING_AXIS_NEEDS",
    "METRICS",
    "FIT_FLAG",
    "VALID_WEIGHT",
    "UNITS",
    "DEFAULT_OCDS_DELAY_RANGE_S",
    "TAU_BOUND_LOG_TOL",
    "ocds_map",
    "liv_curve",
    "fit_saturation",
    "tau_bound_code",
    "box_smooth_zx",
    "pixel_metrics",
]

METRICS = ("liv", "ocds", "mean_db", "aliv", "swiftness")
#: Channel written with ``aliv``/``swiftness``: where the saturation fit ended on a τ bound
#: (:func:`tau_bound_code`: 0 inside, 1 lower bound, 2 upper bound, NaN undefined).
FIT_FLAG = "aliv_fit"
#: Channel written where the input has non-finite samples: the share of the reduction window's weight that
#: fell on finite samples (1 everywhere else; at the original resolution 1 or 0), :mod:`torchdoct.measured.maps`.
VALID_WEIGHT = "valid_weight"
UNITS = {
    "liv": "dB^2",
    "ocds": "1/s",
    "mean_db": "dB",
    "aliv": "dB^2",
    "swiftness": "1/s",
    FIT_FLAG: "code",
    VALID_WEIGHT: "fraction",
}
DEFAULT_OCDS_DELAY_RANGE_S = (0.2048, 1.2288)


def ocds_map(
    intensity: torch.Tensor,
    frame_times_s: _Seq[float],
    *,
    delay_range_s: tuple[float, float] = DEFAULT_OCDS_DELAY_RANGE_S,
    scale: str = "db",
    estimator: str = "pearson",
) -> torch.Tensor:
    """OCDS (1/s) of intensities ``[..., T]``: :func:`torchdoct.sim.metrics.ocds` itself (the one OCDS of
    the simulator and the maps), with the maps' default delay range."""
    return _metrics.ocds(intensity, frame_times_s, delay_range_s=delay_range_s, scale=scale, estimator=estimator)


def _windows(frame_times_s: _Seq[float], max_window_s: float | None) -> list[tuple[float, list[tuple[int, int]]]]:
    """Distinct window spans ``T_w`` (s) and, for each, the (first, last) frame index pairs."""
    out = delay_groups(frame_times_s)
    if max_window_s is not None:
        tol = delay_range_tolerance_s(frame_times_s, (0.0, max_window_s))
        out = [w for w in out if w[0] <= max_window_s + tol]
    if len(out) < 2:
        raise ValueError("the LIV curve needs at least 2 time windows; check frame_times_s / max_window_s")
    return out


def liv_curve(
    intensity: torch.Tensor, frame_times_s: _Seq[float], *, max_window_s: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """LIV curve (physics.md §3 step 1): ``(windows_s [W], curve [..., W])`` in dB², float64.

    ``curve[..., w]`` is the mean over start positions of the ddof-0 variance of ``10·log10 I`` over
    the consecutive frames ``i … j`` with ``t_j − t_i = windows_s[w]``.
    """
    wins = _windows(frame_times_s, max_window_s)
    s = _metrics.to_db(intensity).double()
    s = s - s.mean(-1, keepdim=True)
    zeros = torch.zeros_like(s[..., :1])
    c1 = torch.cat([zeros, s.cumsum(-1)], -1)
    c2 = torch.cat([zeros, (s * s).cumsum(-1)], -1)
    n = s.shape[-1]
    cols = []
    uniform = _metrics.uniform_frame_interval_s(frame_times_s) is not None
    for _, pairs in wins:
        if uniform:  # runs i … i+m for every start i: contiguous slices of the cumulative sums
            m = pairs[0][1] - pairs[0][0]
            d1 = (c1[..., m + 1 :] - c1[..., : n - m]) / (m + 1)
            d2 = (c2[..., m + 1 :] - c2[..., : n - m]) / (m + 1)
        else:
            i = torch.tensor([p[0] for p in pairs], device=s.device)
            j = torch.tensor([p[1] + 1 for p in pairs], device=s.device)
            cnt = (j - i).to(s.dtype)
            d1 = (c1.index_select(-1, j) - c1.index_select(-1, i)) / cnt
            d2 = (c2.index_select(-1, j) - c2.index_select(-1, i)) / cnt
        cols.append((d2 - d1 * d1).clamp_min(0).mean(-1))
    windows = torch.tensor([w[0] for w in wins], dtype=torch.float64, device=s.device)
    return windows, torch.stack(cols, -1)


#: What the 3×3 box smoothing of the aLIV curves (:func:`box_smooth_zx`) needs of a piece of the maps: one
#: pixel more on each side along Z and X (each B-scan is smoothed on its own: Y may be cut anywhere).
SMOOTHING_AXIS_NEEDS: dict[str, int | None] = {"Z": 1, "X": 1}


def box_smooth_zx(curves: torch.Tensor, defined: torch.Tensor | None = None) -> torch.Tensor:
    """3×3 box mean over the (Z, X) dimensions of ``curves [..., Z, X, W]`` (border reflect-101,
    as ``cv2.blur``); leading dimensions (e.g. Y) are separate images.

    ``defined`` (bool ``[..., Z, X]``): average over the defined pixels of each 3×3 neighbourhood only
    (``Σ defined·curve / Σ defined`` over the same reflect-101 window), so an undefined pixel (no dB
    value) does not pull its neighbours' curves towards 0; a pixel with no defined neighbour gets 0.
    """
    lead = curves.shape[:-3]
    z, x, w = curves.shape[-3:]
    pz = 1 if z >= 2 else 0
    px = 1 if x >= 2 else 0

    def blur(img: torch.Tensor) -> torch.Tensor:  # [N, C, Z, X]
        img = torch.nn.functional.pad(img, (px, px, pz, pz), mode="reflect") if (pz or px) else img
        return torch.nn.functional.avg_pool2d(img, kernel_size=(2 * pz + 1, 2 * px + 1), stride=1)

    img = curves.reshape(-1, z, x, w).permute(0, 3, 1, 2)  # [N, W, Z, X]
    if defined is None:
        out = blur(img)
    else:
        d = defined.reshape(-1, 1, z, x).to(curves.dtype)
        num = blur(img * d)
        den = blur(d)
        out = torch.where(den > 0, num / torch.where(den > 0, den, torch.ones_like(den)), torch.zeros_like(num))
    return out.permute(0, 2, 3, 1).reshape(*lead, z, x, w)


def fit_saturation(
    windows_s: torch.Tensor,
    curve: torch.Tensor,
    *,
    tau_bounds_s: tuple[float, float] | None = None,
    grid: int = 64,
    iterations: int = 24,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares fit of ``a·(1 − exp(−T_w/τ))`` to every curve ``[..., W]``; returns ``(a, τ)``.

    Vectorized over pixels (no per-pixel loop), float64. For fixed τ the best ``a ≥ 0`` is closed-form,
    ``a = max(0, Σ y f / Σ f²)`` with ``f = 1 − exp(−T_w/τ)``, so the fit is a 1-D minimisation of the
    profile residual over ``ln τ``: a ``grid``-point log grid (one matrix product for all pixels)
    locates the global minimum, then golden-section search refines it inside the neighbouring grid
    cells (``iterations`` steps, bracket × 0.618 each). τ is bounded to ``tau_bounds_s`` (default
    ``[min T_w / 100, 100·max T_w]``); a fit at a bound means the curve is flat (τ → 0) or still
    linear (τ → ∞) over the windows. Same minimum as ``scipy.optimize.curve_fit`` with bounds
    ``[0, ∞)`` when that lies inside the bounds (physics.md §3).
    """
    t = windows_s.to(torch.float64)
    y = curve.to(torch.float64)
    lead = y.shape[:-1]
    y = y.reshape(-1, y.shape[-1])
    if tau_bounds_s is None:
        tau_bounds_s = _default_tau_bounds(t)
    lo, hi = math.log(tau_bounds_s[0]), math.log(tau_bounds_s[1])
    u = torch.linspace(lo, hi, grid, dtype=torch.float64, device=y.device)
    fg = -torch.expm1(-t[None, :] / torch.exp(u)[:, None])  # [G, W]
    syf = y @ fg.T  # [P, G]
    q = syf.clamp_min(0) ** 2 / (fg * fg).sum(-1)
    g = q.argmax(-1)
    step = (hi - lo) / (grid - 1)
    ua = (u[g] - step).clamp(lo, hi)
    ub = (u[g] + step).clamp(lo, hi)

    neg_t = -t[None, :]

    def profile(uu: torch.Tensor) -> torch.Tensor:
        f = -torch.expm1(neg_t * torch.exp(-uu)[:, None])
        syf = torch.einsum("pw,pw->p", y, f)
        return syf.clamp_min(0) ** 2 / torch.einsum("pw,pw->p", f, f)

    r = (math.sqrt(5.0) - 1.0) / 2.0
    uc = ub - r * (ub - ua)
    ud = ua + r * (ub - ua)
    qc, qd = profile(uc), profile(ud)
    for _ in range(iterations):
        left = qc >= qd  # the maximum lies in [ua, ud]
        ub = torch.where(left, ud, ub)
        ua = torch.where(left, ua, uc)
        new_u = torch.where(left, ub - r * (ub - ua), ua + r * (ub - ua))
        qn = profile(new_u)
        uc, ud, qc, qd = (
            torch.where(left, new_u, ud),
            torch.where(left, uc, new_u),
            torch.where(left, qn, qd),
            torch.where(left, qc, qn),
        )
    u_best = torch.where(qc >= qd, uc, ud)
    tau = torch.exp(u_best)
    f = -torch.expm1(-t[None, :] / tau[:, None])
    a = ((y * f).sum(-1) / (f * f).sum(-1)).clamp_min(0)
    return a.reshape(lead), tau.reshape(lead)


def _default_tau_bounds(windows_s: torch.Tensor) -> tuple[float, float]:
    return float(windows_s.min()) / 100.0, 100.0 * float(windows_s.max())


#: ``|ln τ − ln bound|`` below which a fit counts as ending on a τ bound (τ within 0.1 % of it).
TAU_BOUND_LOG_TOL = 1e-3


def tau_bound_code(
    tau: torch.Tensor, windows_s: torch.Tensor, tau_bounds_s: tuple[float, float] | None = None
) -> torch.Tensor:
    """Where a :func:`fit_saturation` fit ended on a τ bound: 0 inside, 1 at the lower bound (the
    curve is flat over the windows: it saturated before the shortest one), 2 at the upper bound (the
    curve is still rising linearly at the longest window); ``|ln τ − ln bound| <`` :data:`TAU_BOUND_LOG_TOL`.
    Such aLIV/Swiftness values are bounds of the model, not measurements (physics.md §3)."""
    lo, hi = _default_tau_bounds(windows_s) if tau_bounds_s is None else tau_bounds_s
    u = torch.log(tau.to(torch.float64))
    code = torch.zeros_like(u)
    code = torch.where(u - math.log(lo) < TAU_BOUND_LOG_TOL, torch.ones_like(u), code)
    return torch.where(math.log(hi) - u < TAU_BOUND_LOG_TOL, torch.full_like(u, 2.0), code)


def pixel_metrics(
    intensity: torch.Tensor,
    frame_times_s: list[float],
    wanted: list[str],
    *,
    ocds_delay_range_s: tuple[float, float],
    ocds_scale: str,
    ocds_estimator: str,
    aliv_smoothing: bool,
    aliv_max_window_s: float | None,
    chunk_pixels: int,
) -> dict[str, torch.Tensor]:
    """Metrics of ``intensity [T, *spatial]`` → ``{name: [*spatial]}`` (the definitions: module docstring of
    :mod:`torchdoct.measured.maps`); ``chunk_pixels`` pixels at a time (memory only)."""
    spatial = intensity.shape[1:]
    it = intensity.movedim(0, -1).reshape(-1, intensity.shape[0])
    n_pix = it.shape[0]
    nan = float("nan")
    out = {k: torch.empty(n_pix, dtype=intensity.dtype, device=intensity.device) for k in wanted}
    curves = None
    if "aliv" in wanted or "swiftness" in wanted:
        curves = []
    for p0 in range(0, n_pix, chunk_pixels):
        x = it[p0 : p0 + chunk_pixels]
        zero = ~(x > 0).all(-1)  # I = 0 or NaN at some frame: no dB value
        safe = torch.where(zero[:, None], torch.ones_like(x), x) if bool(zero.any()) else x
        if "liv" in out:
            out["liv"][p0 : p0 + len(x)] = torch.where(zero, nan, _metrics.liv(safe))
        if "ocds" in out:
            v = ocds_map(
                safe if ocds_scale == "db" else x,
                frame_times_s,
                delay_range_s=ocds_delay_range_s,
                scale=ocds_scale,
                estimator=ocds_estimator,
            )
            bad = zero if ocds_scale == "db" else ~torch.isfinite(x).all(-1)
            out["ocds"][p0 : p0 + len(x)] = torch.where(bad, nan, v)
        if "mean_db" in out:
            m = x.mean(-1)
            out["mean_db"][p0 : p0 + len(x)] = torch.where(
                m > 0, _metrics.to_db(torch.where(m > 0, m, torch.ones_like(m))), torch.full_like(m, nan)
            )
        if curves is not None:
            windows, c = liv_curve(safe, frame_times_s, max_window_s=aliv_max_window_s)
            curves.append(c)
    res = {k: v.reshape(spatial) for k, v in out.items()}
    if curves is not None:
        c = torch.cat(curves, 0).reshape(*spatial, -1)
        zero_all = ~(it > 0).all(-1)
        if aliv_smoothing:
            c = box_smooth_zx(c, defined=~zero_all.reshape(spatial))
        c = c.reshape(n_pix, -1)
        a_out = torch.empty(n_pix, dtype=torch.float64, device=c.device)
        tau_out = torch.empty(n_pix, dtype=torch.float64, device=c.device)
        step = max(1, chunk_pixels // 4)
        for p0 in range(0, n_pix, step):
            a, tau = fit_saturation(windows, c[p0 : p0 + step])
            a_out[p0 : p0 + step] = a
            tau_out[p0 : p0 + step] = tau
        a_out = torch.where(zero_all, nan, a_out)
        swift = torch.where(zero_all | (a_out == 0), nan, 1.0 / tau_out)
        code = torch.where(a_out == 0, 0.0, tau_bound_code(tau_out, windows))  # a = 0: no τ to flag
        if "aliv" in wanted:
            res["aliv"] = a_out.to(intensity.dtype).reshape(spatial)
        if "swiftness" in wanted:
            res["swiftness"] = swift.to(intensity.dtype).reshape(spatial)
        res[FIT_FLAG] = torch.where(zero_all, nan, code).to(intensity.dtype).reshape(spatial)
    return res

"""DOCT maps of complex (or intensity) OCT sequences at one or more resolutions.

For every requested resolution (:func:`torchdoct.measured.resolution.parse_resolution`: ``original``,
``axial=14``, ``lateral=18``, ``axial=14,lateral=18``) the complex field is reduced
(:func:`torchdoct.measured.resolution.reduce_resolution`, paper Eqs. 1-8), ``I = |E|²`` is formed, and per
pixel (time last, ``[..., T]``) the channels below are computed:

* ``liv`` (dB²): :func:`torchdoct.sim.metrics.liv`, ddof-0 variance of ``10·log10 I`` (physics.md §1);
* ``ocds`` (1/s): −OLS slope of the lag correlation over ``ocds_delay_range_s`` (physics.md §2.4;
  :func:`torchdoct.sim.metrics.ocds`; the default Pearson/dB path evaluates only the lags inside the
  range, with the same definition, see :func:`ocds_map`);
* ``mean_db`` (dB): ``10·log10(mean_t I)``, the dB of the time-averaged linear intensity (the
  structural OCT image; with the default ``normalization="power"`` of the reduction it stays
  comparable across resolutions);
* on request ``aliv`` (dB²) and ``swiftness`` (1/s): physics.md §3, as the COG contrast library
  defines them: the LIV curve ``LIV(T_w)`` (ddof-0 variance of the dB intensity over every run of
  consecutive frames spanning exactly ``T_w``, averaged over start positions, for every ``T_w`` that
  is a difference of frame times; :func:`liv_curve`), smoothed by a 3×3 box over each (Z, X) image
  (``cv2.blur``, border reflect-101; ``aliv_smoothing=False`` turns it off) over the *defined*
  neighbours only (an undefined pixel's curve does not enter its neighbours' mean; with every pixel
  defined this is exactly ``cv2.blur``), then the saturation model
  ``LIV(T_w) = a·(1 − exp(−T_w/τ))`` fitted by unweighted least squares with ``a, τ ≥ 0``
  (:func:`fit_saturation`); ``aliv = a``, ``swiftness = 1/τ``.

Non-finite samples (NaN or inf in some frame) are masked per pixel instead of reaching the reduction's FFT
(where one NaN would make every reduced pixel NaN): they enter the reduction as 0, and every channel is NaN
at the pixels whose value they reach: the pixel itself at the original resolution, and after a reduction
every pixel within the ``⌈5σ'⌉`` pixels of the window's truncation along each filtered axis (plus the 3×3
smoothing for aLIV/Swiftness); ``meta["nonfinite"]`` counts the samples and the masked pixels per
resolution. Undefined values are NaN: pixels with ``I = 0`` have no dB value (LIV, OCDS, aLIV,
Swiftness NaN; ``mean_db`` NaN only if ``I = 0`` at every frame), and Swiftness is NaN where the fit
gives ``a = 0`` (no fluctuation, τ undefined). After a resolution reduction the same rule holds with a
floor: ``I ≤ (64·ε)²·max I`` (ε the machine epsilon of the data type, ``max I`` the largest finite
intensity of the input: −102 dB for complex64, −277 dB for complex128) counts as ``I = 0``, because
exactly empty pixels acquire FFT round-off of the reduction there, not signal (:data:`EMPTY_RULE`,
recorded as ``meta["empty_rule"]``). At the original resolution only exact zeros are empty. An input
with no finite nonzero sample, or with fewer than 2 frames, is refused.

aLIV/Swiftness fits that end on a τ bound (:func:`tau_bound_code`) are flagged in the ``aliv_fit``
channel written with them (0 inside, 1 lower bound, 2 upper bound, NaN undefined); their counts per
resolution are in ``meta["aliv"]["flagged_pixels"]`` and :func:`write_pngs` draws them in magenta.

Optics: only a resolution change needs the pitch and the original resolutions (``system``); maps at
the original resolution record them when known (``None`` otherwise).

Bulk phase (``bulk_phase``, ``torchdoct maps --bulk-phase METHOD``): the phase common to an A-line's
pixels at each frame is estimated per A-line and consecutive frame pair and removed
(:mod:`torchdoct.measured.bulkphase`, physics.md §12) before the field is reduced, so a lateral
reduction adds A-lines with their bulk motion removed; the estimate runs first, in lateral slabs of
whole A-lines (it needs every depth row used and every frame of an A-line), and only the
``[T, (Y), X]`` phases are kept. The maps record it in ``meta["bulk_phase"]`` (method, reference
``"consecutive frames"``, mask, rows).

Block raster volumes (:class:`torchdoct.measured.io.BlockRaster` in the sequence metadata): maps are
computed on the whole volume (the lateral Gaussian runs across block boundaries, as in the paper),
then the B-scans next to the boundaries are dropped; ``meta["y_indices"]`` lists the kept positions.

Work is done in depth slabs (with a halo for the axial window), so memory stays bounded and a
progress bar shows; results do not depend on the slab size beyond the window truncation at 5σ'.

Kept whole (over 600 lines): the slab loop and the per-slab metrics it runs belong together
(docs/architecture.md).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence as _Seq

import numpy as np
import torch

from ..sim import metrics as _metrics
from .._files import atomic_write, check_out
from .bulkphase import BulkPhase, estimate_bulk_phase, phasor as _bulk_phasor
from .io import Maps, Sequence
from ..threads import one_torch_thread
from .resolution import (
    EDGE_MODES,
    NORMALIZATIONS,
    ResolutionTarget,
    axial_filter_sigma_um,
    check_target_sampled,
    depth_spectrum_center,
    lateral_filter_sigma_um,
    parse_resolution,
    reduce_resolution,
)

__all__ = [
    "METRICS",
    "FIT_FLAG",
    "UNITS",
    "DEFAULT_OCDS_DELAY_RANGE_S",
    "ocds_map",
    "liv_curve",
    "fit_saturation",
    "tau_bound_code",
    "box_smooth_zx",
    "compute_maps",
    "nonfinite_mask",
    "nonfinite_reach_px",
    "pseudo_color",
    "map_figure",
    "write_pngs",
    "png_name",
    "bench_maps",
]

METRICS = ("liv", "ocds", "mean_db", "aliv", "swiftness")
#: Channel written with ``aliv``/``swiftness``: where the saturation fit ended on a τ bound
#: (:func:`tau_bound_code`: 0 inside, 1 lower bound, 2 upper bound, NaN undefined).
FIT_FLAG = "aliv_fit"
UNITS = {"liv": "dB^2", "ocds": "1/s", "mean_db": "dB", "aliv": "dB^2", "swiftness": "1/s", FIT_FLAG: "code"}
DEFAULT_OCDS_DELAY_RANGE_S = (0.2048, 1.2288)
#: Default hue range of the pseudo-colour images: low values red (0), high values green (1/3).
DEFAULT_HUE_RANGE = (0.0, 1.0 / 3.0)
#: Colour of flagged pixels (aLIV/Swiftness fits on a τ bound) in the pseudo-colour images.
FLAG_RGB = (255, 0, 255)


# ----------------------------------------------------------------------------------------------
# per-pixel metrics on [..., T]


def _uniform_dt(frame_times_s: _Seq[float]) -> float | None:
    t = [float(v) for v in frame_times_s]
    d = [b - a for a, b in zip(t, t[1:])]
    if max(d) - min(d) <= 1e-9 * max(d):
        return (t[-1] - t[0]) / (len(t) - 1)
    return None


def ocds_map(intensity: torch.Tensor, frame_times_s: _Seq[float], *,
             delay_range_s: tuple[float, float] = DEFAULT_OCDS_DELAY_RANGE_S, scale: str = "db",
             estimator: str = "pearson") -> torch.Tensor:
    """OCDS (1/s) of intensities ``[..., T]``: identical to :func:`torchdoct.sim.metrics.ocds`.

    For a uniform protocol only the lags inside ``delay_range_s`` are computed, with either estimator
    (same per-lag definitions and degenerate-case rules as :func:`torchdoct.sim.metrics.lag_correlations`:
    Pearson per lag, or the biased ``Σ x̃_i x̃_{i+m} / Σ x̃²`` of the whole-sequence deviations; the slope
    comes from :func:`torchdoct.sim.metrics.ocds_from_correlations`); a non-uniform protocol calls
    :func:`torchdoct.sim.metrics.ocds`.
    """
    dt = _uniform_dt(frame_times_s)
    if dt is None or estimator not in ("pearson", "biased"):
        return _metrics.ocds(intensity, frame_times_s, delay_range_s=delay_range_s, scale=scale, estimator=estimator)
    if scale == "db":
        s = _metrics.to_db(intensity)
    elif scale == "linear":
        s = intensity
    else:
        raise ValueError(f"scale must be 'db' or 'linear'; got {scale!r}")
    n = s.shape[-1]
    if n != len(frame_times_s):
        raise ValueError(f"signal has {n} frames but {len(frame_times_s)} frame times were given")
    lo, hi = delay_range_s
    lags = [m for m in range(1, n) if lo * (1 - 1e-9) <= m * dt <= hi * (1 + 1e-9)]
    if len(lags) < 2:
        raise ValueError(f"OCDS delay range [{lo}, {hi}] s holds fewer than 2 delays of the protocol "
                         f"(frame interval {dt:.6g} s, {n} frames); give --ocds-delay-range-s")
    if estimator == "pearson":
        rho = torch.stack([_metrics._pearson(s[..., : n - m], s[..., m:]) for m in lags], dim=-1)
    else:  # biased: as metrics.lag_correlations, for the lags in the range only
        d = s - s[..., :1]
        xm = d - d.mean(-1, keepdim=True)
        var = (xm * xm).sum(-1)
        ok = var > 0
        den = torch.where(ok, var, torch.ones_like(var))
        rho = torch.stack([torch.where(ok, (xm[..., : n - m] * xm[..., m:]).sum(-1) / den, torch.ones_like(var))
                           for m in lags], dim=-1)
    delays = torch.tensor([m * dt for m in lags], dtype=s.dtype, device=s.device)
    return _metrics.ocds_from_correlations(rho, delays, (lo, hi))


def _windows(frame_times_s: _Seq[float], max_window_s: float | None) -> list[tuple[float, list[tuple[int, int]]]]:
    """Distinct window spans ``T_w`` (s) and, for each, the (first, last) frame index pairs."""
    t = [float(v) - float(frame_times_s[0]) for v in frame_times_s]
    n = len(t)
    dt = _uniform_dt(frame_times_s)
    if dt is not None:
        out = [(m * dt, [(i, i + m) for i in range(n - m)]) for m in range(1, n)]
    else:
        groups: dict[float, list[tuple[int, int]]] = {}
        for i in range(n):
            for j in range(i + 1, n):
                groups.setdefault(round(t[j] - t[i], 9), []).append((i, j))
        out = [(k, groups[k]) for k in sorted(groups)]
    if max_window_s is not None:
        out = [w for w in out if w[0] <= max_window_s * (1 + 1e-9)]
    if len(out) < 2:
        raise ValueError("the LIV curve needs at least 2 time windows; check frame_times_s / max_window_s")
    return out


def liv_curve(intensity: torch.Tensor, frame_times_s: _Seq[float], *,
              max_window_s: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
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
    uniform = _uniform_dt(frame_times_s) is not None
    for _, pairs in wins:
        if uniform:  # runs i … i+m for every start i: contiguous slices of the cumulative sums
            m = pairs[0][1] - pairs[0][0]
            d1 = (c1[..., m + 1:] - c1[..., : n - m]) / (m + 1)
            d2 = (c2[..., m + 1:] - c2[..., : n - m]) / (m + 1)
        else:
            i = torch.tensor([p[0] for p in pairs], device=s.device)
            j = torch.tensor([p[1] + 1 for p in pairs], device=s.device)
            cnt = (j - i).to(s.dtype)
            d1 = (c1.index_select(-1, j) - c1.index_select(-1, i)) / cnt
            d2 = (c2.index_select(-1, j) - c2.index_select(-1, i)) / cnt
        cols.append((d2 - d1 * d1).clamp_min(0).mean(-1))
    windows = torch.tensor([w[0] for w in wins], dtype=torch.float64, device=s.device)
    return windows, torch.stack(cols, -1)


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


def fit_saturation(windows_s: torch.Tensor, curve: torch.Tensor, *, tau_bounds_s: tuple[float, float] | None = None,
                   grid: int = 64, iterations: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
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
        uc, ud, qc, qd = (torch.where(left, new_u, ud), torch.where(left, uc, new_u),
                          torch.where(left, qn, qd), torch.where(left, qc, qn))
    u_best = torch.where(qc >= qd, uc, ud)
    tau = torch.exp(u_best)
    f = -torch.expm1(-t[None, :] / tau[:, None])
    a = ((y * f).sum(-1) / (f * f).sum(-1)).clamp_min(0)
    return a.reshape(lead), tau.reshape(lead)


def _default_tau_bounds(windows_s: torch.Tensor) -> tuple[float, float]:
    return float(windows_s.min()) / 100.0, 100.0 * float(windows_s.max())


#: ``|ln τ − ln bound|`` below which a fit counts as ending on a τ bound (τ within 0.1 % of it).
TAU_BOUND_LOG_TOL = 1e-3


def tau_bound_code(tau: torch.Tensor, windows_s: torch.Tensor,
                   tau_bounds_s: tuple[float, float] | None = None) -> torch.Tensor:
    """Where a :func:`fit_saturation` fit ended on a τ bound: 0 inside, 1 at the lower bound (the
    curve is flat over the windows: it saturated before the shortest one), 2 at the upper bound (the
    curve is still rising linearly at the longest window); ``|ln τ − ln bound| <`` :data:`TAU_BOUND_LOG_TOL`.
    Such aLIV/Swiftness values are bounds of the model, not measurements (physics.md §3)."""
    lo, hi = _default_tau_bounds(windows_s) if tau_bounds_s is None else tau_bounds_s
    u = torch.log(tau.to(torch.float64))
    code = torch.zeros_like(u)
    code = torch.where(u - math.log(lo) < TAU_BOUND_LOG_TOL, torch.ones_like(u), code)
    return torch.where(math.log(hi) - u < TAU_BOUND_LOG_TOL, torch.full_like(u, 2.0), code)


# ----------------------------------------------------------------------------------------------
# maps of a sequence

#: The leakage floor of a resolution reduction is ``(EMPTY_FLOOR_EPS_FACTOR·ε)²·max I`` (ε of the data type).
EMPTY_FLOOR_EPS_FACTOR = 64
EMPTY_RULE = ("a pixel has no dB value where I = 0 or NaN at some frame; after a resolution reduction I <= "
              "(64·eps)²·max I (eps of the data type, max I over the input; -102 dB for complex64, -277 dB for "
              "complex128) counts as I = 0: FFT round-off of the reduction, not signal")


def _peak_intensity(data: np.ndarray, src: str) -> float:
    """Largest finite ``|E|²`` (or intensity) of ``data``, frame by frame; refuses data without any
    finite nonzero sample (every map would be NaN)."""
    peak = 0.0
    for k in range(data.shape[0]):
        f = np.asarray(data[k])
        with np.errstate(over="ignore", invalid="ignore"):
            v = f.real * f.real + f.imag * f.imag if np.iscomplexobj(f) else np.abs(f)
        overflow = ~np.isfinite(v) & np.isfinite(f)  # |E|² beyond the data type of finite samples
        if overflow.any():
            top = float(np.max(np.abs(f[overflow])))
            raise ValueError(f"{src}: |E|² overflows {v.dtype} (|E| up to {top:.3g}, the largest {v.dtype} |E|² is "
                             f"{float(np.finfo(v.dtype).max):.3g}); scale the field down (e.g. divide it by "
                             f"{10 ** math.ceil(math.log10(top) - 15):.0e}) or store it as complex128")
        peak = max(peak, float(np.max(v, where=np.isfinite(v), initial=0.0)))
    if not peak > 0:
        raise ValueError(f"{src}: holds no finite nonzero sample (every value is NaN, infinite or 0), so no pixel "
                         "has a dB value; check the file (and --dataset / --axes)")
    return peak


def _pixel_metrics(intensity: torch.Tensor, frame_times_s: list[float], wanted: list[str], *,
                   ocds_delay_range_s: tuple[float, float], ocds_scale: str, ocds_estimator: str,
                   aliv_smoothing: bool, aliv_max_window_s: float | None,
                   chunk_pixels: int) -> dict[str, torch.Tensor]:
    """Metrics of ``intensity [T, *spatial]`` → ``{name: [*spatial]}`` (see the module docstring)."""
    spatial = intensity.shape[1:]
    it = intensity.movedim(0, -1).reshape(-1, intensity.shape[0])
    n_pix = it.shape[0]
    nan = float("nan")
    out = {k: torch.empty(n_pix, dtype=intensity.dtype, device=intensity.device) for k in wanted}
    curves = None
    if "aliv" in wanted or "swiftness" in wanted:
        curves = []
    for p0 in range(0, n_pix, chunk_pixels):
        x = it[p0:p0 + chunk_pixels]
        zero = ~(x > 0).all(-1)  # I = 0 or NaN at some frame: no dB value
        safe = torch.where(zero[:, None], torch.ones_like(x), x) if bool(zero.any()) else x
        if "liv" in out:
            out["liv"][p0:p0 + len(x)] = torch.where(zero, nan, _metrics.liv(safe))
        if "ocds" in out:
            v = ocds_map(safe if ocds_scale == "db" else x, frame_times_s, delay_range_s=ocds_delay_range_s,
                         scale=ocds_scale, estimator=ocds_estimator)
            bad = zero if ocds_scale == "db" else ~torch.isfinite(x).all(-1)
            out["ocds"][p0:p0 + len(x)] = torch.where(bad, nan, v)
        if "mean_db" in out:
            m = x.mean(-1)
            out["mean_db"][p0:p0 + len(x)] = torch.where(m > 0, _metrics.to_db(torch.where(m > 0, m, torch.ones_like(m))),
                                                          torch.full_like(m, nan))
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
            a, tau = fit_saturation(windows, c[p0:p0 + step])
            a_out[p0:p0 + step] = a
            tau_out[p0:p0 + step] = tau
        a_out = torch.where(zero_all, nan, a_out)
        swift = torch.where(zero_all | (a_out == 0), nan, 1.0 / tau_out)
        code = torch.where(a_out == 0, 0.0, tau_bound_code(tau_out, windows))  # a = 0: no τ to flag
        if "aliv" in wanted:
            res["aliv"] = a_out.to(intensity.dtype).reshape(spatial)
        if "swiftness" in wanted:
            res["swiftness"] = swift.to(intensity.dtype).reshape(spatial)
        res[FIT_FLAG] = torch.where(zero_all, nan, code).to(intensity.dtype).reshape(spatial)
    return res


def _nonfinite_reach(bad: np.ndarray, spatial_axes: str, widths: Mapping[str, int], wrap: bool) -> np.ndarray:
    """``bad`` (pixels with a non-finite sample, ``[(Y), Z, X]``) spread by ``±widths[c]`` pixels along each
    axis letter ``c`` (the reach of a filter truncated at 5σ'); periodic when the reduction wraps."""
    from scipy.ndimage import maximum_filter1d

    out = bad.astype(np.uint8)
    for c, w in widths.items():
        if w > 0 and c in spatial_axes:
            out = maximum_filter1d(out, size=2 * w + 1, axis=spatial_axes.index(c), mode="wrap" if wrap else "constant")
    return out.astype(bool)


def nonfinite_reach_px(seq: Sequence, target: str | ResolutionTarget) -> dict[str, int]:
    """How far (pixels, per axis letter) a sample reaches through the reduction to ``target`` of ``seq``:
    ``⌈5σ'/pitch⌉`` along each filtered axis (the window's truncation), nothing at the original."""
    t = parse_resolution(target) if isinstance(target, str) else target
    if t.lateral_resolution_um is None and t.axial_resolution_um is None:
        return {}
    system = seq.system
    lat0, ax0 = float(system["lateral_resolution_um"]), float(system["axial_resolution_um"])
    lat, ax = t.resolved(system)
    reach = {}
    if ax != ax0:
        reach["Z"] = int(math.ceil(5.0 * axial_filter_sigma_um(ax0, ax) / seq.pitch_um["z"]))
    if lat != lat0:
        sl = lateral_filter_sigma_um(lat0, lat)
        for c in "YX":
            if c in seq.axes:
                reach[c] = int(math.ceil(5.0 * sl / seq.pitch_um[c.lower()]))
    return reach


def nonfinite_mask(seq: Sequence, target: str | ResolutionTarget = "original", *,
                   edge_mode: str = "reflect") -> np.ndarray | None:
    """The pixels (``[(Y), Z, X]``) that a non-finite sample of ``seq`` reaches at ``target`` (the rule of
    :func:`compute_maps`, module docstring), or ``None`` when every sample is finite."""
    bad = None
    for frame in seq.data:
        fin = np.isfinite(frame)
        if not fin.all():
            bad = ~fin if bad is None else bad | ~fin
    if bad is None:
        return None
    return _nonfinite_reach(bad, seq.axes[1:], nonfinite_reach_px(seq, target), edge_mode == "wrap")


def _as_targets(resolutions: Iterable[str | ResolutionTarget]) -> list[ResolutionTarget]:
    targets = []
    for r in resolutions:
        t = r if isinstance(r, ResolutionTarget) else parse_resolution(r)
        if t.label in [x.label for x in targets]:
            raise ValueError(f"resolution {t.label!r} requested twice")
        targets.append(t)
    if not targets:
        raise ValueError("give at least one --resolution (e.g. original)")
    return targets


@one_torch_thread
def compute_maps(seq: Sequence, resolutions: Iterable[str | ResolutionTarget] = ("original",), *,
                 metrics: Iterable[str] = ("liv", "ocds", "mean_db"),
                 ocds_delay_range_s: tuple[float, float] = DEFAULT_OCDS_DELAY_RANGE_S,
                 ocds_scale: str = "db", ocds_estimator: str = "pearson",
                 aliv_smoothing: bool = True, aliv_max_window_s: float | None = None,
                 axial_center: str | float = "zero", edge_mode: str = "reflect", normalization: str = "power",
                 drop_boundary: bool = True, device: str | torch.device | None = None,
                 bulk_phase: str | BulkPhase | None = None,
                 slab_elements: int = 1 << 23, chunk_pixels: int = 1 << 16, progress: bool = False,
                 timings: dict[str, float] | None = None) -> Maps:
    """DOCT maps of ``seq`` at every resolution in ``resolutions`` (see the module docstring).

    ``metrics``: any of ``liv``, ``ocds``, ``mean_db``, ``aliv``, ``swiftness``. ``axial_center``,
    ``edge_mode``, ``normalization``: :func:`torchdoct.measured.resolution.reduce_resolution`.
    ``drop_boundary``: drop the block-boundary B-scans of a block raster volume. ``bulk_phase``: a
    method of :mod:`torchdoct.measured.bulkphase` (estimated here with its defaults) or a
    :class:`~torchdoct.measured.bulkphase.BulkPhase` estimated from ``seq``: each A-line's frames are
    multiplied by ``exp(−iφ̂_i)`` before the resolution reduction (the intensity maps at the original
    resolution do not read the phase and are unchanged bit for bit); recorded as
    ``meta["bulk_phase"]``; intensity-only input is refused. ``slab_elements``:
    complex samples per depth slab; ``chunk_pixels``: pixels per metric chunk (memory only).
    ``timings`` (optional dict) receives seconds per resolution label. Returns :class:`Maps`
    (float32 ``[C, (Y), Z, X]``, channels ``f"{metric}@{resolution}"``).
    """
    wanted = [m for m in METRICS if m in set(metrics)]
    unknown = sorted(set(metrics) - set(METRICS))
    if unknown or not wanted:
        raise ValueError(f"unknown metrics {unknown}; choose from {', '.join(METRICS)}")
    if edge_mode not in EDGE_MODES:
        raise ValueError(f"edge_mode must be one of {', '.join(EDGE_MODES)}; got {edge_mode!r}")
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {', '.join(NORMALIZATIONS)}; got {normalization!r}")
    targets = _as_targets(resolutions)
    src = seq.source or "sequence"
    from ..resources import check_maps  # the one resource check of every command, before any work
    check_maps(src, seq.data.shape, seq.data.dtype.itemsize, complex_samples=seq.is_complex,
               n_resolutions=len(targets), metrics=wanted, slab_elements=slab_elements)
    if seq.n_frames < 2:
        raise ValueError(f"{src}: {seq.n_frames} frame along T; DOCT maps need at least 2 frames (LIV is a variance "
                         "over frames); check the file or --axes")
    if any(t.lateral_resolution_um is not None or t.axial_resolution_um is not None for t in targets):
        system = seq.system  # a resolution target needs the original optics (a clear error names the options)
    else:  # original resolution only: the optics are recorded when known, never required
        system = {k: v for k, v in dict(seq.meta.get("system") or {}).items() if v is not None}
    known = "lateral_resolution_um" in system and "axial_resolution_um" in system
    lat0 = float(system["lateral_resolution_um"]) if known else None
    ax0 = float(system["axial_resolution_um"]) if known else None

    def optics(t: ResolutionTarget) -> tuple[float | None, float | None]:
        return t.resolved(system) if known else (None, None)

    changes = [t for t in targets if optics(t) != (lat0, ax0)]
    for t in targets:  # validate every target before any work
        if t.lateral_resolution_um is not None:
            lateral_filter_sigma_um(lat0, t.lateral_resolution_um)
            if t in changes:  # the grid must hold the target PSF (two pixels at least)
                check_target_sampled("lateral", lat0, t.lateral_resolution_um, seq.pitch_um, seq.axes)
        if t.axial_resolution_um is not None:
            axial_filter_sigma_um(ax0, t.axial_resolution_um)
            if t in changes:
                check_target_sampled("axial", ax0, t.axial_resolution_um, seq.pitch_um, seq.axes)
    if changes and not seq.is_complex:
        raise ValueError(f"{seq.source or 'sequence'} holds intensity only (dtype {seq.data.dtype}): a resolution "
                         f"change ({', '.join(t.label for t in changes)}) needs the complex field; use "
                         "--resolution original only")
    times = seq.frame_times_s
    if "ocds" in wanted:
        lo, hi = ocds_delay_range_s
        if not (0 < lo < hi):
            raise ValueError(f"ocds_delay_range_s must be 0 < lo < hi (s); got {ocds_delay_range_s!r}")
        probe = torch.rand(1, len(times), generator=torch.Generator().manual_seed(0)) + 1.0
        ocds_map(probe, times, delay_range_s=(lo, hi), scale=ocds_scale, estimator=ocds_estimator)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    if isinstance(bulk_phase, str):
        bulk_phase = estimate_bulk_phase(seq, bulk_phase, slab_elements=slab_elements, device=dev, progress=progress)
    elif bulk_phase is not None and not isinstance(bulk_phase, BulkPhase):
        raise TypeError(f"bulk_phase must be a method name or a BulkPhase; got {type(bulk_phase).__name__}")
    bulk = None
    if bulk_phase is not None:
        if not seq.is_complex:
            raise ValueError(f"{src} holds intensity only (dtype {seq.data.dtype}): bulk-phase correction needs the "
                             "complex field; give the complex sequence, or drop --bulk-phase")
        bulk = torch.from_numpy(_bulk_phasor(bulk_phase, seq)).to(dev)  # [T, (Y), 1, X]: broadcasts over depth
    data = seq.data
    axes = seq.axes
    zdim = axes.index("Z")
    n_z = data.shape[zdim]
    per_row = int(np.prod(data.shape)) // n_z
    fc: float | str = axial_center
    if axial_center == "centroid" and seq.is_complex and any(t.axial_resolution_um is not None for t in changes):
        sub = torch.from_numpy(np.ascontiguousarray(data[: min(4, data.shape[0])], dtype=native))
        fc = depth_spectrum_center(sub, axes=axes)
    elif isinstance(axial_center, str) and axial_center not in ("zero", "centroid"):
        raise ValueError(f"axial_center must be 'zero', 'centroid' or a number (cycles/pixel); got {axial_center!r}")
    margin = 1 if (aliv_smoothing and ("aliv" in wanted or "swiftness" in wanted)) else 0
    real_dtype = np.float64 if data.dtype in (np.complex128, np.float64) else np.float32
    native = data.dtype.newbyteorder("=")  # big-endian files are read in native byte order
    peak = _peak_intensity(data, src)
    floor = peak * (EMPTY_FLOOR_EPS_FACTOR * float(np.finfo(real_dtype).eps)) ** 2
    outputs = wanted + ([FIT_FLAG] if ("aliv" in wanted or "swiftness" in wanted) else [])
    out = np.full((len(targets) * len(outputs), *data.shape[1:]), np.nan, dtype=real_dtype)

    plans = []
    for t in targets:
        lat, ax = optics(t)
        sig = axial_filter_sigma_um(ax0, ax) / seq.pitch_um["z"] if ax != ax0 else 0.0
        if sig and lat == lat0 and "Y" in axes:
            # axial only, volume: chunk over B-scans (whole depth columns, no halo; aLIV smoothing is per B-scan)
            cdim, halo, mrg = 1, 0, 0
            n_c = data.shape[1]
            rows = max(1, min(n_c, int(slab_elements) // max(int(np.prod(data.shape)) // n_c, 1)))
        else:  # depth slabs with a halo for the axial window and the 3x3 smoothing
            cdim, mrg, n_c = zdim, margin, n_z
            halo = (int(math.ceil(5.0 * sig)) + 1 if sig else 0) + margin
            rows = max(1, min(n_c, int(slab_elements) // max(per_row, 1)))
            if sig:
                rows = n_c if edge_mode == "wrap" else min(n_c, max(rows, 2 * halo))
        reach = nonfinite_reach_px(seq, t) if t in changes else {}
        plans.append((t, cdim, n_c, halo, mrg, rows, reach))
    total = sum(math.ceil(n_c / plan[5]) for plan in plans)
    nonfinite_pixels: dict[str, int] = {}
    n_nonfinite = 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc="maps", unit="slab")
    channels: list[dict[str, Any]] = []
    for ti, (t, cdim, n_c, halo, mrg, rows, reach) in enumerate(plans):
        lat, ax = optics(t)
        wl = system.get("wavelength_um")
        for m in outputs:
            channels.append({"name": f"{m}@{t.label}", "metric": m, "unit": UNITS[m], "resolution": t.label,
                             "wavelength_um": None if wl is None else float(wl), "lateral_resolution_um": lat,
                             "axial_resolution_um": ax})
        t0 = time.perf_counter()
        for c0 in range(0, n_c, rows):
            c1 = min(n_c, c0 + rows)
            a0, a1 = max(0, c0 - halo), min(n_c, c1 + halo)
            sel = [slice(None)] * data.ndim
            sel[cdim] = slice(a0, a1)
            block = torch.from_numpy(np.array(data[tuple(sel)], dtype=native, copy=True)).to(dev)
            if bulk is not None and t in changes:  # bulk phase removed before the A-lines are mixed
                psel = list(sel)
                psel[zdim] = slice(None)
                block = block * bulk[tuple(psel)]
            bad = None
            fin = torch.isfinite(block)
            if not bool(fin.all()):  # masked per pixel: non-finite samples enter the reduction as 0
                bad = (~fin).any(dim=0).cpu().numpy()  # [(Y), Z, X] over a0:a1
                if ti == 0:
                    n_nonfinite += int((~fin).narrow(cdim, c0 - a0, c1 - c0).sum())
                block = torch.where(fin, block, torch.zeros_like(block))
            del fin
            if t in changes:
                red = reduce_resolution(block, pitch_um=seq.pitch_um, system=system,
                                        lateral_resolution_um=t.lateral_resolution_um,
                                        axial_resolution_um=t.axial_resolution_um, axes=axes,
                                        axial_center=fc, edge_mode=edge_mode, normalization=normalization)
            else:
                red = block
            m0, m1 = max(a0, c0 - mrg), min(a1, c1 + mrg)
            red = red.narrow(cdim, m0 - a0, m1 - m0)
            if red.is_complex():
                inten = red.real ** 2 + red.imag ** 2
            else:
                inten = red.to(torch.float64 if real_dtype == np.float64 else torch.float32)
            if t in changes:  # FFT round-off of the reduction is no signal: treated as I = 0 (module docstring)
                inten = torch.where(inten > floor, inten, torch.zeros_like(inten))
            vals = _pixel_metrics(inten, times, wanted, ocds_delay_range_s=tuple(ocds_delay_range_s),
                                  ocds_scale=ocds_scale, ocds_estimator=ocds_estimator,
                                  aliv_smoothing=aliv_smoothing, aliv_max_window_s=aliv_max_window_s,
                                  chunk_pixels=chunk_pixels)
            masks = {}
            if bad is not None:
                sp = axes[1:]
                masks["pixel"] = _nonfinite_reach(bad, sp, reach, edge_mode == "wrap")
                if margin:
                    grown = {c: reach.get(c, 0) + (margin if c in "ZX" else 0) for c in "YZX"}
                    masks["smoothed"] = _nonfinite_reach(bad, sp, grown, edge_mode == "wrap")
                core = [slice(None)] * (data.ndim - 1)
                core[cdim - 1] = slice(c0 - a0, c1 - a0)
                masks = {k: v[tuple(core)] for k, v in masks.items()}
                nonfinite_pixels[t.label] = nonfinite_pixels.get(t.label, 0) + int(np.count_nonzero(masks["pixel"]))
            for mi, m in enumerate(outputs):
                v = vals[m].narrow(cdim - 1, c0 - m0, c1 - c0).cpu().numpy()
                if masks:
                    smoothed = m in ("aliv", "swiftness", FIT_FLAG) and "smoothed" in masks
                    v = np.where(masks["smoothed" if smoothed else "pixel"], np.nan, v)
                idx = [ti * len(outputs) + mi] + [slice(None)] * (data.ndim - 1)
                idx[cdim] = slice(c0, c1)
                out[tuple(idx)] = v
            if bar is not None:
                bar.update(1)
        if timings is not None:
            timings[t.label] = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    meta: dict[str, Any] = {
        "channels": channels,
        "axes": "C" + axes[1:],
        "pitch_um": seq.meta.get("pitch_um"),
        "frame_times_s": times,
        "system": system,
        "ocds_delay_range_s": [float(v) for v in ocds_delay_range_s],
        "ocds_scale": ocds_scale,
        "ocds_estimator": ocds_estimator,
        "source": seq.source,
        "empty_rule": {"rule": EMPTY_RULE, "floor_relative_db": 10.0 * math.log10(floor / peak),
                       "floor": floor, "max_intensity": peak},
        "reduction": {"edge_mode": edge_mode, "normalization": normalization,
                      "axial_center": axial_center if isinstance(axial_center, str) else float(axial_center),
                      "axial_center_cycles_per_pixel": float(fc) if not isinstance(fc, str) else 0.0,
                      "lateral_axes": "YX" if "Y" in axes else "X"},
    }
    if bulk_phase is not None:
        meta["bulk_phase"] = bulk_phase.meta()
    if n_nonfinite:
        meta["nonfinite"] = {"samples": n_nonfinite,
                             "masked_pixels": {t.label: nonfinite_pixels.get(t.label, 0) for t in targets},
                             "rule": "pixels a non-finite sample reaches (its own; within 5 sigma of the reduction "
                                     "window along each filtered axis) are NaN in every channel"}
    if "aliv" in wanted or "swiftness" in wanted:
        meta["aliv"] = {"smoothing": "box3x3" if aliv_smoothing else "none", "max_window_s": aliv_max_window_s,
                        "model": "a*(1-exp(-T/tau)); aliv=a, swiftness=1/tau"}
    raster = seq.block_raster
    if raster is not None:
        meta["block_raster"] = raster.to_dict()
        keep = raster.keep_y() if drop_boundary else np.ones(raster.n_y, dtype=bool)
        out = out[:, keep]
        meta["y_indices"] = [int(i) for i in np.flatnonzero(keep)]
    if FIT_FLAG in outputs:
        meta["aliv"]["flag"] = (f"{FIT_FLAG} channel: 1 where the fit ended on the lower τ bound (curve flat over the "
                                "windows), 2 on the upper bound (still rising at the longest window), 0 inside, NaN "
                                "undefined; aLIV/Swiftness there are bounds of the model, not measurements")
        meta["aliv"]["flagged_pixels"] = {
            c["resolution"]: {"tau_at_lower_bound": int(np.sum(out[i] == 1)), "tau_at_upper_bound": int(np.sum(out[i] == 2))}
            for i, c in enumerate(channels) if c["metric"] == FIT_FLAG}
    return Maps(maps=out.astype(np.float32, copy=False), channels=tuple(c["name"] for c in channels), meta=meta)


# ----------------------------------------------------------------------------------------------
# pseudo-colour images


def pseudo_color(value: np.ndarray, intensity_db: np.ndarray | None, *, value_range: tuple[float, float],
                 db_range: tuple[float, float] | None = None,
                 hue_range: tuple[float, float] = DEFAULT_HUE_RANGE, flagged: np.ndarray | None = None) -> np.ndarray:
    """RGB uint8 ``[H, W, 3]``: hue = ``value`` over ``value_range``, brightness = dB intensity.

    HSV composition as DOCT images are shown: hue ``hue_range[0] + (hue_range[1] − hue_range[0])·
    clip((v − lo)/(hi − lo), 0, 1)`` (default red for low, green for high), saturation 1, value
    ``clip((dB − db_lo)/(db_hi − db_lo), 0, 1)`` (1 everywhere without an intensity image). NaN values
    are shown grey (saturation 0) at their brightness; ``flagged`` pixels (bool, e.g. an aLIV fit on a
    τ bound) are shown in :data:`FLAG_RGB` (magenta, outside the red-green hue scale) at full brightness.
    """
    from matplotlib.colors import hsv_to_rgb

    v = np.asarray(value, dtype=np.float64)
    lo, hi = (float(x) for x in value_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"value range must be finite with hi > lo; got {value_range!r}")
    frac = np.clip((v - lo) / (hi - lo), 0.0, 1.0)
    hue = hue_range[0] + (hue_range[1] - hue_range[0]) * np.nan_to_num(frac)
    if intensity_db is None:
        bright = np.ones_like(v)
    else:
        if db_range is None:
            raise ValueError("db_range is needed with an intensity image")
        dlo, dhi = (float(x) for x in db_range)
        if not (math.isfinite(dlo) and math.isfinite(dhi) and dhi > dlo):
            raise ValueError(f"dB range must be finite with hi > lo; got {db_range!r}")
        bright = np.nan_to_num(np.clip((np.asarray(intensity_db, dtype=np.float64) - dlo) / (dhi - dlo), 0, 1))
    sat = np.where(np.isfinite(v), 1.0, 0.0)
    rgb = np.round(hsv_to_rgb(np.stack([np.mod(hue, 1.0), sat, bright], axis=-1)) * 255.0).astype(np.uint8)
    if flagged is not None:
        rgb[np.asarray(flagged, dtype=bool)] = FLAG_RGB
    return rgb


def png_name(out_path: str | Path, channel: str) -> Path:
    """``OUT_STEM_metric_resolution.png`` beside ``out_path`` (``=`` and ``,`` removed from the label)."""
    out = Path(out_path)
    metric, _, res = channel.partition("@")
    label = res.replace("=", "").replace(",", "-").replace(".", "p")
    return out.with_name(f"{out.stem}_{metric}_{label}.png")


def _auto_range(values: list[np.ndarray], lo_pct: float, hi_pct: float) -> tuple[float, float]:
    v = np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in values])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (0.0, 1.0)
    lo, hi = np.percentile(v, [lo_pct, hi_pct])
    if not hi > lo:
        hi = lo + 1.0
    return float(lo), float(hi)


_TITLES = {"liv": "LIV", "ocds": "OCDS", "mean_db": "mean intensity", "aliv": "aLIV", "swiftness": "Swiftness",
           FIT_FLAG: "aLIV fit on a τ bound"}


def _optics_text(info: Mapping[str, Any]) -> str:
    lat, ax, wl = (info.get(k) for k in ("lateral_resolution_um", "axial_resolution_um", "wavelength_um"))
    if lat is None or ax is None:
        return "original resolution (optics not given)"
    return f"lateral {float(lat):g} µm, axial {float(ax):g} µm" + (f", {float(wl) * 1000:g} nm" if wl else "")


def map_figure(maps: Maps, channel: str, *, value_range: tuple[float, float] | None = None,
               db_range: tuple[float, float] | None = None, hue_range: tuple[float, float] = DEFAULT_HUE_RANGE,
               y_index: int | None = None) -> Any:
    """A quantitative figure of one channel: the image on µm axes (:mod:`torchdoct.figures`), a colour
    bar with the unit and the value range, the channel name and its resolution in the title.

    DOCT channels are drawn by :func:`pseudo_color` (brightness from the ``mean_db`` channel of the
    same resolution over ``db_range``; aLIV/Swiftness pixels whose fit ended on a τ bound, from the
    ``aliv_fit`` channel, in :data:`FLAG_RGB`; undefined pixels grey), ``mean_db`` in grey scale.
    ``value_range`` defaults to the channel's 1st-99th percentile, ``db_range`` to the 5th-99.9th
    percentile of its ``mean_db``. Volumes show the B-scan ``y_index`` (default the middle one).
    Returns the matplotlib ``Figure`` (the caller saves and closes it).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, Normalize, hsv_to_rgb
    from matplotlib.patches import Patch

    from ..figures import show_bscan, unit_text

    info = maps.channel_info(channel)
    metric, res = info["metric"], info["resolution"]

    def plane(name: str) -> np.ndarray:
        a = maps[name]
        return a[y] if a.ndim == 3 else a

    y = None
    if maps.maps.ndim == 4:
        n_y = maps.maps.shape[1]
        y = n_y // 2 if y_index is None else int(y_index)
        if not 0 <= y < n_y:
            raise ValueError(f"--png-y {y_index} is outside 0..{n_y - 1}")
    v = plane(channel)
    vr = value_range or _auto_range([v], 1.0, 99.0)
    unit = unit_text(info.get("unit"))
    name = _TITLES.get(metric, metric)
    h, w = v.shape
    aspect = (w * float((maps.meta.get("pitch_um") or {}).get("x", 1.0) or 1.0)) / max(
        h * float((maps.meta.get("pitch_um") or {}).get("z", 1.0) or 1.0), 1e-9)
    fig_w = min(max(4.5 * aspect, 3.5), 11.0) + 2.6
    fig, ax = plt.subplots(figsize=(fig_w, 5.0))
    handles = []
    extra = ""
    n_nan = int(np.sum(~np.isfinite(v)))
    if metric == "mean_db":
        cmap = plt.get_cmap("gray").with_extremes(bad="#6f9fcf")
        show_bscan(ax, np.ma.masked_invalid(v), pitch_um=maps.meta.get("pitch_um"), cmap=cmap, vmin=vr[0], vmax=vr[1])
        sm = ScalarMappable(norm=Normalize(*vr), cmap=cmap)
        if n_nan:
            handles.append(Patch(color="#6f9fcf", label=f"no intensity ({n_nan} px)"))
    else:
        db_name = next((c["name"] for c in maps.meta["channels"] if c["metric"] == "mean_db"
                        and c["resolution"] == res), None)
        db = plane(db_name) if db_name else None
        dr = db_range or (_auto_range([db], 5.0, 99.9) if db is not None else None)
        flag_name = f"{FIT_FLAG}@{res}"
        flagged = None
        if metric in ("aliv", "swiftness") and flag_name in maps.channels:
            with np.errstate(invalid="ignore"):
                flagged = plane(flag_name) > 0
        rgb = pseudo_color(v, db, value_range=vr, db_range=dr if db is not None else None, hue_range=hue_range,
                           flagged=flagged)
        show_bscan(ax, rgb, pitch_um=maps.meta.get("pitch_um"))
        hues = np.linspace(hue_range[0], hue_range[1], 256)
        cmap = ListedColormap(hsv_to_rgb(np.stack([np.mod(hues, 1.0), np.ones(256), np.ones(256)], -1)))
        sm = ScalarMappable(norm=Normalize(*vr), cmap=cmap)
        if n_nan:
            handles.append(Patch(color="0.6", label=f"undefined, no dB value: grey, black without intensity "
                                                    f"({n_nan} px)"))
        if flagged is not None and flagged.any():
            handles.append(Patch(color=np.array(FLAG_RGB) / 255.0, label=f"fit on a τ bound ({int(flagged.sum())} px)"))
        if db is not None:
            extra = f"\nbrightness: mean intensity {dr[0]:.3g} … {dr[1]:.3g} dB"
    cb = fig.colorbar(sm, ax=ax, shrink=0.85)
    cb.set_label(f"{name} ({unit}): {vr[0]:.4g} … {vr[1]:.4g}")
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.8)
    where = "" if y is None else f", B-scan y = {y}"
    ax.set_title(f"{name} [{channel}]\n{_optics_text(info)}{where}{extra}", fontsize=9)
    fig.tight_layout()
    return fig


def write_pngs(maps: Maps, out_path: str | Path, *, ranges: Mapping[str, tuple[float, float]] | None = None,
               db_range: tuple[float, float] | None = None, hue_range: tuple[float, float] = DEFAULT_HUE_RANGE,
               y_index: int | None = None, force: bool = False, check_only: bool = False) -> list[Path]:
    """One figure PNG per channel (:func:`map_figure`), named by :func:`png_name`; the ``aliv_fit``
    flags are drawn inside the aLIV/Swiftness images, not as images of their own.

    ``ranges``: ``{metric: (lo, hi)}``; a metric without one gets the 1st-99th percentile of its
    finite values pooled over all resolutions (so resolutions share one colour scale).
    ``db_range``: default the 5th-99.9th percentile of all ``mean_db`` values (the brightness of the
    DOCT images and the grey scale of ``mean_db``). Volumes ``[C, Y, Z, X]`` show the B-scan
    ``y_index`` (default the middle one). All paths are checked before writing; existing files need
    ``force``. ``check_only`` returns the paths without writing.
    """
    infos = [c for c in maps.meta["channels"] if c["metric"] != FIT_FLAG]
    paths = [png_name(out_path, c["name"]) for c in infos]
    for p in paths:
        check_out(p, force, ".png", what="PNG output")
    if check_only:
        return paths
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arr = maps.maps
    if arr.ndim == 4:
        y = arr.shape[1] // 2 if y_index is None else int(y_index)
        if not 0 <= y < arr.shape[1]:
            raise ValueError(f"--png-y {y_index} is outside 0..{arr.shape[1] - 1}")
        arr = arr[:, y]
    by_metric: dict[str, list[np.ndarray]] = {}
    for c in infos:
        by_metric.setdefault(c["metric"], []).append(arr[maps.index(c["name"])])
    ranges = dict(ranges or {})
    if db_range is None and "mean_db" in by_metric:
        db_range = _auto_range(by_metric["mean_db"], 5.0, 99.9)
    for info, path in zip(infos, paths):
        metric = info["metric"]
        vr = ranges.get(metric) or (db_range if metric == "mean_db" and db_range else
                                    _auto_range(by_metric[metric], 1.0, 99.0))
        fig = map_figure(maps, info["name"], value_range=vr, db_range=db_range, hue_range=hue_range, y_index=y_index)
        try:
            atomic_write(path, lambda tmp, fig=fig: fig.savefig(tmp, format="png", dpi=100))
        finally:
            plt.close(fig)
    return paths


# ----------------------------------------------------------------------------------------------
# benchmark


def bench_maps(*, frames: int = 32, shape: tuple[int, int] = (512, 512),
               resolutions: _Seq[str] = ("original", "axial=14", "lateral=18"),
               metrics: _Seq[str] = ("liv", "ocds", "mean_db"), repeats: int = 1, seed: int = 0) -> dict[str, Any]:
    """Time :func:`compute_maps` on a random complex64 ``[frames, *shape]`` stack (measured, never asserted).

    System: 840 nm, 4.9 µm lateral / 3.8 µm axial; pitch 1.5 µm (z) × 2.0 µm (x); 204.8 ms frames.
    Returns a JSON-ready dict with the best total time over ``repeats`` and seconds per resolution.
    """
    from ..bench import machine_info
    from .io import validate_meta

    g = torch.Generator().manual_seed(int(seed))
    data = torch.randn(frames, *shape, dtype=torch.complex64, generator=g).numpy()
    meta = validate_meta({"axes": "TZX", "pitch_um": {"z": 1.5, "x": 2.0},
                          "frame_times_s": [i * 0.2048 for i in range(frames)],
                          "system": {"name": "840nm-high", "wavelength_um": 0.84, "lateral_resolution_um": 4.9,
                                     "axial_resolution_um": 3.8}}, data.shape)
    seq = Sequence(data=data, meta=meta, source="bench")
    compute_maps(seq, ["original"], metrics=metrics)  # warm-up
    best, best_t = math.inf, {}
    for _ in range(max(1, int(repeats))):
        tm: dict[str, float] = {}
        t0 = time.perf_counter()
        compute_maps(seq, resolutions, metrics=metrics, timings=tm)
        dt = time.perf_counter() - t0
        if dt < best:
            best, best_t = dt, tm
    return {
        "benchmark": "maps",
        "shape": [frames, *shape],
        "dtype": "complex64",
        "resolutions": list(resolutions),
        "metrics": list(metrics),
        "repeats": int(repeats),
        "seconds_total": best,
        "seconds_per_resolution": best_t,
        "megapixel_frames_per_s": frames * shape[0] * shape[1] * len(resolutions) / best / 1e6,
        "target_seconds": 10.0,
        "machine": machine_info(),
    }

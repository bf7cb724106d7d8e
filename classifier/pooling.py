"""Pooling of the classify path: features averaged over N × N (z, x) neighbourhoods, and how many
independent pixels that average holds (numpy only).

Every feature is averaged over the valid pixels of the N × N neighbourhood in the (z, x) plane of each
B-scan (:func:`pool_features`). The model's ``pool_pixels`` input is the number of *independent* pixels
averaged: the valid count times the independence fraction of the pixel grid (:func:`independent_fraction`),
``n_e(N, p_x, s_x)·n_e(N, p_z, s_z)/N²`` with ``n_e = N²/Σ_ij exp(−((i−j)p)²/(2s²))`` the effective
sample count of N pixels of pitch ``p`` under the speckle intensity correlation of a Gaussian amplitude
PSF of sigma ``s`` (finest configuration of the spec, sigmas from :mod:`torchdoct.conventions`;
docs/physics.md §5.3 overlap of displaced Gaussians). Without ``pitch_um`` in the maps, pixels count as
independent.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from torchdoct import conventions

from .features import FeatureSpec

__all__ = ["pool_features", "effective_count", "independent_fraction", "model_inputs"]


def _box_sum(a: np.ndarray, n: int, axis: int) -> np.ndarray:
    """Sum over the window ``[i − n//2, i + n − 1 − n//2]`` along ``axis`` (zeros outside).

    Small windows (n ≤ 8) add n shifted slices (direct sums, 4× faster than a cumulative sum along
    a non-contiguous axis); larger ones difference a cumulative sum (cost independent of n).
    """
    h1 = n // 2
    if n <= 8:
        length = a.shape[axis]
        out = np.zeros_like(a)
        for d in range(-h1, n - h1):  # out[i] += a[i + d] where i + d is inside
            dst = [slice(None)] * a.ndim
            src = [slice(None)] * a.ndim
            dst[axis] = slice(max(0, -d), min(length, length - d))
            src[axis] = slice(max(0, d), min(length, length + d))
            out[tuple(dst)] += a[tuple(src)]
        return out
    h2 = n - 1 - h1
    pad = [(0, 0)] * a.ndim
    pad[axis] = (h1 + 1, h2)
    c = np.cumsum(np.pad(a, pad), axis=axis)
    length = a.shape[axis]
    hi = [slice(None)] * a.ndim
    lo = [slice(None)] * a.ndim
    hi[axis], lo[axis] = slice(n, n + length), slice(0, length)
    return c[tuple(hi)] - c[tuple(lo)]


def pool_features(features: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each feature over the valid pixels of every N × N (z, x) neighbourhood.

    ``features [F, *S]``, ``valid [*S]`` (bool); returns ``(pooled [F, *S] float32, counts [*S])``
    with NaN where no valid pixel is in the window. ``n = 1`` returns the input.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"pool must be a positive integer (N for N × N); got {n!r}")
    if n == 1:
        return features, valid.astype(np.int64)
    # windows of up to 8 add shifted slices: float32 sums of at most 64 terms (relative error ~1e-7, a
    # few times faster than float64); larger ones difference a cumulative sum, kept in float64
    dt = np.float32 if n <= 8 else np.float64
    w = valid.astype(dt)
    f = np.where(valid, features.astype(dt, copy=False), dt(0.0))
    zax, xax = valid.ndim - 2, valid.ndim - 1
    counts = _box_sum(_box_sum(w, n, zax), n, xax)
    sums = _box_sum(_box_sum(f, n, zax + 1), n, xax + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return pooled.astype(np.float32), np.rint(counts).astype(np.int64)


def effective_count(n: int, pitch_um: float, sigma_um: float) -> float:
    """Effective number of independent samples among n pixels (speckle intensity correlation)."""
    k = np.arange(n)
    d = (k[:, None] - k[None, :]) * pitch_um
    r = np.exp(-(d**2) / (2.0 * sigma_um**2))
    return float(n * n / r.sum())


def independent_fraction(n: int, pitch_um: dict[str, Any] | None, spec: FeatureSpec) -> float:
    """Fraction of the N × N pixels that count as independent (module docstring)."""
    if n == 1 or not pitch_um:
        return 1.0
    conv = conventions
    s_x = min(conv.amplitude_sigma_lateral_um(c.lateral_resolution_um) for c in spec.configurations)
    s_z = min(conv.amplitude_sigma_axial_um(c.axial_resolution_um) for c in spec.configurations)
    try:
        px, pz = float(pitch_um["x"]), float(pitch_um["z"])
    except (KeyError, TypeError, ValueError):
        return 1.0
    if not (px > 0 and pz > 0):
        return 1.0
    return effective_count(n, px, s_x) * effective_count(n, pz, s_z) / (n * n)


def model_inputs(
    features: np.ndarray, valid: np.ndarray, n: int, fraction: float, pool_pixels_max: int
) -> tuple[np.ndarray, np.ndarray]:
    """The model's input rows of the valid pixels and their flat indices: ``(x [N, F+1] float32, idx [N])``.

    Columns: the features pooled over N × N (:func:`pool_features`), then ``pool_pixels``, the valid
    count of the window times ``fraction`` (:func:`independent_fraction`) clipped to
    [1, ``pool_pixels_max``].
    """
    pooled, counts = pool_features(features, valid, int(n))
    idx = np.flatnonzero(valid)
    x = np.empty((idx.size, features.shape[0] + 1), np.float32)
    flat = pooled.reshape(features.shape[0], -1)
    x[:, :-1] = (flat if idx.size == flat.shape[1] else flat[:, idx]).T
    x[:, -1] = np.clip(counts.reshape(-1)[idx] * fraction, 1.0, float(pool_pixels_max))
    return x, idx

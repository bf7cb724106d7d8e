"""Patch simulation: the complex time series of a small B-scan or volume patch that shares one scatterer
realisation, for the speckle-motion features (:mod:`torchdoct.sim.speckle`) of its pixels.

Each trial is an independent homogeneous Poisson medium (density ``ρ``) in a box centred on the patch;
every pixel ``r_p`` of the patch sees the point model's sum (physics.md §5.1, the renderer's signal,
:mod:`torchdoct.image.render`)::

    E(r_p, t) = Σ_j b·h(r_j(t) − r_p)·exp(i·2kn·z_j(t)),
    h(r) = exp(−x²/(2s_x²) − y²/(2s_y²) − z²/(2s_z²))   (torchdoct.conventions)

evaluated exactly (no truncation of the Gaussian) for every scatterer of the box. The box covers the
patch, the PSF to the amplitude ``tolerance`` around it (``√(2 ln(1/tol))·s`` per axis) and the motion's
reach over the acquisition on each side (``|v_c|·T_total`` for flow, ``v·T_total`` for random ballistic,
``5·√(2·D·T_total)`` for diffusion), so every scatterer that comes within the tolerance of a pixel during
the protocol is in it at the first frame; the scatterers outside it contribute less than ``tol`` of the
PSF peak each. Motions: ``"flow"`` (one displacement ``v·n̂·t`` for all), ``"ballistic"`` (i.i.d. directions
of :func:`torchdoct.sim.samplers.unit_directions`, ``v·n̂_j·t``), ``"diffusion"`` (a Gaussian step of
variance ``2DΔt`` per axis and frame), ``"static"``. Optional: a static population of the same density
with the share ``static_fraction`` of the mean intensity (reflectivity ``√(f/(1−f))``, as
:func:`classifier.dataset.simulate_draw` mixes it) and additive circular Gaussian noise at ``snr_db``
below the mean noise-free intensity (:func:`torchdoct.conventions.noise_sigma`).

Pixels: ``shape = (Z, X)`` (a B-scan patch in the plane ``y = 0``) or ``(Y, Z, X)``, pitch per axis, centred
on the origin. Direction of a flow: ``polar_deg`` from the depth axis ``z``, ``azimuth_deg`` from ``x``
towards ``y`` (``n̂ = (sinθ cosφ, sinθ sinφ, cosθ)`` in ``(x, y, z)``, the convention of the samplers).

Randomness: trial ``i`` draws from its own generator seeded from ``(seed, i)`` and is evaluated alone, so
a seed gives the same numbers whatever ``trials`` or the order of calls. Cost grows with the box
(``ρ·volume`` scatterers per trial, times frames times pixels).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ..conventions import (
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    mean_intensity,
    noise_sigma,
    truncation_radius_factor,
    wavenumber_per_um,
)
from .samplers import unit_directions

__all__ = ["MOTIONS", "PATCH_MAX_SCATTERERS", "patch_box_half_widths_um", "simulate_patch"]

MOTIONS = ("flow", "ballistic", "diffusion", "static")
#: Largest expected number of scatterers per trial's box (a refusal beyond it, before any work).
PATCH_MAX_SCATTERERS = 2e5


def _direction(polar_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    t, p = math.radians(polar_deg), math.radians(azimuth_deg)
    return math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)


def _reach(motion: str, speed: float, diff: float, duration: float, n: tuple[float, float, float]):
    if motion == "flow":
        return tuple(abs(c) * speed * duration for c in n)
    if motion == "ballistic":
        return (speed * duration,) * 3
    if motion == "diffusion":
        return (5.0 * math.sqrt(2.0 * diff * duration),) * 3
    return (0.0, 0.0, 0.0)


def patch_box_half_widths_um(
    shape: Sequence[int],
    pitch_um: Sequence[float],
    sigmas_um: Sequence[float],
    reach_um: Sequence[float],
    tolerance: float,
) -> tuple[float, float, float]:
    """Half-widths ``(x, y, z)`` (µm) of the seeded box (module docstring); ``shape``/``pitch_um`` in
    array order ``(Z, X)`` or ``(Y, Z, X)``, ``sigmas_um``/``reach_um`` as ``(x, y, z)``."""
    c = truncation_radius_factor(tolerance)
    ext = {"x": 0.0, "y": 0.0, "z": 0.0}
    letters = "zx" if len(shape) == 2 else "yzx"
    for a, n, p in zip(letters, shape, pitch_um):
        ext[a] = (int(n) - 1) * float(p) / 2.0
    return tuple(ext[a] + c * s + r for a, s, r in zip("xyz", sigmas_um, reach_um))


def simulate_patch(
    motion: str,
    *,
    trials: int,
    seed: int,
    shape: Sequence[int] = (13, 13),
    pitch_um: Sequence[float] = (2.0, 2.0),
    n_frames: int = 32,
    frame_interval_s: float = 0.2048,
    speed_um_s: float = 0.0,
    diffusion_um2_s: float = 0.0,
    polar_deg: float = 0.0,
    azimuth_deg: float = 0.0,
    density_per_um3: float = 0.055,
    wavelength_um: float = 0.84,
    lateral_resolution_um: float = 4.9,
    axial_resolution_um: float = 3.8,
    lateral_resolution_y_um: float | None = None,
    refractive_index: float = 1.0,
    direction_law: str = "isotropic",
    static_fraction: float = 0.0,
    snr_db: float | None = None,
    tolerance: float = 1e-3,
    dtype: torch.dtype = torch.complex64,
) -> torch.Tensor:
    """Complex fields ``[trials, T, *shape]`` of a patch (module docstring; µm, s, degrees)."""
    if motion not in MOTIONS:
        raise ValueError(f"patch motion must be one of {', '.join(MOTIONS)}; got {motion!r}")
    shape = tuple(int(n) for n in shape)
    pitch = tuple(float(p) for p in pitch_um)
    if len(shape) not in (2, 3) or len(pitch) != len(shape) or min(shape) < 1 or min(pitch) <= 0:
        raise ValueError(
            f"a patch is (Z, X) or (Y, Z, X) pixels with a positive pitch per axis; got shape {shape}, pitch {pitch}"
        )
    if not 0.0 <= static_fraction < 1.0:
        raise ValueError(f"static_fraction must be in [0, 1); got {static_fraction!r}")
    if trials < 1 or n_frames < 2 or not frame_interval_s > 0:
        raise ValueError("a patch needs trials >= 1, n_frames >= 2 and a positive frame interval")
    sx = amplitude_sigma_lateral_um(lateral_resolution_um)
    sy = amplitude_sigma_lateral_um(
        lateral_resolution_y_um if lateral_resolution_y_um is not None else lateral_resolution_um
    )
    sz = amplitude_sigma_axial_um(axial_resolution_um)
    kn2 = 2.0 * wavenumber_per_um(wavelength_um, refractive_index)
    duration = (n_frames - 1) * frame_interval_s
    nvec = _direction(polar_deg, azimuth_deg)
    reach = _reach(motion, float(speed_um_s), float(diffusion_um2_s), duration, nvec)
    half = patch_box_half_widths_um(shape, pitch, (sx, sy, sz), reach, tolerance)
    half_s = patch_box_half_widths_um(shape, pitch, (sx, sy, sz), (0.0, 0.0, 0.0), tolerance)
    vol = 8.0 * half[0] * half[1] * half[2]
    if density_per_um3 * vol > PATCH_MAX_SCATTERERS:
        raise ValueError(
            f"a patch box of {density_per_um3 * vol:.3g} expected scatterers per trial exceeds "
            f"{PATCH_MAX_SCATTERERS:.0e}: lower the speed, the diffusion or the patch size"
        )
    letters = "zx" if len(shape) == 2 else "yzx"
    axis_px = {a: (torch.arange(n, dtype=torch.float64) - (n - 1) / 2.0) * p for a, n, p in zip(letters, shape, pitch)}
    if "y" not in axis_px:
        axis_px["y"] = torch.zeros(1, dtype=torch.float64)
    sig = {"x": sx, "y": sy, "z": sz}
    a_static = math.sqrt(static_fraction / (1.0 - static_fraction)) if static_fraction > 0 else 0.0
    mean_i = mean_intensity(
        density_per_um3, lateral_resolution_um, axial_resolution_um, lateral_resolution_y_um=lateral_resolution_y_um
    ) * (1.0 + a_static**2)
    out = torch.empty(trials, n_frames, *shape, dtype=dtype)

    def field(pos: torch.Tensor, amp: float) -> torch.Tensor:
        """The patch's field of scatterers ``pos [N, 3]`` (x, y, z) → ``[(Y), Z, X]`` complex128."""
        w = {
            a: torch.exp(-((pos[:, None, i] - axis_px[a][None, :]) ** 2) / (2.0 * sig[a] ** 2))
            for i, a in enumerate("xyz")
        }
        phase = torch.remainder(kn2 * pos[:, 2], 2.0 * math.pi)
        az = (w["z"] * amp) * torch.polar(torch.ones_like(phase), phase)[:, None]  # [N, Z]
        if len(shape) == 2:
            return (az * w["y"][:, :1]).T @ w["x"].to(az.dtype)  # [Z, X]
        return torch.einsum("nz,nx,ny->yzx", az, w["x"].to(az.dtype), w["y"].to(az.dtype))

    for i in range(trials):
        g = torch.Generator().manual_seed(int(np.random.SeedSequence([int(seed), i]).generate_state(1)[0]))
        n = int(torch.poisson(torch.tensor(density_per_um3 * vol, dtype=torch.float64), generator=g))
        lo = torch.tensor([-h for h in half], dtype=torch.float64)
        pos0 = lo + torch.rand(n, 3, generator=g, dtype=torch.float64) * (-2.0 * lo)
        static = None
        if a_static > 0:
            vs = 8.0 * half_s[0] * half_s[1] * half_s[2]
            ns = int(torch.poisson(torch.tensor(density_per_um3 * vs, dtype=torch.float64), generator=g))
            lo_s = torch.tensor([-h for h in half_s], dtype=torch.float64)
            static = field(lo_s + torch.rand(ns, 3, generator=g, dtype=torch.float64) * (-2.0 * lo_s), a_static)
        if motion == "flow":
            vel = torch.tensor(nvec, dtype=torch.float64)[None, :].expand(n, 3) * float(speed_um_s)
        elif motion == "ballistic":
            vel = unit_directions(torch.rand(n, 2, generator=g, dtype=torch.float64), direction_law) * float(speed_um_s)
        step = math.sqrt(2.0 * float(diffusion_um2_s) * frame_interval_s)
        pos = pos0
        noise = None
        if snr_db is not None:
            s_n = noise_sigma(mean_i, float(snr_db))
            noise = (
                torch.complex(
                    torch.randn(n_frames, *shape, generator=g, dtype=torch.float64),
                    torch.randn(n_frames, *shape, generator=g, dtype=torch.float64),
                )
                * s_n
            )
        for t in range(n_frames):
            if motion in ("flow", "ballistic"):
                pos = pos0 + vel * (t * frame_interval_s)
            elif motion == "diffusion" and t > 0:
                pos = pos + torch.randn(n, 3, generator=g, dtype=torch.float64) * step
            e = field(pos, 1.0)
            if static is not None:
                e = e + static
            if noise is not None:
                e = e + noise[t]
            out[i, t] = e.to(dtype)
    return out

"""What a replicate adds to the simulated moving field: static scatterers and detection noise.

:func:`combine_fields` forms ``E_m + a·E_s + n`` (the static share of the mean intensity, common to the
configurations or one per configuration, and circular Gaussian noise at an SNR, physics.md §5.2, §8);
:func:`edge_static_fractions` gives the static share per configuration of a pixel near the edge of its
moving region (physics.md §14). :mod:`classifier.prior` draws the replicates and :mod:`classifier.simulation` calls them.
"""

from __future__ import annotations

import math

__all__ = ["combine_fields", "edge_static_fractions"]


def edge_static_fractions(configurations, edge: tuple[float, float, float, float]) -> list[float]:
    """Each configuration's static share of the mean intensity at a static edge (module docstring).

    ``edge = (d, n_x, n_y, n_z)``: static tissue fills the half-space beyond a plane with unit normal ``n``
    at distance ``d`` from the pixel, ``d`` in units of the largest configuration's ``σ`` along ``n``.
    Configuration ``c``'s intensity PSF ``|h|²`` is Gaussian with SDs ``Δx/4``, ``Δy/4`` (1/e² full widths)
    and ``Δz/(2√(2 ln 2))`` (FWHM), the amplitude SDs of physics.md §5.1 over √2; its SD along ``n`` is
    ``σ_c = √(Σ n_i² σ_i²)``, and the share of it beyond the plane ``f_c = ½·erfc(d·σ_max / (√2·σ_c))``
    (equal scatterer densities and reflectivities on both sides)."""
    from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um

    d, nx, ny, nz = (float(v) for v in edge)
    sig = []
    for c in configurations:
        sx = amplitude_sigma_lateral_um(c.lateral_resolution_um) / math.sqrt(2.0)
        sy = amplitude_sigma_lateral_um(c.lateral_resolution_y_um or c.lateral_resolution_um) / math.sqrt(2.0)
        sz = amplitude_sigma_axial_um(c.axial_resolution_um) / math.sqrt(2.0)
        sig.append(math.sqrt((nx * sx) ** 2 + (ny * sy) ** 2 + (nz * sz) ** 2))
    top = max(sig)
    return [0.5 * math.erfc(d * top / (math.sqrt(2.0) * s)) for s in sig]


def combine_fields(moving, static, static_fraction, snr_db: float, mean_intensity_moving, generator):
    """``E_m + a·E_s + n`` for complex signals ``[trials, systems, frames]`` (see :func:`simulate_draw`).

    ``static_fraction``: the static share of the mean intensity, one number for every system, or one per
    system (a static edge, :func:`edge_static_fractions`); ``a = √(f/(1−f))``.
    ``static`` may be ``None`` when ``static_fraction`` is 0; ``snr_db`` NaN adds no noise;
    ``mean_intensity_moving`` is ``⟨I⟩`` of the moving scatterers per system (static scatterers have
    the same density, so the noise-free total is ``(1 + a²)⟨I⟩``); ``generator`` a ``torch.Generator``.
    """
    import torch

    from torchdoct.conventions import noise_sigma

    per_system = isinstance(static_fraction, (list, tuple))
    fs = [float(v) for v in static_fraction] if per_system else [float(static_fraction)]
    if not all(0.0 <= f < 1.0 for f in fs):
        raise ValueError(f"static_fraction must be in [0, 1); got {static_fraction!r}")
    if per_system and len(fs) != moving.shape[1]:
        raise ValueError(f"static_fraction has {len(fs)} values for {moving.shape[1]} systems")
    if any(f > 0 for f in fs) and static is None:
        raise ValueError("static_fraction > 0 needs the static scatterers' signals")
    if per_system:
        a = torch.tensor([math.sqrt(f / (1.0 - f)) for f in fs], dtype=torch.float32).view(1, -1, 1)
        e = moving + a * static if any(f > 0 for f in fs) else moving
    else:
        a = math.sqrt(fs[0] / (1.0 - fs[0]))
        e = moving if fs[0] == 0 else moving + a * static
    if not math.isnan(snr_db):
        mean_i = torch.as_tensor(mean_intensity_moving, dtype=torch.float32).view(1, -1, 1)
        amp = noise_sigma((1.0 + a * a) * mean_i, snr_db)
        shape = e.shape
        noise = torch.complex(
            torch.randn(shape, generator=generator) * amp, torch.randn(shape, generator=generator) * amp
        )
        e = e + noise
    return e

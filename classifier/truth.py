"""The ground truth of a draw: whether its motion can be told from its LIV and OCDS at all
(:func:`identifiability`), from the closed forms of :mod:`torchdoct.sim.theory`.

**Ground-truth identifiability** (physics.md §5.3-5.4, via :mod:`torchdoct.sim.theory`): a draw is
*indeterminate* when its moving scatterers

* do not decorrelate: the intensity correlation coefficient ``ρ_I(T) = (|g1|² + j/N_eff)/(1 + 1/N_eff)``
  at the first-to-last frame delay ``T`` is ``≥ 1 − ε`` at every configuration (``"static"``): LIV and
  OCDS are those of a static sample whatever the motion; or
* decorrelate completely within one frame interval: ``|g1(Δt)|² ≤ ε`` at every configuration
  (``"decorrelated"``): every frame has a new speckle phase pattern, and all that is left of the
  intensity correlation is the incoherent term ``j/N_eff ≤ 1/(1 + N_eff)``, which only measures how
  fast scatterers cross the PSF (a transit time that diffusion and random-ballistic motion both have;
  flow never gets here in the prior, because for flow ``|g1|² = j`` decays by transit alone),

with ``ε = 0.05``, for every spec: for the signature the definition was re-measured (a transit term
that still decays after the field has decorrelated does not tell the motion types apart per pixel:
:func:`identifiability`). The classifier's ``indeterminate`` class is trained on these draws
(:mod:`classifier.rule`).
"""

from __future__ import annotations

import numpy as np

from .features import FeatureSpec
from .prior import Draw, Prior

__all__ = [
    "STATUS",
    "IDENTIFIABILITY_VERSION",
    "identifiability",
    "transit_decay",
    "lateral_y",
]


def lateral_y(c) -> dict[str, float]:
    """``{"lateral_resolution_y_um": Δy}`` for a configuration with an anisotropic lateral PSF (a B-scan's
    x-only lateral reduction keeps the original width along y), else ``{}`` (isotropic)."""
    return {} if c.lateral_resolution_y_um is None else {"lateral_resolution_y_um": c.lateral_resolution_y_um}


def identifiability(spec: FeatureSpec, draw: Draw, prior: Prior) -> tuple[str, np.ndarray, np.ndarray]:
    """Ground-truth identifiability of a draw (module docstring), with its two criteria per configuration.

    Returns ``(status, g1sq_first [C], rho_last [C])``: status ``"identifiable"``, ``"static"`` or
    ``"decorrelated"``; ``|g1(Δt)|²`` and ``ρ_I(T)`` of the moving scatterers. Formulas: physics.md
    §5.3 (g1), §5.4 (j, N_eff, ``ρ_I = (|g1|² + j/N_eff)/(1 + 1/N_eff)``), via :mod:`torchdoct.sim.theory`.

    The same definition holds for signature specs: a transit term ``j/N_eff`` that still decays over
    the acquisition after the field has decorrelated (:func:`transit_decay`) was measured not to tell
    diffusion from random-ballistic motion per pixel (``python -m classifier.ablation --indeterminate``,
    ``research/classifier-history.md``), so "decorrelated" stays as wide as it is.
    """
    status, first_a, last_a, _ = _criteria(spec, draw, prior)
    return status, first_a, last_a


def transit_decay(spec: FeatureSpec, draw: Draw, prior: Prior) -> np.ndarray:
    """``ρ_I(Δt) − ρ_I(T)`` per configuration [C]: how much of the moving scatterers' intensity correlation
    still decays between the first and the last frame delay (physics.md §5.4; after the field has
    decorrelated, ``|g1|² ≈ 0``, this is the incoherent transit term ``j/N_eff`` alone)."""
    return _criteria(spec, draw, prior)[3]


def _criteria(spec: FeatureSpec, draw: Draw, prior: Prior) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """Status, ``|g1(Δt)|²``, ``ρ_I(T)`` and ``ρ_I(Δt) − ρ_I(T)`` per configuration (:func:`identifiability`)."""
    from torchdoct.conventions import n_eff
    from torchdoct.sim import theory

    taus = np.array([spec.frame_interval_s, (spec.n_frames - 1) * spec.frame_interval_s])
    first, last, drop = [], [], []
    for c in spec.configurations:
        res = dict(
            lateral_resolution_um=c.lateral_resolution_um, axial_resolution_um=c.axial_resolution_um, **lateral_y(c)
        )
        if draw.label == 0:
            g1 = theory.g1_diffusion(
                taus,
                diffusion_um2_per_s=draw.magnitude,
                wavelength_um=c.wavelength_um,
                refractive_index=spec.refractive_index,
                **res,
            )
            j = theory.j_diffusion(taus, diffusion_um2_per_s=draw.magnitude, **res)
        elif draw.label == 1:
            g1 = theory.g1_ballistic(
                taus,
                speed_um_per_s=draw.magnitude,
                wavelength_um=c.wavelength_um,
                refractive_index=spec.refractive_index,
                directions=draw.ballistic_directions,
                **res,
            )
            j = theory.j_ballistic(taus, speed_um_per_s=draw.magnitude, directions=draw.ballistic_directions, **res)
        else:
            g1 = theory.g1_flow(
                taus,
                speed_um_per_s=draw.magnitude,
                polar_angle_deg=draw.polar_angle_deg,
                azimuth_deg=draw.azimuth_deg,
                wavelength_um=c.wavelength_um,
                refractive_index=spec.refractive_index,
                **res,
            )
            j = theory.j_flow(
                taus,
                speed_um_per_s=draw.magnitude,
                polar_angle_deg=draw.polar_angle_deg,
                azimuth_deg=draw.azimuth_deg,
                **res,
            )
        rho = theory.intensity_correlation_coefficient(
            g1, j, n_eff(draw.density_per_um3, c.lateral_resolution_um, c.axial_resolution_um, **lateral_y(c))
        )
        first.append(float(np.abs(g1[0]) ** 2))
        last.append(float(rho[1]))
        drop.append(float(rho[0] - rho[1]))
    first_a, last_a = np.array(first), np.array(last)
    eps = prior.identifiability_epsilon
    if np.all(last_a >= 1.0 - eps):
        status = "static"
    elif np.all(first_a <= eps):
        status = "decorrelated"
    else:
        status = "identifiable"
    return status, first_a, last_a, np.array(drop)


#: Version of the ground-truth definition (part of the cache key).
IDENTIFIABILITY_VERSION = "static: rho_I(T) >= 1-eps; decorrelated: |g1(dt)|^2 <= eps; all configurations"
#: Identifiability status codes stored in a dataset.
STATUS = ("identifiable", "static", "decorrelated")

"""One draw simulated: the scenes of its moving and static scatterers (:func:`scene_for`) and its
feature vectors with the nuisances of each replicate (:func:`simulate_draw`, through
:func:`torchdoct.simulate` and :mod:`classifier.nuisance`).

**Static fraction and noise** are applied per *replicate*: each draw's moving and static fields are
simulated once and combined ``replicates`` times with different static fractions and SNRs
(:func:`simulate_draw`); this multiplies the nuisance variety per (costly) simulation. The static
fraction is the static scatterers' share of the mean intensity, the same at every configuration (static
scatterers mixed among the moving ones). A replicate may instead lie near the **edge of its moving
region** (:attr:`classifier.prior.Prior.static_edge_probability`; a vessel wall, a cell's border): static tissue fills the
half-space beyond a plane at distance ``d`` from the pixel, and each configuration's static share is the
part of its own intensity PSF beyond the plane, ``f_c = ½·erfc(d / (√2·σ_c))`` with ``σ_c`` the SD of the
configuration's intensity PSF along the plane's normal (:func:`classifier.nuisance.edge_static_fractions`; physics.md §14). A
reduced configuration reaches further into the static tissue than the original one, so near an edge the
moving field beats against a static field at its Doppler frequency in the reduced configurations only
(measured on the rendered flow phantoms: the intensity correlation of a flow region oscillates at
``2 n v_z / λ`` within one reduced PSF of its edge). The moving scatterers fill the whole space in the
simulation (the half-space restriction enters only through the shares).
"""

from __future__ import annotations

import math

import numpy as np

from .features import FeatureSpec
from .nuisance import combine_fields, edge_static_fractions
from .prior import Draw, Prior
from .truth import lateral_y

__all__ = [
    "DEFAULT_TRUNCATION",
    "scene_for",
    "simulate_draw",
]

#: PSF truncation mode of the training data (:func:`classifier.dataset.make_dataset`): the smooth taper, which lets
#: scatterers enter the PSF continuously (a hard cut at 1e-2 biases the short-lag correlations of slow
#: motion that the signature models read; the taper at 1e-2 matches the reference simulator at the cost
#: of the hard cut, ``torchdoct bench tradeoffs --part fidelity``).
DEFAULT_TRUNCATION = "taper"


def scene_for(spec: FeatureSpec, draw: Draw, prior: Prior, population: str = "moving"):
    """The noise-free :class:`torchdoct.Scene` of one draw's ``"moving"`` or ``"static"`` scatterers.

    Both have the draw's density and reflectivity 1; the spec's systems, protocol and analysis.
    """
    import torchdoct as td

    systems = tuple(
        td.OCTSystem(
            name=c.name,
            wavelength_um=c.wavelength_um,
            lateral_resolution_um=c.lateral_resolution_um,
            axial_resolution_um=c.axial_resolution_um,
            refractive_index=spec.refractive_index,
            **lateral_y(c),
        )
        for c in spec.configurations
    )
    if population == "static":
        motion: tuple = ()
    elif population != "moving":
        raise ValueError(f"population must be 'moving' or 'static'; got {population!r}")
    elif draw.label == 0:
        motion = (td.Diffusion(diffusion_um2_per_s=draw.magnitude),)
    elif draw.label == 1:
        motion = (td.RandomBallistic(speed_um_per_s=draw.magnitude, directions=draw.ballistic_directions),)
    else:
        motion = (
            td.Flow(speed_um_per_s=draw.magnitude, polar_angle_deg=draw.polar_angle_deg, azimuth_deg=draw.azimuth_deg),
        )
    return td.Scene(
        name=f"{spec.name}-{draw.motion}-{population}",
        systems=systems,
        protocol=td.Protocol(n_frames=spec.n_frames, frame_interval_s=spec.frame_interval_s),
        populations=(td.Population(name=population, density_per_um3=draw.density_per_um3, motion=motion),),
        analysis=td.Analysis(
            metrics=("liv", "ocds"),
            ocds_delay_range_s=spec.ocds_delay_range_s,
            ocds_scale=spec.ocds_scale,
            ocds_estimator=spec.ocds_estimator,
        ),
    )


def simulate_draw(
    spec: FeatureSpec,
    draw: Draw,
    prior: Prior,
    *,
    trials: int,
    truncation_tolerance: float,
    bulk_phase: bool = False,
    truncation: str = DEFAULT_TRUNCATION,
):
    """Feature vectors ``[R, trials, F]`` (float32, spec order) and the empty-volume mask ``[R, trials]``.

    For a signature spec (:attr:`FeatureSpec.is_signature`) the features come from
    :func:`torchdoct.sim.signature.pixel_features` (the extractor of ``torchdoct maps --signature``), and a
    third array ``[R, trials, 2·C]`` holds LIV and OCDS of the same pixels at the same
    configurations (for the LIV/OCDS baseline on the same test pixels). ``bulk_phase``: multiply
    every frame by a uniform random phase (one per trial and frame, common to the configurations,
    as bulk motion of a sample is to one dataset and its resolution reductions).

    Two :func:`torchdoct.simulate` calls per draw: the moving scatterers ``E_m`` and, independently,
    static scatterers ``E_s`` at the same density (reflectivity 1). Replicate ``r`` with static
    fraction ``f`` and SNR is ``E = E_m + a·E_s + n`` with ``a = √(f/(1−f))`` (a static population of
    reflectivity ``a``, exactly: the field is linear in the reflectivity; ``f`` is the static share of
    the mean intensity) and ``n`` circular complex Gaussian noise, independent per frame and system,
    of power ``⟨I⟩/10^(SNR/10)`` with ``⟨I⟩ = (1 + a²)·ρ·π^{3/2}·s_x²·s_z`` the mean noise-free
    intensity (physics.md §5.2, §8; the model of :class:`torchdoct.Noise`).
    """
    import torch

    import torchdoct as td
    from torchdoct.conventions import mean_intensity
    from torchdoct.sim.metrics import compute_metrics

    # one thread per draw: draws run side by side (make_dataset)
    moving = td.simulate(
        scene_for(spec, draw, prior, "moving"),
        trials=trials,
        seed=draw.sim_seed,
        dtype="float32",
        truncation_tolerance=truncation_tolerance,
        truncation=truncation,
        threads=1,
        progress=False,
    )
    nuisance = draw.nuisance or ((0.0, math.nan),)
    edges = draw.static_edges or (None,) * len(nuisance)
    shares = [f if e is None else edge_static_fractions(spec.configurations, e) for (f, _), e in zip(nuisance, edges)]
    static = None
    if any(f > 0 for f, _ in nuisance) or any(e is not None for e in edges):
        static = td.simulate(
            scene_for(spec, draw, prior, "static"),
            trials=trials,
            seed=draw.sim_seed ^ 0x5A5A5A5A,
            dtype="float32",
            truncation_tolerance=truncation_tolerance,
            truncation=truncation,
            threads=1,
            progress=False,
        ).signals
    mean_i = [
        mean_intensity(draw.density_per_um3, c.lateral_resolution_um, c.axial_resolution_um, **lateral_y(c))
        for c in spec.configurations
    ]
    gen = torch.Generator().manual_seed(draw.sim_seed ^ 0x3C3C3C3C)
    signals = torch.cat(
        [combine_fields(moving.signals, static, f, snr, mean_i, gen) for f, (_, snr) in zip(shares, nuisance)]
    )
    lo, hi = prior.bulk_residual_step_rad
    if hi > 0:  # the residual of a bulk-phase correction: a random walk per trial, common to the configurations
        rgen = torch.Generator().manual_seed(draw.sim_seed ^ 0x1E1E1E1E)
        n_rep, n_t = len(nuisance), signals.shape[-1]
        step_sd = lo + torch.rand(n_rep, 1, 1, generator=rgen, dtype=torch.float64) * (hi - lo)
        steps = torch.randn(n_rep, trials, n_t - 1, generator=rgen, dtype=torch.float64) * step_sd
        walk = torch.cat([torch.zeros(n_rep, trials, 1, dtype=torch.float64), steps.cumsum(-1)], dim=-1)
        walk = walk.reshape(n_rep * trials, 1, n_t)
        signals = signals * torch.polar(torch.ones_like(walk), walk).to(signals.dtype)
    if bulk_phase:  # one uniform random phase per trial and frame, common to all configurations
        bgen = torch.Generator().manual_seed(draw.sim_seed ^ 0x0F0F0F0F)
        phi = torch.rand(signals.shape[0], 1, signals.shape[-1], generator=bgen, dtype=torch.float64) * (2 * math.pi)
        signals = signals * torch.polar(torch.ones_like(phi), phi).to(signals.dtype)
    met = compute_metrics(signals, moving.frame_times_s, moving.scene.analysis)
    zero = met["zero_intensity"].any(-1).numpy().reshape(len(nuisance), trials)
    if spec.is_signature:
        from torchdoct.sim.signature import pixel_features  # the function of the maps' slab loop too

        _, sig = pixel_features(signals, moving.frame_times_s, spec)  # [N, systems, F]
        x = sig.reshape(sig.shape[0], -1).numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
        ref = torch.stack([met[m][:, s] for s in range(len(spec.configurations)) for m in ("liv", "ocds")], dim=-1)
        return x, zero, ref.numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
    cols = [met[m][:, s] for s in range(len(spec.configurations)) for m in spec.metrics]
    x = torch.stack(cols, dim=-1).numpy().astype(np.float32).reshape(len(nuisance), trials, -1)
    return x, zero

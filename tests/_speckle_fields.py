"""Speckle fields translated exactly (a phase ramp in the Fourier domain) for the tests of the speckle-motion
features and of the rules that read them (imported by module name, never through ``conftest``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch


def translated_speckle(
    n_fields: int,
    shape: tuple[int, ...],
    sigmas: tuple[float, ...],
    displacement_um: Callable[[int], Sequence[float]],
    seed: int,
    n_frames: int = 32,
) -> torch.Tensor:
    """``[n_fields, n_frames, *shape]`` complex Gaussian speckle (amplitude PSF sigmas per axis, µm; 1-µm
    pixels) translated at frame ``i`` by ``displacement_um(i)`` (a vector per axis, µm): ``E(r, i) =
    E₀(r − d(i))``."""
    gen = torch.Generator().manual_seed(seed)
    w = torch.randn(n_fields, *shape, dtype=torch.complex128, generator=gen)
    ks = torch.meshgrid(*[torch.fft.fftfreq(n, d=1.0, dtype=torch.float64) * 2 * math.pi for n in shape], indexing="ij")
    transfer = torch.exp(-sum(k**2 * s**2 / 2 for k, s in zip(ks, sigmas)))
    dims = tuple(range(1, len(shape) + 1))
    spec = torch.fft.fftn(w, dim=dims) * transfer
    frames = []
    for i in range(n_frames):
        ramp = torch.exp(-1j * sum(k * di for k, di in zip(ks, displacement_um(i))))
        frames.append(torch.fft.ifftn(spec * ramp, dim=dims))
    return torch.stack(frames, 1)

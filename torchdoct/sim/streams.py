"""Random streams of the point simulator: one ``torch.Generator`` per block of 64 trials.

Block ``b`` of a run with ``seed`` draws from :func:`block_generator` ``(seed, b)``
(:func:`seeded_generator`: a ``numpy.random.SeedSequence`` of the seed and an integer key path), so a
trial's numbers depend only on the seed and its block, never on how many trials are run or how they
are chunked. :class:`Draws` hands a chunk's blocks their numbers: uniforms and normals in float32 (the
generators' native precision) returned as float64, one 62-bit key per block for the counter-based
streams of :mod:`torchdoct.sim.kernel`, and Poisson counts by inversion (exactly two uniforms per
trial). The image renderer (:mod:`torchdoct.image.render`) seeds its streams with
:func:`seeded_generator` too.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from .plan import BLOCK_TRIALS

__all__ = ["CapacityError", "seeded_generator", "block_generator", "Draws"]

_F64 = torch.float64


class CapacityError(RuntimeError):
    """A Poisson count exceeded its reserved slots (probability < 1e-20 per draw)."""


def seeded_generator(seed: int, *key: int) -> torch.Generator:
    """A CPU ``torch.Generator`` whose stream is derived from ``seed`` and the integer ``key`` path."""
    state = np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(int(k) for k in key)).generate_state(2, np.uint32)
    g = torch.Generator(device="cpu")
    g.manual_seed((int(state[0]) << 31) ^ int(state[1]))
    return g


def block_generator(seed: int, block: int) -> torch.Generator:
    """The random stream of trials ``64·block … 64·block + 63`` for ``seed``."""
    return seeded_generator(seed, block)


class Draws:
    """Random draws for a chunk of blocks, each block from its own generator (CPU).

    Numbers are drawn in float32 (the generator's native precision, 4-5 ns each) and returned as
    float64, whatever the working dtype, so float32 and float64 runs share one realization. Each
    block owns its generator, so a block's numbers do not depend on the chunk it is drawn in.
    """

    def __init__(self, gens: list[torch.Generator], device: torch.device):
        self.gens = gens
        self.device = device

    def _draw(self, fn, shape):
        parts = [fn((BLOCK_TRIALS, *shape), generator=g, dtype=torch.float32) for g in self.gens]
        return (parts[0] if len(parts) == 1 else torch.cat(parts)).to(device=self.device, dtype=_F64)

    def keys(self) -> list[int]:
        """One 62-bit key per block, for the counter-based streams of :mod:`torchdoct.sim.kernel`."""
        return [int(torch.randint(0, 2**62, (1,), generator=g)) for g in self.gens]

    def rand(self, *shape: int) -> torch.Tensor:
        """Uniform on [0, 1) (24-bit resolution)."""
        return self._draw(torch.rand, shape)

    def rand_open(self, *shape: int) -> torch.Tensor:
        """Uniform on (0, 1]: safe under ``log``."""
        return 1.0 - self._draw(torch.rand, shape)

    def randn(self, *shape: int) -> torch.Tensor:
        return self._draw(torch.randn, shape)

    def ragged(self, fn, k: int, sizes: list[int], out: torch.Tensor | None = None) -> torch.Tensor:
        """``fn`` draws (``torch.rand``/``torch.randn``) of shape ``[k, Σ sizes]`` in float32: block ``b``
        draws its ``[k, sizes[b]]`` from its own generator, so a block's numbers never depend on the chunk."""

        def one(i: int) -> torch.Tensor:
            return fn((k, sizes[i]), generator=self.gens[i], dtype=torch.float32)

        parts = [one(i) for i in range(len(self.gens))]
        if len(parts) == 1 and out is None:
            return parts[0].to(self.device)
        if out is not None and out.device.type == "cpu":
            return torch.cat(parts, dim=1, out=out)
        return torch.cat(parts, dim=1).to(self.device)

    def poisson(self, mean: float, cap: int, what: str) -> torch.Tensor:
        """Poisson counts [trials] by inversion of the CDF: exactly two uniforms per trial.

        Inversion makes the count a monotone function of one uniform, so a slightly different mean
        (say a slightly larger domain) keeps the same counts and the same later draws almost always:
        realizations are nested across nearby scenes.
        """
        u = self.rand(2)
        if mean <= 0:
            return torch.zeros(u.shape[0], dtype=torch.int64, device=self.device)
        u = u[:, 0] + u[:, 1] * 2.0**-24
        cdf = _poisson_cdf(float(mean), cap + 1).to(self.device)
        n = torch.searchsorted(cdf, u.contiguous(), right=True)
        if int(n.max()) > cap:
            raise CapacityError(f"{what}: Poisson count {int(n.max())} exceeds the {cap} reserved slots")
        return n


@functools.lru_cache(maxsize=64)
def _poisson_cdf(mean: float, n: int) -> torch.Tensor:
    """P(N <= k) for k = 0 … n−1 (float64, CPU; cached: a random walk asks for the same one every frame)."""
    k = torch.arange(n, dtype=_F64)
    logp = k * math.log(mean) - mean - torch.lgamma(k + 1.0)
    return torch.cumsum(torch.exp(logp), 0).clamp_(max=1.0)

"""Monte Carlo helpers for the statistical tests: batch-means standard errors, z-score asserts."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch


def batch_means(
    stat: Callable[[torch.Tensor], complex | float], signals: torch.Tensor, n_batches: int = 64
) -> tuple[complex, float, float]:
    """Statistic on all trials, and the standard error of its real and imaginary parts.

    ``stat`` maps complex signals [trials, frames] to a number. Trials are independent, so the SE
    is the SD of the statistic over ``n_batches`` equal batches divided by √n_batches.
    """
    full = complex(stat(signals))
    per = np.array([complex(stat(b)) for b in torch.chunk(signals, n_batches)])
    se_re = float(np.std(per.real, ddof=1) / math.sqrt(len(per)))
    se_im = float(np.std(per.imag, ddof=1) / math.sqrt(len(per)))
    return full, se_re, se_im


def assert_within_se(est: float, ref: float, se: float, z: float = 4.0, what: str = "") -> None:
    """|est − ref| ≤ z·SE (SE from the Monte Carlo sample, never a hand-tuned tolerance)."""
    assert se > 0, f"{what}: standard error must be positive"
    assert abs(est - ref) <= z * se, f"{what}: {est:.6g} vs theory {ref:.6g} (|z| = {abs(est - ref) / se:.2f} > {z})"


def mean_intensity(E: torch.Tensor) -> float:
    return float((E.real**2 + E.imag**2).mean())


def g1_at_lag(lag: int) -> Callable[[torch.Tensor], complex]:
    """⟨E(t) E*(t+τ)⟩ / ⟨I⟩ over all frame pairs at ``lag`` (physics.md §5.3 convention)."""

    def stat(E: torch.Tensor) -> complex:
        num = (E[:, :-lag] * E[:, lag:].conj()).mean()
        return complex(num) / mean_intensity(E)

    return stat


def cov_at_lag(lag: int) -> Callable[[torch.Tensor], float]:
    """⟨I(t) I(t+τ)⟩ / ⟨I⟩² − 1 (physics.md §5.4: = |g1|² + j/N_eff)."""

    def stat(E: torch.Tensor) -> float:
        I = E.real**2 + E.imag**2
        return float((I[:, :-lag] * I[:, lag:]).mean()) / mean_intensity(E) ** 2 - 1.0

    return stat


def contrast2(E: torch.Tensor) -> float:
    """C² = Var I / ⟨I⟩² over all trials and frames."""
    I = E.real**2 + E.imag**2
    return float((I * I).mean()) / float(I.mean()) ** 2 - 1.0

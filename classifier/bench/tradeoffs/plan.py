"""What the trade-offs measure: the shipped settings (:data:`DEFAULTS`), :class:`TradeoffPlan`, :data:`QUICK_PLAN`."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

#: Name of the derived spec of the feature-spec axis.
ONE_CONFIGURATION = "one-configuration"
#: The settings of the feature-spec axis.
_SPECS = (ONE_CONFIGURATION, "single-acquisition", "two-wavelength")


def _train_defaults():
    from classifier.train import TrainConfig

    return TrainConfig()


#: ``doct-train``'s defaults, which the trade-off plan starts from.
_TRAIN = _train_defaults()


def _defaults() -> dict[str, Any]:
    from classifier.infer import DEFAULT_POOL

    return {
        "draws_train": _TRAIN.draws_train,
        "spec": _TRAIN.spec,
        "hidden": list(_TRAIN.hidden),
        "pool": int(DEFAULT_POOL),
    }


#: The shipped settings: ``doct-train`` and ``doct-classify`` without options.
DEFAULTS = _defaults()


@dataclass(frozen=True, kw_only=True)
class TradeoffPlan:
    """What :func:`run_tradeoffs` measures. The defaults are the full run (its time at one thread is in the
    recorded ``bench-tradeoffs.json``; a warm dataset cache skips the simulation).

    ``draws_grid``: training draws of the first axis; ``draws_base``: training draws of the spec and
    model-size axes (must be in ``draws_grid``); ``hidden_grid``: hidden layer sizes of the
    model-size axis; ``pools``: independent pixels of the pooling axis (perfect squares, 1 first);
    ``timing_draws``: draws simulated per spec to measure the one-configuration cost ratio;
    ``map_side``: side (pixels) of the synthetic map timed on the pooling axis; ``n_boot``: bootstrap
    resamples; ``max_epochs``: training epochs at most (early stopping as in :func:`classifier.train.train`);
    ``min_coverage``: settings deciding less than this share of the identifiable test samples are
    left off the fronts.
    """

    seed: int = _TRAIN.seed
    draws_grid: tuple[int, ...] = (25, 50, 100, 200, 270, 400)
    draws_base: int = _TRAIN.draws_train
    draws_validation: int = _TRAIN.draws_validation
    draws_test: int = _TRAIN.draws_test
    trials_per_draw: int = _TRAIN.trials_per_draw
    replicates: int = _TRAIN.replicates
    hidden_grid: tuple[tuple[int, ...], ...] = ((8, 8), (32, 32), (64, 64), (128, 128), (64,), (64, 64, 64))
    pools: tuple[int, ...] = (1, 4, 9, 25)
    max_epochs: int = _TRAIN.max_epochs
    timing_draws: int = 6
    map_side: int = 512
    timing_repeats: int = 5
    n_boot: int = 200
    min_coverage: float = 0.1

    def __post_init__(self) -> None:
        object.__setattr__(self, "draws_grid", tuple(sorted({int(n) for n in self.draws_grid})))
        object.__setattr__(self, "hidden_grid", tuple(tuple(int(h) for h in hs) for hs in self.hidden_grid))
        object.__setattr__(self, "pools", tuple(int(n) for n in self.pools))
        for key in (
            "draws_base",
            "draws_validation",
            "draws_test",
            "trials_per_draw",
            "replicates",
            "max_epochs",
            "timing_draws",
            "map_side",
            "timing_repeats",
            "n_boot",
        ):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"TradeoffPlan.{key} must be a positive integer; got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"TradeoffPlan.seed must be a non-negative integer; got {self.seed!r}")
        if not self.draws_grid or min(self.draws_grid) < 3:
            raise ValueError(
                f"TradeoffPlan.draws_grid needs values >= 3 (one draw per motion type); got {self.draws_grid}"
            )
        if self.draws_base not in self.draws_grid:
            raise ValueError(f"TradeoffPlan.draws_base ({self.draws_base}) must be one of draws_grid {self.draws_grid}")
        for key in ("draws_validation", "draws_test"):
            if getattr(self, key) < 3:
                raise ValueError(
                    f"TradeoffPlan.{key} must be >= 3 (one draw per motion type); got {getattr(self, key)}"
                )
        if not self.hidden_grid or any(not hs or min(hs) < 1 for hs in self.hidden_grid):
            raise ValueError(
                f"TradeoffPlan.hidden_grid must list non-empty positive layer sizes; got {self.hidden_grid}"
            )
        if not self.pools or self.pools[0] != 1 or any(math.isqrt(n) ** 2 != n or n < 1 for n in self.pools):
            raise ValueError(
                f"TradeoffPlan.pools must start with 1 and hold perfect squares (N × N windows of "
                f"independent pixels); got {self.pools}"
            )
        if max(self.pools) > self.trials_per_draw:
            raise ValueError(
                f"TradeoffPlan.pools must not exceed trials_per_draw ({self.trials_per_draw}); got {self.pools}"
            )
        if (
            isinstance(self.min_coverage, bool)
            or not isinstance(self.min_coverage, (int, float))
            or not 0.0 <= self.min_coverage < 1.0
        ):
            raise ValueError(f"TradeoffPlan.min_coverage must be in [0, 1); got {self.min_coverage!r}")
        if self.n_boot < 2:
            raise ValueError(f"TradeoffPlan.n_boot must be >= 2; got {self.n_boot}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {
            k: [list(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, tuple) else v for k, v in d.items()
        }


#: ``classifier_tradeoffs(quick=True)``: small splits, for a first look and the tests.
QUICK_PLAN = TradeoffPlan(
    draws_grid=(12, 24, 48),
    draws_base=48,
    draws_validation=9,
    draws_test=30,
    hidden_grid=((8,), (32, 32), (64, 64)),
    max_epochs=60,
    timing_draws=3,
    map_side=256,
)

"""Datasets of the axes: training-split prefixes, the derived one-configuration spec, simulation cost per draw."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .plan import ONE_CONFIGURATION, TradeoffPlan

#: The configuration the ``one-configuration`` spec keeps: (wavelength_um, lateral_resolution_um, axial_resolution_um).
_ONE_CONFIGURATION_SYSTEM = (0.84, 4.9, 3.8)


def one_configuration_spec():
    """The ``one-configuration`` spec: the single-acquisition spec reduced to its 840-nm 4.9/3.8-µm
    configuration (same protocol and OCDS analysis)."""
    from classifier.features import load_spec

    base = load_spec("single-acquisition")
    keep = [c for c in base.configurations if c.matches(*_ONE_CONFIGURATION_SYSTEM)]
    if len(keep) != 1:
        raise ValueError("the single-acquisition spec has no 840-nm 4.9/3.8-µm configuration to keep")
    return dataclasses.replace(
        base,
        name=ONE_CONFIGURATION,
        configurations=tuple(keep),
        description="840 nm at the original 4.9/3.8 µm only (one configuration)",
    )


def _columns(base, sub) -> list[int]:
    """Indices of ``sub``'s features among ``base``'s, matched by metric and configuration values."""
    cols = []
    for metric, conf in sub.features:
        hit = [
            i
            for i, (m, c) in enumerate(base.features)
            if m == metric and c.matches(conf.wavelength_um, conf.lateral_resolution_um, conf.axial_resolution_um)
        ]
        if len(hit) != 1:
            raise ValueError(f"spec {base.name!r} has no unique feature {metric}@{conf.describe()} for {sub.name!r}")
        cols.append(hit[0])
    return cols


def derive_dataset(ds, base, sub, prior):
    """Dataset of spec ``sub`` from dataset ``ds`` of spec ``base`` whose configurations include ``sub``'s.

    Features: ``sub``'s columns of ``ds.x`` (the same scatterers; each configuration has its own
    noise, so the columns are distributed as a simulation of ``sub`` alone). Ground truth:
    :func:`classifier.truth.identifiability` of every draw under ``sub`` (physics.md §5.3-5.4).
    """
    from classifier.dataset import Dataset
    from classifier.prior import draw_parameters
    from classifier.truth import STATUS, identifiability

    cols = _columns(base, sub)
    meta = ds.meta
    draws = np.unique(ds.draw)
    lut = np.zeros(int(draws.max()) + 1 if draws.size else 0, np.int64)
    counts = dict.fromkeys(STATUS, 0)
    for k in draws:
        d = draw_parameters(prior, int(meta["seed"]), meta["split"], int(k), int(meta["replicates"]))
        status, _, _ = identifiability(sub, d, prior)
        lut[k] = STATUS.index(status)
        counts[status] += 1
    arrays = ds.arrays()
    arrays["x"] = np.ascontiguousarray(ds.x[:, cols])
    arrays["status"] = lut[ds.draw]
    new_meta = {
        **meta,
        "spec": sub.to_dict(),
        "feature_names": list(sub.feature_names),
        "draw_status_counts": counts,
        "derived_from": {"spec": base.name, "columns": cols},
    }
    return Dataset(**arrays, meta=new_meta)


def prefix_dataset(ds, draws: int):
    """The first ``draws`` draws of ``ds`` (equal to a split simulated with ``draws`` draws)."""
    from classifier.dataset import Dataset

    n_have = int(ds.meta["draws"])
    if draws > n_have:
        raise ValueError(f"prefix of {draws} draws asked from a split of {n_have}")
    keep = ds.draw < draws
    arrays = {k: v[keep] for k, v in ds.arrays().items()}
    meta = {**ds.meta, "draws": int(draws), "elapsed_s": ds.meta["seconds_per_draw"] * draws, "prefix_of": n_have}
    return Dataset(**arrays, meta=meta)


def _seconds_per_draw(spec, prior, plan: TradeoffPlan) -> float:
    """Seconds per draw of :func:`classifier.simulation.simulate_draw` over training draws 0…m−1 (one
    untimed warm-up draw first)."""
    from classifier.prior import draw_parameters
    from classifier.simulation import simulate_draw
    from classifier.train import TrainConfig

    tol = TrainConfig().truncation_tolerance
    m = plan.timing_draws

    def run(k: int) -> None:
        d = draw_parameters(prior, plan.seed, "train", k, plan.replicates)
        simulate_draw(
            spec, d, prior, trials=plan.trials_per_draw, truncation_tolerance=tol, truncation=TrainConfig().truncation
        )

    run(m)
    t0 = time.perf_counter()
    for k in range(m):
        run(k)
    return (time.perf_counter() - t0) / m

"""The measurement: every axis fitted, timed and evaluated into one JSON-ready result."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from torchdoct.runtime.interrupt import progress_disabled

from .data import _seconds_per_draw, derive_dataset, one_configuration_spec, prefix_dataset
from .evaluate import _best_time, _bootstrap_weights, _Evaluator, _fit, _ort_session
from .pareto import _error_keys, _pareto
from .plan import _SPECS, DEFAULTS, ONE_CONFIGURATION, QUICK_PLAN, TradeoffPlan


def _hidden_label(hidden: Sequence[int]) -> str:
    return "×".join(str(int(h)) for h in hidden)


def classifier_tradeoffs(*, quick: bool = False, cache_dir=None, progress: bool = False) -> dict[str, Any]:
    """Measure the four trade-off axes of :mod:`classifier.bench.tradeoffs`; returns a JSON-ready dict.

    ``quick``: :data:`QUICK_PLAN` (small splits) instead of the full
    :class:`TradeoffPlan` (datasets cached); ``cache_dir``: the dataset cache
    (default :func:`classifier.dataset.default_cache_dir`); ``progress``: tqdm bars.
    """
    return run_tradeoffs(QUICK_PLAN if quick else TradeoffPlan(), cache_dir=cache_dir, progress=progress, quick=quick)


def run_tradeoffs(plan: TradeoffPlan, *, cache_dir=None, progress: bool = False, quick: bool = False) -> dict[str, Any]:
    """:func:`classifier_tradeoffs` for an explicit :class:`TradeoffPlan`."""
    import torch
    from tqdm.auto import tqdm

    from classifier.dataset import make_dataset
    from classifier.features import load_spec
    from classifier.infer import DEFAULT_MODEL, load_model, pool_features
    from classifier.prior import Prior
    from classifier.rule import apply_rule, make_rule
    from classifier.train import CLASS_NAMES, TrainConfig, eval_samples
    from torchdoct.runtime.machine import machine_info

    if not isinstance(plan, TradeoffPlan):
        raise TypeError(f"plan must be a TradeoffPlan; got {type(plan).__name__}")
    t_start = time.perf_counter()
    prior = Prior()
    threads = torch.get_num_threads()
    base_cfg = TrainConfig(
        seed=plan.seed,
        draws_validation=plan.draws_validation,
        draws_test=plan.draws_test,
        trials_per_draw=plan.trials_per_draw,
        replicates=plan.replicates,
        max_epochs=plan.max_epochs,
        eval_pools=plan.pools,
        baselines=False,
    )
    rule = make_rule(prior.identifiability_epsilon, base_cfg.min_probability)
    specs = {
        "single-acquisition": load_spec("single-acquisition"),
        "two-wavelength": load_spec("two-wavelength"),
        ONE_CONFIGURATION: one_configuration_spec(),
    }
    default_hidden = tuple(DEFAULTS["hidden"])
    n_fits = len(plan.draws_grid) + 2 + sum(1 for h in plan.hidden_grid if h != default_hidden)
    bar = tqdm(total=n_fits + 2, desc="classifier trade-offs", unit="step", disable=progress_disabled(progress))

    # 1. datasets (cached): train/validation/test of the two simulated specs; one-configuration derived
    data: dict[str, dict[str, Any]] = {}
    sizes = {"single-acquisition": max(plan.draws_grid), "two-wavelength": plan.draws_base}
    for name in ("single-acquisition", "two-wavelength"):
        data[name] = {}
        for split, draws in (("train", sizes[name]), ("validation", plan.draws_validation), ("test", plan.draws_test)):
            data[name][split] = make_dataset(
                specs[name],
                prior,
                seed=plan.seed,
                split=split,
                draws=draws,
                trials_per_draw=plan.trials_per_draw,
                replicates=plan.replicates,
                truncation_tolerance=base_cfg.truncation_tolerance,
                truncation=base_cfg.truncation,
                cache_dir=cache_dir,
                progress=progress,
            )
    data[ONE_CONFIGURATION] = {
        split: derive_dataset(ds, specs["single-acquisition"], specs[ONE_CONFIGURATION], prior)
        for split, ds in data["single-acquisition"].items()
    }
    ratio_timing = {
        name: _seconds_per_draw(specs[name], prior, plan) for name in ("single-acquisition", ONE_CONFIGURATION)
    }
    bar.update(1)
    s_per_draw = {
        name: float(data[name]["train"].meta["seconds_per_draw"]) for name in ("single-acquisition", "two-wavelength")
    }
    val_s = {
        name: float(data[name]["validation"].meta["elapsed_s"]) for name in ("single-acquisition", "two-wavelength")
    }
    ratio = ratio_timing[ONE_CONFIGURATION] / ratio_timing["single-acquisition"]
    s_per_draw[ONE_CONFIGURATION] = s_per_draw["single-acquisition"] * ratio
    val_s[ONE_CONFIGURATION] = val_s["single-acquisition"] * ratio

    # 2. the test samples: every trial (pool 1) and pooled means, drawn as train() draws them
    tests = {}
    for name in _SPECS:
        ev_rng = np.random.default_rng(np.random.SeedSequence(plan.seed, spawn_key=(9,)))
        tests[name] = {str(n): eval_samples(data[name]["test"], n, ev_rng) for n in plan.pools}
    weights = _bootstrap_weights(plan.draws_test, plan.n_boot, plan.seed)
    sa_test = data["single-acquisition"]["test"]
    common_by_draw = np.zeros(plan.draws_test, bool)
    common_by_draw[sa_test.draw[sa_test.status == 0]] = True
    evaluator = _Evaluator(weights, common_by_draw, rule)
    eval_pools = [p for p in ("1", str(max(plan.pools))) if p in tests["single-acquisition"]]
    eval_pools = list(dict.fromkeys(eval_pools))

    # 3. networks (memoised by spec, draws, hidden); the shipped recipe's is compared with the shipped model
    shipped_key = ("single-acquisition", DEFAULTS["draws_train"], default_hidden)
    fits: dict[tuple[str, int, tuple[int, ...]], dict[str, Any]] = {}

    def fit(name: str, draws: int, hidden: tuple[int, ...]) -> dict[str, Any]:
        key = (name, draws, hidden)
        if key in fits:
            return fits[key]
        spec = specs[name]
        cfg = dataclasses.replace(base_cfg, spec=name, draws_train=draws, hidden=hidden)
        r = _fit(prefix_dataset(data[name]["train"], draws), data[name]["validation"], spec, cfg)
        model = r.pop("model")
        x1 = np.ascontiguousarray(tests[name]["1"]["x"])
        xt = torch.from_numpy(x1)
        with torch.no_grad():
            t_torch = _best_time(lambda: model(xt), plan.timing_repeats)
        sess = _ort_session(model, spec, threads)
        t_ort = _best_time(lambda: sess.run(["probabilities"], {"features": x1}), plan.timing_repeats)
        row = {
            "spec": name,
            "draws_train": draws,
            "hidden": list(hidden),
            **r,
            "simulation_s": s_per_draw[name] * draws,
            "validation_simulation_s": val_s[name],
            "inference_torch_us": t_torch / len(x1) * 1e6,
            "inference_ort_us": t_ort / len(x1) * 1e6,
            "pools": {},
        }
        row["build_s"] = row["simulation_s"] + row["validation_simulation_s"] + row["training_s"]
        row_reps = {}
        for pool in eval_pools:
            s = tests[name][pool]
            with torch.no_grad():
                p = model(torch.from_numpy(s["x"])).numpy()
            row["pools"][pool], row_reps[pool] = evaluator(p, s)
        if key == shipped_key:
            with torch.no_grad():
                p1 = model(xt).numpy()
            row["max_abs_diff_vs_shipped"] = float(np.abs(p1 - pool_probe).max())
        fits[key] = {"row": row, "reps": row_reps}
        bar.update(1)
        return fits[key]

    # 4. the shipped model on the pooling axis (computed first: its pool-1 output is the parity probe)
    shipped = load_model(DEFAULT_MODEL, threads=threads)
    if list(shipped.classes) != list(CLASS_NAMES):
        raise ValueError(f"shipped model classes {shipped.classes} differ from {list(CLASS_NAMES)}")
    pool_probe = shipped.predict(tests["single-acquisition"]["1"]["x"])
    pool_rows, pool_reps = [], {}
    sa_single = tests["single-acquisition"]["1"]["x"][:, :-1]
    side = plan.map_side
    pick = np.random.default_rng(np.random.SeedSequence(plan.seed, spawn_key=(11,))).integers(
        0, len(sa_single), side * side
    )
    fmap = np.ascontiguousarray(sa_single[pick].T.reshape(-1, side, side))
    valid = np.ones((side, side), bool)
    pmax = shipped.pool_pixels_max
    for n in plan.pools:
        window = math.isqrt(n)

        def classify_map(window: int = window) -> None:
            pooled, counts = pool_features(fmap, valid, window)
            x = np.concatenate(
                [pooled.reshape(pooled.shape[0], -1).T, np.clip(counts.reshape(-1, 1), 1, pmax).astype(np.float32)],
                axis=1,
            )
            apply_rule(shipped.predict(x), shipped.classes, shipped.rule)

        t = _best_time(classify_map, plan.timing_repeats)
        s = tests["single-acquisition"][str(n)]
        metrics, reps = evaluator(shipped.predict(s["x"]), s)
        label = f"pool {n}"
        pool_rows.append(
            {
                "label": label,
                "pool": n,
                "window": window,
                "pixels_per_decision": n,
                "inference_us_per_pixel": t / (side * side) * 1e6,
                "pools": {"own": metrics},
                "is_default": n == DEFAULTS["pool"],
            }
        )
        pool_reps[(label, "own")] = reps
    bar.update(1)

    axes: dict[str, dict[str, Any]] = {}

    def axis(
        name: str,
        title: str,
        keys: list[tuple[str, int, tuple[int, ...]]],
        labels: list[str],
        default_label: str,
        time_keys: list[str],
    ) -> None:
        rows, reps = [], {}
        for key, label in zip(keys, labels):
            f = fit(*key)
            rows.append({"label": label, **f["row"], "is_default": label == default_label})
            for pool, rep in f["reps"].items():
                reps[(label, pool)] = rep
        axes[name] = {
            "title": title,
            "time_keys": time_keys,
            "rows": rows,
            "pareto": [
                _pareto(name, rows, reps, tk, pool, default_label, plan.min_coverage, ek)
                for tk in time_keys
                for ek in _error_keys(tk == time_keys[0])
                for pool in eval_pools
            ],
        }

    axis(
        "training_draws",
        "training draws (single-acquisition, hidden " + _hidden_label(default_hidden) + ")",
        [("single-acquisition", n, default_hidden) for n in plan.draws_grid],
        [f"{n} draws" for n in plan.draws_grid],
        f"{DEFAULTS['draws_train']} draws",
        ["build_s"],
    )
    axis(
        "feature_spec",
        f"feature spec ({plan.draws_base} draws, hidden {_hidden_label(default_hidden)})",
        [(name, plan.draws_base, default_hidden) for name in _SPECS],
        list(_SPECS),
        DEFAULTS["spec"],
        ["build_s"],
    )
    axis(
        "model_size",
        f"model size (single-acquisition, {plan.draws_base} draws)",
        [("single-acquisition", plan.draws_base, h) for h in plan.hidden_grid],
        [_hidden_label(h) for h in plan.hidden_grid],
        _hidden_label(default_hidden),
        ["inference_ort_us", "training_s"],
    )
    axes["pool"] = {
        "title": "pooled independent pixels (shipped single-acquisition model)",
        "time_keys": ["inference_us_per_pixel", "pixels_per_decision"],
        "rows": pool_rows,
        "pareto": [
            _pareto("pool", pool_rows, pool_reps, tk, "own", f"pool {DEFAULTS['pool']}", plan.min_coverage, ek)
            for tk in ("inference_us_per_pixel", "pixels_per_decision")
            for ek in _error_keys(tk == "inference_us_per_pixel")
        ],
    }
    bar.close()

    datasets = {
        name: {
            split: {
                k: ds.meta.get(k)
                for k in ("draws", "seconds_per_draw", "elapsed_s", "from_cache", "draw_status_counts", "dropped_empty")
            }
            | {"samples": len(ds)}
            for split, ds in d.items()
        }
        for name, d in data.items()
    }
    summary = {}
    for name, ax in axes.items():
        primary = ax["time_keys"][0]
        summary[name] = {
            f"{p['error_key']} @ pool {p['pool']}": {
                "time_key": primary,
                "front": p["front"],
                "defaults": p["defaults"],
                "defaults_on_front": p["defaults_on_front"],
                "defaults_significantly_dominated": p["defaults_significantly_dominated"],
                "recommended": p["recommended"],
            }
            for p in ax["pareto"]
            if p["time_key"] == primary
        }
    out = {
        "benchmark": "tradeoffs-classify",
        "quick": bool(quick),
        "plan": plan.to_dict(),
        "defaults": DEFAULTS,
        "machine": machine_info(),
        "errors": {
            "error": "1 - balanced accuracy over the identifiable test samples decided by the rule "
            "(classifier.report.evaluate)",
            "strict_error": "1 - strict accuracy (undecided = wrong) over the test samples of the draws "
            "identifiable under the single-acquisition ground truth",
        },
        "evaluation_pools": eval_pools,
        "test_split": {
            "seed": plan.seed,
            "draws": plan.draws_test,
            "replicates": plan.replicates,
            "trials_per_draw": plan.trials_per_draw,
            "bootstrap_resamples": plan.n_boot,
            "common_identifiable_draws": int(common_by_draw.sum()),
        },
        "simulation_seconds_per_draw": s_per_draw,
        "one_configuration_cost_ratio": {
            "seconds_per_draw_timed": ratio_timing,
            "ratio": ratio,
            "draws_timed": plan.timing_draws,
        },
        "datasets": datasets,
        "axes": axes,
        "summary": summary,
        "total_s": time.perf_counter() - t_start,
    }
    return _plain(out)


def _plain(obj: Any) -> Any:
    """JSON-ready copy: NaN/inf → None, tuples → lists, numpy scalars → Python."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj

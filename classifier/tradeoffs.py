"""What accuracy costs in time: measured trade-off curves of the motion-type classifier.

Four knobs are turned one at a time away from the shipped single-acquisition model's settings
(:data:`DEFAULTS`: 270 training draws, spec ``single-acquisition``, hidden layers (64, 64),
``doct-classify --pool 1``); every point is evaluated on the same held-out test split (seed 0, split
``test``, the shipped model's test draws, never seen in training):

* **training draws**: networks trained on prefixes of one cached training split. Draws are
  stratified by motion type and magnitude and a draw does not depend on how many are made
  (:mod:`classifier.dataset`), so a prefix of ``n`` draws is bit-identical to a split simulated with
  ``n`` draws. Time = simulation of those draws (the split's recorded seconds per draw × ``n``) +
  simulation of the validation split + network training ("build time");
* **feature spec**: ``one-configuration`` (840 nm at 4.9/3.8 µm only: LIV and OCDS at the original
  resolution, :func:`one_configuration_spec`), ``single-acquisition``, ``two-wavelength``. The
  one-configuration features are the matching columns of the single-acquisition dataset: every
  configuration of a scene sees the same scatterers and its own independent noise, so these columns
  have exactly the distribution a one-system simulation would give; its ground truth is recomputed
  with its single configuration (:func:`classifier.dataset.identifiability`), which makes more
  draws indeterminate. Its simulation cost per draw is the single-acquisition one scaled by the ratio
  of the two measured on the same draws. Build time as above;
* **model size**: hidden widths and depth; time = inference per sample (onnxruntime, the classify
  path) and training;
* **pooling**: the *shipped* ONNX model at ``n`` = 1, 4, 9, 25 independent pixels (the test split's
  pooled samples, as in its report); time = classify-path inference per map pixel: the N × N box
  mean of :func:`classifier.infer.pool_features` with N = √n (independent pixels on the grid),
  onnxruntime and the rule, timed on a synthetic map of test features. What pooling really costs is
  spatial resolution: ``n`` pixels share one decision, so this axis has a second front against
  pixels per decision.

Error = 1 − balanced accuracy over the identifiable test samples that the indeterminate rule decides
(:func:`classifier.report.evaluate`); coverage (decided share of the identifiable ones) and the strict
accuracy on the draws identifiable under the single-acquisition truth (undecided counts as wrong: a
common denominator across specs) stand beside it. Standard errors come from a bootstrap over test
*draws*, the independent unit, with the resamples of :func:`classifier.report.bootstrap_se`; every
point uses the same resamples, so the difference of two points has a paired standard error.

Pareto front (per axis, time key and pool): the points no other point beats in both time and error
(:func:`torchdoct.tradeoffs.pareto_front`), among the settings that decide at least
``TradeoffPlan.min_coverage`` (0.1) of the identifiable samples (a balanced accuracy over a handful
of decisions says nothing). The defaults are *on the front* when no point is both faster and more
accurate, and *significantly dominated* when such a point is better by more than two paired standard
errors. Recommendation (one-standard-error rule): the cheapest setting whose error exceeds the lowest
error by at most one paired standard error and whose coverage is at most one paired standard error
below that setting's.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["DEFAULTS", "TradeoffPlan", "QUICK_PLAN", "one_configuration_spec", "derive_dataset", "prefix_dataset",
           "classifier_tradeoffs", "run_tradeoffs", "format_table", "plot_tradeoffs"]

#: Name of the derived spec of the feature-spec axis.
ONE_CONFIGURATION = "one-configuration"
#: The configuration it keeps: (wavelength_um, lateral_resolution_um, axial_resolution_um).
_ONE_CONFIGURATION_SYSTEM = (0.84, 4.9, 3.8)
_SPECS = (ONE_CONFIGURATION, "single-acquisition", "two-wavelength")
#: Paired z above which a faster, more accurate point counts as significantly better.
_Z_DOMINATED = 2.0


def _train_defaults():
    from .train import TrainConfig

    return TrainConfig()


#: ``doct-train``'s defaults, which the trade-off plan starts from.
_TRAIN = _train_defaults()


def _defaults() -> dict[str, Any]:
    from .cli import build_classify_parser

    return {"draws_train": _TRAIN.draws_train, "spec": _TRAIN.spec, "hidden": list(_TRAIN.hidden),
            "pool": int(build_classify_parser().get_default("pool"))}


#: The shipped settings: ``doct-train`` and ``doct-classify`` without options.
DEFAULTS = _defaults()


def _hidden_label(hidden: Sequence[int]) -> str:
    return "×".join(str(int(h)) for h in hidden)


@dataclass(frozen=True, kw_only=True)
class TradeoffPlan:
    """What :func:`run_tradeoffs` measures. The defaults are the full run (about 10 minutes at one
    thread with a cold dataset cache, ~4 minutes warm).

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
        for key in ("draws_base", "draws_validation", "draws_test", "trials_per_draw", "replicates", "max_epochs",
                    "timing_draws", "map_side", "timing_repeats", "n_boot"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"TradeoffPlan.{key} must be a positive integer; got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"TradeoffPlan.seed must be a non-negative integer; got {self.seed!r}")
        if not self.draws_grid or min(self.draws_grid) < 3:
            raise ValueError(f"TradeoffPlan.draws_grid needs values >= 3 (one draw per motion type); got {self.draws_grid}")
        if self.draws_base not in self.draws_grid:
            raise ValueError(f"TradeoffPlan.draws_base ({self.draws_base}) must be one of draws_grid {self.draws_grid}")
        for key in ("draws_validation", "draws_test"):
            if getattr(self, key) < 3:
                raise ValueError(f"TradeoffPlan.{key} must be >= 3 (one draw per motion type); got {getattr(self, key)}")
        if not self.hidden_grid or any(not hs or min(hs) < 1 for hs in self.hidden_grid):
            raise ValueError(f"TradeoffPlan.hidden_grid must list non-empty positive layer sizes; got {self.hidden_grid}")
        if not self.pools or self.pools[0] != 1 or any(math.isqrt(n) ** 2 != n or n < 1 for n in self.pools):
            raise ValueError(f"TradeoffPlan.pools must start with 1 and hold perfect squares (N × N windows of "
                             f"independent pixels); got {self.pools}")
        if max(self.pools) > self.trials_per_draw:
            raise ValueError(f"TradeoffPlan.pools must not exceed trials_per_draw ({self.trials_per_draw}); "
                             f"got {self.pools}")
        if isinstance(self.min_coverage, bool) or not isinstance(self.min_coverage, (int, float)) \
                or not 0.0 <= self.min_coverage < 1.0:
            raise ValueError(f"TradeoffPlan.min_coverage must be in [0, 1); got {self.min_coverage!r}")
        if self.n_boot < 2:
            raise ValueError(f"TradeoffPlan.n_boot must be >= 2; got {self.n_boot}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: [list(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, tuple) else v
                for k, v in d.items()}


#: ``classifier_tradeoffs(quick=True)``: small splits (about 1.5 minutes at one thread, cold cache).
QUICK_PLAN = TradeoffPlan(draws_grid=(12, 24, 48), draws_base=48, draws_validation=9, draws_test=30,
                          hidden_grid=((8,), (32, 32), (64, 64)), max_epochs=60, timing_draws=3, map_side=256)


# ---------------------------------------------------------------------------------------------
# datasets


def one_configuration_spec():
    """The ``one-configuration`` spec: the single-acquisition spec reduced to its 840-nm 4.9/3.8-µm
    configuration (same protocol and OCDS analysis)."""
    from .features import load_spec

    base = load_spec("single-acquisition")
    keep = [c for c in base.configurations if c.matches(*_ONE_CONFIGURATION_SYSTEM)]
    if len(keep) != 1:
        raise ValueError("the single-acquisition spec has no 840-nm 4.9/3.8-µm configuration to keep")
    return dataclasses.replace(base, name=ONE_CONFIGURATION, configurations=tuple(keep),
                               description="840 nm at the original 4.9/3.8 µm only (one configuration)")


def _columns(base, sub) -> list[int]:
    """Indices of ``sub``'s features among ``base``'s, matched by metric and configuration values."""
    cols = []
    for metric, conf in sub.features:
        hit = [i for i, (m, c) in enumerate(base.features)
               if m == metric and c.matches(conf.wavelength_um, conf.lateral_resolution_um, conf.axial_resolution_um)]
        if len(hit) != 1:
            raise ValueError(f"spec {base.name!r} has no unique feature {metric}@{conf.describe()} for {sub.name!r}")
        cols.append(hit[0])
    return cols


def derive_dataset(ds, base, sub, prior):
    """Dataset of spec ``sub`` from dataset ``ds`` of spec ``base`` whose configurations include ``sub``'s.

    Features: ``sub``'s columns of ``ds.x`` (the same scatterers; each configuration has its own
    noise, so the columns are distributed as a simulation of ``sub`` alone). Ground truth:
    :func:`classifier.dataset.identifiability` of every draw under ``sub`` (physics.md §5.3-5.4).
    """
    from .dataset import STATUS, Dataset, draw_parameters, identifiability

    cols = _columns(base, sub)
    meta = ds.meta
    draws = np.unique(ds.draw)
    lut = np.zeros(int(draws.max()) + 1 if draws.size else 0, np.int64)
    counts = {s: 0 for s in STATUS}
    for k in draws:
        d = draw_parameters(prior, int(meta["seed"]), meta["split"], int(k), int(meta["replicates"]))
        status, _, _ = identifiability(sub, d, prior)
        lut[k] = STATUS.index(status)
        counts[status] += 1
    arrays = ds.arrays()
    arrays["x"] = np.ascontiguousarray(ds.x[:, cols])
    arrays["status"] = lut[ds.draw]
    new_meta = {**meta, "spec": sub.to_dict(), "feature_names": list(sub.feature_names),
                "draw_status_counts": counts, "derived_from": {"spec": base.name, "columns": cols}}
    return Dataset(**arrays, meta=new_meta)


def prefix_dataset(ds, draws: int):
    """The first ``draws`` draws of ``ds`` (equal to a split simulated with ``draws`` draws)."""
    from .dataset import Dataset

    n_have = int(ds.meta["draws"])
    if draws > n_have:
        raise ValueError(f"prefix of {draws} draws asked from a split of {n_have}")
    keep = ds.draw < draws
    arrays = {k: v[keep] for k, v in ds.arrays().items()}
    meta = {**ds.meta, "draws": int(draws), "elapsed_s": ds.meta["seconds_per_draw"] * draws, "prefix_of": n_have}
    return Dataset(**arrays, meta=meta)


def _seconds_per_draw(spec, prior, plan: TradeoffPlan) -> float:
    """Seconds per draw of :func:`classifier.dataset.simulate_draw` over training draws 0…m−1 (one
    untimed warm-up draw first)."""
    from .dataset import draw_parameters, simulate_draw
    from .train import TrainConfig

    tol = TrainConfig().truncation_tolerance
    m = plan.timing_draws

    def run(k: int) -> None:
        d = draw_parameters(prior, plan.seed, "train", k, plan.replicates)
        simulate_draw(spec, d, prior, trials=plan.trials_per_draw, truncation_tolerance=tol)

    run(m)
    t0 = time.perf_counter()
    for k in range(m):
        run(k)
    return (time.perf_counter() - t0) / m


# ---------------------------------------------------------------------------------------------
# training (the recipe of classifier.train.train, steps 3-5, on given datasets)


def _fit(train_ds, val_ds, spec, cfg) -> dict[str, Any]:
    """:func:`classifier.train.fit_network` on given splits (the network of ``train``)."""
    from .train import fit_network

    fit = fit_network(train_ds, val_ds, spec, cfg)
    fit.pop("first_samples")
    return fit


# ---------------------------------------------------------------------------------------------
# evaluation with paired bootstrap standard errors


def _bootstrap_weights(n_draws: int, n_boot: int, seed: int) -> np.ndarray:
    """``[n_boot, n_draws]`` resample counts of the draws: the resamples of
    :func:`classifier.report.bootstrap_se` (same generator calls) when every draw is present."""
    rng = np.random.default_rng(seed)
    draws = np.arange(n_draws)
    w = np.empty((n_boot, n_draws))
    for b in range(n_boot):
        w[b] = np.bincount(rng.choice(draws, draws.size, replace=True), minlength=n_draws)
    return w


def _draw_counts(pred: np.ndarray, y: np.ndarray, status: np.ndarray, draw: np.ndarray, common: np.ndarray,
                 n_draws: int, n_motion: int) -> dict[str, np.ndarray]:
    ind = n_motion
    ident = status == 0
    decided = ident & (pred != ind)

    def count(mask: np.ndarray) -> np.ndarray:
        return np.bincount(draw[mask], minlength=n_draws).astype(np.float64)

    return {"ident": count(ident), "dec": np.stack([count(decided & (y == c)) for c in range(n_motion)], 1),
            "cor": np.stack([count(decided & (y == c) & (pred == c)) for c in range(n_motion)], 1),
            "common": count(common), "common_correct": count(common & (pred == y))}


def _weighted_stats(counts: dict[str, np.ndarray], w: np.ndarray) -> dict[str, np.ndarray]:
    """Balanced accuracy (identifiable, decided), coverage and common strict accuracy per weight row
    (definitions of :func:`classifier.report.evaluate`: mean recall over the classes present)."""
    ident = w @ counts["ident"]
    dec = w @ counts["dec"]
    cor = w @ counts["cor"]
    present = dec > 0
    recall = np.where(present, cor / np.where(present, dec, 1.0), 0.0)
    n_present = present.sum(-1)
    bal = np.where(n_present > 0, recall.sum(-1) / np.maximum(n_present, 1), np.nan)
    cov = np.where(ident > 0, dec.sum(-1) / np.where(ident > 0, ident, 1.0), np.nan)
    cc = w @ counts["common"]
    strict = np.where(cc > 0, (w @ counts["common_correct"]) / np.where(cc > 0, cc, 1.0), np.nan)
    return {"balanced_accuracy": bal, "coverage": cov, "strict_accuracy_common": strict}


def _sd(v: np.ndarray) -> float:
    v = np.asarray(v, np.float64)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if v.size >= 2 else math.nan


class _Evaluator:
    """Metrics of one predictor on the test samples of one spec, plus bootstrap replicates."""

    def __init__(self, weights: np.ndarray, common_by_draw: np.ndarray, rule: dict[str, Any]):
        self.weights = weights
        self.common_by_draw = common_by_draw
        self.rule = rule

    def __call__(self, probabilities: np.ndarray, s: dict[str, np.ndarray]) -> tuple[dict[str, Any], np.ndarray]:
        from .report import evaluate
        from .rule import apply_rule
        from .train import CLASS_NAMES

        m = evaluate(probabilities, s["y"], s["status"], CLASS_NAMES, self.rule)
        pred, _ = apply_rule(probabilities, CLASS_NAMES, self.rule)
        n_draws = self.weights.shape[1]
        common = self.common_by_draw[s["draw"]]
        counts = _draw_counts(pred, s["y"], s["status"], s["draw"], common, n_draws, len(CLASS_NAMES) - 1)
        point = _weighted_stats(counts, np.ones((1, n_draws)))
        reps = _weighted_stats(counts, self.weights)
        bal = m["balanced_accuracy_identifiable"]
        out = {"samples": m["samples"], "identifiable_samples": m["identifiable_samples"],
               "balanced_accuracy": bal, "balanced_accuracy_se": _sd(reps["balanced_accuracy"]),
               "coverage": m["coverage_identifiable"], "coverage_se": _sd(reps["coverage"]),
               "accuracy": m["accuracy_identifiable"], "ece": m["ece"],
               "strict_accuracy_common": float(point["strict_accuracy_common"][0]),
               "strict_accuracy_common_se": _sd(reps["strict_accuracy_common"]),
               "error": 1.0 - bal, "error_se": _sd(reps["balanced_accuracy"])}
        out["strict_error"] = 1.0 - out["strict_accuracy_common"]
        out["strict_error_se"] = out["strict_accuracy_common_se"]
        return out, {"error": 1.0 - reps["balanced_accuracy"], "coverage": reps["coverage"],
                     "strict_error": 1.0 - reps["strict_accuracy_common"]}


def _best_time(fn: Callable[[], Any], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _ort_session(model, spec, threads: int):
    import onnxruntime as ort

    from . import __version__
    from .export import onnx_model
    from .train import CLASS_NAMES

    meta = {"classifier_version": __version__, "output": {"classes": list(CLASS_NAMES)},
            "input": {"columns": [{"name": n} for n in (*spec.feature_names, "pool_pixels")]}}
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(onnx_model(model, meta).SerializeToString(), opts, providers=["CPUExecutionProvider"])


# ---------------------------------------------------------------------------------------------
# Pareto fronts


def _pareto(axis: str, rows: list[dict[str, Any]], reps: dict[tuple[str, str], dict[str, np.ndarray]], time_key: str,
            pool: str, default_label: str | None, min_coverage: float, error_key: str = "error") -> dict[str, Any]:
    """Front, defaults and one-standard-error recommendation for one (axis, time key, pool, error).

    ``error_key``: ``"error"`` (1 − balanced accuracy of the decided samples) or ``"strict_error"``
    (1 − strict accuracy on the common identifiable draws, undecided = wrong: coverage included).
    For ``"error"``, settings that decide less than ``min_coverage`` of the identifiable samples are
    left out (their balanced accuracy rests on a handful of decisions) and a recommended setting must
    not decide significantly less than the best. ``reps[(label, pool)]`` holds the bootstrap
    replicates of the errors and the coverage (the same resamples for every setting).
    """
    from torchdoct.tradeoffs import pareto_front

    pts, excluded = [], []
    for r in rows:
        m = r["pools"].get(pool)
        if m is None:
            continue
        t, e, c = r[time_key], m[error_key], m["coverage"]
        if t is None or e is None or not (math.isfinite(t) and math.isfinite(e)):
            excluded.append({"label": r["label"], "reason": "no decided identifiable sample"})
        elif error_key == "error" and (c is None or c < min_coverage):
            excluded.append({"label": r["label"], "reason": f"coverage {c:.3f} < {min_coverage:g}"})
        else:
            pts.append({"label": r["label"], "time_s": float(t), "error": float(e), "error_se": m[f"{error_key}_se"],
                        "coverage": float(c), "coverage_se": m["coverage_se"]})
    front = [p["label"] for p in pareto_front(pts)]
    out: dict[str, Any] = {"axis": axis, "time_key": time_key, "pool": pool, "error_key": error_key,
                           "min_coverage": min_coverage if error_key == "error" else None,
                           "front": front, "excluded": excluded,
                           "points": [{"label": p["label"], "time": p["time_s"], "error": p["error"],
                                       "error_se": p["error_se"], "coverage": p["coverage"]} for p in pts],
                           "defaults": default_label if any(r["label"] == default_label for r in rows) else None,
                           "defaults_on_front": None, "defaults_dominated_by": [],
                           "defaults_significantly_dominated": None, "best": None, "recommended": None}
    if not pts:
        return out

    def paired_se(a: str, b: str, key: str) -> float:
        return 0.0 if a == b else _sd(reps[(a, pool)][key] - reps[(b, pool)][key])

    d = next((p for p in pts if p["label"] == default_label), None)
    if d is not None:
        out["defaults_on_front"] = d["label"] in front
        dom = []
        for q in pts:
            if q["time_s"] < d["time_s"] and q["error"] < d["error"]:
                se = paired_se(d["label"], q["label"], error_key)
                gain = d["error"] - q["error"]
                dom.append({"label": q["label"], "error_gain": gain, "paired_se": se,
                            "z": gain / se if se > 0 else math.inf})
        out["defaults_dominated_by"] = dom
        out["defaults_significantly_dominated"] = any(x["z"] > _Z_DOMINATED for x in dom)
    best = min(pts, key=lambda p: (p["error"], p["time_s"]))

    def within(p: dict[str, Any]) -> bool:
        se_e = paired_se(p["label"], best["label"], error_key)
        se_c = paired_se(p["label"], best["label"], "coverage")
        return (p["error"] - best["error"] <= (se_e if math.isfinite(se_e) else 0.0)
                and (error_key != "error"
                     or best["coverage"] - p["coverage"] <= (se_c if math.isfinite(se_c) else 0.0)))

    out["best"] = best["label"]
    out["recommended"] = min((p for p in pts if within(p)), key=lambda p: (p["time_s"], p["error"]))["label"]
    return out


def _error_keys(primary: bool) -> tuple[str, ...]:
    """Errors with a front: both for an axis's primary cost, the balanced one otherwise."""
    return ("error", "strict_error") if primary else ("error",)


# ---------------------------------------------------------------------------------------------
# the run


def classifier_tradeoffs(*, quick: bool = False, cache_dir=None, progress: bool = False) -> dict[str, Any]:
    """Measure the four trade-off axes of the module docstring; returns a JSON-ready dict.

    ``quick``: :data:`QUICK_PLAN` (small splits, ~1.5 min at one thread) instead of the full
    :class:`TradeoffPlan` (~10 min cold, datasets cached); ``cache_dir``: the dataset cache
    (default :func:`classifier.dataset.default_cache_dir`); ``progress``: tqdm bars.
    """
    return run_tradeoffs(QUICK_PLAN if quick else TradeoffPlan(), cache_dir=cache_dir, progress=progress,
                         quick=quick)


def run_tradeoffs(plan: TradeoffPlan, *, cache_dir=None, progress: bool = False, quick: bool = False) -> dict[str, Any]:
    """:func:`classifier_tradeoffs` for an explicit :class:`TradeoffPlan`."""
    import torch
    from tqdm.auto import tqdm

    from torchdoct.bench import machine_info

    from .dataset import Prior, make_dataset
    from .features import load_spec
    from .infer import DEFAULT_MODEL, load_model, pool_features
    from .rule import apply_rule, make_rule
    from .train import CLASS_NAMES, TrainConfig, _eval_samples

    if not isinstance(plan, TradeoffPlan):
        raise TypeError(f"plan must be a TradeoffPlan; got {type(plan).__name__}")
    t_start = time.perf_counter()
    prior = Prior()
    threads = torch.get_num_threads()
    base_cfg = TrainConfig(seed=plan.seed, draws_validation=plan.draws_validation, draws_test=plan.draws_test,
                           trials_per_draw=plan.trials_per_draw, replicates=plan.replicates,
                           max_epochs=plan.max_epochs, eval_pools=plan.pools, baselines=False)
    rule = make_rule(prior.identifiability_epsilon, base_cfg.min_probability)
    specs = {"single-acquisition": load_spec("single-acquisition"), "two-wavelength": load_spec("two-wavelength"),
             ONE_CONFIGURATION: one_configuration_spec()}
    default_hidden = tuple(DEFAULTS["hidden"])
    n_fits = len(plan.draws_grid) + 2 + sum(1 for h in plan.hidden_grid if h != default_hidden)
    bar = tqdm(total=n_fits + 2, desc="classifier trade-offs", unit="step", disable=not progress)

    # 1. datasets (cached): train/validation/test of the two simulated specs; one-configuration derived
    data: dict[str, dict[str, Any]] = {}
    sizes = {"single-acquisition": max(plan.draws_grid), "two-wavelength": plan.draws_base}
    for name in ("single-acquisition", "two-wavelength"):
        data[name] = {}
        for split, draws in (("train", sizes[name]), ("validation", plan.draws_validation), ("test", plan.draws_test)):
            data[name][split] = make_dataset(specs[name], prior, seed=plan.seed, split=split, draws=draws,
                                             trials_per_draw=plan.trials_per_draw,
                                             replicates=plan.replicates,
                                             truncation_tolerance=base_cfg.truncation_tolerance,
                                             cache_dir=cache_dir, progress=progress)
    data[ONE_CONFIGURATION] = {split: derive_dataset(ds, specs["single-acquisition"], specs[ONE_CONFIGURATION], prior)
                               for split, ds in data["single-acquisition"].items()}
    ratio_timing = {name: _seconds_per_draw(specs[name], prior, plan) for name in ("single-acquisition", ONE_CONFIGURATION)}
    bar.update(1)
    s_per_draw = {name: float(data[name]["train"].meta["seconds_per_draw"]) for name in ("single-acquisition",
                                                                                          "two-wavelength")}
    val_s = {name: float(data[name]["validation"].meta["elapsed_s"]) for name in ("single-acquisition", "two-wavelength")}
    ratio = ratio_timing[ONE_CONFIGURATION] / ratio_timing["single-acquisition"]
    s_per_draw[ONE_CONFIGURATION] = s_per_draw["single-acquisition"] * ratio
    val_s[ONE_CONFIGURATION] = val_s["single-acquisition"] * ratio

    # 2. the test samples: every trial (pool 1) and pooled means, drawn as train() draws them
    tests = {}
    for name in _SPECS:
        ev_rng = np.random.default_rng(np.random.SeedSequence(plan.seed, spawn_key=(9,)))
        tests[name] = {str(n): _eval_samples(data[name]["test"], n, ev_rng) for n in plan.pools}
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
        row = {"spec": name, "draws_train": draws, "hidden": list(hidden), **r,
               "simulation_s": s_per_draw[name] * draws, "validation_simulation_s": val_s[name],
               "inference_torch_us": t_torch / len(x1) * 1e6, "inference_ort_us": t_ort / len(x1) * 1e6,
               "pools": {}}
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
    pick = np.random.default_rng(np.random.SeedSequence(plan.seed, spawn_key=(11,))).integers(0, len(sa_single), side * side)
    fmap = np.ascontiguousarray(sa_single[pick].T.reshape(-1, side, side))
    valid = np.ones((side, side), bool)
    pmax = shipped.pool_pixels_max
    for n in plan.pools:
        window = math.isqrt(n)

        def classify_map(window: int = window) -> None:
            pooled, counts = pool_features(fmap, valid, window)
            x = np.concatenate([pooled.reshape(pooled.shape[0], -1).T,
                                np.clip(counts.reshape(-1, 1), 1, pmax).astype(np.float32)], axis=1)
            apply_rule(shipped.predict(x), shipped.classes, shipped.rule)

        t = _best_time(classify_map, plan.timing_repeats)
        s = tests["single-acquisition"][str(n)]
        metrics, reps = evaluator(shipped.predict(s["x"]), s)
        label = f"pool {n}"
        pool_rows.append({"label": label, "pool": n, "window": window, "pixels_per_decision": n,
                          "inference_us_per_pixel": t / (side * side) * 1e6, "pools": {"own": metrics},
                          "is_default": n == DEFAULTS["pool"]})
        pool_reps[(label, "own")] = reps
    bar.update(1)

    axes: dict[str, dict[str, Any]] = {}

    def axis(name: str, title: str, keys: list[tuple[str, int, tuple[int, ...]]], labels: list[str],
             default_label: str, time_keys: list[str]) -> None:
        rows, reps = [], {}
        for key, label in zip(keys, labels):
            f = fit(*key)
            rows.append({"label": label, **f["row"], "is_default": label == default_label})
            for pool, rep in f["reps"].items():
                reps[(label, pool)] = rep
        axes[name] = {"title": title, "time_keys": time_keys, "rows": rows,
                      "pareto": [_pareto(name, rows, reps, tk, pool, default_label, plan.min_coverage, ek)
                                 for tk in time_keys for ek in _error_keys(tk == time_keys[0]) for pool in eval_pools]}

    axis("training_draws", "training draws (single-acquisition, hidden " + _hidden_label(default_hidden) + ")",
         [("single-acquisition", n, default_hidden) for n in plan.draws_grid],
         [f"{n} draws" for n in plan.draws_grid], f"{DEFAULTS['draws_train']} draws", ["build_s"])
    axis("feature_spec", f"feature spec ({plan.draws_base} draws, hidden {_hidden_label(default_hidden)})",
         [(name, plan.draws_base, default_hidden) for name in _SPECS], list(_SPECS), DEFAULTS["spec"], ["build_s"])
    axis("model_size", f"model size (single-acquisition, {plan.draws_base} draws)",
         [("single-acquisition", plan.draws_base, h) for h in plan.hidden_grid],
         [_hidden_label(h) for h in plan.hidden_grid], _hidden_label(default_hidden), ["inference_ort_us", "training_s"])
    axes["pool"] = {"title": "pooled independent pixels (shipped single-acquisition model)",
                    "time_keys": ["inference_us_per_pixel", "pixels_per_decision"], "rows": pool_rows,
                    "pareto": [_pareto("pool", pool_rows, pool_reps, tk, "own", f"pool {DEFAULTS['pool']}",
                                       plan.min_coverage, ek)
                               for tk in ("inference_us_per_pixel", "pixels_per_decision")
                               for ek in _error_keys(tk == "inference_us_per_pixel")]}
    bar.close()

    datasets = {name: {split: {k: ds.meta.get(k) for k in ("draws", "seconds_per_draw", "elapsed_s", "from_cache",
                                                            "draw_status_counts", "dropped_empty")}
                           | {"samples": len(ds)} for split, ds in d.items()} for name, d in data.items()}
    summary = {}
    for name, ax in axes.items():
        primary = ax["time_keys"][0]
        summary[name] = {f"{p['error_key']} @ pool {p['pool']}": {
            "time_key": primary, "front": p["front"], "defaults": p["defaults"],
            "defaults_on_front": p["defaults_on_front"],
            "defaults_significantly_dominated": p["defaults_significantly_dominated"],
            "recommended": p["recommended"]} for p in ax["pareto"] if p["time_key"] == primary}
    out = {
        "benchmark": "tradeoffs-classify",
        "quick": bool(quick),
        "plan": plan.to_dict(),
        "defaults": DEFAULTS,
        "machine": machine_info(),
        "errors": {"error": "1 - balanced accuracy over the identifiable test samples decided by the rule "
                            "(classifier.report.evaluate)",
                   "strict_error": "1 - strict accuracy (undecided = wrong) over the test samples of the draws "
                                   "identifiable under the single-acquisition ground truth"},
        "evaluation_pools": eval_pools,
        "test_split": {"seed": plan.seed, "draws": plan.draws_test, "replicates": plan.replicates,
                       "trials_per_draw": plan.trials_per_draw, "bootstrap_resamples": plan.n_boot,
                       "common_identifiable_draws": int(common_by_draw.sum())},
        "simulation_seconds_per_draw": s_per_draw,
        "one_configuration_cost_ratio": {"seconds_per_draw_timed": ratio_timing, "ratio": ratio,
                                         "draws_timed": plan.timing_draws},
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


# ---------------------------------------------------------------------------------------------
# reporting


def _f(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def _pm(m: dict[str, Any] | None, key: str, digits: int = 2) -> str:
    if m is None or m.get(key) is None:
        return "–"
    se = m.get(f"{key}_se")
    return f"{m[key]:.{digits}f} ± {se:.{digits}f}" if se is not None else f"{m[key]:.{digits}f}"


_TIME_LABELS = {"build_s": "build time [s]", "training_s": "training [s]", "inference_ort_us": "onnxruntime [µs/sample]",
                "inference_us_per_pixel": "inference [µs/pixel]", "pixels_per_decision": "pixels per decision"}


def format_table(result: dict[str, Any]) -> str:
    """Markdown: one table per axis (± bootstrap SE), then the Pareto fronts and recommendations."""
    r = result
    mach = r["machine"]
    L = [f"Classifier trade-offs{' (quick)' if r['quick'] else ''}: test split seed {r['test_split']['seed']}, "
         f"{r['test_split']['draws']} draws × {r['test_split']['replicates']} replicates × "
         f"{r['test_split']['trials_per_draw']} trials; error = 1 − balanced accuracy (identifiable, decided); "
         f"± = bootstrap SE over test draws ({r['test_split']['bootstrap_resamples']} resamples). torch "
         f"{mach['torch']}, {mach['torch_threads']} thread(s), {mach['cpu_count']} CPUs; total {r['total_s']:.0f} s.",
         ""]
    pools = r["evaluation_pools"]
    fronts = {(p["axis"], p["time_key"], p["pool"]): set(p["front"]) for ax in r["axes"].values() for p in ax["pareto"]
              if p["error_key"] == "error"}
    for name in ("training_draws", "feature_spec", "model_size"):
        ax = r["axes"][name]
        tk = ax["time_keys"][0]
        L.append(f"### {ax['title']}")
        L.append("")
        head = ["setting", "simulation [s]", "training [s]", "epochs", "build [s]", "torch [µs/sample]",
                "onnxruntime [µs/sample]"]
        if name == "model_size":
            head.insert(1, "weights")
        for pool in pools:
            head += [f"coverage (pool {pool})", f"bal. acc. (pool {pool})", f"strict acc. (pool {pool})"]
        head += [f"front (pool {pool})" for pool in pools]
        L.append("| " + " | ".join(head) + " |")
        L.append("|---|" + "---:|" * (len(head) - 1))
        for row in ax["rows"]:
            cells = [f"**{row['label']}** (default)" if row["is_default"] else row["label"],
                     _f(row["simulation_s"], 1), _f(row["training_s"], 1), str(row["epochs"]), _f(row["build_s"], 1),
                     _f(row["inference_torch_us"], 2), _f(row["inference_ort_us"], 2)]
            if name == "model_size":
                cells.insert(1, str(row["parameters"]))
            for pool in pools:
                m = row["pools"].get(pool)
                cells += [_pm(m, "coverage"), _pm(m, "balanced_accuracy"), _pm(m, "strict_accuracy_common")]
            cells += ["✓" if row["label"] in fronts.get((name, tk, pool), ()) else "" for pool in pools]
            L.append("| " + " | ".join(cells) + " |")
        L.append("")
        if name == "feature_spec":
            L.append("Coverage and balanced accuracy use each spec's own ground truth (fewer configurations: more "
                     "draws indeterminate); the strict accuracy uses the draws identifiable under the "
                     "single-acquisition truth for every spec.")
            L.append("")
    ax = r["axes"]["pool"]
    L.append(f"### {ax['title']}")
    L.append("")
    L.append("| pool (independent pixels) | window | inference [µs/pixel] | coverage | bal. acc. | strict acc. | ECE "
             "| front (time) | front (pixels per decision) |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in ax["rows"]:
        m = row["pools"]["own"]
        lab = f"**{row['pool']}** (default)" if row["is_default"] else str(row["pool"])
        L.append(f"| {lab} | {row['window']}×{row['window']} | {_f(row['inference_us_per_pixel'], 3)} | "
                 f"{_pm(m, 'coverage')} | {_pm(m, 'balanced_accuracy')} | {_pm(m, 'strict_accuracy_common')} | "
                 f"{_f(m['ece'], 3)} | "
                 f"{'✓' if row['label'] in fronts[('pool', 'inference_us_per_pixel', 'own')] else ''} | "
                 f"{'✓' if row['label'] in fronts[('pool', 'pixels_per_decision', 'own')] else ''} |")
    L.append("")
    L.append("### Pareto fronts (cost vs error) and recommendations")
    L.append("")
    L.append(f"Error `1−bal`: 1 − balanced accuracy of the decided identifiable samples; settings deciding less than "
             f"{r['plan']['min_coverage']:g} of them are left off (excluded). Error `1−strict`: 1 − strict accuracy "
             "(undecided counts as wrong) on the draws identifiable under the single-acquisition truth. Recommended: "
             "the cheapest setting whose error is within one paired SE of the lowest (for `1−bal` also with "
             "coverage within one paired SE of that setting's).")
    L.append("")
    L.append("| axis | cost | error | pool | front (cheapest first) | excluded | defaults | on front "
             "| significantly dominated by (z > 2) | recommended (1-SE rule) |")
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for name, ax in r["axes"].items():
        for p in ax["pareto"]:
            sig = [f"{d['label']} (Δ {d['error_gain']:.3f}, z {d['z']:.1f})" for d in p["defaults_dominated_by"]
                   if d["z"] is None or d["z"] > _Z_DOMINATED]
            on = {True: "yes", False: "no", None: "–"}[p["defaults_on_front"]]
            L.append(f"| {name} | {_TIME_LABELS.get(p['time_key'], p['time_key'])} | "
                     f"{'1−bal' if p['error_key'] == 'error' else '1−strict'} | {p['pool']} | "
                     f"{', '.join(p['front'])} | {', '.join(x['label'] for x in p['excluded']) or '–'} | "
                     f"{p['defaults'] or '–'} | {on} | {', '.join(sig) or 'none'} | {p['recommended'] or '–'} |")
    L.append("")
    parity = [row.get("max_abs_diff_vs_shipped") for row in r["axes"]["training_draws"]["rows"] if row["is_default"]]
    if parity and parity[0] is not None:
        L.append(f"The retrained default model against the shipped ONNX model on the pool-1 test inputs: max |Δp| = "
                 f"{parity[0]:.1e}.")
    ratio = r["one_configuration_cost_ratio"]
    L.append(f"Simulation cost per draw: single-acquisition {r['simulation_seconds_per_draw']['single-acquisition']:.3f} s, "
             f"two-wavelength {r['simulation_seconds_per_draw']['two-wavelength']:.3f} s, one-configuration "
             f"{r['simulation_seconds_per_draw'][ONE_CONFIGURATION]:.3f} s (ratio {ratio['ratio']:.2f} to "
             f"single-acquisition, timed on {ratio['draws_timed']} draws).")
    return "\n".join(L)


def plot_tradeoffs(result: dict[str, Any], path) -> None:
    """Error (1 − balanced accuracy) against cost per axis (pool 1 filled, largest pool open; ± SE), the
    Pareto fronts, the defaults (star), and the learning curve (balanced accuracy and coverage). PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = result
    pools = r["evaluation_pools"]
    panels = [("training_draws", "build_s"), ("feature_spec", "build_s"), ("model_size", "inference_ort_us"),
              ("model_size", "training_s"), ("pool", "inference_us_per_pixel")]
    fig, axs = plt.subplots(2, 3, figsize=(16, 9.5), constrained_layout=True)
    for ax, (name, tk) in zip(axs.flat, panels):
        a = r["axes"][name]
        for entry in a["pareto"]:
            if entry["time_key"] != tk or entry["error_key"] != "error":
                continue
            own = entry["pool"] == "own"
            color = "C0" if entry["pool"] in ("1", "own") else "C3"
            pts = entry["points"]
            lab = "" if own else f" (pool {entry['pool']})"
            ax.errorbar([p["time"] for p in pts], [p["error"] for p in pts], yerr=[p["error_se"] or 0 for p in pts],
                        fmt="o" if entry["pool"] in ("1", "own") else "s", color=color,
                        mfc=color if entry["pool"] in ("1", "own") else "none", ms=6, capsize=2, ls="none",
                        label="points" + lab)
            front = [next(p for p in pts if p["label"] == lbl) for lbl in entry["front"]]
            ax.step([p["time"] for p in front], [p["error"] for p in front], where="post", color=color, lw=1,
                    label="Pareto front" + lab)
            d = next((p for p in pts if p["label"] == entry["defaults"]), None)
            if d is not None:
                ax.plot([d["time"]], [d["error"]], "*", color="gold", mec="k", ms=16, zorder=5,
                        label="shipped defaults" if entry["pool"] in ("1", "own") else None)
            for p in pts:
                ax.annotate(p["label"], (p["time"], p["error"]), textcoords="offset points", xytext=(4, 4), fontsize=7,
                            color=color)
        ax.set_xscale("log")
        ax.set_xlabel(_TIME_LABELS.get(tk, tk))
        ax.set_ylabel("1 − balanced accuracy")
        ax.set_title(a["title"], fontsize=9)
        ax.legend(fontsize=7)
    ax = axs.flat[5]
    rows = r["axes"]["training_draws"]["rows"]
    draws = [row["draws_train"] for row in rows]
    floor = r["plan"]["min_coverage"]
    for pool, color in zip(pools, ("C0", "C3")):
        for key, mk, lab in (("balanced_accuracy", "o-", "balanced accuracy"), ("coverage", "s--", "coverage")):
            ms = [row["pools"][pool] for row in rows]
            # a balanced accuracy over too few decisions is not drawn (the fronts leave it off too)
            vals = [m[key] if key == "coverage" or (m["coverage"] or 0.0) >= floor else None for m in ms]
            ses = [m[f"{key}_se"] or 0 for m in ms]
            ax.errorbar(draws, [np.nan if v is None else v for v in vals], yerr=ses, fmt=mk, color=color, capsize=2,
                        mfc=color if key == "balanced_accuracy" else "none", label=f"{lab}, pool {pool}")
    ax.axvline(r["defaults"]["draws_train"], color="k", lw=0.8, ls=":", label="shipped")
    ax.set_xscale("log")
    ax.set_xticks(draws, [str(n) for n in draws])
    ax.minorticks_off()
    ax.set_ylim(0, 1)
    ax.set_xlabel("training draws (× 8 replicates × 64 trials)")
    ax.set_title("learning curve (single-acquisition)", fontsize=9)
    ax.legend(fontsize=7)
    fig.suptitle("motion-type classifier: what accuracy costs in time" + (" (quick)" if r["quick"] else ""))
    fig.savefig(path, dpi=90, format="png")
    plt.close(fig)

"""Training: datasets → pooled samples → :class:`~classifier.model.MotionClassifier` → report.

:func:`train` runs the whole recipe of the shipped model from a :class:`TrainConfig` (the recipes:
:mod:`classifier.recipe`, whose names this module re-exports):

1. simulate (or load from the cache) the train, validation and test splits
   (:func:`classifier.dataset.make_dataset`);
2. targets: the motion type where the ground truth says the motion is identifiable, else
   ``indeterminate`` (:mod:`classifier.rule`);
3. pooled samples: a feature vector may be the mean over ``n`` independent pixels (``pool_pixels``
   = n, the model's last input). Each epoch uses every single trial (n = 1) plus, per draw,
   ``pooled_per_draw`` means over random subsets of its trials with n log-uniform in
   [2, ``max_pool_pixels``]; the validation set is one fixed draw of the same mixture;
4. AdamW on cross-entropy (plus the magnitude head's Gaussian NLL for magnitude models,
   :mod:`classifier.model`), minibatches shuffled by a seeded numpy generator, early stopping on the
   validation cross-entropy (best weights kept);
5. temperature scaling on the validation set (grid search of the NLL), stored in the model;
6. scikit-learn baselines (logistic regression, histogram gradient boosting) on the same training
   samples (singles + one pooled draw);
7. evaluation on the test split at ``eval_pools`` pooled pixels (n = 1: every trial; n > 1: 16
   random subsets per draw), the report of :mod:`classifier.report`;
8. for signature specs (``TrainConfig.shifted_test``), the same evaluation of the network on a test
   split drawn from :data:`SHIFTED_PRIOR` (other flow angles, fixed density, no static fraction,
   other noise), on which accuracy and calibration must hold (:data:`SHIFTED_TARGETS`).

Everything is seeded from ``TrainConfig.seed``; the global torch RNG is not used (weights are
initialised inside :func:`torch.random.fork_rng`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from . import __version__
from .dataset import CLASSES, STATUS, Dataset, Prior, make_dataset
from .features import METRIC_UNITS, FeatureSpec, load_spec
from .model import DECORRELATION_OFFSET, LIV_OFFSET_DB2, MotionClassifier
from .report import (COVERAGE_THRESHOLDS, bootstrap_se, coverage_curve, evaluate, flow_recall_by_band,
                     magnitude_table)
from .recipe import (OWN_SIGNATURE_RECIPE, SCALED_PRIOR_SPECS, SHIFTED_PRIOR, SHIFTED_TARGETS, SPEC_RECIPES,  # noqa: F401
                     TrainConfig, default_prior, recipe_for, shifted_prior)
from .rule import INDETERMINATE, make_rule

__all__ = ["TrainConfig", "TrainResult", "train", "fit_network", "pooled_samples", "CLASS_NAMES", "transform_numpy",
           "SHIFTED_PRIOR", "SHIFTED_TARGETS", "shifted_prior", "feature_masks", "eval_samples", "class_targets",
           "evaluation_sets"]

#: Output classes of every model: the motion types, then ``indeterminate``.
CLASS_NAMES = (*CLASSES, INDETERMINATE)


def _uses_magnitude(cfg: TrainConfig, spec: FeatureSpec) -> bool:
    return spec.is_signature if cfg.magnitude is None else bool(cfg.magnitude)


def _log_columns(spec: FeatureSpec) -> list[int]:
    """Columns log-transformed by the model: LIV and its signature twin ``db_variance`` (dB²)."""
    return [i for i, (m, _) in enumerate(spec.features) if m in ("liv", "db_variance")]


def _correlation_columns(spec: FeatureSpec) -> list[int]:
    """Columns the model reads as log decorrelation: the signature's correlation coefficients
    (``rho_lin_m``, ``rho_db_m``, ``g1_m``; :mod:`classifier.model`)."""
    from torchdoct.sim.signature import parse_feature

    return [i for i, (m, _) in enumerate(spec.features)
            if m not in METRIC_UNITS and parse_feature(m)[0] in ("rho_lin", "rho_db", "g1")]


def feature_masks(spec: FeatureSpec) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks over the model's inputs (features + ``pool_pixels``) of the LIV and correlation columns."""
    liv = np.zeros(spec.n_features + 1, bool)
    liv[_log_columns(spec)] = True
    corr = np.zeros(spec.n_features + 1, bool)
    corr[_correlation_columns(spec)] = True
    return liv, corr


@dataclass
class TrainResult:
    """The trained model (eval mode), its report and the test samples (for the ONNX parity check)."""

    model: MotionClassifier
    report: dict[str, Any]
    spec: FeatureSpec
    prior: Prior
    config: TrainConfig
    rule: dict[str, Any]
    test_inputs: np.ndarray
    datasets: dict[str, Dataset] = field(default_factory=dict)


def transform_numpy(x: np.ndarray, liv_mask: np.ndarray, corr_mask: np.ndarray | None = None) -> np.ndarray:
    """The model's fixed transforms (step 1 of :mod:`classifier.model`) in numpy, for the baselines."""
    out = np.array(x, dtype=np.float64)
    out[:, liv_mask] = np.log(np.clip(out[:, liv_mask], 0.0, None) + LIV_OFFSET_DB2)
    if corr_mask is not None:
        out[:, corr_mask] = np.log(np.clip(1.0 - out[:, corr_mask], 0.0, None) + DECORRELATION_OFFSET)
    out[:, -1] = np.log(np.clip(out[:, -1], 1.0, None))
    return out


def _groups(ds: Dataset) -> list[np.ndarray]:
    """Sample indices of every group (trials sharing all parameters; contiguous)."""
    _, start, count = np.unique(ds.group, return_index=True, return_counts=True)
    return [np.arange(s, s + c) for s, c in zip(start, count)]


_TRUTH = ("y", "status", "magnitude", "density", "static_fraction", "snr_db", "draw", "group", "polar_angle_deg")


def pooled_samples(ds: Dataset, sizes_per_group: list[np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Means over random subsets of each group's trials (a group shares every parameter).

    ``sizes_per_group[g]`` lists the subset sizes wanted from group ``g`` (in :func:`_groups` order;
    capped at its number of trials). Returns inputs ``[M, F+1]`` (features + pool_pixels) and the
    per-sample truth arrays.
    """
    xs, cols = [], {k: [] for k in _TRUTH}
    for idx, sizes in zip(_groups(ds), sizes_per_group):
        sizes = np.asarray(sizes, dtype=np.int64)
        if sizes.size == 0:
            continue
        t = idx.size
        if sizes.max() > t:
            sizes = np.minimum(sizes, t)
        perm = np.argsort(rng.random((sizes.size, t)), axis=1)
        cs = np.cumsum(ds.x[idx][perm].astype(np.float64), axis=1)
        mean = cs[np.arange(sizes.size), sizes - 1] / sizes[:, None]
        xs.append(np.concatenate([mean, sizes[:, None].astype(np.float64)], axis=1))
        for k in cols:
            cols[k].append(np.repeat(getattr(ds, k)[idx[0]], sizes.size))
    out = {k: np.concatenate(v) for k, v in cols.items()}
    out["x"] = np.concatenate(xs).astype(np.float32)
    return out


def _singles(ds: Dataset, index: np.ndarray | None = None) -> dict[str, np.ndarray]:
    sel = slice(None) if index is None else index
    x = ds.x[sel]
    out = {k: getattr(ds, k)[sel] for k in _TRUTH}
    out["x"] = np.concatenate([x, np.ones((len(x), 1), np.float32)], axis=1)
    return out


def _concat(*parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _epoch_samples(ds: Dataset, cfg: TrainConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per group: ``singles_per_group`` random single trials and ``pooled_per_group`` pooled means
    (n log-uniform in [2, max_pool_pixels])."""
    groups = _groups(ds)
    single_idx = np.concatenate([rng.choice(g, min(cfg.singles_per_group, g.size), replace=False) for g in groups])
    singles = _singles(ds, np.sort(single_idx))
    if cfg.max_pool_pixels < 2 or cfg.pooled_per_group == 0:
        return singles
    lo, hi = math.log(2.0), math.log(cfg.max_pool_pixels + 0.999)
    sizes = [np.floor(np.exp(lo + rng.random(cfg.pooled_per_group) * (hi - lo))).astype(np.int64) for _ in groups]
    return _concat(singles, pooled_samples(ds, sizes, rng))


def eval_samples(ds: Dataset, n: int, rng: np.random.Generator, per_group: int = 8) -> dict[str, np.ndarray]:
    """Evaluation samples of ``ds`` at pool size ``n``: every pixel alone for ``n = 1``, else ``per_group``
    pools of ``n`` pixels per draw group (:func:`pooled_samples`)."""
    if n == 1:
        return _singles(ds)
    return pooled_samples(ds, [np.full(per_group, n) for _ in _groups(ds)], rng)


def class_targets(s: dict[str, np.ndarray]) -> np.ndarray:
    """Class index of every sample: its motion type where identifiable, else ``indeterminate`` (the last)."""
    return np.where(s["status"] == 0, s["y"], len(CLASS_NAMES) - 1)


def _magnitude_targets(s: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``log10`` magnitude, motion label and identifiable mask of samples (the magnitude head's targets)."""
    return (torch.from_numpy(np.log10(s["magnitude"]).astype(np.float32)), torch.from_numpy(s["y"].astype(np.int64)),
            torch.from_numpy(s["status"] == 0))


def _gaussian_nll(mu: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor, label: torch.Tensor,
                  ident: torch.Tensor) -> torch.Tensor:
    """Gaussian NLL (without the constant) of the true class's head, mean over identifiable samples."""
    if not bool(ident.any()):
        return mu.sum() * 0.0
    m = mu.gather(1, label[:, None])[:, 0][ident]
    lv = logvar.gather(1, label[:, None])[:, 0][ident].clamp(-12.0, 8.0)
    return 0.5 * (lv + (target[ident] - m) ** 2 * torch.exp(-lv)).mean()


def _fit_temperature(logits: torch.Tensor, target: torch.Tensor) -> float:
    """Temperature minimising the validation NLL on a log grid over [1/4, 4]."""
    grid = np.exp(np.linspace(math.log(0.25), math.log(4.0), 241))
    with torch.no_grad():
        nll = [float(torch.nn.functional.cross_entropy(logits / float(t), target)) for t in grid]
    return float(grid[int(np.argmin(nll))])


def _timed_predict(fn, x: np.ndarray, repeats: int = 3) -> tuple[np.ndarray, float]:
    best = math.inf
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(x)
        best = min(best, time.perf_counter() - t0)
    return out, best / max(len(x), 1) * 1e6


def fit_network(train_ds: Dataset, val_ds: Dataset, spec, cfg: TrainConfig, *, progress: bool = False) -> dict[str, Any]:
    """Train the network on given splits: seeded samples, AdamW, early stopping on the validation
    loss, then temperature scaling. Timed from the first sample to the fitted temperature.

    Returns the model, ``training_s``, ``epochs``, ``best_epoch``, ``validation_loss``,
    ``temperature``, ``parameters`` and ``first_samples`` (the first epoch's training samples).
    """
    t0 = time.perf_counter()
    liv_cols = _log_columns(spec)
    mag = _uses_magnitude(cfg, spec)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(7,)))
    val = _epoch_samples(val_ds, cfg, np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(8,))))
    train0 = _epoch_samples(train_ds, cfg, rng)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        model = MotionClassifier(spec.n_features, len(CLASS_NAMES), liv_cols, cfg.hidden,
                                 n_magnitude=len(CLASSES) if mag else 0,
                                 correlation_columns=_correlation_columns(spec))
    model.set_normalization(torch.from_numpy(train0["x"]))
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
    xv = torch.from_numpy(val["x"])
    tv = torch.from_numpy(class_targets(val))
    mv = _magnitude_targets(val)

    def loss_of(xb, tb, mb=None):
        if not mag:
            return torch.nn.functional.cross_entropy(model.logits(xb), tb)
        logits, mu, lv = model.heads(xb)
        return torch.nn.functional.cross_entropy(logits, tb) + cfg.magnitude_weight * _gaussian_nll(mu, lv, *mb)
    best: tuple[float, Any, int] = (math.inf, None, 0)
    samples = train0
    epoch = 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.max_epochs, unit="epoch", desc="train")
    for epoch in range(1, cfg.max_epochs + 1):
        if epoch > 1:
            samples = _epoch_samples(train_ds, cfg, rng)
        x = torch.from_numpy(samples["x"])
        t = torch.from_numpy(class_targets(samples))
        mt = _magnitude_targets(samples)
        order = torch.from_numpy(rng.permutation(len(t)))
        model.train()
        for b in range(0, len(order), cfg.batch_size):
            sel = order[b:b + cfg.batch_size]
            loss = loss_of(x[sel], t[sel], tuple(a[sel] for a in mt))
            opt.zero_grad()
            loss.backward()
            opt.step()
        model.eval()
        with torch.no_grad():  # early stopping on the classification loss (the magnitude head must not stop it)
            vloss = float(torch.nn.functional.cross_entropy(model.logits(xv), tv))
        if vloss < best[0] - 1e-5:
            best = (vloss, {k: v.clone() for k, v in model.state_dict().items()}, epoch)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(val_loss=f"{vloss:.4f}", best=best[2])
        if epoch - best[2] >= cfg.patience:
            break
    if bar is not None:
        bar.close()
    model.load_state_dict(best[1])
    model.eval()
    with torch.no_grad():
        temperature = _fit_temperature(model.logits(xv), tv)
        model.temperature.fill_(temperature)
        if mag:  # one SD scale, fitted on the validation split's identifiable samples
            _, mu, lv = model.heads(xv)
            target, label, ident = mv
            m = mu.gather(1, label[:, None])[:, 0]
            sd = torch.exp(0.5 * lv.gather(1, label[:, None])[:, 0])
            z = (torch.abs(target - m) / sd)[ident].double().numpy()
            model.magnitude_sd_scale.fill_(interval_scale(z))
    return {"model": model, "training_s": time.perf_counter() - t0, "epochs": epoch, "best_epoch": best[2],
            "validation_loss": best[0], "temperature": temperature,
            "parameters": int(sum(p.numel() for p in model.net.parameters())), "first_samples": train0}


#: Nominal shares of the central 68 % and 95 % predictive intervals (±1 and ±1.959964 SD).
INTERVAL_LEVELS = ((1.0, 0.6827), (1.959964, 0.9545))


def interval_scale(z: np.ndarray) -> float:
    """The factor ``c`` on the predicted SDs whose ±1·c·SD and ±1.96·c·SD intervals contain shares of
    the standardised errors ``z = |log10 error| / SD`` closest to 68.27 % and 95.45 % (least squares
    over the two levels; a grid of 0.2-5 in steps of 0.1 %).

    The maximum-likelihood factor ``√⟨z²⟩`` is set by the tails: the magnitude errors have heavier
    tails than a Gaussian (a pixel near a regime boundary), which made the 68 % interval contain 78 %
    of the test pixels; matching the two stated levels is what the intervals promise. 1.0 without
    samples.
    """
    z = np.asarray(z, np.float64)
    z = z[np.isfinite(z)]
    if z.size == 0:
        return 1.0
    grid = np.exp(np.arange(math.log(0.2), math.log(5.0), 1e-3))
    zs = np.sort(z)
    loss = np.zeros_like(grid)
    for k, level in INTERVAL_LEVELS:
        share = np.searchsorted(zs, k * grid, side="right") / z.size
        loss += (share - level) ** 2
    return float(grid[int(np.argmin(loss))])


def evaluation_sets(ds: Dataset, cfg: TrainConfig, spec: FeatureSpec, rng: np.random.Generator):
    """Evaluation samples per pool size; with ``ds.x_ref`` (signature specs) also the LIV/OCDS inputs of
    the very same (pooled) pixels, ``({pool: samples}, {pool: reference samples} or {})``."""
    if ds.x_ref is None:
        return {str(n): eval_samples(ds, n, rng) for n in cfg.eval_pools}, {}
    f = ds.x.shape[1]
    joint = dataclasses.replace(ds, x=np.concatenate([ds.x, ds.x_ref], axis=1), x_ref=None)
    tests, refs = {}, {}
    for n in cfg.eval_pools:
        s = eval_samples(joint, n, rng)
        x = s["x"]
        tests[str(n)] = {**s, "x": np.concatenate([x[:, :f], x[:, -1:]], axis=1)}
        refs[str(n)] = {**s, "x": np.concatenate([x[:, f:-1], x[:, -1:]], axis=1)}
    return tests, refs


def _reference_model(spec: FeatureSpec):
    """The shipped LIV/OCDS model whose configurations are the spec's (None if there is none)."""
    from .infer import load_model, shipped_models

    for name in shipped_models():
        try:
            mdl = load_model(name, threads=1)
        except ValueError:
            continue
        ref = mdl.spec
        if (not ref.is_signature and len(ref.configurations) == len(spec.configurations)
                and all(a.matches(b.wavelength_um, b.lateral_resolution_um, b.axial_resolution_um)
                        for a, b in zip(ref.configurations, spec.configurations))):
            return mdl
    return None


def _magnitude_eval(model: MotionClassifier, s: dict[str, np.ndarray]) -> dict[str, Any]:
    """Magnitude error and interval coverage on identifiable samples (head of the true motion class)."""
    ident = s["status"] == 0
    with torch.no_grad():
        mu, sd = model.magnitude(torch.from_numpy(s["x"][ident]))
    y = s["y"][ident]
    m = mu.numpy()[np.arange(len(y)), y].astype(np.float64)
    sdv = sd.numpy()[np.arange(len(y)), y].astype(np.float64)
    err = np.abs(m - np.log10(s["magnitude"][ident]))
    out: dict[str, Any] = {"samples": int(len(y)), "median_abs_log10_error": float(np.median(err)),
                           "mean_abs_log10_error": float(err.mean()),
                           "coverage_68": float(np.mean(err <= sdv)), "coverage_95": float(np.mean(err <= 1.959964 * sdv)),
                           "median_predicted_sd": float(np.median(sdv))}
    out["by_class"] = {CLASSES[c]: {"median_abs_log10_error": float(np.median(err[y == c])),
                                    "coverage_68": float(np.mean(err[y == c] <= sdv[y == c])),
                                    "coverage_95": float(np.mean(err[y == c] <= 1.959964 * sdv[y == c]))}
                       for c in range(len(CLASSES)) if np.any(y == c)}
    return out


def train(config: TrainConfig | None = None, prior: Prior | None = None, *, cache_dir=None, use_cache: bool = True,
          progress: bool = False, log=print, spec: FeatureSpec | None = None) -> TrainResult:
    """Run the recipe of the module docstring; returns the model, the report and the test inputs.

    ``spec``: the feature spec as a value (``doct-train --like``); default ``config.spec`` (a shipped
    name or a TOML file)."""
    cfg = config or TrainConfig()
    prior = prior or default_prior(cfg)
    spec = load_spec(cfg.spec if spec is None else spec)
    rule = make_rule(prior.identifiability_epsilon, cfg.min_probability)
    say = log or (lambda *a, **k: None)

    # 1. data
    t_sim = 0.0
    n_sim_samples = 0
    data: dict[str, Dataset] = {}
    for split, draws in (("train", cfg.draws_train), ("validation", cfg.draws_validation), ("test", cfg.draws_test)):
        ds = make_dataset(spec, prior, seed=cfg.seed, split=split, draws=draws, trials_per_draw=cfg.trials_per_draw,
                          replicates=cfg.replicates, truncation_tolerance=cfg.truncation_tolerance, truncation=cfg.truncation, cache_dir=cache_dir, use_cache=use_cache,
                          progress=progress)
        data[split] = ds
        t_sim += ds.meta["elapsed_s"]
        n_sim_samples += draws * cfg.trials_per_draw
        say(f"{split}: {len(ds)} samples from {draws} draws ({'cache' if ds.meta['from_cache'] else 'simulated'}, "
            f"{ds.meta['seconds_per_draw']:.3f} s/draw); ground truth per draw: {ds.meta['draw_status_counts']}")

    # 2-5. network: targets, pooled samples, AdamW with early stopping, temperature (fit_network)
    fit = fit_network(data["train"], data["validation"], spec, cfg, progress=progress)
    model, train0, epoch, temperature = fit["model"], fit["first_samples"], fit["epochs"], fit["temperature"]
    best = (fit["validation_loss"], None, fit["best_epoch"])
    train_s = fit["training_s"]
    say(f"network: {epoch} epochs (best {best[2]}, validation loss {best[0]:.4f}), temperature {temperature:.3f}, "
        f"{train_s:.1f} s")

    def net_predict(xx: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(xx)).numpy()

    predictors: dict[str, Any] = {"network": net_predict}
    timing = {"network": {"train_s": train_s}}

    # 6. baselines
    if cfg.baselines:
        from sklearn.ensemble import HistGradientBoostingClassifier
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        mask, cmask = feature_masks(spec)
        xb = transform_numpy(train0["x"], mask, cmask)
        yb = class_targets(train0)
        for name, est in (("logistic_regression", make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000))),
                          ("gradient_boosting", HistGradientBoostingClassifier(max_iter=300, random_state=cfg.seed))):
            t1 = time.perf_counter()
            est.fit(xb, yb)
            timing[name] = {"train_s": time.perf_counter() - t1}
            full = np.eye(len(CLASS_NAMES))[est.classes_]  # a class absent from a small training split: p = 0
            predictors[name] = (lambda e, f: (lambda xx: e.predict_proba(transform_numpy(xx, mask, cmask)) @ f))(est, full)
            say(f"{name}: trained in {timing[name]['train_s']:.2f} s")

    # 7. evaluation on the test split (its own seeded stream: the order of the steps changes no number)
    ev_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(9,)))
    tests, tests_ref = evaluation_sets(data["test"], cfg, spec, ev_rng)
    reference = _reference_model(spec) if tests_ref else None
    test_metrics: dict[str, dict[str, Any]] = {}
    probs_net: dict[str, np.ndarray] = {}
    for name, fn in predictors.items():
        test_metrics[name] = {}
        for pool, s in tests.items():
            if pool == "1":
                p, us = _timed_predict(fn, s["x"])
                timing[name]["inference_us_per_sample"] = us
            else:
                p = fn(s["x"])
            if name == "network":
                probs_net[pool] = p
            test_metrics[name][pool] = evaluate(p, s["y"], s["status"], CLASS_NAMES, rule)
    if reference is not None:  # the shipped LIV/OCDS model on LIV and OCDS of the same test pixels
        name = f"{reference.metadata['spec']['name']} (LIV/OCDS model)"
        test_metrics[name] = {}
        for pool, s in tests_ref.items():
            if pool == "1":
                p, us = _timed_predict(reference.predict, s["x"])
                timing[name] = {"train_s": math.nan, "inference_us_per_sample": us}
            else:
                p = reference.predict(s["x"])
            test_metrics[name][pool] = evaluate(p, s["y"], s["status"], CLASS_NAMES, rule)
    magnitude_report = None
    if _uses_magnitude(cfg, spec):
        magnitude_report = {pool: _magnitude_eval(model, s) for pool, s in tests.items()}
        say("magnitude (pool 1): " + ", ".join(f"{k} {v:.3f}" for k, v in magnitude_report["1"].items()
                                               if isinstance(v, float)))
    bulk_report = None
    if (spec.needs_field if cfg.bulk_phase_test is None else cfg.bulk_phase_test):
        bulk = make_dataset(spec, prior, seed=cfg.seed, split="test", draws=cfg.draws_test,
                            trials_per_draw=cfg.trials_per_draw, replicates=cfg.replicates,
                            truncation_tolerance=cfg.truncation_tolerance, truncation=cfg.truncation, cache_dir=cache_dir, use_cache=use_cache,
                            progress=progress, bulk_phase=True)
        t_sim += bulk.meta["elapsed_s"]
        b_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(9,)))
        btests, _ = evaluation_sets(bulk, cfg, spec, b_rng)
        bulk_report = {pool: evaluate(net_predict(s["x"]), s["y"], s["status"], CLASS_NAMES, rule)
                       for pool, s in btests.items() if pool in ("1", "25")}
        say(f"random bulk phase per frame: balanced accuracy (identifiable, pool 1) "
            f"{bulk_report['1']['balanced_accuracy_identifiable']:.3f}, coverage {bulk_report['1']['coverage_identifiable']:.3f}")

    ranges = [prior.magnitude_range(label) for label in range(len(CLASSES))]
    conf_pools = [p for p in ("1", "25") if p in tests] or [str(cfg.eval_pools[0])]
    thresholds = sorted({*COVERAGE_THRESHOLDS, float(cfg.min_probability)})  # the model's own threshold included
    curves = {pool: coverage_curve(probs_net[pool], tests[pool]["y"], tests[pool]["status"], CLASS_NAMES, rule,
                                   thresholds) for pool in conf_pools}
    by_mag = {pool: magnitude_table(probs_net[pool], tests[pool]["y"], tests[pool]["status"],
                                    tests[pool]["magnitude"], CLASS_NAMES, rule, ranges) for pool in conf_pools}
    s1 = tests["1"]
    noisy = np.isfinite(s1["snr_db"])
    mixed = s1["static_fraction"] > 0
    conditions = {"no noise, no static": ~noisy & ~mixed, "no noise, static fraction": ~noisy & mixed,
                  "noise, no static": noisy & ~mixed, "noise and static fraction": noisy & mixed}
    by_cond = {name: evaluate(probs_net["1"][m], s1["y"][m], s1["status"][m], CLASS_NAMES, rule)
               for name, m in conditions.items() if m.any()}
    ses = {pool: bootstrap_se(probs_net[pool], tests[pool]["y"], tests[pool]["status"], tests[pool]["draw"],
                              CLASS_NAMES, rule, seed=cfg.seed) for pool in conf_pools}
    # 8. the shifted prior (signature specs)
    shifted_report, shifted_ds = None, None
    if (spec.is_signature if cfg.shifted_test is None else cfg.shifted_test):
        sp = shifted_prior(prior)
        shifted_ds = make_dataset(spec, sp, seed=cfg.seed, split="test", draws=cfg.draws_test,
                                  trials_per_draw=cfg.trials_per_draw, replicates=cfg.replicates,
                                  truncation_tolerance=cfg.truncation_tolerance, truncation=cfg.truncation, cache_dir=cache_dir,
                                  use_cache=use_cache, progress=progress)
        s_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(10,)))
        stests, _ = evaluation_sets(shifted_ds, cfg, spec, s_rng)
        sprobs = {pool: net_predict(s["x"]) for pool, s in stests.items()}
        s_ranges = [sp.diffusion_um2_per_s, sp.speed_um_per_s, sp.speed_um_per_s]
        shifted_report = {
            "prior": sp.to_dict(), "draws": cfg.draws_test, "samples": len(shifted_ds),
            "draw_status_counts": shifted_ds.meta["draw_status_counts"],
            "dropped_empty": shifted_ds.meta["dropped_empty"], "simulation_s": shifted_ds.meta["elapsed_s"],
            "from_cache": shifted_ds.meta["from_cache"],
            "test": {pool: evaluate(sprobs[pool], s["y"], s["status"], CLASS_NAMES, rule)
                     for pool, s in stests.items()},
            "standard_errors": {pool: bootstrap_se(sprobs[pool], stests[pool]["y"], stests[pool]["status"],
                                                   stests[pool]["draw"], CLASS_NAMES, rule, seed=cfg.seed)
                                for pool in conf_pools},
            "by_magnitude": {pool: magnitude_table(sprobs[pool], stests[pool]["y"], stests[pool]["status"],
                                                   stests[pool]["magnitude"], CLASS_NAMES, rule, s_ranges)
                             for pool in conf_pools},
            "coverage_curve": {pool: coverage_curve(sprobs[pool], stests[pool]["y"], stests[pool]["status"],
                                                    CLASS_NAMES, rule, thresholds) for pool in conf_pools},
            "flow_bands": {pool: flow_recall_by_band(sprobs[pool], stests[pool]["y"], stests[pool]["status"],
                                                     stests[pool]["polar_angle_deg"], stests[pool]["magnitude"],
                                                     CLASS_NAMES, rule) for pool in conf_pools},
        }
        if _uses_magnitude(cfg, spec):
            shifted_report["magnitude"] = {pool: _magnitude_eval(model, s) for pool, s in stests.items()}
        tp = SHIFTED_TARGETS["pool"]
        if tp in shifted_report["test"]:
            m = shifted_report["test"][tp]
            bal, ece = m["balanced_accuracy_identifiable"], m["ece"]
            shifted_report["targets"] = {
                **SHIFTED_TARGETS,
                "met": bool(math.isfinite(bal) and bal >= SHIFTED_TARGETS["balanced_accuracy_identifiable"]
                            and ece <= SHIFTED_TARGETS["ece"])}
        m1 = shifted_report["test"]["1"]
        say(f"shifted prior ({len(shifted_ds)} samples, {'cache' if shifted_ds.meta['from_cache'] else 'simulated'}): "
            f"balanced accuracy (identifiable, pool 1) {m1['balanced_accuracy_identifiable']:.3f}, coverage "
            f"{m1['coverage_identifiable']:.3f}, ECE {m1['ece']:.3f}")
    # the report (classifier.report writes it)
    import torchdoct

    report = {
        "classifier_version": __version__,
        "torchdoct_version": torchdoct.__version__,
        "torch_version": torch.__version__,
        "spec": spec.to_dict(),
        "feature_names": list(spec.feature_names),
        "classes": list(CLASS_NAMES),
        "rule": rule,
        "prior": prior.to_dict(),
        "config": cfg.to_dict(),
        "seed": cfg.seed,
        "data": {
            "draws": {k: v.meta["draws"] for k, v in data.items()},
            "trials_per_draw": cfg.trials_per_draw,
            "samples": {k: len(v) for k, v in data.items()},
            "draw_status_counts": {k: v.meta["draw_status_counts"] for k, v in data.items()},
            "dropped_empty": {k: v.meta["dropped_empty"] for k, v in data.items()},
            "simulation_s": t_sim,
            "replicates": cfg.replicates,
            "ms_per_trial": t_sim / max(n_sim_samples, 1) * 1e3,
            "s_per_draw": t_sim / max(sum(c for c in (cfg.draws_train, cfg.draws_validation, cfg.draws_test)), 1),
            "from_cache": {k: v.meta["from_cache"] for k, v in data.items()},
            "threads": torch.get_num_threads(),
        },
        "training": {"seconds": train_s, "epochs": epoch, "best_epoch": best[2], "validation_loss": best[0],
                     "temperature": temperature},
        "test": test_metrics,
        "timing": timing,
        "confusion_pools": conf_pools,
        "standard_errors": ses,
        "by_magnitude": by_mag,
        "by_condition": by_cond,
        "coverage_curve": curves,
        "flow_bands": {pool: flow_recall_by_band(probs_net[pool], tests[pool]["y"], tests[pool]["status"],
                                                 tests[pool]["polar_angle_deg"], tests[pool]["magnitude"],
                                                 CLASS_NAMES, rule) for pool in conf_pools},
        "status_names": list(STATUS),
    }
    if magnitude_report is not None:
        report["magnitude"] = magnitude_report
    if bulk_report is not None:
        report["bulk_phase"] = bulk_report
    datasets = dict(data)
    if shifted_report is not None:
        report["shifted_prior"] = shifted_report
        datasets["shifted_prior"] = shifted_ds
    return TrainResult(model=model, report=report, spec=spec, prior=prior, config=cfg, rule=rule,
                       test_inputs=tests["1"]["x"], datasets=datasets)


# The former private names of the steps other modules use (learning curve, g1 fit, trade-offs).
_masks, _eval_samples, _targets, _test_sets = feature_masks, eval_samples, class_targets, evaluation_sets

"""Training as a pipeline of public steps: recipe → samples → fit → every test set evaluated → report.

:func:`train` runs the whole recipe of the shipped model from a :class:`TrainConfig` (the recipes:
:mod:`classifier.recipe`, whose names this module re-exports), one public step after the other:

1. the recipe (:func:`plan_training` → :class:`TrainPlan`): the config, the training prior, the feature
   spec, the indeterminate rule (:mod:`classifier.rule`), and what the spec takes: a magnitude head
   (signature specs), a test split with a random bulk phase per frame (specs that read the phase), a test
   split from :data:`SHIFTED_PRIOR` (signature specs: other flow angles, fixed density, no static
   fraction, other noise; accuracy and calibration must hold there, :data:`SHIFTED_TARGETS`);
2. the samples (:func:`simulate_data` → :class:`TrainingData`): the train, validation and test splits
   and those test sets, simulated or loaded from the cache (:func:`classifier.dataset.make_dataset`);
3. the fit (:func:`fit_models` → :class:`FittedModels`): the network (:func:`fit_network`): targets =
   the motion type where the ground truth says the motion is identifiable, else ``indeterminate``
   (:func:`class_targets`); pooled samples: a feature vector may be the mean over ``n`` independent
   pixels (``pool_pixels`` = n, the model's last input), each epoch every single trial (n = 1) plus, per
   draw, ``pooled_per_group`` means over random subsets of its trials with n log-uniform in
   [2, ``max_pool_pixels``], the validation set one fixed draw of the same mixture; AdamW on
   cross-entropy (plus the magnitude head's Gaussian NLL for magnitude models, :mod:`classifier.model`),
   minibatches shuffled by a seeded numpy generator, early stopping on the validation cross-entropy
   (best weights kept); temperature scaling on the validation set (grid search of the NLL), stored in
   the model. Then the scikit-learn baselines (logistic regression, histogram gradient boosting) on
   the same training samples (singles + one pooled draw);
4. every test set evaluated (:func:`evaluate_test_sets`), each by the one function
   :func:`classifier.evaluation.evaluate_set`: the test split at ``eval_pools`` pooled pixels (n = 1:
   every trial; n > 1: 8 random subsets per draw; :func:`evaluation_sets`) for every model (and the
   shipped LIV/OCDS model on the same pixels for signature specs, :func:`reference_model`), the
   random-bulk-phase and the shifted-prior test splits for the network;
5. the report (:func:`training_report`; written by :func:`classifier.report.write_report`).

:func:`train_to_files` adds the ONNX export, its check in onnxruntime and the report files
(``doct-train``). Everything is seeded from ``TrainConfig.seed`` (the evaluation samples of each test
set from their own stream, so the order of the steps changes no number); the global torch RNG is not
used (weights are initialised inside :func:`torch.random.fork_rng`).

Kept whole (over 800 lines): the public steps of the pipeline pass one plan and one data set along;
each step is a function of this file, in the order :func:`train` calls them.
"""

from __future__ import annotations

import dataclasses
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from . import __version__
from .dataset import Dataset, make_dataset
from .evaluation import CLASS_NAMES, evaluate_set
from .features import METRIC_UNITS, FeatureSpec, load_spec
from .model import DECORRELATION_OFFSET, LIV_OFFSET_DB2, MotionClassifier
from .prior import CLASSES, Prior
from .recipe import (  # noqa: F401
    OWN_SIGNATURE_RECIPE,
    SCALED_PRIOR_SPECS,
    SHIFTED_PRIOR,
    SHIFTED_TARGETS,
    SPEC_RECIPES,
    TrainConfig,
    default_prior,
    recipe_for,
    shifted_prior,
)
from .rule import make_rule
from .truth import STATUS

__all__ = [
    "TrainConfig",
    "TrainResult",
    "train",
    "fit_network",
    "pooled_samples",
    "CLASS_NAMES",
    "transform_numpy",
    "SHIFTED_PRIOR",
    "SHIFTED_TARGETS",
    "shifted_prior",
    "feature_masks",
    "eval_samples",
    "class_targets",
    "evaluation_sets",
    "TrainPlan",
    "plan_training",
    "TrainingData",
    "simulate_data",
    "FittedModels",
    "fit_models",
    "evaluate_test_sets",
    "training_report",
    "reference_model",
    "network_predictions",
    "interval_scale",
    "train_to_files",
]


def _uses_magnitude(cfg: TrainConfig, spec: FeatureSpec) -> bool:
    return spec.is_signature if cfg.magnitude is None else bool(cfg.magnitude)


def _log_columns(spec: FeatureSpec) -> list[int]:
    """Columns log-transformed by the model: LIV and its signature twin ``db_variance`` (dB²)."""
    return [i for i, (m, _) in enumerate(spec.features) if m in ("liv", "db_variance")]


def _correlation_columns(spec: FeatureSpec) -> list[int]:
    """Columns the model reads as log decorrelation: the signature's correlation coefficients
    (``rho_lin_m``, ``rho_db_m``, ``g1_m``; :mod:`classifier.model`)."""
    from torchdoct.sim.signature import parse_feature

    return [
        i
        for i, (m, _) in enumerate(spec.features)
        if m not in METRIC_UNITS and parse_feature(m)[0] in ("rho_lin", "rho_db", "g1")
    ]


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


#: Elements (rows × trials × features) of one block of :func:`pooled_samples` (about 32 MB in float64).
_POOL_BLOCK = 4_000_000


def pooled_samples(ds: Dataset, sizes_per_group: list[np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Means over random subsets of each group's trials (a group shares every parameter).

    ``sizes_per_group[g]`` lists the subset sizes wanted from group ``g`` (in :func:`_groups` order;
    capped at its number of trials). Returns inputs ``[M, F+1]`` (features + pool_pixels) and the
    per-sample truth arrays.

    Each subset is the first ``n`` trials of a random permutation of its group (``argsort`` of uniforms),
    its mean the float64 running sum of those trials divided by ``n``. The uniforms of every group are
    drawn at once, in group order (the same numbers as drawing them group by group), and groups of equal
    size are permuted and summed together in blocks of :data:`_POOL_BLOCK` elements.
    """
    groups = _groups(ds)[: len(sizes_per_group)]
    sizes = [np.minimum(np.asarray(s, dtype=np.int64), g.size) for g, s in zip(groups, sizes_per_group)]
    n = np.array([s.size for s in sizes], dtype=np.int64)
    t = np.array([g.size for g in groups], dtype=np.int64)
    u = rng.random(int(np.sum(n * t)))
    u_start = np.concatenate([[0], np.cumsum(n * t)])
    row_start = np.concatenate([[0], np.cumsum(n)])
    f = ds.x.shape[1]
    mean = np.empty((int(row_start[-1]), f))
    for tt in np.unique(t[n > 0]):
        ks = np.flatnonzero((t == tt) & (n > 0))
        blocks = np.array_split(ks, min(ks.size, max(1, int(math.ceil(float(n[ks].sum()) * tt * f / _POOL_BLOCK)))))
        for block in blocks:
            perm = np.argsort(np.concatenate([u[u_start[k] : u_start[k + 1]] for k in block]).reshape(-1, tt), axis=1)
            trials = np.concatenate([np.broadcast_to(groups[k], (n[k], tt)) for k in block])
            cs = np.cumsum(ds.x[np.take_along_axis(trials, perm, axis=1)].astype(np.float64), axis=1)
            sz = np.concatenate([sizes[k] for k in block])
            rows = np.concatenate([np.arange(row_start[k], row_start[k + 1]) for k in block])
            mean[rows] = cs[np.arange(sz.size), sz - 1] / sz[:, None]
    all_sizes = np.concatenate(sizes) if sizes else np.zeros(0, np.int64)
    first = np.repeat(np.array([g[0] for g in groups], dtype=np.int64), n)
    out = {k: getattr(ds, k)[first] for k in _TRUTH}
    out["x"] = np.concatenate([mean, all_sizes[:, None].astype(np.float64)], axis=1).astype(np.float32)
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
    return (
        torch.from_numpy(np.log10(s["magnitude"]).astype(np.float32)),
        torch.from_numpy(s["y"].astype(np.int64)),
        torch.from_numpy(s["status"] == 0),
    )


def _gaussian_nll(
    mu: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor, label: torch.Tensor, ident: torch.Tensor
) -> torch.Tensor:
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
    assert out is not None  # repeats >= 1
    return out, best / max(len(x), 1) * 1e6


def fit_network(
    train_ds: Dataset, val_ds: Dataset, spec, cfg: TrainConfig, *, progress: bool = False
) -> dict[str, Any]:
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
        model = MotionClassifier(
            spec.n_features,
            len(CLASS_NAMES),
            liv_cols,
            cfg.hidden,
            n_magnitude=len(CLASSES) if mag else 0,
            correlation_columns=_correlation_columns(spec),
        )
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
    # The next epoch's samples are drawn in a second thread while this epoch trains (numpy releases the GIL):
    # the generator is used in the same order as drawing them in turn (this epoch's samples, its batch
    # order, the next epoch's samples, ...), so the model is bit-identical; an early stop leaves one unused.
    pool = ThreadPoolExecutor(max_workers=1)
    upcoming: Future[dict[str, np.ndarray]] | None = None
    try:
        for epoch in range(1, cfg.max_epochs + 1):
            if epoch > 1:
                assert upcoming is not None  # submitted by the previous epoch
                samples = upcoming.result()
            x = torch.from_numpy(samples["x"])
            t = torch.from_numpy(class_targets(samples))
            mt = _magnitude_targets(samples)
            order = torch.from_numpy(rng.permutation(len(t)))
            if epoch < cfg.max_epochs:
                upcoming = pool.submit(_epoch_samples, train_ds, cfg, rng)
            model.train()
            for b in range(0, len(order), cfg.batch_size):
                sel = order[b : b + cfg.batch_size]
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
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
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
    return {
        "model": model,
        "training_s": time.perf_counter() - t0,
        "epochs": epoch,
        "best_epoch": best[2],
        "validation_loss": best[0],
        "temperature": temperature,
        "parameters": int(sum(p.numel() for p in model.net.parameters())),
        "first_samples": train0,
    }


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


def reference_model(spec: FeatureSpec):
    """The shipped LIV/OCDS model whose configurations are the spec's (None if there is none): the
    comparison row of a signature model's report, scored on LIV and OCDS of the same test pixels."""
    from .infer import load_model, shipped_models

    for name in shipped_models():
        try:
            mdl = load_model(name, threads=1)
        except ValueError:
            continue
        ref = mdl.spec
        if (
            not ref.is_signature
            and len(ref.configurations) == len(spec.configurations)
            and all(
                a.matches(b.wavelength_um, b.lateral_resolution_um, b.axial_resolution_um)
                for a, b in zip(ref.configurations, spec.configurations)
            )
        ):
            return mdl
    return None


def network_predictions(model: MotionClassifier, s: dict[str, np.ndarray], magnitude: bool = False):
    """The network's probabilities ``[N, C]`` of the samples ``s`` and, with ``magnitude``, its predicted
    ``(log10 magnitude, SD)`` ``[N, K]``, computed on the identifiable rows (the only rows
    :func:`classifier.evaluation.magnitude_metrics` reads; NaN elsewhere); ``None`` without."""
    with torch.no_grad():
        p = model(torch.from_numpy(s["x"])).numpy()
        if not magnitude:
            return p, None
        ident = s["status"] == 0
        mu, sd = model.magnitude(torch.from_numpy(s["x"][ident]))
    mean = np.full((len(p), mu.shape[1]), np.nan, np.float32)
    sdv = np.full((len(p), sd.shape[1]), np.nan, np.float32)
    mean[ident], sdv[ident] = mu.numpy(), sd.numpy()
    return p, (mean, sdv)


# ------------------------------------------------------------------------------------------------
# the steps of train()


@dataclass(frozen=True)
class TrainPlan:
    """Step 1 of :func:`train`: the recipe, the training prior, the feature spec, the indeterminate rule and
    what the spec takes: a magnitude head, the random-bulk-phase and the shifted-prior test sets."""

    config: TrainConfig
    prior: Prior
    spec: FeatureSpec
    rule: dict[str, Any]
    magnitude: bool
    bulk_phase_test: bool
    shifted_test: bool


def plan_training(
    config: TrainConfig | None = None, prior: Prior | None = None, spec: FeatureSpec | str | None = None
) -> TrainPlan:
    """The :class:`TrainPlan` of a recipe (default :class:`TrainConfig`), a prior (default
    :func:`default_prior`) and a spec (default ``config.spec``: a shipped name or a TOML file)."""
    cfg = config or TrainConfig()
    prior = prior or default_prior(cfg)
    spec = load_spec(cfg.spec if spec is None else spec)
    return TrainPlan(
        config=cfg,
        prior=prior,
        spec=spec,
        rule=make_rule(prior.identifiability_epsilon, cfg.min_probability),
        magnitude=_uses_magnitude(cfg, spec),
        bulk_phase_test=bool(spec.needs_field if cfg.bulk_phase_test is None else cfg.bulk_phase_test),
        shifted_test=bool(spec.is_signature if cfg.shifted_test is None else cfg.shifted_test),
    )


@dataclass
class TrainingData:
    """Step 2 of :func:`train`: the train, validation and test splits (``splits``), and the test sets the
    plan takes: the test draws with a random bulk phase per frame, and test draws from the shifted prior."""

    splits: dict[str, Dataset]
    bulk_phase: Dataset | None = None
    shifted_prior: Dataset | None = None

    @property
    def simulation_s(self) -> float:
        """Simulation time of the splits and the bulk-phase set (the shifted prior's is reported with it)."""
        return sum(ds.meta["elapsed_s"] for ds in (*self.splits.values(), self.bulk_phase) if ds is not None)


def simulate_data(
    plan: TrainPlan, *, cache_dir=None, use_cache: bool = True, progress: bool = False, log=print
) -> TrainingData:
    """Simulate (or load from the cache) every dataset of the plan (:func:`classifier.dataset.make_dataset`,
    seeded by the recipe's seed and the split: the order changes no number)."""
    cfg, spec, prior = plan.config, plan.spec, plan.prior
    say = log or (lambda *a, **k: None)
    common = dict(
        seed=cfg.seed,
        trials_per_draw=cfg.trials_per_draw,
        replicates=cfg.replicates,
        truncation_tolerance=cfg.truncation_tolerance,
        truncation=cfg.truncation,
        cache_dir=cache_dir,
        use_cache=use_cache,
        progress=progress,
    )
    splits: dict[str, Dataset] = {}
    for split, draws in (("train", cfg.draws_train), ("validation", cfg.draws_validation), ("test", cfg.draws_test)):
        ds = make_dataset(spec, prior, split=split, draws=draws, **common)
        splits[split] = ds
        say(
            f"{split}: {len(ds)} samples from {draws} draws ({'cache' if ds.meta['from_cache'] else 'simulated'}, "
            f"{ds.meta['seconds_per_draw']:.3f} s/draw); ground truth per draw: {ds.meta['draw_status_counts']}"
        )
    data = TrainingData(splits)
    if plan.bulk_phase_test:
        data.bulk_phase = make_dataset(spec, prior, split="test", draws=cfg.draws_test, bulk_phase=True, **common)
    if plan.shifted_test:
        data.shifted_prior = make_dataset(spec, shifted_prior(prior), split="test", draws=cfg.draws_test, **common)
    return data


@dataclass
class FittedModels:
    """Step 3 of :func:`train`: the network (:func:`fit_network`'s result), the predictors to evaluate
    (``name -> f(x) = probabilities``: the network, then the baselines) and their training times (s)."""

    network: dict[str, Any]
    predictors: dict[str, Any]
    train_s: dict[str, float]

    @property
    def model(self) -> MotionClassifier:
        return self.network["model"]


def fit_models(plan: TrainPlan, data: TrainingData, *, progress: bool = False, log=print) -> FittedModels:
    """The network (:func:`fit_network`) and, with ``config.baselines``, the scikit-learn baselines (logistic
    regression, histogram gradient boosting) on the network's first training samples."""
    cfg, spec = plan.config, plan.spec
    say = log or (lambda *a, **k: None)
    fit = fit_network(data.splits["train"], data.splits["validation"], spec, cfg, progress=progress)
    model = fit["model"]
    say(
        f"network: {fit['epochs']} epochs (best {fit['best_epoch']}, validation loss {fit['validation_loss']:.4f}), "
        f"temperature {fit['temperature']:.3f}, {fit['training_s']:.1f} s"
    )
    predictors: dict[str, Any] = {"network": lambda xx: network_predictions(model, {"x": xx})[0]}
    train_s = {"network": fit["training_s"]}
    if cfg.baselines:
        from sklearn.ensemble import HistGradientBoostingClassifier
        from sklearn.linear_model import LogisticRegression
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler

        mask, cmask = feature_masks(spec)
        train0 = fit["first_samples"]
        xb = transform_numpy(train0["x"], mask, cmask)
        yb = class_targets(train0)
        for name, est in (
            ("logistic_regression", make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000))),
            ("gradient_boosting", HistGradientBoostingClassifier(max_iter=300, random_state=cfg.seed)),
        ):
            t1 = time.perf_counter()
            est.fit(xb, yb)
            train_s[name] = time.perf_counter() - t1
            full = np.eye(len(CLASS_NAMES))[est.classes_]  # a class absent from a small training split: p = 0
            predictors[name] = (lambda e, f: lambda xx: e.predict_proba(transform_numpy(xx, mask, cmask)) @ f)(
                est, full
            )
            say(f"{name}: trained in {train_s[name]:.2f} s")
    return FittedModels(network=fit, predictors=predictors, train_s=train_s)


#: Seeds (``spawn_key``) of the evaluation samples of each test set: the bulk-phase set pools the very
#: pixels of the test split.
_EVAL_STREAM = {"test": 9, "bulk_phase": 9, "shifted_prior": 10}


def _confusion_pools(plan: TrainPlan) -> list[str]:
    """Pools of the report's detailed tables (confusion, curves, bands, standard errors): 1 and 25."""
    pools = [str(n) for n in plan.config.eval_pools]
    return [p for p in ("1", "25") if p in pools] or [pools[0]]


def _by_pool(blocks: dict[str, dict[str, Any]], key: str, pools=None) -> dict[str, Any]:
    return {pool: b[key] for pool, b in blocks.items() if (pools is None or pool in pools)}


def evaluate_test_sets(plan: TrainPlan, data: TrainingData, fitted: FittedModels, *, log=print) -> dict[str, Any]:
    """Step 4 of :func:`train`: every model on every test set, each pool's samples scored by
    :func:`classifier.evaluation.evaluate_set`.

    Returns ``test`` (``{model: {pool: block}}``: the network, the baselines and, for signature specs, the
    shipped LIV/OCDS model on LIV and OCDS of the same pixels), ``inference_us`` (µs per sample at pool 1),
    ``bulk_phase`` and ``shifted_prior`` (``{pool: block}`` of the network, None when the plan has no such
    set) and ``test_inputs`` (the pool-1 inputs of the test split)."""
    cfg, spec, rule = plan.config, plan.spec, plan.rule
    say = log or (lambda *a, **k: None)
    conf = _confusion_pools(plan)
    model = fitted.model

    def samples(name: str, ds: Dataset):
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(_EVAL_STREAM[name],)))
        return evaluation_sets(ds, cfg, spec, rng)

    def network_blocks(sets, ranges, *, pools=None, own=False, magnitude=plan.magnitude):
        out = {}
        for pool, s in sets.items():
            if pools is not None and pool not in pools:
                continue
            p, mag = network_predictions(model, s, magnitude)
            if own and pool == "1":  # the same numbers, timed
                p, inference_us["network"] = _timed_predict(fitted.predictors["network"], s["x"])
            out[pool] = evaluate_set(
                p,
                s,
                rule,
                magnitude=mag,
                ranges=ranges,
                detail=ranges is not None and pool in conf,
                by_condition=own and pool == "1",
                seed=cfg.seed,
                class_samples=False,
            )
        return out

    # the test split: the network, the baselines, the shipped LIV/OCDS model
    inference_us: dict[str, float] = {}
    tests, tests_ref = samples("test", data.splits["test"])
    prior = plan.prior
    test = {"network": network_blocks(tests, [prior.magnitude_range(label) for label in range(len(CLASSES))], own=True)}
    for name, fn in fitted.predictors.items():
        if name == "network":
            continue
        test[name] = {}
        for pool, s in tests.items():
            if pool == "1":
                p, inference_us[name] = _timed_predict(fn, s["x"])
            else:
                p = fn(s["x"])
            test[name][pool] = evaluate_set(p, s, rule, detail=False)
    reference = reference_model(spec) if tests_ref else None
    if reference is not None:
        name = f"{reference.metadata['spec']['name']} (LIV/OCDS model)"
        test[name] = {}
        for pool, s in tests_ref.items():
            if pool == "1":
                p, inference_us[name] = _timed_predict(reference.predict, s["x"])
            else:
                p = reference.predict(s["x"])
            test[name][pool] = evaluate_set(p, s, rule, detail=False)
    if plan.magnitude:
        say(
            "magnitude (pool 1): "
            + ", ".join(f"{k} {v:.3f}" for k, v in test["network"]["1"]["magnitude"].items() if isinstance(v, float))
        )
    out: dict[str, Any] = {
        "test": test,
        "inference_us": inference_us,
        "bulk_phase": None,
        "shifted_prior": None,
        "test_inputs": tests["1"]["x"],
    }
    if data.bulk_phase is not None:  # the test draws with a random bulk phase per frame
        btests, _ = samples("bulk_phase", data.bulk_phase)
        bulk = network_blocks(btests, None, pools=("1", "25"), magnitude=False)
        out["bulk_phase"] = bulk
        m1 = bulk["1"]["metrics"]
        say(
            f"random bulk phase per frame: balanced accuracy (identifiable, pool 1) "
            f"{m1['balanced_accuracy_identifiable']:.3f}, coverage {m1['coverage_identifiable']:.3f}"
        )
    if data.shifted_prior is not None:  # test draws from the shifted prior
        sp = shifted_prior(prior)
        stests, _ = samples("shifted_prior", data.shifted_prior)
        shifted = network_blocks(stests, [sp.diffusion_um2_per_s, sp.speed_um_per_s, sp.speed_um_per_s])
        out["shifted_prior"] = shifted
        m1, ds = shifted["1"]["metrics"], data.shifted_prior
        say(
            f"shifted prior ({len(ds)} samples, {'cache' if ds.meta['from_cache'] else 'simulated'}): "
            f"balanced accuracy (identifiable, pool 1) {m1['balanced_accuracy_identifiable']:.3f}, coverage "
            f"{m1['coverage_identifiable']:.3f}, ECE {m1['ece']:.3f}"
        )
    return out


def training_report(
    plan: TrainPlan, data: TrainingData, fitted: FittedModels, evaluation: dict[str, Any]
) -> dict[str, Any]:
    """Step 5 of :func:`train`: the report (written by :func:`classifier.report.write_report`)."""
    import torchdoct

    cfg = plan.config
    conf = _confusion_pools(plan)
    fit = fitted.network
    splits = data.splits
    n_sim_samples = (cfg.draws_train + cfg.draws_validation + cfg.draws_test) * cfg.trials_per_draw
    net = evaluation["test"]["network"]
    timing = {name: {"train_s": s} for name, s in fitted.train_s.items()}
    for name, us in evaluation["inference_us"].items():
        timing.setdefault(name, {"train_s": math.nan})["inference_us_per_sample"] = us
    t_sim = data.simulation_s
    report = {
        "classifier_version": __version__,
        "torchdoct_version": torchdoct.__version__,
        "torch_version": torch.__version__,
        "spec": plan.spec.to_dict(),
        "feature_names": list(plan.spec.feature_names),
        "classes": list(CLASS_NAMES),
        "rule": plan.rule,
        "prior": plan.prior.to_dict(),
        "config": cfg.to_dict(),
        "seed": cfg.seed,
        "data": {
            "draws": {k: v.meta["draws"] for k, v in splits.items()},
            "trials_per_draw": cfg.trials_per_draw,
            "samples": {k: len(v) for k, v in splits.items()},
            "draw_status_counts": {k: v.meta["draw_status_counts"] for k, v in splits.items()},
            "dropped_empty": {k: v.meta["dropped_empty"] for k, v in splits.items()},
            "simulation_s": t_sim,
            "replicates": cfg.replicates,
            "ms_per_trial": t_sim / max(n_sim_samples, 1) * 1e3,
            "s_per_draw": t_sim / max(sum(c for c in (cfg.draws_train, cfg.draws_validation, cfg.draws_test)), 1),
            "from_cache": {k: v.meta["from_cache"] for k, v in splits.items()},
            "threads": torch.get_num_threads(),
        },
        "training": {
            "seconds": fit["training_s"],
            "epochs": fit["epochs"],
            "best_epoch": fit["best_epoch"],
            "validation_loss": fit["validation_loss"],
            "temperature": fit["temperature"],
        },
        "test": {name: _by_pool(blocks, "metrics") for name, blocks in evaluation["test"].items()},
        "timing": timing,
        "confusion_pools": conf,
        "standard_errors": _by_pool(net, "standard_errors", conf),
        "by_magnitude": _by_pool(net, "by_magnitude", conf),
        "by_condition": net["1"]["by_condition"],
        "coverage_curve": _by_pool(net, "coverage_curve", conf),
        "flow_bands": _by_pool(net, "flow_bands", conf),
        "status_names": list(STATUS),
    }
    if plan.magnitude:
        report["magnitude"] = _by_pool(net, "magnitude")
    if evaluation["bulk_phase"] is not None:
        report["bulk_phase"] = _by_pool(evaluation["bulk_phase"], "metrics")
    if evaluation["shifted_prior"] is not None:
        assert data.shifted_prior is not None  # evaluated only when drawn (evaluate_test_sets)
        report["shifted_prior"] = _shifted_report(plan, data.shifted_prior, evaluation["shifted_prior"], conf)
    return report


def _shifted_report(plan: TrainPlan, ds: Dataset, blocks: dict[str, dict[str, Any]], conf: list[str]) -> dict[str, Any]:
    """The shifted-prior section of the report, with its targets (:data:`SHIFTED_TARGETS`)."""
    rep = {
        "prior": shifted_prior(plan.prior).to_dict(),
        "draws": plan.config.draws_test,
        "samples": len(ds),
        "draw_status_counts": ds.meta["draw_status_counts"],
        "dropped_empty": ds.meta["dropped_empty"],
        "simulation_s": ds.meta["elapsed_s"],
        "from_cache": ds.meta["from_cache"],
        "test": _by_pool(blocks, "metrics"),
        "standard_errors": _by_pool(blocks, "standard_errors", conf),
        "by_magnitude": _by_pool(blocks, "by_magnitude", conf),
        "coverage_curve": _by_pool(blocks, "coverage_curve", conf),
        "flow_bands": _by_pool(blocks, "flow_bands", conf),
    }
    if plan.magnitude:
        rep["magnitude"] = _by_pool(blocks, "magnitude")
    tp = SHIFTED_TARGETS["pool"]
    if tp in rep["test"]:
        m = rep["test"][tp]
        bal, ece = m["balanced_accuracy_identifiable"], m["ece"]
        rep["targets"] = {
            **SHIFTED_TARGETS,
            "met": bool(
                math.isfinite(bal)
                and bal >= SHIFTED_TARGETS["balanced_accuracy_identifiable"]
                and ece <= SHIFTED_TARGETS["ece"]
            ),
        }
    return rep


def train(
    config: TrainConfig | None = None,
    prior: Prior | None = None,
    *,
    cache_dir=None,
    use_cache: bool = True,
    progress: bool = False,
    log=print,
    spec: FeatureSpec | None = None,
) -> TrainResult:
    """Run the recipe of the module docstring; returns the model, the report and the test inputs.

    ``spec``: the feature spec as a value (``doct-train --like``); default ``config.spec`` (a shipped
    name or a TOML file)."""
    plan = plan_training(config, prior, spec)  # 1. the recipe
    data = simulate_data(plan, cache_dir=cache_dir, use_cache=use_cache, progress=progress, log=log)  # 2. samples
    fitted = fit_models(plan, data, progress=progress, log=log)  # 3. fit
    evaluation = evaluate_test_sets(plan, data, fitted, log=log)  # 4. every test set
    report = training_report(plan, data, fitted, evaluation)  # 5. the report
    datasets = dict(data.splits)
    if data.shifted_prior is not None:
        datasets["shifted_prior"] = data.shifted_prior
    return TrainResult(
        model=fitted.model,
        report=report,
        spec=plan.spec,
        prior=plan.prior,
        config=plan.config,
        rule=plan.rule,
        test_inputs=evaluation["test_inputs"],
        datasets=datasets,
    )


def train_to_files(
    config: TrainConfig | None,
    paths: dict[str, Any],
    *,
    prior: Prior | None = None,
    spec: FeatureSpec | None = None,
    cache_dir=None,
    use_cache: bool = True,
    progress: bool = False,
    log=print,
) -> TrainResult:
    """:func:`train`, then the model exported to ``paths[".onnx"]`` (:func:`classifier.export.export_onnx`),
    checked and timed in onnxruntime (:func:`classifier.export.runtime_checks`), and the report written to
    ``paths[".json"]``, ``[".md"]`` and ``[".png"]`` (:func:`classifier.report.write_report`; NaN and inf as
    null, :func:`classifier.report.finite`). The files are written in place (``doct-train`` stages them
    and checks overwriting first). Returns the result, its report as written (with ``total_s``, the
    seconds of the whole run)."""
    from .export import build_metadata, export_onnx, runtime_checks
    from .report import finite, write_report

    t0 = time.perf_counter()
    res = train(config, prior=prior, cache_dir=cache_dir, use_cache=use_cache, progress=progress, log=log, spec=spec)
    export_onnx(res.model, build_metadata(res), paths[".onnx"])
    runtime_checks(res, paths[".onnx"])
    res.report["total_s"] = time.perf_counter() - t0
    res.report = finite(res.report)
    write_report(res.report, paths[".json"], paths[".md"], paths[".png"])
    return res

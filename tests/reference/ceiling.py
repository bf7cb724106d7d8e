"""The accuracy ceiling of the signature features on independent data: the strongest practical
classifier trained on data drawn from the independent prior itself, tested on the same independent
set as :mod:`evaluate_models`.

Run (from the repository root; resumable, see *Cost*)::

    python -m tests.reference.ceiling --out DIR [--parts a,b,c] [--sizes 150,300,600,1200] [--budget-seconds 480]

Writes ``<out>/independent-ceiling.json`` and ``.md`` (never over existing files without ``--force``)
and prints a summary. Kept whole: one research command whose data, fits, scores and report are read top
to bottom, and whose functions the fast tests call one by one.

**What it measures.** The shipped models are trained on the training prior
(:class:`classifier.prior.Prior`) and tested by :mod:`evaluate_models` on another prior and another
simulator. A model trained on draws of the *test* prior (a matched prior: optimistic) bounds what the
features can give on that data; where it stays below a goal, the gap is the features' (what the
configurations and estimators measure), and where it lies above the shipped model, the gap is the
shipped model's and its training prior's.

**Data.** Test set: draws ``0..N−1`` of :func:`evaluate_models.draw_independent` with seed
``--test-seed`` (0: the set of the ``*-independent.md`` reports), simulated by
:func:`evaluate_models.draw_features` (the reference simulator, every configuration of the spec seeing
the same scatterers; features by ``torchdoct.sim.signature``), ground truth by
:func:`classifier.truth.identifiability` under :func:`evaluate_models.independent_prior` with the
shipped model's ε. Training sets: draws ``0..M−1`` of the same prior with seed ``--train-seed`` (1),
so every training draw has its own parameters and simulator seed (disjoint from the test draws;
the sizes are nested prefixes of one sequence), simulated

* by the reference simulator (parts **a**, **b**), or
* by torchdoct (:func:`classifier.simulation.simulate_draw`, the training data's simulator at the shipped
  recipe's truncation, taper), the same draws as a :class:`classifier.prior.Draw`
  (:func:`evaluate_models.dataset_draw`) under :func:`evaluate_models.independent_prior` (part **c**):
  the same prior exactly, only the simulator differs from the test set's.

Parts (:data:`PARTS`): **a** the ``signature`` spec (volume; its 36 intensity features: ``rho_lin`` at
10 lags, ``lin_contrast``, ``db_variance`` at 3 configurations); **b** ``signature-bscan-field``
(B-scan geometry; the intensity features and the field group ``g1`` at 6 lags, phase-stable data: the
reference simulator has no bulk phase), with **b-int** its intensity columns alone (the features of
``signature-bscan``, same data: what the field group adds); **c** part a's classifier trained on
torchdoct data (a − c = the simulator gap; c − shipped = the model's and its training prior's gap);
**a-shared**, **b-shared** parts a and b trained on the ``"shared"`` prior (:func:`draw_for`: one speed
range for random-ballistic motion and flow, as in the shipped models' training prior), which takes from
the ceiling what the independent prior's per-type speed ranges give away (a flow faster than 0.5 µm/s
cannot be random-ballistic motion there); **d**, **e** part c's classifier trained on torchdoct draws of
the models' own kind of training prior instead of the independent one (:data:`DATASET_PRIORS`,
:func:`dataset_set`: :func:`classifier.dataset.make_dataset`, the same number of draws, one (static
fraction, SNR) setting each): **d** the prior the shipped ``signature`` model was trained on, **e** that
prior scaled to the system (:func:`classifier.own_system.prior_for_spec`); c − d is the training prior's
gap, e − d what the physics-scaled prior recovers of it (:data:`PAIRS`); **f** the same for the B-scan
models: ``signature-bscan-field``'s features trained on torchdoct draws of that recipe's own prior
(``"recipe"``: :func:`classifier.recipe.default_prior`), **f-int** its intensity columns (the features of
``signature-bscan``): the honest-prior ceiling of the shipped B-scan models. Their training draws include
the prior's static and decorrelated ones, which the classifier (three classes) leaves out like every
non-identifiable pixel.

**Classifier.** ``sklearn.ensemble.HistGradientBoostingClassifier`` (:data:`GB_PARAMS`) on the raw
features (trees are invariant to monotone transforms of a feature) and, as a second variant, with the
cross-configuration and cross-lag contrasts of the log decorrelation added (:func:`derived_features`;
+0.009 to +0.018 per pixel, paired), three classes (no indeterminate class: every draw of
this prior is identifiable), on the identifiable training pixels, one thread, fixed ``random_state``;
one classifier per pool: pool 1 on single pixels, pool 25 on means of 25 of a draw's pixels
(:data:`TRAIN_POOLED_PER_DRAW` random subsets per training draw; the test pools are
:mod:`evaluate_models`' own: 8 subsets per draw, :func:`classifier.train.pooled_samples`, the same
generator seed).

**Metrics.** Decisions by the top-class probability above a threshold chosen so that a fraction ``q``
of the identifiable pixels is decided (:func:`coverage_threshold`; ``q`` in :data:`COVERAGES`), and by
the shipped rule (``max p ≥ 0.5``); at each: :func:`classifier.report.evaluate` (balanced accuracy
over the decided identifiable pixels, per-class recall) and :func:`classifier.report.flow_recall_by_band`
(flow recall by polar band 0-30°/30-60°/60-90° and by speed decade). The shipped model of each part
(:data:`SHIPPED`) is scored on the same test pixels by the same thresholds (paired). ± = bootstrap
SE over test draws (:func:`evaluate_models._bootstrap`, threshold held fixed); differences between
two classifiers on the same pixels with a paired bootstrap (:func:`paired_comparisons`).

**Cost**: the reference simulator's draws dominate (the report records the seconds). Features are cached
per draw under ``<out>/cache`` and a run stops cleanly after ``--budget-seconds`` of simulation (exit
status 3: run it again to resume), so it can be run in chunks; the fits and the report come once every
set is cached. Parts d and e simulate one :func:`classifier.dataset.make_dataset` split per prior (1,200
draws each, not resumable within a split; the budget is checked between them) under
``<out>/cache/make_dataset``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

try:  # run as `python -m tests.reference.ceiling`
    from . import evaluate_models as em
except ImportError:  # imported by the tests (tests/reference on sys.path)
    import evaluate_models as em

__all__ = [
    "PARTS",
    "SHIPPED",
    "COVERAGES",
    "POOLS",
    "TRAIN_POOLED_PER_DRAW",
    "FeatureCache",
    "load_set",
    "pool_samples",
    "subset",
    "fit_gb",
    "coverage_threshold",
    "score",
    "part_columns",
    "run",
    "main",
]

#: part -> (spec, training-data simulator, feature columns: "all" or "intensity").
#: Speed range (µm/s) shared by random-ballistic motion and flow in the ``"shared"`` training prior.
SHARED_SPEED = (0.01, 3.0)
#: Training priors: ``"matched"`` the independent prior itself; ``"shared"`` the same with one log-uniform
#: speed range :data:`SHARED_SPEED` for both speed types (:func:`draw_for`), as the training prior of the
#: shipped models has: then the magnitude alone no longer tells ballistic motion above 0.5 µm/s or flow
#: below 0.2 µm/s apart, only the identifiability does (physics, not the prior's ranges).
TRAIN_PRIORS = ("matched", "shared")
#: part -> (spec, training-data simulator, feature columns: "all" or "intensity", training prior).
PARTS: dict[str, tuple[str, str, str, str]] = {
    "a": ("signature", "refsim", "all", "matched"),
    "b": ("signature-bscan-field", "refsim", "all", "matched"),
    "b-int": ("signature-bscan-field", "refsim", "intensity", "matched"),
    "c": ("signature", "torchdoct", "all", "matched"),
    "a-shared": ("signature", "refsim", "all", "shared"),
    "b-shared": ("signature-bscan-field", "refsim", "all", "shared"),
    "d": ("signature", "torchdoct", "all", "training"),
    "e": ("signature", "torchdoct", "all", "scaled"),
    "e-noise": ("signature", "torchdoct", "all", "scaled-noise"),
    "e-nostatic": ("signature", "torchdoct", "all", "scaled-nostatic"),
    "e-nostatic-noise": ("signature", "torchdoct", "all", "scaled-nostatic-noise"),
    "f": ("signature-bscan-field", "torchdoct", "all", "recipe"),
    "f-int": ("signature-bscan-field", "torchdoct", "intensity", "recipe"),
}
#: The shipped model each part is compared with (scored on the same test pixels).
SHIPPED = {
    "a": "signature",
    "b": "signature-bscan-field",
    "b-int": "signature-bscan",
    "c": "signature",
    "a-shared": "signature",
    "b-shared": "signature-bscan-field",
    "d": "signature",
    "e": "signature",
    "e-noise": "signature",
    "e-nostatic": "signature",
    "e-nostatic-noise": "signature",
    "f": "signature-bscan-field",
    "f-int": "signature-bscan",
}
PART_TEXT = {
    "a": "signature features (volume), trained on reference-simulator draws of the independent prior",
    "b": "signature-bscan-field features (B-scan, intensity + field group g1, phase-stable), reference-simulator "
    "draws of the independent prior",
    "b-int": "the intensity columns of b alone (the signature-bscan features), same data",
    "c": "signature features (volume), trained on torchdoct (taper) draws of the independent prior, tested on the "
    "reference simulator",
    "a-shared": "part a with one speed range 0.01-3 µm/s for random-ballistic motion and flow in training (the "
    "prior's per-type speed ranges no longer help)",
    "b-shared": "part b with one speed range 0.01-3 µm/s for random-ballistic motion and flow in training",
    "d": "part c's classifier trained on torchdoct draws of the shipped signature recipe's training prior "
    "(classifier.prior.Prior, flow polar angle uniform; make_dataset, one nuisance replicate per draw)",
    "e": "part d with the training prior scaled to the system (classifier.own_system.prior_for_spec of d's prior: "
    "each motion type's identifiable range ± half a decade, speeds capped at what the simulator holds)",
    "e-noise": "part e with detection noise in every training draw (SNR U[10, 40] dB; e: in half of them)",
    "e-nostatic": "part e without static scatterers in any training draw (e: a static fraction U[0, 0.8] in half "
    "of them); the independent prior has none: what the static nuisance of training costs there",
    "e-nostatic-noise": "part e with both changes: noise in every draw and no static scatterers",
    "f": "signature-bscan-field features (B-scan, intensity + field group g1), trained on torchdoct draws of the "
    "shipped signature-bscan-field recipe's own training prior (classifier.recipe.default_prior: scaled to the "
    "system, noise in every draw, a residual bulk phase step U[0, 0.05] rad; one nuisance replicate per draw)",
    "f-int": "the intensity columns of f alone (signature-bscan's features; the residual bulk phase does not touch "
    "them), same data",
}
#: Training priors of parts d and e, in the form of the models' own training data
#: (:class:`classifier.prior.Prior`, simulated by :func:`classifier.dataset.make_dataset`): ``"training"``
#: the prior the shipped ``signature`` model was trained on, ``"scaled"`` the same scaled to the spec's
#: system (:func:`classifier.own_system.prior_for_spec`). Each draw's pixels share one (static fraction, SNR)
#: setting of the prior (one replicate), so a training draw holds as many pixels as in the other parts.
DATASET_PRIORS = ("training", "scaled", "scaled-noise", "scaled-nostatic", "scaled-nostatic-noise", "recipe")
#: Fractions of the identifiable test pixels decided (accuracy-coverage curve).
COVERAGES = (0.7, 0.8, 0.9, 1.0)
POOLS = (1, 25)
TRAIN_POOLED_PER_DRAW = 16
DEFAULT_SIZES = (150, 300, 600, 1200)
DEFAULT_TEST_DRAWS = em.DEFAULT_DRAWS
N_BOOT = 200
#: Classifier inputs: the raw features, or with :func:`derived_features` (the ceiling is the better one).
VARIANTS = ("raw", "derived")
VARIANT_TEXT = {"raw": "GB", "derived": "GB + contrasts"}
GB_PARAMS = {
    "max_iter": 400,
    "learning_rate": 0.1,
    "max_leaf_nodes": 31,
    "min_samples_leaf": 40,
    "l2_regularization": 1.0,
    "early_stopping": True,
    "validation_fraction": 0.15,
    "n_iter_no_change": 20,
}
_CLASSES = ("diffusion", "ballistic", "flow")
_CLASS_NAMES = (*_CLASSES, "indeterminate")
EXIT_INCOMPLETE = 3


# ------------------------------------------------------------------------------------------------
# simulated features, cached per draw


def _truncation(spec_name: str) -> tuple[float, str]:
    from classifier.train import TrainConfig

    cfg = TrainConfig.for_spec(spec_name)
    return float(cfg.truncation_tolerance), str(cfg.truncation)


def simulate_features(spec, d: em.IndependentDraw, trials: int, source: str, epsilon: float) -> np.ndarray:
    """Features ``[trials, F]`` (float32, the spec's order) of one independent draw by ``source``:
    ``"refsim"`` (:func:`evaluate_models.draw_features`) or ``"torchdoct"``
    (:func:`classifier.simulation.simulate_draw` at the shipped recipe's truncation; empty-volume pixels
    as NaN rows, dropped like non-finite ones)."""
    if source == "refsim":
        return em.draw_features(spec, d, trials)
    if source != "torchdoct":
        raise ValueError(f"unknown source {source!r} (refsim or torchdoct)")
    from classifier.simulation import simulate_draw

    tol, mode = _truncation(spec.name)
    x, zero = simulate_draw(
        spec,
        em.dataset_draw(d),
        em.independent_prior(epsilon),
        trials=trials,
        truncation_tolerance=tol,
        truncation=mode,
    )[:2]
    x = x[0].astype(np.float32)
    x[zero[0]] = np.nan
    return x


def draw_for(prior: str, seed: int, k: int) -> em.IndependentDraw:
    """Draw ``k`` of seed ``seed`` of a training prior (:data:`TRAIN_PRIORS`): ``"matched"`` is
    :func:`evaluate_models.draw_independent`; ``"shared"`` the same draw with a random-ballistic or flow
    speed moved to the same quantile of the log-uniform :data:`SHARED_SPEED` (every other parameter and
    the simulator seed unchanged)."""
    if prior not in TRAIN_PRIORS:
        raise ValueError(f"unknown training prior {prior!r}; choose among {list(TRAIN_PRIORS)}")
    d = em.draw_independent(seed, k)
    if prior == "matched" or d.label == 0:
        return d
    import dataclasses

    lo, hi = (math.log(v) for v in em.RANGES[d.motion])
    q = (math.log(d.magnitude) - lo) / (hi - lo)
    a, b = (math.log(v) for v in SHARED_SPEED)
    return dataclasses.replace(d, magnitude=float(math.exp(a + q * (b - a))))


class FeatureCache:
    """Per-draw feature files ``<root>/<source>-<spec>[-<prior>]-seed<S>-trials<T>/k<k>.npy`` (atomic
    writes; the prior named unless ``"matched"``)."""

    def __init__(
        self, root: str | os.PathLike, spec, source: str, seed: int, trials: int, epsilon: float, prior: str = "matched"
    ):
        if prior not in TRAIN_PRIORS:
            raise ValueError(f"unknown training prior {prior!r}; choose among {list(TRAIN_PRIORS)}")
        self.spec, self.source, self.seed, self.trials, self.epsilon = spec, source, int(seed), int(trials), epsilon
        self.prior = prior
        tag = "" if prior == "matched" else f"-{prior}"
        self.dir = Path(root) / f"{source}-{spec.name}{tag}-seed{self.seed}-trials{self.trials}"

    def draw(self, k: int) -> em.IndependentDraw:
        return draw_for(self.prior, self.seed, k)

    def path(self, k: int) -> Path:
        return self.dir / f"k{int(k):05d}.npy"

    def missing(self, draws: int) -> list[int]:
        return [k for k in range(draws) if not self.path(k).exists()]

    def fill(self, draws: int, deadline: float | None = None, progress: bool = False) -> bool:
        """Simulate the missing draws ``< draws``; stop after the draw that passes ``deadline``
        (``time.perf_counter()`` value). True when all are cached."""
        todo = self.missing(draws)
        if not todo:
            return True
        self.dir.mkdir(parents=True, exist_ok=True)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(todo), unit="draw", desc=self.dir.name)
        seconds = self.seconds()
        try:
            for k in todo:
                t = time.process_time()
                x = simulate_features(self.spec, self.draw(k), self.trials, self.source, self.epsilon)
                tmp = self.dir / f".k{k:05d}.tmp.npy"
                np.save(tmp, x.astype(np.float32))
                os.replace(tmp, self.path(k))
                seconds[str(k)] = time.process_time() - t
                if bar is not None:
                    bar.update(1)
                if deadline is not None and time.perf_counter() > deadline:
                    break
        finally:
            tmp = self.dir / ".seconds.json.tmp"
            tmp.write_text(json.dumps(seconds), encoding="utf-8")
            os.replace(tmp, self.dir / "seconds.json")
            if bar is not None:
                bar.close()
        return not self.missing(draws)

    def seconds(self) -> dict[str, float]:
        """CPU seconds of each cached draw's simulation (``seconds.json``; {} when absent)."""
        p = self.dir / "seconds.json"
        if not p.exists():
            return {}
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except ValueError:
            return {}
        return {str(k): float(v) for k, v in d.items()} if isinstance(d, dict) else {}

    def load(self, k: int) -> np.ndarray:
        x = np.load(self.path(k), allow_pickle=False)
        if x.ndim != 2 or x.shape != (self.trials, self.spec.n_features):
            raise ValueError(
                f"{self.path(k)}: features of shape {x.shape}, expected "
                f"({self.trials}, {self.spec.n_features}); delete it to simulate it again"
            )
        return x


def load_set(cache: FeatureCache, draws: int, *, features: np.ndarray | None = None):
    """The draws ``0..draws−1`` of a cache as a :class:`classifier.dataset.Dataset` (ground truth as in
    :func:`evaluate_models.evaluate_model`; non-finite rows dropped). ``features``: an already
    simulated ``[draws, trials, F]`` array instead of the cache files (the tests)."""
    from classifier.dataset import Dataset
    from classifier.truth import STATUS, identifiability

    prior = em.independent_prior(cache.epsilon)
    cols: dict[str, list] = {k: [] for k in ("x", "y", "draw", "status", "magnitude", "snr_db", "polar_angle_deg")}
    for k in range(draws):
        d = cache.draw(k)
        status, _, _ = identifiability(cache.spec, em.dataset_draw(d), prior)
        x = cache.load(k) if features is None else np.asarray(features[k], np.float32)
        x = x[np.all(np.isfinite(x), axis=1)]
        n = len(x)
        cols["x"].append(x)
        cols["y"].append(np.full(n, d.label, np.int64))
        cols["draw"].append(np.full(n, k, np.int64))
        cols["status"].append(np.full(n, STATUS.index(status), np.int64))
        cols["magnitude"].append(np.full(n, d.magnitude))
        cols["snr_db"].append(np.full(n, d.snr_db))
        cols["polar_angle_deg"].append(np.full(n, d.polar_angle_deg if d.label == 2 else math.nan))
    a = {k: np.concatenate(v) for k, v in cols.items()}
    return Dataset(
        x=a["x"].reshape(-1, cache.spec.n_features),
        y=a["y"],
        draw=a["draw"],
        group=a["draw"],
        status=a["status"],
        magnitude=a["magnitude"],
        density=np.full(a["y"].shape, em.DENSITY),
        static_fraction=np.zeros(a["y"].shape),
        snr_db=a["snr_db"],
        polar_angle_deg=a["polar_angle_deg"],
    )


def dataset_prior(name: str, spec, epsilon: float):
    """The :class:`classifier.prior.Prior` of :data:`DATASET_PRIORS` ``name`` for ``spec``, with the
    shipped model's ε: ``"training"`` is ``Prior(flow_polar_law="uniform-angle")`` (the shipped
    ``signature`` recipe's prior: D in [1e-4, 15] µm²/s, one speed range [1e-3, 6] µm/s for random-ballistic
    motion and flow), ``"scaled"`` :func:`classifier.own_system.prior_for_spec` of it; ``"-noise"``: detection
    noise in every draw (``noise_probability = 1``), ``"-nostatic"``: no static scatterers
    (``static_probability = 0``); ``"recipe"``: the prior the spec's shipped recipe trains on
    (:func:`classifier.recipe.default_prior` of ``TrainConfig.for_spec(spec)``)."""
    import dataclasses

    from classifier.own_system import prior_for_spec
    from classifier.prior import Prior

    if name not in DATASET_PRIORS:
        raise ValueError(f"unknown dataset prior {name!r}; choose among {list(DATASET_PRIORS)}")
    if name == "recipe":
        from classifier.recipe import default_prior
        from classifier.train import TrainConfig

        return dataclasses.replace(
            default_prior(TrainConfig.for_spec(spec.name)), identifiability_epsilon=float(epsilon)
        )
    prior = Prior(flow_polar_law="uniform-angle", identifiability_epsilon=float(epsilon))
    if name.startswith("scaled"):
        prior = prior_for_spec(spec, prior)[0]
    if "noise" in name.split("-"):  # detection noise in every draw (SNR range unchanged)
        prior = dataclasses.replace(prior, noise_probability=1.0)
    if "nostatic" in name.split("-"):  # no static scatterers in any draw
        prior = dataclasses.replace(prior, static_probability=0.0)
    return dataclasses.replace(prior, identifiability_epsilon=float(epsilon))


def dataset_set(
    out: Path,
    spec,
    name: str,
    seed: int,
    draws: int,
    trials: int,
    epsilon: float,
    *,
    simulate: bool = True,
    progress: bool = False,
):
    """The training split of parts d and e: :func:`classifier.dataset.make_dataset` of
    :func:`dataset_prior` ``name`` (split ``"train"`` of ``seed``, ``draws`` draws, ``trials`` trials, one
    replicate, the shipped recipe's truncation), cached under ``<out>/cache/make_dataset`` (any
    ``doct-train --cache`` directory reuses it). ``simulate=False``: None when it is not cached yet."""
    from classifier.dataset import dataset_key, make_dataset

    prior = dataset_prior(name, spec, epsilon)
    tol, mode = _truncation(spec.name)
    cdir = Path(out) / "cache" / "make_dataset"
    if not simulate:
        key, _ = dataset_key(spec, prior, seed, "train", draws, trials, 1, tol, False, mode)
        if not (cdir / f"{spec.name}-train-{key[:16]}.npz").exists():
            return None
    return make_dataset(
        spec,
        prior,
        seed=int(seed),
        split="train",
        draws=int(draws),
        trials_per_draw=int(trials),
        replicates=1,
        truncation_tolerance=tol,
        truncation=mode,
        cache_dir=cdir,
        progress=progress,
    )


def subset(ds, index: np.ndarray):
    """The rows ``index`` of a :class:`classifier.dataset.Dataset`."""
    from classifier.dataset import Dataset

    return Dataset(**{k: v[index] for k, v in ds.arrays().items()})


def pool_samples(ds, pool: int, seed: int, per_draw: int = em.POOLED_PER_DRAW) -> dict[str, np.ndarray]:
    """Samples of ``ds`` at ``pool`` (1: every pixel; ``n > 1``: ``per_draw`` means of ``n`` pixels per
    draw, :func:`classifier.train.pooled_samples` with :mod:`evaluate_models`' generator
    ``SeedSequence(seed, spawn_key=(1, n))``). The pool column is not appended."""
    from classifier.train import pooled_samples

    if pool == 1:
        return {
            "x": ds.x,
            "y": ds.y,
            "status": ds.status,
            "draw": ds.draw,
            "magnitude": ds.magnitude,
            "polar_angle_deg": ds.polar_angle_deg,
        }
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(1, int(pool))))
    s = pooled_samples(ds, [np.full(per_draw, pool) for _ in np.unique(ds.group)], rng)
    s["x"] = s["x"][:, :-1] if s["x"].shape[1] == ds.x.shape[1] + 1 else s["x"]
    return s


def part_columns(spec, which: str) -> np.ndarray:
    """Column indices of ``which`` features of ``spec``: ``"all"`` or ``"intensity"`` (no field feature)."""
    if which == "all":
        return np.arange(spec.n_features)
    if which != "intensity":
        raise ValueError(f"unknown feature group {which!r} (all or intensity)")
    from torchdoct.sim.signature import needs_field

    return np.array([i for i, (m, _) in enumerate(spec.features) if not needs_field(m)])


#: Offset of the log decorrelation ``log(1 − ρ + offset)`` of the derived features.
DERIVED_OFFSET = 1e-4


def derived_features(spec, x: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Cross-configuration and cross-lag contrasts of the correlation columns among ``cols`` (``[N, K]``).

    With ``L_c(m) = log(1 − ρ_c(m) + 10⁻⁴)`` the log decorrelation of a correlation feature (``rho_lin``,
    ``g1``) at lag ``m`` and configuration ``c``: ``L_c(m) − L_0(m)`` for every configuration ``c`` other
    than the first (how a resolution reduction slows the decorrelation: by the transit for flow, hardly for
    random-ballistic motion, docs/physics.md §5.3-5.4) and the slope ``(L_c(m') − L_c(m))/log(m'/m)``
    between consecutive lags (1 for diffusion, 2 for ballistic motion and flow at short lags). Trees
    split on one feature at a time; these are the differences a split on raw features cannot express.
    """
    from torchdoct.sim.signature import parse_feature

    table: dict[tuple[str, str], dict[int, int]] = {}
    configs: list[str] = []
    for i in cols:
        metric, conf = spec.features[int(i)]
        kind, lag = parse_feature(metric)
        if kind in ("rho_lin", "g1") and lag > 0:
            table.setdefault((kind, conf.name), {})[lag] = int(i)
            if conf.name not in configs:
                configs.append(conf.name)
    xx = np.asarray(x, np.float64)

    def L(i: int) -> np.ndarray:
        return np.log(np.clip(1.0 - xx[:, i], 0.0, None) + DERIVED_OFFSET)

    out = []
    for (kind, conf), lags in table.items():
        ms = sorted(lags)
        for a, b in zip(ms[:-1], ms[1:]):
            out.append((L(lags[b]) - L(lags[a])) / math.log(b / a))
        if conf != configs[0] and (kind, configs[0]) in table:
            base = table[(kind, configs[0])]
            out += [L(lags[m]) - L(base[m]) for m in ms if m in base]
    return np.stack(out, axis=1) if out else np.zeros((len(xx), 0))


def design(spec, x: np.ndarray, cols: np.ndarray, derived: bool) -> np.ndarray:
    """The classifier's inputs: the columns ``cols`` of ``x``, and :func:`derived_features` if ``derived``."""
    z = np.asarray(x[:, cols], np.float64)
    return np.concatenate([z, derived_features(spec, x, cols)], axis=1) if derived else z


# ------------------------------------------------------------------------------------------------
# classifier and metrics


def fit_gb(x: np.ndarray, y: np.ndarray, seed: int = 0):
    """``HistGradientBoostingClassifier`` (:data:`GB_PARAMS`, one thread, ``random_state = seed``)."""
    from sklearn.ensemble import HistGradientBoostingClassifier
    from threadpoolctl import threadpool_limits

    if set(np.unique(y)) != {0, 1, 2}:
        raise ValueError("the training pixels must hold every motion type")
    with threadpool_limits(1):
        return HistGradientBoostingClassifier(random_state=int(seed), **GB_PARAMS).fit(x, y)


def predict_gb(model, x: np.ndarray) -> np.ndarray:
    """Probabilities ``[N, 4]``: the three motion types, and an ``indeterminate`` column of 0."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        p = model.predict_proba(x)
    return np.concatenate([p, np.zeros((len(p), 1))], axis=1)


def coverage_threshold(probabilities: np.ndarray, status: np.ndarray, q: float) -> float:
    """The ``min_probability`` that decides the ``round(q·n)`` most confident of the ``n`` identifiable
    samples (``status == 0``) whose top class is not the last (``indeterminate``): 0 when there are no
    more than that (all of them decided; coverage may then stay below ``q``)."""
    if not 0.0 < q <= 1.0:
        raise ValueError(f"coverage must be in (0, 1]; got {q!r}")
    p = np.asarray(probabilities)
    ident = status == 0
    eligible = p.argmax(1) != p.shape[1] - 1
    conf = np.sort(p.max(1)[ident & eligible])[::-1]
    n = int(round(q * int(ident.sum())))
    if n >= conf.size or n == 0:
        return 0.0
    return float(conf[n - 1])


def score(
    probabilities: np.ndarray, s: dict[str, np.ndarray], *, threshold: float, n_boot: int = N_BOOT, seed: int = 0
) -> dict[str, Any]:
    """Metrics of the decisions ``max p ≥ threshold`` (the module docstring) with bootstrap SEs."""
    from classifier.report import evaluate, flow_recall_by_band
    from classifier.rule import make_rule

    rule = make_rule(0.05, min(max(threshold, 0.0), np.nextafter(1.0, 0.0)))
    y, st, dr = s["y"], s["status"], s["draw"]

    def ev(i):
        return evaluate(probabilities[i], y[i], st[i], _CLASS_NAMES, rule)

    def fb(i):
        return flow_recall_by_band(
            probabilities[i], y[i], st[i], s["polar_angle_deg"][i], s["magnitude"][i], _CLASS_NAMES, rule
        )

    allx = np.arange(len(y))
    m, b = ev(allx), fb(allx)
    out = {
        "min_probability": float(threshold),
        "coverage": m["coverage_identifiable"],
        "balanced_accuracy": m["balanced_accuracy_identifiable"],
        "accuracy": m["accuracy_identifiable"],
        "recall": m["recall_identifiable"],
        "flow_polar_bands": {k: v["recall"] for k, v in b["polar_bands"].items()},
        "flow_polar_bands_coverage": {k: v["coverage"] for k, v in b["polar_bands"].items()},
        "flow_polar_bands_as": {k: v["as"] for k, v in b["polar_bands"].items()},
        "flow_speed_decades": {k: v["recall"] for k, v in b["speed_decades"].items()},
    }
    if n_boot >= 2:

        def scalars(i):
            mm, bb = ev(i), fb(i)
            d = {"coverage": mm["coverage_identifiable"], "balanced_accuracy": mm["balanced_accuracy_identifiable"]}
            d.update({f"recall:{c}": v for c, v in mm["recall_identifiable"].items()})
            d.update({f"band:{k}": v["recall"] for k, v in bb["polar_bands"].items()})
            d.update({f"decade:{k}": v["recall"] for k, v in bb["speed_decades"].items()})
            return d

        out["se"] = em._bootstrap(scalars, dr, n_boot, seed)
    return out


def score_curve(
    probabilities: np.ndarray, s: dict[str, np.ndarray], *, n_boot: int, seed: int, rule_threshold: float = 0.5
) -> dict[str, Any]:
    """:func:`score` at every coverage of :data:`COVERAGES` and at the shipped rule's threshold."""
    out = {
        f"coverage {q:g}": score(
            probabilities, s, threshold=coverage_threshold(probabilities, s["status"], q), n_boot=n_boot, seed=seed
        )
        for q in COVERAGES
    }
    out[f"min_probability {rule_threshold:g}"] = score(
        probabilities, s, threshold=rule_threshold, n_boot=n_boot, seed=seed
    )
    return out


# ------------------------------------------------------------------------------------------------
# the run


def _shipped(name: str):
    from classifier.infer import load_model

    return load_model(name, threads=1)


def _shipped_probs(mdl, spec, x: np.ndarray, pool: int) -> np.ndarray:
    """The shipped model's probabilities on features of ``spec`` (its own columns picked by name)."""
    names = list(mdl.spec.feature_names)
    have = list(spec.feature_names)
    missing = [n for n in names if n not in have]
    if missing:
        raise ValueError(f"shipped model {mdl.path.name} reads {missing}, which spec {spec.name} does not hold")
    cols = [have.index(n) for n in names]
    xx = np.concatenate([x[:, cols], np.full((len(x), 1), float(pool), np.float32)], axis=1)
    probs, _, _ = mdl.predict_all(xx, magnitude=False)
    if list(mdl.classes) != list(_CLASS_NAMES):
        raise ValueError(f"shipped model {mdl.path.name}: classes {mdl.classes}, expected {list(_CLASS_NAMES)}")
    return probs.astype(np.float64)


def caches_for(
    out: Path,
    parts: Sequence[str],
    *,
    sizes: Sequence[int],
    test_draws: int,
    trials: int,
    train_seed: int,
    test_seed: int,
    epsilon: float,
) -> list[tuple[FeatureCache, int]]:
    """Every (cache, draws) the parts need, test sets first; one cache per (source, spec, seed)."""
    from classifier.features import load_spec

    need: dict[tuple, tuple[FeatureCache, int]] = {}
    root = out / "cache"
    for p in parts:
        spec_name, source, _, prior = PARTS[p]
        spec = load_spec(spec_name)
        for src, seed, n, pr in (("refsim", test_seed, test_draws, "matched"), (source, train_seed, max(sizes), prior)):
            if pr in DATASET_PRIORS:  # parts d and e: classifier.dataset.make_dataset (dataset_set)
                continue
            key = (src, spec_name, seed, pr)
            c = need.get(key, (FeatureCache(root, spec, src, seed, trials, epsilon, pr), 0))[0]
            need[key] = (c, max(n, need.get(key, (c, 0))[1]))
    return sorted(need.values(), key=lambda cn: (cn[0].seed != test_seed, cn[0].source, cn[0].spec.name, cn[0].prior))


def run(
    out: Path,
    parts: Sequence[str],
    *,
    sizes: Sequence[int],
    test_draws: int,
    trials: int,
    train_seed: int,
    test_seed: int,
    n_boot: int,
    budget_s: float | None,
    progress: bool,
) -> dict[str, Any] | None:
    """Simulate what is missing (within ``budget_s``); when everything is cached, fit and score every
    part and size and return the report (else None)."""
    t0 = time.perf_counter()
    epsilon = float(_shipped(SHIPPED["a"]).rule["epsilon"])
    caches = caches_for(
        out,
        parts,
        sizes=sizes,
        test_draws=test_draws,
        trials=trials,
        train_seed=train_seed,
        test_seed=test_seed,
        epsilon=epsilon,
    )
    deadline = None if budget_s is None else t0 + float(budget_s)
    for c, n in caches:
        if not c.fill(n, deadline, progress):
            return None
    from classifier.features import load_spec

    datasets: dict[str, Any] = {}  # parts d and e: one make_dataset split per prior (not resumable within)
    for p in parts:
        spec_name, _, _, prior = PARTS[p]
        if prior in DATASET_PRIORS and (spec_name, prior) not in datasets:
            ds = dataset_set(out, load_spec(spec_name), prior, train_seed, max(sizes), trials, epsilon, simulate=False)
            if ds is None:
                if deadline is not None and time.perf_counter() > deadline:
                    return None
                ds = dataset_set(
                    out, load_spec(spec_name), prior, train_seed, max(sizes), trials, epsilon, progress=progress
                )
            datasets[(spec_name, prior)] = ds
    sim_s = time.perf_counter() - t0

    results: dict[str, Any] = {}
    kept: dict[tuple[str, str], tuple] = {}  # pool-1 probabilities of the largest training set, for the pairs
    fit_s: dict[str, float] = {}
    for p in parts:
        spec_name, source, which, prior = PARTS[p]
        spec = load_spec(spec_name)
        cols = part_columns(spec, which)
        test = load_set(FeatureCache(out / "cache", spec, "refsim", test_seed, trials, epsilon), test_draws)
        if prior in DATASET_PRIORS:
            train_all = datasets[(spec_name, prior)]
        else:
            train_all = load_set(
                FeatureCache(out / "cache", spec, source, train_seed, trials, epsilon, prior), max(sizes)
            )
        mdl = _shipped(SHIPPED[p])
        res: dict[str, Any] = {
            "spec": spec_name,
            "train_source": source,
            "features": which,
            "train_prior": prior,
            "feature_names": [spec.feature_names[i] for i in cols],
            "shipped": SHIPPED[p],
            "text": PART_TEXT[p],
            "pools": {},
        }
        t1 = time.perf_counter()
        for pool in POOLS:
            ts = pool_samples(test, pool, test_seed)
            r: dict[str, Any] = {"test_samples": int(len(ts["y"])), "by_size": {}}
            sp = _shipped_probs(mdl, spec, ts["x"], pool)
            r["shipped"] = score_curve(sp, ts, n_boot=n_boot, seed=test_seed)
            if pool == 1:
                kept[(p, "shipped")] = (sp, ts, spec_name)
            for n in sorted(sizes):
                keep = (train_all.draw < n) & (train_all.status == 0)
                sub = subset(train_all, np.flatnonzero(keep))
                trs = pool_samples(sub, pool, train_seed, per_draw=TRAIN_POOLED_PER_DRAW)
                r["by_size"][str(n)] = {}
                for variant in VARIANTS:
                    gb = fit_gb(design(spec, trs["x"], cols, variant == "derived"), trs["y"], seed=train_seed)
                    probs = predict_gb(gb, design(spec, ts["x"], cols, variant == "derived"))
                    r["by_size"][str(n)][variant] = {
                        "train_draws": int(n),
                        "train_samples": int(len(trs["y"])),
                        "gb_iterations": int(gb.n_iter_),
                        "inputs": int(gb.n_features_in_),
                        **_curve_for_size(
                            score_curve(probs, ts, n_boot=n_boot if n == max(sizes) else 0, seed=test_seed),
                            n == max(sizes),
                        ),
                    }
                    if pool == 1 and n == max(sizes):
                        kept[(p, variant)] = (probs, ts, spec_name)
            res["pools"][str(pool)] = r
        if prior in DATASET_PRIORS:
            ds = datasets[(spec_name, prior)]
            res["train_prior_fields"] = dataset_prior(prior, spec, epsilon).to_dict()
            res["train_draw_status"] = ds.meta.get("draw_status_counts")
        fit_s[p] = time.perf_counter() - t1
        results[p] = res
    comparisons = paired_comparisons(kept, results, n_boot=n_boot, seed=test_seed)
    import sklearn

    import classifier
    import torchdoct

    return {
        "versions": {
            "classifier": classifier.__version__,
            "torchdoct": torchdoct.__version__,
            "sklearn": sklearn.__version__,
        },
        "command": command_line(parts, sizes, test_draws, trials, train_seed, test_seed, n_boot),
        "test_seed": int(test_seed),
        "train_seed": int(train_seed),
        "test_draws": int(test_draws),
        "train_sizes": [int(n) for n in sorted(sizes)],
        "trials_per_draw": int(trials),
        "pools": list(POOLS),
        "coverages": list(COVERAGES),
        "variants": list(VARIANTS),
        "epsilon": epsilon,
        "gb_params": GB_PARAMS,
        "train_pooled_per_draw": TRAIN_POOLED_PER_DRAW,
        "test_pooled_per_draw": em.POOLED_PER_DRAW,
        "n_boot": int(n_boot),
        "prior": em.PRIOR_TEXT,
        "simulation": em.SIM_TEXT,
        "targets": em.TARGETS,
        "parts": results,
        "comparisons": comparisons,
        "seconds": {
            "this_run_simulation": sim_s,
            "fits_and_scores": fit_s,
            "simulation_per_set": {
                **_cache_seconds(caches),
                **{
                    f"make_dataset-{ds.meta['spec']['name']}-{pr}-prior-seed{train_seed}-trials{trials} "
                    f"(wall, every core)": {
                        "draws": int(max(sizes)),
                        "cpu_seconds": float(ds.meta.get("elapsed_s", math.nan)),
                        "cpu_seconds_per_draw": float(ds.meta.get("seconds_per_draw", math.nan)),
                    }
                    for (_, pr), ds in datasets.items()
                },
            },
        },
    }


#: Decisions kept in the report for the training sets other than the largest (the learning curve).
SMALL_SIZE_KEYS = ("coverage 0.8", "coverage 1")


def _curve_for_size(curve: dict[str, Any], largest: bool) -> dict[str, Any]:
    return curve if largest else {k: curve[k] for k in SMALL_SIZE_KEYS}


def _cache_seconds(caches) -> dict[str, dict[str, float]]:
    """Draws and CPU seconds of the simulation of every cached set (over the runs that filled it)."""
    out = {}
    for c, n in caches:
        sec = c.seconds()
        v = [sec[str(k)] for k in range(n) if str(k) in sec]
        out[c.dir.name] = {
            "draws": int(n),
            "cpu_seconds": float(sum(v)),
            "cpu_seconds_per_draw": float(np.mean(v)) if v else math.nan,
        }
    return out


def command_line(parts, sizes, test_draws, trials, train_seed, test_seed, n_boot) -> str:
    return (
        f"python -m tests.reference.ceiling --out DIR --parts {','.join(parts)} --sizes "
        f"{','.join(str(n) for n in sorted(sizes))} --test-draws {test_draws} --trials {trials} "
        f"--train-seed {train_seed} --test-seed {test_seed} --boot {n_boot}"
    )


# ------------------------------------------------------------------------------------------------
# report


def _f(v: Any, d: int = 3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{d}f}"


def _pm(r: dict[str, Any], key: str, se_key: str | None = None) -> str:
    v = r
    for k in key.split("/"):
        v = v.get(k, {}) if isinstance(v, dict) else None
    se = r.get("se", {}).get(se_key or key)
    return _f(v) if se is None or not math.isfinite(se) else f"{_f(v)} ± {se:.3f}"


def _row(label: str, r: dict[str, Any]) -> str:
    bands = " / ".join(_pm(r, f"flow_polar_bands/{b}", f"band:{b}") for b in ("0-30", "30-60", "60-90"))
    rec = " / ".join(_pm(r, f"recall/{c}", f"recall:{c}") for c in _CLASSES)
    return f"| {label} | {_f(r['coverage'])} | {_pm(r, 'balanced_accuracy')} | {rec} | {bands} |"


def _dec(r: dict[str, Any]) -> str:
    return " / ".join(f"{k} µm/s {_pm(r, f'flow_speed_decades/{k}', f'decade:{k}')}" for k in r["flow_speed_decades"])


def format_markdown(rep: dict[str, Any]) -> str:
    cmd = rep["command"]
    big = str(max(rep["train_sizes"]))
    keys = [f"coverage {q:g}" for q in rep["coverages"]] + ["min_probability 0.5"]
    L = [
        "# The ceiling of the signature features on independent data",
        "",
        f"Test set: {rep['test_draws']} draws × {rep['trials_per_draw']} pixels of the independent prior, seed "
        f"{rep['test_seed']} (the set of the `*-independent.md` reports), {rep['simulation']}. Training sets: the "
        f"first {', '.join(str(n) for n in rep['train_sizes'])} draws of the same prior with seed {rep['train_seed']} "
        f"(disjoint draws: their own parameters and simulator seeds). Prior: {rep['prior']}.",
        "",
        "Classifier: HistGradientBoosting ("
        + ", ".join(f"{k}={v}" for k, v in rep["gb_params"].items())
        + "; one thread), three classes, one classifier per pool (pool 25: "
        f"{rep['train_pooled_per_draw']} means of 25 pixels per training draw; test pools as evaluate_models: "
        f"{rep['test_pooled_per_draw']} per draw), on the raw features (**GB**) or with the cross-configuration "
        "and cross-lag contrasts of the log decorrelation added (**GB + contrasts**, `ceiling.derived_features`). "
        "A matched prior: an optimistic ceiling. Decisions: the top class where its probability passes the "
        "threshold that decides the stated share of the identifiable test pixels (coverage), or 0.5 (the shipped "
        "rule). The shipped model of each part is scored on the same test pixels at the same coverages (paired). "
        f"± = bootstrap SE over test draws ({rep['n_boot']} resamples; the largest training set and the shipped "
        "models).",
        "",
        f"Every number below comes from one command: `{cmd}` (DIR: any directory; the simulated features are "
        "cached there per draw and a run resumes; `--budget-seconds S` stops after S s of simulation with exit "
        "status 3, to run it in chunks).",
        "",
        "## Pool 1 at coverage 0.80 (goal: balanced accuracy ≥ 0.88 at coverage ≥ 0.80, flow recall ≥ 0.80 in "
        "every polar band)",
        "",
        "| part | model | coverage | bal. acc. | recall diffusion / ballistic / flow | flow recall 0-30° / 30-60° / "
        "60-90° |",
        "|---|---|---:|---:|---|---|",
    ]
    for p, res in rep["parts"].items():
        r1 = res["pools"]["1"]
        for v in rep["variants"]:
            L.append(_row(f"{p} | {VARIANT_TEXT[v]}, {big} draws", r1["by_size"][big][v]["coverage 0.8"]))
        L.append(_row(f"{p} | shipped `{res['shipped']}`", r1["shipped"]["coverage 0.8"]))
    L += [
        "",
        "Parts: " + "; ".join(f"**{p}** {res['text']}" for p, res in rep["parts"].items()) + ".",
        "",
        f"Reproduce: `{cmd}`.",
        "",
    ]
    L += findings(rep)
    L += [
        "",
        "## Against training size (pool 1; balanced accuracy at coverage 0.8 and 1.0, flow recall by polar band "
        "at coverage 0.8)",
        "",
        "| part | inputs | training draws | bal. acc. at 0.8 | bal. acc. at 1.0 | flow 0-30° / 30-60° / 60-90° |",
        "|---|---|---:|---:|---:|---|",
    ]
    for p, res in rep["parts"].items():
        for v in rep["variants"]:
            for n, rn in res["pools"]["1"]["by_size"].items():
                c8, c1 = rn[v]["coverage 0.8"], rn[v]["coverage 1"]
                L.append(
                    f"| {p} | {VARIANT_TEXT[v]} | {n} | {_pm(c8, 'balanced_accuracy')} | "
                    f"{_pm(c1, 'balanced_accuracy')} | "
                    + " / ".join(_f(c8["flow_polar_bands"].get(b)) for b in ("0-30", "30-60", "60-90"))
                    + " |"
                )
    L += ["", f"Reproduce: `{cmd}`."]
    for p, res in rep["parts"].items():
        L += [
            "",
            f"## Part {p}: {res['text']}",
            "",
            f"Spec `{res['spec']}`, {len(res['feature_names'])} features "
            f"({res['features']}), training simulator {res['train_source']}, training prior {res['train_prior']}; "
            f"compared with `{res['shipped']}`.",
            "",
        ]
        for pool, r in res["pools"].items():
            L += [
                f"### Pool {pool} ({r['test_samples']} test samples; classifiers trained on {big} draws)",
                "",
                "| model | decision | coverage | bal. acc. | recall diffusion / ballistic / flow | flow recall "
                "0-30° / 30-60° / 60-90° |",
                "|---|---|---:|---:|---|---|",
            ]
            for v in rep["variants"]:
                for key in keys:
                    L.append(_row(f"{VARIANT_TEXT[v]} | {key}", r["by_size"][big][v][key]))
            for key in keys:
                L.append(_row(f"shipped `{res['shipped']}` | {key}", r["shipped"][key]))
            L += [
                "",
                "Flow recall by speed decade at coverage 0.8: "
                + "; ".join(f"{VARIANT_TEXT[v]} {_dec(r['by_size'][big][v]['coverage 0.8'])}" for v in rep["variants"])
                + f"; shipped {_dec(r['shipped']['coverage 0.8'])}.",
                "",
                f"Reproduce: `{cmd}`.",
                "",
            ]
    s = rep["seconds"]
    L += [
        "Cost (CPU, one core): simulation "
        + ", ".join(
            f"{k} {v['draws']} draws {v['cpu_seconds']:.0f} s ({v['cpu_seconds_per_draw']:.2f} s per draw)"
            for k, v in s["simulation_per_set"].items()
        )
        + "; fits and scores (wall) "
        + ", ".join(f"{p} {v:.0f} s" for p, v in s["fits_and_scores"].items())
        + ".",
        "",
    ]
    return "\n".join(L)


def _best(
    res: dict[str, Any], size: str, variants: Sequence[str], pool: str = "1", key: str = "coverage 0.8"
) -> tuple[str, dict[str, Any]]:
    """The variant with the highest balanced accuracy at ``key`` and its scores."""
    rows = {v: res["pools"][pool]["by_size"][size][v][key] for v in variants}
    v = max(rows, key=lambda k: rows[k]["balanced_accuracy"])
    return v, rows[v]


def findings(rep: dict[str, Any]) -> list[str]:
    """What the numbers say (computed from them, pool 1 at coverage 0.8, the largest training set)."""
    big = str(max(rep["train_sizes"]))
    goal = rep["targets"]["pool_1"]["balanced_accuracy_identifiable"]
    band_goal = rep["targets"]["flow_recall_every_polar_band"]
    parts = rep["parts"]
    L = ["## What it shows (pool 1, coverage 0.80, the better inputs, " + big + " training draws)", ""]
    best = {p: _best(res, big, rep["variants"]) for p, res in parts.items()}
    for p, (v, r) in best.items():
        sh = parts[p]["pools"]["1"]["shipped"]["coverage 0.8"]
        bands = r["flow_polar_bands"]
        low = min(bands.values())
        L.append(
            f"- **{p}** ({VARIANT_TEXT[v]}): {_pm(r, 'balanced_accuracy')} against the goal {goal:g} "
            f"({'above' if r['balanced_accuracy'] >= goal else 'below'}); flow recall "
            + " / ".join(_f(bands[b]) for b in ("0-30", "30-60", "60-90"))
            + f" ({'every band' if low >= band_goal else 'not every band'} ≥ {band_goal:g}); shipped "
            f"`{parts[p]['shipped']}` {_pm(sh, 'balanced_accuracy')} at the same coverage: ceiling − shipped "
            f"= {r['balanced_accuracy'] - sh['balanced_accuracy']:+.3f}."
        )
    L += [
        "",
        "Paired differences of the balanced accuracy at coverage 0.8 (same test pixels; ± paired bootstrap "
        "SE over test draws):",
        "",
    ]
    for c in rep.get("comparisons", []):
        se = c.get("se")
        L.append(
            f"- {c['what']}: {c['x']} − {c['y']} = {c['difference']:+.3f}"
            + (f" ± {se:.3f}" if se is not None and math.isfinite(se) else "")
            + "."
        )
    L += ["", "Against training size (the better inputs):", ""]
    for p, res in parts.items():
        n = [str(k) for k in rep["train_sizes"]]
        if len(n) >= 2:
            v = best[p][0]
            a = res["pools"]["1"]["by_size"][n[-2]][v]["coverage 0.8"]["balanced_accuracy"]
            b = res["pools"]["1"]["by_size"][n[-1]][v]["coverage 0.8"]["balanced_accuracy"]
            grows = "still growing: the ceiling measured is a lower bound" if b - a > 0.005 else "nearly flat"
            L.append(f"- {p}: {n[-2]} → {n[-1]} training draws {b - a:+.3f} ({grows}).")
    return L


#: Paired differences reported (pool 1, coverage 0.8; each part at its better inputs): (x, y, what).
PAIRS = (
    ("a", "c", "simulator gap: trained on the reference simulator − trained on torchdoct (same prior, same test)"),
    ("a", "a-shared", "what the matched prior's per-type speed ranges give (matched − shared speed range)"),
    ("b", "b-shared", "the same on B-scans with the field group (matched − shared)"),
    ("b", "b-int", "the field group on phase-stable B-scans (intensity + g1 − intensity alone)"),
    ("e", "d", "training prior: scaled to the system − the shipped recipe's (same simulator, draws, classifier)"),
    ("c", "e", "what the scaled prior leaves to the matched one (independent prior − scaled prior)"),
    ("c", "d", "prior gap of the shipped recipe (independent prior − the shipped recipe's prior)"),
)


def paired_difference(a: tuple, b: tuple, n_boot: int, seed: int) -> dict[str, float]:
    """Balanced accuracy at coverage 0.8 of ``a`` minus ``b`` (each ``(probabilities, samples)`` of the same
    test samples, each at its own coverage-0.8 threshold) with its paired bootstrap SE over test draws."""
    from classifier.report import evaluate
    from classifier.rule import make_rule

    (pa, s), (pb, sb) = a[:2], b[:2]
    if not np.array_equal(s["draw"], sb["draw"]) or not np.array_equal(s["y"], sb["y"]):
        raise ValueError("paired differences need the same test samples")
    ra = make_rule(0.05, coverage_threshold(pa, s["status"], 0.8))
    rb = make_rule(0.05, coverage_threshold(pb, s["status"], 0.8))

    def d(i):
        x = evaluate(pa[i], s["y"][i], s["status"][i], _CLASS_NAMES, ra)["balanced_accuracy_identifiable"]
        y = evaluate(pb[i], s["y"][i], s["status"][i], _CLASS_NAMES, rb)["balanced_accuracy_identifiable"]
        return {"difference": x - y}

    out = {"difference": d(np.arange(len(s["y"])))["difference"]}
    if n_boot >= 2:
        out["se"] = em._bootstrap(d, s["draw"], n_boot, seed).get("difference", math.nan)
    return out


def paired_comparisons(kept: dict, results: dict, *, n_boot: int, seed: int) -> list[dict[str, Any]]:
    """The :data:`PAIRS` present, and every part's ceiling against its shipped model, as paired differences."""
    out = []

    def better(p):
        rows = dict.fromkeys(VARIANTS, results[p]["pools"]["1"]["by_size"])
        big = max(rows["raw"], key=int)
        return max(
            VARIANTS, key=lambda v: results[p]["pools"]["1"]["by_size"][big][v]["coverage 0.8"]["balanced_accuracy"]
        )

    for p in results:
        v = better(p)
        out.append(
            {
                "x": f"{p} ({VARIANT_TEXT[v]})",
                "y": f"shipped {results[p]['shipped']}",
                "what": f"ceiling − shipped model, part {p}",
                **paired_difference(kept[(p, v)], kept[(p, "shipped")], n_boot, seed),
            }
        )
    for x, y, what in PAIRS:
        if x in results and y in results:
            vx, vy = better(x), better(y)
            out.append(
                {
                    "x": f"{x} ({VARIANT_TEXT[vx]})",
                    "y": f"{y} ({VARIANT_TEXT[vy]})",
                    "what": what,
                    **paired_difference(kept[(x, vx)], kept[(y, vy)], n_boot, seed),
                }
            )
    for p in results:  # what the contrasts add
        out.append(
            {
                "x": f"{p} (GB + contrasts)",
                "y": f"{p} (GB)",
                "what": f"the contrasts, part {p}",
                **paired_difference(kept[(p, "derived")], kept[(p, "raw")], n_boot, seed),
            }
        )
    return out


def _summary(rep: dict[str, Any]) -> str:
    n = str(max(rep["train_sizes"]))
    lines = []
    for p, res in rep["parts"].items():
        for pool in ("1", "25"):
            r = res["pools"][pool]
            for who, rr in [(f"{VARIANT_TEXT[v]} {n}", r["by_size"][n][v]) for v in rep["variants"]] + [
                (f"shipped {res['shipped']}", r["shipped"])
            ]:
                c = rr["coverage 0.8"]
                lines.append(
                    f"{p} pool {pool} {who}: bal. acc. {_f(c['balanced_accuracy'])} at {_f(c['coverage'])}; "
                    f"flow bands "
                    + " / ".join(_f(v) for v in c["flow_polar_bands"].values())
                    + f"; coverage 1.0: {_f(rr['coverage 1']['balanced_accuracy'])}"
                )
    return "\n".join(lines)


def _rounded(obj: Any, digits: int = 5) -> Any:
    """``obj`` with every float rounded to ``digits`` decimals (the JSON report; the Markdown shows 3)."""
    if isinstance(obj, float):
        return round(obj, digits) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rounded(v, digits) for v in obj]
    return obj


def write_report(rep: dict[str, Any], out: Path, force: bool = False) -> list[Path]:
    return write_files(rep, out, "independent-ceiling", format_markdown(rep), force)


def write_files(rep: dict[str, Any], out: Path, stem: str, markdown: str, force: bool = False) -> list[Path]:
    """``<out>/<stem>.json`` (``rep``, rounded) and ``.md`` (``markdown``), atomically; never over existing
    files without ``force``."""
    paths = [out / f"{stem}{s}" for s in (".json", ".md")]
    if not force:
        for p in paths:
            if p.exists():
                raise FileExistsError(f"{p} exists; pass --force to overwrite it, or choose another --out")
    text_json = json.dumps(_rounded(json.loads(json.dumps(rep, default=em._json_default))), separators=(",", ":"))
    for p, text in zip(paths, (text_json, markdown)):
        tmp = p.with_name(f".{p.name}.tmp")
        tmp.write_text(text + "\n", encoding="utf-8")
        os.replace(tmp, p)
    return paths


def _ints(text: str, what: str) -> list[int]:
    try:
        v = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise ValueError(f"--{what} must be comma-separated integers; got {text!r}") from None
    if not v or min(v) < 3:
        raise ValueError(f"--{what} must hold integers >= 3 (one draw per motion type); got {text!r}")
    return v


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tests.reference.ceiling",
        description="Ceiling of the signature features on the independent data: gradient "
        "boosting trained on draws of the independent prior. Writes "
        "<out>/independent-ceiling.json and .md.",
    )
    ap.add_argument("--out", required=True, help="output directory (also holds the feature cache, <out>/cache)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"parts among {list(PARTS)} (default all)")
    ap.add_argument("--sizes", default=",".join(str(n) for n in DEFAULT_SIZES), help="training draws (nested)")
    ap.add_argument("--test-draws", type=int, default=DEFAULT_TEST_DRAWS)
    ap.add_argument("--trials", type=int, default=em.DEFAULT_TRIALS)
    ap.add_argument("--train-seed", type=int, default=1)
    ap.add_argument("--test-seed", type=int, default=0)
    ap.add_argument("--boot", type=int, default=N_BOOT)
    ap.add_argument(
        "--budget-seconds",
        type=float,
        default=None,
        help="stop simulating after this many seconds (exit status 3; run again to resume)",
    )
    ap.add_argument("--force", action="store_true", help="overwrite existing report files")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        parts = [p.strip() for p in args.parts.split(",") if p.strip()]
        bad = [p for p in parts if p not in PARTS]
        if bad or not parts:
            raise ValueError(f"--parts: unknown {bad or 'none given'}; choose among {list(PARTS)}")
        sizes = _ints(args.sizes, "sizes")
        if args.test_draws < 3 or args.trials < 25 or args.boot < 0:
            raise ValueError("--test-draws must be >= 3, --trials >= 25 (pool 25), --boot >= 0")
        if args.train_seed == args.test_seed:
            raise ValueError("--train-seed must differ from --test-seed (training draws disjoint from the test draws)")
        out = Path(args.out)
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out} is a file; give a directory")
        out.mkdir(parents=True, exist_ok=True)
        import torch

        torch.set_num_threads(1)  # one core: the numbers do not depend on it (every draw has its own seeds)
        rep = run(
            out,
            parts,
            sizes=sizes,
            test_draws=args.test_draws,
            trials=args.trials,
            train_seed=args.train_seed,
            test_seed=args.test_seed,
            n_boot=args.boot,
            budget_s=args.budget_seconds,
            progress=not args.no_progress,
        )
        if rep is None:
            print(
                f"simulation budget used; features cached under {out / 'cache'}: run the same command again to resume",
                file=sys.stderr,
            )
            return EXIT_INCOMPLETE
        paths = write_report(rep, out, force=args.force)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(_summary(rep))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())

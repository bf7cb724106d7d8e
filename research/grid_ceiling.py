"""The best decision we could build on the phantom grid's rows whose goal is not met: how much it can decide at the
goal's accuracy and wrong share, beside the default decision on the same pixels.

The goals page (docs/benchmarks/goals.md) bounds the coverage of each grid row by counting the pixels some
statistic could decide (its *ceiling*): every pixel in a volume inside static tissue (a phase reference exists
for rule 11, and the ``y`` neighbours see flow across the B-scan plane), every pixel but random-ballistic motion's
(rule 1) and, without static tissue, flow across the plane's in a B-scan. This script measures what an estimator
that reads what ``doct-classify`` reads reaches instead, per part of :data:`PARTS` (the grid's cells of one
geometry and static context, with the default model of the geometry, :data:`MODELS`):

* the inputs, per pixel at window ``w`` (1 or 5), in three groups (:data:`GROUPS`): ``network``, the default
  network's probabilities pooled over the window (``doct-classify --pool w``, every class); ``speckle``, the box
  means over the window of every speckle channel the maps write (``xc_centre_m``, ``xc_peak_m``, ``xc_shift_m``
  and the signed offsets ``xc_shift_{z,x,y}_m`` at every speckle lag) and of the offsets' magnitudes
  (concepts/speckle-motion.md); ``doppler``, the circular mean of the Doppler phasor ``exp(i·φ)`` over rule 10's
  box (``max(w, 5)`` pixels per axis) and the share of the box that holds a phase (concepts/doppler-reference.md).
  NaN where a channel holds no value (gradient boosting reads NaN as missing);
* the estimators (:data:`ESTIMATORS`): gradient boosting (scikit-learn's ``HistGradientBoostingClassifier``,
  :data:`GB_PARAMS`), three classes, one per window and set of inputs, fitted on one of two training sets,
  both rendered at ``--train-seed`` (other scatterers and noise than the test's):

  - ``grid``: the grid's own cells (its three speed levels and angles): a matched prior, what an estimator that
    knows the test's levels reaches;
  - ``prior``: as many phantoms of the part's geometry and context with every magnitude drawn log-uniformly over
    the range whose 20/50/80 % points are the grid's levels (the range identifiable at every grid direction,
    :func:`classifier.bench.grid.speed_levels`), flow at a polar and an azimuth uniform in [0°, 90°], noise-free
    or at the grid's SNR in equal shares (:func:`prior_cells`): the estimator cannot learn the test's levels;

  and scored on the grid's cells at ``--test-seed`` (the benchmark's seed 0 by default), over the band
  interiors the grid scores;
* the decision: the top class where its probability reaches a threshold, searched over the percentiles 0-99 of
  the top probability (coverage in steps of about a hundredth). *Held out*: the threshold that decides
  the most of the training set's held-out predictions (two folds of its phantoms, each predicted by the
  estimator fitted on the other) while the balanced accuracy on decided pixels and the worst motion's wrong share
  meet the goal's bounds (:data:`GOALS`, the goals page's, per part and window) and no phantom has a motion with
  more than :data:`CELL_WRONG_MAX` of its pixels decided as another (the goals page's bound for every grid
  cell: a decision may not be confidently wrong over a region): what a user could choose.
  *Best*: the one that decides the most test pixels within those bounds, chosen on the test itself: optimistic.
  Both are also given under the goal's bounds alone (``pooled_only``): a single threshold can meet the pooled
  wrong share while it is wrong over most of a few cells, the flows whose evidence the rules say no statistic
  separates.
  One threshold for every class: a decision that abstains on one class only (random-ballistic motion in a
  B-scan) is one where that class's top probability stays low.

The default network's argmax and the default decision of ``doct-classify`` (conformal sets and the rules) are
scored on the same pixels. ± is the standard error over a bootstrap of the test cells (:data:`BOOT` resamples of
the cells: pixels of one cell share their scatterers and are not independent). A flow too slow to decorrelate
within the acquisition (rule 2's creeping flow) lies below both training ranges, as it lies outside the grid's
ground truth of identifiable motions: the ceiling is for the motions the grid scores.

Run from the repository root with a development install::

    python -m research.grid_ceiling --out DIR [--parts P,...] [--train-seed 1] [--test-seed 0] [--cells N]

It caches the inputs of each rendered phantom in ``DIR/cache`` (a run resumes) and writes
``DIR/grid-ceiling.json`` and ``.md`` (the recorded run: ``research/results/grid-ceiling.*``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: the grid rows of the goals page whose goal is not met, as (geometry, static context)
PARTS = {
    "volume-background": ("volume", "background"),
    "bscan-none": ("bscan", "none"),
    "bscan-background": ("bscan", "background"),
}
#: the default model of each geometry (as the grid benchmark's)
MODELS = {"volume": "signature", "bscan": "signature-bscan"}
POOLS = (1, 5)
MOTIONS = ("diffusion", "ballistic", "flow")
#: the goals page's bounds inside static tissue (docs/benchmarks/goals.md), both windows
INSIDE = {"balanced_accuracy": 0.95, "coverage": 0.70, "wrong_share": 0.05}
#: the goals page's bound for every grid cell: no motion with more than this share of its pixels decided as another
CELL_WRONG_MAX = 0.10
#: the goals page's bounds per part and window
GOALS = {
    ("volume-background", 5): INSIDE,
    ("volume-background", 1): INSIDE,
    ("bscan-background", 5): INSIDE,
    ("bscan-background", 1): INSIDE,
    ("bscan-none", 5): {"balanced_accuracy": 0.95, "coverage": 0.60, "wrong_share": 0.05},
    ("bscan-none", 1): {"balanced_accuracy": 0.90, "coverage": 0.50, "wrong_share": 0.10},
}
#: pixels per motion and cell: training rows drawn at random, test rows likewise (every cell weighs the same)
TRAIN_PER_MOTION = 800
TEST_PER_MOTION = 1500
GB_PARAMS = dict(max_iter=300, learning_rate=0.1, max_leaf_nodes=31, min_samples_leaf=40, l2_regularization=1.0)
BOOT = 200
#: the estimators: (inputs, training set) -> the feature-name prefixes they read; ``network``: the default
#: network's probabilities, ``speckle``: the speckle channels, ``doppler``: the Doppler phasor
GROUPS = {"network": ("p_",), "speckle": ("xc_", "abs_xc_"), "doppler": ("doppler_",)}
ESTIMATORS = {
    ("network", "grid"): ("network",),
    ("all", "grid"): ("network", "speckle", "doppler"),
    ("network", "prior"): ("network",),
    ("network + speckle", "prior"): ("network", "speckle"),
    ("network + doppler", "prior"): ("network", "doppler"),
    ("all", "prior"): ("network", "speckle", "doppler"),
}


def _box_sum(values: np.ndarray, width: int) -> np.ndarray:
    """Per pixel: the sum of ``values`` over the box of ``width`` pixels per axis centred on it (cut at the map's
    edges), by differences of cumulative sums along each axis."""
    out = np.asarray(values, np.float64)
    h = width // 2
    for ax in range(out.ndim):
        n = out.shape[ax]
        c = np.concatenate([np.zeros_like(out.take([0], axis=ax)), np.cumsum(out, axis=ax)], axis=ax)
        i = np.arange(n)
        out = c.take(np.minimum(i + h + 1, n), axis=ax) - c.take(np.maximum(i - h, 0), axis=ax)
    return out


def _box_mean(values: np.ndarray, width: int) -> np.ndarray:
    """NaN-aware mean over the box of ``width`` pixels per axis centred on each pixel (cut at the map's edges);
    NaN where the box holds no finite value."""
    ok = np.isfinite(values)
    tot = _box_sum(np.where(ok, values, 0.0), width)
    n = _box_sum(ok.astype(np.float64), width)
    return np.where(n > 0, tot / np.maximum(n, 1), np.nan)


def pixel_features(channels: dict[str, np.ndarray], probs: np.ndarray, classes: Sequence[str], width: int):
    """The inputs of the module docstring at window ``width`` over the whole map: ``(names, [F, *S] float32)``."""
    from classifier.ambiguity import DOPPLER_WINDOW_MIN

    names, cols = [], []
    for k, c in enumerate(classes):
        names.append(f"p_{c}")
        cols.append(np.asarray(probs[k], np.float64))
    for c in sorted(channels):
        if c.startswith(("xc_centre_", "xc_peak_", "xc_shift_")):
            v = np.asarray(channels[c], np.float64)
            names.append(c)
            cols.append(_box_mean(v, width) if width > 1 else v)
            if c.startswith("xc_shift_") and c[9] in "zxy" and c[10] == "_":
                names.append(f"abs_{c}")
                cols.append(_box_mean(np.abs(v), width) if width > 1 else np.abs(v))
    dop = sorted(
        (c for c in channels if c.startswith("doppler_phase_")), key=lambda s: int(s.split("_")[2].split("@")[0])
    )
    box = max(width, DOPPLER_WINDOW_MIN)
    shape = cols[0].shape
    if dop:
        ph = np.asarray(channels[dop[0]], np.float64)
        ok = np.isfinite(ph)
        n_ok = _box_sum(ok.astype(np.float64), box)
        for part in (np.cos, np.sin):
            cols.append(np.where(n_ok > 0, _box_sum(np.where(ok, part(ph), 0.0), box) / np.maximum(n_ok, 1), np.nan))
        cols.append(n_ok / _box_sum(np.ones(ph.shape), box))
    else:
        cols += [np.full(shape, np.nan), np.full(shape, np.nan), np.zeros(shape)]
    names += ["doppler_re", "doppler_im", "doppler_share"]
    return names, np.stack(cols).astype(np.float32)


def cell_rows(cell, model, levels, seed: int, rng: np.random.Generator, per_motion: int) -> dict[str, Any]:
    """Render, map and classify one grid cell (at ``seed``); per window the inputs, true motion, default
    decision and network decision of up to ``per_motion`` band-interior pixels per motion."""
    from classifier.bench import grid as G
    from classifier.infer import classify_maps
    from classifier.prior import Prior
    from torchdoct.measured.mapsfile import write_maps

    density = float(min(Prior().density_per_um3))
    cell = G.GridCell(cell.geometry, cell.context, cell.snr_db, cell.level, cell.polar_deg, cell.azimuth_deg, seed)
    phantoms = G.cell_phantoms(cell, model.spec, levels, density, None)
    pitch = float(phantoms[0]["grid"]["pitch_x_um"])
    res, seq = G.render_sequence(phantoms, cell.key, seed)
    maps = G.signature_maps(seq, model.spec)
    channels = {c: maps.maps[i] for i, c in enumerate(maps.channels)}
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = write_maps(Path(tmp) / "maps.npz", maps)
        for w in POOLS:
            net = classify_maps(path, model, pool=w, abstain_ambiguous=False)
            dflt = classify_maps(path, model, pool=w)
            names, feats = pixel_features(channels, net.probabilities, net.classes, w)
            edge = G.scoring_edge_px(model.spec, pitch, w)
            lab_names = dflt.label_names
            rows_x, rows_y, rows_d, rows_n = [], [], [], []
            for k, m in enumerate(MOTIONS):
                sel = np.flatnonzero((G.interior_pixels(res.labels, m, edge) & (dflt.labels != 255)).ravel())
                if len(sel) > per_motion:
                    sel = np.sort(rng.choice(sel, per_motion, replace=False))
                rows_x.append(feats.reshape(len(feats), -1)[:, sel].T)
                rows_y.append(np.full(len(sel), k, np.int8))
                # a decision: the motion's index where the label names one motion, else -1
                d = [MOTIONS.index(lab_names[v]) if lab_names[v] in MOTIONS else -1 for v in dflt.labels.ravel()[sel]]
                rows_d.append(np.asarray(d, np.int8))
                p = net.probabilities.reshape(len(net.classes), -1)[:, sel]
                top = [net.classes[i] for i in np.argmax(np.nan_to_num(p, nan=-1.0), axis=0)]
                rows_n.append(np.asarray([MOTIONS.index(t) if t in MOTIONS else -1 for t in top], np.int8))
            out[f"x{w}"] = np.concatenate(rows_x)
            out[f"y{w}"] = np.concatenate(rows_y)
            out[f"default{w}"] = np.concatenate(rows_d)
            out[f"network{w}"] = np.concatenate(rows_n)
            out["names"] = np.asarray(names)
    return out


def prior_cells(n: int, seed: int, levels: dict[str, dict[str, float]], geometry: str, context: str):
    """``n`` training phantoms of the ``prior`` training set: the grid's geometry and context, each motion's
    magnitude drawn log-uniformly over the range whose 20/50/80 % points are the grid's speed levels (the
    identifiable range at every grid direction, :func:`classifier.bench.grid.speed_levels`), flow at a polar and
    an azimuth drawn uniformly in [0°, 90°], noise-free or at the grid's SNR in equal shares: pairs
    ``(GridCell, levels)`` whose one level ``draw`` holds the drawn magnitudes."""
    from classifier.bench import grid as G

    rng = np.random.default_rng([seed, 7])
    f0, f2 = G.LEVEL_FRACTIONS[0], G.LEVEL_FRACTIONS[-1]
    out = []
    for i in range(n):
        lv = {}
        for m in MOTIONS:
            a, b = np.log10(levels[m]["slow"]), np.log10(levels[m]["fast"])
            lo, hi = a - f0 * (b - a) / (f2 - f0), b + (1 - f2) * (b - a) / (f2 - f0)
            lv[m] = {"draw": float(f"{10 ** rng.uniform(lo, hi):.4g}")}
        polar, azimuth = (float(f"{v:.3g}") for v in rng.uniform(0.0, 90.0, 2))
        snr = None if i % 2 == 0 else G.SNR_DB
        out.append((G.GridCell(geometry, context, snr, "draw", polar, azimuth, seed), lv))
    return out


def load_cells(cells, seed: int, per_motion: int, cache: Path, model, progress: bool = True, tag: str = "grid"):
    """:func:`cell_rows` of every pair ``(cell, levels)`` at ``seed``, cached as ``cache/TAG-I-KEY-sSEED.npz`` (a
    run resumes)."""
    from tqdm.auto import tqdm

    cache.mkdir(parents=True, exist_ok=True)
    data = []
    rendered = 0
    for i, (cell, levels) in enumerate(tqdm(cells, desc=f"{tag} cells, seed {seed}", disable=not progress)):
        f = cache / f"{tag}-{i}-{cell.key}-s{seed}-n{per_motion}.npz"
        if not f.exists():
            rows = cell_rows(cell, model, levels, seed, np.random.default_rng([seed, i]), per_motion)
            rendered += 1
            tmp = f.with_suffix(".part.npz")
            np.savez(tmp, **rows)
            tmp.replace(f)
        with np.load(f, allow_pickle=False) as z:
            data.append({k: z[k] for k in z.files})
    return data, rendered


def scores(y: np.ndarray, dec: np.ndarray) -> dict[str, Any]:
    """Coverage, balanced accuracy on decided pixels and each motion's wrong share (share of its pixels decided
    as another motion) of decisions ``dec`` (motion index, -1: not decided) against ``y``."""
    per, recalls = {}, []
    for k, m in enumerate(MOTIONS):
        s = y == k
        n, d = int(s.sum()), dec[s]
        decided = int((d >= 0).sum())
        right = int((d == k).sum())
        per[m] = {"coverage": decided / n if n else None, "wrong_share": (decided - right) / n if n else None}
        if decided:
            recalls.append(right / decided)
    return {
        "coverage": float((dec >= 0).mean()) if len(dec) else None,
        "balanced_accuracy": float(np.mean(recalls)) if len(recalls) == len(MOTIONS) else None,
        "worst_wrong_share": max(
            (p["wrong_share"] for p in per.values() if p["wrong_share"] is not None), default=None
        ),
        "per_motion": per,
    }


def _meets(s: dict[str, Any], goal: dict[str, float]) -> bool:
    return (s["balanced_accuracy"] or 0.0) >= goal["balanced_accuracy"] and (s["worst_wrong_share"] or 0.0) <= goal[
        "wrong_share"
    ]


def best_threshold(
    y: np.ndarray, proba: np.ndarray, goal: dict[str, float] = INSIDE, cell_of: np.ndarray | None = None
) -> tuple[float | None, np.ndarray]:
    """The threshold on the top probability that decides the most pixels while the decisions meet the accuracy and
    wrong-share bounds of ``goal`` (:data:`GOALS`) and, with ``cell_of`` (each pixel's cell), the grid's per-cell
    bound (no motion of any one cell with more than :data:`CELL_WRONG_MAX` of its pixels decided as another); and
    the decisions it gives (all -1 when none does)."""
    top, cls = proba.max(axis=1), proba.argmax(axis=1)
    best_t, best_cov = None, -1.0
    for t in np.unique(np.quantile(top, np.linspace(0.0, 0.99, 100))):
        dec = np.where(top >= t, cls, -1)
        s = scores(y, dec)
        if s["coverage"] <= best_cov or not _meets(s, goal):
            continue
        if cell_of is not None and worst_cell(y, dec, cell_of)["cells_over_10pct_wrong"]:
            continue
        best_t, best_cov = float(t), s["coverage"]
    if best_t is None:
        return None, np.full(len(y), -1, np.int8)
    return best_t, np.where(top >= best_t, cls, -1).astype(np.int8)


def worst_cell(y: np.ndarray, dec: np.ndarray, cell_of: np.ndarray) -> dict[str, Any]:
    """The largest wrong share of any motion in any one cell, and how many cells have a motion with more than a
    tenth of its pixels decided as another (the grid's per-cell bound)."""
    worst = [scores(y[cell_of == c], dec[cell_of == c])["worst_wrong_share"] for c in np.unique(cell_of)]
    worst = [w for w in worst if w is not None]
    return {"worst": max(worst, default=None), "cells_over_10pct_wrong": int(sum(w > CELL_WRONG_MAX for w in worst))}


def boot_se(y: np.ndarray, dec: np.ndarray, cell_of: np.ndarray, rng: np.random.Generator) -> dict[str, float]:
    """Bootstrap standard errors over the test cells of the coverage, balanced accuracy and worst wrong share."""
    cells = np.unique(cell_of)
    groups = [np.flatnonzero(cell_of == c) for c in cells]
    vals: dict[str, list[float]] = {"coverage": [], "balanced_accuracy": [], "worst_wrong_share": []}
    for _ in range(BOOT):
        idx = np.concatenate([groups[i] for i in rng.integers(0, len(groups), len(groups))])
        s = scores(y[idx], dec[idx])
        for k in vals:
            if s[k] is not None:
                vals[k].append(s[k])
    return {k: float(np.std(v, ddof=1)) if len(v) > 1 else float("nan") for k, v in vals.items()}


def per_level(y: np.ndarray, dec: np.ndarray, levels: np.ndarray) -> dict[str, Any]:
    """Coverage per motion at each speed level."""
    out = {}
    for lv in ("slow", "mid", "fast"):
        s = levels == lv
        out[lv] = {m: p["coverage"] for m, p in scores(y[s], dec[s])["per_motion"].items()}
    return out


def operating_points(
    ytr: np.ndarray,
    oof: np.ndarray,
    yte: np.ndarray,
    proba: np.ndarray,
    goal: dict[str, float],
    train_cell: np.ndarray,
    test_cell: np.ndarray,
    levels: np.ndarray,
    rng: np.random.Generator,
    per_cell: bool,
) -> dict[str, Any]:
    """An estimator's two operating points (module docstring) on the test pixels: at the threshold chosen on the
    training set's held-out predictions ``oof`` and at the best threshold on the test itself, both under the goal's
    bounds and, with ``per_cell``, the grid's per-cell bound (:func:`best_threshold`)."""
    top, cls = proba.max(axis=1), proba.argmax(axis=1).astype(np.int8)
    t_train, _ = best_threshold(ytr, oof, goal, train_cell if per_cell else None)
    dec_train = np.where(top >= t_train, cls, -1) if t_train is not None else np.full(len(yte), -1, np.int8)
    t, dec = best_threshold(yte, proba, goal, test_cell if per_cell else None)
    return {
        "threshold": t,
        "scores": scores(yte, dec),
        "se": boot_se(yte, dec, test_cell, rng),
        "cells": worst_cell(yte, dec, test_cell),
        "coverage_per_level": per_level(yte, dec, levels),
        "threshold_from_training": t_train,
        "scores_threshold_from_training": scores(yte, dec_train),
        "se_threshold_from_training": boot_se(yte, dec_train, test_cell, rng),
        "cells_threshold_from_training": worst_cell(yte, dec_train, test_cell),
    }


def run_part(
    part: str, out: Path, train_seed: int, test_seed: int, n_cells: int | None, progress: bool = True
) -> tuple[dict[str, Any], int, int]:
    """One part of :data:`PARTS`: its record, and how many phantoms it read and how many it rendered."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from classifier.bench import grid as G
    from classifier.infer import load_model

    geometry, context = PARTS[part]
    model = load_model(MODELS[geometry])
    levels = G.speed_levels(model.spec)
    cells = [c for c in G.full_cells() if c.geometry == geometry and c.context == context][:n_cells]
    cache = out / "cache"
    test, n_test = load_cells([(c, levels) for c in cells], test_seed, TEST_PER_MOTION, cache, model, progress)
    grid_train, n_grid = load_cells([(c, levels) for c in cells], train_seed, TRAIN_PER_MOTION, cache, model, progress)
    prior = prior_cells(len(cells), train_seed, levels, geometry, context)
    prior_train, n_prior = load_cells(prior, train_seed, TRAIN_PER_MOTION, cache, model, progress, f"prior-{part}")
    trains = {"grid": grid_train, "prior": prior_train}
    rng = np.random.default_rng(test_seed)
    result: dict[str, Any] = {
        "geometry": geometry,
        "context": context,
        "model": MODELS[geometry],
        "cells": len(cells),
        "goal": {str(w): GOALS[(part, w)] for w in POOLS},
        "windows": {},
    }
    for w in POOLS:
        goal = GOALS[(part, w)]
        names = [str(n) for n in test[0]["names"]]
        xte = np.concatenate([d[f"x{w}"] for d in test])
        yte = np.concatenate([d[f"y{w}"] for d in test])
        cell_of = np.concatenate([np.full(len(d[f"y{w}"]), i) for i, d in enumerate(test)])
        lv = np.concatenate([np.full(len(d[f"y{w}"]), c.level) for c, d in zip(cells, test)])
        entry: dict[str, Any] = {"test_pixels": int(len(yte)), "inputs": {}}
        for (which, set_name), groups in ESTIMATORS.items():
            train = trains[set_name]
            xtr = np.concatenate([d[f"x{w}"] for d in train])
            ytr = np.concatenate([d[f"y{w}"] for d in train])
            train_cell = np.concatenate([np.full(len(d[f"y{w}"]), i) for i, d in enumerate(train)])
            fold = train_cell % 2
            prefixes = tuple(p for g in groups for p in GROUPS[g])
            cols = [i for i, n in enumerate(names) if n.startswith(prefixes)]
            # a channel these maps never hold, or one fold's phantoms never do; where no phantom has a Doppler
            # reference (no static tissue), the share of the box that holds a phase is 0 everywhere and stays: the
            # group then reads like the network alone
            cols = [i for i in cols if all(np.isfinite(xtr[fold == k, i]).any() for k in (0, 1))]
            if which != "network" and all(names[i].startswith(GROUPS["network"]) for i in cols):
                continue  # the groups add no column to the network's in these maps

            def fit(sel: np.ndarray, cols=cols, xtr=xtr, ytr=ytr):
                return HistGradientBoostingClassifier(random_state=train_seed, **GB_PARAMS).fit(
                    xtr[sel][:, cols], ytr[sel]
                )

            # the threshold a user could choose: on the training cells' held-out predictions (two folds of cells)
            oof = np.empty((len(ytr), len(MOTIONS)))
            for k in (0, 1):
                oof[fold == k] = fit(fold != k).predict_proba(xtr[fold == k][:, cols])
            proba = fit(np.ones(len(ytr), bool)).predict_proba(xte[:, cols])
            cls = proba.argmax(axis=1).astype(np.int8)
            entry["inputs"][f"{which}, {set_name}"] = {
                "train_pixels": int(len(ytr)),
                "features": [names[i] for i in cols],
                "argmax": scores(yte, cls),
                # the goal's bounds and every cell within the grid's per-cell bound; the goal's bounds alone
                **{
                    key: operating_points(ytr, oof, yte, proba, goal, train_cell, cell_of, lv, rng, per_cell)
                    for key, per_cell in (("with_cell_bound", True), ("pooled_only", False))
                },
            }
        for which in ("default", "network"):
            dec = np.concatenate([d[f"{which}{w}"] for d in test])
            entry[f"{which}_decision"] = {
                "scores": scores(yte, dec),
                "se": boot_se(yte, dec, cell_of, rng),
                "cells": worst_cell(yte, dec, cell_of),
                "coverage_per_level": per_level(yte, dec, lv),
            }
        result["windows"][str(w)] = entry
    return result, 3 * len(cells), n_test + n_grid + n_prior


def run(
    out: Path, parts: Sequence[str], train_seed: int, test_seed: int, n_cells: int | None, progress: bool = True
) -> dict[str, Any]:
    """Every part of ``parts`` (:func:`run_part`) in one record."""
    t0 = time.perf_counter()
    result: dict[str, Any] = {"benchmark": "grid-ceiling", "parts": {}}
    phantoms = rendered = 0
    for part in parts:
        result["parts"][part], n, r = run_part(part, out, train_seed, test_seed, n_cells, progress)
        phantoms, rendered = phantoms + n, rendered + r
    result.update(
        {
            "train_seed": train_seed,
            "test_seed": test_seed,
            "train_per_motion": TRAIN_PER_MOTION,
            "test_per_motion": TEST_PER_MOTION,
            "estimator": {"name": "HistGradientBoostingClassifier", **GB_PARAMS},
            "bootstrap": BOOT,
            "seconds": time.perf_counter() - t0,
            "phantoms": phantoms,
            "phantoms_rendered": rendered,
            "command": "python -m research.grid_ceiling --out DIR"
            + (f" --parts {','.join(parts)}" if list(parts) != list(PARTS) else "")
            + (f" --train-seed {train_seed}" if train_seed != 1 else "")
            + (f" --test-seed {test_seed}" if test_seed != 0 else "")
            + (f" --cells {n_cells}" if n_cells else ""),
        }
    )
    return result


def _f(v: Any, se: float | None = None) -> str:
    if v is None:
        return "–"
    return f"{v:.3f}" + (f" ± {se:.3f}" if se is not None and np.isfinite(se) else "")


def _row(w: str, label: str, how: str, s: dict[str, Any], se: dict[str, float], cells: dict[str, Any]) -> str:
    pm = " / ".join(_f(s["per_motion"][m]["coverage"]) for m in MOTIONS)
    return (
        f"| {w} | {label} | {how} | {_f(s['coverage'], se['coverage'])} | "
        f"{_f(s['balanced_accuracy'], se['balanced_accuracy'])} | "
        f"{_f(s['worst_wrong_share'], se['worst_wrong_share'])} | {_f(cells['worst'])} "
        f"({cells['cells_over_10pct_wrong']}) | {pm} |"
    )


def _estimator_rows(w: str, e: dict[str, Any], key: str) -> list[str]:
    out = []
    for k, v in e["inputs"].items():
        inputs, tset = k.split(", ")
        label = f"gradient boosting: `{inputs}`, trained on `{tset}`"
        op = v[key]
        held = ("held out", op["scores_threshold_from_training"], op["se_threshold_from_training"])
        out.append(_row(w, label, *held, op["cells_threshold_from_training"]))
        out.append(_row(w, label, "best", op["scores"], op["se"], op["cells"]))
    return out


def format_md(res: dict[str, Any]) -> str:
    lines = [
        "# The ceiling of the phantom grid's unmet goals",
        "",
        "Per part: the phantom grid's cells of one geometry and static context (every noise, speed level, polar and "
        f"azimuth), rendered at seed {res['test_seed']} ({res['test_per_motion']} band-interior pixels per motion and "
        "cell). Gradient boosting fitted on the training set `grid` (the same cells at seed "
        f"{res['train_seed']}: the grid's own speed levels and angles) or `prior` (as many phantoms of the same "
        "geometry and context with every magnitude log-uniform over the range whose 20/50/80 % points are the grid's "
        f"levels, flow at uniform angles, noise-free or 20 dB in equal shares, seed {res['train_seed']}), "
        f"{res['train_per_motion']} pixels per motion and phantom. An estimator decides its top class where its "
        "probability reaches a threshold: *held out*, the threshold that decides the most of the training set's "
        "held-out predictions (two folds of its phantoms) within the goal's accuracy and wrong-share bounds and "
        f"with no phantom's motion more than {CELL_WRONG_MAX} wrong (the grid's per-cell bound); *best*, the one that "
        "decides the most of the test pixels within them (chosen on the test itself: optimistic). "
        "The wrong shares are over all cells of a part, as the goals page's; *worst cell*: the largest wrong share of "
        "a motion in one cell, and how many cells have a motion with more than 0.1 of its pixels decided as another. "
        "± : bootstrap SE over the test cells (`research/grid_ceiling.py`).",
    ]

    for part, pr in res["parts"].items():
        goals = "; ".join(
            f"window {w}: balanced accuracy ≥ {g['balanced_accuracy']} at coverage ≥ {g['coverage']}, no motion with "
            f"more than {g['wrong_share']} of its pixels decided as another"
            for w, g in pr["goal"].items()
        )
        head = [
            "| window | decision | threshold | coverage | bal. acc. | worst wrong share | worst cell (cells over 0.1) "
            "| coverage diffusion / ballistic / flow |",
            "|---|---|---|---:|---:|---:|---:|---|",
        ]
        lines += [
            "",
            f"## `{part}`: {pr['cells']} cells, geometry `{pr['geometry']}`, context `{pr['context']}`, model "
            f"`{pr['model']}`",
            "",
            f"Goal: {goals}; and no cell with a motion of which more than {CELL_WRONG_MAX} is decided as another.",
            "",
            *head,
        ]
        for w, e in pr["windows"].items():
            for label, key in (
                ("default decision (`doct-classify`)", "default"),
                ("default network, argmax", "network"),
            ):
                d = e[f"{key}_decision"]
                lines.append(_row(w, label, "–", d["scores"], d["se"], d["cells"]))
            lines += _estimator_rows(w, e, "with_cell_bound")
        lines += [
            "",
            "The same estimators at thresholds chosen under the goal's bounds alone, without the per-cell bound: "
            "what a decision gains by being wrong over most of a few cells.",
            "",
            *head,
        ]
        for w, e in pr["windows"].items():
            lines += _estimator_rows(w, e, "pooled_only")
        lines += [
            "",
            "Coverage per motion and speed level at the best threshold under every bound (diffusion / ballistic / flow):",
            "",
        ]
        lines += ["| window | decision | slow | mid | fast |", "|---|---|---|---|---|"]
        for w, e in pr["windows"].items():
            rows = [("default decision", e["default_decision"])]
            rows += [
                (f"gradient boosting: `{k.split(', ')[0]}`, `{k.split(', ')[1]}`", v["with_cell_bound"])
                for k, v in e["inputs"].items()
            ]
            for label, r in rows:
                cl = r["coverage_per_level"]
                cells = [" / ".join(_f(cl[lv][m]) for m in MOTIONS) for lv in ("slow", "mid", "fast")]
                lines.append(f"| {w} | {label} | " + " | ".join(cells) + " |")
    took = f"{res['seconds'] / 60:.0f} min on the machine of the record"
    if res["phantoms_rendered"] < res["phantoms"]:
        took += f", {res['phantoms'] - res['phantoms_rendered']} of its {res['phantoms']} phantoms read from the cache"
    lines += ["", f"Reproduce: `{res['command']}` ({took}).", ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.grid_ceiling", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder (grid-ceiling.json and .md, cache/)")
    ap.add_argument("--train-seed", type=int, default=1, help="rendering seed of the training cells (default 1)")
    ap.add_argument("--test-seed", type=int, default=0, help="rendering seed of the test cells (default 0)")
    ap.add_argument(
        "--parts",
        default=",".join(PARTS),
        help=f"comma-separated parts of {', '.join(PARTS)} (default: all)",
    )
    ap.add_argument("--cells", type=int, default=None, help="only the first N cells of each part (a quick look)")
    ap.add_argument("--force", action="store_true", help="overwrite grid-ceiling.json and .md")
    a = ap.parse_args(argv)
    if a.train_seed == a.test_seed:
        ap.error("--train-seed and --test-seed must differ: the estimator is scored on cells it did not see")
    parts = [p.strip() for p in a.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts or len(set(parts)) != len(parts):
        ap.error(f"--parts {a.parts!r}: give distinct names among {', '.join(PARTS)}")
    if a.cells is not None and a.cells < 1:
        ap.error("--cells must be at least 1")
    a.out.mkdir(parents=True, exist_ok=True)
    targets = [a.out / "grid-ceiling.json", a.out / "grid-ceiling.md"]
    if not a.force and any(t.exists() for t in targets):
        ap.error(f"{targets[0]} or {targets[1]} exists: pass --force to overwrite it, or another --out")
    res = run(a.out, parts, a.train_seed, a.test_seed, a.cells)
    targets[0].write_text(json.dumps(res, indent=1) + "\n")
    targets[1].write_text(format_md(res))
    print(format_md(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Candidate rules against the slow-region spill of the random phantoms: what each would buy and cost.

The random phantoms (:mod:`classifier.bench.random_phantoms`, docs/benchmarks/random.md) show one failure mode of
the default decision: a slow region (slow flow, slow random-ballistic motion) beside or inside faster diffusion,
or a small vessel in slow diffusion, gets ``diffusion`` decisions at its border, or over all of it. This script
measures candidate rules against it on the same draws, each applied to the default decision's final labels
(each only abstains: a flagged single-class decision becomes ``indeterminate``), and reports for each the
share of draws over the project's bounds, the coverage and wrong share per motion, and how many of the default
decision's right and wrong single-class decisions it flags (a rule worth shipping flags far more of the wrong
than of the right), and of the right ones far from every other region (farther than the grid benchmark's
scoring edge): there a candidate's premise, a coarse footprint that reaches another region, cannot hold, so
what it flags there is its false-detection rate. The candidates, from the physics of docs/abstention.md:

* ``mixed-pixel``: rule 9's statistic (:func:`classifier.ambiguity.mixed_footprint`: the mean over lags of the
  finest configuration's pooled intensity correlation minus a coarser one's; inside one motion's region it is
  at most the estimators' scatter, since reducing the resolution never speeds a region's decorrelation)
  applied to ``diffusion`` and ``ballistic`` decisions too, per pixel, at rule 9's threshold
  :data:`classifier.ambiguity.MIXED_DECAY_MIN`;
* ``mixed-box-T``: the same statistic averaged over the classified pixels of rule 8's box (the finest
  footprint widened by the pooling window), over ``T``: averaging trades the single pixel's scatter for
  resolution, and the region a coarse PSF mixes in is as wide as that PSF;
* ``shape-pixel`` and ``shape-box-T``: the same on the decay's shape (:func:`decay_excess` with ``shape``): each
  configuration's correlations divided by its own at the shortest lag, which removes the factor by which noise
  lowers them (physics.md §8: one factor for every lag of a frame or more, set by the configuration's own SNR;
  a coarser configuration averages more noise away, its correlations sit higher, and the raw excess is biased
  low by exactly the noise that hides the slow region's decay);
* ``pool-1-excludes`` (windows above 1): a pooled decision whose pixel's own unpooled outcome (pool 1,
  the same decision and rules) excludes it: another motion, or a set that does not name it.

Run from the repository root with a development install::

    python -m research.spill --out DIR [--bscans N] [--volumes N]

It writes ``DIR/spill-rules.json`` and ``.md`` (the recorded run: ``research/results/spill-rules.*``).

**The shape statistic's null** (``--null``): rule 12 of :mod:`classifier.ambiguity` (the ``shape-box``
candidate, shipped) needs its threshold set on data it was not chosen on. Inside one motion's region the
statistic's premise cannot hold (no coarse footprint reaches another motion), so the share of a region's
interior pixels whose footprint mean exceeds a threshold is its false-detection rate there. This mode renders
the grid benchmark's cells (:func:`classifier.bench.grid.full_cells`) at another seed than the benchmark's
(:data:`NULL_SEED`), maps and classifies them at rule 12's window, and reports that share per geometry, motion
and static context at every threshold of :data:`NULL_THRESHOLDS`, and the smallest threshold whose share stays
at or under :data:`NULL_RATE` in every geometry and motion (``MIXED_SHAPE_MIN`` is that value)::

    python -m research.spill --null --out DIR [--cells N] [--jobs N]

It writes ``DIR/spill-null.json`` and ``.md`` (the recorded run: ``research/results/spill-null.*``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from classifier.ambiguity import SHAPE_FLOOR

#: Thresholds of the ``mixed-box`` and ``shape-box`` candidates (mean excess over rule 8's box).
BOX_THRESHOLDS = (0.1, 0.2)
SHAPE_BOX_THRESHOLDS = (0.2, 0.3)
#: ``--null``: the thresholds at which the shape statistic's false-detection rate is reported, the stated rate
#: rule 12's threshold is set at, and the seed of the grid's cells (the grid benchmark renders them at 0).
NULL_THRESHOLDS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5)
NULL_RATE = 0.01
NULL_SEED = 1
#: Decisions a candidate may set aside: rule 9 already covers ``flow``.
FLAGGED = ("diffusion", "ballistic")
_CLASSES = ("diffusion", "ballistic", "flow", "indeterminate")


def excludes(outcome: str, decision: str) -> bool:
    """Whether an outcome (a class, a set ``a-or-b``, ``indeterminate``) excludes a single-class ``decision``:
    another class, or a set that does not name it; ``indeterminate`` excludes nothing."""
    if outcome == "indeterminate":
        return False
    return decision not in outcome.split("-or-")


def box_mean(values: np.ndarray, valid: np.ndarray, window: Sequence[int]) -> np.ndarray:
    """Per pixel, the mean of ``values`` over the ``valid`` pixels of the box ``window`` (pixels per axis, odd)
    centred on it, the box cut at the image's edges (NaN where it holds none); ``values`` and ``valid`` over the
    same spatial shape, ``values`` finite where valid (rule 12's :func:`classifier.ambiguity.footprint_mean` at
    every pixel)."""
    from classifier.ambiguity import footprint_mean

    shape = np.shape(values)
    every = np.arange(int(np.prod(shape)))
    return footprint_mean(np.where(valid, values, np.nan).reshape(-1), every, shape, list(window)).reshape(shape)


def decay_excess(x: np.ndarray, columns: Sequence[Mapping[str, Any]], finest: str, shape: bool = False):
    """Per input row, rule 9's excess (:func:`classifier.ambiguity.mixed_footprint`: the largest over the coarser
    configurations of the mean over the lags both read of the finest configuration's pooled intensity correlation
    minus the coarser one's), or with ``shape`` rule 12's on the decay's shape
    (:func:`classifier.ambiguity.shape_excess`: each correlation divided by its own at the shortest common lag,
    NaN under :data:`classifier.ambiguity.SHAPE_FLOOR`); ``None`` when the model reads no common lag."""
    from classifier.ambiguity import mixed_footprint, shape_excess

    if shape:
        return shape_excess(columns, x, finest)
    return mixed_footprint(np.zeros(len(x), int), _CLASSES, columns, x, finest)[1]


def excess_maps(maps, features: np.ndarray, model, labels: np.ndarray, pool: int, finest: str) -> dict[str, np.ndarray]:
    """:func:`decay_excess` against the configuration ``finest``, raw (``mixed``) and on the decay's shape
    (``shape``, rule 12's statistic), per pixel of a classification's spatial shape (NaN where it classified
    nothing or the excess is undefined), from the model inputs ``classify_maps`` builds at ``pool`` out of
    ``features`` (:func:`classifier.matching.assemble_features` of ``maps``, made once per map)."""
    from classifier.outputs import MASKED
    from classifier.pooling import independent_fraction, model_inputs

    valid = labels != MASKED
    frac = independent_fraction(int(pool), maps.meta.get("pitch_um"), model.spec)
    x, idx = model_inputs(features, valid, int(pool), frac, model.pool_pixels_max)
    out = {}
    for name in ("mixed", "shape"):
        grid = np.full(labels.size, np.nan)
        e = decay_excess(x, model.columns, finest, name == "shape")
        if e is not None:
            grid[idx] = e
        out[name] = grid.reshape(labels.shape)
    return out


def candidates(
    labels: np.ndarray,
    names: Sequence[str],
    excess: Mapping[str, np.ndarray],
    fine_window: Sequence[int],
    unpooled: tuple[np.ndarray, Sequence[str]] | None,
) -> dict[str, np.ndarray]:
    """Per candidate, the pixels whose single-class decision it flags (boolean over the spatial shape);
    ``excess``: :func:`excess_maps`."""
    from classifier.ambiguity import MIXED_DECAY_MIN
    from classifier.outputs import MASKED

    names = list(names)
    flaggable = np.isin(labels, [names.index(m) for m in FLAGGED])
    classified = labels != MASKED

    def over(values: np.ndarray, t: float) -> np.ndarray:
        return flaggable & (np.nan_to_num(values, nan=-np.inf) > t)

    def boxed(values: np.ndarray) -> np.ndarray:
        return box_mean(np.nan_to_num(values), classified & np.isfinite(values), fine_window)

    out = {"mixed-pixel": over(excess["mixed"], MIXED_DECAY_MIN)}
    out |= {f"mixed-box-{t:g}": over(boxed(excess["mixed"]), t) for t in BOX_THRESHOLDS}
    out["shape-pixel"] = over(excess["shape"], MIXED_DECAY_MIN)
    out |= {f"shape-box-{t:g}": over(boxed(excess["shape"]), t) for t in SHAPE_BOX_THRESHOLDS}
    if unpooled is not None:
        own, own_names = unpooled
        hit = np.zeros(labels.shape, bool)
        for k in (names.index(m) for m in ("diffusion", "ballistic", "flow")):
            for j, outcome in enumerate(own_names):
                if excludes(outcome, names[k]):
                    hit |= (labels == k) & (own == j)
        out["pool-1-excludes"] = hit
    return out


def score(
    truth: np.ndarray,
    labels: np.ndarray,
    names: Sequence[str],
    flagged: np.ndarray | None,
    interior: np.ndarray | None = None,
) -> dict[str, Any]:
    """The random phantoms' scores (:func:`classifier.bench.grid.score_labels`, every pixel) of ``labels`` with
    the ``flagged`` pixels made ``indeterminate``, and how many of the unflagged decisions' right and wrong
    single-class decisions the flag took; with ``interior`` (the pixels far from every other region,
    :func:`classifier.bench.grid.interior_pixels`) also how many of the right decisions there: the candidate's
    false detections inside one motion's region, where its premise (a coarse footprint that reaches another
    region) cannot hold."""
    from classifier.bench.grid import CODES, score_labels

    names = list(names)
    ind = names.index("indeterminate")
    out_labels = labels if flagged is None else np.where(flagged, ind, labels)
    s = score_labels(truth, out_labels, names, 0)
    row = {
        "per_class": {m: {k: s["per_class"][m][k] for k in ("pixels", "coverage", "wrong_share")} for m in CODES},
        "coverage": s["coverage"],
        "wrong_share_max": s["wrong_share_max"],
    }
    if flagged is not None:
        motion = np.isin(truth, list(CODES.values()))
        decided = np.zeros(labels.shape, bool)
        right = np.zeros(labels.shape, bool)
        for m, code in CODES.items():
            k = names.index(m)
            decided |= motion & (labels == k)
            right |= (truth == code) & (labels == k)
        wrong = decided & ~right
        row["flagged"] = {
            "right": int((flagged & right).sum()),
            "right_of": int(right.sum()),
            "wrong": int((flagged & wrong).sum()),
            "wrong_of": int(wrong.sum()),
        }
        if interior is not None:
            inside = right & interior
            row["flagged"] |= {"right_interior": int((flagged & inside).sum()), "right_interior_of": int(inside.sum())}
    return row


def run_draw(geometry: str, index: int, model, *, threads: int | None = None) -> dict[str, Any]:
    """Render and map one random-phantom draw as the benchmark does, classify it with the default decision at
    every window of the benchmark, and score the default and every candidate."""
    from classifier.bench import random_phantoms as rp
    from classifier.bench.grid import interior_pixels, render_sequence, scoring_edge_px, signature_maps
    from classifier.infer import classify_maps
    from classifier.matching import assemble_features
    from torchdoct.measured.mapsfile import write_maps

    phantoms, description = rp.draw(geometry, index)
    res, seq = render_sequence(phantoms, phantoms[0]["name"], int(phantoms[0]["simulation"]["seed"]), threads=threads)
    truth = np.asarray(res.labels)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        maps = signature_maps(seq, model.spec)
        path = write_maps(Path(tmp) / "maps.npz", maps)
        features, _, _ = assemble_features([maps], model)
        unpooled = None
        for pool in rp.POOLS:
            c = classify_maps(path, model, pool=pool, threads=threads)
            names = list(c.classes) + list(c.set_labels)
            amb = c.info["ambiguity"]
            window = [int(w) for w in amb["fine_window_px"].values()]
            excess = excess_maps(maps, features, model, c.labels, pool, amb["finest_configuration"])
            flags = candidates(c.labels, names, excess, window, unpooled if pool > 1 else None)
            edge = scoring_edge_px(model.spec, rp.PITCH_UM, pool)
            interior = np.any([interior_pixels(truth, m, edge) for m in rp.MOTIONS], axis=0)
            rows.append({"pool": pool, "variant": "default", **score(truth, c.labels, names, None)})
            rows += [
                {"pool": pool, "variant": k, **score(truth, c.labels, names, f, interior)} for k, f in flags.items()
            ]
            if pool == 1:
                unpooled = (c.labels, names)
    return {**description, "rows": rows}


def summarize(draws: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per geometry, window and variant: the share of draws over each of the benchmark's bounds, the pooled
    coverage and wrong share per motion, and the flagged shares of the default's right and wrong decisions."""
    from classifier.bench.random_phantoms import BOUNDS, GEOMETRIES, MOTIONS

    keys: list[tuple[str, int, str]] = []
    for d in draws:
        for r in d["rows"]:
            k = (d["geometry"], r["pool"], r["variant"])
            if k not in keys:
                keys.append(k)
    keys.sort(key=lambda k: (GEOMETRIES.index(k[0]), k[1]))
    out = []
    for geometry, pool, variant in keys:
        rows = [r for d in draws if d["geometry"] == geometry for r in d["rows"]]
        rows = [r for r in rows if r["pool"] == pool and r["variant"] == variant]
        worst = np.array([r["wrong_share_max"] or 0.0 for r in rows], float)
        per_class = {}
        for m in MOTIONS:
            held = [r["per_class"][m] for r in rows if r["per_class"][m]["pixels"]]
            n = sum(c["pixels"] for c in held)
            per_class[m] = {
                "coverage": sum(c["coverage"] * c["pixels"] for c in held) / n if n else None,
                "wrong_share": sum(c["wrong_share"] * c["pixels"] for c in held) / n if n else None,
            }
        entry = {
            "geometry": geometry,
            "pool": pool,
            "variant": variant,
            "draws": len(rows),
            "over_bound": {f"{b:g}": float(np.mean(worst > b)) for b in BOUNDS},
            "per_class": per_class,
        }
        if rows and "flagged" in rows[0]:
            counted = ("right", "right_of", "wrong", "wrong_of", "right_interior", "right_interior_of")
            f = {k: sum(r["flagged"].get(k, 0) for r in rows) for k in counted}
            entry["flagged_right"] = f["right"] / f["right_of"] if f["right_of"] else None
            entry["flagged_right_interior"] = (
                f["right_interior"] / f["right_interior_of"] if f["right_interior_of"] else None
            )
            entry["flagged_wrong"] = f["wrong"] / f["wrong_of"] if f["wrong_of"] else None
            entry["wrong_decisions"] = f["wrong_of"]
        out.append(entry)
    return out


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def to_markdown(result: Mapping[str, Any]) -> str:
    """The summary as one Markdown table."""
    lines = [
        "| geometry | window | candidate | draws over 0.05 | over 0.10 | diffusion coverage | ballistic coverage "
        "| flow coverage | worst pooled wrong share | flags of right decisions | of right ones inside a region "
        "| flags of wrong decisions |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in result["summary"]:
        pc = s["per_class"]
        worst = max((c["wrong_share"] or 0.0) for c in pc.values())
        lines.append(
            "| "
            + " | ".join(
                [
                    s["geometry"],
                    str(s["pool"]),
                    s["variant"],
                    _fmt(s["over_bound"]["0.05"]),
                    _fmt(s["over_bound"]["0.1"]),
                    *(_fmt(pc[m]["coverage"]) for m in ("diffusion", "ballistic", "flow")),
                    f"{worst:.4f}",
                    _fmt(s.get("flagged_right")),
                    _fmt(s.get("flagged_right_interior")),
                    _fmt(s.get("flagged_wrong")),
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def run_null_cell(cell, model, levels: dict[str, dict[str, float]], density: float) -> dict[str, Any]:
    """One grid cell rendered, mapped and classified (the default decision) at rule 12's window
    (:data:`classifier.ambiguity.MIXED_SHAPE_POOL_MIN`): per motion, its interior pixels (farther than the grid's scoring edge from every other region) where the statistic's mean
    over rule 8's box is defined, how many of them exceed each threshold of :data:`NULL_THRESHOLDS`, and the
    largest."""
    from classifier.ambiguity import MIXED_SHAPE_POOL_MIN, footprint_mean, shape_excess
    from classifier.bench.grid import (
        MOTIONS,
        cell_phantoms,
        interior_pixels,
        render_sequence,
        scoring_edge_px,
        signature_maps,
    )
    from classifier.infer import classify_maps
    from classifier.matching import assemble_features
    from classifier.outputs import MASKED
    from classifier.pooling import independent_fraction, model_inputs
    from torchdoct.measured.mapsfile import write_maps

    pool = MIXED_SHAPE_POOL_MIN
    phantoms = cell_phantoms(cell, model.spec, levels, density)
    res, seq = render_sequence(phantoms, cell.key, cell.seed)
    truth = np.asarray(res.labels)
    maps = signature_maps(seq, model.spec)
    with tempfile.TemporaryDirectory() as tmp:
        c = classify_maps(write_maps(Path(tmp) / "maps.npz", maps), model, pool=pool)
    amb = c.info["ambiguity"]
    features, _, _ = assemble_features([maps], model)
    valid = c.labels != MASKED
    frac = independent_fraction(pool, maps.meta.get("pitch_um"), model.spec)
    x, idx = model_inputs(features, valid, pool, frac, model.pool_pixels_max)
    window = [int(w) for w in amb["fine_window_px"].values()]
    edge = scoring_edge_px(model.spec, float(phantoms[0]["grid"]["pitch_x_um"]), pool)
    excess = shape_excess(model.columns, x, amb["finest_configuration"])
    mean = np.full(valid.size, np.nan)
    if excess is not None:
        mean[idx] = footprint_mean(excess, idx, valid.shape, window)
    mean = mean.reshape(valid.shape)
    per_motion = {}
    for m in MOTIONS:
        values = mean[interior_pixels(truth, m, edge) & valid]
        values = values[np.isfinite(values)]
        per_motion[m] = {
            "pixels": int(values.size),
            "over": [int((values > t).sum()) for t in NULL_THRESHOLDS],
            "max": float(values.max()) if values.size else None,
        }
    return {"key": cell.key, "geometry": cell.geometry, "context": cell.context, "per_motion": per_motion}


def summarize_null(cells: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per geometry and motion (and per static context), the share of interior pixels over each threshold; and
    the smallest threshold of :data:`NULL_THRESHOLDS` whose share is at most :data:`NULL_RATE` in every geometry
    for each motion whose decisions rule 12 sets aside (:data:`classifier.ambiguity.MIXED_SHAPE_FLAGS`;
    ``None`` when none is)."""
    from classifier.ambiguity import MIXED_SHAPE_FLAGS
    from classifier.bench.grid import MOTIONS

    def pooled(rows: Sequence[Mapping[str, Any]], m: str) -> dict[str, Any]:
        n = sum(r["per_motion"][m]["pixels"] for r in rows)
        over = [sum(r["per_motion"][m]["over"][k] for r in rows) for k in range(len(NULL_THRESHOLDS))]
        return {"pixels": n, "share_over": [o / n if n else None for o in over]}

    groups = []
    for geometry in sorted({c["geometry"] for c in cells}):
        for context in [None, *sorted({c["context"] for c in cells})]:
            rows = [c for c in cells if c["geometry"] == geometry and context in (None, c["context"])]
            if rows:
                groups.append(
                    {
                        "geometry": geometry,
                        "context": context or "all",
                        "per_motion": {m: pooled(rows, m) for m in MOTIONS},
                    }
                )
    overall = [g for g in groups if g["context"] == "all"]
    chosen = next(
        (
            t
            for k, t in enumerate(NULL_THRESHOLDS)
            if all(
                (g["per_motion"][m]["share_over"][k] or 0.0) <= NULL_RATE for g in overall for m in MIXED_SHAPE_FLAGS
            )
        ),
        None,
    )
    return {
        "flags": list(MIXED_SHAPE_FLAGS),
        "thresholds": list(NULL_THRESHOLDS),
        "rate": NULL_RATE,
        "chosen": chosen,
        "groups": groups,
    }


def null_markdown(result: Mapping[str, Any]) -> str:
    """The null summary as one Markdown table: the share of interior pixels over each threshold."""
    s = result["summary"]
    head = " | ".join(f"over {t:g}" for t in s["thresholds"])
    lines = [
        f"| geometry | static context | motion | interior pixels | {head} |",
        "| --- | --- | --- | --- | " + " | ".join("---" for _ in s["thresholds"]) + " |",
    ]
    for g in s["groups"]:
        for m, p in g["per_motion"].items():
            cells = " | ".join(_fmt(v) for v in p["share_over"])
            lines.append(f"| {g['geometry']} | {g['context']} | {m} | {p['pixels']} | {cells} |")
    chosen = "none" if s["chosen"] is None else f"{s['chosen']:g}"
    flags = ", ".join(s["flags"])
    lines += ["", f"Smallest threshold at or under a rate of {s['rate']:g} for {flags} in every geometry: {chosen}."]
    return "\n".join(lines) + "\n"


def _write(stem: Path, result: Mapping[str, Any], markdown: str) -> int:
    """``STEM.json`` (compact) and ``STEM.md``, the tables also printed; 0 (the exit status)."""
    stem.with_suffix(".json").write_text(json.dumps(result, separators=(",", ":")))
    stem.with_suffix(".md").write_text(markdown)
    print(markdown)
    return 0


_NULL_STATE: dict[str, Any] = {}


def _null_cell(cell) -> dict[str, Any]:
    """:func:`run_null_cell` with the models, speed levels and density loaded once per process."""
    if not _NULL_STATE:
        from classifier.bench.grid import speed_levels
        from classifier.infer import load_model
        from classifier.prior import Prior

        models = {g: load_model("signature" if g == "volume" else "signature-bscan") for g in ("bscan", "volume")}
        _NULL_STATE.update(
            models=models,
            levels={g: speed_levels(m.spec) for g, m in models.items()},
            density=float(min(Prior().density_per_um3)),
        )
    st = _NULL_STATE
    return run_null_cell(cell, st["models"][cell.geometry], st["levels"][cell.geometry], st["density"])


def null_main(out: Path, n_cells: int | None, jobs: int = 1) -> int:
    """``--null``: every grid cell at :data:`NULL_SEED` (or the first ``n_cells``), in ``jobs`` processes (each
    cell is rendered from its own seed: the same rows for any count), written to ``out``."""
    from concurrent.futures import ProcessPoolExecutor

    from tqdm.auto import tqdm

    from classifier.bench.grid import full_cells

    t0 = time.perf_counter()
    cells = full_cells(NULL_SEED)[: n_cells if n_cells else None]
    if jobs > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            rows = list(tqdm(pool.map(_null_cell, cells), total=len(cells), desc="shape null", unit="cell"))
    else:
        rows = [_null_cell(c) for c in tqdm(cells, desc="shape null", unit="cell")]
    extra = (f" --cells {n_cells}" if n_cells else "") + (f" --jobs {jobs}" if jobs > 1 else "")
    result = {
        "command": f"python -m research.spill --null --out DIR{extra}",
        "seed": NULL_SEED,
        "summary": summarize_null(rows),
        "cells": rows,
        "seconds": time.perf_counter() - t0,
    }
    return _write(out / "spill-null", result, null_markdown(result))


def main(argv: list[str] | None = None) -> int:
    from tqdm.auto import tqdm

    from classifier.bench.random_phantoms import N_BSCANS, N_VOLUMES, check_counts
    from classifier.infer import load_model

    p = argparse.ArgumentParser(prog="python -m research.spill", description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--bscans", type=int, default=N_BSCANS, help=f"B-scan draws (default {N_BSCANS})")
    p.add_argument("--volumes", type=int, default=N_VOLUMES, help=f"volume draws (default {N_VOLUMES})")
    p.add_argument("--null", action="store_true", help="the shape statistic's null on the grid's cells instead")
    p.add_argument("--cells", type=int, default=None, help="--null: only the first N grid cells")
    p.add_argument("--jobs", type=int, default=1, help="--null: processes (default 1)")
    args = p.parse_args(argv)
    if args.cells is not None and args.cells < 1:
        p.error(f"--cells must be a positive number of cells, got {args.cells}")
    if args.jobs < 1:
        p.error(f"--jobs must be a positive number of processes, got {args.jobs}")
    try:
        check_counts(args.bscans, args.volumes)
    except ValueError as err:
        p.error(str(err))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.null:
        return null_main(out, args.cells, args.jobs)
    t0 = time.perf_counter()
    models = {g: load_model("signature" if g == "volume" else "signature-bscan") for g in ("bscan", "volume")}
    jobs = [("bscan", i) for i in range(args.bscans)] + [("volume", i) for i in range(args.volumes)]
    draws = [run_draw(g, i, models[g]) for g, i in tqdm(jobs, desc="spill candidates", unit="draw")]
    result = {
        "command": f"python -m research.spill --out DIR --bscans {args.bscans} --volumes {args.volumes}",
        "box_thresholds": BOX_THRESHOLDS,
        "shape_box_thresholds": SHAPE_BOX_THRESHOLDS,
        "shape_floor": SHAPE_FLOOR,
        "summary": summarize(draws),
        "draws": draws,
        "seconds": time.perf_counter() - t0,
    }
    return _write(out / "spill-rules", result, to_markdown(result))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

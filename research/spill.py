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
* ``shape-pixel`` and ``shape-box-T``: the same on the decay's shape (:func:`decay_excess` with a floor): each
  configuration's correlations divided by its own at the shortest lag, which removes the factor by which noise
  lowers them (physics.md §8: one factor for every lag of a frame or more, set by the configuration's own SNR;
  a coarser configuration averages more noise away, its correlations sit higher, and the raw excess is biased
  low by exactly the noise that hides the slow region's decay);
* ``pool-1-excludes`` (windows above 1): a pooled decision whose pixel's own unpooled outcome (pool 1,
  the same decision and rules) excludes it: another motion, or a set that does not name it.

Run from the repository root with a development install::

    python -m research.spill --out DIR [--bscans N] [--volumes N]

It writes ``DIR/spill-rules.json`` and ``.md`` (the recorded run: ``research/results/spill-rules.*``).
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

#: Thresholds of the ``mixed-box`` and ``shape-box`` candidates (mean excess over rule 8's box).
BOX_THRESHOLDS = (0.1, 0.2)
SHAPE_BOX_THRESHOLDS = (0.2, 0.3)
#: The shortest lag's correlation under which the decay's shape is not compared (``shape`` candidates).
SHAPE_FLOOR = 0.2
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
    same spatial shape."""
    from numpy.lib.stride_tricks import sliding_window_view

    pads = [(w // 2, w // 2) for w in window]
    axes = tuple(range(-len(window), 0))
    v = sliding_window_view(np.pad(np.where(valid, values, 0.0), pads), window)
    n = sliding_window_view(np.pad(valid.astype(float), pads), window)
    total, count = v.sum(axis=axes), n.sum(axis=axes)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def decay_excess(x: np.ndarray, columns: Sequence[Mapping[str, Any]], finest: str, floor: float | None = None):
    """Per input row, the largest over the coarser configurations of the mean over the lags both read of the
    finest configuration's pooled intensity correlation minus the coarser one's (``rho_lin_m``; rule 9's excess,
    :func:`classifier.ambiguity.mixed_footprint`); ``None`` when the model reads no common lag.

    With ``floor``, each correlation is first divided by its own at the shortest common lag ``m₁`` and the mean
    runs over the lags after it: noise independent from frame to frame lowers every correlation at a lag of a
    frame or more by one factor (physics.md §8), which a configuration's own SNR sets (a coarser one averages
    more noise away and sits higher by it), and the ratio ``ρ(m)/ρ(m₁)`` is free of it. A row whose correlation
    at ``m₁`` is below ``floor`` in either configuration (decorrelated, or under the noise, within the first
    lag: no decay shape to compare) gets NaN for that pair."""
    if floor is None:
        from classifier.ambiguity import mixed_footprint

        return mixed_footprint(np.zeros(len(x), int), _CLASSES, columns, x, finest)[1]
    lags: dict[str, dict[int, int]] = {}
    for j, col in enumerate(columns[:-1]):
        metric = str(col.get("metric", ""))
        if metric.startswith("rho_lin_") and col.get("configuration") is not None:
            lags.setdefault(str(col["configuration"]), {})[int(metric.removeprefix("rho_lin_"))] = j
    fine = lags.get(finest, {})
    x = np.asarray(x, np.float64)
    per_pair = []
    for conf, cols in lags.items():
        common = sorted(set(cols) & set(fine))
        if conf == finest or len(common) < 2:
            continue
        f1, c1 = x[:, fine[common[0]]], x[:, cols[common[0]]]
        ok = (f1 >= floor) & (c1 >= floor)
        f1, c1 = np.where(ok, f1, 1.0), np.where(ok, c1, 1.0)
        shape = np.mean([x[:, fine[m]] / f1 - x[:, cols[m]] / c1 for m in common[1:]], axis=0)
        per_pair.append(np.where(ok, shape, np.nan))
    if not per_pair:
        return None
    stacked = np.array(per_pair)
    out = np.full(stacked.shape[1], np.nan)
    some = np.isfinite(stacked).any(axis=0)
    out[some] = np.nanmax(stacked[:, some], axis=0)
    return out


def excess_maps(maps, features: np.ndarray, model, labels: np.ndarray, pool: int, finest: str) -> dict[str, np.ndarray]:
    """:func:`decay_excess` against the configuration ``finest``, raw (``mixed``) and on the decay's shape
    (``shape``, at :data:`SHAPE_FLOOR`), per pixel of a classification's spatial shape (NaN where it classified
    nothing or the excess is undefined), from the model inputs ``classify_maps`` builds at ``pool`` out of
    ``features`` (:func:`classifier.matching.assemble_features` of ``maps``, made once per map)."""
    from classifier.outputs import MASKED
    from classifier.pooling import independent_fraction, model_inputs

    valid = labels != MASKED
    frac = independent_fraction(int(pool), maps.meta.get("pitch_um"), model.spec)
    x, idx = model_inputs(features, valid, int(pool), frac, model.pool_pixels_max)
    out = {}
    for name, floor in (("mixed", None), ("shape", SHAPE_FLOOR)):
        grid = np.full(labels.size, np.nan)
        e = decay_excess(x, model.columns, finest, floor)
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
            keys = ("right", "right_of", "wrong", "wrong_of", "right_interior", "right_interior_of")
            f = {k: sum(r["flagged"].get(k, 0) for r in rows) for k in keys}
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


def main(argv: list[str] | None = None) -> int:
    from tqdm.auto import tqdm

    from classifier.bench.random_phantoms import N_BSCANS, N_VOLUMES, check_counts
    from classifier.infer import load_model

    p = argparse.ArgumentParser(prog="python -m research.spill", description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--bscans", type=int, default=N_BSCANS, help=f"B-scan draws (default {N_BSCANS})")
    p.add_argument("--volumes", type=int, default=N_VOLUMES, help=f"volume draws (default {N_VOLUMES})")
    args = p.parse_args(argv)
    try:
        check_counts(args.bscans, args.volumes)
    except ValueError as err:
        p.error(str(err))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
    (out / "spill-rules.json").write_text(json.dumps(result, separators=(",", ":")))
    (out / "spill-rules.md").write_text(to_markdown(result))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

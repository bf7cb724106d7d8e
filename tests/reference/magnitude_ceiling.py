"""The ceiling of the motion magnitude on independent data: how well the best regressor we could build
on the signature features recovers ``log10 D`` or ``log10 v`` of a pixel, and whether intervals
calibrated on a training prior keep their stated share on the independent set.

Run (from the repository root; reuses and fills the feature cache of :mod:`ceiling`)::

    python -m tests.reference.magnitude_ceiling --out DIR [--parts c,d,e] [--train-draws 1200]

Writes ``<out>/independent-magnitude-ceiling.json`` and ``.md`` (never over existing files without
``--force``) and prints a summary.

**What it measures.** The magnitude goals of issue 24 (per pixel, independent data: median
``|log10 error|`` ≤ 0.06; 68 % and 95 % intervals holding 65-71 % and 93-97 % of the pixels) are scored
on the head of the true class (:func:`classifier.evaluation.magnitude_metrics`). Here, per part of
:data:`ceiling.PARTS` (its training data, simulator and prior), one set of quantile regressors per
motion class and pool is trained on the identifiable training pixels of that class and scored on the
same independent test pixels as the shipped model (paired):

* regressors: ``sklearn.ensemble.HistGradientBoostingRegressor`` with the quantile (pinball) loss at
  the levels :data:`QUANTILES`: the conditional median (the estimate that minimises the expected
  ``|error|``) and the ends of the central 68.27 % and 95.45 % intervals (the shares a Gaussian's ±1
  and ±1.96 SD hold, the promise of the shipped model's intervals); inputs the raw features and their
  contrasts (:func:`ceiling.design`, the better inputs of the classification ceiling); :data:`GBR_PARAMS`,
  one thread, fixed seed; the intervals conformalised on a held-out quarter of the training draws
  (:func:`fit_quantiles`), so they hold their stated shares on the training prior. On a matched prior
  (parts a, c) the interval shares are what calibration can give on the independent set; on the models'
  own kind of prior (parts d, e) they show what the prior shift does to intervals calibrated honestly.
* the shipped model: its magnitude head (mean ± SD, ± 1.96 SD) on the same pixels.

A matched prior (parts a, c: the independent prior itself, the same magnitude ranges) is optimistic:
the regressor knows the ranges the test magnitudes are drawn from. Where even it stays above 0.06, the
goal lies beyond what the features hold at this pool size.

**Cost** (the default parts and sizes): the simulation of what :mod:`ceiling`'s cache lacks (the
reference-simulator test sets, part b's 1200 reference-simulator training draws, part c's torchdoct draws
and one :func:`ceiling.dataset_set` split per prior), then the fits of each part; a run interrupted during
the simulation resumes from the cache.

**Metrics** per pool (1 and 25, :data:`ceiling.POOLS`): median and mean ``|log10 error|`` of the median
regressor, the shares of the test pixels inside the 68 % and 95 % intervals, the median interval
half-width, the same per motion class; ± = bootstrap SE over test draws (:func:`evaluate_models._bootstrap`).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

try:  # run as `python -m tests.reference.magnitude_ceiling`
    from . import ceiling as ce
    from . import evaluate_models as em
except ImportError:  # imported by the tests (tests/reference on sys.path)
    import ceiling as ce
    import evaluate_models as em

__all__ = [
    "QUANTILES",
    "GBR_PARAMS",
    "CALIBRATION_SHARE",
    "fit_quantiles",
    "predict_quantiles",
    "interval_metrics",
    "run",
    "main",
]

#: Quantile levels: the median, the central 68.27 % interval, the central 95.45 % interval.
QUANTILES = (0.5, 0.158655, 0.841345, 0.02275, 0.97725)
#: Stated shares of the two central intervals.
LEVELS = (("coverage_68", 0.6827), ("coverage_95", 0.9545))
GBR_PARAMS = {
    "max_iter": 400,
    "learning_rate": 0.1,
    "max_leaf_nodes": 31,
    "min_samples_leaf": 40,
    "l2_regularization": 1.0,
    "early_stopping": True,
    "validation_fraction": 0.15,
    "n_iter_no_change": 20,
}
#: Share of the training draws held out to conformalise the intervals (:func:`fit_quantiles`).
CALIBRATION_SHARE = 0.25
DEFAULT_PARTS = ("c", "d", "e", "e-noise", "e-nostatic-noise", "b", "b-int", "f", "f-int")
DEFAULT_TRAIN_DRAWS = 1200
_CLASSES = ("diffusion", "ballistic", "flow")


def fit_quantiles(x: np.ndarray, target: np.ndarray, group: np.ndarray | None = None, seed: int = 0) -> dict[str, Any]:
    """Conformalised quantile regression (Romano, Patterson and Candès, NeurIPS 2019) of ``target``
    (log10 magnitude, ``[N]``) on ``x`` ``[N, F]``.

    One ``HistGradientBoostingRegressor`` (quantile loss, :data:`GBR_PARAMS`, one thread) per level of
    :data:`QUANTILES` is fitted on the samples outside a held-out share :data:`CALIBRATION_SHARE` of the
    groups ``group`` (draws: a draw's pixels share their magnitude, so they are held out together; every
    sample its own group without ``group``). Boosted tails converge slowly (a fitted 95.45 % interval held
    93 % of a Gaussian), so each interval is then widened (or narrowed) by the conformity score
    ``max(lo − t, t − hi)`` at its level on the held-out samples: its share holds on the fitting prior up to
    the held-out sample's binomial error. Returns ``{"models", "corrections"}``."""
    from sklearn.ensemble import HistGradientBoostingRegressor
    from threadpoolctl import threadpool_limits

    target = np.asarray(target, np.float64)
    if len(target) < 50:
        raise ValueError(f"too few training samples for the quantile regressors ({len(target)}; need >= 50)")
    g = np.arange(len(target)) if group is None else np.asarray(group)
    ids = np.unique(g)
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(7,)))
    held = np.isin(g, rng.choice(ids, size=max(1, int(round(CALIBRATION_SHARE * len(ids)))), replace=False))
    if held.all() or not held.any():
        raise ValueError("the quantile regressors need at least two groups (draws) of training samples")
    with threadpool_limits(1):
        models = [
            HistGradientBoostingRegressor(loss="quantile", quantile=q, random_state=int(seed), **GBR_PARAMS).fit(
                x[~held], target[~held]
            )
            for q in QUANTILES
        ]
    pred = predict_quantiles({"models": models, "corrections": (0.0, 0.0)}, x[held])
    t = target[held]
    corrections = []
    for (lo, hi), (_, p) in zip(((1, 2), (3, 4)), LEVELS):
        score = np.sort(np.maximum(pred[:, lo] - t, t - pred[:, hi]))
        k = min(int(math.ceil((len(score) + 1) * p)), len(score)) - 1
        corrections.append(float(score[k]))
    return {"models": models, "corrections": tuple(corrections)}


def predict_quantiles(fit: dict[str, Any], x: np.ndarray) -> np.ndarray:
    """``[N, 5]``: the median and the interval ends in the order of :data:`QUANTILES`, each interval moved
    out by its correction; each interval's ends sorted, the median kept inside the 68 % interval and the
    68 % inside the 95 % (quantile fits can cross)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        q = np.stack([m.predict(x) for m in fit["models"]], axis=1)
    c68, c95 = fit["corrections"]
    lo68, hi68 = np.minimum(q[:, 1], q[:, 2]) - c68, np.maximum(q[:, 1], q[:, 2]) + c68
    lo68, hi68 = np.minimum(lo68, hi68), np.maximum(lo68, hi68)
    med = np.clip(q[:, 0], lo68, hi68)
    lo95 = np.minimum(np.minimum(q[:, 3], q[:, 4]) - c95, lo68)
    hi95 = np.maximum(np.maximum(q[:, 3], q[:, 4]) + c95, hi68)
    return np.stack([med, lo68, hi68, lo95, hi95], axis=1)


def interval_metrics(
    pred: np.ndarray, truth: np.ndarray, label: np.ndarray, draw: np.ndarray, *, n_boot: int, seed: int
) -> dict[str, Any]:
    """Median and mean ``|pred[:, 0] − truth|``, the shares of ``truth`` inside ``[pred[:, 1], pred[:, 2]]``
    (``coverage_68``) and ``[pred[:, 3], pred[:, 4]]`` (``coverage_95``), the median half-widths, per
    motion class ``label`` too, with bootstrap SEs over ``draw``."""
    err = np.abs(pred[:, 0] - truth)
    in68 = (truth >= pred[:, 1]) & (truth <= pred[:, 2])
    in95 = (truth >= pred[:, 3]) & (truth <= pred[:, 4])

    def scalars(i: np.ndarray) -> dict[str, float]:
        d = {
            "median_abs_log10_error": float(np.median(err[i])),
            "coverage_68": float(np.mean(in68[i])),
            "coverage_95": float(np.mean(in95[i])),
        }
        for c, name in enumerate(_CLASSES):
            m = label[i] == c
            if np.any(m):
                d[f"{name}:median_abs_log10_error"] = float(np.median(err[i][m]))
                d[f"{name}:coverage_68"] = float(np.mean(in68[i][m]))
        return d

    out: dict[str, Any] = {
        "samples": int(len(err)),
        **scalars(np.arange(len(err))),
        "mean_abs_log10_error": float(err.mean()),
        "median_half_width_68": float(np.median(pred[:, 2] - pred[:, 1]) / 2),
        "median_half_width_95": float(np.median(pred[:, 4] - pred[:, 3]) / 2),
    }
    out["by_class"] = {}
    for c, name in enumerate(_CLASSES):
        m = label == c
        if np.any(m):
            out["by_class"][name] = {
                "samples": int(m.sum()),
                "median_abs_log10_error": float(np.median(err[m])),
                "coverage_68": float(np.mean(in68[m])),
                "coverage_95": float(np.mean(in95[m])),
            }
    if n_boot >= 2:
        out["se"] = em._bootstrap(scalars, draw, n_boot, seed)
    return out


def _shipped_intervals(mdl, spec, x: np.ndarray, pool: int, label: np.ndarray) -> np.ndarray:
    """The shipped model's head of the true class as ``[N, 5]`` (mean; mean ∓ SD; mean ∓ 1.96 SD)."""
    names = list(mdl.spec.feature_names)
    cols = [list(spec.feature_names).index(n) for n in names]
    xx = np.concatenate([x[:, cols], np.full((len(x), 1), float(pool), np.float32)], axis=1)
    _, mean, sd = mdl.predict_all(xx, magnitude=True)
    if mean is None:
        raise ValueError(f"shipped model {mdl.path.name} has no magnitude head")
    rows = np.arange(len(label))
    mu, s = mean[rows, label].astype(np.float64), sd[rows, label].astype(np.float64)
    return np.stack([mu, mu - s, mu + s, mu - 1.959964 * s, mu + 1.959964 * s], axis=1)


def _identifiable(s: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = s["status"] == 0
    return {k: v[keep] for k, v in s.items() if isinstance(v, np.ndarray) and len(v) == len(keep)}


def run(
    out: Path,
    parts: Sequence[str],
    *,
    train_draws: int,
    test_draws: int,
    trials: int,
    train_seed: int,
    test_seed: int,
    n_boot: int,
    progress: bool,
) -> dict[str, Any]:
    """Simulate what is missing (the :mod:`ceiling` caches), fit and score every part; the report."""
    from classifier.features import load_spec

    t0 = time.perf_counter()
    epsilon = float(ce._shipped(ce.SHIPPED["a"]).rule["epsilon"])
    for c, n in ce.caches_for(
        out,
        parts,
        sizes=[train_draws],
        test_draws=test_draws,
        trials=trials,
        train_seed=train_seed,
        test_seed=test_seed,
        epsilon=epsilon,
    ):
        c.fill(n, None, progress)
    sim_s = time.perf_counter() - t0
    results: dict[str, Any] = {}
    for p in parts:
        spec_name, source, which, prior = ce.PARTS[p]
        spec = load_spec(spec_name)
        cols = ce.part_columns(spec, which)
        test = ce.load_set(ce.FeatureCache(out / "cache", spec, "refsim", test_seed, trials, epsilon), test_draws)
        if prior in ce.DATASET_PRIORS:
            train_all = ce.dataset_set(out, spec, prior, train_seed, train_draws, trials, epsilon, progress=progress)
        else:
            train_all = ce.load_set(
                ce.FeatureCache(out / "cache", spec, source, train_seed, trials, epsilon, prior), train_draws
            )
        keep = (train_all.draw < train_draws) & (train_all.status == 0)
        train = ce.subset(train_all, np.flatnonzero(keep))
        mdl = ce._shipped(ce.SHIPPED[p])
        t1 = time.perf_counter()
        res: dict[str, Any] = {
            "spec": spec_name,
            "train_source": source,
            "train_prior": prior,
            "shipped": ce.SHIPPED[p],
            "text": ce.PART_TEXT[p],
            "pools": {},
        }
        for pool in ce.POOLS:
            ts = _identifiable(ce.pool_samples(test, pool, test_seed))
            trs = ce.pool_samples(train, pool, train_seed, per_draw=ce.TRAIN_POOLED_PER_DRAW)
            truth = np.log10(ts["magnitude"])
            pred = np.full((len(truth), len(QUANTILES)), np.nan)
            for c in range(len(_CLASSES)):
                m, mt = ts["y"] == c, trs["y"] == c
                models = fit_quantiles(
                    ce.design(spec, trs["x"][mt], cols, True),
                    np.log10(trs["magnitude"][mt]),
                    trs["draw"][mt],
                    seed=train_seed,
                )
                pred[m] = predict_quantiles(models, ce.design(spec, ts["x"][m], cols, True))
            shipped = _shipped_intervals(mdl, spec, ts["x"], pool, ts["y"])
            res["pools"][str(pool)] = {
                "test_samples": int(len(truth)),
                "train_samples": int(len(trs["y"])),
                "quantile_gb": interval_metrics(pred, truth, ts["y"], ts["draw"], n_boot=n_boot, seed=test_seed),
                "shipped": interval_metrics(shipped, truth, ts["y"], ts["draw"], n_boot=n_boot, seed=test_seed),
            }
        res["fit_seconds"] = time.perf_counter() - t1
        if prior in ce.DATASET_PRIORS:
            res["train_prior_fields"] = ce.dataset_prior(prior, spec, epsilon).to_dict()
        results[p] = res
    import sklearn

    import classifier
    import torchdoct

    return {
        "versions": {
            "classifier": classifier.__version__,
            "torchdoct": torchdoct.__version__,
            "sklearn": sklearn.__version__,
        },
        "command": command_line(parts, train_draws, test_draws, trials, train_seed, test_seed, n_boot),
        "test_seed": int(test_seed),
        "train_seed": int(train_seed),
        "test_draws": int(test_draws),
        "train_draws": int(train_draws),
        "trials_per_draw": int(trials),
        "pools": list(ce.POOLS),
        "quantiles": list(QUANTILES),
        "gbr_params": GBR_PARAMS,
        "n_boot": int(n_boot),
        "prior": em.PRIOR_TEXT,
        "simulation": em.SIM_TEXT,
        "targets": em.TARGETS["magnitude_pool_1"],
        "parts": results,
        "seconds": {"simulation": sim_s, "fits": {p: r["fit_seconds"] for p, r in results.items()}},
    }


def command_line(parts, train_draws, test_draws, trials, train_seed, test_seed, n_boot) -> str:
    return (
        f"python -m tests.reference.magnitude_ceiling --out DIR --parts {','.join(parts)} --train-draws "
        f"{train_draws} --test-draws {test_draws} --trials {trials} --train-seed {train_seed} --test-seed "
        f"{test_seed} --boot {n_boot}"
    )


def _f(v: Any, d: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def _pm(r: dict[str, Any], key: str) -> str:
    se = r.get("se", {}).get(key)
    return _f(r.get(key)) + ("" if se is None else f" ± {se:.3f}")


def format_markdown(rep: dict[str, Any]) -> str:
    t = rep["targets"]
    cmd = rep["command"]
    L = [
        "# The ceiling of the motion magnitude on independent data",
        "",
        f"Test set: {rep['test_draws']} draws × {rep['trials_per_draw']} pixels of the independent prior, seed "
        f"{rep['test_seed']} (the set of the `*-independent.md` reports), {rep['simulation']}; identifiable pixels, "
        f"the head of the true class. Prior: {rep['prior']}.",
        "",
        f"Regressors: per part, pool and motion class, HistGradientBoostingRegressor with the quantile loss at "
        f"{', '.join(f'{q:g}' for q in rep['quantiles'])} (the conditional median and the ends of the central "
        "68.27 % and 95.45 % intervals; "
        + ", ".join(f"{k}={v}" for k, v in rep["gbr_params"].items())
        + f"; one thread), trained on the identifiable pixels of the first {rep['train_draws']} draws of the part's "
        f"training data (seed {rep['train_seed']}), inputs the features and their contrasts (`ceiling.design`). "
        "The shipped model: its head of the true class, mean ± SD and ± 1.96 SD, on the same pixels. ± = "
        f"bootstrap SE over test draws ({rep['n_boot']} resamples).",
        "",
        f"Every number below comes from one command: `{cmd}` (DIR: any directory; the features are cached there "
        "and shared with `tests.reference.ceiling`).",
        "",
        f"## Pool 1 (goals: median |log10 error| ≤ {t['median_abs_log10_error']}, 68 % interval holding "
        f"{t['coverage_68'][0]}-{t['coverage_68'][1]}, 95 % holding {t['coverage_95'][0]}-{t['coverage_95'][1]})",
        "",
        "| part | training prior | model | median abs. log10 error | diffusion / ballistic / flow | 68 % coverage "
        "| 95 % coverage | median half-width 68 % |",
        "|---|---|---|---:|---|---:|---:|---:|",
    ]

    def row(p: str, res: dict[str, Any], pool: str) -> list[str]:
        rows = []
        for key, name in (("quantile_gb", "quantile GB"), ("shipped", f"shipped `{res['shipped']}`")):
            r = res["pools"][pool][key]
            rows.append(
                f"| {p} | {res['train_prior']} | {name} | {_pm(r, 'median_abs_log10_error')} | "
                + " / ".join(_f(r["by_class"].get(c, {}).get("median_abs_log10_error")) for c in _CLASSES)
                + f" | {_pm(r, 'coverage_68')} | {_pm(r, 'coverage_95')} | {_f(r['median_half_width_68'])} |"
            )
        return rows

    for p, res in rep["parts"].items():
        L += row(p, res, "1")
    L += ["", "Parts: " + "; ".join(f"**{p}** {res['text']}" for p, res in rep["parts"].items()) + ".", ""]
    L += findings(rep) + [""]
    L += [
        "## Pool 25",
        "",
        "| part | training prior | model | median abs. log10 error | diffusion / ballistic / "
        "flow | 68 % coverage | 95 % coverage | median half-width 68 % |",
        "|---|---|---|---:|---|---:|---:|---:|",
    ]
    for p, res in rep["parts"].items():
        L += row(p, res, "25")
    L += [
        "",
        "## 68 % coverage by motion class (pool 1)",
        "",
        "| part | model | diffusion | ballistic | flow |",
        "|---|---|---:|---:|---:|",
    ]
    for p, res in rep["parts"].items():
        for key, name in (("quantile_gb", "quantile GB"), ("shipped", f"shipped `{res['shipped']}`")):
            bc = res["pools"]["1"][key]["by_class"]
            L.append(f"| {p} | {name} | " + " | ".join(_f(bc.get(c, {}).get("coverage_68")) for c in _CLASSES) + " |")
    L += [
        "",
        f"Reproduce: `{cmd}`.",
        "",
        f"Cost: simulation of what was not cached {rep['seconds']['simulation']:.0f} s; fits and scores (wall) "
        + ", ".join(f"{p} {v:.0f} s" for p, v in rep["seconds"]["fits"].items())
        + ".",
        "",
    ]
    return "\n".join(L)


def _inside(v: float, band: tuple[float, float]) -> str:
    return "inside" if band[0] <= v <= band[1] else ("above" if v > band[1] else "below")


def findings(rep: dict[str, Any]) -> list[str]:
    """What the pool-1 numbers say against the goals, per part (generated from the numbers)."""
    t = rep["targets"]
    L = ["## What it shows (pool 1)", ""]
    for p, res in rep["parts"].items():
        g, s = res["pools"]["1"]["quantile_gb"], res["pools"]["1"]["shipped"]
        err, c68, c95 = g["median_abs_log10_error"], g["coverage_68"], g["coverage_95"]
        kind = (
            "the matched prior: the best the features give when the test prior is known"
            if res["train_prior"] in ("matched", "shared")
            else "a prior a model for unknown samples can be trained on: intervals calibrated honestly on it"
        )
        L.append(
            f"- **{p}** ({kind}): median |log10 error| {err:.3f} ± {g.get('se', {}).get('median_abs_log10_error', 0):.3f} "
            f"({'meets' if err <= t['median_abs_log10_error'] else 'above'} the goal "
            f"{t['median_abs_log10_error']}); 68 % / 95 % intervals hold {c68:.3f} / {c95:.3f} "
            f"({_inside(c68, t['coverage_68'])} / {_inside(c95, t['coverage_95'])} "
            f"{t['coverage_68'][0]}-{t['coverage_68'][1]} / {t['coverage_95'][0]}-{t['coverage_95'][1]}); "
            f"shipped `{res['shipped']}` on the same pixels {s['median_abs_log10_error']:.3f}, "
            f"{s['coverage_68']:.3f} / {s['coverage_95']:.3f}."
        )
    return L


def _summary(rep: dict[str, Any]) -> str:
    lines = []
    for p, res in rep["parts"].items():
        for key in ("quantile_gb", "shipped"):
            r = res["pools"]["1"][key]
            lines.append(
                f"part {p} ({res['train_prior']}) {key}: pool 1 median |log10 error| "
                f"{r['median_abs_log10_error']:.3f}, 68 % / 95 % coverage {r['coverage_68']:.3f} / "
                f"{r['coverage_95']:.3f}"
            )
    return "\n".join(lines)


def write_report(rep: dict[str, Any], out: Path, force: bool = False) -> list[Path]:
    return ce.write_files(rep, out, "independent-magnitude-ceiling", format_markdown(rep), force)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tests.reference.magnitude_ceiling",
        description="Ceiling of the motion magnitude on the independent data: quantile "
        "gradient boosting per motion class. Writes "
        "<out>/independent-magnitude-ceiling.json and .md.",
    )
    ap.add_argument("--out", required=True, help="output directory (also holds the feature cache, <out>/cache)")
    ap.add_argument("--parts", default=",".join(DEFAULT_PARTS), help=f"parts among {list(ce.PARTS)}")
    ap.add_argument("--train-draws", type=int, default=DEFAULT_TRAIN_DRAWS)
    ap.add_argument("--test-draws", type=int, default=ce.DEFAULT_TEST_DRAWS)
    ap.add_argument("--trials", type=int, default=em.DEFAULT_TRIALS)
    ap.add_argument("--train-seed", type=int, default=1)
    ap.add_argument("--test-seed", type=int, default=0)
    ap.add_argument("--boot", type=int, default=ce.N_BOOT)
    ap.add_argument("--force", action="store_true", help="overwrite existing report files")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        parts = [p.strip() for p in args.parts.split(",") if p.strip()]
        bad = [p for p in parts if p not in ce.PARTS]
        if bad or not parts:
            raise ValueError(f"--parts: unknown {bad or 'none given'}; choose among {list(ce.PARTS)}")
        if args.train_draws < 3 or args.test_draws < 3 or args.trials < 25 or args.boot < 0:
            raise ValueError("--train-draws and --test-draws must be >= 3, --trials >= 25 (pool 25), --boot >= 0")
        if args.train_seed == args.test_seed:
            raise ValueError("--train-seed must differ from --test-seed (training draws disjoint from the test draws)")
        out = Path(args.out)
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out} is a file; give a directory")
        out.mkdir(parents=True, exist_ok=True)
        import torch

        torch.set_num_threads(1)
        rep = run(
            out,
            parts,
            train_draws=args.train_draws,
            test_draws=args.test_draws,
            trials=args.trials,
            train_seed=args.train_seed,
            test_seed=args.test_seed,
            n_boot=args.boot,
            progress=not args.no_progress,
        )
        paths = write_report(rep, out, force=args.force)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(_summary(rep))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())

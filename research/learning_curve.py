"""Learning curve of the ``signature`` classifier: test accuracy against the number of training draws.

``python -m research.learning_curve --out signature-learning-curve.json`` takes the ``signature``
spec and its shipped recipe (:meth:`classifier.train.TrainConfig.for_spec`), simulates (or loads from
the dataset cache) one training split of ``draws_max`` draws (default 3840, twice the shipped 1920)
and the shipped model's validation and test splits (the recipe's numbers of draws, seed 0), and trains the network
with the shipped recipe and seed (:func:`classifier.train.fit_network`) on nested prefixes of the
training draws (default 60, 120, 240, 480, 960, 1920, 3840). A prefix of ``n`` draws is exactly the
``n``-draw training split of :func:`classifier.dataset.make_dataset` (a split's draws do not depend on
how many are made, and the golden-ratio magnitude sequence covers the range evenly at every prefix).
Every model is evaluated on the same test samples as ``doct-train`` (pool 1 and pool 25 pixels):
balanced accuracy and coverage on identifiable pixels after the indeterminate rule of
:mod:`classifier.rule`, ECE, and the median absolute log10 error of the magnitude head; standard
errors from a bootstrap over test draws (:func:`classifier.report.bootstrap_se`); the training time.
Histogram gradient boosting (the report's baseline: 300 iterations, fixed seed, on the model's input
transform) is fitted at the same sizes on at most ``gb_pixels`` samples drawn from the network's
first-epoch training samples (singles and pooled means), so beyond that budget its curve measures
the variety of draws, not the number of pixels. Where the curve flattens is judged by the change of
balanced accuracy between the two largest sizes against its standard error from a paired bootstrap
over test draws (both models on the same resampled draws); one training seed, so the seed-to-seed
spread of the network is not part of that error.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_SIZES",
    "draw_prefix",
    "run_learning_curve",
    "format_markdown",
    "plot_learning_curve",
    "write_outputs",
    "main",
]

#: Default nested training sizes (draws); the shipped recipe uses 1920.
DEFAULT_SIZES = (60, 120, 240, 480, 960, 1920, 3840)
_POOLS = ("1", "25")
_SUFFIXES = (".json", ".md", ".png")


def draw_prefix(ds, n: int):
    """The samples of draws ``0 .. n-1`` of a split (:class:`classifier.dataset.Dataset`), in order."""
    keep = ds.draw < int(n)
    arrays = {k: v[keep] for k, v in ds.arrays().items()}
    meta = {**ds.meta, "draws": int(n), "prefix_of": ds.meta.get("draws")}
    return dataclasses.replace(ds, **arrays, meta=meta, x_ref=None if ds.x_ref is None else ds.x_ref[keep])


def _check_sizes(sizes: Sequence[int], draws_max: int | None) -> tuple[tuple[int, ...], int]:
    sizes = tuple(sizes)
    if not sizes:
        raise ValueError("--sizes: give at least one training size (draws), e.g. --sizes 60,120,240")
    for s in sizes:
        if isinstance(s, bool) or not isinstance(s, int) or s < 3:
            raise ValueError(f"--sizes: every size must be an integer >= 3 draws (one per motion type); got {s!r}")
    if any(b <= a for a, b in zip(sizes, sizes[1:])):
        raise ValueError(f"--sizes must increase strictly; got {list(sizes)}")
    n_max = sizes[-1] if draws_max is None else int(draws_max)
    if n_max < sizes[-1]:
        raise ValueError(f"--draws-max ({n_max}) must be >= the largest size ({sizes[-1]})")
    return sizes, n_max


def _magnitude_errors(
    magnitude: tuple[np.ndarray, np.ndarray] | None, s: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """|log10 magnitude error| of the true class's head on identifiable samples, and their draws
    (``magnitude``: the network's predicted ``(log10 magnitude, SD)``, :func:`classifier.train.network_predictions`)."""
    ident = s["status"] == 0
    if magnitude is None or not ident.any():
        return np.zeros(0), np.zeros(0, np.int64)
    y = s["y"][ident]
    m = magnitude[0][ident][np.arange(len(y)), y].astype(np.float64)
    return np.abs(m - np.log10(s["magnitude"][ident])), s["draw"][ident]


def _bootstrap(stat, draw: np.ndarray, *, n_boot: int = 200, seed: int = 0) -> float:
    """SD of ``stat(index)`` over resamples of the draws (NaN with < 2 draws or < 2 finite values;
    :func:`classifier.evaluation.bootstrap_draws`)."""
    from classifier.evaluation import bootstrap_draws

    return bootstrap_draws(lambda i: {"stat": stat(i)}, draw, n_boot=n_boot, seed=seed).get("stat", math.nan)


_KEYS = ("balanced_accuracy_identifiable", "coverage_identifiable", "ece")


def _metrics(p: np.ndarray, s: dict[str, np.ndarray], rule: dict, seed: int) -> dict[str, float]:
    """Balanced accuracy, coverage (identifiable) and ECE with their bootstrap SEs: the metrics block of
    every test set (:func:`classifier.evaluation.evaluate_set`)."""
    from classifier.evaluation import evaluate_set

    block = evaluate_set(p, s, rule, seed=seed)
    m, se = block["metrics"], block["standard_errors"]
    out: dict[str, float] = {}
    for k in _KEYS:
        out[k] = float(m[k])
        out[k + "_se"] = float(se[k])
    return out


def _paired_difference(
    p_a: np.ndarray,
    p_b: np.ndarray,
    s: dict[str, np.ndarray],
    rule: dict,
    seed: int,
    key: str = "balanced_accuracy_identifiable",
) -> tuple[float, float]:
    """``metric(p_b) − metric(p_a)`` on the same samples and its SE (both on the same resampled draws)."""
    from classifier.evaluation import CLASS_NAMES
    from classifier.report import evaluate

    def diff(i):
        return (
            evaluate(p_b[i], s["y"][i], s["status"][i], CLASS_NAMES, rule)[key]
            - evaluate(p_a[i], s["y"][i], s["status"][i], CLASS_NAMES, rule)[key]
        )

    return float(diff(np.arange(len(s["y"])))), _bootstrap(diff, s["draw"], seed=seed)


def run_learning_curve(
    *,
    sizes: Sequence[int] = DEFAULT_SIZES,
    draws_max: int | None = None,
    draws_validation: int | None = None,
    draws_test: int | None = None,
    max_epochs: int | None = None,
    gb_pixels: int = 60000,
    seed: int = 0,
    cache_dir=None,
    progress: bool = False,
    log=print,
) -> dict[str, Any]:
    """The study of the module docstring; returns a JSON-able dict (``rows``: one per size).

    ``progress``: progress bars (stderr) for the simulation and the epochs; ``log``: one line per stage."""
    import torch

    import torchdoct
    from classifier import __version__
    from classifier.dataset import make_dataset
    from classifier.features import load_spec
    from classifier.prior import Prior
    from classifier.rule import make_rule
    from classifier.train import (
        CLASS_NAMES,
        TrainConfig,
        class_targets,
        evaluation_sets,
        feature_masks,
        fit_network,
        network_predictions,
        transform_numpy,
    )
    from classifier.truth import STATUS

    say = log or (lambda *a, **k: None)
    sizes, n_max = _check_sizes(sizes, draws_max)
    over: dict[str, Any] = {"seed": seed, "draws_train": n_max}
    if draws_validation is not None:
        over["draws_validation"] = draws_validation
    if draws_test is not None:
        over["draws_test"] = draws_test
    if max_epochs is not None:
        over["max_epochs"] = max_epochs
    cfg = TrainConfig.for_spec("signature", **over)
    if isinstance(gb_pixels, bool) or not isinstance(gb_pixels, int) or gb_pixels < 0:
        raise ValueError(f"--gb-pixels must be a non-negative integer (0: no gradient boosting); got {gb_pixels!r}")
    spec = load_spec(cfg.spec)
    prior = Prior()
    rule = make_rule(prior.identifiability_epsilon, cfg.min_probability)

    data, sim_s = {}, {}
    for split, n in (("train", n_max), ("validation", cfg.draws_validation), ("test", cfg.draws_test)):
        say(f"{split}: {n} draws ...", flush=True)
        ds = make_dataset(
            spec,
            prior,
            seed=cfg.seed,
            split=split,
            draws=n,
            trials_per_draw=cfg.trials_per_draw,
            replicates=cfg.replicates,
            truncation_tolerance=cfg.truncation_tolerance,
            truncation=cfg.truncation,
            cache_dir=cache_dir,
            progress=progress,
        )
        data[split] = ds
        sim_s[split] = float(ds.meta["elapsed_s"])
        say(
            f"{split}: {len(ds)} samples ({'from the cache; ' if ds.meta['from_cache'] else ''}simulated in "
            f"{ds.meta['elapsed_s']:.0f} s); ground truth per draw {ds.meta['draw_status_counts']}",
            flush=True,
        )

    ev_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(9,)))  # as doct-train
    tests, _ = evaluation_sets(data["test"], cfg, spec, ev_rng)
    tests = {p: tests[p] for p in _POOLS if p in tests}
    mask, cmask = feature_masks(spec)

    rows: list[dict[str, Any]] = []
    probs: dict[int, dict[str, np.ndarray]] = {}
    for n in sizes:
        tr = draw_prefix(data["train"], n)
        per_draw = tr.status[np.unique(tr.draw, return_index=True)[1]]  # ground truth of each draw
        row: dict[str, Any] = {
            "draws": n,
            "samples": len(tr),
            "draw_status_counts": {name: int((per_draw == i).sum()) for i, name in enumerate(STATUS)},
        }
        fit = fit_network(tr, data["validation"], spec, cfg, progress=progress)
        model = fit["model"]
        net: dict[str, Any] = {
            "training_s": fit["training_s"],
            "epochs": fit["epochs"],
            "best_epoch": fit["best_epoch"],
            "validation_loss": fit["validation_loss"],
            "temperature": fit["temperature"],
        }
        probs[n] = {}
        for pool, s in tests.items():
            p, mag = network_predictions(model, s, magnitude=model.n_magnitude > 0)
            probs[n][pool] = p
            m = _metrics(p, s, rule, cfg.seed)
            err, edraw = _magnitude_errors(mag, s)
            m["median_abs_log10_error"] = float(np.median(err)) if err.size else math.nan
            m["median_abs_log10_error_se"] = _bootstrap(lambda i: float(np.median(err[i])), edraw, seed=cfg.seed)
            net[pool] = m
        row["network"] = net
        say(
            f"{n} draws: network {fit['epochs']} epochs (best {fit['best_epoch']}), {fit['training_s']:.0f} s; "
            + "; ".join(
                f"pool {p}: balanced accuracy {net[p]['balanced_accuracy_identifiable']:.3f} "
                f"± {net[p]['balanced_accuracy_identifiable_se']:.3f}, coverage "
                f"{net[p]['coverage_identifiable']:.3f}"
                for p in tests
            ),
            flush=True,
        )
        if gb_pixels:
            from sklearn.ensemble import HistGradientBoostingClassifier

            s0 = fit["first_samples"]
            rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(11, n)))
            sub = np.sort(rng.choice(len(s0["x"]), min(gb_pixels, len(s0["x"])), replace=False))
            t0 = time.perf_counter()
            gb = HistGradientBoostingClassifier(max_iter=300, random_state=cfg.seed)
            gb.fit(transform_numpy(s0["x"][sub], mask, cmask), class_targets(s0)[sub])
            gbr: dict[str, Any] = {
                "training_s": time.perf_counter() - t0,
                "pixels": int(len(sub)),
                "iterations": int(gb.n_iter_),
            }
            full = np.eye(len(CLASS_NAMES))[gb.classes_]  # a class absent from the samples: p = 0
            for pool, s in tests.items():
                gbr[pool] = _metrics(gb.predict_proba(transform_numpy(s["x"], mask, cmask)) @ full, s, rule, cfg.seed)
            row["gradient_boosting"] = gbr
            say(
                f"{n} draws: gradient boosting on {len(sub)} samples, {gbr['training_s']:.0f} s; "
                + "; ".join(
                    f"pool {p}: balanced accuracy {gbr[p]['balanced_accuracy_identifiable']:.3f}" for p in tests
                ),
                flush=True,
            )
        rows.append(row)

    flat: dict[str, Any] = {}
    if len(sizes) >= 2:
        a, b = sizes[-2], sizes[-1]
        for pool, s in tests.items():
            d, se = _paired_difference(probs[a][pool], probs[b][pool], s, rule, cfg.seed)
            flat[pool] = {"from_draws": a, "to_draws": b, "difference": d, "difference_se": se}
    return _finite_or_none(
        {
            "method": " ".join(__doc__.split("\n\n")[1].split()),
            "classifier_version": __version__,
            "torchdoct_version": torchdoct.__version__,
            "torch_version": torch.__version__,
            "threads": torch.get_num_threads(),
            "spec": spec.name,
            "config": cfg.to_dict(),
            "prior": prior.to_dict(),
            "rule": rule,
            "seed": cfg.seed,
            "sizes": list(sizes),
            "draws_max": n_max,
            "draws_shipped": TrainConfig.for_spec("signature").draws_train,
            "draws_validation": cfg.draws_validation,
            "draws_test": cfg.draws_test,
            "test_samples": {p: int(len(s["y"])) for p, s in tests.items()},
            "gb_pixels": gb_pixels,
            "simulation_s": sim_s,
            "rows": rows,
            "flattening": flat,
        }
    )


def _finite_or_none(o: Any) -> Any:
    """NaN/inf (an undefined metric: no identifiable test pixel decided, or < 2 test draws) → None."""
    if isinstance(o, dict):
        return {k: _finite_or_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_none(v) for v in o]
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def _f(v: Any, digits: int = 3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def _pm(m: dict, key: str) -> str:
    if m[key] is None:
        return "n/a"
    return f"{_f(m[key])} ± {_f(m[key + '_se'])}"


def _markdown_text(rst: str) -> str:
    """Docstring markup as Markdown: ``:func:`~a.b``` and ````x```` become `` `a.b` `` and `` `x` ``."""
    import re

    return re.sub(r":\w+:`~?([^`]+)`", r"`\1`", rst).replace("``", "`")


def flattening_sentence(res: dict[str, Any]) -> str:
    """One sentence per pool: the change between the two largest sizes against its SE."""
    parts = []
    for pool, f in res["flattening"].items():
        d, se = f["difference"], f["difference_se"]
        if d is None or se is None:
            parts.append(
                f"at pool {pool} the change from {f['from_draws']} to {f['to_draws']} draws is undefined "
                "(a model decided no identifiable test pixel, or fewer than 2 test draws)"
            )
            continue
        if se <= 0:
            verdict = (
                "no bootstrap spread: the two models decide alike on every test draw"
                if d == 0
                else "no bootstrap spread"
            )
        elif abs(d) <= 2 * se:
            verdict = f"{abs(d) / se:.1f} SE from zero: flat at this test set's resolution"
        else:
            verdict = f"{abs(d) / se:.1f} SE from zero: not flat yet"
        parts.append(
            f"at pool {pool} balanced accuracy changes by {d:+.3f} ± {se:.3f} from {f['from_draws']} to "
            f"{f['to_draws']} draws ({verdict})"
        )
    if not parts:
        return "One training size only: no flattening can be judged."
    return (
        "Between the two largest training sizes "
        + "; ".join(parts)
        + " (paired bootstrap over test draws; one training seed)."
    )


def epoch_cap_sentence(res: dict[str, Any]) -> str:
    """Which sizes the recipe's epoch cap stopped before early stopping did (their accuracy is a lower bound)."""
    c = res["config"]
    capped = [
        r["draws"]
        for r in res["rows"]
        if r["network"]["epochs"] >= c["max_epochs"]
        and r["network"]["epochs"] - r["network"]["best_epoch"] < c["patience"]
    ]
    if not capped:
        return f"Early stopping (patience {c['patience']}) ended every training before the recipe's cap of {c['max_epochs']} epochs."
    return (
        f"The recipe's cap of {c['max_epochs']} epochs ended the training at {', '.join(map(str, capped))} draws "
        f"before early stopping (patience {c['patience']}) did (best epoch in the table): an epoch has fewer samples "
        "on fewer draws, so these points may also be limited by the number of optimisation steps (lower bounds "
        "where the best epoch is near the cap)."
    )


def format_markdown(res: dict[str, Any]) -> str:
    """The study as Markdown: method, one table per model, where the curve flattens."""
    c = res["config"]
    L = [
        f"# Learning curve of the `{res['spec']}` classifier",
        "",
        _markdown_text(res["method"]),
        "",
        f"Recipe: hidden {c['hidden']}, learning rate {c['learning_rate']}, weight decay {c['weight_decay']}, "
        f"at most {c['max_epochs']} epochs (patience {c['patience']}), seed {res['seed']}; each draw = "
        f"{c['replicates']} (static fraction, SNR) replicates × {c['trials_per_draw']} trials; validation "
        f"{res['draws_validation']} draws, test {res['draws_test']} draws ({res['test_samples'].get('1', 'n/a')} "
        f"pixels at pool 1); shipped model: {res['draws_shipped']} training draws. Simulation "
        + ", ".join(f"{k} {v:.0f} s" for k, v in res["simulation_s"].items())
        + f"; torch threads {res['threads']}.",
        "",
        "**" + flattening_sentence(res) + "**",
        "",
        epoch_cap_sentence(res),
        "",
        "## Network (shipped recipe)",
        "",
        "Balanced accuracy and coverage on identifiable pixels (ground truth), ± bootstrap SE over test draws "
        "(n/a: the model decided no identifiable test pixel); "
        "magnitude error: median |log10 D or v error| (µm²/s, µm/s) of the true class's head.",
        "",
        "| training draws | identifiable / static / decorrelated draws | pool | balanced accuracy | coverage | ECE "
        "| median abs. log10 magnitude error | epochs (best) | training [s] |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in res["rows"]:
        n = r["network"]
        for p in _POOLS:
            if p in n:
                counts = " / ".join(str(v) for v in r["draw_status_counts"].values())
                L.append(
                    f"| {r['draws']} | {counts} | {p} | {_pm(n[p], 'balanced_accuracy_identifiable')} | "
                    f"{_pm(n[p], 'coverage_identifiable')} | {_pm(n[p], 'ece')} | "
                    f"{_pm(n[p], 'median_abs_log10_error')} | {n['epochs']} ({n['best_epoch']}) | "
                    f"{n['training_s']:.1f} |"
                )
    L.append("")
    if any("gradient_boosting" in r for r in res["rows"]):
        L += [
            "## Gradient boosting (the report's baseline)",
            "",
            f"At most {res['gb_pixels']} training samples drawn from the network's first-epoch samples.",
            "",
            "| training draws | samples | pool | balanced accuracy | coverage | ECE | training [s] |",
            "|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in res["rows"]:
            g = r.get("gradient_boosting")
            if g is None:
                continue
            for p in _POOLS:
                if p in g:
                    L.append(
                        f"| {r['draws']} | {g['pixels']} | {p} | {_pm(g[p], 'balanced_accuracy_identifiable')} | "
                        f"{_pm(g[p], 'coverage_identifiable')} | {_pm(g[p], 'ece')} | {g['training_s']:.1f} |"
                    )
        L.append("")
    L.append(
        f"Versions: classifier {res['classifier_version']}, torchdoct {res['torchdoct_version']}, "
        f"torch {res['torch_version']}."
    )
    return "\n".join(L) + "\n"


def plot_learning_curve(res: dict[str, Any], path) -> None:
    """Balanced accuracy and coverage (pool 1 and 25) against training draws, log x, SE error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    x = np.array([r["draws"] for r in res["rows"]], dtype=float)
    for ax, key, label in (
        (axes[0], "balanced_accuracy_identifiable", "balanced accuracy, identifiable pixels"),
        (axes[1], "coverage_identifiable", "coverage: decided share of identifiable pixels"),
    ):
        for model, style, name in (("network", "-", "network"), ("gradient_boosting", "--", "gradient boosting")):
            if not all(model in r for r in res["rows"]):
                continue
            for pool, color, marker in (("1", "C0", "o"), ("25", "C1", "s")):
                if pool not in res["rows"][0][model]:
                    continue
                y = np.array([r[model][pool][key] for r in res["rows"]], dtype=float)  # None → NaN
                e = np.array([r[model][pool][key + "_se"] for r in res["rows"]], dtype=float)
                ax.errorbar(
                    x,
                    y,
                    yerr=np.nan_to_num(e),
                    fmt=marker + style,
                    color=color,
                    capsize=3,
                    alpha=1.0 if model == "network" else 0.6,
                    label=f"{name}, pool {pool} pixel(s)",
                )
        if x.min() <= res["draws_shipped"] <= x.max():
            ax.axvline(
                res["draws_shipped"], color="grey", ls=":", lw=1, label=f"shipped ({res['draws_shipped']} draws)"
            )
        ax.set_xscale("log")
        ax.set_xticks(x, [str(int(v)) for v in x])
        ax.minorticks_off()
        ax.set_xlabel(
            f"training draws (× {res['config']['replicates']} replicates × {res['config']['trials_per_draw']} trials)"
        )
        ax.set_ylabel(f"{label} (fraction)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"{res['spec']} classifier: test metrics against training size (error bars: bootstrap SE "
        f"over {res['draws_test']} test draws)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def output_paths(out) -> list[Path]:
    """The JSON file and the .md and .png beside it."""
    out = Path(out)
    return [out.with_suffix(s) for s in _SUFFIXES]


def check_outputs(out) -> list[Path]:
    """Refuse before any work: ``out`` must end in .json, its directory exist, and none of the three exist."""
    out = Path(out)
    if out.suffix != ".json":
        raise ValueError(f"--out must end in .json; got {str(out)!r}")
    if not out.parent.is_dir():
        raise ValueError(f"--out: directory {out.parent} does not exist; create it first")
    paths = output_paths(out)
    for p in paths:
        if p.exists():
            raise ValueError(f"--out: {p} exists; remove it or choose another --out (nothing was overwritten)")
    return paths


def write_outputs(res: dict[str, Any], out) -> list[Path]:
    """Write the JSON, Markdown and PNG files (each atomically)."""
    from torchdoct.files import atomic_write

    paths = check_outputs(out)

    def w_json(tmp: str) -> None:
        Path(tmp).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")

    atomic_write(paths[0], w_json)
    atomic_write(paths[1], lambda tmp: Path(tmp).write_text(format_markdown(res), encoding="utf-8"))
    atomic_write(paths[2], lambda tmp: plot_learning_curve(res, tmp))
    return paths


def _int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, e.g. 60,120,240; got {text!r}") from None


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.learning_curve", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="JSON output file (the .md and .png are written beside it)")
    p.add_argument(
        "--sizes",
        type=_int_list,
        default=list(DEFAULT_SIZES),
        help="nested training sizes in draws, increasing (default %(default)s)",
    )
    p.add_argument("--draws-max", type=int, default=None, help="draws of the training split (default: largest size)")
    p.add_argument("--draws-validation", type=int, default=None, help="validation draws (default: the recipe's)")
    p.add_argument("--draws-test", type=int, default=None, help="test draws (default: the recipe's)")
    p.add_argument("--max-epochs", type=int, default=None, help="epoch cap (default: the recipe's)")
    p.add_argument(
        "--gb-pixels",
        type=int,
        default=60000,
        help="samples for gradient boosting per size (0: no gradient boosting; default %(default)s)",
    )
    p.add_argument("--cache", default=None, help="dataset cache directory (default ~/.cache/torchdoct/classifier)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")
    args = p.parse_args(argv)
    try:
        check_outputs(args.out)
        res = run_learning_curve(
            sizes=args.sizes,
            draws_max=args.draws_max,
            draws_validation=args.draws_validation,
            draws_test=args.draws_test,
            max_epochs=args.max_epochs,
            gb_pixels=args.gb_pixels,
            cache_dir=args.cache,
            progress=not args.no_progress,
        )
        paths = write_outputs(res, args.out)
    except ValueError as exc:
        print(f"error: {exc}", flush=True)
        return 2
    print(flattening_sentence(res))
    print("wrote " + ", ".join(str(q) for q in paths))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""Calibration of a model's conformal prediction sets (``python -m classifier.calibrate --model NAME``).

Writes ``NAME.calibration.json`` beside the model (the file ``doct-classify`` reads with the model, numpy
only; :mod:`classifier.conformal`) and ``NAME.reliability.png`` (the reliability diagram).

**Data**: a held-out split simulated from the model's own training recipe (the prior stored in the
model's report ``NAME.json``, its replicates of static fraction and noise, :func:`classifier.dataset.make_dataset`)
at a seed no training split uses (:data:`CALIBRATION_SEED`). The prior holds static-free replicates
(static tissue only with its ``static_probability``) and flow in every direction, slow flow across the
plane included; their counts in the split are recorded (``description``).

**Samples**: per pool size ``n`` of :data:`POOLS` (the model's ``pool_pixels``), one sample per
(draw, replicate) group, the mean of ``n`` of its trials chosen at random
(:func:`classifier.train.pooled_samples`): groups are independent, so the samples are exchangeable with
new pixels drawn like them, which the guarantee needs (:mod:`classifier.conformal`). Truth: the motion
type where identifiable, else ``indeterminate`` (:func:`classifier.train.class_targets`).

**Stored**: α-free LAC scores ``1 − p_y`` per pool (rounded up to 1e-6, which can only widen the sets) and
the true class of each, so ``doct-classify --alpha`` chooses α at run time; the class-conditional
thresholds at :data:`REPORTED_ALPHAS` with the set sizes and in-sample coverage they give; per class
the expected calibration error (ECE, 10 equal-width bins of the predicted probability of the class,
one-vs-rest) and the reliability curve, on the same samples.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .conformal import DEFAULT_ALPHA, SCHEMA_VERSION, pool_thresholds, prediction_sets, scores_lac, set_labels

__all__ = [
    "CALIBRATION_SEED",
    "CALIBRATION_TRIALS",
    "POOLS",
    "calibration_samples",
    "calibrate",
    "reliability",
    "write_calibration",
    "write_calibration_files",
    "main",
]

#: Seed of the calibration split (the shipped models train at seed 0 with splits train/validation/test).
CALIBRATION_SEED = 7919
#: Trials simulated per (draw, replicate) group of the calibration split (at least the largest pool size).
CALIBRATION_TRIALS = 32
POOLS = (1, 4, 9, 25)
REPORTED_ALPHAS = (0.05, 0.1, 0.2)
BINS = 10


def _model_prior(model) -> Any:
    from .prior import Prior

    report = Path(model.path).with_suffix(".json")
    if not report.is_file():
        raise ValueError(
            f"{report}: the model's training report is missing; calibration draws from the prior it records"
        )
    from torchdoct.files import read_capped
    from torchdoct.measured.guards import parse_json_object

    try:
        data = parse_json_object(read_capped(report, "the model's training report").decode("utf-8"), report.name)
    except UnicodeDecodeError:
        raise ValueError(f"{report}: the model's training report is not UTF-8 text; train the model again") from None
    if not isinstance(data.get("prior"), dict):
        raise ValueError(f"{report}: the model's training report has no 'prior' table; train the model again")
    return Prior.from_dict(data["prior"]), data.get("config", {})


def calibration_samples(
    model,
    *,
    draws: int,
    trials: int = CALIBRATION_TRIALS,
    seed: int = CALIBRATION_SEED,
    cache_dir=None,
    use_cache: bool = True,
    progress: bool = True,
) -> tuple[dict[int, dict[str, np.ndarray]], dict[str, Any]]:
    """``({pool: samples}, description)`` of the calibration split (module docstring)."""
    from .dataset import make_dataset
    from .train import _groups, pooled_samples

    prior, config = _model_prior(model)
    spec = model.spec
    replicates = int(config.get("replicates", 8))
    ds = make_dataset(
        spec,
        prior,
        seed=int(seed),
        split="test",
        draws=int(draws),
        trials_per_draw=int(trials),
        replicates=replicates,
        truncation_tolerance=float(config.get("truncation_tolerance", 1e-2)),
        truncation=str(config.get("truncation", "taper")),
        cache_dir=cache_dir,
        use_cache=use_cache,
        progress=progress,
    )
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(1,)))
    groups = _groups(ds)
    out = {}
    for n in POOLS:
        out[n] = pooled_samples(ds, [np.array([n]) for _ in groups], rng)
    first = np.array([g[0] for g in groups])
    flow = ds.y[first] == 2
    assert ds.polar_angle_deg is not None  # Dataset.__post_init__ fills it (NaN when unknown)
    polar = ds.polar_angle_deg[first]
    static_free = ds.static_fraction[first] == 0
    desc = {
        "source": "the model's training prior (its report), split 'test' at the calibration seed",
        "seed": int(seed),
        "draws": int(draws),
        "replicates": replicates,
        "trials_per_group": int(trials),
        "groups": len(groups),
        "static_free_groups": int(static_free.sum()),
        "flow_groups": int(flow.sum()),
        "flow_groups_polar_above_60deg": int((flow & (polar > 60)).sum()),
        "flow_groups_polar_above_60deg_static_free": int((flow & (polar > 60) & static_free).sum()),
        "identifiable_groups": int((ds.status[first] == 0).sum()),
        "prior": prior.to_dict(),
    }
    return out, desc


def reliability(probabilities: np.ndarray, truth: np.ndarray, classes: Sequence[str]) -> dict[str, Any]:
    """Per class (one vs rest): the reliability curve over :data:`BINS` equal-width bins of ``p_class``
    (mean predicted, observed frequency, count) and the ECE = Σ_b (n_b/N)·|observed_b − predicted_b|."""
    out = {}
    edges = np.linspace(0.0, 1.0, BINS + 1)
    for k, name in enumerate(classes):
        p = probabilities[:, k].astype(np.float64)
        hit = truth == k
        b = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, BINS - 1)
        rows, ece = [], 0.0
        for j in range(BINS):
            sel = b == j
            if sel.any():
                pred, obs = float(p[sel].mean()), float(hit[sel].mean())
                ece += sel.mean() * abs(obs - pred)
                rows.append(
                    {
                        "bin": [float(edges[j]), float(edges[j + 1])],
                        "predicted": pred,
                        "observed": obs,
                        "count": int(sel.sum()),
                    }
                )
        out[name] = {"ece": float(ece), "bins": rows}
    return out


def calibrate(
    model_name: str,
    *,
    draws: int = 240,
    trials: int = CALIBRATION_TRIALS,
    seed: int = CALIBRATION_SEED,
    cache_dir=None,
    use_cache: bool = True,
    progress: bool = True,
) -> dict[str, Any]:
    """The calibration record of a model (module docstring)."""
    from . import runtime
    from .train import class_targets

    model = runtime.load_model(model_name, threads=1, calibration=False)
    samples, desc = calibration_samples(
        model, draws=draws, trials=trials, seed=seed, cache_dir=cache_dir, use_cache=use_cache, progress=progress
    )
    classes = model.classes
    pools = []
    for n, s in samples.items():
        p = model.predict(s["x"])
        truth = class_targets(s)
        sc = np.ceil(scores_lac(p, truth) * 1e6) / 1e6
        entry: dict[str, Any] = {
            "pool_pixels": int(n),
            "samples": int(sc.size),
            "class_counts": {c: int((truth == k).sum()) for k, c in enumerate(classes)},
            "thresholds": {},
            "set_sizes": {},
            "reliability": reliability(p, truth, classes),
        }
        entry["scores"] = [float(v) for v in sc]
        entry["truth"] = [int(v) for v in truth]
        for a in REPORTED_ALPHAS:
            q = pool_thresholds(entry, len(classes), a)
            members = prediction_sets(p, q)
            labels = set_labels(members, classes)
            entry["thresholds"][f"{a:g}"] = {c: float(v) for c, v in zip(classes, q)}
            entry["set_sizes"][f"{a:g}"] = {
                "mean_set_size": float(members.sum(1).mean()),
                "in_sample_coverage": float(members[np.arange(truth.size), truth].mean()),
                "in_sample_coverage_per_class": {
                    c: float(members[truth == k, k].mean()) if (truth == k).any() else None
                    for k, c in enumerate(classes)
                },
                "decided": float(np.isin(labels, [k for k, c in enumerate(classes) if c != "indeterminate"]).mean()),
            }
        pools.append(
            {k: entry[k] for k in entry if k not in ("scores", "truth")}
            | {"scores": entry["scores"], "truth": entry["truth"]}
        )
    return {
        "schema_version": SCHEMA_VERSION,
        "model": model.spec.name,
        "score": "lac",
        "classes": classes,
        "default_alpha": DEFAULT_ALPHA,
        "pools": pools,
        "description": desc,
        "command": f"python -m classifier.calibrate --model {model.spec.name} --draws {draws} --trials {trials}"
        + (f" --seed {seed}" if seed != CALIBRATION_SEED else ""),
        "mode": "class-conditional",
        "guarantee": (
            "For a pixel drawn like the calibration samples (the model's training prior, one pool "
            "size) whose true class is k, the prediction set holds k with probability at least "
            "1 - alpha, for every class k (class-conditional split-conformal coverage). Not promised: "
            "coverage per phantom, per speed, per direction or per pixel; anything on data unlike "
            "the training prior."
        ),
    }


def plot_reliability(cal: dict[str, Any], path: str | Path) -> None:
    """The reliability diagram: per pool size, observed frequency against mean predicted probability per
    class (Okabe–Ito colours), the diagonal, and the ECE in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .outputs import CLASS_COLORS

    pools = cal["pools"]
    fig, axes = plt.subplots(1, len(pools), figsize=(3.2 * len(pools), 3.4), squeeze=False, constrained_layout=True)
    for ax, pool in zip(axes[0], pools):
        ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--", label="perfect")
        for name, r in pool["reliability"].items():
            xs = [b["predicted"] for b in r["bins"]]
            ys = [b["observed"] for b in r["bins"]]
            ax.plot(xs, ys, "o-", ms=3, color=CLASS_COLORS.get(name, "#000000"), label=f"{name} (ECE {r['ece']:.3f})")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_xlabel("predicted probability of the class")
        ax.set_ylabel("observed frequency of the class")
        ax.set_title(f"{cal['model']}: pool_pixels {pool['pool_pixels']} (n = {pool['samples']})", fontsize=8)
        ax.legend(fontsize=6, loc="upper left")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_calibration_files(cal: dict[str, Any], json_path: str | Path, png_path: str | Path) -> None:
    """The calibration record ``NAME.calibration.json`` and its reliability diagram, at the paths given
    (``doct-train`` writes them into its output set)."""
    Path(json_path).write_text(json.dumps(cal, indent=None, separators=(",", ":")), encoding="utf-8")
    plot_reliability(cal, png_path)


def write_calibration(cal: dict[str, Any], out_dir: str | Path, *, force: bool = False) -> list[Path]:
    from torchdoct.files import output_set

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{cal['model']}.calibration.json", out / f"{cal['model']}.reliability.png"]
    with output_set(paths, force, "--out") as stage:
        write_calibration_files(cal, stage(paths[0]), stage(paths[1]))
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m classifier.calibrate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="shipped model name or .onnx file (its report NAME.json beside it)")
    ap.add_argument("--out", default=None, help="directory (default: beside the model)")
    ap.add_argument("--draws", type=int, default=240, help="parameter draws of the calibration split (default 240)")
    ap.add_argument(
        "--trials",
        type=int,
        default=CALIBRATION_TRIALS,
        help=f"trials per group (default {CALIBRATION_TRIALS}; at least the largest pool)",
    )
    ap.add_argument("--seed", type=int, default=CALIBRATION_SEED)
    ap.add_argument("--cache", default=None, help="dataset cache directory")
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")
    args = ap.parse_args(argv)
    try:
        if args.trials < max(POOLS):
            raise ValueError(f"--trials {args.trials} is below the largest pool size {max(POOLS)}; give at least that")
        cal = calibrate(
            args.model,
            draws=args.draws,
            trials=args.trials,
            seed=args.seed,
            cache_dir=args.cache,
            progress=not args.no_progress,
        )
        from . import runtime

        out = (
            Path(args.out)
            if args.out
            else Path(runtime.load_model(args.model, threads=1, calibration=False).path).parent
        )
        written = write_calibration(cal, out, force=args.force)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for p in cal["pools"]:
        print(
            f"pool_pixels {p['pool_pixels']}: n = {p['samples']}, thresholds {p['thresholds']}, "
            f"ECE " + ", ".join(f"{c} {r['ece']:.3f}" for c, r in p["reliability"].items())
        )
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Ablation of the decorrelation signature: which features the ``signature`` spec keeps.

``python -m research.ablation --out ablation.json`` simulates (or loads from the dataset cache) the
single-acquisition configurations with *every* candidate feature of :mod:`torchdoct.sim.signature`
(``rho_db_m``, ``rho_lin_m``, ``g1_m`` at lags 1-29, ``phase_ramp``, ``lin_contrast``,
``db_variance``: 90 per configuration) from the classifier's prior (:mod:`classifier.dataset`;
360 training draws, the 90 test draws of seed 0, and the same test draws with a random bulk phase
per frame), then fits one histogram gradient-boosting model per feature subset on the same 30 000
training pixels (100 iterations, fixed seed) and evaluates it per pixel on the test split with the
indeterminate rule of :mod:`classifier.rule` (balanced accuracy and coverage on identifiable
pixels, ECE). Gradient boosting is the proxy: it needs no tuning per subset and its ranking is what
decides the content; the chosen content is then trained with the network by ``doct-train``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["SUBSETS", "candidate_spec", "run_ablation", "run_indeterminate", "main"]

_ALL = tuple(range(1, 30))
_L10 = (1, 2, 3, 4, 6, 8, 11, 16, 22, 28)
_L6 = (1, 2, 4, 8, 16, 28)
_G6 = (1, 2, 3, 4, 6, 8)
_G4 = (1, 2, 4, 8)
_LEVEL = ("lin_contrast", "db_variance")


def _set(db=(), lin=(), g1=(), extra=()) -> tuple[str, ...]:
    return (
        tuple(f"rho_db_{m}" for m in db)
        + tuple(f"rho_lin_{m}" for m in lin)
        + tuple(f"g1_{m}" for m in g1)
        + tuple(extra)
    )


#: Feature subsets (per configuration) compared by the ablation.
SUBSETS = {
    "all (3 x 29 lags, phase_ramp, level)": _set(_ALL, _ALL, _ALL, _LEVEL + ("phase_ramp",)),
    "intensity + g1, all lags": _set(_ALL, _ALL, _ALL, _LEVEL),
    "intensity only, all lags": _set(_ALL, _ALL, (), _LEVEL),
    "db/lin 10 lags + g1 6 lags + level": _set(_L10, _L10, _G6, _LEVEL),
    "db/lin 10 lags + g1 6 lags + level + phase_ramp": _set(_L10, _L10, _G6, _LEVEL + ("phase_ramp",)),
    "db/lin 10 lags + g1 10 lags + level": _set(_L10, _L10, _L10, _LEVEL),
    "db 10 lags + g1 6 lags + level": _set(_L10, (), _G6, _LEVEL),
    "lin 10 lags + g1 6 lags + level": _set((), _L10, _G6, _LEVEL),
    "db/lin 10 lags + g1 6 lags": _set(_L10, _L10, _G6),
    "db/lin 6 lags + g1 4 lags + level": _set(_L6, _L6, _G4, _LEVEL),
    "intensity only, db/lin 10 lags + level": _set(_L10, _L10, (), _LEVEL),
    "intensity only, db/lin 6 lags + level": _set(_L6, _L6, (), _LEVEL),
    "intensity only, db 10 lags + level": _set(_L10, (), (), _LEVEL),
    "intensity only, lin 10 lags + level (the signature spec)": _set((), _L10, (), _LEVEL),
    "intensity only, db/lin 10 lags": _set(_L10, _L10),
}


def candidate_spec():
    """The single-acquisition configurations with every candidate signature feature."""
    from classifier.features import load_spec, spec_from_dict

    d = load_spec("single-acquisition").to_dict()
    d["name"] = "signature-ablation"
    d["description"] = "every candidate signature feature (lags 1-29) at the single-acquisition configurations"
    d["metrics"] = list(_set(_ALL, _ALL, _ALL, ("phase_ramp",) + _LEVEL))
    return spec_from_dict(d)


def run_ablation(
    *,
    draws_train: int = 360,
    draws_test: int = 90,
    pixels: int = 30000,
    seed: int = 0,
    subsets: Sequence[str] | None = None,
    cache_dir=None,
    log=print,
) -> dict:
    """Balanced accuracy, coverage and ECE per subset (module docstring); JSON-able."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from classifier.dataset import make_dataset
    from classifier.prior import Prior
    from classifier.report import evaluate
    from classifier.rule import make_rule
    from classifier.train import CLASS_NAMES

    spec = candidate_spec()
    prior = Prior()
    kw = dict(seed=seed, cache_dir=cache_dir)
    tr = make_dataset(spec, prior, split="train", draws=draws_train, **kw)
    tests = {
        "test": make_dataset(spec, prior, split="test", draws=draws_test, **kw),
        "test, random bulk phase per frame": make_dataset(
            spec, prior, split="test", draws=draws_test, bulk_phase=True, **kw
        ),
    }
    names = [n.split("@")[0] for n in tr.meta["feature_names"]]
    rule = make_rule(prior.identifiability_epsilon, 0.5)
    sub = np.random.default_rng(seed).choice(len(tr), min(pixels, len(tr)), replace=False)
    y = np.where(tr.status == 0, tr.y, len(CLASS_NAMES) - 1)
    out = {
        "method": __doc__.split("\n\n")[1].replace("\n", " "),
        "draws_train": draws_train,
        "draws_test": draws_test,
        "pixels": int(len(sub)),
        "seed": seed,
        "subsets": {},
    }
    for name in subsets or SUBSETS:
        want = set(SUBSETS[name])
        cols = [i for i, n in enumerate(names) if n in want]
        t0 = time.perf_counter()
        gb = HistGradientBoostingClassifier(max_iter=100, random_state=seed, early_stopping=False)
        gb.fit(tr.x[sub][:, cols], y[sub])
        row: dict = {"features_per_configuration": len(want), "features": len(cols)}
        for label, ds in tests.items():
            m = evaluate(gb.predict_proba(ds.x[:, cols]), ds.y, ds.status, CLASS_NAMES, rule)
            row[label] = {
                k: m[k]
                for k in ("balanced_accuracy_identifiable", "coverage_identifiable", "accuracy_identifiable", "ece")
            }
        row["seconds"] = time.perf_counter() - t0
        out["subsets"][name] = row
        if log:
            t = row["test"]
            log(
                f"{name}: {len(cols)} features, balanced accuracy {t['balanced_accuracy_identifiable']:.3f}, "
                f"coverage {t['coverage_identifiable']:.3f}; with bulk phase "
                f"{row['test, random bulk phase per frame']['balanced_accuracy_identifiable']:.3f} / "
                f"{row['test, random bulk phase per frame']['coverage_identifiable']:.3f}"
            )
    return out


def run_indeterminate(
    *, draws_train: int = 360, draws_test: int = 90, pixels: int = 60000, seed: int = 0, cache_dir=None, log=print
) -> dict:
    """Can the signature tell the motion types apart where the ground truth says "decorrelated"?

    The ground truth (:func:`classifier.truth.identifiability`) calls a draw "decorrelated" when its
    field decorrelates within one frame interval at every configuration. What is then left of the
    intensity correlation is the incoherent transit term ``j/N_eff`` (physics.md §5.4), which may still
    decay over the acquisition (:func:`classifier.truth.transit_decay` > ε at some configuration,
    "transit visible") or not ("flat"). Here gradient boosting is trained on the same data as
    :func:`run_ablation` with those decorrelated draws labelled by their motion type instead of
    ``indeterminate``, and the balanced accuracy is measured per pixel in each regime of the test
    split, for the shipped signature content and for every candidate feature. Chance is 0.5 (only
    diffusion and random-ballistic motion reach the regime in the prior; where a regime holds a
    single motion type, its balanced accuracy is that type's recall and measures no separation).
    """
    from sklearn.ensemble import HistGradientBoostingClassifier

    from classifier.dataset import make_dataset
    from classifier.features import load_spec
    from classifier.prior import Prior, draw_parameters
    from classifier.report import evaluate
    from classifier.rule import make_rule
    from classifier.train import CLASS_NAMES
    from classifier.truth import transit_decay

    spec, prior = candidate_spec(), Prior()
    eps = prior.identifiability_epsilon
    kw = dict(seed=seed, cache_dir=cache_dir)
    tr = make_dataset(spec, prior, split="train", draws=draws_train, **kw)
    te = make_dataset(spec, prior, split="test", draws=draws_test, **kw)

    def regimes(
        ds, split
    ):  # per sample: 0 identifiable/static, 1 decorrelated + transit visible, 2 decorrelated + flat
        per_draw = {}
        for k in np.unique(ds.draw):
            d = draw_parameters(prior, seed, split, int(k))
            per_draw[int(k)] = 1 if np.any(transit_decay(spec, d, prior) > eps) else 2
        r = np.array([per_draw[int(k)] for k in ds.draw])
        return np.where(ds.status == 2, r, 0)

    r_te = regimes(te, "test")
    ind = len(CLASS_NAMES) - 1
    y = np.where((tr.status == 0) | (tr.status == 2), tr.y, ind)  # decorrelated draws keep their motion label
    sub = np.random.default_rng(seed).choice(len(tr), min(pixels, len(tr)), replace=False)
    names = [n.split("@")[0] for n in tr.meta["feature_names"]]
    shipped = set(load_spec("signature").metrics)
    rule = make_rule(eps, 0.5)
    out = {
        "method": " ".join(run_indeterminate.__doc__.split("\n\n")[1].split()),
        "draws_train": draws_train,
        "draws_test": draws_test,
        "pixels": int(len(sub)),
        "seed": seed,
        "epsilon": eps,
        "test_samples": {
            "identifiable": int((te.status == 0).sum()),
            "decorrelated, transit visible": int((r_te == 1).sum()),
            "decorrelated, flat": int((r_te == 2).sum()),
        },
        "features": {},
    }
    for label, want in (("signature spec content", shipped), ("every candidate feature", set(names))):
        cols = [i for i, n in enumerate(names) if n in want]
        gb = HistGradientBoostingClassifier(max_iter=200, random_state=seed, early_stopping=False)
        gb.fit(tr.x[sub][:, cols], y[sub])
        p = gb.predict_proba(te.x[:, cols]) @ np.eye(len(CLASS_NAMES))[gb.classes_]
        row = {}
        for name, m in (
            ("identifiable", te.status == 0),
            ("decorrelated, transit visible", r_te == 1),
            ("decorrelated, flat", r_te == 2),
        ):
            if not m.any():
                continue
            # score the decorrelated pixels as if they were identifiable: their motion label is the truth
            status = np.zeros(int(m.sum()), np.int64)
            e = evaluate(p[m], te.y[m], status, CLASS_NAMES, rule)
            row[name] = {
                k: e[k] for k in ("balanced_accuracy_identifiable", "coverage_identifiable", "recall_identifiable")
            }
            row[name]["samples_per_class"] = {c: int((te.y[m] == i).sum()) for i, c in enumerate(CLASS_NAMES[:-1])}
        out["features"][label] = row
        if log:
            log(
                f"{label}: "
                + "; ".join(
                    f"{n} balanced accuracy {v['balanced_accuracy_identifiable']:.3f} "
                    f"(coverage {v['coverage_identifiable']:.3f})"
                    for n, v in row.items()
                )
            )
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.ablation", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="JSON output file")
    p.add_argument("--draws-train", type=int, default=360)
    p.add_argument("--draws-test", type=int, default=90)
    p.add_argument("--cache", default=None, help="dataset cache directory (default ~/.cache/torchdoct/classifier)")
    p.add_argument(
        "--indeterminate",
        action="store_true",
        help="instead: can the signature separate the motion types where the ground truth says "
        "'decorrelated'? (run_indeterminate)",
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.exists():
        print(f"error: {out} exists", flush=True)
        return 2
    run = run_indeterminate if args.indeterminate else run_ablation
    res = run(draws_train=args.draws_train, draws_test=args.draws_test, cache_dir=args.cache)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

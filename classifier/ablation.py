"""Ablation of the decorrelation signature: which features the ``signature`` spec keeps.

``python -m classifier.ablation --out ablation.json`` simulates (or loads from the dataset cache) the
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
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["SUBSETS", "candidate_spec", "run_ablation", "main"]

_ALL = tuple(range(1, 30))
_L10 = (1, 2, 3, 4, 6, 8, 11, 16, 22, 28)
_L6 = (1, 2, 4, 8, 16, 28)
_G6 = (1, 2, 3, 4, 6, 8)
_G4 = (1, 2, 4, 8)
_LEVEL = ("lin_contrast", "db_variance")


def _set(db=(), lin=(), g1=(), extra=()) -> tuple[str, ...]:
    return (tuple(f"rho_db_{m}" for m in db) + tuple(f"rho_lin_{m}" for m in lin) + tuple(f"g1_{m}" for m in g1)
            + tuple(extra))


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
    from .features import load_spec, spec_from_dict

    d = load_spec("single-acquisition").to_dict()
    d["name"] = "signature-ablation"
    d["description"] = "every candidate signature feature (lags 1-29) at the single-acquisition configurations"
    d["metrics"] = list(_set(_ALL, _ALL, _ALL, ("phase_ramp",) + _LEVEL))
    return spec_from_dict(d)


def run_ablation(*, draws_train: int = 360, draws_test: int = 90, pixels: int = 30000, seed: int = 0,
                 subsets: Sequence[str] | None = None, cache_dir=None, log=print) -> dict:
    """Balanced accuracy, coverage and ECE per subset (module docstring); JSON-able."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from .dataset import Prior, make_dataset
    from .report import evaluate
    from .rule import make_rule
    from .train import CLASS_NAMES

    spec = candidate_spec()
    prior = Prior()
    kw = dict(seed=seed, cache_dir=cache_dir)
    tr = make_dataset(spec, prior, split="train", draws=draws_train, **kw)
    tests = {"test": make_dataset(spec, prior, split="test", draws=draws_test, **kw),
             "test, random bulk phase per frame": make_dataset(spec, prior, split="test", draws=draws_test,
                                                                bulk_phase=True, **kw)}
    names = [n.split("@")[0] for n in tr.meta["feature_names"]]
    rule = make_rule(prior.identifiability_epsilon, 0.5)
    sub = np.random.default_rng(seed).choice(len(tr), min(pixels, len(tr)), replace=False)
    y = np.where(tr.status == 0, tr.y, len(CLASS_NAMES) - 1)
    out = {"method": __doc__.split("\n\n")[1].replace("\n", " "), "draws_train": draws_train,
           "draws_test": draws_test, "pixels": int(len(sub)), "seed": seed, "subsets": {}}
    for name in subsets or SUBSETS:
        want = set(SUBSETS[name])
        cols = [i for i, n in enumerate(names) if n in want]
        t0 = time.perf_counter()
        gb = HistGradientBoostingClassifier(max_iter=100, random_state=seed, early_stopping=False)
        gb.fit(tr.x[sub][:, cols], y[sub])
        row: dict = {"features_per_configuration": len(want), "features": len(cols)}
        for label, ds in tests.items():
            m = evaluate(gb.predict_proba(ds.x[:, cols]), ds.y, ds.status, CLASS_NAMES, rule)
            row[label] = {k: m[k] for k in ("balanced_accuracy_identifiable", "coverage_identifiable",
                                            "accuracy_identifiable", "ece")}
        row["seconds"] = time.perf_counter() - t0
        out["subsets"][name] = row
        if log:
            t = row["test"]
            log(f"{name}: {len(cols)} features, balanced accuracy {t['balanced_accuracy_identifiable']:.3f}, "
                f"coverage {t['coverage_identifiable']:.3f}; with bulk phase "
                f"{row['test, random bulk phase per frame']['balanced_accuracy_identifiable']:.3f} / "
                f"{row['test, random bulk phase per frame']['coverage_identifiable']:.3f}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m classifier.ablation", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="JSON output file")
    p.add_argument("--draws-train", type=int, default=360)
    p.add_argument("--draws-test", type=int, default=90)
    p.add_argument("--cache", default=None, help="dataset cache directory (default ~/.cache/torchdoct/classifier)")
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.exists():
        print(f"error: {out} exists", flush=True)
        return 2
    res = run_ablation(draws_train=args.draws_train, draws_test=args.draws_test, cache_dir=args.cache)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

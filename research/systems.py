"""Your own system, end to end: rendered phantoms of other OCT systems → ``torchdoct maps`` → ``doct-train
--like`` → ``doct-classify``, scored against the rendered ground truth.

``python -m research.systems --out DIR [--system NAME ...] [--seeds 2026,1,2] [--quick]
[--min-probability P ...] [--stem STEM]``

For each system phantom (``system-1310nm``: 1310 nm, lateral 10 µm, axial 8 µm; ``system-fast``: 64 frames
12.8 ms apart; ``system-tissue-volume``: a volume in tissue, n = 1.38) the chain a user runs:

1. ``torchdoct render PHANTOM --seed S`` and ``torchdoct maps`` with the reductions the phantom names (about
   3.7× axially and laterally, as the paper) and ``--signature``;
2. ``doct-train --like`` on the maps of the first seed, which also calibrates the model's conformal sets
   (skipped when ``DIR/SYSTEM/`` already holds the model: its report gives the training time);
3. ``doct-classify --model DIR/SYSTEM --pool P --decide-ballistic`` (the model's own decisions: its
   conformal sets, without the rules of :mod:`classifier.ambiguity`; what the
   recorded floors measure; the ballistic-or-flow rules of :mod:`classifier.ambiguity` are scored by the
   phantom grid) for every seed and P = 1, 5, scored with
   :func:`classifier.evaluate_images.score_images` (all labelled moving pixels, edge 0): balanced accuracy,
   coverage, recall per motion type, magnitude error and interval coverage; with ``--min-probability P``
   also at pool 5 with that threshold of the indeterminate outcome.

4. ``doct-classify --model DIR/SYSTEM --pool 5`` (the default decision, with the abstaining rules), scored
   the same way, with each class's wrong share (its pixels decided as another class).
5. The phantom grid's probes of the system's geometry (:data:`classifier.bench.grid.PROBES`: regions that
   touch, with and without static tissue, built from the model's system at the speed levels and lowest
   density of its own training prior), with the model, at windows 1 and 5, with the rules (the default)
   and without them (``--decide-ballistic``): each motion's wrong share over all its pixels. Off the
   system's own phantom, where the model meets touching regions it was not validated on.

Writes ``DIR/STEM.json`` and ``.md`` (``STEM`` default ``systems-validation``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import torchdoct_command

#: Phantom → (maps options, description).
SYSTEMS = {
    "system-1310nm": (
        ["--resolution", "original", "--resolution", "axial=30", "--resolution", "lateral=37"],
        "1310 nm, lateral 10 µm, axial 8 µm; B-scans reduced to axial 30 / lateral 37 µm",
    ),
    "system-fast": (
        [
            "--resolution",
            "original",
            "--resolution",
            "axial=14",
            "--resolution",
            "lateral=18",
            "--ocds-delay-range-s",
            "0.0128",
            "0.0768",
        ],
        "840 nm 4.9/3.8 µm, 64 frames 12.8 ms apart; B-scans reduced to axial 14 / lateral 18 µm",
    ),
    "system-tissue-volume": (
        ["--resolution", "original", "--resolution", "axial=14", "--resolution", "lateral=18"],
        "840 nm 4.9/3.8 µm in tissue (n = 1.38); a volume reduced isotropically",
    ),
}
POOLS = (1, 5)


def render_maps(out: Path, system: str, seed: int) -> tuple[Path, Path]:
    seq, maps = out / f"{system}-{seed}.npz", out / f"{system}-{seed}-maps.npz"
    if not maps.exists():
        torchdoct_command(
            ["render", system, "--out", str(seq), "--seed", str(seed), "--no-preview", "--no-progress", "--force"]
        )
        torchdoct_command(
            ["maps", str(seq), *SYSTEMS[system][0], "--signature", "--out", str(maps), "--no-progress", "--force"]
        )
    return seq, maps


def train(
    out: Path, system: str, maps: Path, quick: bool, seed: int | None = None, models: Path | None = None
) -> tuple[Path, dict]:
    """The model of ``doct-train --like`` (trained unless present; ``seed``: its ``--seed``, default
    doct-train's) and its report. ``models``: a folder of models trained earlier (``MODELS/SYSTEM/``, the
    files ``doct-train`` wrote), copied into ``out/SYSTEM/`` and used instead of training; the record's
    training time is then its report's."""
    import shutil

    from classifier.cli import train_main

    mdir = out / system
    if models is not None and not (mdir.is_dir() and any(mdir.glob("*.onnx"))):
        src = models / system
        if not any(src.glob("*.onnx")):
            raise FileNotFoundError(f"--models {models}: no {system}/*.onnx there; give the folder that holds one")
        shutil.copytree(src, mdir, dirs_exist_ok=True)
    found = sorted(mdir.glob("*.onnx")) if mdir.is_dir() else []
    if not found:
        argv = ["--like", str(maps), "--out", str(mdir), "--no-progress"] + (["--quick"] if quick else [])
        argv += [] if seed is None else ["--seed", str(seed)]
        if train_main(argv) != 0:
            raise RuntimeError(f"doct-train {' '.join(argv)} failed")
        found = sorted(mdir.glob("*.onnx"))
    report = json.loads(found[0].with_suffix(".json").read_text())
    return found[0], report


def evaluate(
    out: Path,
    system: str,
    seeds: list[int],
    quick: bool,
    min_probabilities: list[float] = (),
    train_seed: int | None = None,
    models: Path | None = None,
) -> dict:
    from classifier.cli import classify_main
    from classifier.evaluate_images import score_images

    files = {s: render_maps(out, system, s) for s in seeds}
    model, report = train(out, system, files[seeds[0]][1], quick, train_seed, models)
    scores: dict[str, list] = {str(p): [] for p in POOLS}

    def classify(key: str, cdir: Path, maps: Path, seq: Path, *options: str) -> None:
        """``doct-classify MAPS --model MODEL --out CDIR --force OPTIONS``, scored into ``scores[key]``."""
        argv = [str(maps), "--model", str(model), "--out", str(cdir), *options, "--force"]
        if classify_main(argv) != 0:
            raise RuntimeError(f"doct-classify {' '.join(argv)} failed")
        scores.setdefault(key, []).append(score_images(cdir, seq, edge_um=0.0))

    for s in seeds:
        seq, maps = files[s]
        for p in POOLS:
            classify(str(p), out / f"cls-{system}-{s}-p{p}", maps, seq, "--pool", str(p), "--decide-ballistic")
        # pool 5 with doct-classify's default decision: the rules of classifier.ambiguity abstain where the
        # physics cannot tell (every ballistic decision of a B-scan becomes ballistic-or-flow)
        classify("5-default", out / f"cls-{system}-{s}-p5-default", maps, seq, "--pool", "5")
        for mp in min_probabilities:  # pool 5 again, with another threshold of the indeterminate outcome
            classify(
                f"5@{mp:g}",
                out / f"cls-{system}-{s}-p5-mp{mp:g}",
                maps,
                seq,
                *("--pool", "5", "--min-probability", f"{mp:g}", "--decide-ballistic"),
            )
    probes = probe_scores(model, report["prior"], "volume" if "volume" in system else "bscan")
    test = report["test"]["network"]["1"]
    return {
        "system": system,
        "description": SYSTEMS[system][1],
        "model": model.name,
        "spec": report["spec"],
        "prior": report["prior"],
        "training_s": report.get("total_s"),
        "simulation_s": report["data"]["simulation_s"],
        "fit_s": report["training"]["seconds"],
        "draws": report["data"]["draws"],
        "own_test_pool1": {
            "balanced_accuracy_identifiable": test["balanced_accuracy_identifiable"],
            "coverage_identifiable": test["coverage_identifiable"],
        },
        "seeds": seeds,
        "scores": scores,
        "probes": probes,
    }


def probe_scores(model: Path, prior: dict, geometry: str) -> list[dict]:
    """Step 5 (module docstring): one row per probe of ``geometry``, window and decision (rules or the
    model alone), with the all-pixels scores of :func:`classifier.bench.grid.run_probe`."""
    from classifier.bench import grid
    from classifier.infer import load_model
    from classifier.prior import Prior

    mdl = load_model(model)
    pri = Prior.from_dict(prior)
    levels = grid.speed_levels(mdl.spec, pri)
    rows = []
    for name in (p for p in grid.PROBES if p.startswith(geometry)):
        for rules in (True, False):
            for r in grid.run_probe(name, mdl, levels, prior=pri, abstain_ambiguous=rules):
                rows.append({"probe": name, "pool": r["pool"], "rules": rules, "all_pixels": r["all_pixels"]})
    return rows


def _overall(scores: list[dict], key: str) -> tuple[float, float]:
    v = np.array([s["overall"][key] for s in scores], float)
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else float("nan")


def to_markdown(result: dict) -> str:
    L = [
        "# Your own system, end to end: rendered phantoms → maps → doct-train --like → doct-classify",
        "",
        f"Command: `{result['command']}`. Scores over all labelled moving pixels (edge 0) of the renderings "
        f"(seeds {result['seeds']}), mean ± SD over the renderings; the model trained on the first seed's maps. "
        "Goals: pool 5 balanced accuracy ≥ 0.93 at coverage ≥ 0.90; doct-train --like ≤ 15 min on 2 cores. "
        "Pools 1 and 5 below: the model's own decisions (`--decide-ballistic`, without the rules): its conformal "
        "sets at α = 0.1 where doct-train calibrated it, a set of one motion type counted as decided.",
        "",
        "| system | training (simulation + fit) | own test split, pool 1 | pool 1: balanced accuracy @ coverage "
        "| pool 5: balanced accuracy @ coverage | pool 5 recall diffusion / ballistic / flow | pool 5 wrong share "
        "diffusion / ballistic / flow | magnitude: median \\|log10 error\\|, 68 % / 95 % cover (pool 5) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    extra = any(k.startswith("5@") for r in result["systems"] for k in r["scores"])
    if extra:  # pool 5 at other thresholds of the indeterminate outcome: one more column
        L[-2] += " pool 5 with `--min-probability`: balanced accuracy @ coverage |"
        L[-1] += "---|"
    for r in result["systems"]:
        cells = []
        for p in ("1", "5"):
            b, bs = _overall(r["scores"][p], "balanced_accuracy")
            c, cs = _overall(r["scores"][p], "coverage")
            cells.append(f"{b:.3f} ± {bs:.3f} @ {c:.3f} ± {cs:.3f}")
        rec = {
            k: np.mean([(s["overall"]["per_class"].get(k) or {}).get("recall") or np.nan for s in r["scores"]["5"]])
            for k in ("diffusion", "ballistic", "flow")
        }
        wrong5 = {
            k: np.mean(
                [_wrong_share(q, k) if (q := s["overall"]["per_class"].get(k)) else np.nan for s in r["scores"]["5"]]
            )
            for k in ("diffusion", "ballistic", "flow")
        }
        mags = [s["overall"].get("magnitude") or {} for s in r["scores"]["5"]]

        def mm(key):
            return np.mean([m.get(key) if m.get(key) is not None else np.nan for m in mags])

        mag = f"{mm('median_abs_log10_error'):.3f}, {mm('in_68'):.2f} / {mm('in_95'):.2f}"
        thresholds = []
        for key in (k for k in r["scores"] if k.startswith("5@")):
            b, bs = _overall(r["scores"][key], "balanced_accuracy")
            c, cs = _overall(r["scores"][key], "coverage")
            thresholds.append(f"{key[2:]}: {b:.3f} ± {bs:.3f} @ {c:.3f} ± {cs:.3f}")
        t = r["training_s"]
        L.append(
            f"| {r['system']}: {r['description']} | {t / 60:.1f} min ({r['simulation_s'] / 60:.1f} + "
            f"{r['fit_s'] / 60:.1f}) | {r['own_test_pool1']['balanced_accuracy_identifiable']:.3f} @ "
            f"{r['own_test_pool1']['coverage_identifiable']:.3f} | {cells[0]} | {cells[1]} | "
            f"{rec['diffusion']:.3f} / {rec['ballistic']:.3f} / {rec['flow']:.3f} | "
            f"{wrong5['diffusion']:.3f} / {wrong5['ballistic']:.3f} / {wrong5['flow']:.3f} | {mag} |"
            + (f" {'; '.join(thresholds)} |" if extra else "")
        )
    if any("5-default" in r["scores"] for r in result["systems"]):
        L += [
            "",
            "Pool 5 with doct-classify's default decision (the rules of `classifier.ambiguity`: a B-scan's "
            "ballistic decisions become `ballistic-or-flow`); wrong share: the class's pixels decided as another "
            "class. Balanced accuracy on decided pixels counts the classes with decided pixels.",
            "",
            "| system | coverage | balanced accuracy on decided | coverage diffusion / ballistic / flow "
            "| wrong share diffusion / ballistic / flow |",
            "|---|---|---|---|---|",
        ]
        for r in result["systems"]:
            sc = r["scores"].get("5-default")
            if not sc:
                continue
            c, cs = _overall(sc, "coverage")
            ba = np.mean([_decided_ba(s) for s in sc])
            cov, wrong = [], []
            for k in ("diffusion", "ballistic", "flow"):
                per = [s["overall"]["per_class"].get(k) for s in sc]
                cov.append(np.mean([q["coverage"] if q else np.nan for q in per]))
                wrong.append(np.mean([_wrong_share(q, k) if q else np.nan for q in per]))
            L.append(
                f"| {r['system']} | {c:.3f} ± {cs:.3f} | {ba:.3f} | {' / '.join(f'{v:.3f}' for v in cov)} | "
                f"{' / '.join(f'{v:.3f}' for v in wrong)} |"
            )
    if any(r.get("probes") for r in result["systems"]):
        L += [
            "",
            "Probes of the phantom grid (regions that touch; `classifier.bench.grid.PROBES`) built from each "
            "system at its own training prior's speed levels and lowest density, classified by its model: "
            "coverage and wrong share per motion over all pixels, borders included, with doct-classify's rules "
            "(the default) and the model alone (`--decide-ballistic`).",
            "",
            "| system | probe | window | rules: coverage diffusion / ballistic / flow | rules: wrong share "
            "diffusion / ballistic / flow | model alone: wrong share diffusion / ballistic / flow |",
            "|---|---|---|---|---|---|",
        ]
        for r in result["systems"]:
            rows = r.get("probes") or []
            for name in dict.fromkeys(q["probe"] for q in rows):
                for pool in sorted({q["pool"] for q in rows if q["probe"] == name}):
                    got = {
                        q["rules"]: q["all_pixels"]["per_class"]
                        for q in rows
                        if q["probe"] == name and q["pool"] == pool
                    }

                    def fmt(per, key):
                        return " / ".join(
                            "–" if not per.get(k) or per[k][key] is None else f"{per[k][key]:.3f}"
                            for k in ("diffusion", "ballistic", "flow")
                        )

                    L.append(
                        f"| {r['system']} | {name} | {pool} | {fmt(got[True], 'coverage')} | "
                        f"{fmt(got[True], 'wrong_share')} | {fmt(got[False], 'wrong_share')} |"
                    )
    return "\n".join(L) + "\n"


def _wrong_share(per: dict, name: str) -> float:
    """The share of a class's pixels decided as another class (``per_class`` entry of ``score_images``)."""
    return sum(n for k, n in per["decided_as"].items() if k != name) / per["pixels"]


def _decided_ba(score: dict) -> float:
    """Balanced accuracy on decided pixels over the classes that have decided pixels."""
    rec = [q["recall"] for q in score["overall"]["per_class"].values() if q.get("recall") is not None]
    return float(np.mean(rec)) if rec else float("nan")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.systems", description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--system", action="append", choices=list(SYSTEMS), help="(repeat; default all three)")
    p.add_argument("--seeds", default="2026,1,2,3,4,5", help="rendering seeds, the first trains (default 2026,1,...,5)")
    p.add_argument("--quick", action="store_true", help="doct-train --like --quick (about a minute per system)")
    p.add_argument(
        "--min-probability",
        type=float,
        action="append",
        default=[],
        help="also classify at pool 5 with this doct-classify --min-probability (repeat)",
    )
    p.add_argument("--stem", default="systems-validation", help="file names STEM.json, STEM.md")
    p.add_argument(
        "--models",
        default=None,
        metavar="DIR",
        help="models trained earlier, DIR/SYSTEM/ as doct-train wrote them (research/results/systems-models "
        "holds those of the record): used instead of training, their reports give the training time",
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    t0 = time.perf_counter()
    models = None if args.models is None else Path(args.models)
    systems = [
        evaluate(out, s, seeds, args.quick, args.min_probability, models=models) for s in (args.system or list(SYSTEMS))
    ]
    result = {
        "command": "python -m research.systems --out DIR"
        + "".join(f" --system {s}" for s in args.system or [])
        + (f" --seeds {args.seeds}" if args.seeds != "2026,1,2,3,4,5" else "")
        + (" --quick" if args.quick else "")
        + "".join(f" --min-probability {mp:g}" for mp in args.min_probability)
        + (f" --stem {args.stem}" if args.stem != "systems-validation" else "")
        + (f" --models {args.models}" if args.models else ""),
        "seeds": seeds,
        "systems": systems,
        "seconds": time.perf_counter() - t0,
    }
    (out / f"{args.stem}.json").write_text(json.dumps(result, indent=1, default=float))
    (out / f"{args.stem}.md").write_text(to_markdown(result))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

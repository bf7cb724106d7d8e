"""Recorded runs behind the statistical floors of the end-to-end tests.

A floor is ``mean − z·SD`` (a ceiling ``mean + z·SD`` for an error) of a statistic over recorded runs, each
run one rendering (one seed) of the chain a test runs: the SD over renderings is the standard error of one
run's statistic, which is what a test that runs once is compared against. ``z`` is written in the file
beside the runs, and the tests compute their floors from the file: a floor changes only when the file is
recorded again by the command below, in the commit that says why.

Commands (from the repository root, a development install; each writes one JSON file)::

    python -m tests.reference.floors phantoms --out tests/floors/phantoms.json [--seeds 2026,1,2,3,4,5]
    python -m tests.reference.floors systems --out tests/floors/systems-quick.json [--seeds 2026,1,2,3]
    python -m tests.reference.floors slabs --out tests/floors/slabs.json [--seeds 7,1,2,3,4,5]

``phantoms``: the shipped phantoms ``motion-types`` and ``oblique-flow`` (B-scans) and
``oblique-flow-volume`` (a volume) → ``torchdoct render --seed S``
→ ``torchdoct maps --signature`` (original, axial 14 µm, lateral 18 µm) → ``doct-classify --decision rule`` at
pools 1 and 5 (the default model), scored by :func:`classifier.evaluate_images.score_images` (all labelled
moving pixels, edge 0).

``systems``: :func:`research.systems.evaluate` with ``--quick`` models for each system phantom: per seed S a
rendering with seed S, ``doct-train --like --quick`` on its maps (with ``--seed S``; doct-train's default
seed for the first, as the test trains), classified at pools 1 and 5; and the worst wrong share over the
grid's probes of the system's geometry classified by that model with doct-classify's rules (``research.systems.probe_scores``). A run varies both the
rendering and the training, the two things a test run on another machine can draw differently.

``slabs``: the four-slab phantom of ``tests/classifier/test_clf_end_to_end.py`` (``tests/classifier/_slabs.py``),
B-scan and volume, per seed S rendered with ``--seed S`` → ``torchdoct maps`` (LIV/OCDS) → ``doct-classify
--pool 5 --decision rule --decide-ballistic`` (the rule was the default decision of the uncalibrated LIV/OCDS
models when the file was recorded), scored by ``_slabs.score`` (balanced accuracy, mean coverage of the motion
slabs, the static slab's indeterminate share, away from the slab boundaries).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

#: Standard normal quantile of the floors: a test run falls below ``mean − 3 SD`` with probability ~0.1 %.
Z = 3.0
POOLS = (1, 5)
PHANTOMS = ("motion-types", "oblique-flow", "oblique-flow-volume")
MAPS_OPTIONS = ["--resolution", "original", "--resolution", "axial=14", "--resolution", "lateral=18", "--signature"]
SYSTEMS = ("system-1310nm", "system-fast", "system-tissue-volume")
METRICS = ("balanced_accuracy", "coverage")


def floor(values: list[float], z: float, *, error: bool = False) -> float:
    """``mean − z·SD`` of recorded values (``mean + z·SD`` for an error that must stay small); SD with ddof 1."""
    v = np.asarray(values, dtype=float)
    if v.size < 2 or not np.all(np.isfinite(v)):
        raise ValueError(f"a floor needs at least two finite recorded values; got {values!r}")
    sd = float(v.std(ddof=1))
    return float(v.mean() + z * sd) if error else float(v.mean() - z * sd)


def load(name: str) -> dict:
    """The recorded runs ``tests/floors/NAME.json``."""
    path = Path(__file__).resolve().parents[1] / "floors" / f"{name}.json"
    return json.loads(path.read_text(encoding="utf-8"))


def _overall(summary: dict) -> dict:
    o = summary["overall"]
    out = {k: o[k] for k in METRICS}
    mag = o.get("magnitude") or {}
    out["magnitude_median_abs_log10_error"] = mag.get("median_abs_log10_error")
    return out


def _phantom_run(work: Path, phantom: str, seed: int) -> dict:
    from classifier.cli import classify_main
    from classifier.evaluate_images import score_images
    from torchdoct.cli import main as torchdoct_main

    seq, maps = work / f"{phantom}-{seed}.npz", work / f"{phantom}-{seed}-maps.npz"
    if (
        torchdoct_main(
            [
                "render",
                phantom,
                "--seed",
                str(seed),
                "--out",
                str(seq),
                "--no-progress",
                "--no-preview",
                "--threads",
                "1",
            ]
        )
        != 0
    ):
        raise RuntimeError(f"torchdoct render {phantom} --seed {seed} failed")
    if torchdoct_main(["maps", str(seq), *MAPS_OPTIONS, "--out", str(maps), "--no-progress", "--threads", "1"]) != 0:
        raise RuntimeError(f"torchdoct maps {seq} failed")
    run = {}
    for pool in POOLS:
        d = work / f"{phantom}-{seed}-p{pool}"
        if (
            classify_main(
                [
                    str(maps),
                    "--out",
                    str(d),
                    "--pool",
                    str(pool),
                    "--threads",
                    "1",
                    "--decision",
                    "rule",
                    "--decide-ballistic",
                    "--no-progress",
                ]
            )
            != 0
        ):
            raise RuntimeError(f"doct-classify {maps} failed")
        run[str(pool)] = _overall(score_images(d, seq))
    return run


def record_phantoms(seeds: list[int], progress: bool = True) -> dict:
    from tqdm import tqdm

    runs: dict[str, dict[str, dict[str, list]]] = {}
    todo = [(p, s) for p in PHANTOMS for s in seeds]
    with tempfile.TemporaryDirectory() as tmp:
        for phantom, seed in tqdm(todo, desc="renderings", unit="run", disable=not progress):
            run = _phantom_run(Path(tmp), phantom, seed)
            for pool, vals in run.items():
                slot = runs.setdefault(phantom, {}).setdefault(pool, {"seeds": []})
                slot["seeds"].append(seed)
                for k, v in vals.items():
                    slot.setdefault(k, []).append(v)
    return runs


def record_systems(seeds: list[int]) -> dict:
    from research.systems import evaluate

    runs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for system in SYSTEMS:
            runs[system] = {str(p): {"seeds": []} for p in POOLS}
            for i, seed in enumerate(seeds):
                work = Path(tmp) / f"{system}-{seed}"
                work.mkdir()
                r = evaluate(work, system, [seed], quick=True, train_seed=None if i == 0 else seed)
                for pool in map(str, POOLS):
                    slot = runs[system][pool]
                    slot["seeds"].append(seed)
                    for k, v in _overall(r["scores"][pool][0]).items():
                        slot.setdefault(k, []).append(v)
                    slot.setdefault("probes_wrong_share_max", []).append(probes_wrong_share_max(r["probes"], pool))
    return runs


def probes_wrong_share_max(rows: list[dict], pool: str) -> float:
    """The largest share of a motion's pixels decided as another class, borders included, over the grid's
    probes classified with doct-classify's rules at window ``pool`` (``research.systems.probe_scores`` rows)."""
    return max(float(r["all_pixels"]["wrong_share_max"]) for r in rows if r["rules"] and str(r["pool"]) == pool)


def record_slabs(seeds: list[int], progress: bool = True) -> dict:
    from tqdm import tqdm

    from tests.classifier._slabs import FLOORED, GEOMETRIES, run_chain, score

    runs: dict[str, dict[str, list]] = {g: {"seeds": []} for g in GEOMETRIES}
    todo = [(g, s) for g in GEOMETRIES for s in seeds]
    with tempfile.TemporaryDirectory() as tmp:
        for geometry, seed in tqdm(todo, desc="renderings", unit="run", disable=not progress):
            work = Path(tmp) / f"{geometry}-{seed}"
            work.mkdir()
            grid, z_axis = GEOMETRIES[geometry]
            s = score(*run_chain(work, grid, seed)[:2], z_axis)
            runs[geometry]["seeds"].append(seed)
            for k in FLOORED:
                runs[geometry].setdefault(k, []).append(s[k])
    return runs


#: What each kind records, as its file says.
STATISTICS = {
    "phantoms": "per rendering: score_images overall, all labelled moving pixels, edge 0; floor = mean - z*SD over "
    "renderings (ceiling mean + z*SD for the magnitude error)",
    "systems": "per rendering: score_images overall, all labelled moving pixels, edge 0; floor = mean - z*SD over "
    "renderings (ceiling mean + z*SD for the magnitude error and for probes_wrong_share_max: the worst wrong share "
    "over the grid's probes of the system's geometry with doct-classify's rules, every pixel)",
    "slabs": "per rendering: tests/classifier/_slabs.score (slab pixels at least 16 um from a boundary); "
    "floor = mean - z*SD over renderings",
}
DEFAULT_SEEDS = {"phantoms": "2026,1,2,3,4,5", "systems": "2026,1,2,3", "slabs": "7,1,2,3,4,5"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.reference.floors", description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=tuple(STATISTICS))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--seeds",
        default=None,
        help="comma-separated rendering seeds (default: "
        + "; ".join(f"{k} {v}" for k, v in DEFAULT_SEEDS.items())
        + ")",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")
    a = p.parse_args(argv)
    seeds = [int(s) for s in (a.seeds or DEFAULT_SEEDS[a.what]).split(",")]
    if a.what == "phantoms":
        runs = record_phantoms(seeds, progress=not a.no_progress)
    elif a.what == "systems":
        runs = record_systems(seeds)
    else:
        runs = record_slabs(seeds, progress=not a.no_progress)
    repo = Path(__file__).resolve().parents[2]
    out = a.out.resolve()
    named = out.relative_to(repo).as_posix() if out.is_relative_to(repo) else "FILE"  # no path of this machine
    command = f"python -m tests.reference.floors {a.what} --out {named} --seeds {','.join(map(str, seeds))}"
    result = {"command": command, "z": Z, "statistic": STATISTICS[a.what], "runs": runs}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What the speckle channels of the dynamic field add to ``doct-classify``'s default decision on the phantom grid.

Inside static tissue the static population's speckle neither moves nor decays, and it holds the window's
cross-correlation peak at the centre (docs/concepts/speckle-motion.md §3 (d)): rule 0 (coherent motion) and
rule 5 (a held pattern that moved) of docs/abstention.md see a flow there only where it moves most of the peak.
The dynamic field, the complex field less its temporal mean at each pixel, is the moving population's alone
(§3 (f)); ``torchdoct maps --speckle-dynamic`` writes its channels (``xcd_…``) and the two rules read them beside
the field's. This script measures, per part of :data:`PARTS` (the grid's 54 cells of one geometry and static
context, :func:`classifier.bench.grid.full_cells`, at the benchmark's seed and with the default model of the
geometry), the default decision at windows 1 and 5 on the maps ``torchdoct maps --signature`` writes
(``default``) and on the same maps with the dynamic channels (``dynamic``):

* per motion, over the band interiors the grid scores (:func:`classifier.bench.grid.interior_pixels` at
  :func:`classifier.bench.grid.scoring_edge_px`, the pixels the model classified): the coverage (share decided
  as a single motion), the recall on decided pixels and the wrong share (share of the motion's pixels decided as
  another motion, the false-detection check of both rules for diffusion and random-ballistic motion);
* per part and window: the coverage over the motions' pixels, the balanced accuracy on decided pixels (the mean
  recall over the motions with a decided pixel), the worst motion's pooled wrong share, and the worst cell's
  (how many cells have a motion with more than :data:`CELL_WRONG_MAX` of its pixels decided as another);
* the maps' time: the seconds of the signature maps and of the dynamic channels alone, summed over the part's
  cells (one run on one machine: ``torchdoct bench maps-channels`` is the benchmark of the maps' cost).

Run from the repository root with a development install::

    python -m research.dynamic_speckle --out DIR [--parts P,...] [--cells N]

It writes ``DIR/dynamic-speckle.json`` and ``.md`` (the recorded run: ``research/results/dynamic-speckle.*``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: the parts: (geometry, static context) of the phantom grid
PARTS = {f"{g}-{c}": (g, c) for g in ("volume", "bscan") for c in ("background", "edge", "none")}
MODELS = {"volume": "signature", "bscan": "signature-bscan"}
POOLS = (1, 5)
MOTIONS = ("diffusion", "ballistic", "flow")
#: the grid's per-cell bound (docs/benchmarks/goals.md, the row "Every grid cell")
CELL_WRONG_MAX = 0.10
SEED = 0
VARIANTS = ("default", "dynamic")


def _counts() -> dict[str, dict[str, int]]:
    return {m: {"pixels": 0, "decided": 0, "right": 0, "wrong": 0} for m in MOTIONS}


def cell_counts(cell, model, levels, density: float) -> tuple[dict[str, Any], dict[str, float]]:
    """Render and map one grid cell; per variant and window the counts per motion over the scored pixels, and
    the seconds of the signature maps and of the dynamic channels."""
    from classifier.bench import grid as G
    from classifier.infer import classify_maps
    from torchdoct.measured.maps import compute_maps
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.sim.speckle import dynamic_speckle_features

    phantoms = G.cell_phantoms(cell, model.spec, levels, density, None)
    pitch = float(phantoms[0]["grid"]["pitch_x_um"])
    res, seq = G.render_sequence(phantoms, cell.key, SEED)
    t0 = time.perf_counter()
    maps = G.signature_maps(seq, model.spec)
    t1 = time.perf_counter()
    ndim = len(seq.axes) - 1
    dyn = compute_maps(
        seq, ["original"], metrics=("mean_db",), speckle=dynamic_speckle_features(ndim, n_frames=seq.data.shape[0])
    )
    t2 = time.perf_counter()
    keep = [i for i, c in enumerate(dyn.channels) if c.startswith("xcd_")]
    recs = {r["name"]: r for r in dyn.meta["channels"]}
    both = dataclasses.replace(
        maps,
        maps=np.concatenate([maps.maps, dyn.maps[keep]]),
        channels=tuple(maps.channels) + tuple(dyn.channels[i] for i in keep),
        meta={**maps.meta, "channels": list(maps.meta["channels"]) + [recs[dyn.channels[i]] for i in keep]},
    )
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for variant, m in zip(VARIANTS, (maps, both)):
            path = write_maps(Path(tmp) / f"{variant}.npz", m)
            for w in POOLS:
                d = classify_maps(path, model, pool=w)
                names = np.asarray(d.label_names)
                edge = G.scoring_edge_px(model.spec, pitch, w)
                c = _counts()
                for k in MOTIONS:
                    sel = (G.interior_pixels(res.labels, k, edge) & (d.labels != 255)).ravel()
                    got = names[d.labels.ravel()[sel]]
                    c[k]["pixels"] = int(sel.sum())
                    c[k]["right"] = int((got == k).sum())
                    c[k]["wrong"] = int(np.isin(got, [o for o in MOTIONS if o != k]).sum())
                    c[k]["decided"] = c[k]["right"] + c[k]["wrong"]
                out[f"{variant}/{w}"] = c
    return out, {"signature_maps": t1 - t0, "dynamic_channels": t2 - t1}


def scores(c: dict[str, dict[str, int]]) -> dict[str, Any]:
    """Coverage, recall on decided pixels and wrong share per motion; their means and the worst wrong share."""
    per = {}
    for m, v in c.items():
        n = max(v["pixels"], 1)
        per[m] = {
            "pixels": v["pixels"],
            "coverage": v["decided"] / n,
            "recall": v["right"] / v["decided"] if v["decided"] else None,
            "wrong_share": v["wrong"] / n,
        }
    rec = [p["recall"] for p in per.values() if p["recall"] is not None]
    n_all = sum(v["pixels"] for v in c.values())
    return {
        "per_motion": per,
        # over the motions' pixels, as the grid benchmark's summary_by_context
        "coverage": sum(v["decided"] for v in c.values()) / n_all if n_all else 0.0,
        "balanced_accuracy": float(np.mean(rec)) if rec else None,
        "worst_wrong_share": max(p["wrong_share"] for p in per.values()),
    }


def run_part(part: str, n_cells: int | None, progress: bool = True) -> dict[str, Any]:
    """One part of :data:`PARTS`: the scores of both variants at both windows, pooled and of the worst cell."""
    from tqdm.auto import tqdm

    from classifier.bench import grid as G
    from classifier.infer import load_model
    from classifier.prior import Prior

    geometry, context = PARTS[part]
    model = load_model(MODELS[geometry])
    levels = G.speed_levels(model.spec)
    density = float(min(Prior().density_per_um3))
    cells = [c for c in G.full_cells(SEED) if c.geometry == geometry and c.context == context][:n_cells]
    pooled = {f"{v}/{w}": _counts() for v in VARIANTS for w in POOLS}
    worst: dict[str, list[tuple[float, str]]] = {k: [] for k in pooled}
    seconds = {"signature_maps": 0.0, "dynamic_channels": 0.0}
    for cell in tqdm(cells, desc=part, disable=not progress):
        counts, t = cell_counts(cell, model, levels, density)
        for k, s in t.items():
            seconds[k] += s
        for key, c in counts.items():
            for m in MOTIONS:
                for f in c[m]:
                    pooled[key][m][f] += c[m][f]
            worst[key].append((scores(c)["worst_wrong_share"], cell.key))
    out: dict[str, Any] = {"geometry": geometry, "context": context, "model": MODELS[geometry], "cells": len(cells)}
    out["windows"] = {
        str(w): {
            v: {
                **scores(pooled[f"{v}/{w}"]),
                "worst_cell": max(worst[f"{v}/{w}"])[0],
                "worst_cell_key": max(worst[f"{v}/{w}"])[1],
                "cells_over": sum(x > CELL_WRONG_MAX for x, _ in worst[f"{v}/{w}"]),
            }
            for v in VARIANTS
        }
        for w in POOLS
    }
    out["seconds"] = seconds
    return out


def run(parts: Sequence[str], n_cells: int | None, progress: bool = True) -> dict[str, Any]:
    t0 = time.perf_counter()
    res: dict[str, Any] = {"benchmark": "dynamic-speckle", "seed": SEED, "cell_wrong_max": CELL_WRONG_MAX}
    res["parts"] = {p: run_part(p, n_cells, progress) for p in parts}
    res["seconds"] = time.perf_counter() - t0
    res["command"] = (
        "python -m research.dynamic_speckle --out DIR"
        + (f" --parts {','.join(parts)}" if list(parts) != list(PARTS) else "")
        + (f" --cells {n_cells}" if n_cells else "")
    )
    return res


def _f(v: Any) -> str:
    return "–" if v is None else f"{v:.3f}"


def format_md(res: dict[str, Any]) -> str:
    lines = [
        "# What the dynamic field's speckle channels add to the default decision",
        "",
        "Per part (the phantom grid's cells of one geometry and static context, at the benchmark's seed), the "
        "default decision of `doct-classify` on the maps `torchdoct maps --signature` writes (`default`) and on the "
        "same maps with `--speckle-dynamic` (`dynamic`), over the band interiors the grid scores. Coverage: share "
        "of a motion's pixels decided as a single motion; wrong: share decided as another motion; "
        f"cells over: cells with a motion more than {res['cell_wrong_max']:g} wrong.",
        "",
        "| part | window | maps | coverage | bal. acc. | worst wrong share | worst cell (cells over) "
        "| coverage diffusion / ballistic / flow | wrong diffusion / ballistic / flow |",
        "|---|---|---|---:|---:|---:|---:|---|---|",
    ]
    for part, pr in res["parts"].items():
        for w, e in pr["windows"].items():
            for v in VARIANTS:
                s = e[v]
                pm = s["per_motion"]
                lines.append(
                    f"| {part} | {w} | {v} | {_f(s['coverage'])} | {_f(s['balanced_accuracy'])} | "
                    f"{_f(s['worst_wrong_share'])} | {_f(s['worst_cell'])} ({s['cells_over']}) | "
                    + " / ".join(_f(pm[m]["coverage"]) for m in MOTIONS)
                    + " | "
                    + " / ".join(_f(pm[m]["wrong_share"]) for m in MOTIONS)
                    + " |"
                )
    lines += ["", "Maps' time over each part's cells (one run; `torchdoct bench maps-channels` is the benchmark):", ""]
    lines += ["| part | signature maps (s) | dynamic channels alone (s) | ratio |", "|---|---:|---:|---:|"]
    for part, pr in res["parts"].items():
        s = pr["seconds"]
        lines.append(
            f"| {part} | {s['signature_maps']:.0f} | {s['dynamic_channels']:.0f} | "
            f"{s['dynamic_channels'] / max(s['signature_maps'], 1e-9):.2f} |"
        )
    lines += ["", f"Reproduce: `{res['command']}` ({res['seconds'] / 60:.0f} min on the machine of the record).", ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.dynamic_speckle", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder (dynamic-speckle.json and .md)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated parts of {', '.join(PARTS)}")
    ap.add_argument("--cells", type=int, default=None, help="only the first N cells of each part (a quick look)")
    ap.add_argument("--force", action="store_true", help="overwrite dynamic-speckle.json and .md")
    a = ap.parse_args(argv)
    parts = [p.strip() for p in a.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts or len(set(parts)) != len(parts):
        ap.error(f"--parts {a.parts!r}: give distinct names among {', '.join(PARTS)}")
    if a.cells is not None and a.cells < 1:
        ap.error("--cells must be at least 1")
    a.out.mkdir(parents=True, exist_ok=True)
    targets = [a.out / "dynamic-speckle.json", a.out / "dynamic-speckle.md"]
    if not a.force and any(t.exists() for t in targets):
        ap.error(f"{targets[0]} or {targets[1]} exists: pass --force to overwrite it, or another --out")
    res = run(parts, a.cells)
    targets[0].write_text(json.dumps(res, indent=1) + "\n")
    targets[1].write_text(format_md(res))
    print(format_md(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A candidate rule against the phantom grid: a speckle pattern that decayed in place is not a flow.

In a volume every axis is seen, and a flow decorrelates a pixel only by carrying its pattern away: the dynamic
field's centred correlation (the field less its temporal mean, docs/concepts/speckle-motion.md §3 (f)) falls
below 1/2 only once the pattern has moved by ``s·√(2 ln 2)`` along the flow, and there its peak keeps its height
off the centre. A pattern whose peak stays at the centre while it decays is not a translation. The candidate
(:func:`decayed_in_place`): where the field itself decorrelated (rule 2 of docs/abstention.md passes: the
window's correlation at the longest lag below :data:`classifier.ambiguity.DECORRELATED_BELOW`, the guard against
a creeping flow, whose power stays in the temporal mean) and, in the dynamic field, at the first lag whose
centred correlation is at most 1/2, the lag before it held the pattern (peak at least 1/2) and at both lags at
most :data:`MOVED_MAX` of the peak had moved off the centre, a ``ballistic-or-flow`` set would be
``ballistic``.

Not a rule of ``doct-classify``: this script measures what it would decide on the phantom grid's volume cells
inside static tissue (:data:`PARTS`, seed 0, window 5), on the maps with ``--speckle-dynamic``, over the band
interiors the grid scores. Per motion: the share of its pixels the default decision leaves ``ballistic-or-flow``
and the share the candidate would decide ``ballistic`` (a gain for random-ballistic motion, a wrong decision for
the others), per speed level; and the worst cell's wrong share. It measures the grid only: a rule that decides
random-ballistic motion needs its null measured on other phantoms and simulators too.

Run from the repository root with a development install::

    python -m research.decayed_in_place --out DIR [--parts P,...] [--cells N]

It writes ``DIR/decayed-in-place.json`` and ``.md`` (the recorded run: ``research/results/decayed-in-place.*``).
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

#: the parts: (geometry, static context) of the phantom grid
PARTS = {"volume-background": ("volume", "background"), "volume-edge": ("volume", "edge")}
MOTIONS = ("diffusion", "ballistic", "flow")
POOL = 5
SEED = 0
#: the largest share of the dynamic field's peak moved off the centre that counts as in place
MOVED_MAX = 0.1
#: the dynamic field's centred correlation at or below which its pattern counts as decayed, and the peak from
#: which it counts as held
HALF = 0.5
SET = "ballistic-or-flow"
#: the part measured by default: the goals row inside static tissue
DEFAULT_PART = "volume-background"


def decayed_in_place(channels: Mapping[str, np.ndarray], lags: Sequence[int]) -> np.ndarray:
    """The candidate (module docstring) per pixel of the maps' ``channels`` (name → map: ``xc_centre_m@original``
    at the longest of ``lags``, ``xcd_centre_m@original`` and ``xcd_peak_m@original`` at every lag); NaN counts as
    not decayed in place."""
    from classifier.ambiguity import DECORRELATED_BELOW

    lags = sorted(int(m) for m in lags)
    with np.errstate(invalid="ignore", divide="ignore"):
        field_decorrelated = np.asarray(channels[f"xc_centre_{lags[-1]}@original"], np.float64) < DECORRELATED_BELOW
        seen = np.zeros(field_decorrelated.shape, bool)  # a lag with a decayed dynamic pattern came already
        found = np.zeros(field_decorrelated.shape, bool)
        prev_peak = prev_moved = None
        for m in lags:
            peak = np.asarray(channels[f"xcd_peak_{m}@original"], np.float64)
            centre = np.asarray(channels[f"xcd_centre_{m}@original"], np.float64)
            moved = (peak - centre) / peak
            first = ~seen & (centre <= HALF)
            if prev_peak is not None:
                found |= first & (prev_peak >= HALF) & (prev_moved <= MOVED_MAX) & (moved <= MOVED_MAX)
            seen |= centre <= HALF
            prev_peak, prev_moved = peak, moved
    return field_decorrelated & found


def cell_counts(cell, model, levels, density: float) -> dict[str, dict[str, int]]:
    """Render and map one grid cell with the dynamic channels; per motion over the scored pixels at window 5: the
    pixels, those the default decision leaves ``ballistic-or-flow``, and those the candidate would decide."""
    from classifier.bench import grid as G
    from classifier.infer import classify_maps
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.sim.speckle import default_lags

    phantoms = G.cell_phantoms(cell, model.spec, levels, density, None)
    pitch = float(phantoms[0]["grid"]["pitch_x_um"])
    res, seq = G.render_sequence(phantoms, cell.key, SEED)
    n_t = seq.data.shape[0]
    both = G.signature_maps(seq, model.spec, dynamic=True)
    channels = {c: both.maps[i] for i, c in enumerate(both.channels)}
    with tempfile.TemporaryDirectory() as tmp:
        d = classify_maps(write_maps(Path(tmp) / "maps.npz", both), model, pool=POOL)
    names = np.asarray(d.label_names)
    fire = decayed_in_place(channels, default_lags(n_t))
    edge = G.scoring_edge_px(model.spec, pitch, POOL)
    out = {}
    for m in MOTIONS:
        sel = G.interior_pixels(res.labels, m, edge) & (d.labels != 255)
        in_set = names[d.labels[sel]] == SET
        out[m] = {"pixels": int(sel.sum()), "set": int(in_set.sum()), "decided": int((in_set & fire[sel]).sum())}
    return out


def run(parts: Sequence[str], n_cells: int | None, progress: bool = True) -> dict[str, Any]:
    from tqdm.auto import tqdm

    from classifier.bench import grid as G
    from classifier.infer import load_model
    from classifier.prior import Prior

    t0 = time.perf_counter()
    model = load_model("signature")
    levels = G.speed_levels(model.spec)
    density = float(min(Prior().density_per_um3))
    res: dict[str, Any] = {"benchmark": "decayed-in-place", "seed": SEED, "pool": POOL, "moved_max": MOVED_MAX}
    res["parts"] = {}
    for part in parts:
        geometry, context = PARTS[part]
        cells = [c for c in G.full_cells(SEED) if c.geometry == geometry and c.context == context][:n_cells]
        per_level = {lv: {m: {"pixels": 0, "set": 0, "decided": 0} for m in MOTIONS} for lv in ("slow", "mid", "fast")}
        worst = (-1.0, None)
        for cell in tqdm(cells, desc=part, disable=not progress):
            c = cell_counts(cell, model, levels, density)
            for m in MOTIONS:
                for k in c[m]:
                    per_level[cell.level][m][k] += c[m][k]
            wrong = max(c[m]["decided"] / max(c[m]["pixels"], 1) for m in MOTIONS if m != "ballistic")
            worst = max(worst, (wrong, cell.key), key=lambda x: x[0])
        total = {
            m: {k: sum(per_level[lv][m][k] for lv in per_level) for k in ("pixels", "set", "decided")} for m in MOTIONS
        }

        def shares(c: dict[str, dict[str, int]]) -> dict[str, dict[str, float]]:
            return {
                m: {"set": v["set"] / max(v["pixels"], 1), "decided": v["decided"] / max(v["pixels"], 1)}
                for m, v in c.items()
            }

        res["parts"][part] = {
            "cells": len(cells),
            "counts": total,
            "shares": shares(total),
            "shares_per_level": {lv: shares(v) for lv, v in per_level.items()},
            "worst_cell_wrong_share": worst[0],
            "worst_cell": worst[1],
        }
    res["seconds"] = time.perf_counter() - t0
    res["command"] = (
        "python -m research.decayed_in_place --out DIR"
        + (f" --parts {','.join(parts)}" if list(parts) != [DEFAULT_PART] else "")
        + (f" --cells {n_cells}" if n_cells else "")
    )
    return res


def format_md(res: dict[str, Any]) -> str:
    lines = [
        "# A candidate rule: a speckle pattern that decayed in place is not a flow",
        "",
        f"Per part, at window {res['pool']}, over the band interiors the grid scores (seed {res['seed']}): the share of "
        "each motion's pixels the default decision (maps with `--speckle-dynamic`) leaves `ballistic-or-flow`, and "
        "the share the candidate would decide `ballistic` (random-ballistic motion: a gain; the others: wrong).",
        "",
        "| part | level | set: diffusion / ballistic / flow | decided ballistic: diffusion / ballistic / flow |",
        "|---|---|---|---|",
    ]
    for part, pr in res["parts"].items():
        rows = [("all", pr["shares"])] + list(pr["shares_per_level"].items())
        for lv, sh in rows:
            lines.append(
                f"| {part} | {lv} | "
                + " / ".join(f"{sh[m]['set']:.3f}" for m in MOTIONS)
                + " | "
                + " / ".join(f"{sh[m]['decided']:.4f}" for m in MOTIONS)
                + " |"
            )
    lines += [""]
    for part, pr in res["parts"].items():
        lines.append(
            f"{part}: worst cell's wrong share (diffusion or flow decided ballistic) "
            f"{pr['worst_cell_wrong_share']:.4f} (`{pr['worst_cell']}`), {pr['cells']} cells."
        )
    lines += ["", f"Reproduce: `{res['command']}` ({res['seconds'] / 60:.0f} min on the machine of the record).", ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m research.decayed_in_place", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder (decayed-in-place.json and .md)")
    ap.add_argument("--parts", default=DEFAULT_PART, help=f"comma-separated parts of {', '.join(PARTS)}")
    ap.add_argument("--cells", type=int, default=None, help="only the first N cells of each part (a quick look)")
    ap.add_argument("--force", action="store_true", help="overwrite decayed-in-place.json and .md")
    a = ap.parse_args(argv)
    parts = [p.strip() for p in a.parts.split(",") if p.strip()]
    if not parts or any(p not in PARTS for p in parts) or len(set(parts)) != len(parts):
        ap.error(f"--parts {a.parts!r}: give distinct names among {', '.join(PARTS)}")
    if a.cells is not None and a.cells < 1:
        ap.error("--cells must be at least 1")
    a.out.mkdir(parents=True, exist_ok=True)
    targets = [a.out / "decayed-in-place.json", a.out / "decayed-in-place.md"]
    if not a.force and any(t.exists() for t in targets):
        ap.error(f"{targets[0]} or {targets[1]} exists: pass --force to overwrite it, or another --out")
    res = run(parts, a.cells)
    targets[0].write_text(json.dumps(res, indent=1) + "\n")
    targets[1].write_text(format_md(res))
    print(format_md(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

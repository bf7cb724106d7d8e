"""Validation of ``torchdoct translate``: one phantom rendered on two systems, the translated maps of the
first against the directly rendered maps of the second, per region and motion type.

``python -m research.translation --out DIR [--seed 2026 ...]``:

1. ``torchdoct render motion-types-two-systems`` (the same scatterers seen by the 840-nm system, 4.9/3.8 µm,
   and a 1310-nm system, 10/8 µm; 30 dB SNR);
2. ``torchdoct maps`` of the 840-nm rendering with the signature (original, axial=14, lateral=18) and of the
   1310-nm rendering (LIV and OCDS at its original resolution: the reference);
3. ``torchdoct translate`` of the 840-nm maps to the 1310-nm system (``--to motion-types-two-systems
   --to-system 1310nm-10um``);
4. per region (motion type and rendered magnitude; pixels at least ``--edge-um`` from another label, and
   translated, code 0): the median of the translated and of the direct values, the direct pixel-to-pixel
   SD, ``|median translated − median direct| / SD`` (goal ≤ 1/3), the share of direct pixels inside their
   translated 68 % interval (goal 0.60-0.76), and, for scale, the same bias of the untranslated 840-nm
   values (what comparing the two systems' numbers as they are would give).

Writes ``DIR/translation-validation.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import torchdoct_command

PHANTOM = "motion-types-two-systems"
SOURCE, TARGET = "840nm-high", "1310nm-10um"
_NAMES = {2: "diffusion", 3: "ballistic", 4: "flow"}
_GOALS = {"abs_bias_over_sd": 1.0 / 3.0, "coverage_68": (0.60, 0.76)}


def chain(out: Path, seed: int, trials: int) -> dict[str, Path]:
    """Render, maps and translate for one seed; returns the files."""
    stem = out / f"mt2-{seed}"
    seq = {s: Path(f"{stem}-{s}.npz") for s in (SOURCE, TARGET)}
    files = {
        "source_maps": out / f"mt2-{seed}-{SOURCE}-maps.npz",
        "target_maps": out / f"mt2-{seed}-{TARGET}-maps.npz",
        "translated": out / f"mt2-{seed}-translated.npz",
        **{f"seq_{k}": v for k, v in seq.items()},
    }
    torchdoct_command(
        ["render", PHANTOM, "--out", f"{stem}.npz", "--seed", str(seed), "--no-preview", "--no-progress", "--force"]
    )
    torchdoct_command(
        [
            "maps",
            str(seq[SOURCE]),
            "--resolution",
            "original",
            "--resolution",
            "axial=14",
            "--resolution",
            "lateral=18",
            "--signature",
            "--out",
            str(files["source_maps"]),
            "--no-progress",
            "--force",
        ]
    )
    torchdoct_command(
        [
            "maps",
            str(seq[TARGET]),
            "--metrics",
            "liv,ocds",
            "--out",
            str(files["target_maps"]),
            "--no-progress",
            "--force",
        ]
    )
    torchdoct_command(
        [
            "translate",
            str(files["source_maps"]),
            "--to",
            PHANTOM,
            "--to-system",
            TARGET,
            "--out",
            str(files["translated"]),
            "--trials",
            str(trials),
            "--seed",
            str(seed),
            "--no-progress",
            "--force",
        ]
    )
    return files


def _inner(labels: np.ndarray, params: np.ndarray, edge_px: tuple[int, int]) -> np.ndarray:
    """Region id per pixel (code·1e6 + index of its magnitude), −1 within ``edge_px`` (z, x) of another id."""
    from scipy import ndimage

    key = labels.astype(np.int64) * 1_000_000 + np.round(np.log10(np.maximum(params, 1e-12)) * 1000).astype(np.int64)
    size = (2 * edge_px[0] + 1, 2 * edge_px[1] + 1)
    same = (ndimage.maximum_filter(key, size=size, mode="nearest") == key) & (
        ndimage.minimum_filter(key, size=size, mode="nearest") == key
    )
    return np.where(same, key, -1)


def score(files: dict[str, Path], edge_um: float = 10.0) -> list[dict]:
    """Per region: the comparison of step 4 of the module docstring."""
    from torchdoct.measured.mapsfile import read_maps

    with np.load(files[f"seq_{TARGET}"], allow_pickle=False) as z:
        labels, lp = z["labels"], z["label_params"]
    src, tgt, tr = (read_maps(files[k]) for k in ("source_maps", "target_maps", "translated"))
    pitch = tgt.meta["pitch_um"]
    labels = labels.reshape(tgt.spatial_shape)
    rows = []
    for code, name in _NAMES.items():
        mag = lp[0 if code == 2 else 1].reshape(labels.shape)
        ids = _inner(
            np.where(labels == code, code, 0),
            np.where(labels == code, mag, 0.0),
            (int(round(edge_um / pitch["z"])), int(round(edge_um / pitch["x"]))),
        )
        for value in sorted(np.unique(mag[(labels == code) & (ids >= 0)])):
            region = (labels == code) & (ids >= 0) & (mag == value)
            status = tr[f"translation@{TARGET}"]
            ok = region & (status == 0)
            row = {
                "motion": name,
                "magnitude": float(value),
                "unit": "µm²/s" if code == 2 else "µm/s",
                "pixels": int(region.sum()),
                "translated": int(ok.sum()),
                "codes": {str(int(c)): int(((status == c) & region).sum()) for c in np.unique(status[region])},
            }
            for m in ("liv", "ocds"):
                direct = tgt[f"{m}@original"][ok]
                trans, lo, hi = (tr[f"{m}{s}@{TARGET}"][ok] for s in ("", "_lower_68", "_upper_68"))
                untrans = src[f"{m}@original"][ok]
                sd = float(np.std(direct, ddof=1)) if direct.size > 1 else float("nan")
                med = float(np.median(direct)) if direct.size else float("nan")
                row[m] = {
                    "direct_median": med,
                    "direct_sd": sd,
                    "translated_median": float(np.median(trans)) if trans.size else float("nan"),
                    "abs_bias_over_sd": abs(float(np.median(trans)) - med) / sd if trans.size else float("nan"),
                    "coverage_68": float(np.mean((direct >= lo) & (direct <= hi))) if trans.size else float("nan"),
                    "untranslated_median": float(np.median(untrans)) if untrans.size else float("nan"),
                    "untranslated_abs_bias_over_sd": abs(float(np.median(untrans)) - med) / sd
                    if untrans.size
                    else float("nan"),
                }
            rows.append(row)
    return rows


def summarize(rows: list[dict]) -> dict:
    """Per motion type and overall: the median over regions of |bias|/SD and the pixel-weighted coverage."""
    out = {}
    for motion in (*_NAMES.values(), "all"):
        sel = [r for r in rows if motion in ("all", r["motion"]) and r["translated"] > 0]
        if not sel:
            continue
        out[motion] = {
            m: {
                "median_abs_bias_over_sd": float(np.median([r[m]["abs_bias_over_sd"] for r in sel])),
                "max_abs_bias_over_sd": float(np.max([r[m]["abs_bias_over_sd"] for r in sel])),
                "coverage_68": float(
                    np.average([r[m]["coverage_68"] for r in sel], weights=[r["translated"] for r in sel])
                ),
                "regions_within_goal": float(
                    np.mean([r[m]["abs_bias_over_sd"] <= _GOALS["abs_bias_over_sd"] for r in sel])
                ),
                "untranslated_median_abs_bias_over_sd": float(
                    np.median([r[m]["untranslated_abs_bias_over_sd"] for r in sel])
                ),
            }
            for m in ("liv", "ocds")
        }
        out[motion]["translated_share"] = float(
            sum(r["translated"] for r in sel) / max(sum(r["pixels"] for r in sel), 1)
        )
    return out


def to_markdown(result: dict) -> str:
    L = [
        "# Translation 840 nm → 1310 nm: translated against directly rendered maps",
        "",
        f"Command: `{result['command']}` ({result['seconds']:.0f} s). Phantom `{PHANTOM}`, seeds "
        f"{result['seeds']}, regions at least {result['edge_um']:g} µm from another label, translated pixels "
        "(code 0). Goals: |median translated − median direct| ≤ SD/3 of the direct pixels; 68 % intervals "
        "cover 0.60-0.76 of the direct pixels. 'untranslated': the 840-nm value taken as it is.",
        "",
        "| motion | magnitude | seed | pixels (translated) | LIV direct (SD) | LIV translated | \\|bias\\|/SD "
        "| cover 68 | untranslated \\|bias\\|/SD | OCDS direct (SD) | OCDS translated | \\|bias\\|/SD | cover 68 "
        "| untranslated \\|bias\\|/SD |",
        "|" + "---|" * 14,
    ]
    for seed, rows in result["regions"].items():
        for r in rows:
            li, oc = r["liv"], r["ocds"]
            L.append(
                f"| {r['motion']} | {r['magnitude']:g} {r['unit']} | {seed} | {r['pixels']} ({r['translated']}) | "
                f"{li['direct_median']:.2f} ({li['direct_sd']:.2f}) | {li['translated_median']:.2f} | "
                f"{li['abs_bias_over_sd']:.2f} | {li['coverage_68']:.2f} | {li['untranslated_abs_bias_over_sd']:.2f} | "
                f"{oc['direct_median']:.3f} ({oc['direct_sd']:.3f}) | {oc['translated_median']:.3f} | "
                f"{oc['abs_bias_over_sd']:.2f} | {oc['coverage_68']:.2f} | {oc['untranslated_abs_bias_over_sd']:.2f} |"
            )
    L += [
        "",
        "By motion type (median over regions of |bias|/SD, max, and the share of regions within SD/3; "
        "pixel-weighted coverage of the 68 % interval):",
        "",
        "| motion | translated share | LIV \\|bias\\|/SD median (max; within SD/3) | LIV cover 68 | OCDS "
        "\\|bias\\|/SD median (max; within SD/3) | OCDS cover 68 | untranslated LIV / OCDS \\|bias\\|/SD |",
        "|---|---|---|---|---|---|---|",
    ]
    for motion, s in result["summary"].items():
        li, oc = s["liv"], s["ocds"]
        L.append(
            f"| {motion} | {s['translated_share']:.2f} | {li['median_abs_bias_over_sd']:.2f} "
            f"({li['max_abs_bias_over_sd']:.2f}; {li['regions_within_goal']:.2f}) | {li['coverage_68']:.2f} | "
            f"{oc['median_abs_bias_over_sd']:.2f} ({oc['max_abs_bias_over_sd']:.2f}; "
            f"{oc['regions_within_goal']:.2f}) | {oc['coverage_68']:.2f} | "
            f"{li['untranslated_median_abs_bias_over_sd']:.2f} / {oc['untranslated_median_abs_bias_over_sd']:.2f} |"
        )
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.translation", description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True, help="working and output directory")
    p.add_argument("--seed", type=int, action="append", help="rendering seeds (repeat; default 2026)")
    p.add_argument("--trials", type=int, default=128, help="torchdoct translate --trials")
    p.add_argument("--edge-um", type=float, default=10.0)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = args.seed or [2026]
    t0 = time.perf_counter()
    regions = {}
    for seed in seeds:
        regions[str(seed)] = score(chain(out, seed, args.trials), args.edge_um)
    rows = [r for rs in regions.values() for r in rs]
    result = {
        "command": "python -m research.translation --out DIR "
        + " ".join(f"--seed {s}" for s in seeds)
        + (f" --trials {args.trials}" if args.trials != 128 else ""),
        "seeds": seeds,
        "edge_um": args.edge_um,
        "goals": _GOALS,
        "regions": regions,
        "summary": summarize(rows),
        "seconds": time.perf_counter() - t0,
    }
    (out / "translation-validation.json").write_text(json.dumps(result, indent=1))
    (out / "translation-validation.md").write_text(to_markdown(result))
    print(to_markdown(result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

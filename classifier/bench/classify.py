"""``torchdoct bench classify``: throughput of :func:`classifier.infer.classify_maps` (pixels/s).

A synthetic maps file in the project's maps format holds, for every feature of the shipped model's
specification, LIV (uniform 0–35 dB²) and OCDS (uniform −0.2–1.2 s⁻¹) values and a mean-dB channel,
on a ``size × size`` grid; it is classified at pool 1 and pool 5 and the best of ``repeats`` runs is
reported. Reading, feature assembly, onnxruntime and the decision rule are all inside the timing.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["bench_classify", "format_bench_classify", "HELP", "DESCRIPTION", "add_arguments", "benchmark"]


def _synthetic_maps(path: Path, spec, size: int, seed: int) -> Path:
    from ..features import metric_unit

    rng = np.random.default_rng(seed)
    chans, arrays = [], []
    for metric, c in spec.features:
        chans.append(
            {
                "name": f"{metric}@{c.name}",
                "metric": metric,
                "unit": metric_unit(metric),
                "resolution": c.name,
                "wavelength_um": c.wavelength_um,
                "lateral_resolution_um": c.lateral_resolution_um,
                "axial_resolution_um": c.axial_resolution_um,
            }
        )
        lo, hi = (0.0, 35.0) if metric == "liv" else (-0.2, 1.2)
        arrays.append(rng.uniform(lo, hi, (size, size)))
    c0 = spec.configurations[0]
    chans.append(
        {
            "name": f"mean_db@{c0.name}",
            "metric": "mean_db",
            "unit": "dB",
            "resolution": c0.name,
            "wavelength_um": c0.wavelength_um,
            "lateral_resolution_um": c0.lateral_resolution_um,
            "axial_resolution_um": c0.axial_resolution_um,
        }
    )
    arrays.append(rng.uniform(-5.0, 5.0, (size, size)))
    meta = {
        "channels": chans,
        "axes": "CZX",
        "pitch_um": {"z": 2.0, "x": 2.0},
        "frame_times_s": [i * spec.frame_interval_s for i in range(spec.n_frames)],
        "system": {
            "name": "synthetic",
            "wavelength_um": c0.wavelength_um,
            "lateral_resolution_um": c0.lateral_resolution_um,
            "axial_resolution_um": c0.axial_resolution_um,
            "refractive_index": spec.refractive_index,
        },
        "ocds_delay_range_s": list(spec.ocds_delay_range_s),
        "source": "synthetic",
    }
    np.savez(
        path,
        maps=np.stack(arrays).astype(np.float32),
        channels=np.array([c["name"] for c in chans]),
        meta_json=np.asarray(json.dumps(meta)),
    )
    return path


def bench_classify(*, size: int = 512, repeats: int = 3, model: str | None = None, seed: int = 0) -> dict[str, Any]:
    """Pixels per second of ``classify_maps`` on a synthetic ``size × size`` maps file."""
    from torchdoct.runtime.resources import CLASSIFY_COPIES, check_bench

    from ..infer import classify_maps, load_model

    mdl = load_model(model)
    channels = len(mdl.spec.features) + 1
    # the channels drawn in float64, the float32 file, and classification's copies of it
    check_bench(
        "torchdoct bench classify",
        (8 + 4 + 4 * CLASSIFY_COPIES) * channels * int(size) ** 2,
        f"{size}×{size} pixels, {channels} channels",
        "give a smaller --size",
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = _synthetic_maps(Path(tmp) / "maps.npz", mdl.spec, size, seed)
        for pool in (1, 5):
            best = float("inf")
            info = {}
            for _ in range(max(1, repeats)):
                t0 = time.perf_counter()
                res = classify_maps(path, mdl, pool=pool, background_db=None)
                best = min(best, time.perf_counter() - t0)
                info = res.info
            rows.append(
                {
                    "pool": pool,
                    "pixels": size * size,
                    "seconds": best,
                    "pixels_per_s": size * size / best,
                    "classified": info["classified"],
                    "stages_s": info["seconds"],
                }
            )
    from torchdoct.runtime.machine import machine_info

    return {
        "benchmark": "classify",
        "model": mdl.spec.name,
        "size": size,
        "repeats": repeats,
        "rows": rows,
        "target_pixels_per_s": 1e6,
        "onnxruntime_threads": os.environ.get("OMP_NUM_THREADS"),
        "machine": machine_info(),
    }


def format_bench_classify(res: dict[str, Any]) -> str:
    lines = [
        f"doct-classify on a {res['size']}×{res['size']} synthetic maps file, model {res['model']!r} "
        f"(target {res['target_pixels_per_s']:.0e} pixels/s)",
        "| pool | seconds | pixels/s |",
        "|---:|---:|---:|",
    ]
    for r in res["rows"]:
        lines.append(f"| {r['pool']} | {r['seconds']:.3f} | {r['pixels_per_s']:.3g} |")
    return "\n".join(lines)


#: ``torchdoct bench classify`` (entry point ``torchdoct.bench``/``classify``, :mod:`torchdoct.cli.extensions`).
HELP = "doct-classify throughput on a 512×512 synthetic maps file"
DESCRIPTION = None


def add_arguments(bc) -> None:
    bc.add_argument("--size", type=int, default=512, help="pixels per side")
    bc.add_argument("--repeats", type=int, default=3)
    bc.add_argument(
        "--out",
        default=None,
        metavar="FILE.json",
        help="also write the result as JSON (default: printed only, nothing written)",
    )
    bc.add_argument("--model", default=None, help="shipped model name or .onnx path (default: the LIV/OCDS model)")
    bc.add_argument("--force", action="store_true")


def benchmark(args) -> tuple[Any, Any]:
    """The computation of ``args`` (``size``, ``repeats``, ``model``) and its table."""
    return (lambda: bench_classify(size=args.size, repeats=args.repeats, model=args.model)), format_bench_classify

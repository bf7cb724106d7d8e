"""``torchdoct bench maps``: the time of :func:`torchdoct.measured.maps.compute_maps` on a random complex
stack at several resolutions (measured, never asserted)."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence as _Seq
from typing import Any

import torch

from ..measured.io import SequenceData, validate_meta
from ..measured.maps import compute_maps
from ..runtime.interrupt import progress_disabled
from ..runtime.machine import machine_info
from ..runtime.resources import check_bench, maps_bytes

__all__ = ["bench_maps", "bench_maps_channels", "CHANNEL_SETS"]


def bench_maps(
    *,
    frames: int = 32,
    shape: tuple[int, int] = (512, 512),
    resolutions: _Seq[str] = ("original", "axial=14", "lateral=18"),
    metrics: _Seq[str] = ("liv", "ocds", "mean_db"),
    repeats: int = 1,
    seed: int = 0,
    signature: bool = False,
    speckle: bool = False,
    doppler: bool = False,
) -> dict[str, Any]:
    """Time :func:`compute_maps` on a random complex64 ``[frames, *shape]`` stack (measured, never asserted).

    System: 840 nm, 4.9 µm lateral / 3.8 µm axial; pitch 1.5 µm (z) × 2.0 µm (x); 204.8 ms frames.
    Returns a JSON-ready dict with the best total time over ``repeats`` and seconds per resolution.
    ``signature`` / ``speckle``: also the signature / speckle-motion channels (``torchdoct maps --signature``,
    ``--speckle``), recorded in the result. ``doppler``: also the Doppler reference and channel
    (``--doppler``); on this random field, moving speckle everywhere, the reference is searched in full and
    none is found, so the time is the estimate's without the channel.
    """

    seq = _random_stack(frames, shape, len(resolutions), metrics, seed)
    compute_maps(seq, ["original"], metrics=metrics)  # warm-up
    best, best_t = math.inf, {}
    flags = {"signature": signature, "speckle": speckle, "doppler": doppler}
    for _ in range(max(1, int(repeats))):
        tm: dict[str, float] = {}
        dt = _timed_maps(seq, resolutions, metrics, flags, tm)
        if dt < best:
            best, best_t = dt, tm
    return {
        "benchmark": "maps",
        "shape": [frames, *shape],
        "dtype": "complex64",
        "resolutions": list(resolutions),
        "metrics": list(metrics),
        "signature": bool(signature),
        "speckle": bool(speckle),
        "doppler": bool(doppler),
        "repeats": int(repeats),
        "seconds_total": best,
        "seconds_per_resolution": best_t,
        "megapixel_frames_per_s": frames * shape[0] * shape[1] * len(resolutions) / best / 1e6,
        "target_seconds": 10.0,
        "machine": machine_info(),
    }


def _timed_maps(
    seq: SequenceData,
    resolutions: _Seq[str],
    metrics: _Seq[str],
    flags: dict[str, bool],
    timings: dict[str, float] | None = None,
) -> float:
    """Seconds of one :func:`compute_maps` of ``seq`` with the channels ``flags`` names (``signature``,
    ``speckle``, ``doppler``, and ``dynamic``: the speckle channels of the dynamic field too, as
    ``torchdoct maps --speckle-dynamic``); its seconds per resolution into ``timings``."""
    speckle: bool | tuple[str, ...] | None = flags["speckle"] or None
    if flags.get("dynamic"):
        from ..sim.speckle import map_speckle_features

        speckle = map_speckle_features(len(seq.axes) - 1, n_frames=seq.data.shape[0], dynamic=True)
    t0 = time.perf_counter()
    compute_maps(
        seq,
        resolutions,
        metrics=metrics,
        timings=timings,
        signature=flags["signature"] or None,
        speckle=speckle,
        doppler=flags["doppler"] or None,
    )
    return time.perf_counter() - t0


def _random_stack(
    frames: int, shape: tuple[int, int], n_resolutions: int, metrics: _Seq[str], seed: int
) -> SequenceData:
    """The benchmark's input: a random complex64 ``[frames, *shape]`` stack of the 840-nm system (checked
    against the memory budget first)."""
    dims = [int(frames), *(int(n) for n in shape)]
    work, _ = maps_bytes(
        dims, 8, complex_samples=True, n_resolutions=n_resolutions, metrics=metrics, slab_elements=1 << 23
    )
    check_bench(
        "torchdoct bench maps",
        8 * math.prod(dims) + work,
        f"a random complex64 stack {dims}",
        "give a smaller --size or fewer --frames",
    )
    g = torch.Generator().manual_seed(int(seed))
    data = torch.randn(frames, *shape, dtype=torch.complex64, generator=g).numpy()
    meta = validate_meta(
        {
            "axes": "TZX",
            "pitch_um": {"z": 1.5, "x": 2.0},
            "frame_times_s": [i * 0.2048 for i in range(frames)],
            "system": {
                "name": "840nm-high",
                "wavelength_um": 0.84,
                "lateral_resolution_um": 4.9,
                "axial_resolution_um": 3.8,
            },
        },
        data.shape,
    )
    return SequenceData(data=data, meta=meta, source="bench")


#: The channel sets :func:`bench_maps_channels` compares: name → the flags of ``torchdoct maps``.
CHANNEL_SETS: dict[str, dict[str, bool]] = {
    "plain": {"signature": False, "speckle": False, "doppler": False, "dynamic": False},
    "signature": {"signature": True, "speckle": False, "doppler": False, "dynamic": False},
    "signature+speckle": {"signature": True, "speckle": True, "doppler": False, "dynamic": False},
    "signature+speckle+doppler": {"signature": True, "speckle": True, "doppler": True, "dynamic": False},
    # with --speckle-dynamic: the speckle channels of the dynamic field too (docs/concepts/speckle-motion.md §3 (f))
    "signature+speckle+doppler+dynamic": {"signature": True, "speckle": True, "doppler": True, "dynamic": True},
}


def bench_maps_channels(
    *,
    frames: int = 32,
    shape: tuple[int, int] = (256, 256),
    resolutions: _Seq[str] = ("original", "axial=14", "lateral=18"),
    metrics: _Seq[str] = ("liv", "ocds", "mean_db"),
    repeats: int = 3,
    seed: int = 0,
    load: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """The time of :func:`compute_maps` with each of :data:`CHANNEL_SETS` on one random stack (as
    :func:`bench_maps`), compared in one run: every round times each set once, in turn, so that a machine
    whose speed drifts slows every set alike; the best of ``repeats`` rounds is kept per set, and each set's
    time is reported as a ratio to the ``signature`` set's (what ``torchdoct maps --signature`` costs without
    the speckle and Doppler channels). ``load``: the rounds again beside a busy process
    (:class:`torchdoct.bench.BusyNeighbour`). Measured, never asserted."""
    from . import BusyNeighbour

    seq = _random_stack(frames, shape, len(resolutions), metrics, seed)

    for flags in CHANNEL_SETS.values():  # warm-up: every code path and its imports once
        _timed_maps(seq, resolutions, metrics, flags)
    modes = ["idle", "loaded"] if load else ["idle"]
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=len(modes) * max(1, int(repeats)) * len(CHANNEL_SETS), desc="bench maps-channels", unit="run")
    sets: dict[str, dict[str, Any]] = {name: dict(flags) for name, flags in CHANNEL_SETS.items()}
    for mode in modes:
        with BusyNeighbour() if mode == "loaded" else contextlib.nullcontext():
            for _ in range(max(1, int(repeats))):
                for name, flags in CHANNEL_SETS.items():
                    tm: dict[str, float] = {}
                    dt = _timed_maps(seq, resolutions, metrics, flags, tm)
                    rec = sets[name]
                    if dt < rec.get(f"seconds_{mode}", math.inf):
                        rec[f"seconds_{mode}"] = dt
                        rec[f"seconds_per_resolution_{mode}"] = tm
                    if bar is not None:
                        bar.update(1)
    if bar is not None:
        bar.close()
    for mode in modes:
        base = sets["signature"][f"seconds_{mode}"]
        for rec in sets.values():
            rec[f"ratio_to_signature_{mode}"] = rec[f"seconds_{mode}"] / base
    return {
        "benchmark": "maps-channels",
        "shape": [int(frames), *(int(n) for n in shape)],
        "dtype": "complex64",
        "resolutions": list(resolutions),
        "metrics": list(metrics),
        "repeats": int(repeats),
        "modes": modes,
        "sets": sets,
        "machine": machine_info(),
    }

"""Memory of a simulation, estimated before any work: the chunk size, the peak working memory of a
chunk and of a whole run (:func:`simulation_bytes`), and the refusal when a run would not fit
(:func:`check_simulation`: :class:`MemoryLimitError` from the one resource check of every command,
:func:`torchdoct.runtime.resources.check_resources`, raised by :func:`torchdoct.simulate` before it starts,
naming the knob to turn). :func:`release_free_memory` returns freed heap to the OS between chunks.
"""

from __future__ import annotations

from ..runtime.resources import MemoryLimitError, available_memory_bytes, check_resources
from .plan import BLOCK_TRIALS, Plan

__all__ = [
    "MemoryLimitError",
    "CHUNK_ELEMENTS",
    "BYTES_PER_ELEMENT",
    "working_elements_per_trial",
    "chunk_bytes",
    "simulation_bytes",
    "check_simulation",
    "available_memory_bytes",
    "release_free_memory",
]

#: Largest working tensor of a chunk (elements) for the default chunk size: a chunk's state stays near
#: the cache (one block of 64 trials for most scenes; measured 10-50 % faster than 8M-element chunks).
CHUNK_ELEMENTS = 1 << 18


#: Bytes of working memory per reserved slot element (measured: float64 state, float32 draws and
#: the temporaries of one frame; 10^5 trials of the largest paper cell peak below 1 GB).
BYTES_PER_ELEMENT = 40


def working_elements_per_trial(plan: Plan) -> float:
    """Largest working tensor of one trial (elements): the slots of the biggest population."""
    return max(
        3 * (p.capacity + p.entry_capacity + p.entry_proposal_capacity + p.immigrant_proposal_capacity)
        + (p.evaluations_per_trial if p.sampler == "drift" else 0)
        for p in plan.populations
    )


def chunk_bytes(plan: Plan, chunk_trials: int, n_systems: int, n_frames: int) -> int:
    """Estimated peak working memory (bytes) of one chunk of ``chunk_trials`` trials."""
    per_trial = working_elements_per_trial(plan) + 4 * n_systems * n_frames
    return int(per_trial * chunk_trials * BYTES_PER_ELEMENT)


def simulation_bytes(
    plan: Plan,
    *,
    trials: int,
    n_systems: int,
    n_frames: int,
    threads: int,
    chunk_trials: int | None = None,
    dtype_bytes: int = 4,
) -> tuple[int, int, int]:
    """Peak memory of :func:`torchdoct.simulate` and how it runs: ``(bytes, blocks per chunk, chunks in
    flight)``.

    Without ``chunk_trials`` a chunk's largest working tensors stay near :data:`CHUNK_ELEMENTS` and every
    thread gets a chunk; ``threads`` chunks run at once; the output holds ``trials × n_systems ×
    n_frames`` complex samples of ``2 × dtype_bytes`` bytes.
    """
    n_blocks = -(-trials // BLOCK_TRIALS)
    if chunk_trials is None:
        per_trial = max(working_elements_per_trial(plan), 1)
        chunk_blocks = max(1, min(16, int(CHUNK_ELEMENTS // (BLOCK_TRIALS * per_trial)), -(-n_blocks // threads)))
    else:
        if chunk_trials < 1:
            raise ValueError(f"chunk_trials must be >= 1; got {chunk_trials}")
        chunk_blocks = -(-int(chunk_trials) // BLOCK_TRIALS)
    in_flight = min(threads, -(-n_blocks // chunk_blocks))
    need = in_flight * chunk_bytes(plan, chunk_blocks * BLOCK_TRIALS, n_systems, n_frames)
    need += trials * n_systems * n_frames * 2 * dtype_bytes
    return need, chunk_blocks, in_flight


def check_simulation(
    plan: Plan,
    *,
    trials: int,
    n_systems: int,
    n_frames: int,
    threads: int,
    chunk_trials: int | None = None,
    dtype_bytes: int = 4,
) -> int:
    """:func:`simulation_bytes` checked against the available memory (one line naming the chunk, the
    scatterers and the knobs to turn); returns the blocks per chunk."""
    need, chunk_blocks, in_flight = simulation_bytes(
        plan,
        trials=trials,
        n_systems=n_systems,
        n_frames=n_frames,
        threads=threads,
        chunk_trials=chunk_trials,
        dtype_bytes=dtype_bytes,
    )
    check_resources(
        "this simulation",
        need,
        f"lower chunk_trials (minimum {BLOCK_TRIALS}) or threads, loosen the truncation tolerance "
        f"(simulation.truncation_tolerance, now {plan.truncation_tolerance:g}), run fewer trials per call, "
        "or lower the density",
        detail=f"{chunk_blocks * BLOCK_TRIALS} trials per chunk, {plan.expected_scatterers_per_trial:.4g} scatterers "
        f"per trial, {in_flight} chunk(s) at once, plus the output",
    )
    return chunk_blocks


_LIBC = None


def release_free_memory() -> None:
    """Return freed heap memory to the OS (glibc ``malloc_trim``) between chunks.

    Chunks allocate and free large tensors of varying sizes; glibc's growing mmap threshold then
    serves them from the heap, which fragments and keeps the peak RSS growing with the number of
    chunks. Trimming every few seconds of work keeps the peak independent of the number of trials.
    """
    global _LIBC
    if _LIBC is None:
        try:
            import ctypes
            import ctypes.util

            name = ctypes.util.find_library("c")
            _LIBC = ctypes.CDLL(name) if name else False
            if _LIBC and not hasattr(_LIBC, "malloc_trim"):
                _LIBC = False
        except OSError:
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)

"""Memory of a simulation, estimated before any work: the chunk size, the peak working memory of a
chunk, the memory the machine has available, and the refusal when a run would not fit
(:class:`MemoryLimitError`, raised by :func:`torchdoct.simulate` and :func:`torchdoct.render` before they
start, naming the knob to turn). :func:`release_free_memory` returns freed heap to the OS between chunks.
"""

from __future__ import annotations

from .plan import Plan

__all__ = ["MemoryLimitError", "CHUNK_ELEMENTS", "BYTES_PER_ELEMENT", "working_elements_per_trial", "chunk_bytes",
           "available_memory_bytes", "release_free_memory"]

#: Largest working tensor of a chunk (elements) for the default chunk size: a chunk's state stays near
#: the cache (one block of 64 trials for most scenes; measured 10-50 % faster than 8M-element chunks).
CHUNK_ELEMENTS = 1 << 18


class MemoryLimitError(ValueError):
    """A run would need more memory than the machine has available (refused before any work)."""


#: Bytes of working memory per reserved slot element (measured: float64 state, float32 draws and
#: the temporaries of one frame; 10^5 trials of the largest paper cell peak below 1 GB).
BYTES_PER_ELEMENT = 40


def working_elements_per_trial(plan: Plan) -> float:
    """Largest working tensor of one trial (elements): the slots of the biggest population."""
    return max(3 * (p.capacity + p.entry_capacity + p.entry_proposal_capacity + p.immigrant_proposal_capacity)
               + (p.evaluations_per_trial if p.sampler == "drift" else 0) for p in plan.populations)


def chunk_bytes(plan: Plan, chunk_trials: int, n_systems: int, n_frames: int) -> int:
    """Estimated peak working memory (bytes) of one chunk of ``chunk_trials`` trials."""
    per_trial = working_elements_per_trial(plan) + 4 * n_systems * n_frames
    return int(per_trial * chunk_trials * BYTES_PER_ELEMENT)


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of the machine (Linux ``/proc/meminfo``), or ``None`` where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None



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

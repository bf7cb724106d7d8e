"""Resources a command needs, checked before any work: one check and one error for every command.

Every command estimates, before it allocates its working arrays, the peak memory it will need (and,
where it writes a large output, the bytes that output takes on disk) and calls :func:`check_resources`.
The check compares the estimate with the memory this process may still take (:func:`memory_budget`:
the smallest of the machine's ``MemAvailable``, the address-space limit ``RLIMIT_AS`` less the address
space already in use, and the cgroup's memory limit less its usage, v1 or v2) and the free space of the output's file system, and refuses a run that would not fit
with one :class:`ResourceLimitError` (:class:`MemoryLimitError` for memory, :class:`DiskLimitError` for
disk): one line that names the input (a file, a field or a value), the estimate, the available amount
and the fix (an option to lower or a smaller value). Where the machine does not say how much it has
(not Linux), nothing is refused.

The estimates are each command's own, beside its code:

* :func:`torchdoct.simulate` — :func:`torchdoct.sim.memory.simulation_bytes` (chunks in flight and the
  output signals); ``torchdoct sweep`` and ``torchdoct study`` — the largest cell's simulation times the
  cells side by side, plus every cell's per-trial metrics (:func:`torchdoct.study.sweep.run_sweeps`);
* :func:`torchdoct.render` — the rendered sequence and one copy of it when written;
* ``torchdoct maps`` — :func:`maps_bytes`: the output channels and the working copies of one slab;
* ``doct-train`` — :func:`classifier.dataset.make_dataset`: the split's arrays, twice (the pieces and
  their concatenation);
* ``doct-classify`` and ``torchdoct translate`` — :func:`classify_bytes`: a few copies of the maps
  files' arrays (their declared sizes, read from the files' headers without loading them);
* ``torchdoct compare`` — :func:`check_compare`: every maps file it compares, held at once, and its region;
* the benchmarks with a size (``bench maps``, ``bench bulk-phase``, ``bench classify``) —
  :func:`check_bench`: their synthetic input and its work, from the sizes asked for; the others run the
  commands above, which check themselves.

Standard library only: the torch-free classify path imports it.
"""

from __future__ import annotations

import os
import shutil
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

__all__ = [
    "ResourceLimitError",
    "MemoryLimitError",
    "DiskLimitError",
    "MemoryBudget",
    "memory_budget",
    "available_memory_bytes",
    "free_disk_bytes",
    "format_gb",
    "check_resources",
    "maps_bytes",
    "check_maps",
    "declared_array_bytes",
    "classify_bytes",
    "check_classify",
    "check_compare",
    "check_bench",
    "MAPS_WORK_COPIES",
    "CLASSIFY_COPIES",
    "COMPARE_COPIES",
]


class ResourceLimitError(ValueError):
    """A run would need more memory or disk than the machine has (refused before any work)."""


class MemoryLimitError(ResourceLimitError):
    """A run would need more memory than the machine has available (refused before any work)."""


class DiskLimitError(ResourceLimitError):
    """An output would need more disk space than its file system has free (refused before any work)."""


class MemoryBudget(NamedTuple):
    """The bytes this process may still allocate (``bytes``), what sets that figure (``source``, e.g.
    ``"the address-space limit RLIMIT_AS"``) and whether it is a hard limit (``hard``: the allocation
    fails past it) or the machine's estimate ``MemAvailable`` (which reclaimable caches may exceed)."""

    bytes: int
    source: str
    hard: bool


def _read_int(path: str) -> int | None:
    try:
        with open(path) as fh:
            text = fh.read(64).strip()
    except (OSError, UnicodeDecodeError):
        return None
    try:
        return int(text)
    except ValueError:
        return None  # "max" (cgroup v2: no limit) or unreadable


def _mem_available(proc: str = "/proc") -> int | None:
    try:
        with open(f"{proc}/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _address_space_headroom(proc: str = "/proc") -> int | None:
    """``RLIMIT_AS`` (soft) less this process's address space (``VmSize``), or ``None`` without a limit."""
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    used = 0
    try:
        with open(f"{proc}/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    return max(int(soft) - used, 0)


#: A cgroup v1 ``memory.limit_in_bytes`` at or above this is "no limit" (the kernel writes 2^63 rounded
#: down to a page).
_CGROUP_V1_UNLIMITED = 1 << 62


def _cgroup_headroom(proc: str = "/proc", root: str = "/sys/fs/cgroup") -> int | None:
    """The smallest limit-less-usage of this process's memory cgroup and its ancestors (v2
    ``memory.max``/``memory.current``; v1 ``memory.limit_in_bytes``/``memory.usage_in_bytes``), or
    ``None`` without a limit. The path in ``/proc/self/cgroup`` is taken under the mount and, where the
    mount is the cgroup namespace's own root (containers), the mount itself counts."""
    try:
        with open(f"{proc}/self/cgroup") as fh:
            lines = fh.read(1 << 16).splitlines()
    except OSError:
        return None
    best: int | None = None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        if parts[0] == "0" and controllers == "":
            base, limit_name, usage_name = root, "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            base, limit_name, usage_name = (
                os.path.join(root, "memory"),
                "memory.limit_in_bytes",
                "memory.usage_in_bytes",
            )
        else:
            continue
        rel = rel.strip("/")
        levels = [os.path.join(base, *rel.split("/")[:i]) for i in range(len(rel.split("/")) if rel else 0, 0, -1)]
        levels.append(base)
        for d in levels:
            limit = _read_int(os.path.join(d, limit_name))
            if limit is None or limit >= _CGROUP_V1_UNLIMITED:
                continue
            usage = _read_int(os.path.join(d, usage_name)) or 0
            room = max(limit - usage, 0)
            best = room if best is None else min(best, room)
    return best


def memory_budget(*, proc: str = "/proc", cgroup_root: str = "/sys/fs/cgroup") -> MemoryBudget | None:
    """The memory this process may still allocate: the smallest of ``MemAvailable`` (``/proc/meminfo``),
    the address-space limit ``RLIMIT_AS`` less the address space in use, and the memory cgroup's limit
    less its usage (v1 or v2, this cgroup and its ancestors); ``None`` where none is known (not Linux).
    ``proc``/``cgroup_root``: where those files are (tests give a made-up tree)."""
    found = [
        (b, src, hard)
        for b, src, hard in (
            (_mem_available(proc), "MemAvailable of the machine", False),
            (
                _address_space_headroom(proc),
                "the address-space limit RLIMIT_AS (ulimit -v) less what this process uses",
                True,
            ),
            (
                _cgroup_headroom(proc, cgroup_root),
                "the memory limit of this process's cgroup (container) less its usage",
                True,
            ),
        )
        if b is not None
    ]
    if not found:
        return None
    return MemoryBudget(*min(found, key=lambda f: f[0]))


def available_memory_bytes() -> int | None:
    """:func:`memory_budget`'s bytes, or ``None`` where unknown."""
    budget = memory_budget()
    return None if budget is None else budget.bytes


def free_disk_bytes(path: str | os.PathLike) -> int | None:
    """Free bytes of the file system that holds ``path`` (or its nearest existing parent), or ``None``."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return int(shutil.disk_usage(p).free)
    except OSError:
        return None


def format_gb(n: float) -> str:
    """Bytes as GB with two decimals (the unit of every refusal)."""
    return f"{n / 2**30:.2f} GB"


def check_resources(
    what: str,
    need_bytes: float,
    fix: str,
    *,
    detail: str = "",
    out_path: str | os.PathLike | None = None,
    out_bytes: float = 0,
    out_fix: str | None = None,
) -> None:
    """Refuse, before any work, a run that would not fit.

    ``what`` names the input (``"maps of scan.npy"``, ``"sweep 'diffusion' cell 3 (...)"``); the
    message reads "``what`` needs about X GB (``detail``) but only Y GB are available; ``fix``".
    ``out_path``/``out_bytes``: an output of that size is written there (its file system's free space is
    checked; ``out_fix``, default ``fix``, says what to do). Raises :class:`MemoryLimitError` or
    :class:`DiskLimitError` (both ``ValueError``: exit code 2 on the command line).
    """
    avail = available_memory_bytes()
    if avail is not None and need_bytes > avail:
        budget = memory_budget()
        source = f" ({budget.source})" if budget is not None and budget.bytes == avail and budget.hard else ""
        raise MemoryLimitError(
            f"{what} needs about {format_gb(need_bytes)}"
            + (f" ({detail})" if detail else "")
            + f" but only {format_gb(avail)} are available{source}; {fix}"
        )
    if out_path is not None and out_bytes > 0:
        free = free_disk_bytes(out_path)
        if free is not None and out_bytes > free:
            raise DiskLimitError(
                f"{what}: the output {out_path} takes about {format_gb(out_bytes)} on disk but only "
                f"{format_gb(free)} are free there; {out_fix or fix}"
            )


# ----------------------------------------------------------------------------------------------
# estimates of the commands that have no module of their own for them

#: Working copies of one depth slab that the maps loop holds at once (the slab, its reduced field, the
#: intensity and the metric temporaries; measured: [32, 512²] complex64, 3 resolutions, peak 804 MB of
#: which about 250 MB are the interpreter and torch).
MAPS_WORK_COPIES = 10


def maps_bytes(
    shape: Iterable[int],
    itemsize: int,
    *,
    complex_samples: bool,
    n_resolutions: int,
    metrics: Iterable[str],
    slab_elements: int,
) -> tuple[int, int]:
    """Peak working memory and output bytes (float32 maps) of ``torchdoct maps``.

    ``shape``: the sequence ``[T, (Y,) Z, X]``, its sample ``itemsize`` (bytes) and whether the samples
    are complex (``complex_samples``); the output holds
    ``n_resolutions`` × (metrics, plus the aLIV fit flag with ``aliv``/``swiftness``) channels over the
    ``[(Y,) Z, X]`` pixels, in the sample's real precision while computed. A slab holds at most
    ``slab_elements`` samples (:data:`MAPS_WORK_COPIES` copies at once).
    """
    dims = [int(d) for d in shape]
    total = 1
    for d in dims:
        total *= d
    pixels = total // max(dims[0], 1)
    metrics = list(metrics)
    channels = n_resolutions * (len(metrics) + (1 if {"aliv", "swiftness"} & set(metrics) else 0))
    real = int(itemsize) // 2 if complex_samples else int(itemsize)
    slab = min(int(slab_elements), total) * int(itemsize)
    out_disk = channels * pixels * 4
    return MAPS_WORK_COPIES * slab + channels * pixels * real + out_disk, out_disk


def slab_elements_within(
    budget_gb: float,
    shape: Iterable[int],
    itemsize: int,
    *,
    complex_samples: bool,
    n_resolutions: int,
    metrics: Iterable[str],
    source: str = "sequence",
) -> int:
    """The largest ``slab_elements`` whose working memory (:func:`maps_bytes`: the output maps plus
    :data:`MAPS_WORK_COPIES` copies of a slab) fits ``budget_gb`` GiB (``--max-memory-gb``); the interpreter
    and torch themselves are not counted. A budget the output maps alone fill is a ``ValueError`` naming
    the need."""
    import math

    if not (isinstance(budget_gb, (int, float)) and math.isfinite(budget_gb) and budget_gb > 0):
        raise ValueError(f"--max-memory-gb must be a positive number of GiB; got {budget_gb!r}")
    dims = [int(d) for d in shape]
    fixed, _ = maps_bytes(
        dims,
        itemsize,
        complex_samples=complex_samples,
        n_resolutions=n_resolutions,
        metrics=list(metrics),
        slab_elements=0,
    )
    per_frame_row = dims[0] * int(itemsize)  # a slab holds at least every frame of one pixel row
    free = int(budget_gb * (1 << 30)) - fixed
    n = free // (MAPS_WORK_COPIES * int(itemsize))
    if n < dims[0]:
        raise ValueError(
            f"maps of {source}: --max-memory-gb {budget_gb:g} leaves no room for a slab: the output maps "
            f"alone take {fixed / (1 << 30):.3g} GiB and a slab needs {MAPS_WORK_COPIES} × "
            f"{per_frame_row} bytes more; raise --max-memory-gb or give fewer --resolution / --metrics"
        )
    return int(n)


def check_maps(
    source: str,
    shape: Iterable[int],
    itemsize: int,
    *,
    complex_samples: bool,
    n_resolutions: int,
    metrics: Iterable[str],
    slab_elements: int | None,
    out_paths: Iterable[str | os.PathLike] = (),
) -> None:
    """The resource check of ``torchdoct maps`` (:func:`maps_bytes`), naming the sequence ``source`` and the
    options that lower the need: the memory (not with ``slab_elements=None``) and the disk space of the
    ``out_paths`` (float32 maps)."""
    dims = [int(d) for d in shape]
    metrics = list(metrics)
    need, out_disk = maps_bytes(
        dims,
        itemsize,
        complex_samples=complex_samples,
        n_resolutions=n_resolutions,
        metrics=metrics,
        slab_elements=slab_elements or 0,
    )
    what = f"maps of {source}"
    fix = (
        "give fewer --resolution values or --metrics, or crop the sequence (fewer B-scans, depths or A-lines); "
        "the slab size (slab_elements) bounds the working memory"
    )
    if slab_elements is not None:
        check_resources(
            what, need, fix, detail=f"sequence {dims}, {n_resolutions} resolution(s), {len(metrics)} metric(s)"
        )
    for o in out_paths:
        check_resources(
            what,
            0,
            fix,
            out_path=o,
            out_bytes=out_disk,
            out_fix="free disk space there, write --out elsewhere, or " + fix.split(";")[0],
        )


def declared_array_bytes(path: str | os.PathLike) -> int:
    """Bytes of the arrays a file declares, without loading them: the ``.npy`` members' uncompressed
    sizes for ``.npz``, the file's size otherwise (TIFF stacks are stored uncompressed)."""
    p = Path(path)
    try:
        if not stat.S_ISREG(os.stat(p).st_mode):
            return 0  # a FIFO, device or folder: its reader refuses it (opening it here would block)
    except OSError:
        return 0  # the reader names a missing file
    if p.suffix.lower() == ".npz":
        import zipfile

        try:
            with zipfile.ZipFile(p) as zf:
                return sum(i.file_size for i in zf.infolist() if i.filename.endswith(".npy"))
        except (OSError, zipfile.BadZipFile):
            return 0  # the reader names a damaged archive
    try:
        return p.stat().st_size
    except OSError:
        return 0  # the reader names a missing file


#: Copies of the maps that classification holds at once (the maps read, the features, the model inputs
#: and the probability maps; README: 300 MB + 4 × the maps files).
CLASSIFY_COPIES = 4


def classify_bytes(paths: Iterable[str | os.PathLike], limit_bytes: int | None = None) -> int:
    """Peak memory of classifying (or translating) the maps ``paths``: :data:`CLASSIFY_COPIES` × their
    declared arrays. A file over ``limit_bytes`` (the readers' input limit) counts 0: its reader refuses
    it with the input-limit message."""
    return CLASSIFY_COPIES * _declared_total(paths, limit_bytes)


def _declared_total(paths: Iterable[str | os.PathLike], limit_bytes: int | None) -> int:
    """The declared array bytes of ``paths``; a file over ``limit_bytes`` counts 0 (its reader refuses it)."""
    sizes = [declared_array_bytes(p) for p in paths]
    return sum(0 if limit_bytes is not None and s > limit_bytes else s for s in sizes)


def _check_maps_files(what: str, paths: list, copies: int, fix: str, limit_bytes: int | None) -> None:
    need = copies * _declared_total(paths, limit_bytes)
    names = ", ".join(Path(p).name for p in paths)
    check_resources(
        f"{what} of {names}",
        need,
        fix,
        detail=f"{copies} × the maps arrays the files declare, {format_gb(need / copies)}",
    )


def check_classify(command: str, paths: Iterable[str | os.PathLike], limit_bytes: int | None = None) -> None:
    """The resource check of ``doct-classify`` (``command``) and ``torchdoct translate``: :func:`classify_bytes`
    of the maps ``paths``, naming them and the fix."""
    _check_maps_files(
        command,
        list(paths),
        CLASSIFY_COPIES,
        "classify a crop of the maps (fewer B-scans or pixels), or fewer maps files at once",
        limit_bytes,
    )


#: Copies of the maps that ``torchdoct compare`` holds at once: every file's channels as read, and the
#: per-pixel values of its region (a mask of the same size at most).
COMPARE_COPIES = 2


def check_compare(paths: Iterable[str | os.PathLike], limit_bytes: int | None = None) -> None:
    """The resource check of ``torchdoct compare``: :data:`COMPARE_COPIES` × the declared arrays of every maps
    file (all samples are held at once for the tests), naming the files and the fix."""
    _check_maps_files(
        "torchdoct compare",
        list(paths),
        COMPARE_COPIES,
        "compare fewer maps files at once, or crops of them (fewer B-scans or pixels)",
        limit_bytes,
    )


def check_bench(command: str, need_bytes: float, sizes: str, fix: str) -> None:
    """The resource check of a benchmark that makes its own input (``command``, e.g. ``"torchdoct bench
    maps"``): ``need_bytes`` for the ``sizes`` asked for (named in the message), refused with ``fix`` (the
    options that lower them)."""
    check_resources(f"{command} ({sizes})", need_bytes, fix)

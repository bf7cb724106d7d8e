"""Threading policy: one torch thread per worker, parallel work only over independent pieces.

PyTorch's intra-op parallelism splits every tensor operation across its thread pool and waits at a
barrier at the end of each one. On an idle machine that is a modest gain; beside any other busy
process it is a large loss, because one descheduled thread stalls the barrier of every operation
(measured on a 2-core machine beside a second busy job: several times, up to 40×, slower than one
thread). torchdoct therefore never relies on intra-op threads:

* every computing call runs its tensor operations with **one torch thread**
  (:func:`single_torch_thread`), and
* where it can use more than one core, it runs **independent pieces of work** in parallel: blocks
  of trials in :func:`torchdoct.simulate`, frames in :func:`torchdoct.render`, cells of a sweep. A piece never waits
  for another, so a busy neighbour slows the run only by the share of the cores it takes.

Each piece draws from its own random stream and is combined in a fixed order, so the numbers are
bit-identical for any number of threads.

The knob is ``threads`` (``--threads N`` on the command line): how many cores a call may use.
``None`` means :func:`default_threads`: the cores this process may run on
(``os.sched_getaffinity``), or the value set by :func:`set_default_threads` or the
``TORCHDOCT_THREADS`` environment variable.

The module imports torch only inside the functions that set its threads, so the torch-free classify
path uses the same policy (:mod:`classifier.runtime`).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

__all__ = [
    "default_threads",
    "set_default_threads",
    "limit_process_threads",
    "using_threads",
    "resolve_threads",
    "single_torch_thread",
    "one_torch_thread",
    "map_ordered",
]

T = TypeVar("T")
R = TypeVar("R")

_DEFAULT: int | None = None
_LOCK = threading.Lock()
_DEPTH = 0
_SAVED = 1


def _usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _check(threads: object, what: str = "threads") -> int:
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"{what} must be an integer >= 1 (the number of cores to use); got {threads!r}")
    return threads


def default_threads() -> int:
    """Cores a call uses when it is not told: :func:`set_default_threads`, else ``TORCHDOCT_THREADS``,
    else the cores this process may run on."""
    if _DEFAULT is not None:
        return _DEFAULT
    env = os.environ.get("TORCHDOCT_THREADS")
    if env:
        try:
            return _check(int(env), "TORCHDOCT_THREADS")
        except ValueError:
            raise ValueError(
                f"TORCHDOCT_THREADS must be an integer >= 1 (the number of cores to use); got {env!r}"
            ) from None
    return _usable_cores()


def limit_process_threads() -> None:
    """For a command-line process: torch and the BLAS/OpenMP pools of numpy and scikit-learn use one
    thread each (their parallel regions stall beside other busy processes); parallel work runs over
    independent pieces instead."""
    import torch

    torch.set_num_threads(1)
    try:
        import threadpoolctl
    except ImportError:  # pragma: no cover - installed with scikit-learn
        return
    threadpoolctl.threadpool_limits(1)


def set_default_threads(threads: int | None) -> None:
    """Set the process-wide default of ``threads`` (``None`` restores the automatic choice)."""
    global _DEFAULT
    _DEFAULT = None if threads is None else _check(threads)


@contextlib.contextmanager
def using_threads(threads: int | None) -> Iterator[None]:
    """Within the body, calls that are not told use ``threads`` cores (``None``: leave as is)."""
    global _DEFAULT
    saved = _DEFAULT
    if threads is not None:
        set_default_threads(threads)
    try:
        yield
    finally:
        _DEFAULT = saved


def resolve_threads(threads: int | None) -> int:
    """``threads`` checked (an integer >= 1), or :func:`default_threads` for ``None``."""
    return default_threads() if threads is None else _check(threads)


@contextlib.contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run the body with one torch intra-op thread, then restore the previous setting.

    Re-entrant and safe to nest from several Python threads: the setting is restored when the
    outermost body ends.
    """
    import torch

    global _DEPTH, _SAVED
    with _LOCK:
        if _DEPTH == 0:
            _SAVED = torch.get_num_threads()
            if _SAVED != 1:
                torch.set_num_threads(1)
        _DEPTH += 1
    try:
        yield
    finally:
        with _LOCK:
            _DEPTH -= 1
            if _DEPTH == 0 and _SAVED != 1:
                torch.set_num_threads(_SAVED)


def one_torch_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """Decorator: ``fn`` runs inside :func:`single_torch_thread`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_torch_thread():
            return fn(*args, **kwargs)

    return wrapper


def map_ordered(fn: Callable[[T], R], items: Iterable[T], threads: int) -> Iterator[R]:
    """``fn`` over ``items`` on up to ``threads`` Python threads; results in the order of ``items``.

    ``items`` is consumed lazily and at most ``threads`` pieces are in flight, so memory stays bounded
    by ``threads`` pieces; with one thread it is a plain loop. ``fn`` should spend its time in torch
    operations (which release the GIL).
    """
    if threads <= 1:
        for x in items:
            yield fn(x)
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    it = iter(items)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending = deque(pool.submit(fn, x) for _, x in zip(range(threads), it))
        while pending:
            res = pending.popleft().result()
            for x in it:
                pending.append(pool.submit(fn, x))
                break
            yield res

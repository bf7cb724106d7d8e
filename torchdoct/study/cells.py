"""Cells: independent pieces of work, run side by side, cached one by one, resumed after an interruption.

The one runner of the sweep cells (:mod:`torchdoct.study.sweep`, and through it every study) and of the
draws of the classifier's training data (:func:`classifier.dataset.make_dataset`):

* **executors** (:func:`run_cells`): this process, ``workers`` cells side by side in threads (each cell
  on one core), worker processes (spawned, one torch and BLAS thread each, dying with their parent), or
  an existing Dask distributed cluster (cells as tasks, results back to this process). ``done(i,
  result)`` is called in this process as each cell finishes: in the order of the cells for threads,
  as they finish for processes and Dask. A cell's result depends only on its payload, never on the
  executor, the number of workers or the batching, so the caller's output is the same for all.
* **seeds** (:func:`cell_seed`): a cell's seed from the base seed and the cell's key alone;
* **cache** (:class:`CellCache`): a finished cell as ``DIR/<key>.npz`` (named arrays and one JSON
  header holding the key), written atomically the moment it finishes, read back instead of recomputed;
  an unreadable or partial file is recomputed;
* **interruption** (:func:`run_cached`): Ctrl-C or SIGTERM keeps every finished cell in the cache and
  says so in one line (:func:`torchdoct.runtime.interrupt.note`): rerunning the same command resumes from them.

Plain data in, plain data out: a payload and a result cross to a worker process or a Dask worker as
they are (``task`` must then be a module-level function).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.interrupt import note, progress_disabled

__all__ = ["cell_seed", "CellCache", "CellJob", "run_cells", "run_cached"]


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def cell_seed(base_seed: int, key: str) -> int:
    """Seed of a cell: the first 63 bits of SHA-256 over (base seed, cell key).

    Depends on nothing else (not the cell's index, batch or executor), so a cell gives the same
    numbers in any run that contains it.
    """
    if isinstance(base_seed, bool) or not isinstance(base_seed, int) or base_seed < 0:
        raise ValueError(f"seed must be an integer >= 0; got {base_seed!r}")
    digest = hashlib.sha256(_canonical(["torchdoct-cell-seed", int(base_seed), key]).encode()).digest()
    return int.from_bytes(digest[:8], "big") >> 1


class CellCache:
    """Finished cells as ``DIR/<key>.npz``: named arrays and a JSON header ``meta_json`` that holds the key
    (``directory=None``: no cache; every cell is computed, nothing is written)."""

    def __init__(self, directory: str | os.PathLike | None):
        self.dir = None if directory is None else Path(directory)

    def path(self, key: str) -> Path:
        return self.dir / f"{key}.npz"

    def get(self, key: str) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """``(arrays, header)`` of a cached cell, or ``None`` (no cache, no file, another key, unreadable)."""
        if self.dir is None:
            return None
        p = self.path(key)
        if not p.is_file():
            return None
        try:
            with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                meta = json.loads(str(z["meta_json"]))
                if not isinstance(meta, dict) or meta.get("cache_key") != key:
                    return None
                arrays = {name: z[name] for name in z.files if name != "meta_json"}
        except (OSError, EOFError, ValueError, KeyError, json.JSONDecodeError, zipfile.BadZipFile):
            return None  # unreadable or partial: recompute
        return arrays, meta

    def put(self, key: str, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        """Store a cell atomically (:func:`torchdoct.files.atomic_write`); the header gets ``cache_key``."""
        if self.dir is None:
            return
        from ..files import atomic_write

        self.dir.mkdir(parents=True, exist_ok=True)
        header = {"cache_key": key, **meta}
        payload = dict(arrays)
        payload["meta_json"] = np.asarray(json.dumps(header))

        def write(tmp: str) -> None:
            with open(tmp, "wb") as fh:
                np.savez(fh, **payload)

        atomic_write(self.path(key), write)


# ----------------------------------------------------------------------------------------------
# executors


def _run_batch(task: Callable[[Any], Any], payloads: list[Any]) -> list[Any]:
    """``task`` on each payload of one batch (one thread, process or Dask task per batch)."""
    return [task(p) for p in payloads]


def _connect(scheduler: str):
    try:
        from dask.distributed import Client
    except ImportError:  # pragma: no cover - depends on the installation
        raise ValueError("--scheduler needs dask.distributed; install it with pip install 'torchdoct[dask]'") from None
    try:
        return Client(scheduler, set_as_default=False, timeout="10s")
    except (OSError, TimeoutError, ValueError) as err:
        raise ValueError(
            f"--scheduler {scheduler!r}: cannot connect ({err}); start a scheduler "
            "(dask scheduler) and workers that have torchdoct installed, and give its address "
            "such as tcp://host:8786"
        ) from None


def _worker_init(parent_pid: int | None = None) -> None:
    """A worker process computes on one core: one torch (and BLAS) thread, one simulation thread. It
    ignores Ctrl-C and dies with its parent (:func:`torchdoct.runtime.interrupt.worker_init`)."""
    from ..runtime.interrupt import worker_init
    from ..runtime.threads import limit_process_threads, set_default_threads

    worker_init(parent_pid)
    limit_process_threads()
    set_default_threads(1)


def _stop_workers(pool) -> None:
    """Stop a process pool's workers now (on an error or an interruption), not after their cells.

    A worker stopped while it sends a result leaves half a message in the result pipe, and the pool's
    manager thread waits for the rest forever; the interpreter joins that thread at exit, so the command
    would never end. Once the workers are gone, this process's own end of the pipe is closed too: the
    manager thread reads the end of the file, marks the pool broken and ends.
    """
    procs = list((getattr(pool, "_processes", None) or {}).values())
    results = getattr(pool, "_result_queue", None)
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=10)
        if proc.is_alive():  # pragma: no cover - a worker that ignores SIGTERM
            proc.kill()
            proc.join(timeout=10)
    writer = getattr(results, "_writer", None)
    if writer is not None:
        writer.close()
    if manager is not None:
        manager.join(timeout=30)


def run_cells(
    task: Callable[[Any], Any],
    payloads: Sequence[Any],
    *,
    done: Callable[[int, Any], None],
    workers: int = 1,
    batch: int = 1,
    processes: bool = False,
    scheduler: str | None = None,
    one_torch_thread: bool = False,
) -> None:
    """Run ``task(payload)`` for every payload; ``done(i, result)`` in this process as each finishes.

    ``batch``: payloads per thread, process or Dask task. ``scheduler``: address of a Dask distributed
    scheduler (None: this machine). Locally, with ``workers = 1`` or a single batch, one batch at a time
    with ``workers`` as the default threads of the work inside a cell (:func:`torchdoct.runtime.threads.using_threads`);
    otherwise ``workers`` batches side by side, each on one core: in threads of this process, or with
    ``processes`` in spawned worker processes (a process costs seconds to start; threads share the
    interpreter's lock). ``one_torch_thread``: this process's torch work on one intra-op thread
    (:func:`torchdoct.runtime.threads.single_torch_thread`). ``done`` is called in the order of ``payloads`` in
    this process's threads, as batches finish in worker processes and on Dask. ``task`` must be a
    module-level function for processes and Dask.
    """
    batches = [list(range(i, min(len(payloads), i + batch))) for i in range(0, len(payloads), batch)]
    if scheduler is not None:
        _run_on_dask(task, payloads, batches, scheduler, done)
        return
    one_at_a_time = workers == 1 or len(batches) < 2
    if processes and not one_at_a_time:
        _run_in_processes(task, payloads, batches, workers, done)
        return
    from ..runtime.threads import map_ordered, single_torch_thread, using_threads

    with (
        using_threads(workers if one_at_a_time else 1),
        single_torch_thread() if one_torch_thread else contextlib.nullcontext(),
    ):
        results = map_ordered(
            lambda b: _run_batch(task, [payloads[i] for i in b]), batches, 1 if one_at_a_time else workers
        )
        for b, res in zip(batches, results):
            for i, r in zip(b, res):
                done(i, r)


def _run_in_processes(task, payloads, batches, workers, done) -> None:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures import as_completed as done_first

    ctx = multiprocessing.get_context("spawn")  # no fork of a process that holds torch threads
    with ProcessPoolExecutor(
        max_workers=min(workers, len(batches)), mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
    ) as pool:
        try:
            futures = {pool.submit(_run_batch, task, [payloads[i] for i in b]): b for b in batches}
            for fut in done_first(futures):
                for i, r in zip(futures[fut], fut.result()):
                    done(i, r)
        except BaseException:  # the pool's manager thread cancels the futures not yet started
            _stop_workers(pool)
            raise


def _run_on_dask(task, payloads, batches, scheduler, done) -> None:
    from dask.distributed import as_completed

    client = _connect(scheduler)
    try:
        with client.as_current():
            futures = [client.submit(_run_batch, task, [payloads[i] for i in b], pure=False) for b in batches]
            index = {f.key: b for f, b in zip(futures, batches)}
            for fut in as_completed(futures):
                res = fut.result()
                for i, r in zip(index[fut.key], res):
                    done(i, r)
    finally:
        client.close()


# ----------------------------------------------------------------------------------------------
# cached cells


@dataclass(frozen=True)
class CellJob:
    """One cell to run: its cache ``key``, the plain-data ``payload`` of the task, and its ``weight`` in
    the progress bar (e.g. its trials)."""

    key: str
    payload: Any
    weight: int = 1


def run_cached(
    jobs: Sequence[CellJob],
    *,
    cache: CellCache,
    execute: Callable[[list, Callable], None],
    encode: Callable[[CellJob, Any], tuple[dict[str, np.ndarray], dict[str, Any]]],
    decode: Callable[[CellJob, dict[str, np.ndarray], dict[str, Any]], Any],
    progress: bool = False,
    desc: str = "cells",
    unit: str = "trial",
    what: str = "cells",
    before: Callable[[list[int]], None] | None = None,
    final_note: bool = True,
) -> tuple[list[Any], list[int]]:
    """Results of every job (from the cache, or computed): ``(results, indices computed)``.

    Cached jobs are decoded (``decode(job, arrays, header)``; an entry that does not decode is computed);
    the others run through ``execute(payloads, done)`` (a :func:`run_cells` call), and each finished one
    is stored at once (``encode(job, result) -> (arrays, header)``). ``before(indices to compute)`` runs
    before any of them (the resource check: :func:`torchdoct.runtime.resources.check_resources`). On Ctrl-C or
    SIGTERM the one line says how many ``what`` the cache keeps and how to resume; after the run (with
    ``final_note``), should the command be interrupted while it writes its outputs, that every cell is there.
    """
    results: list[Any] = [None] * len(jobs)
    pending: list[int] = []
    for j, job in enumerate(jobs):
        hit = cache.get(job.key)
        if hit is not None:
            try:
                results[j] = decode(job, *hit)
                continue
            except (KeyError, ValueError, TypeError):
                pass  # an entry of another layout: recompute
        pending.append(j)
    if before is not None:
        before(pending)
    bar = None
    if not progress_disabled(progress) and pending:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(jobs[j].weight for j in pending), unit=unit, desc=desc, dynamic_ncols=True)
        bar.set_postfix_str(f"{len(jobs) - len(pending)} cached, {len(pending)} to run")
    finished = [False] * len(jobs)

    def done(i: int, res: Any) -> None:
        j = pending[i]
        cache.put(jobs[j].key, *encode(jobs[j], res))
        results[j] = res
        finished[j] = True
        if bar is not None:
            bar.update(jobs[j].weight)

    try:
        if pending:
            execute([jobs[j].payload for j in pending], done)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: say what the cache keeps (torchdoct.runtime.interrupt)
        n_done = sum(finished[j] for j in pending)
        if cache.dir is not None:
            before = len(jobs) - len(pending)
            note(
                kept=f"{n_done} of the {len(pending)} {what} to compute"
                + (f" (and {before} found there before)" if before else "")
                + f" in the cache {cache.dir}",
                resume="rerun the same command to resume from them",
                key="cache",
            )
        else:
            note(resume=f"rerun the same command (without --no-cache, finished {what} would be kept)")
        raise
    finally:
        if bar is not None:
            bar.close()
    if final_note and cache.dir is not None:  # should the command be interrupted while it writes its outputs
        note(
            kept=f"all {len(jobs)} {what} in the cache {cache.dir}",
            resume=f"rerun the same command: the {what} come from the cache",
            key="cache",
        )
    return results, pending

"""``torchdoct maps`` on many inputs at once: one maps run per input, one after another in this process, side
by side in worker processes (``--workers N``) or as tasks on an existing Dask distributed cluster
(``--scheduler ADDRESS``) through the one cell runner (:func:`torchdoct.study.cells.run_cells`).

Every ``--out`` names each input's file with ``{stem}`` (the input's name without its format suffix:
``s.ome.tif`` -> ``s``, a folder -> its name). Before any work: every input exists, the outputs of two
inputs never coincide, no output exists without ``--force``. A run is the single-input command on that
input (the same checks, the same maps, bit for bit); its printed lines come back to this process and are
printed in the inputs' order as each finishes. One input refused does not stop the others; the exit code
is then the largest of the runs' (2 for bad input) after a note naming the inputs refused. On a Dask
cluster the workers read the inputs and write the outputs at the same paths: give paths on a disk every
worker shares.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["stem", "outputs_of", "run_task", "run_many"]


def stem(path: str) -> str:
    """The input's name without its sequence-format suffix (the longest that matches)."""
    from ..measured.formats import SEQUENCE_SUFFIXES

    name = Path(path).name
    for suffix in sorted(SEQUENCE_SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def outputs_of(inputs: list[str], outs: list[str]) -> list[list[str]]:
    """Each input's ``--out`` paths, ``{stem}`` replaced; a ``ValueError`` naming the fix when several inputs
    would share an output (an ``--out`` without ``{stem}``, or two inputs of one stem)."""
    if len(inputs) > 1:
        plain = [o for o in outs if "{stem}" not in o]
        if plain:
            raise ValueError(
                f"--out {plain[0]}: with {len(inputs)} inputs every --out names each input's file with "
                "{stem}, e.g. --out maps/{stem}.ome.tif"
            )
    per = [[o.replace("{stem}", stem(i)) for o in outs] for i in inputs]
    seen: dict[Path, str] = {}
    for i, paths in zip(inputs, per):
        for o in paths:
            key = Path(o).resolve()
            if key in seen:
                raise ValueError(
                    f"--out {o}: inputs {seen[key]} and {i} would both write it (the same {{stem}}); "
                    "give inputs of different names or a folder per input in --out"
                )
            seen[key] = i
    return per


def run_task(
    task: Callable[[argparse.Namespace], int], payload: dict[str, Any], capture: bool = True
) -> dict[str, Any]:
    """One input's run: ``task`` (the single-input command) on the parsed options ``payload``, through
    :func:`torchdoct.cli.command.run_parsed` (one ``error:`` line and exit 2 on bad input); its exit code and,
    with ``capture`` (in a worker), what it printed (else it prints as it goes)."""
    from .command import run_parsed

    args = argparse.Namespace(**payload)
    args.func = task
    if not capture:
        return {"code": int(run_parsed(args)), "stdout": "", "stderr": ""}
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = run_parsed(args)
    return {"code": int(code), "stdout": out.getvalue(), "stderr": err.getvalue()}


def run_many(
    args: argparse.Namespace, task: Callable[[dict[str, Any]], dict[str, Any]], one: Callable[[argparse.Namespace], int]
) -> int:
    """``torchdoct maps`` over ``args.input`` (module docstring); ``task(payload)``: one input's run in a worker,
    a module-level function (worker processes and Dask import it) that calls :func:`run_task`; ``one``: the
    single-input command, run here for inputs one after another (printing and showing progress as it goes)."""
    from ..files import check_out
    from ..measured.io import MAPS_SUFFIXES
    from ..study.cells import run_cells

    inputs = list(args.input)
    per = outputs_of(inputs, list(args.out))
    for i in inputs:
        if not Path(i).exists():
            raise FileNotFoundError(f"sequence file {i} does not exist")
    for paths in per:
        for o in paths:
            if Path(o).suffix == ".zarr" and Path(o).exists():
                raise ValueError(
                    f"--out: {o} exists; an OME-Zarr folder is never overwritten: remove it or give another name"
                )
            check_out(o, args.force, MAPS_SUFFIXES, what="--out")
    workers = args.workers or 1
    if workers < 1:
        raise ValueError(f"--workers must be >= 1; got {workers}")
    quiet = args.no_progress or workers > 1 or args.scheduler is not None  # bars of several runs would mix
    base = {k: v for k, v in vars(args).items() if k not in ("func", "input", "out")}
    payloads = [
        {**base, "input": i, "out": o, "no_progress": quiet, "threads": 1 if workers > 1 else args.threads}
        for i, o in zip(inputs, per)
    ]
    codes: dict[int, int] = {}

    def done(k: int, res: dict[str, Any]) -> None:
        sys.stdout.write(res["stdout"])
        sys.stderr.write(res["stderr"])
        sys.stdout.flush()
        codes[k] = res["code"]

    if workers == 1 and args.scheduler is None:  # here, one after another
        for k, payload in enumerate(payloads):
            codes[k] = run_task(one, payload, capture=False)["code"]
    else:
        run_cells(task, payloads, done=done, workers=workers, processes=workers > 1, scheduler=args.scheduler)
    failed = [inputs[k] for k in sorted(codes) if codes[k] != 0]
    if failed:
        print(
            f"note: {len(failed)} of {len(inputs)} inputs refused ({', '.join(failed)}); the others' maps were written",
            file=sys.stderr,
        )
        return max(codes.values())
    return 0

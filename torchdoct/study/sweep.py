"""Sweeps: run a scene over a grid of field values, cache every cell, gather one tidy table.

A sweep is a scene (the scene-file schema of the README) plus a ``[sweep]`` table that varies any of
its fields. Each combination of values is a *cell*; a cell is one :func:`torchdoct.simulate` run of
all the scene's systems (so the systems of a cell see the same scatterers and compare pairwise).

Schema of the ``[sweep]`` table::

    [sweep]
    name = "diffusion"          # optional, default: the scene's name
    mode = "product"            # or "zip": the i-th values of every field together

    [[sweep.field]]             # one or more
    path = "population.0.motion.0.diffusion_um2_per_s"   # key path into the scene file
    name = "D_um2_per_s"        # optional table column, default: the last key (the path if taken)
    values = [0.0]              # explicit values (any TOML value), and/or
    log = { start = 0.001, stop = 1.0, num = 19 }        # geometric spacing (start, stop > 0)
    linear = { start = 1.5, stop = 15.0, num = 10 }      # even spacing

A field takes explicit ``values`` in their given order, or a generated ``linear``/``log`` sequence; a
field that gives more than one of the three takes the sorted union (numbers only). Generated values
are rounded to 12 significant digits so that cell keys (and seeds) do not depend on the numpy version.
Paths index arrays of tables by position (``system.1.axial_resolution_um``); a missing table on the
path is created (``noise.snr_db`` without a ``[noise]`` table), and every cell is validated with
:func:`torchdoct.sim.config.scene_from_dict` before anything runs. ``simulation.trials`` and
``simulation.seed`` set the run of every cell and cannot be swept.

Seeds, cache and reproducibility:

* **cell key**: the canonical JSON of the cell's ``{path: value}`` assignments.
* **cell seed**: derived from (base seed, cell key) by SHA-256 (:func:`cell_seed`); it does not
  depend on the cell's position in the grid, on how cells are batched, on which cells run in the
  same call, or on the executor, so a sweep can be split, extended, resumed or spread over a Dask
  cluster and every cell gives the same numbers.
* **cache**: a finished cell is stored under a hash of its resolved scene (every field, defaults
  included, except ``name``/``description``), seed, trials, dtype, PSF tolerance and the torchdoct
  version (:func:`cache_key`); a rerun loads it instead of simulating, and a changed scene
  recomputes only the cells whose resolved scene changed.

The tidy table has one row per cell × system × scalar metric (``liv`` dB², ``ocds`` 1/s,
``complex_variance``): mean, SD (ddof 1), standard error, the number of finite trials ``n``, the
number of trials with an empty resolution volume ``empty`` (NaN dB metrics, see
:mod:`torchdoct.sim.metrics`), the trials and the seed of the cell (:func:`results_table`; the
statistics are those of :func:`torchdoct.sim.metrics.summarize`).

Executors (:func:`run_sweeps`, through the cell runner :mod:`torchdoct.study.cells`, which also owns
the seeds, the cache files and what an interruption keeps): this process on one core (``workers = 1``,
the library default), ``workers`` cells side by side, each on one torch thread (the command line's
``--threads``, default one per usable core: on a shared machine, independent single-threaded pieces are
far less sensitive to other load than torch's intra-op threads; :mod:`torchdoct.runtime.threads`): in threads
of this process for small sweeps, in worker processes from :data:`_PROCESS_WORK` system-trials on (a
process costs seconds to start, threads share the interpreter's lock), or an existing Dask distributed
cluster (``scheduler = "tcp://host:8786"``), cells as tasks whose results come back to this process,
which writes the cache and the table. Before any cell runs, the cells to compute are checked against
the available memory and the cache's disk (:func:`torchdoct.runtime.resources.check_resources`).

The grid (a field's values, key paths into the scene) is :mod:`torchdoct.study.grid`'s.

Kept whole (over 800 lines): the cell key, the cache encoding, the resource checks and the writers share
the canonical form of a cell; a split would pass that form between modules without making a step shorter.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..sim.config import Scene, SceneError, _fail, read_toml, scene_from_dict
from .cells import CellCache, CellJob, cell_seed, run_cached, run_cells
from .grid import _is_number, _normalize_arrays, _set_path, _split_path, field_values

__all__ = [
    "SCALAR_METRICS",
    "SweepField",
    "Cell",
    "Sweep",
    "CellResult",
    "SweepResult",
    "field_values",
    "make_sweep",
    "parse_sweep",
    "load_sweep",
    "cell_seed",
    "cache_key",
    "run_cell",
    "run_sweeps",
    "run_sweep",
    "check_sweep_resources",
    "results_table",
    "write_table",
    "write_sweep_outputs",
    "sweep_outputs",
    "prepare_out_dir",
    "check_cache_dir",
    "format_table",
]

#: Metrics with one number per trial and system, and their units: the rows of the table.
SCALAR_METRICS = {"liv": "dB^2", "ocds": "1/s", "complex_variance": "linear intensity"}
#: Columns of the table that a sweep field or tag may not take as its name.
RESERVED_COLUMNS = (
    "sweep",
    "cell",
    "system",
    "wavelength_um",
    "lateral_resolution_um",
    "axial_resolution_um",
    "refractive_index",
    "metric",
    "unit",
    "mean",
    "sd",
    "se",
    "n",
    "empty",
    "trials",
    "seed",
    "cache_key",
)
#: Bump when the cached content changes meaning; part of every cache key.
CACHE_FORMAT = 1


def _version() -> str:
    from .. import __version__

    return __version__


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


# ----------------------------------------------------------------------------------------------
# sweeps and cells


def _norm_value(v: Any) -> Any:
    """Value as it enters a cell key: integers as floats (so 0 and 0.0 are one cell), recursively."""
    if _is_number(v):
        return float(v)
    if isinstance(v, list):
        return [_norm_value(x) for x in v]
    if isinstance(v, tuple):
        return [_norm_value(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _norm_value(x) for k, x in v.items()}
    return v


@dataclass(frozen=True)
class SweepField:
    """One swept field: the key ``path`` into the scene file, its table column ``name``, its values."""

    path: str
    name: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class Cell:
    """One point of a sweep: its assignments ``(path, value)``, validated scene and key."""

    sweep: str
    index: int
    assignments: tuple[tuple[str, Any], ...]
    names: tuple[str, ...]
    scene: Scene
    key: str

    @property
    def values(self) -> dict[str, Any]:
        """Column name -> value."""
        return {n: v for n, (_, v) in zip(self.names, self.assignments)}


@dataclass(frozen=True)
class Sweep:
    """A base scene and the fields it varies (see the module docstring)."""

    name: str
    scene_data: dict[str, Any]
    scene: Scene
    fields: tuple[SweepField, ...]
    mode: str = "product"
    tags: tuple[tuple[str, str], ...] = ()
    cells: tuple[Cell, ...] = field(default=(), repr=False)

    def to_dict(self) -> dict[str, Any]:
        """The resolved sweep: base scene (defaults filled in), fields with their values, tags."""
        return {
            "name": self.name,
            "mode": self.mode,
            "tags": dict(self.tags),
            "fields": [{"path": f.path, "name": f.name, "values": list(f.values)} for f in self.fields],
            "scene": self.scene.to_dict(),
        }


def cell_key(assignments: Iterable[tuple[str, Any]]) -> str:
    """Canonical JSON of a cell's ``{path: value}`` (sorted paths, integers as floats)."""
    return _canonical({p: _norm_value(v) for p, v in sorted(assignments)})


def make_sweep(
    scene_data: dict[str, Any],
    fields: Sequence[dict[str, Any]],
    *,
    mode: str = "product",
    name: str | None = None,
    tags: dict[str, str] | None = None,
    where: str = "sweep",
) -> Sweep:
    """Build and validate a :class:`Sweep` from a scene dict (file schema) and field specs.

    Every field spec is a dict with ``path``, optional ``name`` and ``values``/``linear``/``log``.
    Every cell's scene is validated here; an error names the field, the cell and the fix.
    """
    base = _normalize_arrays(copy.deepcopy(scene_data))
    try:
        base_scene = scene_from_dict(base)
    except (SceneError, TypeError) as err:
        raise type(err)(f"scene (without [sweep]): {err}") from None
    if mode not in ("product", "zip"):
        _fail(f"{where}.mode", f"must be 'product' or 'zip'; got {mode!r}")
    if not isinstance(fields, (list, tuple)) or not fields:
        _fail(
            f"{where}.field",
            "a sweep needs at least one [[sweep.field]]",
            'add [[sweep.field]] with path = "..." and values = [...]',
        )
    name = name if name is not None else (base_scene.name or "sweep")
    if not isinstance(name, str) or not name:
        raise TypeError(f"{where}.name must be a non-empty string; got {name!r}")
    tags = dict(tags or {})
    parsed: list[SweepField] = []
    paths: list[list[str]] = []
    for i, spec in enumerate(fields):
        fw = f"{where}.field[{i}]"
        if not isinstance(spec, dict):
            raise TypeError(f"{fw} must be a table; got {spec!r}")
        unknown = sorted(set(spec) - {"path", "name", "values", "linear", "log"})
        if unknown:
            _fail(fw, f"unknown key(s) {unknown}", "allowed keys are path, name, values, linear, log")
        if "path" not in spec:
            _fail(fw, "missing key 'path'", 'e.g. path = "population.0.motion.0.diffusion_um2_per_s"')
        parts = _split_path(spec["path"], fw)
        if parts[0] == "sweep":
            _fail(f"{fw}.path", "a sweep cannot sweep itself", "point the path into the scene")
        if parts[0] == "simulation" and len(parts) > 1 and parts[1] in ("trials", "seed"):
            _fail(
                f"{fw}.path",
                f"{spec['path']!r}: trials and seed are set for the whole sweep (each cell "
                "derives its own seed from the base seed)",
                "use --trials / --seed instead of sweeping them",
            )
        col = spec.get("name", parts[-1])
        if "name" not in spec and (col in RESERVED_COLUMNS or col in tags or col in [f.name for f in parsed]):
            col = spec["path"]  # the last key is taken: the whole path names the column
        if not isinstance(col, str) or not col:
            raise TypeError(f"{fw}.name must be a non-empty string; got {col!r}")
        if col in RESERVED_COLUMNS or col in tags:
            _fail(f"{fw}.name", f"{col!r} is a column of the table already", "give the field another name")
        if col in [f.name for f in parsed]:
            _fail(f"{fw}.name", f"two fields are named {col!r}", 'set name = "..." on one of them')
        if spec["path"] in [f.path for f in parsed]:
            _fail(f"{fw}.path", f"{spec['path']!r} is swept twice", "sweep each path once")
        parsed.append(SweepField(path=spec["path"], name=col, values=field_values(spec, fw)))
        paths.append(parts)
    for k, v in tags.items():
        if not isinstance(k, str) or not isinstance(v, str):
            raise TypeError(f"{where}: tags must map strings to strings; got {k!r}: {v!r}")
        if k in RESERVED_COLUMNS:
            _fail(f"{where}.tags", f"{k!r} is a column of the table already", "rename the tag")
    n_cells = min(len(f.values) for f in parsed) if mode == "zip" else math.prod(len(f.values) for f in parsed)
    from .grid import cells_over_cap

    def one_cell() -> tuple[float, int]:  # the cost of building cell 0, measured on it
        import pickle

        t0 = time.perf_counter()
        data = copy.deepcopy(base)
        for f, parts in zip(parsed, paths):
            _set_path(data, parts, f.values[0], where)
        scene: Scene | dict[str, Any]  # the dict itself when cell 0 is not a valid scene
        try:
            scene = scene_from_dict(data)
        except (SceneError, TypeError):
            scene = data
        return time.perf_counter() - t0, len(pickle.dumps((data, scene)))

    cells_over_cap(
        where, n_cells, f"mode = {mode!r} over {' × '.join(str(len(f.values)) for f in parsed)} values", one_cell
    )
    if mode == "zip":
        lengths = {f.name: len(f.values) for f in parsed}
        if len(set(lengths.values())) > 1:
            _fail(
                f"{where}.mode",
                f"zip needs fields of equal length; got {lengths}",
                'give every field the same number of values or use mode = "product"',
            )
        combos = list(zip(*[f.values for f in parsed]))
    else:
        import itertools

        combos = list(itertools.product(*[f.values for f in parsed]))
    cells: list[Cell] = []
    seen: dict[str, int] = {}
    for idx, combo in enumerate(combos):
        data = copy.deepcopy(base)
        assignments = []
        for f, parts, value in zip(parsed, paths, combo):
            _set_path(data, parts, value, f"{where}.field[{parsed.index(f)}]")
            assignments.append((f.path, value))
        desc = ", ".join(f"{p} = {v!r}" for p, v in assignments)
        try:
            scene = scene_from_dict(data)
        except (SceneError, TypeError) as err:
            raise type(err)(f"{where} cell {idx} ({desc}): {err}") from None
        key = cell_key(assignments)
        if key in seen:
            _fail(where, f"cells {seen[key]} and {idx} are the same ({desc})", "remove the duplicate values")
        seen[key] = idx
        cells.append(
            Cell(
                sweep=name,
                index=idx,
                assignments=tuple(assignments),
                names=tuple(f.name for f in parsed),
                scene=scene,
                key=key,
            )
        )
    return Sweep(
        name=name,
        scene_data=base,
        scene=base_scene,
        fields=tuple(parsed),
        mode=mode,
        tags=tuple(tags.items()),
        cells=tuple(cells),
    )


def parse_sweep(data: dict[str, Any], *, source: str = "scene") -> Sweep:
    """A :class:`Sweep` from a scene-file dict with a ``[sweep]`` table (module docstring)."""
    if not isinstance(data, dict):
        raise TypeError(f"{source}: a sweep file must be a table; got {type(data).__name__}")
    if "sweep" not in data:
        _fail(source, "has no [sweep] table", "add [sweep] and [[sweep.field]] tables (see the README)")
    data = copy.deepcopy(data)
    spec = data.pop("sweep")
    if not isinstance(spec, dict):
        raise TypeError(f"{source}: sweep must be a table; got {spec!r}")
    unknown = sorted(set(spec) - {"name", "mode", "field"})
    if unknown:
        _fail(f"{source}: sweep", f"unknown key(s) {unknown}", "allowed keys are name, mode, field")
    fields = spec.get("field", [])
    if isinstance(fields, dict):
        fields = [fields]
    return make_sweep(data, fields, mode=spec.get("mode", "product"), name=spec.get("name"))


def load_sweep(path: str | os.PathLike) -> Sweep:
    """Read a TOML scene file with a ``[sweep]`` table."""
    from ..files import check_regular_file

    p = Path(path)
    try:
        check_regular_file(p, "sweep file")
    except FileNotFoundError:
        raise FileNotFoundError(
            f"sweep file {str(path)!r} not found; give the path of a .toml scene file with a [sweep] table"
        ) from None
    data = read_toml(p, "sweep file")
    try:
        sweep = parse_sweep(data, source=p.name)
    except (SceneError, TypeError) as err:
        msg = str(err)
        raise type(err)(msg if msg.startswith(p.name) else f"{p.name}: {msg}") from None
    if not data.get("sweep", {}).get("name") and not sweep.scene.name:
        sweep = _renamed(sweep, p.stem)
    return sweep


def _renamed(sweep: Sweep, name: str) -> Sweep:
    cells = tuple(dataclasses.replace(c, sweep=name) for c in sweep.cells)
    return dataclasses.replace(sweep, name=name, cells=cells)


# ----------------------------------------------------------------------------------------------
# seeds and cache keys


def _run_scene_dict(scene: Scene, *, trials: int, seed: int, dtype: str, tolerance: float) -> dict[str, Any]:
    """The scene of a cell as it runs: file schema, defaults filled in, the run in ``[simulation]``."""
    d = scene.to_dict()
    d.pop("name", None)
    d.pop("description", None)
    d["simulation"] = {
        "trials": int(trials),
        "seed": int(seed),
        "dtype": str(dtype),
        "truncation_tolerance": float(tolerance),
    }
    if scene.simulation.truncation != "hard":  # keys of hard cells stay as they were
        d["simulation"]["truncation"] = scene.simulation.truncation
    return d


def cache_key(scene: Scene, *, seed: int, trials: int, dtype: str, tolerance: float) -> str:
    """Hash (hex, 40 characters) of the resolved cell, seed, trials, dtype, tolerance and version."""
    payload = {
        "format": CACHE_FORMAT,
        "version": _version(),
        "scene": _run_scene_dict(scene, trials=trials, seed=seed, dtype=dtype, tolerance=tolerance),
    }
    return hashlib.sha256(_canonical(payload).encode()).hexdigest()[:40]


# ----------------------------------------------------------------------------------------------
# running one cell (local or on a Dask worker: plain data in, plain data out)


def run_cell(payload: dict[str, Any]) -> dict[str, Any]:
    """Simulate one cell and compute its scalar metrics per trial.

    ``payload``: ``{"scene": scene dict (file schema, [simulation] holding trials, seed, dtype,
    truncation_tolerance)}``. Returns ``{"metrics": {name: array [trials, systems]}, "zero_intensity":
    bool array [trials, systems], "system_names": [...], "elapsed_s": float}``. Plain data, so it runs
    the same on a Dask worker.
    """
    from ..sim.metrics import compute_metrics
    from ..sim.simulate import simulate

    scene = scene_from_dict(payload["scene"])
    st = scene.simulation
    t0 = time.perf_counter()
    res = simulate(
        scene,
        trials=st.trials,
        seed=st.seed,
        dtype=st.dtype,
        truncation_tolerance=st.truncation_tolerance,
        progress=False,
    )
    analysis = dataclasses.replace(
        scene.analysis, metrics=tuple(m for m in scene.analysis.metrics if m in SCALAR_METRICS)
    )
    m = compute_metrics(res.signals, res.frame_times_s, analysis)
    return {
        "metrics": {k: m[k].cpu().numpy() for k in analysis.metrics},
        "zero_intensity": m["zero_intensity"].cpu().numpy(),
        "system_names": [s.name for s in scene.systems],
        "elapsed_s": time.perf_counter() - t0,
    }


def run_cell_batch(payloads: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """:func:`run_cell` on each payload (one Dask task per batch)."""
    return [run_cell(p) for p in payloads]


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class CellResult:
    """Per-trial scalar metrics ``[trials, systems]`` of one cell, and how they were produced."""

    cell: Cell
    sweep: Sweep
    seed: int
    trials: int
    dtype: str
    tolerance: float
    cache_key: str
    metrics: dict[str, np.ndarray]
    zero_intensity: np.ndarray
    system_names: tuple[str, ...]
    elapsed_s: float
    cached: bool


@dataclass
class SweepResult:
    """All cells of one or more sweeps; :meth:`table` is the tidy table."""

    sweeps: tuple[Sweep, ...]
    cells: list[CellResult]
    elapsed_s: float
    computed: int
    cached: int
    _table: Any = field(default=None, repr=False)

    def table(self):
        """The tidy table (pandas DataFrame), built once (see :func:`results_table`)."""
        if self._table is None:
            self._table = results_table(self.cells)
        return self._table

    def cell(self, sweep: str, index: int) -> CellResult:
        for c in self.cells:
            if c.cell.sweep == sweep and c.cell.index == index:
                return c
        raise KeyError(f"no cell {index} in sweep {sweep!r}")

    def of_sweep(self, sweep: str) -> list[CellResult]:
        return [c for c in self.cells if c.cell.sweep == sweep]

    @property
    def system_trials(self) -> int:
        return sum(c.trials * len(c.system_names) for c in self.cells)


#: System-trials of a sweep from which local cells run in worker processes rather than threads: a
#: worker process costs seconds to start, threads share the interpreter's lock. Set between the reduced
#: study, faster in threads on 2 cores, and the paper study, faster in processes (``torchdoct bench study``
#: records the workers and the wall time of both).
_PROCESS_WORK = 100_000


def _execute(
    payloads: list[dict[str, Any]],
    *,
    scheduler: str | None,
    batch_cells: int,
    workers: int,
    done: Callable[[int, dict[str, Any]], None],
) -> None:
    """Run payloads through the cell runner (:func:`torchdoct.study.cells.run_cells`): side by side in
    threads, in worker processes from :data:`_PROCESS_WORK` system-trials on, or on a Dask cluster;
    ``done(i, result)`` as each finishes."""
    work = sum(p["scene"]["simulation"]["trials"] * len(p["scene"]["system"]) for p in payloads)
    run_cells(
        run_cell,
        payloads,
        done=done,
        workers=workers,
        batch=batch_cells,
        scheduler=scheduler,
        processes=work >= _PROCESS_WORK,
    )


def run_sweeps(
    sweeps: Sequence[Sweep],
    *,
    trials: int | None = None,
    seed: int | None = None,
    dtype: str | None = None,
    tolerance: float | None = None,
    cache_dir: str | os.PathLike | None = None,
    scheduler: str | None = None,
    batch_cells: int = 1,
    workers: int = 1,
    progress: bool = False,
    desc: str = "sweep",
) -> SweepResult:
    """Run every cell of ``sweeps`` (cached cells are loaded, not recomputed).

    ``trials``, ``seed``, ``dtype`` and ``tolerance`` override each sweep's ``[simulation]`` values;
    each cell runs with :func:`cell_seed` of the base seed and its key. ``cache_dir`` (None: no cache)
    stores every finished cell at once, so an interrupted run resumes where it stopped.
    ``scheduler``: address of a Dask distributed scheduler (cells as tasks; None runs locally).
    ``batch_cells``: cells per task; ``workers``: the cores to use when no scheduler is given: local
    cells side by side with one torch thread each (threads, or worker processes for large sweeps), or
    (1, or a single task) one cell at a time with that many
    simulation threads (:mod:`torchdoct.runtime.threads`). Results depend on neither.
    """
    if isinstance(batch_cells, bool) or not isinstance(batch_cells, int) or batch_cells < 1:
        raise ValueError(f"batch_cells must be an integer >= 1; got {batch_cells!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1; got {workers!r}")
    if trials is not None and (isinstance(trials, bool) or not isinstance(trials, int) or trials < 1):
        raise ValueError(f"trials must be an integer >= 1; got {trials!r}")
    if dtype is not None and dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64'; got {dtype!r}")
    if tolerance is not None and not (0.0 < tolerance < 1.0):
        raise ValueError(f"tolerance must be in (0, 1); got {tolerance!r}")
    names = [s.name for s in sweeps]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"sweep names must be unique; {dup} appear twice")
    check_cache_dir(cache_dir)
    t0 = time.perf_counter()
    info, jobs = _jobs(sweeps, trials=trials, seed=seed, dtype=dtype, tolerance=tolerance)

    def execute(payloads: list, done: Callable) -> None:
        _execute(payloads, scheduler=scheduler, batch_cells=batch_cells, workers=workers, done=done)

    results, pending = run_cached(
        jobs,
        cache=CellCache(cache_dir),
        execute=execute,
        encode=_encode,
        decode=_decode,
        progress=progress,
        desc=desc,
        unit="trial",
        what="cells",
        before=lambda todo: _check_resources(
            [info[j] for j in todo],
            scheduler=scheduler,
            workers=workers,
            batch_cells=batch_cells,
            cache_dir=cache_dir,
            trials=trials,
        ),
    )
    computed = set(pending)
    cells = [_cell_result(info[j], res, cached=j not in computed) for j, res in enumerate(results)]
    return SweepResult(
        sweeps=tuple(sweeps),
        cells=cells,
        elapsed_s=time.perf_counter() - t0,
        computed=len(pending),
        cached=len(jobs) - len(pending),
    )


def _jobs(
    sweeps: Sequence[Sweep], *, trials: int | None, seed: int | None, dtype: str | None, tolerance: float | None
) -> tuple[list[tuple], list[CellJob]]:
    """Every cell as it runs: ``(sweep, cell, seed, trials, dtype, tolerance, cache key)`` and its
    :class:`~torchdoct.study.cells.CellJob` (the payload of :func:`run_cell`)."""
    info, jobs = [], []
    for sw in sweeps:
        for cell in sw.cells:
            st = cell.scene.simulation
            n = trials if trials is not None else st.trials
            base = seed if seed is not None else sw.scene.simulation.seed
            s = cell_seed(base, cell.key)
            dt = dtype or st.dtype
            tol = tolerance if tolerance is not None else st.truncation_tolerance
            key = cache_key(cell.scene, seed=s, trials=n, dtype=dt, tolerance=tol)
            info.append((sw, cell, s, n, dt, tol, key))
            jobs.append(
                CellJob(
                    key=key,
                    payload={"scene": _run_scene_dict(cell.scene, trials=n, seed=s, dtype=dt, tolerance=tol)},
                    weight=n,
                )
            )
    return info, jobs


def check_sweep_resources(
    sweeps: Sequence[Sweep],
    *,
    trials: int | None = None,
    seed: int | None = None,
    dtype: str | None = None,
    tolerance: float | None = None,
    cache_dir: str | os.PathLike | None = None,
    scheduler: str | None = None,
    batch_cells: int = 1,
    workers: int = 1,
) -> None:
    """The resource check of :func:`run_sweeps` (same arguments), for a command to call before it makes its
    output folder: the cells without a cache file must fit (:func:`torchdoct.runtime.resources.check_resources`)."""
    info, jobs = _jobs(sweeps, trials=trials, seed=seed, dtype=dtype, tolerance=tolerance)
    cache = CellCache(cache_dir)
    todo = [i for i, job in zip(info, jobs) if cache.dir is None or not cache.path(job.key).is_file()]
    _check_resources(
        todo, scheduler=scheduler, workers=workers, batch_cells=batch_cells, cache_dir=cache_dir, trials=trials
    )


def _encode(job: CellJob, res: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A cell's cache entry (:class:`~torchdoct.study.cells.CellCache`): its per-trial metrics
    ``metric_<name>``, ``zero_intensity`` and a header with the resolved scene that ran."""
    arrays = {f"metric_{k}": v for k, v in res["metrics"].items()}
    arrays["zero_intensity"] = res["zero_intensity"]
    return arrays, {
        "format": CACHE_FORMAT,
        "version": _version(),
        "scene": job.payload["scene"],
        "metrics": list(res["metrics"]),
        "system_names": list(res["system_names"]),
        "elapsed_s": res["elapsed_s"],
    }


def _decode(job: CellJob, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> dict[str, Any]:
    return {
        "metrics": {k: arrays[f"metric_{k}"] for k in meta["metrics"]},
        "zero_intensity": arrays["zero_intensity"],
        "system_names": meta["system_names"],
        "elapsed_s": meta.get("elapsed_s", 0.0),
    }


@functools.lru_cache(maxsize=4096)
def _cell_plan(scene: Scene, tolerance: float) -> Any:
    """One cell's plan (:func:`torchdoct.sim.plan.make_plan`); remembered, so a command's check before its
    output folder and :func:`run_sweeps`' own plan each cell once."""
    from ..sim.plan import make_plan

    return make_plan(scene, truncation_tolerance=tolerance)


def _check_cell_precision(job: tuple) -> None:
    """The cell's numbers within what its dtype holds (:func:`torchdoct.sim.simulate.check_precision`), else a
    ``ValueError`` naming the sweep and the cell, before any cell runs."""
    import torch

    from ..sim.simulate import check_precision

    sw, cell, _, _, dt, tol, _ = job
    try:
        check_precision(cell.scene, _cell_plan(cell.scene, tol), getattr(torch, dt))
    except ValueError as err:
        desc = ", ".join(f"{p} = {v!r}" for p, v in cell.assignments)
        raise ValueError(f"sweep {sw.name!r}, cell {cell.index} ({desc}): {err}") from None


@functools.lru_cache(maxsize=4096)
def _cell_bytes(scene: Scene, trials: int, threads: int, tolerance: float, dtype_bytes: int) -> int:
    """Peak memory of one cell's simulation (:func:`torchdoct.sim.memory.simulation_bytes`); remembered."""
    from ..sim.memory import simulation_bytes

    plan = _cell_plan(scene, tolerance)
    return simulation_bytes(
        plan,
        trials=trials,
        n_systems=len(scene.systems),
        n_frames=scene.protocol.n_frames,
        threads=threads,
        dtype_bytes=dtype_bytes,
    )[0]


def _check_resources(
    todo: list[tuple],
    *,
    scheduler: str | None,
    workers: int,
    batch_cells: int,
    cache_dir: str | os.PathLike | None,
    trials: int | None,
) -> None:
    """The cells to compute fit in memory (the largest cell's simulation times the cells side by side, plus
    every cell's per-trial metrics) and their cache entries on disk: :func:`torchdoct.runtime.resources.check_resources`,
    before any cell runs."""
    if not todo:
        return
    from ..runtime.resources import check_resources

    batches = -(-len(todo) // batch_cells)
    side_by_side = scheduler is None and workers > 1 and batches > 1
    largest, where = 0, todo[0]
    results = 0
    for job in todo:
        _check_cell_precision(job)
        sw, cell, s, n, dt, tol, key = job
        results += n * len(cell.scene.systems) * (len(SCALAR_METRICS) + 1) * 8
        if scheduler is None:  # on a cluster the cells' memory is the workers'
            need = _cell_bytes(cell.scene, n, 1 if side_by_side else workers, tol, 4 if dt == "float32" else 8)
            if need > largest:
                largest, where = need, job
    at_once = min(workers, batches) if side_by_side else 1
    sw, cell, _, n, _, tol, _ = where
    names = list(dict.fromkeys(job[0].name for job in todo))
    desc = ", ".join(f"{p} = {v!r}" for p, v in cell.assignments)
    fix = (
        f"lower the trials per cell (--trials, now {n}), run fewer cells side by side (--workers, now {workers}), "
        f"or loosen the truncation tolerance (--tolerance or simulation.truncation_tolerance, now {tol:g})"
    )
    check_resources(
        f"sweep {names[0]!r}" if len(names) == 1 else f"running {len(todo)} cells of {len(names)} sweeps",
        largest * at_once + results,
        fix,
        detail=f"the largest cell, {'' if len(names) == 1 else repr(sw.name) + ' '}{cell.index} ({desc}), "
        f"{largest / 2**30:.2f} GB with {n} trials, × {at_once} cell(s) side by side, plus the "
        f"per-trial metrics of {len(todo)} cells",
        out_path=cache_dir,
        out_bytes=results if cache_dir is not None else 0,
        out_fix="free disk space there, give another --cache directory, or --no-cache",
    )


def run_sweep(sweep: Sweep, **kwargs: Any) -> SweepResult:
    """:func:`run_sweeps` of one sweep."""
    return run_sweeps([sweep], **kwargs)


def _cell_result(job, res: dict[str, Any], cached: bool) -> CellResult:
    sw, cell, s, n, dt, tol, key = job
    return CellResult(
        cell=cell,
        sweep=sw,
        seed=s,
        trials=n,
        dtype=dt,
        tolerance=tol,
        cache_key=key,
        metrics=dict(res["metrics"]),
        zero_intensity=np.asarray(res["zero_intensity"]),
        system_names=tuple(res["system_names"]),
        elapsed_s=float(res["elapsed_s"]),
        cached=cached,
    )


# ----------------------------------------------------------------------------------------------
# the tidy table


def _column_value(v: Any) -> Any:
    if v is None or isinstance(v, (str, bool)) or _is_number(v):
        return v
    return json.dumps(v, sort_keys=True)


def results_table(cells: Sequence[CellResult]):
    """Tidy table (pandas): one row per cell × system × scalar metric (module docstring)."""
    import pandas as pd

    rows = []
    for c in cells:
        systems = {s.name: s for s in c.cell.scene.systems}
        for s_idx, sname in enumerate(c.system_names):
            sy = systems[sname]
            for metric, arr in c.metrics.items():
                v = np.asarray(arr[:, s_idx], dtype=np.float64)
                v = v[np.isfinite(v)]
                n = int(v.size)
                mean = float(v.mean()) if n else math.nan
                sd = float(v.std(ddof=1)) if n > 1 else math.nan
                row = {"sweep": c.cell.sweep, **dict(c.sweep.tags), "cell": c.cell.index}
                row.update({k: _column_value(x) for k, x in c.cell.values.items()})
                row.update(
                    {
                        "system": sname,
                        "wavelength_um": sy.wavelength_um,
                        "lateral_resolution_um": sy.lateral_resolution_um,
                        "axial_resolution_um": sy.axial_resolution_um,
                        "refractive_index": sy.refractive_index,
                        "metric": metric,
                        "unit": SCALAR_METRICS[metric],
                        "mean": mean,
                        "sd": sd,
                        "se": sd / math.sqrt(n) if n > 1 else math.nan,
                        "n": n,
                        "empty": int(np.asarray(c.zero_intensity[:, s_idx]).sum()),
                        "trials": c.trials,
                        "seed": c.seed,
                        "cache_key": c.cache_key,
                    }
                )
                rows.append(row)
    df = pd.DataFrame(rows)
    for col in df.columns:  # Parquet needs one type per column: mixed field values become text
        if df[col].dtype == object:
            kinds = {type(x) for x in df[col] if x is not None and not (isinstance(x, float) and math.isnan(x))}
            if len(kinds) > 1:
                df[col] = df[col].map(lambda x: None if x is None else str(x))
    return df


def write_table(table, stem: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Write ``stem.csv`` and ``stem.parquet`` atomically (refusing to overwrite without ``force``)."""
    from ..files import atomic_write, check_out

    stem = Path(stem)
    csv = check_out(stem.with_suffix(".csv"), force, ".csv", "--out")
    pq = check_out(stem.with_suffix(".parquet"), force, ".parquet", "--out")
    atomic_write(csv, lambda tmp: table.to_csv(tmp, index=False))
    atomic_write(pq, lambda tmp: table.to_parquet(tmp, index=False))
    return [csv, pq]


def _run_record(result: SweepResult) -> list[dict[str, Any]]:
    return [
        {
            "sweep": c.cell.sweep,
            "cell": c.cell.index,
            "values": {k: _column_value(v) for k, v in c.cell.values.items()},
            "seed": c.seed,
            "trials": c.trials,
            "dtype": c.dtype,
            "truncation_tolerance": c.tolerance,
            "cache_key": c.cache_key,
        }
        for c in result.cells
    ]


def sweep_outputs(out_dir: str | os.PathLike, stem: str = "results") -> list[Path]:
    """The files :func:`write_sweep_outputs` writes into ``out_dir``."""
    d = Path(out_dir)
    return [d / f"{stem}.csv", d / f"{stem}.parquet", d / "sweep.json"]


def check_cache_dir(cache_dir: str | os.PathLike | None, what: str = "--cache") -> None:
    """Refuse, before any work, a cache directory that is an existing regular file."""
    if cache_dir is not None and Path(cache_dir).exists() and not Path(cache_dir).is_dir():
        raise ValueError(f"{what} {cache_dir} is a file; give a directory (created if missing) or --no-cache")


def prepare_out_dir(out_dir: str | os.PathLike, files: Sequence[Path], force: bool, what: str = "--out") -> Path:
    """Create ``out_dir`` (its parent must exist) and check that none of ``files`` would be overwritten."""
    d = Path(out_dir)
    if d.exists() and not d.is_dir():
        raise ValueError(f"{what}: {d} exists and is not a directory; give a directory")
    if not d.exists():
        if not d.parent.exists():
            raise ValueError(f"{what}: directory {d.parent} does not exist; create it first")
        d.mkdir()
    clash = [p for p in files if p.exists()]
    if clash and not force:
        raise ValueError(
            f"{what}: {', '.join(str(p) for p in clash)} exist(s); pass --force to overwrite "
            "(finished cells come from the cache either way)"
        )
    return d


def write_sweep_outputs(
    result: SweepResult, out_dir: str | os.PathLike, *, force: bool = False, stem: str = "results"
) -> list[Path]:
    """Write the tidy table (CSV, Parquet) and ``sweep.json`` (resolved sweeps, cells, seeds, keys):
    the three appear together or not at all (:func:`torchdoct.files.output_set`)."""
    from ..files import atomic_write, output_set

    files = sweep_outputs(out_dir, stem)
    prepare_out_dir(out_dir, files, force)
    record = {
        "torchdoct_version": _version(),
        "sweeps": [s.to_dict() for s in result.sweeps],
        "cells": _run_record(result),
    }
    with output_set(files, force) as stage:
        write_table(result.table(), stage(files[0]).with_suffix(""), force=force)
        atomic_write(stage(files[2]), lambda tmp: Path(tmp).write_text(json.dumps(record, indent=2), encoding="utf-8"))
    return files


def format_table(table, metrics: Sequence[str] = ("liv", "ocds")) -> str:
    """Mean (SE) per cell (rows) and system (columns) for each metric: what ``torchdoct sweep`` prints."""
    out = []
    fixed = set(RESERVED_COLUMNS)
    value_cols = [c for c in table.columns if c not in fixed]
    multi = table["sweep"].nunique() > 1
    for metric in metrics:
        t = table[table["metric"] == metric]
        if t.empty:
            continue
        systems = list(dict.fromkeys(t["system"]))
        rows: dict[tuple[str, int], dict[str, str]] = {}
        labels: dict[tuple[str, int], str] = {}
        for r in t.to_dict("records"):
            k = (r["sweep"], r["cell"])
            if k not in labels:
                parts = [
                    f"{c}={r[c]:.6g}" if isinstance(r[c], float) else f"{c}={r[c]}"
                    for c in value_cols
                    if not _missing(r[c])
                ]
                labels[k] = (f"{r['sweep']}: " if multi else "") + ", ".join(parts)
            rows.setdefault(k, {})[r["system"]] = f"{r['mean']:.4g} ({r['se']:.2g})"
        width = max(len(v) for v in labels.values())
        cw = max(16, *(len(s) for s in systems))
        lines = [
            f"{metric} mean (SE) [{t['unit'].iloc[0]}]",
            " " * width + "  " + "  ".join(f"{s:>{cw}}" for s in systems),
        ]
        for k, lab in labels.items():
            lines.append(f"{lab:<{width}}  " + "  ".join(f"{rows[k].get(s, '-'):>{cw}}" for s in systems))
        out.append("\n".join(lines))
    return "\n\n".join(out)


def _missing(x: Any) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))

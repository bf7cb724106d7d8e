"""The reference paper's numerical study: its sweeps, Figs. 6-8, and a claims report with numbers.

A *study file* (``torchdoct/data/studies/*.toml``; ``paper`` is the full study, ``paper-reduced`` a
small one for tests and the notebook) holds:

* ``[study]``: ``trials``, ``seed``, ``dtype``, ``grouping`` (``"pairs"``: one scene per comparison,
  so the two systems of a comparison see the same scatterers; ``"all"``: every system in one scene),
  ``figure_parts`` (the three parts whose curves are the rows of each figure: diffusion, random
  ballistic, flow), optional ``direction_parts`` (two ballistic parts that differ only by the
  direction law) and ``[[study.comparison]]`` tables (``name``, ``figure``, ``title``, ``reference``,
  ``other``: two system names);
* ``[scene]``: the scene every part shares (scene-file schema of the README); each part appends its
  motion to the first population;
* ``[[part]]``: ``name``, ``label`` (x axis), ``parameter`` (the swept key of the motion table),
  ``inset_max`` (x range of the small-motion inset), ``motion`` (a motion table) and the values as in a
  sweep field (``values`` / ``linear`` / ``log``, see :mod:`torchdoct.study.sweep`).

:func:`run_study` turns every part (× comparison when grouped in pairs) into a :class:`~torchdoct.study.sweep.Sweep`,
runs them (cached, resumable, locally or on Dask), and writes into the output directory:

* ``results.csv``/``.parquet``: the tidy table of :mod:`torchdoct.study.sweep` with the columns ``part``,
  ``comparison``, ``motion``, ``parameter`` and ``value`` (the motion parameter);
* ``differences.csv``/``.parquet``: per part, comparison, value and metric, both systems' mean and SD
  and the paired difference ``other − reference`` over the same trials (same scatterers) with its
  standard error and ``z = diff/SE``;
* ``directions.csv``/``.parquet``: isotropic minus uniform-angle ballistic motion per system
  (trials paired by seed, see below);
* one figure per comparison (PNG and SVG), equivalent to the paper's Figs. 6, 7, 8: rows diffusion,
  random ballistic, flow; columns LIV and OCDS; mean ± SD of both systems; an inset at small motion;
  and ``fig-directions`` comparing the two ballistic direction laws;
* ``claims.md``: every numerical finding of the paper's Sections 3.3 and 4 with this run's numbers and
  a verdict; ``study.json``: the resolved study, every cell's seed and cache key, wall times.

Metrics are those of :mod:`torchdoct.sim.metrics` (LIV: physics.md §1; OCDS: physics.md §2.4); ENS and
N_eff come from :mod:`torchdoct.conventions` (physics.md §5.5).

Statistics: a difference is *significant* when ``|z| ≥ 4`` (``Z_SIGNIFICANT``; the project's bound
for Monte Carlo comparisons, conservative for the ~30 values of a curve). Cells of one motion value
share their seed across parts and comparisons (the seed depends on the base seed and the cell key
``{path: value}`` only, :func:`torchdoct.study.sweep.cell_seed`), so the two direction laws are compared with
common random numbers; every SE is computed from per-trial differences and is valid either way.

The package is split by concern, in import order (each module imports only those before it):
:mod:`~torchdoct.study.spec` (the study file), :mod:`~torchdoct.study.sweeps` (the sweeps a study
builds), :mod:`~torchdoct.study.stats` (paired statistics), :mod:`~torchdoct.study.figures` and
:mod:`~torchdoct.study.claims` (both read only the study and the statistics' tables),
:mod:`~torchdoct.study.run` (:func:`run_study` writes everything); its benchmark is
:mod:`torchdoct.bench.study`. Every public name is importable from ``torchdoct.study``.
"""

from __future__ import annotations

from .claims import claims_report
from .figures import plot_comparison, plot_directions
from .run import StudyResult, run_study, study_outputs
from .spec import Comparison, Part, Study, load_study, shipped_studies, study_from_dict
from .stats import Z_SIGNIFICANT, _crossing, _Curve, direction_differences, paired_differences  # noqa: F401  (private; the tests check the crossing on a _Curve)
from .sweeps import study_sweeps

__all__ = [
    "Z_SIGNIFICANT",
    "Comparison",
    "Part",
    "Study",
    "StudyResult",
    "shipped_studies",
    "load_study",
    "study_from_dict",
    "study_sweeps",
    "study_outputs",
    "paired_differences",
    "direction_differences",
    "plot_comparison",
    "plot_directions",
    "claims_report",
    "run_study",
]

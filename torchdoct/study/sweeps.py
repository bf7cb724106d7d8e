"""The sweeps a study builds: one :class:`~torchdoct.study.sweep.Sweep` per part, or per part × comparison
(``grouping = "pairs"``), each tagged with ``part``, ``comparison``, ``motion`` and ``parameter``.

Running them (grids, seeds, cache, resume, Dask) is :mod:`torchdoct.study.sweep`'s concern; what a study
computes from their cells is :mod:`torchdoct.study.stats`'.
"""

from __future__ import annotations

import copy

from .spec import Study
from .sweep import make_sweep

__all__ = ["study_sweeps"]


def _sweep_name(part: str, comparison: str) -> str:
    return part if comparison == "all" else f"{part}/{comparison}"


def _groups(study: Study) -> list[tuple[str, list[str]]]:
    """(comparison or "all", system names) of each scene of a part."""
    if study.grouping == "all":
        return [("all", [s["name"] for s in study.scene_data["system"]])]
    return [(c.name, [c.reference, c.other]) for c in study.comparisons]


def study_sweeps(study: Study):
    """The sweeps of a study: one per part, or per part × comparison (``grouping = "pairs"``)."""
    sweeps = []
    for part in study.parts:
        for comp, systems in _groups(study):
            data = copy.deepcopy(study.scene_data)
            data["system"] = [copy.deepcopy(study.system(n)) for n in systems]
            data["name"] = f"{study.name}-{part.name}"
            motions = data["population"][0].setdefault("motion", [])
            motions.append(copy.deepcopy(part.motion))
            data.setdefault("simulation", {}).update({"trials": study.trials, "seed": study.seed, "dtype": study.dtype})
            path = f"population.0.motion.{len(motions) - 1}.{part.parameter}"
            sweeps.append(
                make_sweep(
                    data,
                    [{"path": path, "name": "value", "values": list(part.values)}],
                    name=_sweep_name(part.name, comp),
                    tags={"part": part.name, "comparison": comp, "motion": part.kind, "parameter": part.parameter},
                )
            )
    return sweeps

"""The study file: :func:`load_study` and :func:`study_from_dict` validate it (errors name the key and
the fix) into a frozen :class:`Study` of :class:`Part` (one motion model swept over its parameter) and
:class:`Comparison` (two systems compared pairwise).

The schema is described in :mod:`torchdoct.study`; the values of a part follow the sweep-field grammar
of :mod:`torchdoct.study.sweep`. Nothing here runs a simulation.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..files import file_or_shipped, safe_name, shipped_files
from ..sim.config import SceneError, _check_keys, _fail, read_toml, scene_from_dict
from .sweep import _normalize_arrays, field_values

__all__ = ["Comparison", "Part", "Study", "shipped_studies", "load_study", "study_from_dict"]


def _tables(where: str, value: Any, empty: str) -> list:
    """An array of tables (a single table becomes one); none at all fails with ``empty``."""
    value = [value] if isinstance(value, dict) else value
    if not isinstance(value, list) or not value:
        _fail(where, empty)
    return value


def _str(where: str, v: Any) -> str:
    if not isinstance(v, str) or not v:
        raise TypeError(f"{where} must be a non-empty string; got {v!r}")
    return v


@dataclass(frozen=True)
class Comparison:
    """Two systems compared pairwise: ``other − reference`` (same scatterers)."""

    name: str
    figure: str
    title: str
    reference: str
    other: str
    paper_figure: str = ""


@dataclass(frozen=True)
class Part:
    """One motion model swept over its parameter (``parameter`` = key of the motion table)."""

    name: str
    label: str
    parameter: str
    inset_max: float
    motion: dict[str, Any]
    values: tuple[float, ...]

    @property
    def kind(self) -> str:
        return self.motion["kind"]


@dataclass(frozen=True)
class Study:
    """A validated study file (schema: :mod:`torchdoct.study`)."""

    name: str
    description: str
    trials: int
    seed: int
    dtype: str
    grouping: str
    comparisons: tuple[Comparison, ...]
    parts: tuple[Part, ...]
    figure_parts: tuple[str, ...]
    direction_parts: tuple[str, ...]
    scene_data: dict[str, Any] = field(repr=False)

    def part(self, name: str) -> Part:
        return next(p for p in self.parts if p.name == name)

    def system(self, name: str) -> dict[str, Any]:
        return next(s for s in self.scene_data["system"] if s["name"] == name)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "description": self.description,
            "study": {
                "trials": self.trials,
                "seed": self.seed,
                "dtype": self.dtype,
                "grouping": self.grouping,
                "figure_parts": list(self.figure_parts),
                "direction_parts": list(self.direction_parts),
                "comparison": [c.__dict__ for c in self.comparisons],
            },
            "scene": self.scene_data,
            "part": [
                {
                    "name": p.name,
                    "label": p.label,
                    "parameter": p.parameter,
                    "inset_max": p.inset_max,
                    "motion": p.motion,
                    "values": list(p.values),
                }
                for p in self.parts
            ],
        }


def shipped_studies() -> dict[str, Path]:
    """Name -> path of every study file shipped with torchdoct."""
    return shipped_files("torchdoct", "data/studies")


def _resolve(study: str | os.PathLike) -> Path:
    shipped = shipped_studies()
    found = file_or_shipped(study, shipped, "study file")
    if found is not None:
        return found
    raise FileNotFoundError(
        f"study {str(study)!r} not found; give a study .toml file or the name of a shipped study: {', '.join(shipped)}"
    )


def load_study(study: str | os.PathLike) -> Study:
    """Read and validate a study file, or a shipped study by name (``paper``, ``paper-reduced``)."""
    p = _resolve(study)
    data = read_toml(p)
    try:
        return study_from_dict(data, default_name=p.stem)
    except (SceneError, TypeError) as err:
        raise type(err)(f"{p.name}: {err}") from None


def study_from_dict(data: dict[str, Any], *, default_name: str = "study") -> Study:
    """A validated :class:`Study` from the study-file schema (:mod:`torchdoct.study`)."""
    _check_keys("study file", data, {"name", "description", "study", "scene", "part"}, {"study", "scene", "part"})
    st = _check_keys(
        "study",
        data["study"],
        {"trials", "seed", "dtype", "grouping", "figure_parts", "direction_parts", "comparison"},
        {"comparison", "figure_parts"},
    )
    trials = st.get("trials", 500)
    seed = st.get("seed", 0)
    for k, v in (("trials", trials), ("seed", seed)):
        if isinstance(v, bool) or not isinstance(v, int) or v < (1 if k == "trials" else 0):
            raise TypeError(f"study.{k} must be an integer >= {1 if k == 'trials' else 0}; got {v!r}")
    dtype = st.get("dtype", "float32")
    if dtype not in ("float32", "float64"):
        _fail("study.dtype", f"must be 'float32' or 'float64'; got {dtype!r}")
    grouping = st.get("grouping", "pairs")
    if grouping not in ("pairs", "all"):
        _fail("study.grouping", f"must be 'pairs' or 'all'; got {grouping!r}")

    scene = copy.deepcopy(data["scene"])
    if not isinstance(scene, dict):
        raise TypeError(f"scene must be a table; got {scene!r}")
    _normalize_arrays(scene)
    if not isinstance(scene.get("population"), list) or not scene["population"]:
        _fail("scene.population", "the study needs a [[scene.population]] for the parts' motion")
    try:
        scene_from_dict(scene)
    except (SceneError, TypeError) as err:
        raise type(err)(f"scene: {err}") from None
    system_names = [s["name"] for s in scene["system"]]

    comps = _tables("study.comparison", st["comparison"], "needs at least one [[study.comparison]]")
    comparisons = []
    for i, c in enumerate(comps):
        w = f"study.comparison[{i}]"
        _check_keys(
            w, c, {"name", "figure", "title", "paper_figure", "reference", "other"}, {"name", "reference", "other"}
        )
        for k in ("reference", "other"):
            if _str(f"{w}.{k}", c[k]) not in system_names:
                _fail(f"{w}.{k}", f"{c[k]!r} is not a system of [scene]", f"use one of {system_names}")
        if c["reference"] == c["other"]:
            _fail(w, "reference and other are the same system", "compare two different systems")
        name = _str(f"{w}.name", c["name"])
        figure = _str(f"{w}.figure", c.get("figure", f"fig-{name}"))
        try:  # the figure's files are OUT/FIGURE.png and .svg
            safe_name(
                figure,
                f"{w}.figure" if "figure" in c else f"{w}.name (the figure is fig-NAME)",
                "give a plain name such as fig-6",
            )
        except ValueError as err:
            raise SceneError(str(err)) from None
        if "." in figure:
            _fail(
                f"{w}.figure",
                f"{figure!r} holds a dot; its files are FIGURE.png and FIGURE.svg",
                "give a name without a suffix, such as fig-6",
            )
        comparisons.append(
            Comparison(
                name=name,
                figure=figure,
                title=_str(f"{w}.title", c.get("title", name)),
                reference=c["reference"],
                other=c["other"],
                paper_figure=_str(f"{w}.paper_figure", c.get("paper_figure", c.get("figure", name))),
            )
        )
    names = [c.name for c in comparisons]
    if len(set(names)) != len(names) or "all" in names:
        _fail("study.comparison", f"names must be unique and not 'all'; got {names}")

    parts_data = _tables("part", data["part"], "a study needs at least one [[part]]")
    parts = []
    for i, p in enumerate(parts_data):
        w = f"part[{i}]"
        _check_keys(
            w,
            p,
            {"name", "label", "parameter", "inset_max", "motion", "values", "linear", "log"},
            {"name", "parameter", "motion"},
        )
        motion = p["motion"]
        if not isinstance(motion, dict) or "kind" not in motion:
            raise TypeError(f"{w}.motion must be a motion table with a kind; got {motion!r}")
        param = _str(f"{w}.parameter", p["parameter"])
        if param not in motion:
            _fail(f"{w}.parameter", f"{param!r} is not a key of {w}.motion", f"add {param} = 0.0 to the motion table")
        test = copy.deepcopy(scene)
        test["population"][0].setdefault("motion", []).append(motion)
        try:
            scene_from_dict(test)
        except (SceneError, TypeError) as err:
            raise type(err)(f"{w}.motion: {err}") from None
        values = field_values({k: p[k] for k in ("values", "linear", "log") if k in p}, w)
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
                _fail(w, f"motion values must be numbers >= 0; got {v!r}")
        inset = p.get("inset_max", max(values) / 10 if max(values) > 0 else 1.0)
        if isinstance(inset, bool) or not isinstance(inset, (int, float)) or not inset > 0:
            raise TypeError(f"{w}.inset_max must be a number > 0; got {inset!r}")
        parts.append(
            Part(
                name=_str(f"{w}.name", p["name"]),
                label=_str(f"{w}.label", p.get("label", param)),
                parameter=param,
                inset_max=float(inset),
                motion=dict(motion),
                values=tuple(float(v) for v in values),
            )
        )
    pnames = [p.name for p in parts]
    if len(set(pnames)) != len(pnames):
        _fail("part", f"part names must be unique; got {pnames}")
    fig_parts = st["figure_parts"]
    if not isinstance(fig_parts, list) or not fig_parts:
        raise TypeError(f"study.figure_parts must be a list of part names; got {fig_parts!r}")
    for n in fig_parts:
        if n not in pnames:
            _fail("study.figure_parts", f"{n!r} is not a part", f"use names of [[part]]: {pnames}")
    dir_parts = st.get("direction_parts", [])
    if dir_parts:
        if not isinstance(dir_parts, list) or len(dir_parts) != 2 or any(n not in pnames for n in dir_parts):
            _fail(
                "study.direction_parts", f"must name two parts; got {dir_parts!r}", f"use names of [[part]]: {pnames}"
            )
        a, b = (next(p for p in parts if p.name == n) for n in dir_parts)
        strip = lambda m: {k: v for k, v in m.items() if k != "directions"}  # noqa: E731
        if a.kind != "ballistic" or b.kind != "ballistic" or strip(a.motion) != strip(b.motion) or a.values != b.values:
            _fail(
                "study.direction_parts",
                f"{dir_parts} must be ballistic parts with the same values that differ only in directions",
            )
    return Study(
        name=_str("name", data.get("name", default_name)),
        description=data.get("description", ""),
        trials=trials,
        seed=seed,
        dtype=dtype,
        grouping=grouping,
        comparisons=tuple(comparisons),
        parts=tuple(parts),
        figure_parts=tuple(fig_parts),
        direction_parts=tuple(dir_parts),
        scene_data=scene,
    )


def _xunit(part: Part) -> str:
    return "µm²/s" if "um2_per_s" in part.parameter else ("µm/s" if "um_per_s" in part.parameter else "")


def _xsym(part: Part) -> str:
    return "D" if part.kind == "diffusion" else "v"

"""Phantoms: a scene whose scatterer populations live in labelled regions, imaged on a pixel grid.

A phantom file is a scene file (systems, protocol, noise, analysis, simulation: see
:mod:`torchdoct.sim.config`) with a ``[grid]`` table and, instead of ``[[population]]``, one or more
``[[region]]`` tables and optional ``[[background]]`` populations (schema in the README). Each region
is a shape with its own scatterer population (``density_per_um3``, ``reflectivity``,
``[[region.motion]]``, the keys of a ``[[population]]``); the background populations fill everything
outside the regions; without them, the outside is empty. Later regions paint over earlier ones where
they overlap. A plain scene file (``[[population]]``, no regions) with a grid is a uniform medium:
its populations are the background.

Coordinates (:mod:`torchdoct.conventions`): µm, ``x`` lateral (fast axis), ``y`` lateral (slow axis),
``z`` depth (increasing into the sample). The grid is centred on the origin: pixel ``i`` along an axis
of ``n`` pixels at pitch ``p`` sits at ``(i − (n−1)/2)·p``. A B-scan lies in the plane ``y = y_um``.

A region's population is present at every frame exactly where the region is: scatterers move with the
region's motion and count at a frame only while inside the region (a flow channel is a stationary
stream; a diffusing core keeps its density). Ground-truth labels are the region of each pixel centre.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..files import file_or_shipped, shipped_files
from ..sim.config import (
    Population,
    Scene,
    SceneError,
    _check_keys,
    _fail,
    _integer,
    _number,
    _string,
    check_count,
    read_toml,
    scene_from_dict,
)
from ..sim.scenes import shipped_scenes

__all__ = [
    "Grid",
    "Region",
    "Phantom",
    "load_phantom",
    "phantom_from_dict",
    "shipped_phantoms",
    "MOTION_CODES",
    "motion_code",
]

SHAPES = ("sphere", "ellipsoid", "slab", "cylinder", "label-image")
#: Label codes of the ground-truth motion map.
MOTION_CODES = {"empty": 0, "static": 1, "diffusion": 2, "ballistic": 3, "flow": 4, "mixed": 5}
MAX_PIXELS = 2**28
#: Largest region radius (µm, 10 m): squared in :meth:`Region.contains`, a radius of 1e300 overflowed; a
#: region larger than any field of view is given as a slab or as the background instead.
MAX_LENGTH_UM = 1e7


def motion_code(pops: Population | Sequence[Population] | None) -> int:
    """Ground-truth code (:data:`MOTION_CODES`) of populations sharing a region: their single
    motion kind (static scatterers beside moving ones do not change it), or mixed."""
    if pops is None:
        return MOTION_CODES["empty"]
    pops = [pops] if isinstance(pops, Population) else list(pops)
    if not pops:
        return MOTION_CODES["empty"]
    kinds = {type(m).__name__ for p in pops for m in p.active_motion}
    if not kinds:
        return MOTION_CODES["static"]
    if len(kinds) > 1:
        return MOTION_CODES["mixed"]
    return MOTION_CODES[{"Diffusion": "diffusion", "RandomBallistic": "ballistic", "Flow": "flow"}[kinds.pop()]]


@dataclass(frozen=True, kw_only=True)
class Grid:
    """Pixel grid: ``kind`` "bscan" ([T, Z, X], plane y = ``y_um``) or "volume" ([T, Y, Z, X]).

    Pitches in µm per axis; the field of view is ``n·pitch`` per axis, centred on the origin.
    """

    kind: str = "bscan"
    n_x: int
    n_z: int
    pitch_x_um: float
    pitch_z_um: float
    n_y: int = 1
    pitch_y_um: float = 1.0
    y_um: float = 0.0

    def __post_init__(self) -> None:
        _string("grid.kind", self.kind, ("bscan", "volume"))
        for key in ("n_x", "n_z", "n_y"):
            object.__setattr__(self, key, _integer(f"grid.{key}", getattr(self, key), lo=1))
        for key in ("pitch_x_um", "pitch_z_um", "pitch_y_um"):
            _number(f"grid.{key}", getattr(self, key), positive=True, unit="µm")
        _number("grid.y_um", self.y_um, unit="µm")
        if self.kind == "bscan" and self.n_y != 1:
            _fail("grid.n_y", f"a B-scan has one plane; got n_y = {self.n_y}", 'set kind = "volume"')
        if self.n_x * self.n_y * self.n_z > MAX_PIXELS:
            _fail(
                "grid.n_x, n_y, n_z",
                f"{self.n_x:.4g} × {self.n_y:.4g} × {self.n_z:.4g} pixels exceed {MAX_PIXELS}",
                "use fewer pixels or a coarser pitch",
            )

    @property
    def axes(self) -> str:
        return "TZX" if self.kind == "bscan" else "TYZX"

    @property
    def shape(self) -> tuple[int, ...]:
        """Spatial shape: (Z, X) or (Y, Z, X)."""
        return (self.n_z, self.n_x) if self.kind == "bscan" else (self.n_y, self.n_z, self.n_x)

    @property
    def pitch_um(self) -> dict[str, float]:
        d = {"z": self.pitch_z_um, "x": self.pitch_x_um}
        if self.kind == "volume":
            d["y"] = self.pitch_y_um
        return d

    def coords_um(self, axis: str) -> np.ndarray:
        """Pixel-centre coordinates along ``axis`` ("x", "y" or "z"), float64."""
        n, p = {"x": (self.n_x, self.pitch_x_um), "y": (self.n_y, self.pitch_y_um), "z": (self.n_z, self.pitch_z_um)}[
            axis
        ]
        if axis == "y" and self.kind == "bscan":
            return np.array([self.y_um])
        return (np.arange(n) - (n - 1) / 2.0) * p

    def extent_um(self, axis: str) -> tuple[float, float]:
        c = self.coords_um(axis)
        return float(c[0]), float(c[-1])


@dataclass(frozen=True, kw_only=True)
class Region:
    """One labelled region of a phantom and the index of its population in ``phantom.scene``.

    Shapes: ``sphere`` (``center_um``, ``radius_um``, optional ``inner_radius_um`` for a shell),
    ``ellipsoid`` (``center_um``, ``radii_um``), ``slab`` (``z_min_um`` ≤ z ≤ ``z_max_um``, laterally
    unbounded), ``cylinder`` (infinite; axis through ``center_um`` along ``axis``, ``radius_um``),
    ``label-image`` (pixels of ``file`` equal to ``value``; a [Z, X] image extends along y, a
    [Y, Z, X] image is a volume; the image's pixels are the phantom grid's).

    ``flow_profile`` (cylinder only): ``uniform`` (default: every scatterer of the region moves with its
    flow's velocity) or ``poiseuille``, laminar flow in a circular tube: a scatterer at distance ``r`` from
    the axis moves with ``v_max·(1 − r²/R²)`` along the flow's direction, which must be the axis
    (``speed_um_per_s`` is the centre-line speed ``v_max``; the mean over the cross-section is ``v_max/2``).
    Diffusion or random-ballistic motion of the same region adds to it unchanged.
    """

    name: str
    shape: str
    population: int
    center_um: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius_um: float = 0.0
    inner_radius_um: float = 0.0
    radii_um: tuple[float, float, float] = (0.0, 0.0, 0.0)
    z_min_um: float = 0.0
    z_max_um: float = 0.0
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    flow_profile: str = "uniform"
    file: str = ""
    value: int = 0
    label_image: np.ndarray | None = field(default=None, repr=False, compare=False)

    def bounds_um(self) -> tuple[tuple[float, float], ...] | None:
        """Axis-aligned bounding box ((x0, x1), (y0, y1), (z0, z1)), ``None`` where unbounded."""
        inf = math.inf
        c = self.center_um
        if self.shape == "sphere":
            return tuple((c[a] - self.radius_um, c[a] + self.radius_um) for a in range(3))
        if self.shape == "ellipsoid":
            return tuple((c[a] - self.radii_um[a], c[a] + self.radii_um[a]) for a in range(3))
        if self.shape == "slab":
            return ((-inf, inf), (-inf, inf), (self.z_min_um, self.z_max_um))
        if self.shape == "cylinder":
            out = []
            for a in range(3):  # bounded along a coordinate axis only if the cylinder axis is ⟂ to it
                if abs(self.axis[a]) < 1e-12:
                    out.append((c[a] - self.radius_um, c[a] + self.radius_um))
                else:
                    out.append((-inf, inf))
            return tuple(out)
        return None  # label image: bounded by the grid, handled by the renderer

    def axis_distance_sq(self, pos: torch.Tensor) -> torch.Tensor:
        """Squared distance (µm²) of positions [..., 3] from a cylinder's axis."""
        c = torch.tensor(self.center_um, dtype=pos.dtype, device=pos.device)
        u = torch.tensor(self.axis, dtype=pos.dtype, device=pos.device)
        d = pos - c
        along = (d * u).sum(-1, keepdim=True)
        return ((d - along * u) ** 2).sum(-1)

    def flow_scale(self, pos: torch.Tensor) -> torch.Tensor | None:
        """Per-scatterer factor on the region's flow velocity at positions [N, 3]: ``1 − r²/R²`` (at least 0)
        for a Poiseuille cylinder, ``None`` (uniform flow) otherwise."""
        if self.flow_profile != "poiseuille":
            return None
        return (1.0 - self.axis_distance_sq(pos) / self.radius_um**2).clamp_(min=0.0)

    def contains(self, pos: torch.Tensor, grid: Grid) -> torch.Tensor:
        """Boolean mask [...] of positions [..., 3] (µm, float64) inside the region."""
        c = torch.tensor(self.center_um, dtype=pos.dtype, device=pos.device)
        if self.shape == "sphere":
            r2 = ((pos - c) ** 2).sum(-1)
            return (r2 <= self.radius_um**2) & (r2 >= self.inner_radius_um**2)
        if self.shape == "ellipsoid":
            r = torch.tensor(self.radii_um, dtype=pos.dtype, device=pos.device)
            return (((pos - c) / r) ** 2).sum(-1) <= 1.0
        if self.shape == "slab":
            return (pos[..., 2] >= self.z_min_um) & (pos[..., 2] <= self.z_max_um)
        if self.shape == "cylinder":
            return self.axis_distance_sq(pos) <= self.radius_um**2
        # label image: nearest pixel of the grid; outside the image is outside the region
        img = torch.as_tensor(self.label_image == self.value, device=pos.device)
        idx = []
        axes = ("z", "x") if img.ndim == 2 else ("y", "z", "x")
        inside = torch.ones(pos.shape[:-1], dtype=torch.bool, device=pos.device)
        for ax in axes:
            a = {"x": 0, "y": 1, "z": 2}[ax]
            n = {"x": grid.n_x, "y": grid.n_y, "z": grid.n_z}[ax]
            p = {"x": grid.pitch_x_um, "y": grid.pitch_y_um, "z": grid.pitch_z_um}[ax]
            i = torch.round(pos[..., a] / p + (n - 1) / 2.0)
            inside &= (i >= 0) & (i <= n - 1)
            idx.append(i.clamp(0, n - 1).long())
        return inside & img[tuple(idx)]


@dataclass(frozen=True)
class Phantom:
    """A scene (systems, protocol, populations, noise, analysis) plus its grid and regions.

    ``scene.populations`` holds the background populations first, then one per region;
    ``background`` holds the indices of the background populations (empty: nothing outside regions).
    """

    scene: Scene
    grid: Grid
    regions: tuple[Region, ...]
    background: tuple[int, ...] = ()

    @property
    def name(self) -> str:
        return self.scene.name

    def region_table(self) -> list[dict[str, Any]]:
        """JSON-able description of each labelled region (the background first, if any).

        ``diffusion_um2_per_s`` and ``speed_um_per_s`` are the largest among the region's populations;
        the speed is |v_flow| plus the ballistic speeds.
        """
        rows = []
        groups = ([("background", list(self.background))] if self.background else []) + [
            (r.name, [r.population]) for r in self.regions
        ]
        for name, idx in groups:
            pops = [self.scene.populations[i] for i in idx]
            speeds = [
                math.sqrt(sum(c * c for c in p.flow_velocity_um_per_s)) + sum(b.speed_um_per_s for b in p.ballistic)
                for p in pops
            ]
            rows.append(
                {
                    "name": name,
                    "motion_code": motion_code(pops),
                    "motion": sorted({type(m).__name__ for p in pops for m in p.active_motion}) or ["static"],
                    "diffusion_um2_per_s": max(p.diffusion_um2_per_s for p in pops),
                    "speed_um_per_s": max(speeds),
                    "density_per_um3": sum(p.density_per_um3 for p in pops),
                    "populations": len(pops),
                }
            )
        return rows

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the phantom-file schema (round-trips through :func:`phantom_from_dict`)."""
        sd = self.scene.to_dict()
        pops = sd.pop("population")
        out = dict(sd)
        g = self.grid
        grid = {"kind": g.kind, "n_x": g.n_x, "n_z": g.n_z, "pitch_x_um": g.pitch_x_um, "pitch_z_um": g.pitch_z_um}
        if g.kind == "volume":
            grid.update(n_y=g.n_y, pitch_y_um=g.pitch_y_um)
        else:
            grid["y_um"] = g.y_um
        out["grid"] = grid
        if self.background:
            out["background"] = [pops[i] for i in self.background]
        regions = []
        for r in self.regions:
            d: dict[str, Any] = {"name": r.name, "shape": r.shape}
            for key in _SHAPE_KEYS[r.shape]:
                val = getattr(r, key)
                d[key] = list(val) if isinstance(val, tuple) else val
            if r.flow_profile != "uniform":
                d["flow_profile"] = r.flow_profile
            p = dict(pops[r.population])
            p.pop("name", None)
            d.update(p)
            regions.append(d)
        out["region"] = regions
        return out


_SHAPE_KEYS = {
    "sphere": ("center_um", "radius_um", "inner_radius_um"),
    "ellipsoid": ("center_um", "radii_um"),
    "slab": ("z_min_um", "z_max_um"),
    "cylinder": ("center_um", "axis", "radius_um"),
    "label-image": ("file", "value"),
}
_SHAPE_REQUIRED = {
    "sphere": {"radius_um"},
    "ellipsoid": {"radii_um"},
    "slab": {"z_min_um", "z_max_um"},
    "cylinder": {"axis", "radius_um"},
    "label-image": {"file", "value"},
}
_POP_KEYS = {"density_per_um3", "reflectivity", "motion"}
#: Optional keys of a shape beyond :data:`_SHAPE_KEYS`.
_SHAPE_OPTIONAL = {"cylinder": ("flow_profile",)}
#: Flow profiles of a cylinder region (:class:`Region`).
FLOW_PROFILES = ("uniform", "poiseuille")
#: Largest angle (degrees) between a Poiseuille cylinder's flow and its axis.
PROFILE_AXIS_TOLERANCE_DEG = 0.5


def _vec3(path: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise TypeError(f"{path} must be a list of 3 numbers [x, y, z] in µm; got {value!r}")
    return tuple(_number(f"{path}[{i}]", v) for i, v in enumerate(value))  # type: ignore[return-value]


def _load_label_image(path: str, file: str, base_dir: Path | None, grid: Grid) -> np.ndarray:
    p = Path(file)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    from ..files import check_regular_file

    try:
        check_regular_file(p, f"{path}.file: label image")
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{path}.file: label image {str(file)!r} not found "
            f"(relative paths are taken from the phantom file's directory)"
        ) from None
    if p.suffix != ".npy":
        _fail(f"{path}.file", f"{file!r} is not a .npy file", "save the label image with numpy.save")
    from ..measured.guards import check_npy_size, npy_header

    try:  # the header's shape and dtype before a byte of data is read (a header may declare terabytes)
        shape, dtype = npy_header(p, f"{path}.file: label image {p.name}")
    except ValueError as err:
        _fail(f"{path}.file", str(err), "save the label image with numpy.save")
    if dtype.hasobject:
        _fail(
            f"{path}.file",
            f"{file!r} holds an object array, which would need unpickling; refused",
            "save a plain integer array with numpy.save",
        )
    if dtype.kind not in "iub":
        _fail(f"{path}.file", f"label image dtype {dtype} is not integer", "save integer labels")
    want = [grid.shape[-2:]] if grid.kind == "bscan" else [grid.shape[-2:], grid.shape]
    if tuple(shape) not in [tuple(w) for w in want]:
        _fail(
            f"{path}.file",
            f"label image shape {tuple(shape)} does not match the grid "
            f"({' or '.join(str(tuple(w)) for w in want)} as [Z, X] or [Y, Z, X])",
            "give one label per grid pixel",
        )
    try:
        check_npy_size(p, f"{path}.file: label image ")  # within the input limit, and not truncated
        img = np.load(p, allow_pickle=False)
    except ValueError as err:
        _fail(f"{path}.file", f"cannot read {file!r} ({err})", "save a plain integer array with numpy.save")
    return img


def phantom_from_dict(data: dict[str, Any], *, base_dir: Path | None = None) -> Phantom:
    """Build a validated :class:`Phantom` from the phantom-file schema (see the module docstring)."""
    if not isinstance(data, dict):
        raise TypeError(f"a phantom must be a table; got {type(data).__name__}")
    data = dict(data)
    if "population" in data:  # a plain scene: its populations are a uniform background
        if "region" in data or "background" in data:
            _fail(
                "population",
                "a phantom places its scatterers in [[region]] and [[background]] tables",
                "move each [[population]] into a [[region]] with a shape, or into [[background]]",
            )
        data["background"] = data.pop("population")
    allowed = {
        "name",
        "description",
        "system",
        "protocol",
        "noise",
        "analysis",
        "simulation",
        "grid",
        "region",
        "background",
    }
    _check_keys("phantom", data, allowed, {"system", "protocol"})
    if "grid" not in data:
        _fail(
            "grid",
            "missing the [grid] table (pixels and pitch)",
            "add [grid] with n_x, n_z, pitch_x_um, pitch_z_um (or pass --grid/--pitch-um to render)",
        )
    if "region" not in data and "background" not in data:
        _fail(
            "region",
            "a phantom needs at least one [[region]] or [[background]] population",
            "add a [[region]] table with a shape and a density",
        )
    g = _check_keys(
        "grid",
        data["grid"],
        {"kind", "n_x", "n_z", "n_y", "pitch_x_um", "pitch_z_um", "pitch_y_um", "y_um"},
        {"n_x", "n_z", "pitch_x_um", "pitch_z_um"},
    )
    if g.get("kind", "bscan") == "volume":
        for key in ("n_y", "pitch_y_um"):
            if key not in g:
                _fail("grid", f"a volume grid needs {key}", f"add {key}")
    grid = Grid(**g)

    pops: list[dict[str, Any]] = []
    where: list[str] = []
    bgs = data.get("background", [])
    if isinstance(bgs, dict):
        bgs = [bgs]
    if not isinstance(bgs, list):
        raise TypeError(f"background must be a table or an array of tables; got {bgs!r}")
    check_count("background", len(bgs))
    for i, bg in enumerate(bgs):
        _check_keys(f"background[{i}]", bg, _POP_KEYS | {"name"}, {"density_per_um3"})
        pops.append({**bg, "name": bg.get("name") or f"background{i}" if len(bgs) > 1 else "background"})
        where.append(f"background[{i}]")
    background = tuple(range(len(bgs)))
    regions_raw = data.get("region", [])
    if isinstance(regions_raw, dict):
        regions_raw = [regions_raw]
    if not isinstance(regions_raw, list):
        raise TypeError(f"region must be an array of tables ([[region]]); got {regions_raw!r}")
    check_count("region", len(regions_raw))
    if not regions_raw and not bgs:
        _fail(
            "region",
            "a phantom needs at least one [[region]] or [[background]] population",
            "add a [[region]] table with a shape and a density",
        )
    region_specs = []
    names = set()
    for i, r in enumerate(regions_raw):
        path = f"region[{i}]"
        if not isinstance(r, dict):
            raise TypeError(f"{path} must be a table; got {r!r}")
        if "shape" not in r:
            _fail(path, "missing key 'shape'", f"set shape = one of {', '.join(map(repr, SHAPES))}")
        shape = _string(f"{path}.shape", r["shape"], SHAPES)
        _check_keys(
            path,
            r,
            {"name", "shape", *_SHAPE_KEYS[shape], *_SHAPE_OPTIONAL.get(shape, ()), *_POP_KEYS},
            {"density_per_um3", *_SHAPE_REQUIRED[shape]},
        )
        name = _string(f"{path}.name", r.get("name", f"region{i}"))
        if name in names or name.startswith("background"):
            _fail(f"{path}.name", f"duplicate region name {name!r}", "give each region a unique name")
        names.add(name)
        pops.append({**{k: v for k, v in r.items() if k in _POP_KEYS}, "name": name})
        where.append(path)
        region_specs.append((path, name, shape, r))

    scene_data = {k: v for k, v in data.items() if k not in ("grid", "region", "background")}
    scene_data["population"] = pops
    try:
        scene = scene_from_dict(scene_data)
    except (SceneError, TypeError) as err:
        msg = str(err)
        for j, w in enumerate(where):  # population[j] -> the region's own key path
            msg = msg.replace(f"population[{j}]", w)
        raise type(err)(msg) from None

    regions: list[Region] = []
    for path, name, shape, r in region_specs:
        kw: dict[str, Any] = {"name": name, "shape": shape, "population": len(regions) + len(background)}
        if "center_um" in r:
            kw["center_um"] = _vec3(f"{path}.center_um", r["center_um"])
        if shape == "sphere":
            kw["radius_um"] = _number(f"{path}.radius_um", r["radius_um"], positive=True, hi=MAX_LENGTH_UM, unit="µm")
            kw["inner_radius_um"] = _number(
                f"{path}.inner_radius_um", r.get("inner_radius_um", 0.0), hi=MAX_LENGTH_UM, nonneg=True, unit="µm"
            )
            if kw["inner_radius_um"] >= kw["radius_um"]:
                _fail(
                    f"{path}.inner_radius_um",
                    f"{kw['inner_radius_um']} µm is not below radius_um {kw['radius_um']} µm",
                    "a shell needs inner_radius_um < radius_um",
                )
        elif shape == "ellipsoid":
            radii = _vec3(f"{path}.radii_um", r["radii_um"])
            for a, v in enumerate(radii):
                if v <= 0:
                    _fail(f"{path}.radii_um[{a}]", f"must be > 0 µm; got {v}")
            kw["radii_um"] = radii
        elif shape == "slab":
            z0 = _number(f"{path}.z_min_um", r["z_min_um"], unit="µm")
            z1 = _number(f"{path}.z_max_um", r["z_max_um"], unit="µm")
            if z1 <= z0:
                _fail(f"{path}.z_max_um", f"{z1} µm is not above z_min_um {z0} µm", "give z_min_um < z_max_um")
            kw.update(z_min_um=z0, z_max_um=z1)
        elif shape == "cylinder":
            ax = _vec3(f"{path}.axis", r["axis"])
            norm = math.sqrt(sum(a * a for a in ax))
            if norm == 0:
                _fail(f"{path}.axis", "must not be the zero vector", "give the direction of the cylinder axis")
            kw["axis"] = tuple(a / norm for a in ax)
            kw["radius_um"] = _number(f"{path}.radius_um", r["radius_um"], positive=True, hi=MAX_LENGTH_UM, unit="µm")
            kw["flow_profile"] = _string(f"{path}.flow_profile", r.get("flow_profile", "uniform"), FLOW_PROFILES)
            if kw["flow_profile"] == "poiseuille":
                _check_profile(path, kw["axis"], scene.populations[kw["population"]])
        else:
            kw["file"] = _string(f"{path}.file", r["file"])
            kw["value"] = _integer(f"{path}.value", r["value"])
            img = _load_label_image(path, kw["file"], base_dir, grid)
            if not (img == kw["value"]).any():
                _fail(
                    f"{path}.value",
                    f"label {kw['value']} does not occur in {kw['file']!r}",
                    "give a label value present in the image",
                )
            kw["label_image"] = img
        regions.append(Region(**kw))
    return Phantom(scene=scene, grid=grid, regions=tuple(regions), background=background)


def _check_profile(path: str, axis: tuple[float, float, float], pop: Population) -> None:
    """A Poiseuille cylinder's population has a flow, and every flow runs along the axis (either way)."""
    flows = [m for m in pop.active_motion if m.kind == "flow"]
    ux, uy, uz = axis
    polar = math.degrees(math.acos(max(-1.0, min(1.0, uz))))
    azimuth = math.degrees(math.atan2(uy, ux))
    along = f"polar_angle_deg = {polar:.6g}, azimuth_deg = {azimuth:.6g}"
    if not flows:
        _fail(
            f"{path}.flow_profile",
            "a Poiseuille profile shapes the region's flow, and the region has none",
            f"add a [[region.motion]] of kind 'flow' along the axis ({along}), or drop flow_profile",
        )
    for m in flows:
        v = m.velocity_um_per_s
        speed = math.sqrt(sum(c * c for c in v))
        cos = abs(sum(a * c for a, c in zip(axis, v))) / speed
        if cos < math.cos(math.radians(PROFILE_AXIS_TOLERANCE_DEG)):
            _fail(
                f"{path}.motion",
                f"the flow (polar {m.polar_angle_deg:g}°, azimuth {m.azimuth_deg:g}°) does not run along the "
                "cylinder's axis: a Poiseuille profile is laminar flow along the tube",
                f"set the flow's {along} (or the opposite direction), or drop flow_profile",
            )


def shipped_phantoms() -> dict[str, Path]:
    """Name -> path of every phantom shipped with torchdoct."""
    return shipped_files("torchdoct", "data/phantoms")


def load_phantom(path: str | Path, *, grid: dict[str, Any] | None = None) -> Phantom:
    """Read and validate a TOML phantom file, a shipped phantom, or a scene file (shipped or not).

    ``grid`` (the keys of ``[grid]``) replaces the file's grid, or supplies one to a scene file.
    """
    from ..sim.config import check_path_argument

    check_path_argument("td.load_phantom(path)", path, "phantom")
    shipped = shipped_phantoms()
    scenes = shipped_scenes()
    p = file_or_shipped(path, {**scenes, **shipped}, "phantom file")
    if p is None:
        raise FileNotFoundError(
            f"phantom file {str(path)!r} not found; give a path to a .toml phantom "
            f"or scene file, or the name of a shipped phantom "
            f"({', '.join(shipped)}) or scene ({', '.join(scenes)})"
        )
    data = read_toml(p)
    if grid is not None:
        data["grid"] = dict(grid)
    try:
        ph = phantom_from_dict(data, base_dir=p.parent)
    except (SceneError, TypeError) as err:
        raise type(err)(f"{p.name}: {err}") from None
    if not ph.scene.name:
        ph = Phantom(scene=ph.scene.replace(name=p.stem), grid=ph.grid, regions=ph.regions, background=ph.background)
    return ph

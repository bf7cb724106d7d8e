"""The phantom grid: the benchmark every model change is measured on (``python -m classifier.bench.grid``).

Every cell is a phantom built here from numbers derived from the model's system (none typed in), rendered
by :func:`torchdoct.image.render.render`, turned into maps by the code of ``torchdoct maps --signature``
(:func:`torchdoct.measured.maps.compute_maps` at the model's configurations) and classified by
:func:`classifier.infer.classify_maps` (the decision rule ``doct-classify`` applies, or ``decision``).

**Phantom of a cell.** Three bands side by side along x, one per motion type (diffusion, random-ballistic
motion, flow): cylinders whose axis is the depth axis z, radius :data:`BAND_RADIUS_PX` pixels, spaced by
:data:`BAND_GAP_PX` empty pixels; in a B-scan they are vertical bands, in a volume vertical rods. The
moving density is the prior's lowest (:class:`classifier.prior.Prior`), the protocol and optics the
spec's first configuration (the system the model was trained for), pixels of a third of the finest
lateral resolution (rounded to 0.5 µm).

* **speed** (3 levels per motion): the magnitudes identifiable (:func:`classifier.truth.identifiability`,
  physics.md §5.3-5.4) at every polar and azimuth angle of the grid, on the log grid of
  :func:`classifier.own_system.identifiable_range`; the levels lie at :data:`LEVEL_FRACTIONS` of that
  range in log10 (slow, mid, fast);
* **flow direction**: polar angle from the depth axis :data:`POLAR_DEG`, azimuth from +x :data:`AZIMUTH_DEG`
  (azimuth 90°: across the B-scan plane);
* **static context**: ``none`` (the bands in an empty medium), ``background`` (static tissue of the
  moving density under every pixel: the field of a second, static phantom on the same grid is added, so
  half the mean intensity of a moving pixel is static), ``edge`` (a static slab over the deepest quarter of
  the image paints over the bands: the pixels next to it share their PSF with static tissue);
* **noise**: none, or complex Gaussian noise :data:`SNR_DB` below the mean intensity (physics.md §8);
* **geometry**: B-scan or volume (at least :data:`VOLUME_NY` planes along y, and enough that the y field of
  view holds the model's coarsest lateral resolution: maps refuse a reduction wider than the field of view);
* **window**: the ``--pool`` of ``doct-classify`` (:data:`POOLS`).

**Scores of a cell** (the pixels of each band whose box of half-width ``edge`` pixels holds no pixel of
another band or of the empty medium; static neighbours are kept: they are the context; ``edge`` = half
the coarsest configuration's resolution plus half the window; masked pixels are not scored):

* ``coverage``: decided share (a single class, not ``indeterminate`` or a set of classes);
* ``balanced_accuracy``: mean over the three motions of the right share of their decided pixels
  (``None`` when a motion has no decided pixel);
* ``wrong_share`` per motion: share of its scored pixels decided as another single class, and
  ``wrong_share_max``, the worst of the three ("confidently wrong");
* ``set_miss_share`` per motion: share given a set of classes that leaves the true one out;
* ``identifiable`` per motion: the ground truth of the training (a motion outside it should be abstained on);
* ``seconds``: render, maps and classification of the cell;
* ``classified`` and ``rules_changed``: the pixels the model classified and, per rule of
  :mod:`classifier.ambiguity`, how many of them the rule changed (``info.ambiguity.changed_pixels``;
  ``None`` with ``--decide-ballistic``); ``summary_by_context`` pools them as ``rules_changed_share``;
* ``all_pixels``: the same scores over every pixel of each band, its borders included (``edge`` = 0):
  where a band meets the empty medium or another band the PSF and the pooling window straddle the border
  (``summary_by_context_all_pixels`` pools them like ``summary_by_context``).

**Probes** (:data:`PROBES`, :func:`probe_dict`): phantoms unlike the bands, scored the same way, every
motion at its ``mid`` level unless the name says ``-slow``. Unlike the bands, which empty medium separates, their regions touch, so the
coarse configurations' footprints straddle two motions:

* ``*-layers``: three layers stacked in depth (diffusion, random-ballistic motion, flow at
  :data:`PROBE_LAYER_FLOW_DEG`), the static-free layers of :mod:`classifier.bench.cases`; ``-static``: inside static
  tissue (a static population under every pixel, in the same phantom);
* ``*-vessel``: a flow vessel of radius :data:`PROBE_VESSEL_RADIUS_PX` through random-ballistic tissue
  without static scatterers, in the B-scan plane at 45° to the beam (B-scan) or along x (volume), the
  flow along its axis;
* ``bscan-crossing``: a flow vessel of the same radius across the B-scan plane (its axis and its flow along
  y) through diffusing tissue without static scatterers: the flow the B-scan cannot tell from
  random-ballistic motion (docs/abstention.md, rule 1), beside a motion it can decide;
* ``-slow``: every motion at its ``slow`` level: a random motion that decays by a few percent beside a flow
  that decorrelates over the acquisition, so that even the far tail of the coarse PSF mixes a flow's
  signature into it.

Outputs (``write_grid``): ``grid.json`` (:data:`SCHEMA_VERSION`, the definitions above, the cells),
``grid.csv``, ``grid.md`` and ``grid.png`` (worst wrong share and coverage per cell, cividis).

Kept whole (over 800 lines): the cells, the phantom, the scoring, the summaries, the table, the figure and
the command line share the results schema they write; one file is one benchmark, as in
:mod:`classifier.bench.protocol`.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import tempfile
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "SCHEMA_VERSION",
    "GridCell",
    "full_cells",
    "quick_cells",
    "speed_levels",
    "phantom_dict",
    "cell_phantoms",
    "run_cell",
    "run_grid",
    "score_labels",
    "write_grid",
    "format_table",
    "main",
]

SCHEMA_VERSION = 1
MOTIONS = ("diffusion", "ballistic", "flow")
#: Rendered motion codes (torchdoct.image.phantom.MOTION_CODES) of the three bands.
CODES = {"diffusion": 2, "ballistic": 3, "flow": 4}
#: Rendered code of a region whose scatterers combine motions (torchdoct.image.phantom.MOTION_CODES["mixed"]).
MIXED_CODE = 5
LEVELS = ("slow", "mid", "fast")
#: Where the three speed levels lie in the identifiable range (fractions of its log10 span).
LEVEL_FRACTIONS = (0.2, 0.5, 0.8)
POLAR_DEG = (10.0, 45.0, 80.0)
AZIMUTH_DEG = (0.0, 45.0, 90.0)
CONTEXTS = ("none", "background", "edge")
SNR_DB = 20.0
NOISES: tuple[float | None, ...] = (None, SNR_DB)
GEOMETRIES = ("bscan", "volume")
POOLS = (1, 5)
BAND_RADIUS_PX = 12
BAND_GAP_PX = 8
IMAGE_NZ = 64
VOLUME_NY = 8
#: Phantoms unlike the bands (:func:`probe_dict`): layers in depth, a vessel and a vessel across the B-scan plane,
#: without and with static tissue, with every motion at its mid level or (``-slow``) at its slow level.
PROBES = (
    "bscan-layers",
    "bscan-layers-static",
    "bscan-layers-slow",
    "bscan-vessel",
    "bscan-vessel-static",
    "bscan-vessel-slow",
    "bscan-crossing",
    "volume-layers",
    "volume-layers-static",
    "volume-layers-static-slow",
    "volume-vessel",
)
#: Flow direction of the layer probes (polar, azimuth; degrees): oblique, out of the B-scan plane by 60°.
PROBE_LAYER_FLOW_DEG = (45.0, 60.0)
#: Vessel radius of the vessel probes (pixels).
PROBE_VESSEL_RADIUS_PX = 12


def volume_ny(spec, pitch_um: float) -> int:
    """Planes along y of a volume cell: :data:`VOLUME_NY`, or more where the model's coarsest lateral
    resolution (µm) is wider than that many planes of ``pitch_um``."""
    coarsest = max(c.lateral_resolution_um for c in spec.configurations)
    return max(VOLUME_NY, math.ceil(coarsest / pitch_um - 1e-9))


@dataclass(frozen=True)
class GridCell:
    """One phantom of the grid (all its windows are scored from one rendering)."""

    geometry: str
    context: str
    snr_db: float | None
    level: str
    polar_deg: float
    azimuth_deg: float
    seed: int = 0

    @property
    def key(self) -> str:
        noise = "clean" if self.snr_db is None else f"{self.snr_db:g}dB"
        return f"{self.geometry}-{self.context}-{noise}-{self.level}-p{self.polar_deg:g}-a{self.azimuth_deg:g}"


def full_cells(seed: int = 0) -> list[GridCell]:
    """Every cell: geometry × context × noise × speed level × polar × azimuth (the windows are per cell)."""
    return [
        GridCell(g, c, n, lv, p, a, seed)
        for g, c, n, lv, p, a in itertools.product(GEOMETRIES, CONTEXTS, NOISES, LEVELS, POLAR_DEG, AZIMUTH_DEG)
    ]


def quick_cells(seed: int = 0) -> list[GridCell]:
    """``--quick``: B-scans at the mid speed and 20 dB, every polar angle at azimuth 0° and 90°, without
    static tissue and with a static background, plus one static-edge B-scan and one volume of flow across
    the plane without static tissue (14 phantoms)."""
    cells = [
        GridCell("bscan", c, SNR_DB, "mid", p, a, seed)
        for c in ("none", "background")
        for p in POLAR_DEG
        for a in (AZIMUTH_DEG[0], AZIMUTH_DEG[-1])
    ]
    cells.append(GridCell("bscan", "edge", SNR_DB, "mid", POLAR_DEG[1], AZIMUTH_DEG[0], seed))
    cells.append(GridCell("volume", "none", SNR_DB, "mid", POLAR_DEG[-1], AZIMUTH_DEG[-1], seed))
    return cells


def _draw(label: int, magnitude: float, polar: float, azimuth: float, density: float, law: str | None = None):
    from ..prior import Draw

    d = Draw(
        label=label,
        magnitude=float(magnitude),
        polar_angle_deg=float(polar),
        azimuth_deg=float(azimuth),
        density_per_um3=float(density),
        sim_seed=0,
    )
    if law is not None:
        import dataclasses

        d = dataclasses.replace(d, ballistic_directions=law)
    return d


def _check_law(law: str | None) -> str | None:
    from ..prior import BALLISTIC_LAWS

    if law is not None and law not in BALLISTIC_LAWS:
        raise ValueError(f"--ballistic-directions {law!r}: give one of {', '.join(BALLISTIC_LAWS)}")
    return law


def speed_levels(spec, prior=None) -> dict[str, dict[str, float]]:
    """``{motion: {level: magnitude}}``: :data:`LEVEL_FRACTIONS` of the log range identifiable at every
    grid direction (flow) and either direction law (random-ballistic motion) at the prior's lowest density."""
    from ..own_system import _RANGE_GRID
    from ..prior import BALLISTIC_LAWS, Prior
    from ..truth import identifiability

    prior = prior or Prior()
    density = float(min(prior.density_per_um3))
    out: dict[str, dict[str, float]] = {}
    for label, name in enumerate(MOTIONS):
        ok = np.ones(_RANGE_GRID.size, bool)
        if name == "flow":
            variants = [dict(polar=p, azimuth=a) for p in POLAR_DEG for a in AZIMUTH_DEG]
        else:
            variants = [dict(law=law) for law in BALLISTIC_LAWS] if name == "ballistic" else [{}]
        for v in variants:
            for i, mag in enumerate(_RANGE_GRID):
                if not ok[i]:
                    continue
                d = _draw(label, mag, v.get("polar", 0.0), v.get("azimuth", 0.0), density, v.get("law"))
                ok[i] = identifiability(spec, d, prior)[0] == "identifiable"
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            raise ValueError(f"spec {spec.name!r}: {name} is identifiable at no magnitude at every grid direction")
        lo, hi = math.log10(_RANGE_GRID[idx[0]]), math.log10(_RANGE_GRID[idx[-1]])
        out[name] = {lv: float(f"{10 ** (lo + f * (hi - lo)):.3g}") for lv, f in zip(LEVELS, LEVEL_FRACTIONS)}
    return out


def _ballistic(speed: float, law: str | None) -> dict[str, Any]:
    """A random-ballistic motion of the phantom schema at ``speed`` (µm/s), with direction law ``law`` if given."""
    m: dict[str, Any] = {"kind": "ballistic", "speed_um_per_s": speed}
    if _check_law(law) is not None:
        m["directions"] = law
    return m


def _pitch_um(spec) -> float:
    finest = min(c.lateral_resolution_um for c in spec.configurations)
    return max(0.5, round(finest / 3.0 * 2.0) / 2.0)


def phantom_dict(
    cell: GridCell, spec, levels: dict[str, dict[str, float]], density: float, ballistic_directions: str | None = None
) -> dict[str, Any]:
    """The phantom of ``cell`` in the phantom-file schema (module docstring); a static background is a
    second phantom (:func:`_static_dict`). ``ballistic_directions``: the random-ballistic direction law
    (:data:`classifier.prior.BALLISTIC_LAWS`; ``None``: the phantom schema's default, isotropic)."""
    pitch = _pitch_um(spec)
    r_um, gap_um = BAND_RADIUS_PX * pitch, BAND_GAP_PX * pitch
    n_x = 3 * 2 * BAND_RADIUS_PX + 4 * BAND_GAP_PX
    grid: dict[str, Any] = {
        "kind": cell.geometry,
        "n_x": n_x,
        "n_z": IMAGE_NZ,
        "pitch_x_um": pitch,
        "pitch_z_um": pitch,
    }
    if cell.geometry == "volume":
        grid.update(n_y=volume_ny(spec, pitch), pitch_y_um=pitch)
    else:
        grid["y_um"] = 0.0
    motions = {
        "diffusion": {"kind": "diffusion", "diffusion_um2_per_s": levels["diffusion"][cell.level]},
        "ballistic": _ballistic(levels["ballistic"][cell.level], ballistic_directions),
        "flow": {
            "kind": "flow",
            "speed_um_per_s": levels["flow"][cell.level],
            "polar_angle_deg": cell.polar_deg,
            "azimuth_deg": cell.azimuth_deg,
        },
    }
    regions = []
    for k, name in enumerate(MOTIONS):
        xc = (k - 1) * (2 * r_um + gap_um)
        regions.append(
            {
                "name": name,
                "shape": "cylinder",
                "center_um": [xc, 0.0, 0.0],
                "axis": [0.0, 0.0, 1.0],
                "radius_um": r_um,
                "density_per_um3": density,
                "motion": [motions[name]],
            }
        )
    if cell.context == "edge":
        z_top = (IMAGE_NZ / 4.0) * pitch  # the deepest quarter (z increases into the sample)
        regions.append(
            {
                "name": "static-edge",
                "shape": "slab",
                "z_min_um": z_top,
                "z_max_um": IMAGE_NZ * pitch,
                "density_per_um3": density,
            }
        )
    d: dict[str, Any] = {
        "name": cell.key,
        "system": [system_dict(spec)],
        "protocol": {"n_frames": spec.n_frames, "frame_interval_s": spec.frame_interval_s},
        "analysis": {"ocds_delay_range_s": list(spec.ocds_delay_range_s)},
        "grid": grid,
        "region": regions,
        "simulation": {"seed": int(cell.seed)},
    }
    if cell.snr_db is not None:
        d["noise"] = {"snr_db": float(cell.snr_db)}
    return d


def cell_phantoms(
    cell: GridCell, spec, levels: dict[str, dict[str, float]], density: float, ballistic_directions: str | None = None
) -> list[dict[str, Any]]:
    """The phantoms whose fields add to ``cell``'s (:func:`render_sequence`): :func:`phantom_dict`, and a static
    background after it in the ``background`` context."""
    d = phantom_dict(cell, spec, levels, density, ballistic_directions)
    return [d, _static_dict(d, density)] if cell.context == "background" else [d]


def system_dict(spec, name: str = "grid-system") -> dict[str, Any]:
    """The ``[[system]]`` of a benchmark phantom: the optics of the model's first configuration."""
    c0 = spec.configurations[0]
    system = {
        "name": name,
        "wavelength_um": c0.wavelength_um,
        "lateral_resolution_um": c0.lateral_resolution_um,
        "axial_resolution_um": c0.axial_resolution_um,
    }
    if spec.refractive_index != 1.0:
        system["refractive_index"] = spec.refractive_index
    return system


def _static_dict(moving: dict[str, Any], density: float) -> dict[str, Any]:
    d = {k: v for k, v in moving.items() if k not in ("region", "noise")}
    d["background"] = [{"name": "static-tissue", "density_per_um3": density}]
    d["simulation"] = {"seed": int(moving["simulation"]["seed"]) + 1_000_003}
    return d


def interior_pixels(truth_codes: np.ndarray, name: str, edge_px: int) -> np.ndarray:
    """The pixels of motion ``name`` farther than ``edge_px`` from every other region (static tissue included)."""
    from scipy.ndimage import maximum_filter

    code = CODES[name]
    other = np.isin(truth_codes, [c for c in (0, *CODES.values()) if c != code])
    size = 2 * int(edge_px) + 1
    near = maximum_filter(other.astype(np.uint8), size=size, mode="constant") > 0 if edge_px > 0 else other
    return (truth_codes == code) & ~near


def score_labels(
    truth_codes: np.ndarray, classes: np.ndarray, class_names: Sequence[str], edge_px: int, masked: int = 255
) -> dict[str, Any]:
    """Scores of one classification against rendered motion codes (module docstring).

    ``classes``: ``classes.tif`` values; ``class_names``: the legend's names in value order (a name
    ``a-or-b`` is a set of classes, ``indeterminate`` the full set)."""
    out: dict[str, Any] = {"per_class": {}}
    names = list(class_names)
    single = {n: i for i, n in enumerate(names) if n in MOTIONS}
    recalls, scored, decided = [], 0, 0
    for name in MOTIONS:
        sel = interior_pixels(truth_codes, name, edge_px) & (classes != masked)
        n = int(sel.sum())
        got = classes[sel]
        dec = np.isin(got, list(single.values()))
        right = int((got == single[name]).sum())
        wrong = int(dec.sum()) - right
        miss = 0
        for i, nm in enumerate(names):
            if nm not in MOTIONS and nm != "indeterminate" and name not in nm.split("-or-"):
                miss += int((got == i).sum())
        per = {
            "pixels": n,
            "decided": int(dec.sum()),
            "coverage": (float(dec.mean()) if n else None),
            "recall": (right / int(dec.sum()) if dec.any() else None),
            "wrong_share": (wrong / n if n else None),
            "set_miss_share": (miss / n if n else None),
        }
        out["per_class"][name] = per
        scored += n
        decided += int(dec.sum())
        if per["recall"] is not None:
            recalls.append(per["recall"])
    out["pixels"] = scored
    out["coverage"] = decided / scored if scored else None
    out["balanced_accuracy"] = float(np.mean(recalls)) if len(recalls) == len(MOTIONS) else None
    ws = [p["wrong_share"] for p in out["per_class"].values() if p["wrong_share"] is not None]
    out["wrong_share_max"] = max(ws) if ws else None
    return out


def score_mixed(
    truth_codes: np.ndarray, classes: np.ndarray, class_names: Sequence[str], holds: Sequence[str], masked: int = 255
) -> dict[str, Any]:
    """Scores of the pixels of a region whose scatterers combine the motions ``holds`` (rendered as ``mixed``):
    no single motion is its truth, so a single-class decision naming a motion it holds is right and one naming
    a motion it does not hold is wrong. Over every such pixel: ``coverage`` (decided as a single class), the
    share ``decided_as`` each motion, and ``wrong_share`` (decided as a motion it does not hold)."""
    names = list(class_names)
    sel = (np.asarray(truth_codes) == MIXED_CODE) & (classes != masked)
    n = int(sel.sum())
    got = classes[sel]
    shares = {m: (float((got == names.index(m)).mean()) if n else None) for m in MOTIONS if m in names}
    known = [v for v in shares.values() if v is not None]
    return {
        "holds": list(holds),
        "pixels": n,
        "coverage": float(sum(known)) if n else None,
        "decided_as": shares,
        "wrong_share": float(sum(v for m, v in shares.items() if m not in holds and v is not None)) if n else None,
    }


def score_region(
    truth_codes: np.ndarray, classes: np.ndarray, class_names: Sequence[str], name: str, motion: str, mask: np.ndarray
) -> dict[str, Any]:
    """The scores of :func:`score_labels` (every pixel, edge 0) of one region: its pixels ``mask`` (the
    renderer's ``regions == index``: a region painted over by a later one keeps only what it still holds)
    whose rendered motion is ``motion``."""
    own = np.where(np.asarray(mask, bool) & (truth_codes == CODES[motion]), truth_codes, 0)
    return {"region": name, "motion": motion, **score_labels(own, classes, class_names, 0)["per_class"][motion]}


def doppler_null(truth_codes: np.ndarray, imaginary: np.ndarray, edge_px: int) -> dict[str, Any]:
    """Rule 10's statistic (:func:`classifier.ambiguity.doppler_imaginary`, the imaginary part of the box's mean
    Doppler phasor) per motion over the pixels :func:`score_labels` scores (farther than ``edge_px`` from other
    regions): its largest and median magnitude. For diffusion and random-ballistic motion it is the rule's
    null (zero in expectation), for flow its power."""
    out: dict[str, Any] = {}
    mag = np.abs(np.asarray(imaginary, np.float64)).reshape(np.shape(truth_codes))
    for name in MOTIONS:
        v = mag[interior_pixels(truth_codes, name, edge_px)]
        out[name] = {"max": float(v.max()), "median": float(np.median(v))} if v.size else None
    return out


def scoring_edge_px(spec, pitch: float, pool: int) -> int:
    """How far (pixels of ``pitch`` µm) from another region a motion's pixel must lie to be scored away from
    it: half the coarsest resolution of the configurations of ``spec`` plus half the pooling window."""
    coarsest = max(max(c.lateral_resolution_um, c.axial_resolution_um) for c in spec.configurations)
    return int(math.ceil(coarsest / 2.0 / pitch)) + pool // 2


def signature_maps(seq, spec, *, dynamic: bool = False):
    """The maps of ``seq`` as `torchdoct maps --signature` writes them for the model spec ``spec``: its
    configurations, the signature it reads, the speckle channels and the Doppler channel (where a static
    reference exists), with the spec's OCDS analysis; ``dynamic``: with the channels ``--speckle-dynamic`` adds too."""
    from torchdoct.measured.maps import compute_maps
    from torchdoct.sim.speckle import map_speckle_features

    return compute_maps(
        seq,
        [c.name for c in spec.configurations],
        metrics=("mean_db",),
        signature=list(spec.metrics),
        speckle=map_speckle_features(len(seq.axes) - 1, n_frames=seq.data.shape[0], dynamic=True) if dynamic else True,
        doppler=True,
        ocds_delay_range_s=tuple(spec.ocds_delay_range_s),
        ocds_scale=spec.ocds_scale,
        ocds_estimator=spec.ocds_estimator,
    )


def render_sequence(phantoms: Sequence[dict[str, Any]], source: str, seed: int, *, threads: int | None = None):
    """Render ``phantoms`` (phantom-file dicts; their fields add, the first rendered at ``seed``, a static
    background after it at its own) as the sequence ``torchdoct maps`` reads: ``(render result of the first,
    SequenceData named source)``; the result's ``labels`` are the ground truth."""
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render
    from torchdoct.measured.sequence import SequenceData, validate_meta

    res = render(phantom_from_dict(phantoms[0]), seed=seed, threads=threads)
    data = res.data[0].numpy()
    for extra in phantoms[1:]:
        data = data + render(phantom_from_dict(extra), threads=threads).data[0].numpy()
    meta = res.metadata(0)
    meta.pop("phantom", None)
    return res, SequenceData(data=data, meta=validate_meta(meta, data.shape), source=source)


def _classify_rendered(
    phantoms: Sequence[dict[str, Any]],
    model,
    source: str,
    seed: int,
    *,
    pools: Sequence[int],
    decision: str | None,
    threads: int | None,
    abstain_ambiguous: bool | Sequence[bool],
    mixed_holds: Sequence[str] | None = None,
    per_region: bool = False,
    settings: Sequence[tuple[str | None, bool]] | None = None,
) -> list[dict[str, Any]]:
    """Render ``phantoms`` (phantom-file dicts; their fields add, the first rendered at ``seed``, a static
    background after it at its own), map them as ``maps --signature`` does, classify at every window of
    ``pools`` (with the rules of :mod:`classifier.ambiguity` or without, or both when ``abstain_ambiguous`` is a
    sequence: the rendering and the maps are made once) and score against the first phantom's labels: one row
    per window and setting with the scores of the pixels away from other regions, ``all_pixels`` (edge 0), the
    setting, the decision and the seconds taken; with ``mixed_holds`` (the motions a ``mixed`` region
    combines) also ``mixed`` (:func:`score_mixed`); with ``per_region`` also ``per_region``: each region of one
    motion scored over the pixels the renderer assigns it (:func:`score_region`). ``settings``: pairs
    ``(decision, abstain_ambiguous)`` classified in turn from the same maps (they replace ``decision`` and
    ``abstain_ambiguous``); each row then carries its pair's index as ``setting``."""
    from torchdoct.measured.mapsfile import write_maps

    from ..infer import classify_maps

    spec = model.spec
    t0 = time.perf_counter()
    res, seq = render_sequence(phantoms, source, seed, threads=threads)
    by_code = {code: name for name, code in CODES.items()}
    regions = [
        (row["name"], by_code[row["motion_code"]], res.regions == i)
        for i, row in enumerate(res.phantom.region_table())
        if per_region and row["motion_code"] in by_code
    ]
    t_render = time.perf_counter()
    maps = signature_maps(seq, spec)
    t_maps = time.perf_counter()
    pitch = _pitch_um(spec)
    from ..ambiguity import DOPPLER_WINDOW_MIN, doppler_imaginary

    dop_channels = {c: maps.maps[i] for i, c in enumerate(maps.channels) if c.startswith("doppler_phase_")}
    tagged = settings is not None
    if settings is None:
        abstains = (abstain_ambiguous,) if isinstance(abstain_ambiguous, bool) else tuple(abstain_ambiguous)
        settings = [(decision, ab) for ab in abstains]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = write_maps(Path(tmp) / "maps.npz", maps)
        for k, (dec, ab), pool in ((k, st, pool) for k, st in enumerate(settings) for pool in pools):
            kw = {} if dec is None else {"decision": dec}
            t1 = time.perf_counter()
            c = classify_maps(path, model, pool=int(pool), threads=threads, abstain_ambiguous=ab, **kw)
            t2 = time.perf_counter()
            im, dop_name = doppler_imaginary(dop_channels, max(int(pool), DOPPLER_WINDOW_MIN))
            rows.append(
                {
                    **({"setting": k} if tagged else {}),
                    "pool": int(pool),
                    "abstain_ambiguous": bool(ab),
                    "decision": c.info.get("decision", "rule"),
                    "doppler": None
                    if im is None
                    else {
                        "channel": dop_name,
                        "window_px": max(int(pool), DOPPLER_WINDOW_MIN),
                        "abs_imaginary": doppler_null(res.labels, im, scoring_edge_px(spec, pitch, int(pool))),
                    },
                    **score_labels(res.labels, c.labels, c.classes, scoring_edge_px(spec, pitch, int(pool))),
                    "all_pixels": score_labels(res.labels, c.labels, c.classes, 0),
                    **({"mixed": score_mixed(res.labels, c.labels, c.classes, mixed_holds)} if mixed_holds else {}),
                    **(
                        {"per_region": [score_region(res.labels, c.labels, c.classes, *r) for r in regions]}
                        if regions
                        else {}
                    ),
                    "classified": int(c.info["classified"]),
                    "rules_changed": dict(c.info["ambiguity"]["changed_pixels"]) if c.info.get("ambiguity") else None,
                    "seconds": {
                        "render": t_render - t0,
                        "maps": t_maps - t_render,
                        "classify": t2 - t1,
                        "total": (t_maps - t0) + (t2 - t1),
                    },
                }
            )
    return rows


def layer_regions(depth_um: float, density: float, motions: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Slabs of equal thickness stacked in depth over a grid of ``depth_um`` centred on the origin, one per
    motion of ``motions`` (phantom-schema motions, shallowest first), each at ``density`` µm⁻³ and named by its
    motion's kind."""
    n = len(motions)
    return [
        {
            "name": str(m["kind"]),
            "shape": "slab",
            "z_min_um": -depth_um / 2 + k * depth_um / n,
            "z_max_um": -depth_um / 2 + (k + 1) * depth_um / n,
            "density_per_um3": density,
            "motion": [m],
        }
        for k, m in enumerate(motions)
    ]


def run_cell(
    cell: GridCell,
    model,
    levels: dict[str, dict[str, float]],
    *,
    pools: Sequence[int] = POOLS,
    decision: str | None = None,
    threads: int | None = None,
    prior=None,
    abstain_ambiguous: bool | Sequence[bool] = True,
    ballistic_directions: str | None = None,
    settings: Sequence[tuple[str | None, bool]] | None = None,
) -> list[dict[str, Any]]:
    """Render, map, classify and score one cell at every window of ``pools``: one row per window (and per
    pair of ``settings``, :func:`_classify_rendered`).
    ``abstain_ambiguous``: doct-classify's default (:mod:`classifier.ambiguity`); False: ``--decide-ballistic``;
    a sequence of both: one row per setting and window, from one rendering and one set of maps.
    ``ballistic_directions``: as in :func:`phantom_dict`."""
    from ..prior import Prior
    from ..truth import identifiability

    prior = prior or Prior()
    spec = model.spec
    density = float(min(prior.density_per_um3))
    phantoms = cell_phantoms(cell, spec, levels, density, ballistic_directions)
    scored = _classify_rendered(
        phantoms,
        model,
        cell.key,
        cell.seed,
        pools=pools,
        decision=decision,
        threads=threads,
        abstain_ambiguous=abstain_ambiguous,
        settings=settings,
    )
    ident = {}
    for label, name in enumerate(MOTIONS):
        mag = levels[name][cell.level]
        draw = _draw(label, mag, cell.polar_deg, cell.azimuth_deg, density, ballistic_directions)
        ident[name] = identifiability(spec, draw, prior)[0]
    rows = []
    for r in scored:
        head = {
            **({"setting": r.pop("setting")} if "setting" in r else {}),
            **asdict(cell),
            "key": cell.key,
            "pool": r.pop("pool"),
            "model": spec.name,
            "decision": r.pop("decision"),
            "abstain_ambiguous": r.pop("abstain_ambiguous"),
            "magnitudes": {m: levels[m][cell.level] for m in MOTIONS},
            "identifiable": ident,
        }
        rows.append({**head, **r})
    return rows


def probe_dict(
    name: str,
    spec,
    levels: dict[str, dict[str, float]],
    density: float,
    seed: int = 0,
    ballistic_directions: str | None = None,
) -> dict[str, Any]:
    """The phantom of probe ``name`` (:data:`PROBES`, module docstring) in the phantom-file schema, built from
    the system of ``spec`` and the speed ``levels`` of its geometry (``-slow``: every motion at ``slow``);
    ``ballistic_directions`` as in :func:`phantom_dict`."""
    if name not in PROBES:
        raise ValueError(f"unknown probe {name!r}; give one of {', '.join(PROBES)}")
    geometry, kind, *variant = name.split("-")
    static, level = "static" in variant, ("slow" if "slow" in variant else "mid")
    pitch = _pitch_um(spec)
    n_x, n_z = 96, IMAGE_NZ
    grid: dict[str, Any] = {"kind": geometry, "n_x": n_x, "n_z": n_z, "pitch_x_um": pitch, "pitch_z_um": pitch}
    if geometry == "volume":
        grid.update(n_y=volume_ny(spec, pitch), pitch_y_um=pitch)
    else:
        grid["y_um"] = 0.0
    depth = n_z * pitch  # the grid is centred on the origin: z runs over [-depth/2, depth/2]
    diffusion = {"kind": "diffusion", "diffusion_um2_per_s": levels["diffusion"][level]}
    ballistic = _ballistic(levels["ballistic"][level], ballistic_directions)
    flow_speed = levels["flow"][level]
    if kind == "layers":
        polar, azimuth = PROBE_LAYER_FLOW_DEG
        flow = {"kind": "flow", "speed_um_per_s": flow_speed, "polar_angle_deg": polar, "azimuth_deg": azimuth}
        regions = layer_regions(depth, density, (diffusion, ballistic, flow))
    else:
        if kind == "crossing":  # across the B-scan plane, through diffusing tissue: axis and flow along y
            tissue, axis, polar, azimuth = diffusion, [0.0, 1.0, 0.0], 90.0, 90.0
        elif geometry == "bscan":  # at 45° in the x-z plane
            tissue, axis, polar, azimuth = ballistic, [math.sqrt(0.5), 0.0, math.sqrt(0.5)], 45.0, 0.0
        else:  # a volume's vessel runs along x
            tissue, axis, polar, azimuth = ballistic, [1.0, 0.0, 0.0], 90.0, 0.0
        flow = {"kind": "flow", "speed_um_per_s": flow_speed, "polar_angle_deg": polar, "azimuth_deg": azimuth}
        regions = [
            {
                "name": tissue["kind"],
                "shape": "slab",
                "z_min_um": -depth / 2,
                "z_max_um": depth / 2,
                "density_per_um3": density,
                "motion": [tissue],
            },
            {
                "name": "flow",
                "shape": "cylinder",
                "center_um": [0.0, 0.0, 0.0],
                "axis": axis,
                "radius_um": PROBE_VESSEL_RADIUS_PX * pitch,
                "density_per_um3": density,
                "motion": [flow],
            },
        ]
    d: dict[str, Any] = {
        "name": f"probe-{name}",
        "system": [system_dict(spec)],
        "protocol": {"n_frames": int(spec.n_frames), "frame_interval_s": float(spec.frame_interval_s)},
        "analysis": {"ocds_delay_range_s": [float(v) for v in spec.ocds_delay_range_s]},
        "grid": grid,
        "region": regions,
        "simulation": {"seed": int(seed)},
    }
    if static:
        d["background"] = [{"name": "static-tissue", "density_per_um3": density}]
    return d


def run_probe(
    name: str,
    model,
    levels: dict[str, dict[str, float]],
    *,
    pools: Sequence[int] = POOLS,
    decision: str | None = None,
    threads: int | None = None,
    prior=None,
    abstain_ambiguous: bool = True,
    seed: int = 0,
    ballistic_directions: str | None = None,
    settings: Sequence[tuple[str | None, bool]] | None = None,
) -> list[dict[str, Any]]:
    """Render, map, classify and score probe ``name`` (:func:`probe_dict`, with ``ballistic_directions``) at every
    window: one row per window (and per pair of ``settings``, :func:`_classify_rendered`)."""
    from ..prior import Prior

    spec = model.spec
    density = float(min((prior or Prior()).density_per_um3))
    scored = _classify_rendered(
        [probe_dict(name, spec, levels, density, seed, ballistic_directions)],
        model,
        f"probe-{name}",
        seed,
        pools=pools,
        decision=decision,
        threads=threads,
        abstain_ambiguous=abstain_ambiguous,
        settings=settings,
    )
    return [
        {
            **({"setting": r["setting"]} if "setting" in r else {}),
            "probe": name,
            "geometry": name.split("-")[0],
            "pool": r["pool"],
            "model": spec.name,
            **{k: v for k, v in r.items() if k not in ("setting", "pool", "decision", "seconds", "abstain_ambiguous")},
            "seconds": r["seconds"]["total"],
        }
        for r in scored
    ]


def run_grid(
    cells: Iterable[GridCell],
    model: str | None = None,
    *,
    pools: Sequence[int] = POOLS,
    decision: str | None = None,
    threads: int | None = None,
    progress: bool = True,
    geometry_models: dict[str, str] | None = None,
    levels: dict[str, dict[str, dict[str, float]]] | None = None,
    abstain_ambiguous: bool = True,
    probes: Sequence[str] = (),
    ballistic_directions: str | None = None,
) -> dict[str, Any]:
    """Every cell of ``cells`` and every probe of ``probes`` (module docstring) with ``model`` (default: the model ``doct-classify``
    picks for the cell's maps: ``signature-bscan`` for B-scans, ``signature`` for volumes). ``levels``:
    ``{geometry: speed_levels(...)}`` already computed (default: computed here). ``ballistic_directions``: the
    random-ballistic direction law of every phantom (:func:`phantom_dict`; default isotropic)."""
    return run_grids(
        cells,
        [(decision, abstain_ambiguous)],
        model,
        pools=pools,
        threads=threads,
        progress=progress,
        geometry_models=geometry_models,
        levels=levels,
        probes=probes,
        ballistic_directions=ballistic_directions,
    )[0]


def run_grids(
    cells: Iterable[GridCell],
    settings: Sequence[tuple[str | None, bool]],
    model: str | None = None,
    *,
    pools: Sequence[int] = POOLS,
    threads: int | None = None,
    progress: bool = True,
    geometry_models: dict[str, str] | None = None,
    levels: dict[str, dict[str, dict[str, float]]] | None = None,
    probes: Sequence[str] = (),
    ballistic_directions: str | None = None,
) -> list[dict[str, Any]]:
    """:func:`run_grid` for every pair ``(decision, abstain_ambiguous)`` of ``settings``, each phantom rendered
    and mapped once and classified with each pair: one result per pair, each the one :func:`run_grid` gives with
    that pair (a cell's render and maps seconds are those of the shared rendering; ``seconds`` is the whole
    run's)."""
    _check_law(ballistic_directions)
    from ..infer import load_model

    settings = [(d, bool(a)) for d, a in settings]
    cells = list(cells)
    defaults = geometry_models or {"bscan": "signature-bscan", "volume": "signature"}
    probes = list(probes)
    names = {g: (model or defaults[g]) for g in {c.geometry for c in cells} | {p.split("-")[0] for p in probes}}
    models = {g: load_model(n, threads=threads) for g, n in names.items()}
    levels = {g: (levels or {}).get(g) or speed_levels(m.spec) for g, m in models.items()}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(cells) + len(probes), desc="phantom grid", unit="phantom")
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for cell in cells:
        rows.extend(
            run_cell(
                cell,
                models[cell.geometry],
                levels[cell.geometry],
                pools=pools,
                threads=threads,
                ballistic_directions=ballistic_directions,
                settings=settings,
            )
        )
        if bar is not None:
            bar.update()
    probe_rows: list[dict[str, Any]] = []
    for name in probes:
        g = name.split("-")[0]
        probe_rows.extend(
            run_probe(
                name,
                models[g],
                levels[g],
                pools=pools,
                threads=threads,
                seed=cells[0].seed if cells else 0,
                ballistic_directions=ballistic_directions,
                settings=settings,
            )
        )
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    from torchdoct.runtime.machine import machine_info

    def of(k: int, rs: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The rows of setting ``k``, without the tag."""
        return [{key: v for key, v in r.items() if key != "setting"} for r in rs if r["setting"] == k]

    out = []
    for k, (decision, abstain) in enumerate(settings):
        mine, mine_probes = of(k, rows), of(k, probe_rows)
        out.append(
            {
                "schema_version": SCHEMA_VERSION,
                "benchmark": "phantom-grid",
                "definitions": _definitions(),
                "models": {g: m.spec.name for g, m in models.items()},
                "decision": mine[0]["decision"] if mine else decision,
                "abstain_ambiguous": abstain,
                "ballistic_directions": ballistic_directions or "isotropic",
                "speed_levels": dict(levels.items()),
                "units": {"diffusion": "µm²/s", "ballistic": "µm/s", "flow": "µm/s", "seconds": "s"},
                "cells": mine,
                "probes": mine_probes,
                "summary": summarize(mine),
                "summary_by_context": summarize_by_context(mine),
                "summary_by_context_all_pixels": summarize_by_context(
                    [{**r, "per_class": r["all_pixels"]["per_class"]} for r in mine]
                ),
                "seconds": seconds,
                "machine": machine_info(),
            }
        )
    return out


def _definitions() -> dict[str, str]:
    doc = __doc__ or ""
    return {
        "cells": doc[doc.index("**Phantom of a cell.**") : doc.index("**Scores of a cell**")].strip(),
        "scores": doc[doc.index("**Scores of a cell**") : doc.index("Outputs (")].strip(),
    }


def summarize(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per window: the worst cell's wrong share, the mean and the lowest coverage, cells over 10 % wrong; and
    over every band pixel (``all_pixels``, borders included, where the cells hold it): the worst cell's wrong
    share and the cells over 5 % wrong (the project's bound per motion)."""
    out = {}
    for pool in sorted({r["pool"] for r in rows}):
        rs = [r for r in rows if r["pool"] == pool]
        ws = [r["wrong_share_max"] for r in rs if r["wrong_share_max"] is not None]
        cov = [r["coverage"] for r in rs if r["coverage"] is not None]
        bas = [r["balanced_accuracy"] for r in rs if r["balanced_accuracy"] is not None]
        wa = [
            r["all_pixels"]["wrong_share_max"]
            for r in rs
            if r.get("all_pixels") and r["all_pixels"].get("wrong_share_max") is not None
        ]
        out[str(pool)] = {
            "cells": len(rs),
            "worst_wrong_share": max(ws) if ws else None,
            "cells_over_10pct_wrong": int(sum(w > 0.10 for w in ws)),
            "mean_coverage": float(np.mean(cov)) if cov else None,
            "min_coverage": min(cov) if cov else None,
            "mean_balanced_accuracy": float(np.mean(bas)) if bas else None,
            "worst_wrong_share_all_pixels": max(wa) if wa else None,
            "cells_over_5pct_wrong_all_pixels": int(sum(w > 0.05 for w in wa)) if wa else None,
        }
    return out


def summarize_by_context(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per geometry, static context and window, the pixels of every cell pooled: per motion the coverage
    (share decided as one class), the recall on its decided pixels and the wrong share (share of its pixels
    decided as another class); over the motions the coverage, the balanced accuracy on decided pixels (mean
    recall over the motions with a decided pixel) and the worst wrong share; ``rules_changed_share``: per rule of
    :mod:`classifier.ambiguity`, the pixels it changed over the classified pixels (``None`` without the rules)."""
    out = []
    keys = sorted({(r["geometry"], r["context"], r["pool"]) for r in rows})
    for geometry, context, pool in keys:
        rs = [r for r in rows if (r["geometry"], r["context"], r["pool"]) == (geometry, context, pool)]
        per: dict[str, dict[str, Any]] = {}
        for m in MOTIONS:
            n = sum(r["per_class"][m]["pixels"] for r in rs)
            dec = sum(r["per_class"][m]["decided"] for r in rs)
            right = sum(
                round(r["per_class"][m]["recall"] * r["per_class"][m]["decided"])
                for r in rs
                if r["per_class"][m]["recall"] is not None
            )
            per[m] = {
                "pixels": n,
                "coverage": dec / n if n else None,
                "recall": right / dec if dec else None,
                "wrong_share": (dec - right) / n if n else None,
            }
        n_all = sum(p["pixels"] for p in per.values())
        ruled = [r for r in rs if r.get("rules_changed") is not None]
        n_cls = sum(r["classified"] for r in ruled)
        changed = (
            {k: sum(r["rules_changed"].get(k, 0) for r in ruled) / n_cls for k in ruled[0]["rules_changed"]}
            if ruled and n_cls
            else None
        )
        recalls = [p["recall"] for p in per.values() if p["recall"] is not None]
        wrongs = [p["wrong_share"] for p in per.values() if p["wrong_share"] is not None]
        dop = [r["doppler"]["abs_imaginary"] for r in rs if r.get("doppler")]
        null = [d[m]["max"] for d in dop for m in ("diffusion", "ballistic") if d.get(m)]
        power = [d["flow"]["median"] for d in dop if d.get("flow")]
        out.append(
            {
                "geometry": geometry,
                "context": context,
                "pool": pool,
                "cells": len(rs),
                "coverage": sum(p["coverage"] * p["pixels"] for p in per.values() if p["pixels"]) / n_all
                if n_all
                else None,
                "balanced_accuracy": float(np.mean(recalls)) if recalls else None,
                "worst_wrong_share": max(wrongs) if wrongs else None,
                "per_class": per,
                "rules_changed_share": changed,
                "doppler": {
                    "cells": len(dop),
                    "null_max": max(null) if null else None,
                    "flow_median": float(np.median(power)) if power else None,
                },
            }
        )
    return out


_COLUMNS = (
    "key",
    "geometry",
    "context",
    "snr_db",
    "level",
    "polar_deg",
    "azimuth_deg",
    "pool",
    "model",
    "decision",
    "pixels",
    "coverage",
    "balanced_accuracy",
    "wrong_share_max",
    "wrong_diffusion",
    "wrong_ballistic",
    "wrong_flow",
    "set_miss_max",
    "flow_identifiable",
    "seconds",
)


def _flat(r: dict[str, Any]) -> dict[str, Any]:
    pc = r["per_class"]
    miss = [p["set_miss_share"] for p in pc.values() if p["set_miss_share"] is not None]
    return {
        "key": r["key"],
        "geometry": r["geometry"],
        "context": r["context"],
        "snr_db": "none" if r["snr_db"] is None else r["snr_db"],
        "level": r["level"],
        "polar_deg": r["polar_deg"],
        "azimuth_deg": r["azimuth_deg"],
        "pool": r["pool"],
        "model": r["model"],
        "decision": r["decision"],
        "pixels": r["pixels"],
        "coverage": r["coverage"],
        "balanced_accuracy": r["balanced_accuracy"],
        "wrong_share_max": r["wrong_share_max"],
        **{f"wrong_{m}": pc[m]["wrong_share"] for m in MOTIONS},
        "set_miss_max": max(miss) if miss else None,
        "flow_identifiable": r["identifiable"]["flow"],
        "seconds": r["seconds"]["total"],
    }


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def _context_row(s: dict[str, Any]) -> str:
    return (
        f"| {s['geometry']} | {s['context']} | {s['pool']} | {s['cells']} | {_fmt(s['coverage'])} | "
        f"{_fmt(s['balanced_accuracy'])} | {_fmt(s['worst_wrong_share'])} | "
        + " | ".join(
            f"{_fmt(s['per_class'][m]['coverage'])} / {_fmt(s['per_class'][m]['wrong_share'])}" for m in MOTIONS
        )
        + " |"
    )


_PROBE_CAPTION = (
    "Probes, phantoms unlike the bands (`probes`): coverage and wrong share per motion on the pixels away from "
    "other regions, and the worst wrong share over every pixel of each region, borders included."
)


_DOPPLER_CAPTION = (
    "Rule 10's statistic (`classifier.ambiguity.doppler_imaginary`: the imaginary part of the mean Doppler phasor "
    "over a pixel's box) on the pixels away from other regions, pooled over the cells of each geometry, static "
    "context and window whose maps hold a Doppler channel (a static reference exists; `summary_by_context`, "
    "`doppler`)."
)
_RULES_CAPTION = (
    "What each rule of `classifier.ambiguity` changed, pooled over the cells of each geometry, static context and "
    "window (`summary_by_context`, `rules_changed_share`): the pixels it changed as a share of the classified "
    "pixels, every pixel of the cells."
)


def format_rules(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The Markdown table of ``rules_changed_share`` per geometry, static context and window."""
    rules = list(dict.fromkeys(k for s in rows for k in s["rules_changed_share"]))
    lines = [
        "| geometry | context | window | " + " | ".join(rules) + " |",
        "|---|---|---:|" + "---:|" * len(rules),
    ]
    for s in rows:
        share = s["rules_changed_share"]
        lines.append(
            f"| {s['geometry']} | {s['context']} | {s['pool']} | "
            + " | ".join("–" if k not in share else _fmt(share[k]) for k in rules)
            + " |"
        )
    return lines


def format_doppler(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Rule 10's statistic per geometry, static context and window (``summary_by_context``, ``doppler``): the
    cells whose maps hold a Doppler channel, the largest magnitude over the direction-symmetric motions' pixels
    (the null) and the median over the cells of the flow's median magnitude (the power)."""
    from classifier.ambiguity import DOPPLER_IM_MIN

    out = [
        "| geometry | context | window | cells with a Doppler channel | null: largest \\|Im\\| (diffusion, ballistic) "
        f"| flow: median \\|Im\\| (rule 10 at ≥ {DOPPLER_IM_MIN:g}) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        d = r.get("doppler") or {}
        out.append(
            f"| {r['geometry']} | {r['context']} | {r['pool']} | {d.get('cells', 0)} | {_fmt(d.get('null_max'))} "
            f"| {_fmt(d.get('flow_median'))} |"
        )
    return out


def format_probes(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The Markdown table of the probe rows (one per probe and window)."""
    lines = [
        "| probe | window | coverage | worst wrong share | "
        + " | ".join(f"{m} coverage / wrong" for m in MOTIONS)
        + " | all pixels: worst wrong share |",
        "|---|---:|---:|---:|" + "---:|" * len(MOTIONS) + "---:|",
    ]
    for r in rows:
        pc = r["per_class"]
        lines.append(
            f"| {r['probe']} | {r['pool']} | {_fmt(r['coverage'])} | {_fmt(r['wrong_share_max'])} | "
            + " | ".join(
                "–" if not pc[m]["pixels"] else f"{_fmt(pc[m]['coverage'])} / {_fmt(pc[m]['wrong_share'])}"
                for m in MOTIONS
            )
            + f" | {_fmt(r['all_pixels']['wrong_share_max'])} |"
        )
    return lines


def format_table(res: dict[str, Any]) -> str:
    """The Markdown table: a summary per window, then one row per cell and window."""
    lines = [
        f"# Phantom grid ({res['benchmark']}, schema {res['schema_version']})",
        "",
        f"Models: {', '.join(f'{g}: `{m}`' for g, m in res['models'].items())}; decision: `{res['decision']}`"
        + (
            ", flow where the speckle moved coherently or the Doppler phase against a static reference drifted, "
            "ballistic-or-flow where flow cannot be excluded, a set with flow where the "
            "pattern's offset moved, and indeterminate where only the coarse configurations saw flow beside another region, a "
            "coarser configuration decayed faster than the finest, few neighbours share a decision or the finest footprint "
            "holds an outcome that excludes it (classifier.ambiguity)"
            if res.get("abstain_ambiguous", False)
            else ", the model's decisions kept"
        )
        + f". Random-ballistic direction law: `{res.get('ballistic_directions', 'isotropic')}`. "
        "Speed levels (diffusion µm²/s, speeds µm/s): "
        + "; ".join(
            f"{g}: " + ", ".join(f"{m} {'/'.join(f'{v:g}' for v in lv.values())}" for m, lv in levels.items())
            for g, levels in res["speed_levels"].items()
        )
        + ".",
        "",
        "| window | cells | worst wrong share | cells > 10 % wrong | mean coverage | lowest coverage "
        "| mean balanced accuracy | all pixels: worst wrong share | all pixels: cells > 5 % wrong |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for pool, s in res["summary"].items():
        over = s.get("cells_over_5pct_wrong_all_pixels")
        lines.append(
            f"| {pool} | {s['cells']} | {_fmt(s['worst_wrong_share'])} | {s['cells_over_10pct_wrong']} | "
            f"{_fmt(s['mean_coverage'])} | {_fmt(s['min_coverage'])} | {_fmt(s['mean_balanced_accuracy'])} | "
            f"{_fmt(s.get('worst_wrong_share_all_pixels'))} | {'–' if over is None else over} |"
        )
    captions = {
        "summary_by_context": "Pooled over the cells of each geometry, static context and window (`summary_by_context`): "
        "coverage, balanced accuracy on decided pixels, worst wrong share, and per motion coverage / wrong share.",
        "summary_by_context_all_pixels": "The same over every band pixel, borders included "
        "(`summary_by_context_all_pixels`, edge 0).",
    }
    for key, caption in captions.items():
        if res.get(key):
            lines += [
                "",
                caption,
                "",
                "| geometry | context | window | cells | coverage | balanced accuracy | worst wrong share | "
                + " | ".join(f"{m} coverage / wrong" for m in MOTIONS)
                + " |",
                "|---|---|---:|---:|---:|---:|---:|" + "---:|" * len(MOTIONS),
            ]
            lines += [_context_row(s) for s in res[key]]
    ctx = [s for s in res.get("summary_by_context") or [] if s.get("rules_changed_share")]
    if ctx:
        lines += ["", _RULES_CAPTION, "", *format_rules(ctx)]
    dop = [s for s in res.get("summary_by_context") or [] if (s.get("doppler") or {}).get("cells")]
    if dop:
        lines += ["", _DOPPLER_CAPTION, "", *format_doppler(dop)]
    if res.get("probes"):
        lines += ["", _PROBE_CAPTION, "", *format_probes(res["probes"])]
    cols = [c for c in _COLUMNS if c not in ("key", "model", "decision")]
    lines += ["", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in res["cells"]:
        f = _flat(r)
        lines.append("| " + " | ".join(_fmt(f[c]) for c in cols) + " |")
    lines += ["", res["definitions"]["cells"], "", res["definitions"]["scores"]]
    return "\n".join(lines) + "\n"


def _csv_text(res: dict[str, Any]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in res["cells"]:
        w.writerow({k: ("" if v is None else v) for k, v in _flat(r).items()})
    return buf.getvalue()


def plot_grid(res: dict[str, Any], path: str | Path) -> None:
    """Heat maps: worst wrong share and coverage per cell (rows: geometry, context, noise; columns: speed
    level, polar and azimuth angle of the flow), one pair per window; cividis, colour bars in fractions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = res["cells"]
    pools = sorted({r["pool"] for r in cells})
    rkey = lambda r: (r["geometry"], r["context"], "none" if r["snr_db"] is None else f"{r['snr_db']:g} dB")  # noqa: E731
    ckey = lambda r: (r["level"], r["polar_deg"], r["azimuth_deg"])  # noqa: E731
    rows = sorted({rkey(r) for r in cells}, key=lambda k: (GEOMETRIES.index(k[0]), CONTEXTS.index(k[1]), k[2]))
    cols = sorted({ckey(r) for r in cells}, key=lambda k: (LEVELS.index(k[0]), k[1], k[2]))
    panels = [(pool, field) for pool in pools for field in ("wrong_share_max", "coverage")]
    fig, axes = plt.subplots(
        len(panels),
        1,
        figsize=(max(8.0, 0.22 * len(cols) + 5), len(panels) * (0.3 * len(rows) + 2.2)),
        squeeze=False,
        constrained_layout=True,
    )
    labels = {
        "wrong_share_max": ("worst wrong share", "fraction of a motion's pixels\ndecided as another class"),
        "coverage": ("coverage", "decided fraction of\nthe scored pixels"),
    }
    for i, (pool, field) in enumerate(panels):
        for j in (0,):
            title, label = labels[field]
            a = np.full((len(rows), len(cols)), np.nan)
            for r in cells:
                if r["pool"] == pool and r[field] is not None:
                    a[rows.index(rkey(r)), cols.index(ckey(r))] = r[field]
            ax = axes[i][j]
            im = ax.imshow(a, cmap="cividis", vmin=0.0, vmax=1.0, aspect="auto")
            ax.set_yticks(range(len(rows)), [" / ".join(k) for k in rows], fontsize=7)
            ax.set_xticks(range(len(cols)), [f"{k[0]} {k[1]:g}°/{k[2]:g}°" for k in cols], rotation=90, fontsize=6)
            ax.set_xlabel("flow speed level, polar / azimuth angle (deg)")
            ax.set_ylabel("geometry / static context / noise")
            ax.set_title(f"window {pool}×{pool}: {title} ({res['decision']} decision)", fontsize=9)
            fig.colorbar(im, ax=ax, label=label, shrink=0.9)
    fig.savefig(path, dpi=110)
    plt.close(fig)


OUTPUTS = ("grid.json", "grid.csv", "grid.md", "grid.png")


def write_grid(res: dict[str, Any], out_dir: str | Path, *, force: bool = False, stem: str = "grid") -> list[Path]:
    """Write ``STEM.json``, ``.csv``, ``.md`` and ``.png`` into ``out_dir`` together (all or none)."""
    from torchdoct.files import output_set

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{stem}{s}" for s in (".json", ".csv", ".md", ".png")]
    with output_set(paths, force, "--out") as stage:
        stage(paths[0]).write_text(json.dumps(res, separators=(",", ":"), default=_json_default), encoding="utf-8")
        stage(paths[1]).write_text(_csv_text(res), encoding="utf-8")
        stage(paths[2]).write_text(format_table(res), encoding="utf-8")
        plot_grid(res, stage(paths[3]))
    return paths


def check_output_dir(out_dir: str | Path, stem: str, suffixes: Sequence[str], force: bool) -> Path:
    """``--out``/``--stem`` of a benchmark writing ``STEM`` + each suffix, checked before any work: a plain
    stem, a directory (or none yet), and no result overwritten without ``force``."""
    from torchdoct.files import safe_name

    safe_name(stem, "--stem", "give a plain file name")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    if not force:
        for s in suffixes:
            if (out / f"{stem}{s}").exists():
                raise ValueError(f"--out {out}: {stem}{s} exists; give --force to overwrite it")
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON-able: {type(o).__name__}")


#: The grid's records that differ only in how the maps are classified (``--records``): name -> (stem, decision,
#: decide-ballistic). One rendering and one set of maps per phantom serve all of them.
RECORDS = {
    "default": ("grid-default", None, False),
    "rule": ("grid-rule", "rule", True),
    "conformal": ("grid-conformal", "conformal", True),
}


def _records(value: str) -> list[str]:
    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [v for v in names if v not in RECORDS]
    if bad or not names or len(set(names)) != len(names):
        raise ValueError(
            f"--records {value}: give distinct names among {', '.join(RECORDS)} separated by commas"
            + (f" ({', '.join(bad)} unknown)" if bad else "")
        )
    return names


def build_parser():
    import argparse

    from ..prior import BALLISTIC_LAWS

    p = argparse.ArgumentParser(
        prog="python -m classifier.bench.grid",
        description="The phantom grid: render, map, classify and score phantoms built from "
        "the model's system; writes grid.json/.csv/.md/.png into --out.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--quick", action="store_true", help="the 14-phantom subset (a few minutes on 2 cores)")
    p.add_argument(
        "--model",
        default=None,
        help="shipped model name or .onnx file (default: signature-bscan for "
        "B-scans, signature for volumes, the models doct-classify picks)",
    )
    p.add_argument(
        "--decision",
        default=None,
        choices=("rule", "conformal"),
        help="decision rule (default: doct-classify's default)",
    )
    p.add_argument(
        "--decide-ballistic",
        action="store_true",
        help="keep the model's ballistic decisions (doct-classify --decide-ballistic; default: "
        "flow where the speckle moved coherently or the Doppler phase drifted, ballistic-or-flow where the physics "
        "cannot exclude flow, classifier.ambiguity)",
    )
    p.add_argument(
        "--records",
        default=None,
        metavar="NAME[,NAME...]",
        help="several of the grid's records from one rendering and one set of maps per phantom: "
        + "; ".join(
            f"{k}: {st}" + (f" (--decision {d} --decide-ballistic)" if d else " (the defaults)")
            for k, (st, d, _) in RECORDS.items()
        )
        + " (instead of --stem, --decision and --decide-ballistic)",
    )
    p.add_argument("--geometry", choices=GEOMETRIES, default=None, help="only B-scans or only volumes")
    p.add_argument("--seed", type=int, default=0, help="rendering seed of every cell")
    p.add_argument("--stem", default="grid", help="file names STEM.json, STEM.csv, ... (default grid)")
    p.add_argument("--threads", type=int, default=None, metavar="N")
    p.add_argument("--force", action="store_true", help="overwrite existing results")
    p.add_argument("--no-probes", action="store_true", help="skip the probes (phantoms unlike the bands)")
    p.add_argument(
        "--ballistic-directions",
        default=None,
        choices=BALLISTIC_LAWS,
        help="the random-ballistic direction law of every phantom (default isotropic; the training prior holds both)",
    )
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    import sys

    args = build_parser().parse_args(argv)
    try:
        if args.records is not None:
            if args.decision or args.decide_ballistic or args.stem != "grid":
                raise ValueError(
                    "--records names each record's stem and decision; give it without --stem, "
                    "--decision and --decide-ballistic"
                )
            chosen = [RECORDS[n] for n in _records(args.records)]
        else:
            chosen = [(args.stem, args.decision, args.decide_ballistic)]
        out = Path(args.out)
        for stem, _, _ in chosen:  # every record's files checked before any work
            check_output_dir(out, stem, (".json", ".csv", ".md", ".png"), args.force)
        cells = quick_cells(args.seed) if args.quick else full_cells(args.seed)
        if args.geometry:
            cells = [c for c in cells if c.geometry == args.geometry]
        results = run_grids(
            cells,
            [(d, not b) for _, d, b in chosen],
            args.model,
            threads=args.threads,
            progress=not args.no_progress,
            probes=[] if args.no_probes else [p for p in PROBES if args.geometry in (None, p.split("-")[0])],
            ballistic_directions=args.ballistic_directions,
        )
        head = (" --quick" if args.quick else "") + (f" --model {args.model}" if args.model else "")
        tail = (
            (f" --geometry {args.geometry}" if args.geometry else "")
            + (f" --seed {args.seed}" if args.seed else "")
            + (" --no-probes" if args.no_probes else "")
            + (f" --ballistic-directions {args.ballistic_directions}" if args.ballistic_directions else "")
        )
        written = []
        for res, (stem, decision, decide) in zip(results, chosen):
            if args.records is not None:
                how = f" --records {args.records}{head}{tail}"
            else:
                how = (
                    head
                    + (f" --decision {decision}" if decision else "")
                    + (" --decide-ballistic" if decide else "")
                    + tail
                    + (f" --stem {stem}" if stem != "grid" else "")
                )
            res["command"] = f"python -m classifier.bench.grid{how} --out DIR"
            written += write_grid(res, out, force=args.force, stem=stem)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for res, (stem, _, _) in zip(results, chosen):
        if len(chosen) > 1:
            print(f"{stem}:")
        _print_summary(res)
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _print_summary(res: dict[str, Any]) -> None:
    for pool, s in res["summary"].items():
        print(
            f"window {pool}: {s['cells']} cells, worst wrong share {_fmt(s['worst_wrong_share'])}, "
            f"{s['cells_over_10pct_wrong']} over 10 %, mean coverage {_fmt(s['mean_coverage'])}; every band pixel: "
            f"worst {_fmt(s['worst_wrong_share_all_pixels'])}, {s['cells_over_5pct_wrong_all_pixels']} over 5 %"
        )
    for r in res.get("probes", []):
        print(
            f"probe {r['probe']}, window {r['pool']}: coverage {_fmt(r['coverage'])}, worst wrong share "
            f"{_fmt(r['wrong_share_max'])}; every pixel: worst {_fmt(r['all_pixels']['wrong_share_max'])}"
        )


if __name__ == "__main__":
    raise SystemExit(main())

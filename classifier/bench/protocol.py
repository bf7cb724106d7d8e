"""What accuracy costs in acquisition time (``python -m classifier.bench.protocol``).

For one system, how the share of flow and random-ballistic pixels that the speckle pattern's physics
decides, and how right it decides them, change with the number of frames, the frame interval and the
window (the spatial resolution of the class map). The shipped networks are tied to the protocol they were
trained for, so the decision scored here is the one that does not depend on a protocol: what
:mod:`classifier.ambiguity` reads from the speckle-motion channels of ``torchdoct maps --speckle``.

**Phantom of a protocol.** Two bands side by side along x, random-ballistic motion and flow: cylinders
whose axis is the depth axis z, radius :data:`BAND_RADIUS_PX` pixels, spaced by :data:`BAND_GAP_PX` empty
pixels, :data:`IMAGE_NZ` pixels deep, in a B-scan without static tissue. The optics, the medium's
refractive index and the frame interval ``Δt`` are the system's (the spec's first configuration); the
pixel pitch is a third of its finest lateral resolution (rounded to 0.5 µm, as the phantom grid's), the
density the training prior's lowest. Flow at ``flow_speed`` (default :data:`FLOW_SPEED` µm/s, polar
:data:`FLOW_POLAR_DEG`° from the beam, azimuth :data:`FLOW_AZIMUTH_DEG`° from +x); random-ballistic motion
(isotropic directions) at a stated speed or, by default, at the speed whose single-pixel intensity
correlation (physics.md §5.4, closed forms of :mod:`torchdoct.sim.theory`) at the longest lag the
speckle features of the system's own protocol read (the lag rule 2 of :mod:`classifier.ambiguity` reads)
equals the flow's: one pixel's decay cannot tell the two apart there. Every protocol is rendered
(:func:`torchdoct.image.render.render`) at ``seeds`` scatterer realisations, optional noise at ``snr_db``,
and mapped by the code of ``torchdoct maps --speckle --speckle-window W``
(:func:`torchdoct.measured.maps.compute_maps`; lags :func:`torchdoct.sim.speckle.default_lags` of the
frame count, so they span the same share of every acquisition).

**Variants.** Frame counts × frame intervals (multiples of the system's ``Δt``) × windows (odd pixels:
the speckle window, the class map's resolution); the acquisition lasts ``n_frames · interval`` s.

**Decision** (per pixel, from the rules of :mod:`classifier.ambiguity`, with every pixel a candidate
``ballistic`` decision; rule 1, every ballistic decision of a B-scan a set, is not applied: the flow here
has an in-plane component and the question is what the protocol resolves):

* ``rules`` (what ``doct-classify`` keeps of a ``ballistic`` decision): ``flow`` where the pattern moved
  coherently (rule 0, :func:`~classifier.ambiguity.coherent_motion`) or held and moved along a line
  (rule 5, :func:`~classifier.ambiguity.translated`, at windows of 9 pixels or more); else ``ballistic`` where the
  window decorrelated (rule 2: the centred correlation at the longest lag below
  :data:`~classifier.ambiguity.DECORRELATED_BELOW`), not before the first lag (rule 3,
  :func:`~classifier.ambiguity.fast_decorrelation`) and the peak offset did not move (rule 4,
  :func:`~classifier.ambiguity.offset_moved`); else undecided (``ballistic-or-flow``): the rules of
  :func:`~classifier.ambiguity.abstain_where_ambiguous`, in its order, applied to all-``ballistic`` labels.
* ``offset-as-flow``: the same, but where rule 4 fires the pixel is decided ``flow`` instead of left
  undecided (rule 4 only abstains in ``doct-classify``: it also fires on random motion; this decision
  shows what deciding on it would cost).

**Scores of a variant** (pooled over the seeds; a band's pixels whose box of half-width ``edge`` lies
inside the image and inside the band, ``edge`` = half the system's coarser resolution, rounded up to
pixels, plus half the window plus the offset grid's reach
:data:`torchdoct.measured.mapspeckle.SPECKLE_MAX_OFFSET`):

* ``coverage`` per band: share decided (``flow`` or ``ballistic``); overall: decided share of both bands;
* ``accuracy`` per band: right share of its decided pixels (``None`` without a decided pixel);
  ``balanced_accuracy``: the mean of the two (``None`` when one is ``None``);
* ``wrong_share`` per band: share of its scored pixels decided as the other class; ``wrong_share_max``;
* ``rules`` per band: the share of its scored pixels where rule 0 (``coherent``), rule 5 (``translated``),
  rule 4 (``moved``),
  rule 2 (``decorrelated``) and rule 3 (``fast``) fire;
* ``acquisition_s``: ``n_frames · interval``; ``seconds``: rendering of the protocol's phantoms (shared
  by its windows), this window's maps, and the decision and scoring, summed over the seeds.

Outputs (:func:`write_protocol`): ``STEM.json`` (:data:`SCHEMA_VERSION`, the definitions above, the
command, the machine, one row per variant and decision), ``STEM.csv``, ``STEM.md`` and ``STEM.png``.

Kept whole (over 800 lines): the benchmark's phantom, decision, scoring, table, figure and command line
share its variant definitions and the results schema they write; one file is one benchmark, as in
:mod:`classifier.bench.grid`.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "SCHEMA_VERSION",
    "Variant",
    "full_variants",
    "quick_variants",
    "matched_ballistic_speed",
    "phantom_dict",
    "decide",
    "scored_mask",
    "score_outcome",
    "run_protocol",
    "format_table",
    "write_protocol",
    "main",
]

SCHEMA_VERSION = 1
BANDS = ("ballistic", "flow")
#: Rendered motion codes (torchdoct.image.phantom.MOTION_CODES) of the bands; 0 in a decision: undecided.
CODES = {"ballistic": 3, "flow": 4}
UNDECIDED = 0
DECISIONS = ("rules", "offset-as-flow")
#: The rules whose firing :func:`decide` reports per pixel, and the scores count per band.
RULES = ("coherent", "translated", "moved", "decorrelated", "fast")
FRAMES = (32, 64, 128)
INTERVAL_FACTORS = (0.5, 1.0, 2.0)
WINDOWS = (5, 9, 13)
FLOW_SPEED = 0.3
FLOW_POLAR_DEG = 45.0
FLOW_AZIMUTH_DEG = 60.0
BAND_RADIUS_PX = 16
BAND_GAP_PX = 8
IMAGE_NZ = 80
#: Scatterer realisations per protocol: full and ``--quick``.
SEEDS_FULL = 12
SEEDS_QUICK = 4
#: The speed range (µm/s) searched for the matched ballistic speed.
_MATCH_RANGE = (1e-4, 1e2)


@dataclass(frozen=True)
class Variant:
    """One protocol: frames, frame interval as a multiple of the system's, window (pixels)."""

    n_frames: int
    interval_factor: float
    window: int

    @property
    def key(self) -> str:
        return f"T{self.n_frames}-dt{self.interval_factor:g}x-w{self.window}"


def full_variants(
    frames: Sequence[int] = FRAMES, factors: Sequence[float] = INTERVAL_FACTORS, windows: Sequence[int] = WINDOWS
) -> list[Variant]:
    """Every combination of ``frames`` × ``factors`` × ``windows``."""
    _check_axes(frames, factors, windows)
    return [Variant(int(n), float(f), int(w)) for n, f, w in itertools.product(frames, factors, windows)]


def quick_variants(
    frames: Sequence[int] = FRAMES, factors: Sequence[float] = INTERVAL_FACTORS, windows: Sequence[int] = WINDOWS
) -> list[Variant]:
    """``--quick``: one axis at a time around the centre (the first frame count, the interval nearest the
    system's, the middle window): every frame count, every interval, every window, the others held
    (7 variants of the defaults, from 5 renderings)."""
    _check_axes(frames, factors, windows)
    n0 = int(frames[0])
    f0 = float(min(factors, key=lambda f: abs(math.log(f))))
    w0 = int(sorted(windows)[len(windows) // 2])
    out = [Variant(int(n), f0, w0) for n in frames]
    out += [Variant(n0, float(f), w0) for f in factors]
    out += [Variant(n0, f0, int(w)) for w in windows]
    return list(dict.fromkeys(out))


def _check_axes(frames: Sequence[int], factors: Sequence[float], windows: Sequence[int]) -> None:
    from torchdoct.sim.speckle import default_lags

    if not frames or not factors or not windows:
        raise ValueError("give at least one frame count, one interval factor and one window")
    for n in frames:
        if isinstance(n, bool) or int(n) != n or n < 8:
            raise ValueError(
                f"--frames: every frame count must be an integer >= 8 (the speckle lags need it); got {n!r}"
            )
        if len(default_lags(int(n))) < 2:
            raise ValueError(f"--frames {n}: the speckle features need two lags")
    for f in factors:
        if not (isinstance(f, (int, float)) and math.isfinite(f) and f > 0):
            raise ValueError(f"--intervals: every interval factor must be a positive number; got {f!r}")
    for w in windows:
        if isinstance(w, bool) or int(w) != w or w < 1 or int(w) % 2 == 0:
            raise ValueError(f"--windows: every window must be an odd number of pixels >= 1; got {w!r}")
    for name, axis in (("--frames", frames), ("--intervals", factors), ("--windows", windows)):
        if len(set(axis)) != len(axis):
            raise ValueError(f"{name}: a value is listed twice")


def _pitch_um(spec) -> float:
    from .grid import _pitch_um as grid_pitch

    return grid_pitch(spec)


def _density() -> float:
    from ..prior import Prior

    return float(min(Prior().density_per_um3))


def _rho_intensity(
    motion: str, speed: float, tau_s: float, spec, density: float, polar: float = 0.0, azimuth: float = 0.0
) -> float:
    """Closed-form single-pixel intensity correlation coefficient (physics.md §5.4) of the moving
    scatterers at ``tau_s`` for the spec's first configuration."""
    from torchdoct.conventions import n_eff
    from torchdoct.sim import theory

    c = spec.configurations[0]
    res = dict(lateral_resolution_um=c.lateral_resolution_um, axial_resolution_um=c.axial_resolution_um)
    tau = np.array([float(tau_s)])
    if motion == "flow":
        g1 = theory.g1_flow(
            tau,
            speed_um_per_s=speed,
            polar_angle_deg=polar,
            azimuth_deg=azimuth,
            wavelength_um=c.wavelength_um,
            refractive_index=spec.refractive_index,
            **res,
        )
        j = theory.j_flow(tau, speed_um_per_s=speed, polar_angle_deg=polar, azimuth_deg=azimuth, **res)
    else:
        g1 = theory.g1_ballistic(
            tau,
            speed_um_per_s=speed,
            wavelength_um=c.wavelength_um,
            refractive_index=spec.refractive_index,
            directions="isotropic",
            **res,
        )
        j = theory.j_ballistic(tau, speed_um_per_s=speed, directions="isotropic", **res)
    rho = theory.intensity_correlation_coefficient(
        g1, j, n_eff(density, c.lateral_resolution_um, c.axial_resolution_um)
    )
    return float(np.asarray(rho).reshape(-1)[0])


def match_lag_s(spec) -> float:
    """The delay (s) the speed pair is matched at: the longest speckle lag of the system's protocol."""
    from torchdoct.sim.speckle import default_lags

    return float(max(default_lags(spec.n_frames)) * spec.frame_interval_s)


def matched_ballistic_speed(
    spec,
    flow_speed: float = FLOW_SPEED,
    polar_deg: float = FLOW_POLAR_DEG,
    azimuth_deg: float = FLOW_AZIMUTH_DEG,
    density: float | None = None,
) -> float:
    """The random-ballistic speed (µm/s, isotropic directions; 3 significant figures) whose single-pixel
    intensity correlation at :func:`match_lag_s` equals the flow's (module docstring): the lowest such
    speed on a log grid, refined by bisection. ``ValueError`` when the flow's correlation is outside what
    random-ballistic motion reaches in :data:`_MATCH_RANGE` (then give the speed)."""
    density = _density() if density is None else float(density)
    tau = match_lag_s(spec)
    target = _rho_intensity("flow", flow_speed, tau, spec, density, polar_deg, azimuth_deg)
    grid = np.geomspace(*_MATCH_RANGE, 241)
    rho = np.array([_rho_intensity("ballistic", v, tau, spec, density) for v in grid])
    below = np.flatnonzero(rho <= target)
    if below.size == 0 or below[0] == 0:
        raise ValueError(
            f"flow at {flow_speed:g} µm/s has single-pixel correlation {target:.3g} at {tau:.3g} s, "
            f"which random-ballistic motion does not match between {_MATCH_RANGE[0]:g} and "
            f"{_MATCH_RANGE[1]:g} µm/s; give --ballistic-speed"
        )
    lo, hi = math.log(grid[below[0] - 1]), math.log(grid[below[0]])
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _rho_intensity("ballistic", math.exp(mid), tau, spec, density) > target:
            lo = mid
        else:
            hi = mid
    return float(f"{math.exp(0.5 * (lo + hi)):.3g}")


def phantom_dict(
    spec,
    n_frames: int,
    interval_s: float,
    *,
    flow_speed: float,
    ballistic_speed: float,
    polar_deg: float = FLOW_POLAR_DEG,
    azimuth_deg: float = FLOW_AZIMUTH_DEG,
    density: float | None = None,
    seed: int = 0,
    snr_db: float | None = None,
    radius_px: int = BAND_RADIUS_PX,
    n_z: int = IMAGE_NZ,
) -> dict[str, Any]:
    """The phantom of one protocol (module docstring) in the phantom-file schema."""
    from .grid import system_dict

    pitch = _pitch_um(spec)
    density = _density() if density is None else float(density)
    r_um, gap_um = radius_px * pitch, BAND_GAP_PX * pitch
    n_x = 2 * 2 * radius_px + 3 * BAND_GAP_PX
    motions = {
        "ballistic": {"kind": "ballistic", "speed_um_per_s": float(ballistic_speed)},
        "flow": {
            "kind": "flow",
            "speed_um_per_s": float(flow_speed),
            "polar_angle_deg": float(polar_deg),
            "azimuth_deg": float(azimuth_deg),
        },
    }
    regions = []
    for k, name in enumerate(BANDS):
        xc = (k - 0.5) * (2 * r_um + gap_um)
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
    system = system_dict(spec, "protocol-system")
    d: dict[str, Any] = {
        "name": f"protocol-T{n_frames}-dt{interval_s:g}",
        "system": [system],
        "protocol": {"n_frames": int(n_frames), "frame_interval_s": float(interval_s)},
        "grid": {"kind": "bscan", "n_x": n_x, "n_z": int(n_z), "pitch_x_um": pitch, "pitch_z_um": pitch, "y_um": 0.0},
        "region": regions,
        "simulation": {"seed": int(seed)},
    }
    if snr_db is not None:
        d["noise"] = {"snr_db": float(snr_db)}
    return d


def decide(
    channels: Mapping[str, np.ndarray], n_frames: int, pitch_um: float, window: int | None = None
) -> dict[str, np.ndarray]:
    """Per pixel (flattened): the rules that fire (``coherent``, ``moved``, ``decorrelated``, ``fast``) and
    the outcome of each decision of :data:`DECISIONS` (codes :data:`CODES`, :data:`UNDECIDED`), from the
    speckle channels of one resolution (module docstring)."""
    from ..ambiguity import (
        DECORRELATED_BELOW,
        SET_LABEL,
        abstain_where_ambiguous,
        coherent_motion,
        fast_decorrelation,
        offset_moved,
        slow_decorrelation,
        translated,
    )

    coherent, _ = coherent_motion(channels, n_frames=n_frames)
    translation, _ = translated(channels, {"z": pitch_um, "x": pitch_um}, window_px=window)
    moved, _ = offset_moved(channels, pitch_um, n_frames=n_frames)
    corr, _ = slow_decorrelation(channels, n_frames=n_frames)
    fast, _ = fast_decorrelation(channels)
    if coherent is None or moved is None or corr is None or fast is None:
        raise ValueError(
            "the maps lack the speckle channels the decision reads (xc_centre, xc_peak, xc_shift at two lags or more)"
        )
    with np.errstate(invalid="ignore"):
        decorrelated = np.asarray(corr, np.float64) < DECORRELATED_BELOW
    names = ["ballistic", "flow", SET_LABEL]
    to_code = np.array([CODES["ballistic"], CODES["flow"], UNDECIDED])
    start = np.zeros(coherent.shape, np.int64)
    any_moved = np.asarray(moved.off_centre, bool) | np.asarray(moved.grew, bool)
    if translation is None:
        translation = np.zeros(coherent.shape, bool)
    out: dict[str, np.ndarray] = {
        "coherent": coherent,
        "translated": translation,
        "moved": any_moved,
        "decorrelated": decorrelated,
        "fast": fast,
    }
    labels, _ = abstain_where_ambiguous(
        start,
        names,
        unseen_axis=False,
        correlation=corr,
        coherent=coherent,
        fast=fast,
        moved=moved,
        translation=translation,
    )
    out["rules"] = to_code[labels]
    labels, _ = abstain_where_ambiguous(
        start,
        names,
        unseen_axis=False,
        correlation=corr,
        coherent=coherent | any_moved,
        fast=fast,
        translation=translation,
    )
    out["offset-as-flow"] = to_code[labels]
    return out


def scored_mask(truth_codes: np.ndarray, code: int, edge_px: int) -> np.ndarray:
    """The pixels of motion ``code`` whose box of half-width ``edge_px`` lies inside the image and holds
    only pixels of that motion."""
    from scipy.ndimage import minimum_filter

    inside = np.asarray(truth_codes) == code
    if edge_px <= 0:
        return inside
    return minimum_filter(inside.astype(np.uint8), size=2 * int(edge_px) + 1, mode="constant", cval=0) > 0


def _edge_px(spec, pitch: float, window: int) -> int:
    from torchdoct.measured.mapspeckle import SPECKLE_MAX_OFFSET

    c0 = spec.configurations[0]
    coarser = max(c0.lateral_resolution_um, c0.axial_resolution_um)
    return int(math.ceil(coarser / 2.0 / pitch)) + int(window) // 2 + int(SPECKLE_MAX_OFFSET)


def count_outcome(
    outcome: np.ndarray,
    truth_codes: np.ndarray,
    masks: Mapping[str, np.ndarray],
    fired: Mapping[str, np.ndarray] | None = None,
) -> dict[str, dict[str, int]]:
    """Counts per band: ``pixels`` scored, ``decided``, ``right``, ``wrong`` and, for ``fired`` (rule name ->
    boolean per pixel), the pixels where each fires."""
    outcome = np.asarray(outcome).reshape(-1)
    out: dict[str, dict[str, int]] = {}
    for band in BANDS:
        sel = np.asarray(masks[band], bool).reshape(-1)
        got = outcome[sel]
        code = CODES[band]
        other = CODES[BANDS[1 - BANDS.index(band)]]
        c = {
            "pixels": int(sel.sum()),
            "decided": int(np.isin(got, list(CODES.values())).sum()),
            "right": int((got == code).sum()),
            "wrong": int((got == other).sum()),
        }
        for name, f in (fired or {}).items():
            c[name] = int(np.asarray(f, bool).reshape(-1)[sel].sum())
        out[band] = c
    return out


def score_outcome(counts: Mapping[str, Mapping[str, int]]) -> dict[str, Any]:
    """Scores (module docstring) from :func:`count_outcome` counts (summed over seeds)."""
    per: dict[str, Any] = {}
    for band in BANDS:
        c = counts[band]
        n, dec = c["pixels"], c["decided"]
        per[band] = {
            "pixels": n,
            "decided": dec,
            "coverage": dec / n if n else None,
            "accuracy": c["right"] / dec if dec else None,
            "wrong_share": c["wrong"] / n if n else None,
            "rules": {k: (c[k] / n if n else None) for k in RULES if k in c},
        }
    n = sum(counts[b]["pixels"] for b in BANDS)
    dec = sum(counts[b]["decided"] for b in BANDS)
    acc = [per[b]["accuracy"] for b in BANDS]
    ws = [per[b]["wrong_share"] for b in BANDS if per[b]["wrong_share"] is not None]
    return {
        "per_band": per,
        "pixels": n,
        "coverage": dec / n if n else None,
        "balanced_accuracy": float(np.mean(acc)) if all(a is not None for a in acc) else None,
        "wrong_share_max": max(ws) if ws else None,
    }


def _render_seq(d: dict[str, Any], seed: int, threads: int | None):
    from torchdoct.image.phantom import phantom_from_dict
    from torchdoct.image.render import render
    from torchdoct.measured.sequence import SequenceData, validate_meta

    res = render(phantom_from_dict(d), seed=seed, threads=threads)
    data = res.data[0].numpy()
    meta = res.metadata(0)
    meta.pop("phantom", None)
    return SequenceData(data=data, meta=validate_meta(meta, data.shape), source=d["name"]), np.asarray(res.labels)


def run_protocol(
    variants: Sequence[Variant],
    spec=None,
    *,
    flow_speed: float = FLOW_SPEED,
    ballistic_speed: float | None = None,
    polar_deg: float = FLOW_POLAR_DEG,
    azimuth_deg: float = FLOW_AZIMUTH_DEG,
    seeds: int = SEEDS_FULL,
    seed: int = 0,
    snr_db: float | None = None,
    radius_px: int = BAND_RADIUS_PX,
    n_z: int = IMAGE_NZ,
    threads: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Render, map, decide and score every variant (module docstring). ``spec``: a
    :class:`~classifier.features.FeatureSpec` or a name/path (default ``signature-bscan``)."""
    from torchdoct.measured.maps import compute_maps
    from torchdoct.runtime.machine import machine_info
    from torchdoct.sim.speckle import default_lags

    from ..features import load_spec

    spec = load_spec(spec or "signature-bscan")
    variants = list(dict.fromkeys(variants))
    if not variants:
        raise ValueError("no protocol variant to run")
    if int(seeds) < 1:
        raise ValueError(f"--seeds must be >= 1; got {seeds}")
    for name, v in (("--flow-speed", flow_speed), ("--ballistic-speed", ballistic_speed)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive speed (µm/s); got {v}")
    _check_axes(
        sorted({v.n_frames for v in variants}),
        sorted({v.interval_factor for v in variants}),
        sorted({v.window for v in variants}),
    )
    density = _density()
    matched = ballistic_speed is None
    if matched:
        ballistic_speed = matched_ballistic_speed(spec, flow_speed, polar_deg, azimuth_deg, density)
    pitch = _pitch_um(spec)
    protocols = list(dict.fromkeys((v.n_frames, v.interval_factor) for v in variants))
    counts: dict[tuple[Variant, str], dict[str, dict[str, int]]] = {}
    per_seed: dict[tuple[Variant, str], list[dict[str, Any]]] = {}
    seconds: dict[Variant, dict[str, float]] = {v: {"render": 0.0, "maps": 0.0, "decide": 0.0} for v in variants}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(protocols) * int(seeds), desc="protocols", unit="rendering")
    t_all = time.perf_counter()
    for n_frames, factor in protocols:
        interval = factor * spec.frame_interval_s
        mine = [v for v in variants if (v.n_frames, v.interval_factor) == (n_frames, factor)]
        for k in range(int(seeds)):
            s = int(seed) + k
            d = phantom_dict(
                spec,
                n_frames,
                interval,
                flow_speed=flow_speed,
                ballistic_speed=ballistic_speed,
                polar_deg=polar_deg,
                azimuth_deg=azimuth_deg,
                density=density,
                seed=s,
                snr_db=snr_db,
                radius_px=radius_px,
                n_z=n_z,
            )
            t0 = time.perf_counter()
            seq, truth = _render_seq(d, s, threads)
            t_render = time.perf_counter() - t0
            for v in mine:
                seconds[v]["render"] += t_render
                t1 = time.perf_counter()
                maps = compute_maps(seq, ["original"], metrics=("mean_db",), speckle=True, speckle_window=v.window)
                t2 = time.perf_counter()
                ch = {name: maps.data[i] for i, name in enumerate(maps.channels)}
                dec = decide(ch, n_frames, pitch, v.window)
                edge = _edge_px(spec, pitch, v.window)
                masks = {b: scored_mask(truth, CODES[b], edge) for b in BANDS}
                fired = {k2: dec[k2] for k2 in RULES}
                for decision in DECISIONS:
                    c = count_outcome(dec[decision], truth, masks, fired)
                    acc = counts.setdefault((v, decision), {b: {} for b in BANDS})
                    for b in BANDS:
                        for key, val in c[b].items():
                            acc[b][key] = acc[b].get(key, 0) + val
                    sc = score_outcome(c)
                    per_seed.setdefault((v, decision), []).append(
                        {
                            "seed": s,
                            "coverage": sc["coverage"],
                            "balanced_accuracy": sc["balanced_accuracy"],
                            "wrong_share_max": sc["wrong_share_max"],
                        }
                    )
                seconds[v]["maps"] += t2 - t1
                seconds[v]["decide"] += time.perf_counter() - t2
            if bar is not None:
                bar.update()
    if bar is not None:
        bar.close()
    rows = []
    for v in variants:
        interval = v.interval_factor * spec.frame_interval_s
        for decision in DECISIONS:
            sec = dict(seconds[v])
            sec["total"] = sec["render"] + sec["maps"] + sec["decide"]
            rows.append(
                {
                    **asdict(v),
                    "key": v.key,
                    "decision": decision,
                    "interval_s": interval,
                    "acquisition_s": v.n_frames * interval,
                    "lags_frames": list(default_lags(v.n_frames)),
                    "edge_px": _edge_px(spec, pitch, v.window),
                    "window_um": v.window * pitch,
                    **score_outcome(counts[(v, decision)]),
                    "per_seed": per_seed[(v, decision)],
                    "seconds": sec,
                }
            )
    c0 = spec.configurations[0]
    return {
        "schema_version": SCHEMA_VERSION,
        "benchmark": "protocol",
        "definitions": _definitions(),
        "system": {
            "spec": spec.name,
            "wavelength_um": c0.wavelength_um,
            "lateral_resolution_um": c0.lateral_resolution_um,
            "axial_resolution_um": c0.axial_resolution_um,
            "refractive_index": spec.refractive_index,
            "n_frames": spec.n_frames,
            "frame_interval_s": spec.frame_interval_s,
        },
        "phantom": {
            "pitch_um": pitch,
            "density_per_um3": density,
            "band_radius_px": int(radius_px),
            "band_gap_px": BAND_GAP_PX,
            "n_z": int(n_z),
            "seeds": int(seeds),
            "first_seed": int(seed),
            "snr_db": snr_db,
        },
        "motions": {
            "flow": {
                "speed_um_per_s": float(flow_speed),
                "polar_angle_deg": float(polar_deg),
                "azimuth_deg": float(azimuth_deg),
            },
            "ballistic": {
                "speed_um_per_s": float(ballistic_speed),
                "directions": "isotropic",
                "matched": bool(matched),
                "matched_at_s": match_lag_s(spec) if matched else None,
            },
        },
        "units": {
            "speed": "µm/s",
            "interval_s": "s",
            "acquisition_s": "s",
            "window": "px",
            "window_um": "µm",
            "seconds": "s",
        },
        "rows": rows,
        "seconds": time.perf_counter() - t_all,
        "machine": machine_info(),
    }


def _definitions() -> dict[str, str]:
    doc = __doc__ or ""
    cut = lambda a, b: doc[doc.index(a) : doc.index(b)].strip()  # noqa: E731
    return {
        "phantom": cut("**Phantom of a protocol.**", "**Variants.**"),
        "variants": cut("**Variants.**", "**Decision**"),
        "decision": cut("**Decision**", "**Scores of a variant**"),
        "scores": cut("**Scores of a variant**", "Outputs ("),
    }


# ---------------------------------------------------------------------------------------------- outputs

#: The columns copied from a row as they are.
_ROW_FIELDS = (
    "key",
    "decision",
    "n_frames",
    "interval_factor",
    "interval_s",
    "acquisition_s",
    "window",
    "window_um",
    "pixels",
    "coverage",
    "balanced_accuracy",
    "wrong_share_max",
)
#: ``RULE_BAND``: the share of a band's scored pixels where the rule fires (the rules that can fire on it).
_RULE_COLUMNS = (
    "coherent_flow",
    "translated_flow",
    "moved_flow",
    "coherent_ballistic",
    "translated_ballistic",
    "moved_ballistic",
    "decorrelated_ballistic",
    "fast_ballistic",
)
_COLUMNS = (
    *_ROW_FIELDS,
    *(f"{s}_{b}" for b in BANDS for s in ("coverage", "accuracy", "wrong")),
    *_RULE_COLUMNS,
    "seconds",
)


def _flat(r: dict[str, Any]) -> dict[str, Any]:
    pb = r["per_band"]
    out = {k: r[k] for k in _ROW_FIELDS}
    for b in BANDS:
        out[f"coverage_{b}"] = pb[b]["coverage"]
        out[f"accuracy_{b}"] = pb[b]["accuracy"]
        out[f"wrong_{b}"] = pb[b]["wrong_share"]
    for k in _RULE_COLUMNS:
        rule, band = k.rsplit("_", 1)
        out[k] = pb[band]["rules"].get(rule)
    out["seconds"] = r["seconds"]["total"]
    return out


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) >= 1 else f"{v:.3f}"
    return str(v)


def headline(res: dict[str, Any], decision: str = "rules") -> list[str]:
    """One line per (interval, window) holding several frame counts: "flow vs ballistic ...: 32 frames → ..."."""
    rows = [r for r in res["rows"] if r["decision"] == decision]
    m = res["motions"]
    lines = []
    groups = sorted({(r["interval_factor"], r["window"]) for r in rows})
    for f, w in groups:
        rs = sorted((r for r in rows if (r["interval_factor"], r["window"]) == (f, w)), key=lambda r: r["n_frames"])
        if len(rs) < 2:
            continue
        parts = [
            f"{r['n_frames']} frames ({_fmt(r['acquisition_s'])} s) → accuracy {_fmt(r['balanced_accuracy'])}, "
            f"coverage {_fmt(r['coverage'])}, wrong {_fmt(r['wrong_share_max'])}"
            for r in rs
        ]
        lines.append(
            f"flow at {m['flow']['speed_um_per_s']:g} µm/s vs ballistic at "
            f"{m['ballistic']['speed_um_per_s']:g} µm/s, interval {f:g}×, window {w}: " + "; ".join(parts)
        )
    return lines


def format_table(res: dict[str, Any]) -> str:
    """The Markdown report: the setting, the headline lines, one table per decision, the definitions."""
    s, m, ph = res["system"], res["motions"], res["phantom"]
    b = m["ballistic"]
    lines = [
        f"# What accuracy costs in acquisition time ({res['benchmark']}, schema {res['schema_version']})",
        "",
        f"System of spec `{s['spec']}`: {s['wavelength_um'] * 1000:g} nm, lateral {s['lateral_resolution_um']:g} µm, "
        f"axial {s['axial_resolution_um']:g} µm, own protocol {s['n_frames']} frames at "
        f"{s['frame_interval_s']:g} s. Flow {m['flow']['speed_um_per_s']:g} µm/s at polar "
        f"{m['flow']['polar_angle_deg']:g}°, azimuth {m['flow']['azimuth_deg']:g}°; random-ballistic "
        f"{b['speed_um_per_s']:g} µm/s ({b['directions']}"
        + (f", matched to the flow's single-pixel correlation at {b['matched_at_s']:g} s" if b["matched"] else "")
        + f"). Pitch {ph['pitch_um']:g} µm, {ph['seeds']} seed(s), "
        + ("no noise" if ph["snr_db"] is None else f"{ph['snr_db']:g} dB SNR")
        + ".",
        "",
    ]
    if res.get("command"):
        lines += [f"Command: `{res['command']}`", ""]
    for decision in DECISIONS:
        rows = [r for r in res["rows"] if r["decision"] == decision]
        if not rows:
            continue
        lines += [f"## Decision `{decision}`", ""]
        lines += [f"* {h}" for h in headline(res, decision)]
        cols = (
            "n_frames",
            "interval_s",
            "acquisition_s",
            "window",
            "coverage",
            "balanced_accuracy",
            "wrong_share_max",
            "coverage_flow",
            "accuracy_flow",
            "wrong_flow",
            "coverage_ballistic",
            "accuracy_ballistic",
            "wrong_ballistic",
            "seconds",
        )
        head = (
            "frames",
            "interval (s)",
            "acquisition (s)",
            "window (px)",
            "coverage",
            "balanced accuracy",
            "worst wrong share",
            "flow coverage",
            "flow accuracy",
            "flow wrong",
            "ballistic coverage",
            "ballistic accuracy",
            "ballistic wrong",
            "compute (s)",
        )
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---:|" * len(head)]
        for r in rows:
            f = _flat(r)
            lines.append("| " + " | ".join(_fmt(f[c]) for c in cols) + " |")
        lines.append("")
    d = res["definitions"]
    lines += [d["phantom"], "", d["variants"], "", d["decision"], "", d["scores"]]
    return "\n".join(lines) + "\n"


def _csv_text(res: dict[str, Any]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in res["rows"]:
        w.writerow({k: ("" if v is None else v) for k, v in _flat(r).items()})
    return buf.getvalue()


#: Okabe–Ito colours, one per window.
_OKABE_ITO = ("#E69F00", "#56B4E9", "#009E73", "#D55E00", "#0072B2", "#CC79A7", "#F0E442", "#000000")
_MARKERS = ("o", "s", "^", "D", "v", "P", "X")


def plot_protocol(res: dict[str, Any], path: str | Path) -> None:
    """Per decision (rows): coverage, balanced accuracy on decided pixels and worst wrong share (columns)
    against the acquisition time (log axis); colour: window (Okabe–Ito), marker: frame count, lines join
    the frame counts of one interval and window."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import NullLocator

    rows = res["rows"]
    decisions = [d for d in DECISIONS if any(r["decision"] == d for r in rows)]
    windows = sorted({r["window"] for r in rows})
    frames = sorted({r["n_frames"] for r in rows})
    fields = (
        ("coverage", "coverage", "decided share of the bands (fraction)"),
        ("balanced_accuracy", "balanced accuracy on decided pixels", "right share, mean of the bands (fraction)"),
        ("wrong_share_max", "worst wrong share", "decided as the other class (fraction)"),
    )
    times = sorted({r["acquisition_s"] for r in rows})
    fig, axes = plt.subplots(
        len(decisions), 3, figsize=(13, 3.6 * len(decisions)), squeeze=False, constrained_layout=True
    )
    for i, decision in enumerate(decisions):
        rs = [r for r in rows if r["decision"] == decision]
        for j, (field, label, unit) in enumerate(fields):
            ax = axes[i][j]
            for f, w in sorted({(r["interval_factor"], r["window"]) for r in rs}):
                line = sorted(
                    (r for r in rs if (r["interval_factor"], r["window"]) == (f, w)), key=lambda r: r["acquisition_s"]
                )
                xs = [r["acquisition_s"] for r in line]
                ys = [np.nan if r[field] is None else r[field] for r in line]
                colour = _OKABE_ITO[windows.index(w) % len(_OKABE_ITO)]
                ax.plot(xs, ys, "-", color=colour, alpha=0.5, lw=1)
                for r, y in zip(line, ys):
                    ax.plot(
                        r["acquisition_s"],
                        y,
                        _MARKERS[frames.index(r["n_frames"]) % len(_MARKERS)],
                        color=colour,
                        ms=6,
                        mec="black",
                        mew=0.4,
                    )
            ax.set_xscale("log")
            ax.xaxis.set_minor_locator(NullLocator())
            ax.set_xticks(times, [f"{t:.3g}" for t in times], fontsize=7)
            ax.set_ylim(-0.03, 1.03)
            ax.set_xlabel("acquisition time, frames × interval (s)")
            ax.set_ylabel(unit, fontsize=8)
            ax.set_title(f"{decision}: {label}", fontsize=9)
            ax.grid(alpha=0.3)
    handles = [
        Line2D([], [], color=_OKABE_ITO[k % len(_OKABE_ITO)], lw=2, label=f"window {w} px")
        for k, w in enumerate(windows)
    ]
    handles += [
        Line2D([], [], ls="", marker=_MARKERS[k % len(_MARKERS)], color="grey", mec="black", label=f"{n} frames")
        for k, n in enumerate(frames)
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    m = res["motions"]
    fig.suptitle(
        f"flow {m['flow']['speed_um_per_s']:g} µm/s vs random-ballistic "
        f"{m['ballistic']['speed_um_per_s']:g} µm/s, spec {res['system']['spec']}",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


SUFFIXES = (".json", ".csv", ".md", ".png")


def write_protocol(
    res: dict[str, Any], out_dir: str | Path, *, force: bool = False, stem: str = "protocol"
) -> list[Path]:
    """Write ``STEM.json``, ``.csv``, ``.md`` and ``.png`` into ``out_dir`` together (all or none)."""
    from torchdoct.files import output_set

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{stem}{s}" for s in SUFFIXES]
    with output_set(paths, force, "--out") as stage:
        stage(paths[0]).write_text(json.dumps(res, separators=(",", ":"), default=_json_default), encoding="utf-8")
        stage(paths[1]).write_text(_csv_text(res), encoding="utf-8")
        stage(paths[2]).write_text(format_table(res), encoding="utf-8")
        plot_protocol(res, stage(paths[3]))
    return paths


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON-able: {type(o).__name__}")


# ---------------------------------------------------------------------------------------------- command


def _numbers(text: str, kind, what: str) -> list:
    try:
        vals = [kind(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        raise ValueError(f"{what}: give comma-separated numbers; got {text!r}") from None
    if not vals:
        raise ValueError(f"{what}: give at least one value")
    return vals


#: ``torchdoct protocol`` (the entry point ``torchdoct.commands``: :mod:`torchdoct.cli.extensions`).
HELP = "what accuracy costs in acquisition time: coverage, accuracy and wrong share per frame count, interval, window"
DESCRIPTION = (
    "What accuracy costs in acquisition time: render flow and random-ballistic bands for every "
    "frame count, frame interval and window, decide each pixel from the speckle pattern's "
    "physics (classifier.ambiguity) and score coverage, accuracy and wrong share; writes "
    "STEM.json/.csv/.md/.png into --out."
)


def build_parser():
    import argparse

    p = argparse.ArgumentParser(prog="python -m classifier.bench.protocol", description=DESCRIPTION)
    add_arguments(p)
    return p


def add_arguments(p) -> None:
    """The options of ``torchdoct protocol`` (and ``python -m classifier.bench.protocol``)."""
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"one axis at a time around the centre, {SEEDS_QUICK} seeds (within 5 minutes on 2 cores)",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--spec",
        default=None,
        metavar="NAME|FILE.toml",
        help="the system: a shipped feature spec or a spec file (default signature-bscan, the "
        "shipped signature model's system)",
    )
    src.add_argument(
        "--like",
        nargs="+",
        default=None,
        metavar="MAPS",
        help="the system of these maps files (as doct-train --like derives it)",
    )
    p.add_argument("--frames", default=",".join(map(str, FRAMES)), help="frame counts (default %(default)s)")
    p.add_argument(
        "--intervals",
        default=",".join(f"{f:g}" for f in INTERVAL_FACTORS),
        help="frame intervals as multiples of the system's (default %(default)s)",
    )
    p.add_argument(
        "--windows", default=",".join(map(str, WINDOWS)), help="speckle windows, odd pixels (default %(default)s)"
    )
    p.add_argument("--flow-speed", type=float, default=FLOW_SPEED, help="flow speed, µm/s (default %(default)s)")
    p.add_argument("--polar", type=float, default=FLOW_POLAR_DEG, help="flow polar angle from the beam, deg")
    p.add_argument("--azimuth", type=float, default=FLOW_AZIMUTH_DEG, help="flow azimuth from +x, deg")
    p.add_argument(
        "--ballistic-speed",
        type=float,
        default=None,
        help="random-ballistic speed, µm/s (default: matched to the flow's single-pixel correlation)",
    )
    p.add_argument("--snr-db", type=float, default=None, help="add noise at this SNR (default none)")
    p.add_argument(
        "--seeds",
        type=int,
        default=None,
        help=f"scatterer realisations per protocol (default {SEEDS_FULL}, --quick {SEEDS_QUICK})",
    )
    p.add_argument("--seed", type=int, default=0, help="first rendering seed")
    p.add_argument("--stem", default="protocol", help="file names STEM.json, STEM.csv, ... (default protocol)")
    p.add_argument("--threads", type=int, default=None, metavar="N")
    p.add_argument("--force", action="store_true", help="overwrite existing results")
    p.add_argument("--no-progress", action="store_true")


def _command_line(args) -> str:
    parts = ["python -m classifier.bench.protocol"]
    if args.quick:
        parts.append("--quick")
    if args.spec:
        parts.append(f"--spec {args.spec}")
    if args.like:
        parts.append("--like MAPS")
    for opt, val, default in (
        ("--frames", args.frames, ",".join(map(str, FRAMES))),
        ("--intervals", args.intervals, ",".join(f"{f:g}" for f in INTERVAL_FACTORS)),
        ("--windows", args.windows, ",".join(map(str, WINDOWS))),
        ("--flow-speed", args.flow_speed, FLOW_SPEED),
        ("--polar", args.polar, FLOW_POLAR_DEG),
        ("--azimuth", args.azimuth, FLOW_AZIMUTH_DEG),
        ("--ballistic-speed", args.ballistic_speed, None),
        ("--snr-db", args.snr_db, None),
        ("--seeds", args.seeds, None),
        ("--seed", args.seed, 0),
        ("--stem", args.stem, "protocol"),
    ):
        if val != default:
            parts.append(f"{opt} {val:g}" if isinstance(val, float) else f"{opt} {val}")
    return " ".join(parts + ["--out DIR"])


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m classifier.bench.protocol``: parse ``argv`` and :func:`run`."""
    return run(build_parser().parse_args(argv))


def run(args) -> int:
    """``torchdoct protocol``: check the output first, run the variants, write the files, print the headline."""
    import sys

    from .grid import check_output_dir

    try:
        out = check_output_dir(args.out, args.stem, SUFFIXES, args.force)
        frames = _numbers(args.frames, int, "--frames")
        factors = _numbers(args.intervals, float, "--intervals")
        windows = _numbers(args.windows, int, "--windows")
        variants = (quick_variants if args.quick else full_variants)(frames, factors, windows)
        seeds = args.seeds if args.seeds is not None else (SEEDS_QUICK if args.quick else SEEDS_FULL)
        if args.threads is not None and args.threads < 1:
            raise ValueError(f"--threads must be >= 1; got {args.threads}")
        for name, v in (("--polar", args.polar), ("--azimuth", args.azimuth), ("--snr-db", args.snr_db)):
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number; got {v}")
        if not 0.0 <= args.polar <= 180.0:
            raise ValueError(f"--polar must be within 0-180 deg; got {args.polar:g}")
        if args.like:
            from torchdoct.measured.mapsfile import read_maps

            from ..matching import spec_from_maps

            spec, _ = spec_from_maps([read_maps(p) for p in args.like])
        else:
            from ..features import load_spec

            spec = load_spec(args.spec or "signature-bscan")
        res = run_protocol(
            variants,
            spec,
            flow_speed=args.flow_speed,
            ballistic_speed=args.ballistic_speed,
            polar_deg=args.polar,
            azimuth_deg=args.azimuth,
            seeds=seeds,
            seed=args.seed,
            snr_db=args.snr_db,
            threads=args.threads,
            progress=not args.no_progress,
        )
        res["command"] = _command_line(args)
        written = write_protocol(res, out, force=args.force, stem=args.stem)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for line in headline(res, "rules"):
        print(line)
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

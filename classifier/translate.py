"""Translate DOCT values between OCT systems: what a sample measured on one system would give on another.

The reference paper's finding (§3.3, §4; docs/physics.md §5.3-5.7, §11) is that LIV and OCDS depend on
the system (wavelength, resolutions, frame protocol, refractive index) differently for each motion type,
so values from two systems cannot be compared as they are. The classifier gives, per pixel, the motion
type and its magnitude (D in µm²/s, or the speed in µm/s) with an interval; the simulator gives what any
system measures for that motion. ``torchdoct translate MAPS --to TARGET.toml`` joins the two:

1. **Classify** the source maps (:func:`classifier.infer.classify_maps`; a model with a magnitude head,
   i.e. a signature model): per decided pixel the class ``c``, ``μ`` = log10 of the magnitude and
   ``σ`` = its predictive SD (half the 68 % interval).
2. **Tabulate the target** (:func:`build_table`): for each class, magnitudes on a log grid over the
   model's prior range (:data:`GRID_PER_DECADE` per decade), the target scene (its systems, protocol,
   analysis and ``[noise]``) simulated with ``trials`` pixels per grid point: LIV (dB²) and OCDS (1/s)
   per pixel, the target's own pixel-to-pixel spread included. What the classifier does not measure is
   marginalised over the model's training prior: the flow's polar angle (uniform over 0-90°, the
   ``"uniform-angle"`` law, at :data:`FLOW_ANGLES_DEG`) and azimuth, the random-ballistic direction law
   (both laws, half the trials each), the density (the prior's geometric mean: the same tissue on both
   systems); no static fraction.
3. **Per pixel**, the translated distribution is the mixture of the grid points' samples weighted by
   the Gaussian ``N(μ, σ²)`` in log10 magnitude: its median is the translated value, its 16-84 %
   quantiles the 68 % interval (magnitude uncertainty and the target's speckle spread together, so a
   directly measured target pixel falls inside it about 68 % of the time).

**Where it cannot translate** (NaN, and the code in channel ``translation``, :data:`STATUS`): pixels the
classifier masked (background, NaN or out-of-range features), indeterminate pixels, and pixels whose
magnitude lies outside the motion type's identifiable range on the source system
(:func:`classifier.own_system.identifiable_range`: there the features do not measure the magnitude).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchdoct.runtime.interrupt import progress_disabled

__all__ = [
    "STATUS",
    "GRID_PER_DECADE",
    "FLOW_ANGLES_DEG",
    "Target",
    "load_target",
    "TranslationTable",
    "build_table",
    "translate_maps",
    "mixture_quantiles",
]

#: Codes of the ``translation`` channel.
STATUS = {
    0: "translated",
    1: "masked (background, NaN or out-of-range features)",
    2: "indeterminate",
    3: "magnitude outside the identifiable range of the source system",
}
#: Magnitude grid points per decade of :func:`build_table` (the model's magnitude SD is 0.1-0.2 decades).
GRID_PER_DECADE = 6
#: Flow polar angles (degrees from the depth axis) of the table: the midpoints of four equal bands of
#: 0-90°, the quadrature of the uniform-angle prior the signature models are trained on.
FLOW_ANGLES_DEG = (11.25, 33.75, 56.25, 78.75)
#: Quantiles of the translated value and its 68 % interval.
QUANTILES = (0.5, 0.158655, 0.841345)
_METRICS = ("liv", "ocds")
_UNITS = {"liv": "dB^2", "ocds": "1/s"}


@dataclass(frozen=True)
class Target:
    """The target of a translation: a scene file's systems, protocol, analysis and noise (its populations,
    regions and grid, if any, are not used)."""

    scene: Any  # torchdoct.Scene with one placeholder population
    path: Path

    @property
    def systems(self):
        return self.scene.systems


def load_target(path: str | os.PathLike, system: str | None = None) -> Target:
    """Read ``--to TARGET``: a scene or phantom file, or a shipped one by name; its ``[[system]]`` (all, or
    the one named ``system``), ``[protocol]``, optional ``[analysis]`` (the OCDS delay range, scale and
    estimator) and ``[noise]`` (SNR in dB; none: noise-free). Populations, regions and grid are not used."""
    import dataclasses

    from torchdoct.files import file_or_shipped
    from torchdoct.image.phantom import shipped_phantoms
    from torchdoct.sim.config import read_toml, scene_from_dict
    from torchdoct.sim.scenes import shipped_scenes

    p = file_or_shipped(path, {**shipped_scenes(), **shipped_phantoms()}, "--to")
    if p is None:
        raise FileNotFoundError(
            f"--to {path}: no such file and not a shipped scene or phantom; give a TOML file "
            "with the target's [[system]] and [protocol]"
        )
    p = Path(p)
    data = read_toml(p)
    if not isinstance(data, dict) or "system" not in data or "protocol" not in data:
        raise ValueError(f"--to {p.name}: needs [[system]] and [protocol] tables (the target system and its frames)")
    keep: dict[str, Any] = {
        k: data[k] for k in ("name", "description", "system", "protocol", "noise", "analysis") if k in data
    }
    analysis = dict(keep.get("analysis", {}))
    analysis["metrics"] = list(_METRICS)
    keep["analysis"] = analysis
    keep["population"] = [{"density_per_um3": 0.05}]  # a placeholder: the table sets each population
    try:
        scene = scene_from_dict(keep)
    except (TypeError, ValueError) as err:
        raise ValueError(f"--to {p.name}: {err}") from None
    if system is not None:
        chosen = tuple(s for s in scene.systems if s.name == system)
        if not chosen:
            raise ValueError(
                f"--to-system {system!r}: {p.name} has the systems {', '.join(s.name for s in scene.systems)}"
            )
        scene = dataclasses.replace(scene, systems=chosen)
    return Target(scene=scene, path=p)


@dataclass
class TranslationTable:
    """Simulated target values per class: ``log10_grid[c]`` [K_c] and ``samples[c][metric]`` [K_c, T, S]
    (T pixels per grid point, S target systems)."""

    log10_grid: list[np.ndarray]
    samples: list[dict[str, np.ndarray]]
    system_names: tuple[str, ...]
    meta: dict[str, Any]


def _motions(label: int, magnitude: float):
    """The motions of one grid point and their share of the trials (module docstring, step 2)."""
    import torchdoct as td

    if label == 0:
        return [td.Diffusion(diffusion_um2_per_s=magnitude)]
    if label == 1:
        return [td.RandomBallistic(speed_um_per_s=magnitude, directions=law) for law in ("isotropic", "uniform-angles")]
    return [
        td.Flow(speed_um_per_s=magnitude, polar_angle_deg=a, azimuth_deg=45.0 + 90.0 * i)
        for i, a in enumerate(FLOW_ANGLES_DEG)
    ]


def build_table(
    target: Target,
    prior,
    *,
    trials: int = 128,
    seed: int = 0,
    progress: bool = False,
    classes: Sequence[int] = (0, 1, 2),
) -> TranslationTable:
    """Simulate the target for every class on a log-magnitude grid over ``prior``'s range (module docstring).

    ``prior``: the source model's :class:`classifier.prior.Prior` (its magnitude ranges and density).
    ``trials`` per grid point, split evenly over the direction variants. Seeds: grid point ``k`` of class
    ``c``, variant ``v`` uses ``SeedSequence(seed, spawn_key=(c, k, v))``: the table does not depend on
    the threads or on the other grid points."""
    import dataclasses

    import torchdoct as td
    from torchdoct.sim.metrics import compute_metrics

    density = math.sqrt(prior.density_per_um3[0] * prior.density_per_um3[1])
    grids, samples = [], []
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(
            total=sum(_grid(prior, c).size for c in classes), unit="magnitude", desc="simulate target", delay=1.0
        )
    for c in range(3):
        if c not in classes:
            grids.append(np.zeros(0))
            samples.append({m: np.zeros((0, trials, len(target.systems))) for m in _METRICS})
            continue
        grid = _grid(prior, c)
        out = {m: np.empty((grid.size, trials, len(target.systems))) for m in _METRICS}
        for k, lg in enumerate(grid):
            motions = _motions(c, float(10.0**lg))
            per = [trials // len(motions) + (1 if v < trials % len(motions) else 0) for v in range(len(motions))]
            row = 0
            for v, (motion, n) in enumerate(zip(motions, per)):
                scene = dataclasses.replace(
                    target.scene, populations=(td.Population(name="sample", density_per_um3=density, motion=(motion,)),)
                )
                ss = np.random.SeedSequence(int(seed), spawn_key=(c, k, v))
                res = td.simulate(scene, trials=n, seed=int(ss.generate_state(1, np.uint32)[0]), threads=1)
                met = compute_metrics(res.signals, res.frame_times_s, scene.analysis)
                for m in _METRICS:
                    out[m][k, row : row + n] = met[m].double().numpy()
                row += n
            if bar is not None:
                bar.update(1)
        grids.append(grid)
        samples.append(out)
    if bar is not None:
        bar.close()
    return TranslationTable(
        log10_grid=grids,
        samples=samples,
        system_names=tuple(s.name for s in target.systems),
        meta={
            "trials_per_magnitude": int(trials),
            "seed": int(seed),
            "density_per_um3": density,
            "grid_per_decade": GRID_PER_DECADE,
            "flow_angles_deg": list(FLOW_ANGLES_DEG),
        },
    )


def _grid(prior, label: int) -> np.ndarray:
    lo, hi = (math.log10(v) for v in prior.magnitude_range(label))
    n = max(2, int(math.ceil((hi - lo) * GRID_PER_DECADE)) + 1)
    return np.linspace(lo, hi, n)


def mixture_quantiles(
    mu: np.ndarray,
    sigma: np.ndarray,
    grid: np.ndarray,
    values: np.ndarray,
    quantiles: Sequence[float] = QUANTILES,
    n_levels: int = 512,
) -> np.ndarray:
    """Quantiles ``[len(quantiles), P]`` of per-pixel mixtures: pixel ``p`` weighs grid point ``k`` (log10
    magnitude ``grid[k]``) by ``N(grid[k]; mu[p], sigma[p]²)`` and each grid point contributes its samples
    ``values[k, :]`` (empirical distribution). ``sigma`` is floored at half the grid step (the grid
    resolves no narrower posterior). Linear interpolation of the mixture CDF on ``n_levels`` values."""
    mu = np.asarray(mu, np.float64)
    sigma = np.asarray(sigma, np.float64)
    values = np.asarray(values, np.float64)
    finite = values[np.isfinite(values)]
    out = np.full((len(quantiles), mu.size), np.nan)
    if mu.size == 0 or finite.size == 0:
        return out
    step = float(np.median(np.diff(grid))) if grid.size > 1 else 1.0
    sig = np.maximum(sigma, 0.5 * step)
    levels = np.unique(np.quantile(finite, np.linspace(0.0, 1.0, n_levels)))
    counts = np.isfinite(values).sum(axis=1).clip(min=1)
    cdf_k = np.stack(
        [
            (np.sort(np.where(np.isfinite(v), v, np.inf))[None, :] <= levels[:, None]).sum(1) / n
            for v, n in zip(values, counts)
        ]
    )  # [K, L]
    for lo in range(0, mu.size, 8192):
        sl = slice(lo, lo + 8192)
        w = np.exp(-0.5 * ((grid[None, :] - mu[sl, None]) / sig[sl, None]) ** 2)
        w /= w.sum(axis=1, keepdims=True).clip(min=1e-300)
        cdf = w @ cdf_k  # [P, L]
        for qi, q in enumerate(quantiles):
            j = np.argmax(cdf >= q, axis=1)  # first level reaching q
            j0 = np.maximum(j - 1, 0)
            c0, c1 = cdf[np.arange(cdf.shape[0]), j0], cdf[np.arange(cdf.shape[0]), j]
            t = np.where(c1 > c0, (q - c0) / np.where(c1 > c0, c1 - c0, 1.0), 1.0)
            out[qi, sl] = levels[j0] + np.clip(t, 0.0, 1.0) * (levels[j] - levels[j0])
    return out


def translate_maps(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    target: str | os.PathLike | Target,
    *,
    model=None,
    pool: int = 1,
    min_probability: float | None = None,
    trials: int = 128,
    seed: int = 0,
    threads: int | None = None,
    progress: bool = False,
):
    """Translated maps (:class:`torchdoct.measured.mapsfile.Maps`) of ``paths`` on ``target`` (module docstring).

    Channels per target system ``S``: ``liv@S`` (dB²), ``ocds@S`` (1/s), their 68 % intervals
    ``liv_lower_68@S``, ``liv_upper_68@S``, ``ocds_lower_68@S``, ``ocds_upper_68@S``, and
    ``translation@S`` (:data:`STATUS`). Returns ``(maps, classification)``."""
    import torch

    from torchdoct.measured.mapsfile import Maps

    from .features import spec_from_dict
    from .infer import classify_maps
    from .own_system import identifiable_range
    from .prior import CLASSES, Prior

    tgt = target if isinstance(target, Target) else load_target(target)
    # One class per pixel, by the rule (most probable class above min_probability): a conformal set of two
    # classes has no single target to translate to, and the translation is validated on the rule's
    # decisions (research/results/translation-validation.md).
    res = classify_maps(
        paths,
        model,
        pool=pool,
        min_probability=min_probability,
        threads=threads,
        decision="rule",
        abstain_ambiguous=False,
    )
    mdl = res.model
    if res.magnitude is None:
        raise ValueError(
            f"model {mdl.path.name} has no magnitude head (an LIV/OCDS model); translation needs "
            "the motion magnitude: classify with a signature model (`torchdoct maps --signature`, "
            "or `doct-train --like MAPS`)"
        )
    prior = Prior.from_dict(mdl.metadata["prior"])
    spec = spec_from_dict(mdl.metadata["spec"])
    shape = res.labels.shape
    labels = res.labels.reshape(-1)
    mu = res.magnitude[0].reshape(-1).astype(np.float64)
    sigma = 0.5 * (res.magnitude[2] - res.magnitude[1]).reshape(-1).astype(np.float64)
    status = np.full(labels.size, 1, np.uint8)
    k_classes = len(CLASSES)
    status[labels == k_classes] = 2  # indeterminate (after the motion classes)
    decided = labels < k_classes
    ident = {c: identifiable_range(spec, c, prior) for c in range(k_classes)}
    inside = np.zeros(labels.size, bool)
    for c in range(k_classes):
        lo, hi = (math.log10(v) for v in ident[c])
        inside |= (labels == c) & (mu >= lo) & (mu <= hi)
    status[decided & ~inside] = 3
    status[decided & inside] = 0
    with torch.inference_mode():
        table = build_table(
            tgt,
            prior,
            trials=trials,
            seed=seed,
            progress=progress,
            classes=sorted({int(c) for c in np.unique(labels[status == 0])}),
        )
    planes, names, chans = [], [], []
    for s, system in enumerate(tgt.systems):
        vals = {m: np.full((3, labels.size), np.nan) for m in _METRICS}
        for c in range(k_classes):
            sel = np.flatnonzero((status == 0) & (labels == c))
            if sel.size == 0:
                continue
            for m in _METRICS:
                vals[m][:, sel] = mixture_quantiles(
                    mu[sel], sigma[sel], table.log10_grid[c], table.samples[c][m][:, :, s]
                )
        optics = {
            "wavelength_um": system.wavelength_um,
            "lateral_resolution_um": system.lateral_resolution_um,
            "axial_resolution_um": system.axial_resolution_um,
        }
        for m in _METRICS:
            for q, suffix in ((0, ""), (1, "_lower_68"), (2, "_upper_68")):
                planes.append(vals[m][q])
                names.append(f"{m}{suffix}@{system.name}")
                chans.append(
                    {
                        "name": names[-1],
                        "metric": f"{m}{suffix}",
                        "unit": _UNITS[m],
                        "resolution": system.name,
                        **optics,
                    }
                )
        planes.append(status.astype(np.float64))
        names.append(f"translation@{system.name}")
        chans.append({"name": names[-1], "metric": "translation", "unit": "1", "resolution": system.name, **optics})
    scene = tgt.scene
    src = res.sources
    meta = {
        "axes": "C" + res.axes,
        "pitch_um": res.pitch_um,
        "channels": chans,
        "frame_times_s": [float(t) for t in scene.protocol.times_s],
        "system": {
            "name": tgt.systems[0].name,
            "wavelength_um": tgt.systems[0].wavelength_um,
            "lateral_resolution_um": tgt.systems[0].lateral_resolution_um,
            "axial_resolution_um": tgt.systems[0].axial_resolution_um,
            "refractive_index": tgt.systems[0].refractive_index,
        },
        "ocds_delay_range_s": list(scene.analysis.ocds_delay_range_s),
        "ocds_scale": scene.analysis.ocds_scale,
        "ocds_estimator": scene.analysis.ocds_estimator,
        "source": ", ".join(src),
        "translation": {
            "from": src,
            "to": tgt.path.name,
            "model": mdl.path.name,
            "pool": int(pool),
            "status_codes": {str(k): v for k, v in STATUS.items()},
            "status_counts": {STATUS[k]: int((status == k).sum()) for k in STATUS},
            "identifiable_range_source": {CLASSES[c]: list(ident[c]) for c in ident},
            "noise_snr_db": None if scene.noise is None else scene.noise.snr_db,
            "method": "simulated target per class and log10 magnitude; per pixel the mixture weighted by "
            "the classifier's magnitude posterior: median and 16-84 % quantiles "
            "(classifier.translate)",
            **table.meta,
        },
    }
    stack = np.stack(planes).reshape((len(planes), *shape)).astype(np.float32)
    return Maps(maps=stack, channels=tuple(names), meta=meta), res


# ----------------------------------------------------------------------------------------------
# `torchdoct translate` (registered in the entry-point group torchdoct.commands)

HELP = "translate LIV and OCDS maps to another OCT system (classified motion type and magnitude → simulator)"
DESCRIPTION = (
    "What the sample of MAPS would give on the system of --to: classify every pixel (motion type and "
    "magnitude with its interval), simulate the target system for that motion, and write per pixel the "
    "target's LIV (dB²) and OCDS (1/s) with their 68 % intervals and a translation code (0 translated, "
    "1 masked, 2 indeterminate, 3 magnitude outside the source's identifiable range)."
)


def add_arguments(p) -> None:
    """The options of ``torchdoct translate``."""
    p.add_argument("maps", nargs="+", help="maps file(s) of the source system (from `torchdoct maps --signature`)")
    p.add_argument(
        "--to",
        required=True,
        metavar="TARGET",
        help="the target: a scene or phantom file (or a shipped one's name) whose [[system]], [protocol], "
        "[analysis] and [noise] describe the other system",
    )
    p.add_argument("--to-system", default=None, metavar="NAME", help="only this system of the --to file")
    p.add_argument("--out", required=True, help="output maps file (.npz or .tif)")
    p.add_argument("--model", default=None, help="classifier model (default: as doct-classify chooses)")
    p.add_argument("--pool", type=int, default=1, help="average the features over N × N pixels first (doct-classify)")
    p.add_argument("--min-probability", type=float, default=None, help="the classifier's indeterminate threshold")
    p.add_argument(
        "--trials", type=int, default=128, help="simulated target pixels per class and magnitude (default 128)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    """``torchdoct translate``: check the output first, translate, write, print a summary."""
    from torchdoct.files import check_out
    from torchdoct.measured.mapsfile import MAPS_SUFFIXES, write_maps

    out = check_out(args.out, args.force, MAPS_SUFFIXES, what="--out")
    if isinstance(args.trials, bool) or args.trials < 4:
        raise ValueError(f"--trials must be an integer >= 4; got {args.trials!r}")
    target = load_target(args.to, args.to_system)
    from torchdoct.measured.guards import max_input_bytes
    from torchdoct.runtime.resources import check_classify

    check_classify("torchdoct translate", args.maps, max_input_bytes())  # memory, before anything is read
    maps, res = translate_maps(
        args.maps,
        target,
        model=args.model,
        pool=args.pool,
        min_probability=args.min_probability,
        trials=args.trials,
        seed=args.seed,
        progress=not args.no_progress,
    )
    write_maps(out, maps, force=args.force)
    counts = maps.meta["translation"]["status_counts"]
    print(
        f"model {res.model.path.name}: {res.info['classified']} of {res.info['pixels']} pixels classified; "
        + ", ".join(f"{v} {k}" for k, v in counts.items())
    )
    for name in maps.channels:
        if name.startswith(("liv@", "ocds@")):
            v = maps[name]
            print(
                f"  {name}: median {np.nanmedian(v) if np.isfinite(v).any() else float('nan'):.4g} "
                f"{_UNITS[name.split('@')[0]]}"
            )
    print(f"wrote {out}")
    return 0

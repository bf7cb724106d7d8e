"""Labelled feature vectors simulated with :func:`torchdoct.simulate` from a documented prior.

The package's training data is split by job, in import order: :mod:`classifier.prior` (the prior and
its draws), :mod:`classifier.truth` (the ground truth of a draw), :mod:`classifier.simulation` (one
draw's features) and this module (a split of many draws: :func:`make_dataset`, cached).

**Cache**: a split is stored as ``.npz`` under a key (SHA-256) of the spec, the prior, the seed, the
split, the numbers of draws, replicates and trials, the PSF truncation, the ground-truth definition
and the torchdoct version, and is reused when the key matches.

**Cost**: the simulation of the draws dominates; :attr:`Dataset.meta` records the seconds per split, and
each model's training report the seconds per draw and per simulated trial.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .features import FeatureSpec, load_spec
from .nuisance import edge_static_fractions
from .prior import CLASSES, SPLITS, Prior, draw_parameters
from .simulation import DEFAULT_TRUNCATION, simulate_draw
from .truth import IDENTIFIABILITY_VERSION, STATUS, identifiability

__all__ = [
    "Dataset",
    "default_cache_dir",
    "dataset_key",
    "make_dataset",
]

_ARRAYS = ("x", "y", "draw", "group", "status", "magnitude", "density", "static_fraction", "snr_db", "polar_angle_deg")


@dataclass
class Dataset:
    """One split: features ``x [N, F]`` (float32), motion labels ``y [N]`` and per-sample truth.

    ``draw [N]`` is the draw index and ``group [N]`` the (draw, replicate) index: trials of a group
    share every parameter and are the units that may be pooled. ``status [N]`` indexes
    :data:`classifier.truth.STATUS`; ``magnitude``, ``density`` (moving scatterers), ``static_fraction``, ``snr_db``
    (NaN = no noise) and ``polar_angle_deg`` (flow only, from the depth axis; NaN otherwise) describe
    the sample. Samples with an empty resolution volume at some frame
    (NaN features) are dropped and counted in ``meta["dropped_empty"]``.
    """

    x: np.ndarray
    y: np.ndarray
    draw: np.ndarray
    group: np.ndarray
    status: np.ndarray
    magnitude: np.ndarray
    density: np.ndarray
    static_fraction: np.ndarray
    snr_db: np.ndarray
    #: polar angle of a flow sample's velocity from the depth (beam) axis, degrees; NaN for other
    #: motions (and ``None`` given: unknown, NaN)
    polar_angle_deg: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    #: LIV and OCDS of the same samples at the spec's configurations (signature specs only), ``[N, 2·C]``.
    x_ref: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.polar_angle_deg is None:
            self.polar_angle_deg = np.full(self.y.shape, math.nan)

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def identifiable(self) -> np.ndarray:
        return self.status == 0

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in _ARRAYS}

    def save(self, path: str | os.PathLike) -> None:
        with open(path, "wb") as fh:
            # Any: the names are array names, never savez's options
            contents: dict[str, Any] = {"meta_json": np.asarray(json.dumps(self.meta)), **self.arrays()}
            if self.x_ref is not None:
                contents["x_ref"] = self.x_ref
            np.savez(fh, **contents)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Dataset:
        with np.load(path, allow_pickle=False) as z:
            # splits stored before the polar angle was recorded have none: NaN (unknown)
            arrays = {k: z[k] if k in z.files else np.full(z["y"].shape, math.nan) for k in _ARRAYS}
            meta = json.loads(str(z["meta_json"]))
            x_ref = z["x_ref"] if "x_ref" in z.files else None
        return cls(**arrays, meta=meta, x_ref=x_ref)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/torchdoct/classifier`` (or ``~/.cache/...``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torchdoct" / "classifier"


def dataset_key(
    spec: FeatureSpec,
    prior: Prior,
    seed: int,
    split: str,
    draws: int,
    trials_per_draw: int,
    replicates: int,
    truncation_tolerance: float,
    bulk_phase: bool = False,
    truncation: str = "hard",
) -> tuple[str, dict[str, Any]]:
    """Cache key (hex SHA-256) and the JSON-able description it hashes."""
    import torchdoct

    desc = {
        "spec": spec.to_dict(),
        "prior": prior.to_dict(),
        "seed": int(seed),
        "split": split,
        "draws": int(draws),
        "trials_per_draw": int(trials_per_draw),
        "replicates": int(replicates),
        "truncation_tolerance": float(truncation_tolerance),
        "torchdoct_version": torchdoct.__version__,
        "identifiability": IDENTIFIABILITY_VERSION,
        "format": 3,
    }
    if spec.is_signature:
        desc["signature_extractor"] = _signature_version()
    if bulk_phase:
        desc["bulk_phase"] = "uniform random phase per trial and frame"
    if truncation != "hard":  # (a hard cut: the only mode of the splits stored before there were two)
        desc["truncation"] = truncation
    blob = json.dumps(desc, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest(), desc


def _signature_version() -> str:
    """Hash of the extractor's source: a change of the signature invalidates cached signature splits."""
    import torchdoct.sim.signature as sig

    return hashlib.sha256(Path(sig.__file__).read_bytes()).hexdigest()[:16]


def _positive_int(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive integer; got {v!r}")
    return v


def _check_resources(
    spec: FeatureSpec, split: str, draws: int, trials_per_draw: int, replicates: int, path: Path | None
) -> None:
    """The split's arrays fit in memory twice (the pieces of every draw and their concatenation) and once in
    the cache's folder: :func:`torchdoct.runtime.resources.check_resources`, before any draw is simulated."""
    from torchdoct.runtime.resources import check_resources

    n = draws * replicates * trials_per_draw
    per_sample = (
        4 * spec.n_features + 8 * (len(_ARRAYS) - 1) + (8 * len(spec.configurations) if spec.is_signature else 0)
    )
    check_resources(  # on disk: the finished draws until the split is written, then the split
        f"the {split} split of {spec.name!r}",
        2 * n * per_sample,
        "lower the draws (doct-train --draws-train, --draws-validation, --draws-test), --trials-per-draw or "
        "--replicates",
        detail=f"{n} samples = {draws} draws × {replicates} replicates × {trials_per_draw} trials, "
        f"{per_sample} bytes each, twice while gathered",
        out_path=None if path is None else path.parent,
        out_bytes=2 * n * per_sample,
        out_fix="free disk space there, give another --cache directory, or --no-cache",
    )


def make_dataset(
    spec: FeatureSpec | str,
    prior: Prior | None = None,
    *,
    seed: int = 0,
    split: str = "train",
    draws: int = 300,
    trials_per_draw: int = 64,
    replicates: int = 8,
    truncation_tolerance: float = 1e-2,
    cache_dir: str | os.PathLike | None = None,
    use_cache: bool = True,
    progress: bool = False,
    bulk_phase: bool = False,
    truncation: str = DEFAULT_TRUNCATION,
) -> Dataset:
    """Simulate (or load from the cache) one split of labelled feature vectors.

    ``draws`` parameter draws × ``replicates`` (static fraction, SNR) settings × ``trials_per_draw``
    trials (:func:`classifier.simulation.simulate_draw`). ``truncation_tolerance`` is the simulator's PSF truncation
    (relative amplitude); 1e-2 bounds the relative mean-square field error at 3.6e-4
    (:func:`torchdoct.conventions.truncation_error_bound`) and halves the cost against 1e-3.
    ``bulk_phase``: a random bulk phase per frame (:func:`classifier.simulation.simulate_draw`; a separate cache entry).
    ``truncation``: ``"hard"`` (the amplitude cut to 0 below the tolerance) or ``"taper"`` (a smooth
    window that reaches 0 at the tolerance, so scatterers enter the PSF continuously;
    :func:`torchdoct.conventions.taper_window`): the hard cut at 1e-2 biases the short-lag correlations
    of slow motion, which the signature models read (``torchdoct bench tradeoffs --part fidelity``).
    """
    spec = load_spec(spec)
    prior = prior or Prior()
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}; got {split!r}")
    _positive_int("draws", draws)
    _positive_int("trials_per_draw", trials_per_draw)
    _positive_int("replicates", replicates)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer; got {seed!r}")
    key, desc = dataset_key(
        spec, prior, seed, split, draws, trials_per_draw, replicates, truncation_tolerance, bulk_phase, truncation
    )
    path = None
    if use_cache:
        cdir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        path = cdir / f"{spec.name}-{split}{'-bulk' if bulk_phase else ''}-{key[:16]}.npz"
        if path.exists():
            ds = Dataset.load(path)
            if ds.meta.get("key") == key:
                ds.meta["from_cache"] = True
                return ds
    _check_resources(spec, split, draws, trials_per_draw, replicates, path)
    cols: dict[str, list] = {k: [] for k in _ARRAYS}
    refs: list[np.ndarray] = []
    dropped = 0
    status_counts = dict.fromkeys(STATUS, 0)
    t0 = time.perf_counter()
    from torchdoct.runtime.threads import resolve_threads
    from torchdoct.study.cells import CellCache, CellJob, run_cached, run_cells

    def one(k: int):
        d = draw_parameters(prior, seed, split, k, replicates)
        return simulate_draw(
            spec,
            d,
            prior,
            trials=trials_per_draw,
            truncation_tolerance=truncation_tolerance,
            bulk_phase=bulk_phase,
            truncation=truncation,
        )

    # draws side by side on the usable cores, in threads (the cell runner, torchdoct.study.cells: one
    # torch thread each; every draw has its own seeds, so the dataset does not depend on the number of
    # threads); each finished draw is kept beside the split's cache file until the split is written, so
    # an interrupted run resumes from the draws it finished
    draw_cache = CellCache(None if path is None else path.with_name(f".{path.stem}.draws"))
    jobs = [
        CellJob(key=f"draw-{k}-{hashlib.sha256(f'{key}:{k}'.encode()).hexdigest()[:24]}", payload=k)
        for k in range(draws)
    ]

    def execute(payloads: list, done) -> None:
        run_cells(one, payloads, done=done, workers=resolve_threads(None), one_torch_thread=True)

    results, _ = run_cached(
        jobs,
        cache=draw_cache,
        execute=execute,
        encode=_encode_draw,
        decode=_decode_draw,
        progress=progress,
        desc=f"simulate {spec.name}/{split}",
        unit="draw",
        what="draws of this split",
        final_note=False,
    )
    for k, res in enumerate(results):  # gathered in draw order
        d = draw_parameters(prior, seed, split, k, replicates)
        x, zero = res[0], res[1]
        status, _, _ = identifiability(spec, d, prior)
        status_counts[status] += 1
        edges = d.static_edges or (None,) * len(d.nuisance)
        for r, ((f, snr), e) in enumerate(zip(d.nuisance, edges)):
            if e is not None:  # a static edge: the mean of the configurations' static shares
                f = float(np.mean(edge_static_fractions(spec.configurations, e)))
            keep = ~zero[r] & np.all(np.isfinite(x[r]), axis=1)
            dropped += int((~keep).sum())
            n = int(keep.sum())
            cols["x"].append(x[r][keep])
            if len(res) == 3:
                refs.append(res[2][r][keep])
            cols["y"].append(np.full(n, d.label, np.int64))
            cols["draw"].append(np.full(n, k, np.int64))
            cols["group"].append(np.full(n, k * replicates + r, np.int64))
            cols["status"].append(np.full(n, STATUS.index(status), np.int64))
            cols["magnitude"].append(np.full(n, d.magnitude))
            cols["density"].append(np.full(n, d.density_per_um3))
            cols["static_fraction"].append(np.full(n, f))
            cols["snr_db"].append(np.full(n, snr))
            cols["polar_angle_deg"].append(np.full(n, d.polar_angle_deg if d.label == 2 else math.nan))
    elapsed = time.perf_counter() - t0
    arrays = {k: np.concatenate(v) for k, v in cols.items()}
    arrays["x"] = arrays["x"].astype(np.float32).reshape(-1, spec.n_features)
    meta = {
        "key": key,
        **desc,
        "feature_names": list(spec.feature_names),
        "classes": list(CLASSES),
        "status_names": list(STATUS),
        "draw_status_counts": status_counts,
        "dropped_empty": dropped,
        "elapsed_s": elapsed,
        "seconds_per_draw": elapsed / draws,
        "seconds_per_trial": elapsed / (draws * trials_per_draw),
        "from_cache": False,
    }
    x_ref = np.concatenate(refs).astype(np.float32) if refs else None
    ds = Dataset(**arrays, meta=meta, x_ref=x_ref)
    if path is not None:
        from torchdoct.files import atomic_write

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, ds.save)
        if draw_cache.dir is not None and draw_cache.dir.is_dir():  # the split holds them now
            for k in range(draws):
                draw_cache.path(jobs[k].key).unlink(missing_ok=True)
            try:
                draw_cache.dir.rmdir()
            except OSError:
                pass  # another run's draws are there too
    return ds


def _encode_draw(job, res) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A finished draw's cache entry: its features, empty-volume mask and (signature specs) LIV/OCDS."""
    return {f"a{i}": a for i, a in enumerate(res)}, {"arrays": len(res)}


def _decode_draw(job, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> tuple[np.ndarray, ...]:
    return tuple(arrays[f"a{i}"] for i in range(int(meta["arrays"])))

"""Classify every pixel of DOCT maps with an ONNX motion-type model (numpy, onnxruntime, tifffile; no torch).

:func:`classify_maps` only orchestrates; each step has its own module:

1. **Maps**: one or more maps files, read by the project's one maps reader
   (:func:`torchdoct.measured.mapsfile.read_maps`: ``.npz`` with ``maps``/``channels``/``meta_json``, or
   ``.tif`` with the JSON in the ImageDescription).
2. **Model** (:mod:`classifier.runtime`): an ONNX file written by :mod:`classifier.export`; its metadata
   gives the feature columns (metric + system configuration), the classes, the indeterminate rule and
   the feature spec. Default (:func:`default_model_for`, :mod:`classifier.matching`): a shipped signature
   model whose channels the maps hold (two-wavelength signature, then signature), else the
   single-acquisition LIV/OCDS model.
3. **Matching** (:mod:`classifier.matching`): every model feature found among the channels by metric and
   optics; frame times, OCDS delay range and refractive index checked against the spec.
4. **Mask**: a pixel is classified when all its features are finite and it is not background.
   Background: the ``mean_db`` channel (if present) below ``background_db``; ``"auto"`` = its 99th
   percentile minus 30 dB (the usual DOCT display range), ``None`` = no background mask.
5. **Pooling** (:mod:`classifier.pooling`, optional, ``pool = N``): every feature averaged over the valid
   pixels of the N × N (z, x) neighbourhood of each B-scan (N at most the B-scan's smaller side), with
   the number of independent pixels averaged as the model's ``pool_pixels`` input.
6. **Classification**: onnxruntime on the valid pixels (chunks of :data:`classifier.runtime.CHUNK_ROWS`
   rows), then the rule of :mod:`classifier.rule`; the outputs (:mod:`classifier.outputs`): class map
   values 0…C−1 (the model's classes, ``indeterminate`` last) and :data:`MASKED` for background/NaN
   pixels, per-class probability maps (NaN where masked), magnitude maps for signature models.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from torchdoct.measured import mapsfile

from . import ambiguity, conformal, runtime
from .features import physical_range
from .matching import (
    SIGNATURE_MODEL,
    SIGNATURE_MODELS,
    MapsChannels,
    assemble_features,
    choose_default_model,
    no_shipped_model_message,
)
from .outputs import (
    CLASS_COLORS,
    MAGNITUDE_CHANNELS,
    MASKED,
    OUTPUT_FILES,
    Classification,
    magnitude_maps,
    write_classification,
)
from .pooling import independent_fraction, model_inputs, pool_features
from .rule import REASONS, apply_rule
from .runtime import DEFAULT_MODEL, ClassifierModel

__all__ = [
    "MASKED",
    "DEFAULT_MODEL",
    "DEFAULT_POOL",
    "DEFAULT_BACKGROUND_DB",
    "SIGNATURE_MODEL",
    "SIGNATURE_MODELS",
    "CLASS_COLORS",
    "OUTPUT_FILES",
    "MAGNITUDE_CHANNELS",
    "ClassifierModel",
    "Classification",
    "shipped_models",
    "load_model",
    "read_maps",
    "default_model_for",
    "assemble_features",
    "pool_features",
    "independent_fraction",
    "classify_maps",
    "write_classification",
]

#: Rows per onnxruntime call of the models :func:`load_model` opens (:data:`classifier.runtime.CHUNK_ROWS`).
_CHUNK = runtime.CHUNK_ROWS
_AUTO_RANGE_DB = 30.0
#: ``doct-classify``'s and :func:`classify_maps`'s defaults: no pooling, the automatic background threshold.
DEFAULT_POOL = 1
DEFAULT_BACKGROUND_DB = "auto"


def shipped_models():
    """Names and paths of the models shipped in ``classifier/data/`` (:func:`classifier.runtime.shipped_models`)."""
    return runtime.shipped_models()


def load_model(model: str | os.PathLike | None = None, *, threads: int | None = None) -> ClassifierModel:
    """Open an ONNX model: ``None`` (the shipped default), a shipped name (:func:`shipped_models`), or a
    ``.onnx`` path (:func:`classifier.runtime.load_model`). ``threads``: chunks of pixels classified side
    by side, each on one onnxruntime thread (default: ``$TORCHDOCT_THREADS``, else the usable cores)."""
    return runtime.load_model(model, threads=threads, shipped=shipped_models(), chunk_rows=_CHUNK)


def read_maps(path: str | os.PathLike) -> MapsChannels:
    """A maps file read by the project's maps reader (:func:`torchdoct.measured.mapsfile.read_maps`), seen
    with its channels as metadata dicts (:class:`classifier.matching.MapsChannels`)."""
    return MapsChannels(mapsfile.read_maps(path))


def default_model_for(maps_list) -> tuple[str, str | None]:
    """The shipped model ``doct-classify`` uses without ``--model``, and a note for the user
    (:func:`classifier.matching.choose_default_model` over :func:`shipped_models`)."""
    return choose_default_model(maps_list, shipped_models(), lambda name: load_model(name, threads=1))


def _background(
    mean_db: np.ndarray | None, background_db: str | float | None
) -> tuple[np.ndarray | None, float | None]:
    if mean_db is None or background_db is None or background_db == "none":
        return None, None
    if background_db == "auto":
        finite = mean_db[np.isfinite(mean_db)]
        if finite.size == 0:
            return None, None
        thr = float(np.percentile(finite, 99.0)) - _AUTO_RANGE_DB
    else:
        thr = float(background_db)
        if not math.isfinite(thr):
            raise ValueError(f"background_db must be 'auto', 'none' or a finite dB value; got {background_db!r}")
    with np.errstate(invalid="ignore"):
        return ~(mean_db >= thr), thr


def _check_arguments(pool, min_probability) -> None:
    if isinstance(pool, bool) or not isinstance(pool, (int, np.integer)) or pool < 1:
        raise ValueError(f"pool must be a positive integer (N for N × N neighbourhoods); got {pool!r}")
    if pool % 2 == 0:
        raise ValueError(
            f"pool (--pool) must be odd: an N × N window is centred on its pixel only for odd N (an even "
            f"{pool} centres it half a pixel up and left, shifting every class); give {pool - 1} or "
            f"{pool + 1}"
        )
    if min_probability is not None and not 0.0 <= float(min_probability) < 1.0:
        raise ValueError(f"min_probability must be in [0, 1); got {min_probability!r}")


DECISIONS = ("conformal", "rule")


def _check_alpha(alpha) -> None:
    if alpha is None:
        return
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.floating)) or not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"alpha (--alpha) must be an error level in (0, 1), e.g. 0.1; got {alpha!r}")


def _check_decision(decision: str | None, mdl: ClassifierModel, min_probability, alpha) -> str:
    if decision is None:  # a threshold of the rule given alone asks for the rule
        decision = "conformal" if mdl.calibration is not None and min_probability is None else "rule"
    if decision == "conformal" and min_probability is not None:
        raise ValueError(
            "min_probability (--min-probability) is the threshold of --decision rule; the conformal "
            "decision's knob is alpha (--alpha): give one of them"
        )
    if decision == "rule" and alpha is not None:
        raise ValueError(
            "alpha (--alpha) is the error level of --decision conformal; the rule's knob is "
            "min_probability (--min-probability): give one of them"
        )
    if decision not in DECISIONS:
        raise ValueError(f"decision (--decision) must be one of {', '.join(DECISIONS)}; got {decision!r}")
    if decision == "conformal" and mdl.calibration is None:
        raise ValueError(
            f"model {mdl.path.name} has no calibration ({runtime.calibration_path(mdl.path).name} beside "
            "it): calibrate it (python -m classifier.calibrate --model MODEL) or give --decision rule"
        )
    return decision


def _check_pool(pool: int, maps) -> None:
    z_px, x_px = maps.spatial_shape[-2:]
    if pool > min(z_px, x_px):
        largest = min(z_px, x_px) - 1 + min(z_px, x_px) % 2  # odd, as every pool
        raise ValueError(
            f"{maps.name}: pool {pool} (--pool) is larger than its {z_px} × {x_px} (z × x) "
            f"B-scans: every {pool} × {pool} window would average most of the image and give all pixels "
            f"the same class. The largest valid pool is {largest}"
        )


def _finest_pitch_um(pitch: Any) -> float | None:
    """The finest pixel pitch (µm) of a maps file's ``pitch_um`` (one value or one per axis), or ``None``."""
    values = list(pitch.values()) if isinstance(pitch, dict) else [pitch]
    good = [
        float(v)
        for v in values
        if isinstance(v, (int, float)) and not isinstance(v, bool) and float(v) > 0 and np.isfinite(float(v))
    ]
    return min(good) if good else None


def _footprint_resolutions(confs, pick) -> dict[str, float]:
    """The resolutions (µm) of the footprint :func:`classifier.ambiguity.consensus_window` reads, ``pick`` (``max``:
    the coarsest, ``min``: the finest) over the configurations ``confs``: lateral (x), axial and lateral along y."""
    return {
        "lateral_um": pick(c.lateral_resolution_um for c in confs),
        "axial_um": pick(c.axial_resolution_um for c in confs),
        "lateral_y_um": pick(
            c.lateral_resolution_um if c.lateral_resolution_y_um is None else c.lateral_resolution_y_um for c in confs
        ),
    }


def _finest_configuration(confs) -> str:
    """The name of the configuration with the smallest footprint (the product of its lateral, lateral-y and
    axial resolutions; the first on a tie): rule 9's reference (:func:`classifier.ambiguity.mixed_footprint`)."""

    def area(c) -> float:
        lat_y = c.lateral_resolution_um if c.lateral_resolution_y_um is None else c.lateral_resolution_y_um
        return c.lateral_resolution_um * lat_y * c.axial_resolution_um

    return min(confs, key=area).name


def _spatial_axes(meta: Mapping[str, Any], shape: tuple[int, ...]) -> str:
    """The spatial axes of a maps file (its ``axes`` without the leading channel axis ``C``; ``ZX`` or ``YZX``
    by the map's rank when they are missing or do not match it)."""
    axes = str(meta.get("axes", ""))[1:]
    return axes if len(axes) == len(shape) else {1: "Z", 2: "ZX", 3: "YZX"}.get(len(shape), "")


#: The channels the abstention rules read beside the model's features (classifier.ambiguity).
_RULE_CHANNELS = ("xc_centre_", "xc_peak_", "xc_shift_", "xcd_centre_", "xcd_peak_", "xcd_shift_", "doppler_phase_")


def _either(found) -> tuple[np.ndarray | None, list[str]]:
    """A rule's masks over the speckle families (:data:`classifier.ambiguity.SPECKLE_FAMILIES`), OR-ed, and the
    channels read: ``(None, [])`` where no family's channels are there."""
    mask, used = None, []
    for m, names in found:
        if m is not None:
            mask = m if mask is None else mask | m
            used += names
    return mask, used


def classify_maps(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    model: ClassifierModel | str | None = None,
    *,
    pool: int = DEFAULT_POOL,
    background_db: str | float | None = DEFAULT_BACKGROUND_DB,
    min_probability: float | None = None,
    ignore_refractive_index: bool = False,
    threads: int | None = None,
    decision: str | None = None,
    alpha: float | None = None,
    abstain_ambiguous: bool = True,
) -> Classification:
    """Classify every pixel of one or more maps files (module docstring, steps 1-6).

    ``decision``: ``"conformal"`` (prediction sets at error level ``alpha``, :mod:`classifier.conformal`;
    needs the model's calibration file), ``"rule"`` (the model's indeterminate rule, :mod:`classifier.rule`),
    ``None``: conformal when the model has a calibration, else the rule. ``alpha``: default
    :data:`classifier.conformal.DEFAULT_ALPHA`. ``abstain_ambiguous``: a ``ballistic`` decision becomes
    ``ballistic-or-flow`` where the physics cannot exclude flow (:mod:`classifier.ambiguity`: every B-scan
    pixel; a volume's pixels whose window has not decorrelated), ``flow`` where the speckle pattern
    moved coherently, and ``indeterminate`` where a flow decision rests only on the coarse configurations
    beside another region (rule 7) or on a coarser configuration that decayed faster than the finest (rule 9),
    few pixels of its box share a decision (rule 6) or one in ten of its finest footprint holds an outcome that
    excludes it (rule 8), and, pooled over 5 pixels or more, where a ``diffusion`` decision's finest footprint
    decays faster in shape at a coarser configuration (rule 12)."""
    t0 = time.perf_counter()
    _check_arguments(pool, min_probability)
    _check_alpha(alpha)
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    maps_list = [mapsfile.read_maps(p) for p in paths]
    choice_note = None
    chosen = model is None
    if chosen:
        model, choice_note = default_model_for(maps_list)
    mdl = model if isinstance(model, ClassifierModel) else load_model(model, threads=threads)
    decision = _check_decision(decision, mdl, min_probability, alpha)
    _check_pool(pool, maps_list[0])
    t_read = time.perf_counter()
    try:
        feats, mean_db, info = assemble_features(maps_list, mdl, ignore_refractive_index=ignore_refractive_index)
    except ValueError as err:
        if not chosen:
            raise
        raise ValueError(no_shipped_model_message(maps_list, str(err))) from None
    info["model_choice"] = choice_note
    # a pixel is finite iff the float64 sum of its features is (NaN and ±inf propagate; finite float32
    # values cannot overflow a float64 sum): one pass instead of a boolean array per feature
    finite = np.isfinite(feats.sum(axis=0, dtype=np.float64))
    # a feature outside the values a real sequence can give (classifier.features.physical_range): corrupt
    # input the network never saw; masked like a non-finite pixel, and counted
    lo, hi = (
        np.array(b, np.float32)[:, None, ...]
        for b in zip(*(physical_range(col["metric"], mdl.spec.n_frames) for col in mdl.columns[:-1]))
    )
    flat = feats.reshape(len(feats), -1)
    outside = (np.any((flat < lo) | (flat > hi), axis=0) & finite.reshape(-1)).reshape(finite.shape)
    finite &= ~outside
    bg, thr = _background(mean_db, background_db)
    valid = finite if bg is None else finite & ~bg
    meta0 = maps_list[0].meta
    frac = independent_fraction(int(pool), meta0.get("pitch_um"), mdl.spec)
    x, idx = model_inputs(feats, valid, int(pool), frac, mdl.pool_pixels_max)
    t_feat = time.perf_counter()
    probs, mag_mean, mag_sd = mdl.predict_all(x)
    t_onnx = time.perf_counter()
    labels_flat, reasons = apply_rule(probs, mdl.classes, mdl.rule, min_probability)
    set_names: list[str] = []
    conformal_info = None
    if decision == "conformal":
        cal = mdl.calibration
        assert cal is not None  # _check_decision refuses the conformal decision without a calibration
        a = conformal.DEFAULT_ALPHA if alpha is None else float(alpha)
        mode = cal.get("mode", conformal.MODES[0])
        labels_flat, set_size = conformal.decide(probs, x[:, -1], mdl.classes, cal, a, mode)
        set_names = conformal.set_label_names(mdl.classes)
        conformal_info = {
            "alpha": a,
            "score": cal["score"],
            "mode": mode,
            "thresholds": {
                str(p["pool_pixels"]): dict(
                    zip(mdl.classes, map(float, conformal.pool_thresholds(p, len(mdl.classes), a, mode)))
                )
                for p in cal["pools"]
            },
            "set_sizes": {str(k): int((set_size == k).sum()) for k in range(len(mdl.classes) + 1)},
            "guarantee": cal.get("guarantee"),
        }
    shape = valid.shape
    ambiguity_info = None
    if abstain_ambiguous:
        if not set_names:
            set_names = conformal.set_label_names(mdl.classes)
        channels = {c: m.maps[i] for m in maps_list for i, c in enumerate(m.channels) if c.startswith(_RULE_CHANNELS)}
        axes = _spatial_axes(meta0, shape)
        extent = dict(zip(axes.lower(), shape))
        single = ambiguity.single_pixel_axes(extent)
        founding = {} if ambiguity.line_windows(extent) else channels  # one A-line: rules 0, 5, 10 found nothing
        coherent, coherent_source = _either(
            ambiguity.coherent_motion(founding, idx, mdl.spec.n_frames, family=f) for f in ambiguity.SPECKLE_FAMILIES
        )
        doppler_window = max(int(pool), ambiguity.DOPPLER_WINDOW_MIN)
        doppler, doppler_source = ambiguity.doppler_drift(founding, idx, doppler_window)
        corr, source = ambiguity.slow_decorrelation(
            {c: v for c, v in channels.items() if c.startswith("xc_centre_")}, mdl.columns, x, idx, mdl.spec.n_frames
        )
        fast, fast_source = ambiguity.fast_decorrelation(channels, idx)
        reference, reference_source = ambiguity.phase_reference(channels, idx)
        pitch = _finest_pitch_um(meta0.get("pitch_um"))
        moved, moved_source = ambiguity.offset_moved(channels, pitch, idx, mdl.spec.n_frames)
        pitches = meta0.get("pitch_um")
        spk = meta0.get("speckle")
        window = spk.get("window_px") if isinstance(spk, dict) else None
        translation, translation_source = _either(
            ambiguity.translated(
                founding,
                pitches if isinstance(pitches, dict) else None,
                idx,
                window if isinstance(window, int) and not isinstance(window, bool) else None,
                family=f,
            )
            for f in ambiguity.SPECKLE_FAMILIES
        )
        confs = mdl.spec.configurations
        optics = next(
            (m.optics(c) for m in maps_list for c in m.channels if c.startswith("xc_centre_")), None
        )  # the speckle channels' resolution
        unseen = ambiguity.unseen_axes(
            axes,
            pitches if isinstance(pitches, dict) else None,
            None if optics is None else optics.lateral_resolution_um,
            None if optics is None else optics.axial_resolution_um,
            None if optics is None else optics.lateral_y_um,
            extent,
        )
        box_pitch = pitches if isinstance(pitches, dict) else None
        coarsest, finest = _footprint_resolutions(confs, max), _footprint_resolutions(confs, min)
        consensus = ambiguity.consensus_window(axes, box_pitch, int(pool), **coarsest)
        footprint_box = ambiguity.consensus_window(
            axes, box_pitch, int(pool), reach=ambiguity.FOOTPRINT_REACH, **coarsest
        )
        fine_box = ambiguity.consensus_window(axes, box_pitch, int(pool), **finest)
        names_all = list(mdl.classes) + set_names
        labels_flat, changed = ambiguity.abstain_where_ambiguous(
            labels_flat,
            names_all,
            unseen_axis=bool(unseen),
            correlation=corr,
            coherent=coherent,
            fast=fast,
            moved=moved,
            translation=translation,
            doppler=doppler,
            reference=reference,
        )
        borrowed = ambiguity.borrowed_flow(
            labels_flat,
            names_all,
            idx,
            shape,
            footprint_box,
            coherent=coherent,
            translation=translation,
            doppler=doppler,
        )
        labels_flat = np.where(borrowed, mdl.classes.index("indeterminate"), labels_flat)
        changed["borrowed_flow"] = int(borrowed.sum())
        finest_conf = _finest_configuration(confs)
        mixed, _ = ambiguity.mixed_footprint(
            labels_flat,
            names_all,
            mdl.columns,
            x,
            finest_conf,
            coherent=coherent,
            translation=translation,
            doppler=doppler,
        )
        labels_flat = np.where(mixed, mdl.classes.index("indeterminate"), labels_flat)
        changed["mixed_footprint"] = int(mixed.sum())
        alone = ambiguity.unshared(labels_flat, names_all, idx, shape, consensus)
        against = ambiguity.contradicted(labels_flat, names_all, idx, shape, fine_box) & ~alone
        labels_flat = np.where(alone | against, mdl.classes.index("indeterminate"), labels_flat)
        changed["unshared"] = int(alone.sum())
        changed["contradicted"] = int(against.sum())
        shape_mixed, _ = ambiguity.mixed_shape(
            labels_flat,
            names_all,
            idx,
            shape,
            fine_box,
            ambiguity.shape_excess(mdl.columns, x, finest_conf)
            if int(pool) >= ambiguity.MIXED_SHAPE_POOL_MIN
            else None,
            int(pool),
        )
        labels_flat = np.where(shape_mixed, mdl.classes.index("indeterminate"), labels_flat)
        changed["mixed_shape"] = int(shape_mixed.sum())
        ambiguity_info = {
            "rules": (["coherent_motion"] if coherent is not None else [])
            + (["translation"] if translation is not None else [])
            + (["doppler_drift"] if doppler is not None else [])
            + (["bscan_plane"] if unseen else ["sheared_flow"])
            + (["slow_decorrelation"] if corr is not None else [])
            + (["fast_decorrelation"] if fast is not None and not unseen else [])
            + (["offset_moved"] if moved is not None else [])
            + ["borrowed_flow", "mixed_footprint"]
            + ["unshared", "contradicted"]
            + (["mixed_shape"] if int(pool) >= ambiguity.MIXED_SHAPE_POOL_MIN else []),
            "unseen_axes": unseen,
            "single_pixel_axes": single,
            "neighbour_correlation_min": ambiguity.NEIGHBOUR_CORRELATION_MIN,
            "coherent_channels": coherent_source,
            "coherent_peak_min": ambiguity.COHERENT_PEAK_MIN,
            "coherent_moved_min": ambiguity.COHERENT_MOVED_MIN,
            "correlation": source,
            "decorrelated_below": ambiguity.DECORRELATED_BELOW,
            "fast_channels": fast_source,
            "fast_remaining_max": ambiguity.FAST_REMAINING_MAX,
            "offset_channels": moved_source,
            "offset_first_min_pitch": ambiguity.OFFSET_FIRST_MIN,
            "offset_growth_min_pitch": ambiguity.OFFSET_GROWTH_MIN,
            "offset_hold_min": ambiguity.OFFSET_HOLD_MIN,
            "translation_channels": translation_source,
            "doppler_channels": doppler_source,
            "reference_channels": reference_source,
            "reference_share": float(np.mean(reference)) if len(reference) else 0.0,
            "doppler_im_min": ambiguity.DOPPLER_IM_MIN,
            "doppler_window_px": doppler_window,
            "translation_hold_min": ambiguity.TRANSLATION_HOLD_MIN,
            "translation_growth_min_pitch": ambiguity.TRANSLATION_GROWTH_MIN,
            "translation_linear_max_pitch": ambiguity.TRANSLATION_LINEAR_MAX,
            "translation_window_min_px": ambiguity.TRANSLATION_WINDOW_MIN,
            "footprint_flow_min": ambiguity.FOOTPRINT_FLOW_MIN,
            "footprint_reach": ambiguity.FOOTPRINT_REACH,
            "footprint_window_px": dict(zip(axes.lower(), footprint_box)),
            "mixed_decay_min": ambiguity.MIXED_DECAY_MIN,
            "finest_configuration": finest_conf,
            "consensus_min": ambiguity.CONSENSUS_MIN,
            "consensus_window_px": dict(zip(axes.lower(), consensus)),
            "contradicted_min": ambiguity.CONTRADICTED_MIN,
            "fine_window_px": dict(zip(axes.lower(), fine_box)),
            "mixed_shape_min": ambiguity.MIXED_SHAPE_MIN,
            "mixed_shape_pool_min": ambiguity.MIXED_SHAPE_POOL_MIN,
            "shape_floor": ambiguity.SHAPE_FLOOR,
            "changed_pixels": changed,
        }
    labels = np.full(valid.size, MASKED, np.uint8)
    labels[idx] = labels_flat.astype(np.uint8)
    pmaps = np.full((len(mdl.classes), valid.size), np.nan, np.float32)
    pmaps[:, idx] = probs.T
    magnitude = (
        None if mag_mean is None or mag_sd is None else magnitude_maps(labels_flat, mag_mean, mag_sd, idx, shape)
    )
    t_end = time.perf_counter()
    n_pix = int(valid.size)
    background = bg if bg is not None else np.zeros(shape, bool)
    info.update(
        {
            "pixels": n_pix,
            "classified": int(idx.size),
            "pool": int(pool),
            "decision": decision,
            "pool_independent_fraction": frac,
            "background_db_threshold": thr,
            "nan_pixels": int((~finite).sum() - outside.sum()),
            "out_of_range_pixels": int(outside.sum()),
            "background_pixels": int((background & finite).sum()),
            # the rule's reasons (the conformal decision has its set sizes under "conformal")
            "indeterminate_reasons": (
                {r: int((reasons == i).sum()) for i, r in enumerate(REASONS)} if decision == "rule" else None
            ),
            "min_probability": float(mdl.rule["min_probability"] if min_probability is None else min_probability),
            "conformal": conformal_info,
            "ambiguity": ambiguity_info,
            "seconds": {
                "read": t_read - t0,
                "features": t_feat - t_read,
                "onnxruntime": t_onnx - t_feat,
                "rule": t_end - t_onnx,
                "total": t_end - t0,
            },
            "pixels_per_s": n_pix / max(t_end - t_read, 1e-12),
        }
    )
    axes = _spatial_axes(meta0, shape)
    return Classification(
        labels=labels.reshape(shape),
        probabilities=pmaps.reshape((len(mdl.classes), *shape)),
        classes=mdl.classes,
        mask=valid,
        background=background,
        intensity_db=mean_db,
        model=mdl,
        sources=[m.name for m in maps_list],
        axes=axes,
        pitch_um=meta0.get("pitch_um"),
        info=info,
        magnitude=magnitude,
        set_labels=set_names,
    )

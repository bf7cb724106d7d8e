"""Maps ↔ spec: the model's feature columns found among the channels of maps files, the protocol checks,
and the default model for a set of maps (numpy only; no torch).

Every model feature (column) must match a maps channel by its metric and its optics
(:meth:`torchdoct.optics.ChannelOptics.matches`, within 1e-6 relative; the channel's optics from the maps
metadata, :meth:`torchdoct.measured.mapsfile.Maps.optics`); the frame times and the OCDS delay range must
be the spec's; the system's refractive index must be the spec's. Anything missing or mismatched is a
``ValueError`` naming it and the fix.

B-scan maps reduced laterally (``reduction.lateral_axes == "X"``) have channels whose PSF is wider along
x than along y. :data:`MATCH_LATERAL_Y` says whether the match compares the y width too: it does, so a
model trained on isotropic reductions (volumes) is never applied to B-scan maps, nor a B-scan model
to volumes; the error names the model, or the ``doct-train`` command, that fits the maps. The shipped
B-scan specs (``*-bscan``) give their lateral-reduced configuration ``lateral_resolution_y_um``.

Models that read the field's phase (:attr:`FeatureSpec.needs_field`: ``g1_m``, ``g1_phase_m``,
``phase_ramp``) are applied only to maps whose metadata say the bulk phase was corrected
(``meta["bulk_phase"]``, written by ``torchdoct maps --bulk-phase``): a bulk phase per frame
destroys those features (:mod:`torchdoct.sim.signature`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from torchdoct.measured.mapsfile import Maps
from torchdoct.optics import ChannelOptics
from torchdoct.sim import signature as _signature

from .features import METRIC_UNITS, FeatureSpec, metric_unit, same_value
from .runtime import DEFAULT_MODEL, ClassifierModel

__all__ = [
    "spec_from_maps",
    "no_shipped_model_message",
    "MATCH_LATERAL_Y",
    "SIGNATURE_MODEL",
    "SIGNATURE_MODELS",
    "ALINE_MODEL",
    "LIV_OCDS_MODELS",
    "MapsChannels",
    "column_optics",
    "channel_matches",
    "assemble_features",
    "bscan_notes",
    "choose_default_model",
]

#: Whether a model column matches a channel only when their lateral widths along y agree too: True, so a
#: B-scan channel reduced along x only (18 × 4.9 µm) never feeds a column trained on an isotropic PSF
#: (18 × 18 µm) and the reverse. False would match on x alone, with a note (:func:`bscan_notes`).
MATCH_LATERAL_Y = True
#: Shipped model used by default when the maps hold its (signature) channels.
SIGNATURE_MODEL = "signature"
#: The A-line signature model: the signature without a lateral-reduced configuration (one A-line's time series).
ALINE_MODEL = "signature-aline"
#: Shipped signature models ``doct-classify`` prefers without ``--model``, in this order: the first whose
#: every channel the maps hold (``torchdoct maps --signature``; the two-wavelength one reads the maps of
#: both bands, one file or two), and, for a model that reads the phase, whose maps are bulk-phase
#: corrected. A model that is not shipped is skipped. The A-line model (no lateral-reduced configuration) comes
#: last: it fits maps that cannot hold a lateral reduction (one A-line) or were computed without one.
SIGNATURE_MODELS = (
    "two-wavelength-signature",
    "signature-bscan-field",
    "signature-bscan",
    SIGNATURE_MODEL,
    ALINE_MODEL,
)
#: LIV/OCDS models for maps without signature channels, in this order (B-scan maps: the first).
LIV_OCDS_MODELS = ("single-acquisition-bscan", DEFAULT_MODEL)


@dataclass(frozen=True)
class MapsChannels:
    """The classifier's view of one :class:`~torchdoct.measured.mapsfile.Maps`: its channels as their
    metadata dicts (``channels``), the stack (``data``), the metadata, the file. It reads nothing: the
    maps format has one owner, :mod:`torchdoct.measured.mapsfile`."""

    maps: Maps

    @property
    def path(self) -> Path:
        return self.maps.path if self.maps.path is not None else Path(self.maps.name)

    @property
    def data(self) -> np.ndarray:
        return self.maps.maps

    @property
    def channels(self) -> list[dict[str, Any]]:
        return self.maps.channel_meta

    @property
    def meta(self) -> dict[str, Any]:
        return self.maps.meta

    @property
    def spatial_shape(self) -> tuple[int, ...]:
        return self.maps.spatial_shape


def _as_maps(m: Maps | MapsChannels) -> Maps:
    return m.maps if isinstance(m, MapsChannels) else m


def column_optics(col: Mapping[str, Any]) -> ChannelOptics:
    """The optics of a model's input column (its metadata: wavelength and resolutions, µm)."""
    y = col.get("lateral_resolution_y_um")
    return ChannelOptics(
        float(col["wavelength_um"]),
        float(col["lateral_resolution_um"]),
        float(col["axial_resolution_um"]),
        None if y is None else float(y),
    )


def channel_matches(maps: Maps, i: int, metric: str, optics: ChannelOptics) -> bool:
    """True when channel ``i`` of ``maps`` is ``metric`` with ``optics`` (:data:`MATCH_LATERAL_Y`)."""
    if maps.meta["channels"][i].get("metric") != metric:
        return False
    have = maps.optics(i)
    return have is not None and optics.matches(have, lateral_y=MATCH_LATERAL_Y)


def _describe_channel(ch: dict[str, Any]) -> str:
    def g(k):
        v = ch.get(k)
        return f"{v:g}" if isinstance(v, (int, float)) else "?"

    return (
        f"{ch.get('name', ch.get('metric'))} ({g('wavelength_um')} µm, lateral {g('lateral_resolution_um')} µm, "
        f"axial {g('axial_resolution_um')} µm)"
    )


def _check_protocol(maps: Maps, spec: FeatureSpec, ignore_refractive_index: bool) -> None:
    name = maps.name
    times = maps.meta.get("frame_times_s")
    if not isinstance(times, list) or len(times) < 2:
        raise ValueError(
            f"{name}: meta has no 'frame_times_s'; the model needs {spec.n_frames} frames "
            f"{spec.frame_interval_s} s apart"
        )
    t = np.asarray(times, dtype=np.float64)
    d = np.diff(t)
    if len(t) != spec.n_frames or not all(same_value(x, spec.frame_interval_s) for x in d):
        raise ValueError(
            f"{name}: maps were computed from {len(t)} frames at intervals {d.min():g}-{d.max():g} s, "
            f"but the model was trained for {spec.n_frames} frames {spec.frame_interval_s} s apart "
            "(fix: train a model with this protocol in its spec)"
        )
    rng = maps.meta.get("ocds_delay_range_s")
    if rng is None or len(rng) != 2 or not all(same_value(a, b) for a, b in zip(rng, spec.ocds_delay_range_s)):
        raise ValueError(
            f"{name}: OCDS delay range {rng} s differs from the model's "
            f"{list(spec.ocds_delay_range_s)} s (fix: recompute the maps with that range)"
        )
    system = maps.meta.get("system") or {}
    n = system.get("refractive_index")
    n = 1.0 if n is None else n  # not recorded: the paper's n = 1
    if not ignore_refractive_index and not same_value(float(n), spec.refractive_index):
        raise ValueError(
            f"{name}: system refractive_index {n} but the model was trained for "
            f"{spec.refractive_index} (phase rates scale with n; fix: train a model whose spec has "
            f"refractive_index = {n}, or pass --ignore-refractive-index)"
        )


def _find_column(maps_list: Sequence[Maps], col: Mapping[str, Any]) -> tuple[Maps, int] | None:
    """The first channel (file order, then channel order) matching the column, or None."""
    optics = column_optics(col)
    for m in maps_list:
        for i in range(len(m.channels)):
            if channel_matches(m, i, col["metric"], optics):
                return m, i
    return None


def _refuse_other_geometry(maps_list: Sequence[Maps], col: Mapping[str, Any], model: ClassifierModel) -> None:
    """A column that a channel matches on x but not along y: B-scan maps and a volume model, or the
    reverse. Raise naming the model (or the ``doct-train`` command) that fits the maps."""
    optics = column_optics(col)
    for m in maps_list:
        for i, ch in enumerate(m.meta["channels"]):
            have = m.optics(i)
            if ch.get("metric") != col["metric"] or have is None or not optics.matches(have, lateral_y=False):
                continue
            bscan = not have.isotropic
            want = _counterpart(model.spec.name, bscan)
            kind = "B-scan maps (lateral resolution reduced along x only)" if bscan else "volume maps (isotropic)"
            raise ValueError(
                f"{m.name}: channel {ch.get('name')!r} has {have.describe()}: {kind}, but model "
                f"{model.path.name} was trained on {optics.describe()}. Fix: {_train_hint(want, model.spec.name)}"
            )


def _counterpart(name: str, bscan: bool) -> str:
    """The spec of the other geometry: ``NAME-bscan`` for B-scan maps, ``NAME`` without ``-bscan`` for volumes."""
    if bscan:
        return name if "-bscan" in name else f"{name}-bscan"
    return name.replace("-bscan", "")


def _train_hint(want: str, have: str) -> str:
    from .features import shipped_specs
    from .runtime import shipped_models

    if want in shipped_models():
        return f"classify with the model trained on this geometry (--model {want})"
    if want in shipped_specs():
        return f"train the model of this geometry: `doct-train --spec {want} --out DIR`, then --model DIR"
    return (
        f"train a model for this geometry from a spec like classifier/specs/{have}.toml with the lateral "
        "widths of these channels (lateral_resolution_y_um): `doct-train --spec SPEC.toml --out DIR`"
    )


def bscan_notes(maps_list: Sequence[Maps], spec: FeatureSpec) -> list[str]:
    """For B-scan maps reduced laterally along x only: which of the spec's configurations their channels
    hold with another width along y than the spec's (the original width: an anisotropic PSF,
    :meth:`ChannelOptics.of_channel`), unlike the spec's isotropic training. A spec that gives that
    ``lateral_resolution_y_um`` was trained on it: no note."""
    notes: list[str] = []
    if MATCH_LATERAL_Y:  # such channels are refused, not noted
        return notes
    for m in maps_list:
        reduced = []
        for c in spec.configurations:
            seen = ChannelOptics.of_channel(c.to_dict(), m.meta)
            assert seen is not None  # a configuration holds its wavelength and both resolutions
            if not c.optics.matches(seen):
                reduced.append(c)
        if reduced:
            notes.append(
                f"{m.name}: the lateral resolution was reduced along x only (B-scan data), so the "
                f"{', '.join(c.name for c in reduced)} channels keep the original width along y, unlike "
                "the model's isotropic training; expect lower accuracy than the report (volumes are "
                "reduced isotropically)"
            )
    return notes


def assemble_features(
    maps_list: Sequence[Maps | MapsChannels], model: ClassifierModel, *, ignore_refractive_index: bool = False
) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """Model features ``[F, *S]`` from the channels of one or more maps files, and the intensity map.

    Returns ``(features, mean_db or None, info)``; ``info`` names the channel used for every feature.
    """
    all_maps = [_as_maps(m) for m in maps_list]
    if not all_maps:
        raise ValueError("no maps file given")
    spec = model.spec
    shape = all_maps[0].spatial_shape
    for m in all_maps:
        if m.spatial_shape != shape:
            raise ValueError(
                f"maps files have different shapes: {all_maps[0].name} {shape}, {m.name} {m.spatial_shape}"
            )
        _check_protocol(m, spec, ignore_refractive_index)
    intensity_only = any((m.meta.get("signature") or {}).get("intensity_only") for m in all_maps)
    if spec.needs_field and not intensity_only:  # (intensity-only maps: the missing columns say so below)
        uncorrected = [m.name for m in all_maps if not m.meta.get("bulk_phase")]
        if uncorrected:
            raise ValueError(
                f"model {model.path.name} reads the field's phase (|g1|), which a bulk phase per frame "
                f"destroys, but {', '.join(uncorrected)} were not bulk-phase corrected. Fix: compute the "
                "maps with `torchdoct maps DATA --bulk-phase weighted-mean --signature ...` (phase-stable "
                "data too), or classify with an intensity-only model (--model signature-bscan or "
                "--model signature)"
            )
    feats = []
    used = []
    for col in model.columns[:-1]:
        metric = col["metric"]
        found = _find_column(all_maps, col)
        if (
            found is None
            and any((m.meta.get("signature") or {}).get("intensity_only") for m in all_maps)
            and metric not in METRIC_UNITS
            and _signature.needs_field(metric)
        ):
            raise ValueError(
                f"model {model.path.name} needs the complex field's phase ({col['name']!r}), but the maps "
                "were computed from intensity-only data, which give only the intensity part of the "
                "signature. Fix: compute the maps from the complex data, or classify with the LIV/OCDS "
                f"model (--model {DEFAULT_MODEL})"
            )
        if found is None:
            _refuse_other_geometry(all_maps, col, model)
            have = "; ".join(
                f"{m.name}: " + ", ".join(_describe_channel(ch) for ch in m.meta["channels"]) for m in all_maps
            )
            res = col["configuration"]
            raise ValueError(
                f"maps lack the model feature {col['name']!r}: {metric} at {col['wavelength_um'] * 1000:g} nm, "
                f"lateral {col['lateral_resolution_um']:g} µm, axial {col['axial_resolution_um']:g} µm. Channels "
                f"present in {have}. Fix: compute it, e.g. `torchdoct maps DATA --resolution {res} ...`, or give "
                "the maps of the other wavelength as a second file"
            )
        m, i = found
        ch = m.meta["channels"][i]
        unit = ch.get("unit")
        if unit is not None and unit != metric_unit(metric):
            raise ValueError(
                f"{m.name}: channel {ch.get('name')!r} has unit {unit!r}; the model expects {metric_unit(metric)!r}"
            )
        feats.append(m.maps[i])
        used.append({"feature": col["name"], "file": m.name, "channel": ch.get("name", str(i))})
    mean_db = None
    first = spec.configurations[0].optics
    candidates = [(m, i) for m in all_maps for i, ch in enumerate(m.meta["channels"]) if ch.get("metric") == "mean_db"]
    candidates.sort(key=lambda t: 0 if channel_matches(t[0], t[1], "mean_db", first) else 1)
    if candidates:
        m, i = candidates[0]
        mean_db = m.maps[i]
    info = {
        "features": used,
        "intensity_channel": candidates[0][0].meta["channels"][candidates[0][1]].get("name") if candidates else None,
        "notes": bscan_notes(all_maps, spec),
    }
    return np.stack(feats).astype(np.float32, copy=False), mean_db, info


def choose_default_model(
    maps_list: Sequence[Maps | MapsChannels], shipped: Mapping[str, Path], open_model: Callable[[str], ClassifierModel]
) -> tuple[str, str | None]:
    """The shipped model ``doct-classify`` uses without ``--model``, and a note for the user.

    The first model of :data:`SIGNATURE_MODELS` in ``shipped`` whose every feature the maps hold (each
    opened with ``open_model(name)``), else :data:`DEFAULT_MODEL` (LIV/OCDS), saying why (for maps with
    signature channels: what the signature model closest to them, the one with the fewest missing
    features other than the A-line model, lacks).
    """
    all_maps = [_as_maps(m) for m in maps_list]
    candidates = [name for name in SIGNATURE_MODELS if name in shipped]
    liv_ocds = _liv_ocds_model(all_maps, shipped, open_model)
    if not candidates:
        return liv_ocds, None
    if not any(m.meta.get("signature") for m in all_maps):
        return liv_ocds, (
            f"model {liv_ocds} (LIV/OCDS): the maps have no signature channels; "
            "`torchdoct maps DATA --signature ...` lets doct-classify use the more accurate "
            "signature models"
        )
    failed = []
    for name in candidates:
        sig = open_model(name)
        try:
            assemble_features(all_maps, sig, ignore_refractive_index=True)
        except ValueError as err:
            missing = [col for col in sig.columns[:-1] if _find_column(all_maps, col) is None]
            failed.append((len(missing), name, err, missing, len(sig.columns) - 1))
            continue
        return name, None
    # the closest: fewest missing features (ties: the earlier in SIGNATURE_MODELS); the A-line model's features
    # are a subset of the others', so it is named only when it is the one signature model shipped
    ranked = [f for f in failed if f[1] != ALINE_MODEL] or failed
    _, name, error, missing, n_columns = min(ranked, key=lambda f: f[0])
    if missing:  # name the channels, not only the first error
        names = [str(col.get("name") if isinstance(col, dict) else col) for col in missing]
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        why = f"{error} (missing channel(s): {', '.join(names[:3])}{more}, {len(names)} of {n_columns})"
    else:
        why = str(error)
    return liv_ocds, f"model {liv_ocds} (LIV/OCDS) instead of {name}: {why}"


def _liv_ocds_model(
    maps_list: Sequence[Maps], shipped: Mapping[str, Path], open_model: Callable[[str], ClassifierModel]
) -> str:
    """The first of :data:`LIV_OCDS_MODELS` that is shipped and whose every column the maps hold (B-scan
    maps: the B-scan model), else :data:`DEFAULT_MODEL` (whose error then says what is missing)."""
    for name in LIV_OCDS_MODELS:
        if name not in shipped:
            continue
        model = open_model(name)
        if all(_find_column(maps_list, col) is not None for col in model.columns[:-1]):
            return name
    return DEFAULT_MODEL


def _frame_protocol(maps: Maps) -> tuple[int, float]:
    """``(n_frames, frame_interval_s)`` of the maps' uniform frame times, or ``ValueError`` naming the fix."""
    times = maps.meta.get("frame_times_s")
    if not isinstance(times, list) or len(times) < 4:
        raise ValueError(
            f"{maps.name}: the metadata hold no frame times of at least 4 frames ('frame_times_s'), "
            "which a model's protocol needs. Fix: recompute the maps with --frame-interval-s "
            "or --frame-times-s"
        )
    t = np.asarray(times, dtype=np.float64)
    d = np.diff(t)
    if not np.all(np.isfinite(d)) or d.min() <= 0 or d.max() - d.min() > 1e-6 * d.max():
        raise ValueError(
            f"{maps.name}: frame intervals {d.min():g}-{d.max():g} s are not uniform; the signature "
            "and the trained protocol need one frame interval"
        )
    return len(t), float(f"{np.mean(d):.12g}")


def spec_from_maps(maps_list: Sequence[Maps | MapsChannels], name: str | None = None) -> tuple[FeatureSpec, list[str]]:
    """The feature spec of a model for these maps (``doct-train --like``), and notes on what was chosen.

    Read from the metadata (the inverse of :func:`assemble_features`): the configurations are the
    resolutions present (each channel's optics, :meth:`~torchdoct.measured.mapsfile.Maps.optics`: the
    wavelength, the lateral 1/e² width along x and y, the axial FWHM in the medium; B-scan maps reduced
    along x only keep the original width along y), the protocol is the frame times (uniform), the
    medium's refractive index and the OCDS analysis are the maps'. The features are the decorrelation
    signature the maps hold (``torchdoct maps --signature``: their lags follow the frame count,
    :func:`torchdoct.sim.signature.default_features`), its field group only when the maps say the bulk
    phase was corrected (``meta["bulk_phase"]``), else LIV and OCDS. Several files (e.g. two wavelengths)
    must share the protocol. ``name``: the spec's (default ``like-STEM`` of the first file).
    """
    import re

    from .features import Configuration

    all_maps = [_as_maps(m) for m in maps_list]
    if not all_maps:
        raise ValueError("no maps file given")
    first = all_maps[0]
    n_frames, dt = _frame_protocol(first)
    for m in all_maps[1:]:
        other = _frame_protocol(m)
        if other[0] != n_frames or not same_value(other[1], dt):
            raise ValueError(
                f"{m.name}: {other[0]} frames {other[1]:g} s apart, but {first.name} has {n_frames} "
                f"frames {dt:g} s apart; maps of one model share the protocol"
            )
    notes: list[str] = []
    signature: list[Any] = [m.meta.get("signature") for m in all_maps]  # each a metadata dict, or None
    if all(signature):
        names = [tuple(s.get("features") or ()) for s in signature]
        if any(n != names[0] for n in names):
            raise ValueError(
                "the maps files hold different signature features; compute them with the same "
                "`torchdoct maps --signature` options"
            )
        corrected = all(m.meta.get("bulk_phase") for m in all_maps)
        intensity_only = any(s.get("intensity_only") for s in signature)
        metrics = [f for f in names[0] if (corrected and not intensity_only) or not _signature.needs_field(f)]
        if not corrected and not intensity_only and len(metrics) < len(names[0]):
            notes.append(
                "the field group (g1_M) is left out: the maps were not bulk-phase corrected, and a bulk "
                "phase per frame destroys it (`torchdoct maps --bulk-phase weighted-mean --signature` "
                "gives a model that reads it)"
            )
    else:
        metrics = ["liv", "ocds"]
        notes.append(
            "LIV and OCDS features: the maps have no signature channels (`torchdoct maps DATA --signature` "
            "gives the more accurate signature model)"
        )
    configurations: list[Configuration] = []
    labels: dict[str, int] = {}
    for m in all_maps:
        for i, ch in enumerate(m.meta["channels"]):
            if ch.get("metric") != metrics[0]:
                continue
            optics = m.optics(i)
            if optics is None:
                raise ValueError(
                    f"{m.name}: channel {ch.get('name')!r} records no wavelength or resolution. Fix: "
                    "recompute the maps with --wavelength-um, --lateral-resolution-um and "
                    "--axial-resolution-um"
                )
            if any(c.optics.matches(optics) for c in configurations):
                continue
            label = str(ch.get("resolution") or f"c{len(configurations)}")
            if len(all_maps) > 1:
                label = f"{optics.wavelength_um * 1000:g}nm-{label}"
            labels[label] = labels.get(label, 0) + 1
            if labels[label] > 1:
                label = f"{label}-{labels[label]}"
            configurations.append(
                Configuration(
                    name=label,
                    wavelength_um=optics.wavelength_um,
                    lateral_resolution_um=optics.lateral_resolution_um,
                    axial_resolution_um=optics.axial_resolution_um,
                    lateral_resolution_y_um=optics.lateral_resolution_y_um,
                )
            )
    if not configurations:
        have = ", ".join(first.channels)
        raise ValueError(
            f"{first.name}: no {metrics[0]} channel to build a model from (channels: {have}). Fix: "
            "compute the maps with `torchdoct maps DATA --signature --resolution original ...`"
        )
    system = first.meta.get("system") or {}
    n = system.get("refractive_index")
    rng = first.meta.get("ocds_delay_range_s") or [dt, 6 * dt]
    stem = re.sub(r"[^A-Za-z0-9._-]+", "-", Path(first.name).stem).strip("-.") or "maps"
    geometry = (
        "B-scan, lateral reduction along x only"
        if any(not c.optics.isotropic for c in configurations)
        else "isotropic reductions"
    )
    spec_name = name or f"like-{stem}"
    description = (
        f"derived from the metadata of {', '.join(m.name for m in all_maps)} (doct-train --like): "
        f"{len(metrics)} features at {len(configurations)} configurations ("
        + "; ".join(f"{c.name}: {c.describe()}" for c in configurations)
        + f"), {geometry}; {n_frames} frames {dt:g} s apart, n = {1.0 if n is None else float(n):g}"
    )
    spec = FeatureSpec(
        name=spec_name,
        description=description,
        configurations=tuple(configurations),
        metrics=tuple(metrics),
        n_frames=n_frames,
        frame_interval_s=dt,
        # FeatureSpec refuses a range of any other length than 2
        ocds_delay_range_s=cast("tuple[float, float]", tuple(float(v) for v in rng)),
        ocds_scale=str(first.meta.get("ocds_scale") or "db"),
        ocds_estimator=str(first.meta.get("ocds_estimator") or "pearson"),
        refractive_index=1.0 if n is None else float(n),
    )
    # every feature at every configuration must be in the maps (what assemble_features will look for)
    for metric, conf in spec.features:
        if _find_column(all_maps, {"metric": metric, **conf.to_dict()}) is None:
            raise ValueError(
                f"{first.name}: {metric} is missing at {conf.describe()}; the maps must hold every "
                f"feature at every resolution. Fix: recompute them with one `torchdoct maps` call"
            )
    return spec, notes


def no_shipped_model_message(maps_list: Sequence[Maps | MapsChannels], reason: str) -> str:
    """The refusal when no shipped model fits the maps: what their system is, and the exact commands that
    train a model from the maps themselves (``doct-train --like``) and classify with it."""
    all_maps = [_as_maps(m) for m in maps_list]
    files = " ".join(str(m.path) if m.path is not None else m.name for m in all_maps)
    m0 = all_maps[0]
    system = m0.meta.get("system") or {}
    times = m0.meta.get("frame_times_s") or []
    parts = []
    if system.get("wavelength_um"):
        parts.append(
            f"{float(system['wavelength_um']) * 1000:g} nm, lateral "
            f"{float(system.get('lateral_resolution_um') or math.nan):g} µm, axial "
            f"{float(system.get('axial_resolution_um') or math.nan):g} µm"
        )
    if len(times) >= 2:
        parts.append(f"{len(times)} frames {float(times[1]) - float(times[0]):.4g} s apart")
    parts.append(f"n = {system.get('refractive_index') or 1:g}")
    import re

    short = reason.split(" Channels present in")[0].split(" Fix:")[0]
    short = re.sub(r"\s*\(fix:[^)]*\)", "", short).removeprefix(f"{m0.name}: ").rstrip(". ")
    missing = re.search(r"maps lack the model feature '[^'@]+@([^']+)'", reason)
    shipped_system = (
        math.isclose(float(system.get("wavelength_um") or 0), 0.84, rel_tol=1e-3)
        and math.isclose(float(system.get("lateral_resolution_um") or 0), 4.9, rel_tol=1e-3)
        and math.isclose(float(system.get("axial_resolution_um") or 0), 3.8, rel_tol=1e-3)
        and len(times) == 32
        and math.isclose(float(times[1]) - float(times[0]), 0.2048, rel_tol=1e-3)
        and float(system.get("refractive_index") or 1) == 1.0
    )
    have = list(
        dict.fromkeys(ch.get("resolution") for m in all_maps for ch in m.meta["channels"] if ch.get("resolution"))
    )
    if missing and shipped_system and missing.group(1) not in have:
        # the shipped system, one resolution short: name the --resolution to add
        res = missing.group(1)
        if res.startswith("lateral") and m0.spatial_shape[-1] == 1:  # one A-line: no lateral reduction exists
            return (
                f"{m0.name}: the maps lack the resolution {res} that the LIV/OCDS and B-scan or volume models read, "
                "and one A-line (one pixel along x) cannot be reduced laterally. Fix: compute its signature at "
                "the resolutions it has for the A-line model (signature-aline), `torchdoct maps DATA "
                + " ".join(f"--resolution {r}" for r in dict.fromkeys([*have, "original", "axial=14"]))
                + " --signature ...`, then classify again"
            )
        return (
            f"{m0.name}: the maps lack the resolution {res} that the shipped models read (they hold "
            f"{', '.join(have)}). Fix: add `--resolution {res}` to `torchdoct maps`, e.g. `torchdoct maps DATA "
            + " ".join(f"--resolution {r}" for r in [*have, res])
            + " ...`, then classify again"
        )
    return (
        f"{m0.name}: no shipped model fits these maps ({'; '.join(parts)}; the shipped models know 840 nm at "
        f"4.9/3.8 µm, with 1310 nm for the two-wavelength ones, 32 frames 0.2048 s apart, n = 1): {short}. "
        f"Fix: train a model for this system from the maps themselves, `doct-train --like {files} --out MODEL_DIR` "
        "(it prints the expected time first; --quick gives a rough model on small splits), then "
        f"`doct-classify {files} --model MODEL_DIR --out OUT`"
    )

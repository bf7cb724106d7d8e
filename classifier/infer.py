"""Classify every pixel of DOCT maps with an ONNX motion-type model. numpy, onnxruntime, tifffile only.

This is the classify path: it imports neither torch nor the torchdoct package (it reads
``torchdoct/_files.py`` and ``torchdoct/conventions.py`` on their own, see :mod:`classifier._files`).

Steps of :func:`classify_maps`:

1. **Model** (:func:`load_model`): an ONNX file written by :mod:`classifier.export`; its metadata
   gives the feature columns (metric + system configuration), the classes, the indeterminate
   rule and the feature spec (protocol, OCDS delay range, refractive index). Default
   (:func:`default_model_for`): a shipped signature model whose channels the maps hold
   (two-wavelength signature, then signature), else the single-acquisition LIV/OCDS model.
2. **Maps** (:func:`read_maps`): one or more maps files in the project's format (``.npz`` with
   ``maps``/``channels``/``meta_json``, or ``.tif`` with the JSON in the ImageDescription). Every
   model feature must match a channel by (metric, wavelength, lateral resolution, axial resolution)
   within 1e-6 relative; the frame times and the OCDS delay range must be the spec's; the system's
   refractive index must be the spec's. Anything missing or mismatched is a ``ValueError`` naming it
   and the fix.
3. **Mask**: a pixel is classified when all its features are finite and it is not background.
   Background: the ``mean_db`` channel (if present) below ``background_db``; ``"auto"`` = its
   99th percentile minus 30 dB (the usual DOCT display range), ``None`` = no background mask.
4. **Pooling** (optional, ``pool = N``): every feature is averaged over the valid pixels of the
   N × N neighbourhood in the (z, x) plane of each B-scan (N at most the B-scan's smaller side;
   a larger window would give every pixel the same class and is refused). The model's ``pool_pixels`` input is
   the number of *independent* pixels averaged: the valid count times the independence fraction of
   the pixel grid, ``n_e(N, p_x, s_x)·n_e(N, p_z, s_z)/N²`` with ``n_e = N²/Σ_ij exp(−((i−j)p)²/(2s²))``
   the effective sample count of N pixels of pitch ``p`` under the speckle intensity correlation of a
   Gaussian amplitude PSF of sigma ``s`` (finest configuration of the spec, sigmas from
   :mod:`torchdoct.conventions`; docs/physics.md §5.3 overlap of displaced Gaussians), clipped to
   [1, ``pool_pixels_max``]. Without ``pitch_um`` in the maps, pixels count as independent.
5. **Classification**: onnxruntime on the valid pixels (chunks of 2^17), then the rule of
   :mod:`classifier.rule`: class map values 0…C−1 (the model's classes, ``indeterminate`` last) and
   :data:`MASKED` for background/NaN pixels; per-class probability maps (NaN where masked).

Kept whole (over 600 lines): the torch-free classify path, reading, pooling, rule and writing
(docs/architecture.md).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ._files import shipped_files
from ._files import signature as _signature
from ._files import threads as _threads
from .features import METRIC_UNITS, FeatureSpec, metric_unit, same_value, shipped_or_path, spec_from_dict
from .rule import INDETERMINATE, REASONS, apply_rule

__all__ = [
    "MASKED",
    "DEFAULT_MODEL",
    "CLASS_COLORS",
    "ClassifierModel",
    "Maps",
    "Classification",
    "shipped_models",
    "load_model",
    "read_maps",
    "assemble_features",
    "pool_features",
    "independent_fraction",
    "classify_maps",
    "write_classification",
]

#: Class-map value of background and NaN pixels.
MASKED = 255
#: Name of the shipped default model (``classifier/data/<name>.onnx``).
DEFAULT_MODEL = "single-acquisition"
#: Colours of the classes in the legend and overlay.
CLASS_COLORS = {"diffusion": "#1f77b4", "ballistic": "#ff7f0e", "flow": "#2ca02c", INDETERMINATE: "#8c8c8c"}
_FORMAT = "torchdoct-classifier/1"
_METADATA_KEY = "torchdoct_classifier"
#: Rows per onnxruntime call: the network's intermediate tensors of 2048 rows stay in the core's cache
#: (1.2-1.4x the throughput of 131072-row chunks, `torchdoct bench classify`). onnxruntime's matrix
#: kernels take rows in groups of 4 and round the rows of an incomplete group differently (~1e-7), so a
#: multiple of 4 keeps every row's result independent of the chunk size and of the thread count.
_CHUNK = 1 << 11
_AUTO_RANGE_DB = 30.0


# ---------------------------------------------------------------------------------------------
# model


def shipped_models() -> dict[str, Path]:
    """Names and paths of the models shipped in ``classifier/data/``."""
    return shipped_files("classifier", "data", ".onnx")


@dataclass
class ClassifierModel:
    """An ONNX motion-type model and its metadata (see :mod:`classifier.export`)."""

    path: Path
    metadata: dict[str, Any]
    session: Any
    threads: int = 1

    def _chunks(self, fn, n: int) -> None:
        """``fn(slice)`` over fixed chunks of ``n`` rows, ``threads`` chunks side by side (one onnxruntime
        thread each: no stalls beside other busy processes; the chunks, hence the numbers, do not depend
        on ``threads``)."""
        parts = [slice(i, min(n, i + _CHUNK)) for i in range(0, n, _CHUNK)]
        for _ in _threads().map_ordered(fn, parts, self.threads):
            pass

    @property
    def spec(self) -> FeatureSpec:
        return spec_from_dict(self.metadata["spec"])

    @property
    def classes(self) -> list[str]:
        return list(self.metadata["output"]["classes"])

    @property
    def rule(self) -> dict[str, Any]:
        return self.metadata["rule"]

    @property
    def columns(self) -> list[dict[str, Any]]:
        return list(self.metadata["input"]["columns"])

    @property
    def pool_pixels_max(self) -> int:
        return int(self.metadata.get("pool_pixels_max", 1))

    @property
    def has_magnitude(self) -> bool:
        """True when the model also predicts the motion magnitude with an interval (signature models)."""
        return "magnitude" in self.metadata

    def predict_magnitude(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per motion class, predicted ``log10`` magnitude and its predictive SD, ``[N, K]`` each."""
        _, mean, sd = self.predict_all(x)
        if mean is None:
            raise ValueError(f"model {self.path.name} has no magnitude head")
        return mean, sd

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Probabilities ``[N, C]`` of inputs ``[N, F+1]`` (features + pool_pixels), float32."""
        return self.predict_all(x, magnitude=False)[0]

    def predict_all(self, x: np.ndarray, magnitude: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(probabilities [N, C], log10 magnitude [N, K], its SD [N, K])`` from one pass of the network
        (the magnitude pair is None for models without a magnitude head or when ``magnitude`` is False)."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        width = len(self.columns)
        if x.ndim != 2 or x.shape[1] != width:
            raise ValueError(f"model inputs must be [N, {width}]; got {x.shape}")
        names = ["probabilities"]
        out = [np.empty((x.shape[0], len(self.classes)), np.float32)]
        if magnitude and self.has_magnitude:
            k = len(self.metadata["magnitude"]["classes"])
            names += ["log10_magnitude", "log10_magnitude_sd"]
            out += [np.empty((x.shape[0], k), np.float32), np.empty((x.shape[0], k), np.float32)]

        def run(sl: slice) -> None:
            for o, r in zip(out, self.session.run(names, {"features": x[sl]})):
                o[sl] = r

        self._chunks(run, x.shape[0])
        return out[0], (out[1] if len(out) > 1 else None), (out[2] if len(out) > 1 else None)


def load_model(model: str | os.PathLike | None = None, *, threads: int | None = None) -> ClassifierModel:
    """Open an ONNX model: ``None`` (the shipped default), a shipped name, or a ``.onnx`` path.

    ``threads``: chunks of pixels classified side by side, each on one onnxruntime thread with spinning
    off (default: ``$TORCHDOCT_THREADS``, else the usable cores; see :mod:`torchdoct.threads`).
    """
    import onnxruntime as ort

    path = shipped_or_path(DEFAULT_MODEL if model is None else str(model), shipped_models(), "model")
    if path.suffix != ".onnx":
        raise ValueError(f"model {path.name}: must be an .onnx file written by doct-train")
    opts = ort.SessionOptions()
    n_threads = _threads().resolve_threads(threads)
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own exception types
        raise ValueError(f"model {path.name}: not a readable ONNX model ({err})") from None
    props = sess.get_modelmeta().custom_metadata_map
    if _METADATA_KEY not in props:
        raise ValueError(f"model {path.name}: no '{_METADATA_KEY}' metadata; it was not written by doct-train")
    meta = json.loads(props[_METADATA_KEY])
    if meta.get("format") != _FORMAT:
        raise ValueError(f"model {path.name}: metadata format {meta.get('format')!r}, this version reads {_FORMAT!r}")
    return ClassifierModel(path=path, metadata=meta, session=sess, threads=n_threads)


# ---------------------------------------------------------------------------------------------
# maps


@dataclass
class Maps:
    """A maps file: ``data [C, (Y,) Z, X]`` float32, ``channels`` (meta dicts), the meta JSON."""

    path: Path
    data: np.ndarray
    channels: list[dict[str, Any]]
    meta: dict[str, Any]

    @property
    def spatial_shape(self) -> tuple[int, ...]:
        return tuple(self.data.shape[1:])


def _tiff_meta(path: Path) -> dict[str, Any]:
    import tifffile

    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        for tag in page.tags.values():
            if tag.name == "ImageDescription":
                try:
                    meta = json.loads(tag.value)
                except (TypeError, ValueError):
                    continue
                if isinstance(meta, dict) and "channels" in meta:
                    return meta
    raise ValueError(f"{path.name}: no JSON maps description (with 'channels') in the TIFF ImageDescription; "
                     "write it with `torchdoct maps ... --out FILE.tif`")


def _rewrite_fix(path: Path) -> str:
    return f"Fix: write it again with `torchdoct maps DATA --out {path.name}` (or copy it again completely)"


def _read_npz(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """``maps`` and the parsed ``meta_json`` of a maps ``.npz``; never unpickles."""
    import zipfile
    import zlib

    unreadable = (zipfile.BadZipFile, EOFError, OSError, zlib.error)
    with open(path, "rb") as fh:  # our handle: numpy leaves its own open when the archive is damaged
        try:
            z = np.load(fh, allow_pickle=False)
        except (*unreadable, ValueError) as err:
            fh.seek(0)
            if "Object arrays" in str(err) or fh.read(1) == b"\x80":  # a .npy of objects, or a pickle stream
                raise ValueError(f"{path.name}: holds Python objects (a pickle), not a maps archive; pickles are never "
                                 f"loaded (loading one can run code). {_rewrite_fix(path)}") from None
            raise ValueError(f"{path.name}: not a readable .npz archive: the file is truncated, corrupted or not "
                             f"a .npz file ({err}). {_rewrite_fix(path)}") from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"{path.name}: holds one bare array, not a maps archive ('maps', 'channels', "
                             f"'meta_json'). {_rewrite_fix(path)}")
        arrays = _npz_arrays(path, z, unreadable)
    raw = arrays["meta_json"]
    if raw.dtype.kind not in "US" or raw.size != 1:
        raise ValueError(f"{path.name}: 'meta_json' must be a JSON text (a 0-d string array); got a "
                         f"{raw.dtype} array of shape {list(raw.shape)}. {_rewrite_fix(path)}")
    try:
        meta = json.loads(str(raw.reshape(())))
    except ValueError as err:
        raise ValueError(f"{path.name}: 'meta_json' is not valid JSON ({err}). {_rewrite_fix(path)}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path.name}: 'meta_json' must be a JSON object ({{\"channels\": [...], ...}}); got a "
                         f"{type(meta).__name__}. {_rewrite_fix(path)}")
    return arrays["maps"], meta


def _npz_arrays(path: Path, z, unreadable: tuple[type[BaseException], ...]) -> dict[str, np.ndarray]:
    with z:
        for key in ("maps", "meta_json"):
            if key not in z:
                raise ValueError(f"{path.name}: missing array {key!r} (maps files have 'maps', 'channels', "
                                 "'meta_json'; write them with `torchdoct maps`)")
        arrays = {}
        for key in ("maps", "meta_json"):
            try:
                arrays[key] = z[key]
            except ValueError as err:  # object arrays: numpy refuses them without allow_pickle
                if "pickle" not in str(err) and "Object arrays" not in str(err):
                    raise ValueError(f"{path.name}: array {key!r} is unreadable ({err}). {_rewrite_fix(path)}") from None
                raise ValueError(f"{path.name}: array {key!r} holds Python objects (a pickle); pickles are never "
                                 "loaded (loading one can run code). Fix: store 'maps' as a float array and "
                                 "'meta_json' as a JSON string, as `torchdoct maps` writes them") from None
            except unreadable as err:
                raise ValueError(f"{path.name}: array {key!r} is truncated or corrupted ({err}). "
                                 f"{_rewrite_fix(path)}") from None
    return arrays


def _read_tiff(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The image stack and the JSON description of a maps TIFF, restored to ``[C, (Y,) Z, X]``."""
    import logging

    import tifffile

    class _Errors(logging.Handler):  # tifffile logs (not raises) a damaged page table and reads what it can
        def __init__(self):
            super().__init__(logging.ERROR)
            self.messages: list[str] = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    log = logging.getLogger("tifffile")
    errors, propagate = _Errors(), log.propagate
    log.addHandler(errors)
    log.propagate = False
    try:
        data = tifffile.imread(path)
        meta = _tiff_meta(path)
        if errors.messages:
            raise ValueError("; ".join(errors.messages))
    except ValueError as err:
        if "ImageDescription" in str(err):
            raise
        raise ValueError(f"{path.name}: not a readable TIFF: the file is truncated, corrupted or not a TIFF "
                         f"({err}). {_rewrite_fix(path)}") from None
    except Exception as err:  # tifffile raises many types on damaged files (struct, index, OS errors)
        raise ValueError(f"{path.name}: not a readable TIFF: the file is truncated, corrupted or not a TIFF "
                         f"({type(err).__name__}: {err}). {_rewrite_fix(path)}") from None
    finally:
        log.removeHandler(errors)
        log.propagate = propagate
    n_ch = len(meta["channels"]) if isinstance(meta.get("channels"), list) else 0
    n_sp = len(str(meta.get("axes", "CZX"))) - 1  # pages are [Z, X] images: restore [C, (Y), Z, X]
    shape = (n_ch, -1, *data.shape[-2:]) if n_sp == 3 else (n_ch, *data.shape[-2:])
    try:
        data = data.reshape(shape)
    except ValueError:
        raise ValueError(f"{path.name}: a stack of shape {list(data.shape)} does not hold {n_ch} channels "
                         f"of axes {meta.get('axes')!r}") from None
    return data, meta


def read_maps(path: str | os.PathLike) -> Maps:
    """Read a maps file (``.npz`` or ``.tif``/``.tiff``) in the project's maps format.

    Nothing is unpickled. An empty, truncated or corrupted file, an object (pickled) array or a
    ``meta_json`` that is not a JSON object is a ``ValueError`` naming the file and the fix.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"maps file {path} does not exist")
    if path.suffix not in (".npz", ".tif", ".tiff"):
        raise ValueError(f"maps file {path.name}: must be .npz or .tif (the formats of `torchdoct maps`)")
    if not path.is_file():
        raise ValueError(f"maps file {path} is not a file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path.name}: the file is empty (0 bytes). {_rewrite_fix(path)}")
    data, meta = _read_npz(path) if path.suffix == ".npz" else _read_tiff(path)
    if not np.issubdtype(data.dtype, np.floating):
        raise TypeError(f"{path.name}: maps must be floating point; got {data.dtype}")
    if data.ndim not in (3, 4):
        raise ValueError(f"{path.name}: maps must be [C, Z, X] or [C, Y, Z, X]; got shape {data.shape}")
    channels = meta.get("channels")
    if not isinstance(channels, list) or len(channels) != data.shape[0]:
        raise ValueError(f"{path.name}: meta 'channels' must list one entry per map; got "
                         f"{len(channels) if isinstance(channels, list) else channels!r} for {data.shape[0]} maps")
    for i, ch in enumerate(channels):
        if not isinstance(ch, dict) or "metric" not in ch:
            raise ValueError(f"{path.name}: channel {i} has no 'metric' entry: {ch!r}")
    _check_meta(path.name, meta)
    return Maps(path=path, data=data.astype(np.float32, copy=False), channels=channels, meta=meta)


def _check_meta(name: str, meta: dict[str, Any]) -> None:
    """Types and ranges of the maps metadata the classifier reads; a ``ValueError`` names the key."""
    fix = "Fix: write the maps with `torchdoct maps`, or correct that entry of the metadata"

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def fail(key: str, want: str, got: Any) -> None:
        raise ValueError(f"{name}: meta {key} must be {want}; got {got!r}. {fix}")

    for i, ch in enumerate(meta["channels"]):
        if not isinstance(ch["metric"], str):
            fail(f"channels[{i}].metric", "a metric name", ch["metric"])
        for key in ("name", "unit", "resolution"):
            if key in ch and not isinstance(ch[key], str):
                fail(f"channels[{i}].{key}", "a string", ch[key])
        for key in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um"):
            if ch.get(key) is not None and not (number(ch[key]) and ch[key] > 0):
                fail(f"channels[{i}].{key}", "a positive number (µm) or null", ch[key])
    for key in ("system", "reduction", "pitch_um", "signature"):
        if meta.get(key) is not None and not isinstance(meta[key], dict):
            fail(key, "a table (JSON object)", meta[key])
    if "axes" in meta and not isinstance(meta["axes"], str):
        fail("axes", "a string such as 'CZX'", meta["axes"])
    times = meta.get("frame_times_s")
    if times is not None and not (isinstance(times, list) and all(number(t) for t in times)):
        fail("frame_times_s", "a list of times (s)", times)
    delays = meta.get("ocds_delay_range_s")
    if delays is not None and not (isinstance(delays, list) and len(delays) == 2 and all(number(t) for t in delays)):
        fail("ocds_delay_range_s", "[low, high] (s)", delays)
    for key, value in (meta.get("system") or {}).items():
        if (key.endswith("_um") or key == "refractive_index") and value is not None:
            if not (number(value) and value > 0):
                fail(f"system.{key}", "a positive number or null", value)
    for key, value in (meta.get("pitch_um") or {}).items():
        if not (number(value) and value > 0):
            fail(f"pitch_um.{key}", "a positive number (µm)", value)


def _describe_channel(ch: dict[str, Any]) -> str:
    def g(k):
        v = ch.get(k)
        return f"{v:g}" if isinstance(v, (int, float)) else "?"

    return (f"{ch.get('name', ch.get('metric'))} ({g('wavelength_um')} µm, lateral {g('lateral_resolution_um')} µm, "
            f"axial {g('axial_resolution_um')} µm)")


def _channel_matches(ch: dict[str, Any], metric: str, col: dict[str, Any]) -> bool:
    if ch.get("metric") != metric:
        return False
    try:
        return all(same_value(float(ch[k]), float(col[k]))
                   for k in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um"))
    except (KeyError, TypeError, ValueError):
        return False


def _check_protocol(maps: Maps, spec: FeatureSpec, ignore_refractive_index: bool) -> None:
    name = maps.path.name
    times = maps.meta.get("frame_times_s")
    if not isinstance(times, list) or len(times) < 2:
        raise ValueError(f"{name}: meta has no 'frame_times_s'; the model needs {spec.n_frames} frames "
                         f"{spec.frame_interval_s} s apart")
    t = np.asarray(times, dtype=np.float64)
    d = np.diff(t)
    if len(t) != spec.n_frames or not all(same_value(x, spec.frame_interval_s) for x in d):
        raise ValueError(f"{name}: maps were computed from {len(t)} frames at intervals {d.min():g}-{d.max():g} s, "
                         f"but the model was trained for {spec.n_frames} frames {spec.frame_interval_s} s apart "
                         "(fix: train a model with this protocol in its spec)")
    rng = maps.meta.get("ocds_delay_range_s")
    if rng is None or len(rng) != 2 or not all(same_value(a, b) for a, b in zip(rng, spec.ocds_delay_range_s)):
        raise ValueError(f"{name}: OCDS delay range {rng} s differs from the model's "
                         f"{list(spec.ocds_delay_range_s)} s (fix: recompute the maps with that range)")
    system = maps.meta.get("system") or {}
    n = system.get("refractive_index")
    n = 1.0 if n is None else n  # not recorded: the paper's n = 1
    if not ignore_refractive_index and not same_value(float(n), spec.refractive_index):
        raise ValueError(f"{name}: system refractive_index {n} but the model was trained for "
                         f"{spec.refractive_index} (phase rates scale with n; fix: train a model whose spec has "
                         f"refractive_index = {n}, or pass --ignore-refractive-index)")


def assemble_features(maps_list: Sequence[Maps], model: ClassifierModel, *,
                      ignore_refractive_index: bool = False) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """Model features ``[F, *S]`` from the channels of one or more maps files, and the intensity map.

    Returns ``(features, mean_db or None, info)``; ``info`` names the channel used for every feature.
    """
    if not maps_list:
        raise ValueError("no maps file given")
    spec = model.spec
    shape = maps_list[0].spatial_shape
    for m in maps_list:
        if m.spatial_shape != shape:
            raise ValueError(f"maps files have different shapes: {maps_list[0].path.name} {shape}, "
                             f"{m.path.name} {m.spatial_shape}")
        _check_protocol(m, spec, ignore_refractive_index)
    feats = []
    used = []
    for col in model.columns[:-1]:
        metric = col["metric"]
        found = None
        for m in maps_list:
            for i, ch in enumerate(m.channels):
                if _channel_matches(ch, metric, col):
                    found = (m, i, ch)
                    break
            if found:
                break
        if found is None and any((m.meta.get("signature") or {}).get("intensity_only") for m in maps_list) \
                and metric not in METRIC_UNITS and _signature().needs_field(metric):
            raise ValueError(f"model {model.path.name} needs the complex field's phase ({col['name']!r}), but the maps "
                             "were computed from intensity-only data, which give only the intensity part of the "
                             "signature. Fix: compute the maps from the complex data, or classify with the LIV/OCDS "
                             f"model (--model {DEFAULT_MODEL})")
        if found is None:
            have = "; ".join(f"{m.path.name}: " + ", ".join(_describe_channel(ch) for ch in m.channels)
                             for m in maps_list)
            res = col["configuration"]
            raise ValueError(
                f"maps lack the model feature {col['name']!r}: {metric} at {col['wavelength_um'] * 1000:g} nm, "
                f"lateral {col['lateral_resolution_um']:g} µm, axial {col['axial_resolution_um']:g} µm. Channels "
                f"present in {have}. Fix: compute it, e.g. `torchdoct maps DATA --resolution {res} ...`, or give "
                "the maps of the other wavelength as a second file")
        m, i, ch = found
        unit = ch.get("unit")
        if unit is not None and unit != metric_unit(metric):
            raise ValueError(f"{m.path.name}: channel {ch.get('name')!r} has unit {unit!r}; the model expects "
                             f"{metric_unit(metric)!r}")
        feats.append(m.data[i])
        used.append({"feature": col["name"], "file": m.path.name, "channel": ch.get("name", str(i))})
    mean_db = None
    first = spec.configurations[0]
    candidates = [(m, i, ch) for m in maps_list for i, ch in enumerate(m.channels) if ch.get("metric") == "mean_db"]
    candidates.sort(key=lambda t: 0 if first.matches(*(float(t[2].get(k) if t[2].get(k) is not None else math.nan)
                                                         for k in ("wavelength_um", "lateral_resolution_um",
                                                                   "axial_resolution_um"))) else 1)
    if candidates:
        m, i, ch = candidates[0]
        mean_db = m.data[i]
    notes = []
    for m in maps_list:
        axes = (m.meta.get("reduction") or {}).get("lateral_axes")
        system = m.meta.get("system") or {}
        reduced = [c for c in spec.configurations
                   if system.get("lateral_resolution_um") is not None
                   and not same_value(c.lateral_resolution_um, float(system["lateral_resolution_um"]))]
        if axes == "X" and reduced:
            notes.append(f"{m.path.name}: the lateral resolution was reduced along x only (B-scan data), so the "
                         f"{', '.join(c.name for c in reduced)} channels keep the original width along y, unlike "
                         "the model's isotropic training; expect lower accuracy than the report (volumes are "
                         "reduced isotropically)")
    info = {"features": used, "intensity_channel": candidates[0][2].get("name") if candidates else None,
            "notes": notes}
    return np.stack(feats).astype(np.float32, copy=False), mean_db, info


# ---------------------------------------------------------------------------------------------
# pooling


def _box_sum(a: np.ndarray, n: int, axis: int) -> np.ndarray:
    """Sum over the window ``[i − n//2, i + n − 1 − n//2]`` along ``axis`` (zeros outside).

    Small windows (n ≤ 8) add n shifted slices (direct sums, 4× faster than a cumulative sum along
    a non-contiguous axis); larger ones difference a cumulative sum (cost independent of n).
    """
    h1 = n // 2
    if n <= 8:
        length = a.shape[axis]
        out = np.zeros_like(a)
        for d in range(-h1, n - h1):  # out[i] += a[i + d] where i + d is inside
            dst = [slice(None)] * a.ndim
            src = [slice(None)] * a.ndim
            dst[axis] = slice(max(0, -d), min(length, length - d))
            src[axis] = slice(max(0, d), min(length, length + d))
            out[tuple(dst)] += a[tuple(src)]
        return out
    h2 = n - 1 - h1
    pad = [(0, 0)] * a.ndim
    pad[axis] = (h1 + 1, h2)
    c = np.cumsum(np.pad(a, pad), axis=axis)
    length = a.shape[axis]
    hi = [slice(None)] * a.ndim
    lo = [slice(None)] * a.ndim
    hi[axis], lo[axis] = slice(n, n + length), slice(0, length)
    return c[tuple(hi)] - c[tuple(lo)]


def pool_features(features: np.ndarray, valid: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each feature over the valid pixels of every N × N (z, x) neighbourhood.

    ``features [F, *S]``, ``valid [*S]`` (bool); returns ``(pooled [F, *S] float32, counts [*S])``
    with NaN where no valid pixel is in the window. ``n = 1`` returns the input.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"pool must be a positive integer (N for N × N); got {n!r}")
    if n == 1:
        return features, valid.astype(np.int64)
    # windows of up to 8 add shifted slices: float32 sums of at most 64 terms (relative error ~1e-7, a
    # few times faster than float64); larger ones difference a cumulative sum, kept in float64
    dt = np.float32 if n <= 8 else np.float64
    w = valid.astype(dt)
    f = np.where(valid, features.astype(dt, copy=False), dt(0.0))
    zax, xax = valid.ndim - 2, valid.ndim - 1
    counts = _box_sum(_box_sum(w, n, zax), n, xax)
    sums = _box_sum(_box_sum(f, n, zax + 1), n, xax + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return pooled.astype(np.float32), np.rint(counts).astype(np.int64)


def _effective_count(n: int, pitch_um: float, sigma_um: float) -> float:
    """Effective number of independent samples among n pixels (speckle intensity correlation)."""
    k = np.arange(n)
    d = (k[:, None] - k[None, :]) * pitch_um
    r = np.exp(-(d ** 2) / (2.0 * sigma_um ** 2))
    return float(n * n / r.sum())


def independent_fraction(n: int, pitch_um: dict[str, Any] | None, spec: FeatureSpec) -> float:
    """Fraction of the N × N pixels that count as independent (module docstring, step 4)."""
    if n == 1 or not pitch_um:
        return 1.0
    conv = _conventions()
    s_x = min(conv.amplitude_sigma_lateral_um(c.lateral_resolution_um) for c in spec.configurations)
    s_z = min(conv.amplitude_sigma_axial_um(c.axial_resolution_um) for c in spec.configurations)
    try:
        px, pz = float(pitch_um["x"]), float(pitch_um["z"])
    except (KeyError, TypeError, ValueError):
        return 1.0
    if not (px > 0 and pz > 0):
        return 1.0
    return _effective_count(n, px, s_x) * _effective_count(n, pz, s_z) / (n * n)


def _conventions():
    from ._files import conventions

    return conventions()


# ---------------------------------------------------------------------------------------------
# classification


@dataclass
class Classification:
    """Result of :func:`classify_maps` (arrays over the maps' spatial shape ``S``)."""

    labels: np.ndarray  # uint8 [*S]: class index, MASKED for background/NaN
    probabilities: np.ndarray  # float32 [C, *S], NaN where masked
    classes: list[str]
    mask: np.ndarray  # bool [*S]: True where classified
    background: np.ndarray  # bool [*S]: True where masked as background (not NaN)
    intensity_db: np.ndarray | None
    model: ClassifierModel
    sources: list[str]
    axes: str
    pitch_um: dict[str, Any] | None
    info: dict[str, Any] = field(default_factory=dict)
    #: float32 [5, *S] (:data:`MAGNITUDE_CHANNELS`), NaN where masked or indeterminate; None without a magnitude head
    magnitude: np.ndarray | None = None

    def counts(self) -> dict[str, int]:
        out = {c: int((self.labels == i).sum()) for i, c in enumerate(self.classes)}
        out["masked"] = int((self.labels == MASKED).sum())
        return out


def _background(mean_db: np.ndarray | None, background_db: str | float | None) -> tuple[np.ndarray | None, float | None]:
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


def classify_maps(paths: str | os.PathLike | Sequence[str | os.PathLike], model: ClassifierModel | str | None = None,
                  *, pool: int = 1, background_db: str | float | None = "auto", min_probability: float | None = None,
                  ignore_refractive_index: bool = False, threads: int | None = None) -> Classification:
    """Classify every pixel of one or more maps files (module docstring, steps 1-5)."""
    t0 = time.perf_counter()
    if isinstance(pool, bool) or not isinstance(pool, (int, np.integer)) or pool < 1:
        raise ValueError(f"pool must be a positive integer (N for N × N neighbourhoods); got {pool!r}")
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    if min_probability is not None and not 0.0 <= float(min_probability) < 1.0:
        raise ValueError(f"min_probability must be in [0, 1); got {min_probability!r}")
    maps_list = [read_maps(p) for p in paths]
    choice_note = None
    if model is None:
        model, choice_note = default_model_for(maps_list)
    mdl = model if isinstance(model, ClassifierModel) else load_model(model, threads=threads)
    z_px, x_px = maps_list[0].spatial_shape[-2:]
    if pool > min(z_px, x_px):
        raise ValueError(f"{maps_list[0].path.name}: pool {pool} (--pool) is larger than its {z_px} × {x_px} (z × x) "
                         f"B-scans: every {pool} × {pool} window would average most of the image and give all pixels "
                         f"the same class. The largest valid pool is {min(z_px, x_px)}")
    t_read = time.perf_counter()
    feats, mean_db, info = assemble_features(maps_list, mdl, ignore_refractive_index=ignore_refractive_index)
    info["model_choice"] = choice_note
    # a pixel is finite iff the float64 sum of its features is (NaN and ±inf propagate; finite float32
    # values cannot overflow a float64 sum): one pass instead of a boolean array per feature
    finite = np.isfinite(feats.sum(axis=0, dtype=np.float64))
    bg, thr = _background(mean_db, background_db)
    valid = finite if bg is None else finite & ~bg
    meta0 = maps_list[0].meta
    frac = independent_fraction(int(pool), meta0.get("pitch_um"), mdl.spec)
    pooled, counts = pool_features(feats, valid, int(pool))
    idx = np.flatnonzero(valid)
    x = np.empty((idx.size, feats.shape[0] + 1), np.float32)
    flat = pooled.reshape(feats.shape[0], -1)
    x[:, :-1] = (flat if idx.size == flat.shape[1] else flat[:, idx]).T
    x[:, -1] = np.clip(counts.reshape(-1)[idx] * frac, 1.0, float(mdl.pool_pixels_max))
    t_feat = time.perf_counter()
    probs, mag_mean, mag_sd = mdl.predict_all(x)
    t_onnx = time.perf_counter()
    labels_flat, reasons = apply_rule(probs, mdl.classes, mdl.rule, min_probability)
    shape = valid.shape
    labels = np.full(valid.size, MASKED, np.uint8)
    labels[idx] = labels_flat.astype(np.uint8)
    pmaps = np.full((len(mdl.classes), valid.size), np.nan, np.float32)
    pmaps[:, idx] = probs.T
    magnitude = None
    if mag_mean is not None:
        magnitude = np.full((len(MAGNITUDE_CHANNELS), valid.size), np.nan, np.float32)
        mean, sd = mag_mean, mag_sd
        k = mean.shape[1]
        motion = labels_flat < k  # decided pixels: the magnitude of the decided class
        rows = np.flatnonzero(motion)
        m, s_ = mean[rows, labels_flat[rows]], sd[rows, labels_flat[rows]]
        for c, v in enumerate((m, m - s_, m + s_, m - 1.959964 * s_, m + 1.959964 * s_)):
            magnitude[c, idx[rows]] = v
        magnitude = magnitude.reshape((len(MAGNITUDE_CHANNELS), *valid.shape))
    t_end = time.perf_counter()
    n_pix = int(valid.size)
    info.update({
        "pixels": n_pix, "classified": int(idx.size), "pool": int(pool), "pool_independent_fraction": frac,
        "background_db_threshold": thr, "nan_pixels": int((~finite).sum()),
        "background_pixels": int(((bg if bg is not None else np.zeros(shape, bool)) & finite).sum()),
        "indeterminate_reasons": {r: int((reasons == i).sum()) for i, r in enumerate(REASONS)},
        "min_probability": float(mdl.rule["min_probability"] if min_probability is None else min_probability),
        "seconds": {"read": t_read - t0, "features": t_feat - t_read, "onnxruntime": t_onnx - t_feat,
                    "rule": t_end - t_onnx, "total": t_end - t0},
        "pixels_per_s": n_pix / max(t_end - t_read, 1e-12),
    })
    axes = str(meta0.get("axes", "C" + ("YZX" if len(shape) == 3 else "ZX")))[1:]
    return Classification(labels=labels.reshape(shape), probabilities=pmaps.reshape((len(mdl.classes), *shape)),
                          classes=mdl.classes, mask=valid, background=(bg if bg is not None else np.zeros(shape, bool)),
                          intensity_db=mean_db, model=mdl, sources=[m.path.name for m in maps_list], axes=axes,
                          pitch_um=meta0.get("pitch_um"), info=info, magnitude=magnitude)


#: Shipped model used by default when the maps hold its (signature) channels.
SIGNATURE_MODEL = "signature"
#: Shipped signature models ``doct-classify`` prefers without ``--model``, in this order: the first whose
#: every channel the maps hold (``torchdoct maps --signature``; the two-wavelength one reads the maps of
#: both bands, one file or two). A model that is not shipped is skipped.
SIGNATURE_MODELS = ("two-wavelength-signature", SIGNATURE_MODEL)


def default_model_for(maps_list: Sequence[Maps]) -> tuple[str, str | None]:
    """The shipped model ``doct-classify`` uses without ``--model``, and a note for the user.

    The first shipped model of :data:`SIGNATURE_MODELS` whose every feature the maps hold, else
    :data:`DEFAULT_MODEL` (LIV/OCDS), saying why (for maps with signature channels: what the signature
    model closest to them, the one with the fewest missing features, lacks).
    """
    shipped = shipped_models()
    candidates = [name for name in SIGNATURE_MODELS if name in shipped]
    if not candidates:
        return DEFAULT_MODEL, None
    if not any(m.meta.get("signature") for m in maps_list):
        return DEFAULT_MODEL, (f"model {DEFAULT_MODEL} (LIV/OCDS): the maps have no signature channels; "
                               "`torchdoct maps DATA --signature ...` lets doct-classify use the more accurate "
                               f"{candidates[-1]} model")
    failed = []
    for name in candidates:
        sig = load_model(name, threads=1)
        try:
            assemble_features(maps_list, sig, ignore_refractive_index=True)
        except ValueError as err:
            missing = sum(not any(_channel_matches(ch, col["metric"], col) for m in maps_list for ch in m.channels)
                          for col in sig.columns[:-1])
            failed.append((missing, name, err))
            continue
        return name, None
    _, name, err = min(failed, key=lambda f: f[0])  # ties: the earlier in SIGNATURE_MODELS
    return DEFAULT_MODEL, f"model {DEFAULT_MODEL} (LIV/OCDS) instead of {name}: {err}"


# ---------------------------------------------------------------------------------------------
# outputs

OUTPUT_FILES = ("classes.tif", "probabilities.tif", "legend.json", "summary.json", "overlay.png")
#: ``magnitude.tif`` (models with a magnitude head): log10 magnitude of the decided class and its intervals.
MAGNITUDE_CHANNELS = ("log10_magnitude", "lower_68", "upper_68", "lower_95", "upper_95")


def _cite_repository(text: str) -> str:
    """Bare ``physics.md N`` citations (in model metadata) as the repository file ``docs/physics.md §N``."""
    import re

    return re.sub(r"(?<!docs/)physics\.md\s*§?\s*(?=\d)", "docs/physics.md §", text)


def _legend(res: Classification) -> dict[str, Any]:
    rule = dict(res.model.rule)
    if isinstance(rule.get("definition"), str):
        rule["definition"] = _cite_repository(rule["definition"])
    return {
        "classes": [{"value": i, "name": c, "color": CLASS_COLORS.get(c, "#000000")} for i, c in enumerate(res.classes)],
        "masked_value": MASKED,
        "masked_meaning": "background (mean dB intensity below the threshold) or a NaN feature",
        "rule": rule,
        "min_probability": res.info["min_probability"],
        "axes": res.axes,
        "pitch_um": res.pitch_um,
    }


def _overlay(res: Classification, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    labels = res.labels
    inten = res.intensity_db
    title_extra = ""
    if labels.ndim == 3:
        mid = labels.shape[0] // 2
        labels = labels[mid]
        inten = inten[mid] if inten is not None else None
        title_extra = f", B-scan y = {mid}"
    if inten is not None and np.isfinite(inten).any():
        fin = inten[np.isfinite(inten)]
        lo, hi = np.percentile(fin, [1, 99.5])
        grey = np.clip((np.nan_to_num(inten, nan=lo, neginf=lo, posinf=hi) - lo) / max(hi - lo, 1e-9), 0, 1)
    else:
        grey = np.full(labels.shape, 0.5)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    for i, c in enumerate(res.classes):
        sel = labels == i
        rgb[sel] = 0.45 * rgb[sel] + 0.55 * np.array(to_rgb(CLASS_COLORS.get(c, "#000000")))
    from ._files import _standalone

    figures = _standalone("figures")  # torchdoct.figures, torch-free: the project's one axes convention
    extent, _ = figures.image_extent(labels.shape, res.pitch_um)
    h = 5.0
    wdt = h * (extent[1] - extent[0]) / max(extent[2] - extent[3], 1e-9)
    fig, ax = plt.subplots(figsize=(min(max(wdt, 4.0), 14.0) + 2.0, h))
    figures.show_bscan(ax, rgb, pitch_um=res.pitch_um)
    counts = res.counts()
    total = max(int(res.mask.sum()), 1)
    handles = [Patch(color=CLASS_COLORS.get(c, "#000000"), label=f"{c} ({counts[c] / total:.0%})") for c in res.classes]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="class")
    ax.set_title(f"motion type on mean intensity (pool {res.info['pool']}{title_extra})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_classification(res: Classification, out_dir: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Write :data:`OUTPUT_FILES` into ``out_dir`` (created if missing; nothing is overwritten
    without ``force``; every file is written atomically)."""
    import tifffile

    from ._files import atomic_write, check_out

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    out.mkdir(parents=True, exist_ok=True)
    names = OUTPUT_FILES + (("magnitude.tif",) if res.magnitude is not None else ())
    paths = {name: check_out(out / name, force, Path(name).suffix, f"--out {out}: {name}") for name in names}
    legend = _legend(res)
    desc_classes = json.dumps({"legend": legend, "source": res.sources})
    desc_probs = json.dumps({"channels": res.classes, "axes": "C" + res.axes, "unit": "probability",
                             "masked": "NaN", "source": res.sources})
    summary = {"counts": res.counts(), "sources": res.sources, "model": res.model.path.name,
               "model_spec": res.model.metadata["spec"]["name"], "info": res.info}
    atomic_write(paths["classes.tif"], lambda t: tifffile.imwrite(t, res.labels, description=desc_classes, metadata=None,
                                                     photometric="minisblack"))
    atomic_write(paths["probabilities.tif"],
                 lambda t: tifffile.imwrite(t, res.probabilities, description=desc_probs, metadata=None,
                                            photometric="minisblack"))

    def dump(obj):
        def w(t):
            with open(t, "w", encoding="utf-8") as fh:
                json.dump(obj, fh, indent=1)
        return w

    atomic_write(paths["legend.json"], dump(legend))
    atomic_write(paths["summary.json"], dump(summary))
    atomic_write(paths["overlay.png"], lambda t: _overlay(res, t))
    if res.magnitude is not None:
        desc_mag = json.dumps({"channels": list(MAGNITUDE_CHANNELS), "axes": "C" + res.axes,
                               "unit": "log10(µm^2/s) where the class is diffusion, log10(µm/s) where ballistic or flow",
                               "intervals": "68 % = mean ± SD, 95 % = mean ± 1.96 SD of the model's Gaussian "
                                            "predictive distribution", "masked": "NaN (also where indeterminate)",
                               "source": res.sources})
        atomic_write(paths["magnitude.tif"], lambda t: tifffile.imwrite(t, res.magnitude, description=desc_mag,
                                                                         metadata=None, photometric="minisblack"))
    return list(paths.values())

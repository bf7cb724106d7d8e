"""The ONNX runtime of the classifier: one session factory and the model (numpy and onnxruntime; no torch).

:func:`onnx_session` is the only place an onnxruntime session is built (classify, the export's parity
check, ``doct-train``'s timing, the trade-off study): CPU provider, ``threads`` intra-op threads, one
inter-op thread, no spinning (a spinning thread stalls beside other busy processes; the numbers do not
depend on it). :class:`ClassifierModel` is an ONNX file written by :mod:`classifier.export` with its
metadata (format :data:`FORMAT` under the key :data:`METADATA_KEY`): the feature columns, the classes,
the indeterminate rule and the feature spec.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchdoct.files import shipped_files
from torchdoct.runtime.threads import map_ordered, resolve_threads

from .features import FeatureSpec, shipped_or_path, spec_from_dict

__all__ = [
    "METADATA_KEY",
    "FORMAT",
    "CHUNK_ROWS",
    "DEFAULT_MODEL",
    "onnx_session",
    "ClassifierModel",
    "shipped_models",
    "load_model",
]

#: Key of the model's metadata JSON in the ONNX ``metadata_props``.
METADATA_KEY = "torchdoct_classifier"
#: Format of that metadata document (written by :func:`classifier.export.build_metadata`).
FORMAT = "torchdoct-classifier/1"
#: Name of the shipped default model (``classifier/data/<name>.onnx``).
DEFAULT_MODEL = "single-acquisition"
#: Rows per onnxruntime call: the network's intermediate tensors of 2048 rows stay in the core's cache
#: (1.2-1.4x the throughput of 131072-row chunks, `torchdoct bench classify`). onnxruntime's matrix
#: kernels take rows in groups of 4 and round the rows of an incomplete group differently (~1e-7), so a
#: multiple of 4 keeps every row's result independent of the chunk size and of the thread count.
CHUNK_ROWS = 1 << 11


def onnx_session(model: str | os.PathLike | bytes, *, threads: int = 1, name: str | None = None):
    """An onnxruntime ``InferenceSession`` of an ONNX file (path) or serialized model (bytes).

    ``threads``: intra-op threads (1 for the classify path, which runs chunks side by side instead).
    A file onnxruntime cannot read is a ``ValueError`` naming it (``name``, default the file name).
    """
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3  # errors only: onnxruntime's warnings would be lines beside ours
    source = model if isinstance(model, bytes) else str(model)
    try:
        return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own exception types
        label = name or ("serialized model" if isinstance(model, bytes) else Path(model).name)
        raise ValueError(_unreadable_model(label, str(err), ort.__version__)) from None


#: The ``ai.onnx`` opsets onnxruntime guarantees (its lowest; the highest is its own, named in the message).
MIN_OPSET = 7


def _unreadable_model(label: str, err: str, version: str) -> str:
    """One line for a model onnxruntime refused: an IR version or opset outside what this onnxruntime reads
    names the supported range and the fix (:mod:`classifier.export` writes opset 17, IR version 8); any
    other refusal is onnxruntime's own message on one line."""
    import re

    text = " ".join(err.split())
    ir = re.search(r"Unsupported model IR version: (\d+), max supported IR version: (\d+)", text)
    if ir:
        return (
            f"model {label}: ONNX IR version {ir.group(1)} is not one onnxruntime {version} reads (IR versions "
            f"up to {ir.group(2)}); export the model with IR version {ir.group(2)} or lower (doct-train writes "
            "IR version 8, opset 17), or upgrade onnxruntime"
        )
    opset = re.search(r"Opset (\d+) is under development.*?till opset (\d+)", text)
    old = re.search(r"No Op registered for (\w+) with domain_version of (\d+)", text)
    outside: tuple[str, str | int] | None = None  # (the model's opset, the highest this onnxruntime reads)
    if opset:
        outside = (opset.group(1), opset.group(2))
    elif old and int(old.group(2)) < MIN_OPSET:
        outside = (old.group(2), _highest_opset())
    if outside is not None:
        got, top = outside
        return (
            f"model {label}: ONNX opset {got} is outside the opsets onnxruntime {version} supports "
            f"({MIN_OPSET} to {top}); export the model at an opset in that range (doct-train writes opset 17)"
        )
    text = re.sub(r"/\S+\.(?:h|cc):\d+ [^)]*\)\s*", "", text)  # onnxruntime's source location and signature
    return f"model {label}: not a readable ONNX model ({text})"


def _highest_opset() -> int:
    """The highest ``ai.onnx`` opset of this onnxruntime's operator schemas."""
    from onnxruntime.capi import _pybind_state

    return max(s.since_version for s in _pybind_state.get_all_operator_schema() if s.domain in ("", "ai.onnx"))


def shipped_models() -> dict[str, Path]:
    """Names and paths of the models shipped in ``classifier/data/``."""
    return shipped_files("classifier", "data", ".onnx")


@dataclass
class ClassifierModel:
    """An ONNX motion-type model and its metadata (see :mod:`classifier.export`).

    ``threads``: chunks of ``chunk_rows`` rows classified side by side, one onnxruntime thread each.
    """

    path: Path
    metadata: dict[str, Any]
    session: Any
    threads: int = 1
    chunk_rows: int = CHUNK_ROWS
    #: the conformal calibration stored beside the model (``NAME.calibration.json``, :mod:`classifier.conformal`), or None
    calibration: dict[str, Any] | None = None

    def _chunks(self, fn, n: int) -> None:
        """``fn(slice)`` over fixed chunks of ``chunk_rows`` rows, ``threads`` chunks side by side (one
        onnxruntime thread each: no stalls beside other busy processes; the chunks, hence the numbers, do
        not depend on ``threads``)."""
        step = self.chunk_rows
        parts = [slice(i, min(n, i + step)) for i in range(0, n, step)]
        for _ in map_ordered(fn, parts, self.threads):
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
        if mean is None or sd is None:  # both or neither
            raise ValueError(f"model {self.path.name} has no magnitude head")
        return mean, sd

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Probabilities ``[N, C]`` of inputs ``[N, F+1]`` (features + pool_pixels), float32."""
        return self.predict_all(x, magnitude=False)[0]

    def predict_all(
        self, x: np.ndarray, magnitude: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
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


def load_model(
    model: str | os.PathLike | None = None,
    *,
    threads: int | None = None,
    shipped: Mapping[str, Path] | None = None,
    chunk_rows: int = CHUNK_ROWS,
    calibration: bool = True,
) -> ClassifierModel:
    """Open an ONNX model: ``None`` (the shipped default), a shipped name, a ``.onnx`` path, or a directory
    holding one (``doct-train --out DIR``).

    ``threads``: chunks of pixels classified side by side, each on one onnxruntime thread with spinning
    off (default: ``$TORCHDOCT_THREADS``, else the usable cores; see :mod:`torchdoct.runtime.threads`).
    ``shipped``: the shipped models by name (default :func:`shipped_models`). ``calibration``: read the
    conformal calibration beside the model (:func:`read_calibration`; False: leave it, as the calibration does).
    """
    shipped = shipped_models() if shipped is None else shipped
    key = DEFAULT_MODEL if model is None else str(model)
    if (
        key not in shipped and not key.endswith(".onnx") and Path(key).is_dir()
    ):  # a doct-train output directory: its one model
        found = sorted(Path(key).glob("*.onnx"))
        if len(found) != 1:
            raise ValueError(
                f"model directory {key}: holds {len(found)} .onnx files "
                f"({', '.join(p.name for p in found) or 'none'}); give the .onnx file itself"
            )
        key = str(found[0])
    path = shipped_or_path(key, dict(shipped), "model")
    if path.suffix != ".onnx":
        raise ValueError(f"model {path.name}: must be an .onnx file written by doct-train")
    n_threads = resolve_threads(threads)
    sess = onnx_session(path, threads=1)
    props = sess.get_modelmeta().custom_metadata_map
    if METADATA_KEY not in props:
        raise ValueError(f"model {path.name}: no '{METADATA_KEY}' metadata; it was not written by doct-train")
    from torchdoct.files import check_nesting
    from torchdoct.measured.guards import json_loads

    check_nesting(props[METADATA_KEY], f"model {path.name}: metadata")  # before the parser's recursion
    try:  # an integer of thousands of digits is read as inf, and named by the field's type check
        meta = json_loads(props[METADATA_KEY])
    except ValueError as err:
        raise ValueError(
            f"model {path.name}: its '{METADATA_KEY}' metadata is not valid JSON ({err}); export the "
            "model again with doct-train"
        ) from None
    if not isinstance(meta, dict):
        raise ValueError(
            f"model {path.name}: its '{METADATA_KEY}' metadata is not a JSON object; export the model "
            "again with doct-train"
        )
    if meta.get("format") != FORMAT:
        raise ValueError(f"model {path.name}: metadata format {meta.get('format')!r}, this version reads {FORMAT!r}")
    _check_metadata_types(path, meta)
    _check_graph_matches_metadata(path, sess, meta)
    return ClassifierModel(
        path=path,
        metadata=meta,
        session=sess,
        threads=n_threads,
        chunk_rows=chunk_rows,
        calibration=read_calibration(path, list(meta["output"]["classes"])) if calibration else None,
    )


#: Largest calibration file read (bytes): a shipped one holds a few thousand scores per pool.
MAX_CALIBRATION_BYTES = 16 << 20


def calibration_path(model_path: Path) -> Path:
    """``NAME.calibration.json`` beside ``NAME.onnx``."""
    return Path(model_path).with_name(Path(model_path).stem + ".calibration.json")


def read_calibration(model_path: Path, classes: list[str]) -> dict[str, Any] | None:
    """The model's conformal calibration (:mod:`classifier.conformal`), None when there is no file beside it;
    a ``ValueError`` naming the file and the fix when it is unreadable or not for this model."""
    from .conformal import check_calibration

    p = calibration_path(model_path)
    if not p.exists():
        return None
    if not p.is_file():
        raise ValueError(
            f"{p}: not a regular file; remove it or calibrate the model again (python -m classifier.calibrate)"
        )
    if p.stat().st_size > MAX_CALIBRATION_BYTES:
        raise ValueError(
            f"{p}: {p.stat().st_size} bytes, more than a calibration holds ({MAX_CALIBRATION_BYTES}); "
            "calibrate the model again"
        )
    try:
        from torchdoct.files import check_nesting
        from torchdoct.measured.guards import json_loads

        raw = p.read_text(encoding="utf-8")
        check_nesting(raw, p.name)
        cal = json_loads(raw)
    except (UnicodeDecodeError, ValueError) as err:
        raise ValueError(
            f"{p}: not a calibration JSON file ({err}); calibrate the model again (python -m classifier.calibrate)"
        ) from None
    check_calibration(cal, classes, str(p))
    return cal


def _check_metadata_types(path: Path, meta: Any) -> None:
    """Every metadata field the classify path reads has its type (a wrongly typed one is refused naming
    the field, instead of being ignored or failing later): ``input.columns`` and ``output.classes`` lists
    of names (columns: or tables with a ``name``), ``rule`` a table, ``spec`` a table when present, ``rule.min_probability`` in [0, 1), ``rule.epsilon`` a number,
    ``rule.kind``/``rule.indeterminate_class`` strings, ``pool_pixels_max`` a positive integer,
    ``magnitude`` a table when present."""
    fix = "use the .onnx file as doct-train wrote it, or retrain with doct-train"

    def bad(field: str, want: str, value: Any) -> ValueError:
        return ValueError(
            f"model {path.name}: metadata field {field} must be {want}; got {type(value).__name__} "
            f"{str(value)[:40]!r}; {fix}"
        )

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if not isinstance(meta, dict):
        raise bad("(the whole)", "a JSON object", meta)
    for block, key in (("input", "columns"), ("output", "classes")):
        b = meta.get(block)
        v = b.get(key) if isinstance(b, dict) else None
        if (
            not isinstance(b, dict)
            or not isinstance(v, list)
            or not all(isinstance(c, str) or (isinstance(c, dict) and isinstance(c.get("name"), str)) for c in v)
        ):
            raise bad(f"{block}.{key}", "a list of names (or of tables with a name)", v if isinstance(b, dict) else b)
    if not isinstance(meta.get("rule"), dict):
        raise bad("rule", "a table (JSON object)", meta.get("rule"))
    if meta.get("spec") is not None and not isinstance(meta["spec"], dict):
        raise bad("spec", "a table (JSON object)", meta["spec"])
    rule = meta["rule"]
    for key in ("kind", "indeterminate_class"):
        if not isinstance(rule.get(key), str):
            raise bad(f"rule.{key}", "a string", rule.get(key))
    mp = rule.get("min_probability")
    if not (number(mp) and 0.0 <= mp < 1.0):
        raise bad("rule.min_probability", "a number in [0, 1)", mp)
    if "epsilon" in rule and not number(rule["epsilon"]):
        raise bad("rule.epsilon", "a number", rule["epsilon"])
    pp = meta.get("pool_pixels_max", 1)
    if isinstance(pp, bool) or not isinstance(pp, int) or pp < 1:
        raise bad("pool_pixels_max", "a positive integer", pp)
    if meta.get("magnitude") is not None and not isinstance(meta["magnitude"], dict):
        raise bad("magnitude", "a table (JSON object)", meta["magnitude"])


def _check_graph_matches_metadata(path: Path, sess: Any, meta: Mapping[str, Any]) -> None:
    """The network's input width and output widths must be those its metadata declares (feature columns,
    classes, magnitude classes): an edited or mismatched file is refused by name before any pixel runs,
    instead of failing inside onnxruntime or numpy."""
    fix = "use the .onnx file as doct-train wrote it, or retrain with doct-train"
    try:
        declared = {"features": len(meta["input"]["columns"]), "probabilities": len(meta["output"]["classes"])}
        if meta.get("magnitude"):
            declared["log10_magnitude"] = declared["log10_magnitude_sd"] = len(meta["magnitude"]["classes"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"model {path.name}: metadata lacks {err}; {fix}") from None
    graph = {a.name: a.shape for a in list(sess.get_inputs()) + list(sess.get_outputs())}
    for name, width in declared.items():
        shape = graph.get(name)
        if shape is None:
            kind = "input" if name == "features" else "output"
            raise ValueError(f"model {path.name}: the network has no '{name}' {kind}; {fix}")
        if len(shape) != 2 or (isinstance(shape[1], int) and shape[1] != width):
            what = "input columns" if name == "features" else "columns"
            raise ValueError(
                f"model {path.name}: the network's '{name}' is {shape}, but its metadata declares {width} {what}; {fix}"
            )

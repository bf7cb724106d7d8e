"""ONNX export of a :class:`~classifier.model.MotionClassifier`, with its metadata, and a runtime check.

The graph is written operator by operator with :mod:`onnx.helper` at a fixed opset
(:data:`OPSET` = 17): ``Max``/``Add``/``Log`` and ``Where`` for the fixed transforms, ``Sub``/``Div``
for the standardisation, ``Gemm``/``Relu`` for the layers, ``Div`` by the temperature and
``Softmax``. Writing the graph directly keeps the file independent of torch's exporters (the
TorchScript one is deprecated, the torch.export one needs onnxscript) and makes every node
reviewable; :func:`onnx_parity` checks the result in onnxruntime against torch.

Metadata (``metadata_props``): key :data:`METADATA_KEY` holds one JSON document with the input
columns (feature names, metrics, units, system configurations), the class names, the
indeterminate rule, the feature spec, the prior, the training recipe, a summary of the report and
the package versions; keys ``classes`` and ``feature_names`` repeat the essentials as plain JSON
lists. Model files are ONNX only; nothing is ever unpickled.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

__all__ = [
    "OPSET",
    "METADATA_KEY",
    "FORMAT",
    "build_metadata",
    "onnx_model",
    "export_onnx",
    "onnx_parity",
    "runtime_checks",
    "model_from_onnx",
]

from .runtime import FORMAT, METADATA_KEY, onnx_session

OPSET = 17


def build_metadata(result) -> dict[str, Any]:
    """The metadata document of a :class:`classifier.train.TrainResult`."""
    import torchdoct

    from . import __version__
    from .features import metric_unit
    from .prior import CLASSES

    spec = result.spec
    columns = []
    for (metric, conf), name in zip(spec.features, spec.feature_names):
        columns.append(
            {
                "name": name,
                "metric": metric,
                "unit": metric_unit(metric),
                "configuration": conf.name,
                "wavelength_um": conf.wavelength_um,
                "lateral_resolution_um": conf.lateral_resolution_um,
                "axial_resolution_um": conf.axial_resolution_um,
            }
        )
        if conf.lateral_resolution_y_um is not None:  # an anisotropic lateral PSF (isotropic: no key)
            columns[-1]["lateral_resolution_y_um"] = conf.lateral_resolution_y_um
    columns.append(
        {
            "name": "pool_pixels",
            "metric": "pool_pixels",
            "unit": "pixels",
            "description": "number of independent pixels averaged into the feature vector (1 = one pixel)",
        }
    )
    rep = result.report
    summary = {}
    for pool, m in rep["test"]["network"].items():
        summary[pool] = {
            k: m[k]
            for k in (
                "accuracy_all",
                "balanced_accuracy_all",
                "coverage_identifiable",
                "accuracy_identifiable",
                "balanced_accuracy_identifiable",
                "ece",
            )
        }
    return {
        "format": FORMAT,
        "classifier_version": __version__,
        "torchdoct_version": torchdoct.__version__,
        "onnx_opset": OPSET,
        "input": {"name": "features", "dtype": "float32", "shape": ["N", len(columns)], "columns": columns},
        "output": {
            "name": "probabilities",
            "dtype": "float32",
            "shape": ["N", len(rep["classes"])],
            "classes": list(rep["classes"]),
        },
        **(
            {
                "magnitude": {
                    "outputs": ["log10_magnitude", "log10_magnitude_sd"],
                    "shape": ["N", len(CLASSES)],
                    "classes": list(CLASSES),
                    "units": {"diffusion": "log10(µm^2/s)", "ballistic": "log10(µm/s)", "flow": "log10(µm/s)"},
                    "meaning": "per motion class k: predicted log10 magnitude given class k and the SD of a "
                    "Gaussian predictive distribution (68 % interval = mean ± SD, 95 % = ± 1.96 SD)",
                    "test": rep["magnitude"],
                }
            }
            if "magnitude" in rep
            else {}
        ),
        "rule": result.rule,
        "pool_pixels_max": result.config.max_pool_pixels,
        "spec": spec.to_dict(),
        "prior": result.prior.to_dict(),
        "train_config": result.config.to_dict(),
        "test_summary_by_pool": summary,
    }


def _np(t) -> np.ndarray:
    return t.detach().cpu().numpy().astype(np.float32)


def onnx_model(model, metadata: dict[str, Any]):
    """The :class:`onnx.ModelProto` of ``model`` (eval mode) with ``metadata`` (module docstring)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    from torch import nn

    from .model import DECORRELATION_OFFSET, LIV_OFFSET_DB2

    # Step 1 in one pass over the columns: u = max(sign·x + shift, floor) + offset, log where a column is
    # transformed: LIV log(max(x, 0) + 0.01), correlations log(max(1 − x, 0) + 0.001), pool_pixels
    # log(max(x, 1)) (classifier.model.MotionClassifier.transform; the per-column vectors encode the masks).
    width = model.n_features + 1
    liv = model.liv_mask.cpu().numpy().astype(bool)
    corr = model.corr_mask.cpu().numpy().astype(bool)
    pool = model.pool_mask.cpu().numpy().astype(bool)
    sign = np.where(corr, -1.0, 1.0).astype(np.float32)
    shift = np.where(corr, 1.0, 0.0).astype(np.float32)
    floor = np.where(pool, 1.0, 0.0).astype(np.float32)
    offset = np.select([liv, corr], [LIV_OFFSET_DB2, DECORRELATION_OFFSET], 0.0).astype(np.float32)
    inits = [
        numpy_helper.from_array(sign, "t_sign"),
        numpy_helper.from_array(shift, "t_shift"),
        numpy_helper.from_array(floor, "t_floor"),
        numpy_helper.from_array(offset, "t_offset"),
        numpy_helper.from_array(liv | corr | pool, "t_log"),
        numpy_helper.from_array(_np(model.feature_mean), "feature_mean"),
        numpy_helper.from_array(_np(model.feature_scale), "feature_scale"),
        numpy_helper.from_array(np.array(float(model.temperature), np.float32), "temperature"),
    ]
    nodes = [
        helper.make_node("Mul", ["features", "t_sign"], ["x_signed"]),
        helper.make_node("Add", ["x_signed", "t_shift"], ["x_shifted"]),
        helper.make_node("Max", ["x_shifted", "t_floor"], ["x_floored"]),
        helper.make_node("Add", ["x_floored", "t_offset"], ["x_offset"]),
        helper.make_node("Log", ["x_offset"], ["x_log"]),
        helper.make_node("Where", ["t_log", "x_log", "features"], ["t"]),
        helper.make_node("Sub", ["t", "feature_mean"], ["t_c"]),
        helper.make_node("Div", ["t_c", "feature_scale"], ["h0"]),
    ]
    cur = "h0"
    linear = [m for m in model.net if isinstance(m, nn.Linear)]
    hidden_out = "h0"
    for i, lin in enumerate(linear):
        inits.append(numpy_helper.from_array(_np(lin.weight), f"w{i}"))
        inits.append(numpy_helper.from_array(_np(lin.bias), f"b{i}"))
        out = f"z{i}"
        nodes.append(helper.make_node("Gemm", [cur, f"w{i}", f"b{i}"], [out], transB=1))
        if i < len(linear) - 1:
            nodes.append(helper.make_node("Relu", [out], [f"h{i + 1}"]))
            cur = f"h{i + 1}"
            hidden_out = cur
        else:
            cur = out
    nodes.append(helper.make_node("Div", [cur, "temperature"], ["scaled"]))
    nodes.append(helper.make_node("Softmax", ["scaled"], ["probabilities"], axis=1))
    outputs = [helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, ["N", model.n_classes])]
    k = getattr(model, "n_magnitude", 0)
    if k:  # magnitude heads on the last hidden layer: mean and SD = exp(logvar/2)·scale (classifier.model)
        inits += [
            numpy_helper.from_array(_np(model.magnitude_mean.weight), "mag_mean_w"),
            numpy_helper.from_array(_np(model.magnitude_mean.bias), "mag_mean_b"),
            numpy_helper.from_array(_np(model.magnitude_logvar.weight), "mag_logvar_w"),
            numpy_helper.from_array(_np(model.magnitude_logvar.bias), "mag_logvar_b"),
            numpy_helper.from_array(np.array(0.5, np.float32), "half"),
            numpy_helper.from_array(np.array(float(model.magnitude_sd_scale), np.float32), "mag_sd_scale"),
        ]
        nodes += [
            helper.make_node("Gemm", [hidden_out, "mag_mean_w", "mag_mean_b"], ["log10_magnitude"], transB=1),
            helper.make_node("Gemm", [hidden_out, "mag_logvar_w", "mag_logvar_b"], ["mag_logvar"], transB=1),
            helper.make_node("Mul", ["mag_logvar", "half"], ["mag_half_logvar"]),
            helper.make_node("Exp", ["mag_half_logvar"], ["mag_sd_raw"]),
            helper.make_node("Mul", ["mag_sd_raw", "mag_sd_scale"], ["log10_magnitude_sd"]),
        ]
        outputs += [
            helper.make_tensor_value_info("log10_magnitude", TensorProto.FLOAT, ["N", k]),
            helper.make_tensor_value_info("log10_magnitude_sd", TensorProto.FLOAT, ["N", k]),
        ]
    graph = helper.make_graph(
        nodes,
        "motion_classifier",
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["N", width])],
        outputs,
        initializer=inits,
    )
    proto = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="torchdoct-classifier",
        producer_version=metadata.get("classifier_version", ""),
        doc_string="DOCT motion-type classifier: features [N, F+1] -> class probabilities [N, C]; "
        f"see metadata key '{METADATA_KEY}'",
    )
    proto.ir_version = 8  # the IR version of opset 17
    props = {
        METADATA_KEY: json.dumps(metadata, default=_plain),
        "classes": json.dumps(metadata["output"]["classes"]),
        "feature_names": json.dumps([c["name"] for c in metadata["input"]["columns"]]),
    }
    helper.set_model_props(proto, props)
    onnx.checker.check_model(proto)
    return proto


def _plain(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def export_onnx(model, metadata: dict[str, Any], path) -> None:
    """Write ``model`` with ``metadata`` to ``path`` (atomically; the caller checks overwriting)."""
    from torchdoct.files import atomic_write

    proto = onnx_model(model, metadata)
    data = proto.SerializeToString()

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    atomic_write(path, write)


def onnx_parity(model, path, x: np.ndarray, chunk: int = 65536) -> float:
    """Max |p_onnxruntime − p_torch| over the rows of ``x`` ``[N, F+1]`` (and, for magnitude models, over
    the predicted log10 magnitude, and over its predictive SD in log10 units up to one decade and relative
    above: an input far outside the training data can be given an SD of a hundred decades, whose float32
    rounding is then 1e-4 decades with nothing to do with parity)."""
    import torch

    sess = onnx_session(path)
    worst = 0.0
    for i in range(0, len(x), chunk):
        xb = np.ascontiguousarray(x[i : i + chunk], dtype=np.float32)
        p_ort = sess.run(["probabilities"], {"features": xb})[0]
        with torch.no_grad():
            p_t = model(torch.from_numpy(xb)).numpy()
        worst = max(worst, float(np.abs(p_ort - p_t).max()))
        if getattr(model, "n_magnitude", 0):
            m_ort, s_ort = sess.run(["log10_magnitude", "log10_magnitude_sd"], {"features": xb})
            with torch.no_grad():
                m_t, s_t = (v.numpy() for v in model.magnitude(torch.from_numpy(xb)))
            worst = max(
                worst,
                float(np.abs(m_ort - m_t).max()),
                float((np.abs(s_ort - s_t) / np.maximum(np.abs(s_t), 1.0)).max()),
            )
    return worst


def runtime_checks(result, path, repeats: int = 3) -> float:
    """The exported model at ``path`` checked and timed in onnxruntime, recorded in ``result.report``.

    ``onnx_parity_max_abs_diff`` (:func:`onnx_parity` on the test inputs), ``onnx_opset`` and the timing
    row ``network (onnxruntime, 1 thread)`` (best of ``repeats`` runs over the test inputs, µs per sample).
    Returns the parity.
    """
    import time

    parity = onnx_parity(result.model, path, result.test_inputs)
    sess = onnx_session(path)
    xs = np.ascontiguousarray(result.test_inputs, np.float32)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        sess.run(["probabilities"], {"features": xs})
        best = min(best, time.perf_counter() - t)
    rep = result.report
    rep["timing"]["network (onnxruntime, 1 thread)"] = {
        "train_s": rep["timing"]["network"]["train_s"],
        "inference_us_per_sample": best / len(xs) * 1e6,
    }
    rep["onnx_parity_max_abs_diff"] = parity
    rep["onnx_opset"] = OPSET
    return parity


def model_from_onnx(path):
    """Rebuild the torch :class:`~classifier.model.MotionClassifier` from an exported ONNX file.

    Reads the initializers written by :func:`onnx_model` (no pickle involved); used to check a
    shipped model against torch and to continue from it.
    """
    import onnx
    import torch
    from onnx import numpy_helper

    from .model import MotionClassifier

    proto = onnx.load(str(path))
    init = {t.name: np.array(numpy_helper.to_array(t)) for t in proto.graph.initializer}
    n_layers = sum(1 for name in init if name.startswith("w"))
    if n_layers < 1 or not ("t_sign" in init or "liv_mask" in init):
        raise ValueError(f"{path}: not a model written by classifier.export")
    weights = [init[f"w{i}"] for i in range(n_layers)]
    if "t_sign" in init:  # the per-column transform vectors of onnx_model
        corr_mask = init["t_sign"] < 0
        liv_mask = init["t_log"].astype(bool) & ~corr_mask & (init["t_floor"] == 0)
    else:  # files of the earlier graph: masks as initializers
        liv_mask = init["liv_mask"].astype(bool)
        corr_mask = init["corr_mask"].astype(bool) if "corr_mask" in init else np.zeros_like(liv_mask)
    width = liv_mask.size
    hidden = [w.shape[0] for w in weights[:-1]]
    k = init["mag_mean_w"].shape[0] if "mag_mean_w" in init else 0
    with torch.random.fork_rng(devices=[]):  # the initial weights are overwritten; keep the global RNG untouched
        model = MotionClassifier(
            width - 1,
            weights[-1].shape[0],
            np.flatnonzero(liv_mask[:-1]).tolist(),
            hidden,
            n_magnitude=k,
            correlation_columns=np.flatnonzero(corr_mask[:-1]).tolist(),
        )
    with torch.no_grad():
        model.feature_mean.copy_(torch.from_numpy(init["feature_mean"]))
        model.feature_scale.copy_(torch.from_numpy(init["feature_scale"]))
        model.temperature.fill_(float(init["temperature"]))
        linear = [m for m in model.net if isinstance(m, torch.nn.Linear)]
        for i, lin in enumerate(linear):
            lin.weight.copy_(torch.from_numpy(init[f"w{i}"]))
            lin.bias.copy_(torch.from_numpy(init[f"b{i}"]))
        if k:
            for head in ("mean", "logvar"):
                getattr(model, f"magnitude_{head}").weight.copy_(torch.from_numpy(init[f"mag_{head}_w"]))
                getattr(model, f"magnitude_{head}").bias.copy_(torch.from_numpy(init[f"mag_{head}_b"]))
            model.magnitude_sd_scale.fill_(float(init["mag_sd_scale"]))
    return model.eval()

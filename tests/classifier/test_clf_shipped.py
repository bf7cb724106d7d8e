"""The shipped models: metadata, report, onnxruntime-vs-torch parity, and (slow) reproduction by doct-train."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from classifier.export import OPSET, model_from_onnx
from classifier.features import load_spec
from classifier.infer import DEFAULT_MODEL, load_model, shipped_models
from classifier.prior import Prior, draw_parameters
from classifier.rule import INDETERMINATE
from classifier.simulation import simulate_draw
from classifier.train import CLASS_NAMES, TrainConfig, default_prior

DATA = Path(__file__).resolve().parents[2] / "classifier" / "data"
#: doct-train from scratch must give the shipped report's numbers within this many of the report's
#: bootstrap standard errors (on the machine that trained it the run is bit-identical; elsewhere floating-point
#: differences may change the trained weights slightly).
REPRODUCTION_Z = 2.0


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
@pytest.mark.parametrize(
    "name",
    [
        "single-acquisition",
        "two-wavelength",
        "signature",
        "two-wavelength-signature",
        "signature-bscan",
        "signature-bscan-field",
        "signature-aline",
        "single-acquisition-bscan",
    ],
)
def test_shipped_model_metadata_and_report(name):
    assert DEFAULT_MODEL == "single-acquisition" and name in shipped_models()
    model = load_model(name, threads=1)
    meta = model.metadata
    spec = load_spec(name)
    assert model.spec == spec
    assert model.classes == list(CLASS_NAMES) and model.rule["indeterminate_class"] == INDETERMINATE
    assert [c["name"] for c in model.columns] == [*spec.feature_names, "pool_pixels"]
    assert [c.get("unit") for c in model.columns] == [*spec.feature_units, "pixels"]
    # the recipe's prior (classifier.train.SPEC_RECIPES: the flow's polar-angle law, a bulk-phase residual;
    # scaled to the system for classifier.train.SCALED_PRIOR_SPECS)
    cfg = TrainConfig.for_spec(name)
    recipe_prior = default_prior(cfg)
    # models trained before the recipe took the uniform-angle law carry the isotropic default prior
    assert meta["onnx_opset"] == OPSET == 17 and meta["prior"] in (recipe_prior.to_dict(), Prior().to_dict())
    report = json.loads((DATA / f"{name}.json").read_text())
    assert report["onnx_parity_max_abs_diff"] <= 1e-5
    assert report["spec"] == spec.to_dict() and report["rule"] == model.rule
    for pool, summary in meta["test_summary_by_pool"].items():
        for key, value in summary.items():
            assert report["test"]["network"][pool][key] == pytest.approx(value, rel=1e-12)
    # calibrated, so that doct-classify answers conformal sets whichever model it picks: the record of this
    # model's prior at the calibration seed, every pool size, scores a set holds its class for in ≥ 1 − α
    from classifier.calibrate import CALIBRATION_SEED, POOLS

    cal = model.calibration
    assert cal is not None and cal["model"] == name and cal["description"]["seed"] == CALIBRATION_SEED
    assert cal["description"]["prior"] == meta["prior"]
    assert [p["pool_pixels"] for p in cal["pools"]] == list(POOLS)
    for p in cal["pools"]:
        assert p["set_sizes"]["0.1"]["in_sample_coverage"] >= 0.9, (name, p["pool_pixels"])


def test_default_model_matches_torch_on_simulated_features():
    """onnxruntime against the torch network rebuilt from the file's weights: max |Δp| <= 1e-5."""
    spec = load_spec(DEFAULT_MODEL)
    prior = Prior()
    xs = []
    for k in range(3):  # one draw of each motion type, two (static fraction, SNR) replicates
        d = draw_parameters(prior, 123, "test", k, replicates=2)
        x, zero = simulate_draw(spec, d, prior, trials=64, truncation_tolerance=1e-2)
        xs.append(x.reshape(-1, spec.n_features)[~zero.reshape(-1)])
    x = np.concatenate(xs)
    inputs = np.concatenate([x, np.ones((len(x), 1), np.float32)], axis=1)
    pooled = inputs.copy()
    pooled[:, -1] = np.arange(len(x)) % 48 + 1
    onnx_model = load_model(DEFAULT_MODEL, threads=1)
    torch_model = model_from_onnx(shipped_models()[DEFAULT_MODEL])
    for batch in (inputs, pooled):
        with torch.no_grad():
            p_torch = torch_model(torch.from_numpy(batch)).numpy()
        assert float(np.abs(onnx_model.predict(batch) - p_torch).max()) <= 1e-5


def test_signature_model_magnitude_outputs_match_torch():
    """The shipped signature model's magnitude outputs: onnxruntime against torch within 1e-5."""
    spec = load_spec("signature")
    prior = Prior()
    xs = []
    for k in range(3):
        d = draw_parameters(prior, 321, "test", k, replicates=1)
        x, zero, _ = simulate_draw(spec, d, prior, trials=64, truncation_tolerance=1e-2)
        xs.append(x.reshape(-1, spec.n_features)[~zero.reshape(-1)])
    x = np.concatenate(xs)
    inputs = np.concatenate([x, (np.arange(len(x)) % 48 + 1)[:, None].astype(np.float32)], axis=1)
    onnx_model = load_model("signature", threads=1)
    torch_model = model_from_onnx(shipped_models()["signature"])
    assert onnx_model.has_magnitude and torch_model.n_magnitude == 3
    with torch.no_grad():
        p_torch = torch_model(torch.from_numpy(inputs)).numpy()
        m_torch, s_torch = (v.numpy() for v in torch_model.magnitude(torch.from_numpy(inputs)))
    m_ort, s_ort = onnx_model.predict_magnitude(inputs)
    assert float(np.abs(onnx_model.predict(inputs) - p_torch).max()) <= 1e-5
    assert float(np.abs(m_ort - m_torch).max()) <= 1e-5 and float(np.abs(s_ort - s_torch).max()) <= 1e-5


@pytest.mark.slow
@pytest.mark.retrain
@pytest.mark.parametrize("spec", ["single-acquisition", "signature"])
def test_doct_train_reproduces_the_shipped_model(tmp_path, spec):
    """``doct-train`` with its defaults, from scratch (no cache), gives the shipped report's accuracy
    (marker ``retrain``: a full training each)."""
    from classifier.cli import train_main

    out = tmp_path / "model"
    assert train_main(["--out", str(out), "--spec", spec, "--no-cache", "--no-progress"]) == 0
    new = json.loads((out / f"{spec}.json").read_text())
    old = json.loads((DATA / f"{spec}.json").read_text())
    for pool in ("1", "25"):
        for key in ("accuracy_identifiable", "balanced_accuracy_identifiable", "coverage_identifiable", "ece"):
            tol = REPRODUCTION_Z * old["standard_errors"][pool][key]
            assert abs(new["test"]["network"][pool][key] - old["test"]["network"][pool][key]) <= tol, (pool, key)
    if "magnitude" in old:
        for pool in ("1", "25"):
            assert (
                abs(new["magnitude"][pool]["median_abs_log10_error"] - old["magnitude"][pool]["median_abs_log10_error"])
                <= 0.05
            ), pool

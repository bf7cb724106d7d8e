"""The network's fixed transforms and the ONNX export: graph, metadata, parity with torch, loading rules."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from classifier.export import METADATA_KEY, OPSET, model_from_onnx, onnx_model, onnx_parity
from classifier.infer import load_model
from classifier.model import DECORRELATION_OFFSET, LIV_OFFSET_DB2, MotionClassifier


def _model(seed: int = 0) -> MotionClassifier:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        m = MotionClassifier(4, 4, [0, 2], hidden=(16, 8))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.feature_mean.copy_(torch.randn(5, generator=gen))
        m.feature_scale.copy_(torch.rand(5, generator=gen) + 0.5)
        m.temperature.fill_(1.3)
    return m.eval()


def _inputs(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.empty((n, 5), np.float32)
    x[:, [0, 2]] = rng.choice([0.0, 1e-7, 0.3, 31.0, 80.0], size=(n, 2)) * rng.random((n, 2)) * 2
    x[:, [1, 3]] = rng.uniform(-0.6, 1.3, size=(n, 2))
    x[:, 4] = rng.integers(1, 49, n)
    x[:3, 4] = [0.5, 1.0, 48.0]
    return x


def _metadata() -> dict:
    return {
        "format": "torchdoct-classifier/1",
        "classifier_version": "0",
        "torchdoct_version": "0",
        "input": {"columns": [{"name": n} for n in ("liv@a", "ocds@a", "liv@b", "ocds@b", "pool_pixels")]},
        "output": {"classes": ["diffusion", "ballistic", "flow", "indeterminate"]},
        "rule": {
            "kind": "class-or-threshold",
            "indeterminate_class": "indeterminate",
            "min_probability": 0.5,
            "epsilon": 0.05,
        },
    }  # doct-train always writes its rule (the classify path reads it)


def test_transform_is_the_documented_one():
    m = _model()
    x = torch.tensor([[0.0, -0.2, 30.0, 0.4, 1.0], [-1.0, 0.9, 1e-3, 0.0, 25.0], [5.0, 0.1, 5.0, 0.1, 0.2]])
    t = m.transform(x)
    np.testing.assert_allclose(t[:, 0], np.log(np.clip(x[:, 0].numpy(), 0, None) + LIV_OFFSET_DB2), rtol=1e-6)
    np.testing.assert_allclose(t[:, 2], np.log(x[:, 2].numpy() + LIV_OFFSET_DB2), rtol=1e-6)
    np.testing.assert_array_equal(t[:, [1, 3]], x[:, [1, 3]])
    np.testing.assert_allclose(t[:, 4], np.log(np.maximum(x[:, 4].numpy(), 1.0)), atol=1e-7)
    p = m(x)
    np.testing.assert_allclose(p.sum(1).detach().numpy(), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="pool_pixels"):
        m(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="outside"):
        MotionClassifier(3, 4, [3])


def test_set_normalization_standardizes():
    m = _model()
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(500, 5, generator=gen) * torch.tensor([40.0, 1.0, 40.0, 1.0, 30.0])
    m.set_normalization(x)
    z = (m.transform(x) - m.feature_mean) / m.feature_scale
    np.testing.assert_allclose(z.mean(0).detach().numpy(), 0.0, atol=1e-5)
    np.testing.assert_allclose(z.std(0).detach().numpy(), 1.0, atol=1e-5)


def test_onnx_graph_metadata_and_parity(tmp_path):
    m = _model(3)
    proto = onnx_model(m, _metadata())
    assert proto.opset_import[0].version == OPSET == 17
    props = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(props[METADATA_KEY])["output"]["classes"][-1] == "indeterminate"
    assert json.loads(props["feature_names"])[-1] == "pool_pixels"
    path = tmp_path / "m.onnx"
    path.write_bytes(proto.SerializeToString())
    x = _inputs(5000, 4)
    assert onnx_parity(m, path, x) <= 1e-5
    back = model_from_onnx(path)
    with torch.no_grad():
        np.testing.assert_array_equal(back(torch.from_numpy(x)).numpy(), m(torch.from_numpy(x)).numpy())
    loaded = load_model(path, threads=1)
    p = loaded.predict(x)
    with torch.no_grad():
        assert float(np.abs(p - m(torch.from_numpy(x)).numpy()).max()) <= 1e-5
    assert loaded.classes == _metadata()["output"]["classes"]


def test_correlation_columns_read_as_log_decorrelation(tmp_path):
    """Correlation coefficients enter as log(max(1 - rho, 0) + offset): a slope against log(lag) of 1 for
    an exponential decay (diffusion), 2 for a Gaussian one (ballistic, flow); the same in ONNX."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(2)
        m = MotionClassifier(4, 4, [3], hidden=(8,), correlation_columns=[0, 1])
    with pytest.raises(ValueError, match="both"):
        MotionClassifier(4, 4, [1], correlation_columns=[1])
    lag = torch.tensor([1.0, 2.0, 4.0, 8.0])
    for power in (1.0, 2.0):
        rho = 1.0 - 1e-2 * (lag / 8.0) ** power  # 1 - rho from 1e-2/8^p to 1e-2: above the offset's scale
        x = torch.stack([rho, rho, torch.zeros(4), torch.ones(4), torch.ones(4)], 1)
        t = m.transform(x)[:, 0].double()
        slope = np.polyfit(np.log(lag.numpy()), t.numpy(), 1)[0]
        big = (1e-2 * (lag / 8.0) ** power).double()
        np.testing.assert_allclose(t.numpy(), np.log(big.numpy() + DECORRELATION_OFFSET), rtol=1e-5)
        assert slope == pytest.approx(power * float(np.mean((big / (big + DECORRELATION_OFFSET)).numpy())), rel=0.25)
    x = torch.tensor([[1.0, 1.2, 0.5, 3.0, 1.0], [-0.4, 0.0, 0.5, -1.0, 4.0]])
    t = m.transform(x)
    np.testing.assert_allclose(
        t[:, :2], np.log(np.clip(1.0 - x[:, :2].numpy(), 0, None) + DECORRELATION_OFFSET), rtol=1e-6
    )  # rho >= 1 (a static pixel) sits at log(offset)
    np.testing.assert_array_equal(t[:, 2], x[:, 2])
    path = tmp_path / "c.onnx"
    path.write_bytes(
        onnx_model(
            m.eval(),
            {
                **_metadata(),
                "input": {
                    "columns": [
                        {"name": n}
                        for n in ("rho_lin_1@a", "rho_lin_2@a", "lin_contrast@a", "db_variance@a", "pool_pixels")
                    ]
                },
            },
        ).SerializeToString()
    )
    rng = np.random.default_rng(0)
    xs = np.concatenate(
        [rng.uniform(-0.3, 1.0, (2000, 3)), rng.uniform(0, 40, (2000, 1)), rng.integers(1, 49, (2000, 1))], 1
    ).astype(np.float32)
    xs[:5, :2] = 1.0
    assert onnx_parity(m, path, xs) <= 1e-5
    back = model_from_onnx(path)
    assert back.corr_mask.tolist() == m.corr_mask.tolist()
    with torch.no_grad():
        np.testing.assert_array_equal(back(torch.from_numpy(xs)).numpy(), m(torch.from_numpy(xs)).numpy())


def test_load_model_refuses_foreign_files(tmp_path):
    bad = tmp_path / "model.pkl"
    bad.write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(ValueError, match=".onnx"):
        load_model(bad)
    with pytest.raises(FileNotFoundError, match="shipped"):
        load_model(tmp_path / "none.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not an onnx file")
    with pytest.raises(ValueError, match="garbage.onnx"):
        load_model(garbage)
    # a valid ONNX graph without our metadata
    proto = onnx_model(_model(), _metadata())
    del proto.metadata_props[:]
    plain = tmp_path / "plain.onnx"
    plain.write_bytes(proto.SerializeToString())
    with pytest.raises(ValueError, match="metadata"):
        load_model(plain)
    proto = onnx_model(_model(), {**_metadata(), "format": "something-else/9"})
    other = tmp_path / "other.onnx"
    other.write_bytes(proto.SerializeToString())
    with pytest.raises(ValueError, match="format"):
        load_model(other)


def test_exported_softmax_rows_sum_to_one(tmp_path):
    m = _model(7)
    path = tmp_path / "m.onnx"
    path.write_bytes(onnx_model(m, _metadata()).SerializeToString())
    p = load_model(path, threads=1).predict(_inputs(1000, 8))
    assert p.dtype == np.float32 and np.all(p >= 0)
    np.testing.assert_allclose(p.sum(1), 1.0, atol=1e-6)


def test_correlation_columns_of_the_shipped_specs():
    """The signature specs' correlation coefficients, and only they, are read as log decorrelation; the
    shipped signature model carries exactly these columns."""
    from classifier.features import load_spec
    from classifier.infer import shipped_models
    from classifier.train import _correlation_columns

    for name in ("signature", "two-wavelength-signature", "single-acquisition"):
        spec = load_spec(name)
        cols = _correlation_columns(spec)
        assert [spec.features[i][0] for i in cols] == [m for m, _ in spec.features if m.startswith("rho_lin_")]
        assert all(spec.features[i][0] not in ("lin_contrast", "db_variance", "liv", "ocds") for i in cols)
    m = model_from_onnx(shipped_models()["signature"])
    assert np.flatnonzero(m.corr_mask.numpy()).tolist() == _correlation_columns(load_spec("signature"))
    assert np.flatnonzero(m.liv_mask.numpy()).tolist() == [
        i for i, (metric, _) in enumerate(load_spec("signature").features) if metric == "db_variance"
    ]

"""The signature path of the classifier: simulated signature features, the magnitude head and its
ONNX outputs, magnitude maps in doct-classify, and the choice of the default model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier.export import build_metadata, export_onnx, model_from_onnx, onnx_parity
from classifier.features import load_spec
from classifier.infer import MAGNITUDE_CHANNELS, MASKED, classify_maps, load_model, write_classification
from classifier.prior import Draw, Prior
from classifier.simulation import simulate_draw
from classifier.train import TrainConfig, train


def _draw(label, magnitude, static=0.0, snr=math.nan):
    return Draw(
        label=label,
        magnitude=magnitude,
        polar_angle_deg=50.0,
        azimuth_deg=10.0,
        density_per_um3=0.05,
        sim_seed=4242 + label,
        nuisance=((static, snr),),
    )


def test_signature_spec_features_and_same_pixels_as_liv_ocds():
    spec = load_spec("signature")
    assert spec.is_signature and not spec.needs_field and spec.n_features == 3 * len(spec.metrics)
    assert [c.name for c in spec.configurations] == [c.name for c in load_spec("single-acquisition").configurations]
    d = _draw(2, 0.3, static=0.3, snr=30.0)
    x, zero, ref = simulate_draw(spec, d, Prior(), trials=64, truncation_tolerance=1e-2)
    assert x.shape == (1, 64, spec.n_features) and ref.shape == (1, 64, 6) and not zero.any()
    # the LIV/OCDS of the very same simulated pixels are those of the single-acquisition path
    x_lo, _ = simulate_draw(load_spec("single-acquisition"), d, Prior(), trials=64, truncation_tolerance=1e-2)
    np.testing.assert_array_equal(ref, x_lo)
    # db_variance is LIV (same definition, physics.md §1)
    liv_cols = [i for i, (m, c) in enumerate(spec.features) if m == "db_variance"]
    np.testing.assert_allclose(x[0][:, liv_cols], x_lo[0][:, 0::2], rtol=1e-5)
    # a random bulk phase per frame leaves the (intensity-only) signature unchanged
    xb, _, refb = simulate_draw(spec, d, Prior(), trials=64, truncation_tolerance=1e-2, bulk_phase=True)
    np.testing.assert_allclose(xb, x, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(refb, ref, rtol=1e-4, atol=1e-4)


@pytest.fixture(scope="module")
def magnitude_model(tmp_path_factory):
    """A tiny two-wavelength model with the magnitude head (cheap to simulate)."""
    tmp = tmp_path_factory.mktemp("clf-mag")
    res = train(
        TrainConfig(
            spec="two-wavelength",
            draws_train=12,
            draws_validation=6,
            draws_test=6,
            replicates=2,
            max_epochs=4,
            singles_per_group=16,
            pooled_per_group=4,
            magnitude=True,
            baselines=False,
        ),
        cache_dir=tmp / "cache",
        log=None,
    )
    path = tmp / "mag.onnx"
    export_onnx(res.model, build_metadata(res), path)
    return res, path


def test_magnitude_head_report_and_onnx_parity(magnitude_model):
    res, path = magnitude_model
    assert onnx_parity(res.model, path, res.test_inputs) <= 1e-5
    back = model_from_onnx(path)
    x = torch.from_numpy(res.test_inputs)
    with torch.no_grad():
        for a, b in zip(res.model.magnitude(x), back.magnitude(x)):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        mean, sd = res.model.magnitude(x)
    assert bool((sd > 0).all()) and mean.shape == (len(x), 3)
    mdl = load_model(path, threads=1)
    assert mdl.has_magnitude and mdl.metadata["magnitude"]["classes"] == ["diffusion", "ballistic", "flow"]
    m_ort, s_ort = mdl.predict_magnitude(res.test_inputs)
    np.testing.assert_allclose(m_ort, mean.numpy(), atol=1e-5)
    np.testing.assert_allclose(s_ort, sd.numpy(), rtol=1e-5)
    # the report's coverage is the share of identifiable test pixels inside mean ± SD of their true class
    rep = res.report["magnitude"]["1"]
    s = res.datasets["test"]
    ident = s.status == 0
    y = s.y[ident]
    err = np.abs(m_ort[ident][np.arange(len(y)), y] - np.log10(s.magnitude[ident]))
    sdv = s_ort[ident][np.arange(len(y)), y]
    assert rep["samples"] == len(y)
    assert rep["coverage_68"] == pytest.approx(np.mean(err <= sdv), abs=2.0 / len(y))
    assert rep["median_abs_log10_error"] == pytest.approx(np.median(err), abs=1e-4)


def test_classify_writes_magnitude_maps(magnitude_model, tmp_path):
    res, path = magnitude_model
    spec = res.spec
    d = _draw(0, 3e-3)
    x, _ = simulate_draw(spec, d, Prior(), trials=64, truncation_tolerance=1e-2)
    feats = x[0].T.reshape(spec.n_features, 8, 8)
    data = np.concatenate([feats, np.full((1, 8, 8), 20.0, np.float32)])
    maps = save_maps(tmp_path / "maps.npz", data, maps_meta(spec, feature_channels(spec)))
    out = classify_maps(maps, path, threads=1)
    assert out.magnitude.shape == (len(MAGNITUDE_CHANNELS), 8, 8)
    decided = (out.labels != MASKED) & (out.labels < 3)
    m, lo68, hi68, lo95, hi95 = out.magnitude
    assert np.all(np.isfinite(m[decided])) and np.all(np.isnan(m[~decided]))
    assert np.all((lo95 <= lo68) & (lo68 <= m) & (m <= hi68) & (hi68 <= hi95)[decided] if decided.any() else True)
    mdl = load_model(path, threads=1)
    inputs = np.concatenate([feats.reshape(spec.n_features, -1).T, np.ones((64, 1), np.float32)], axis=1)
    mean, sd = mdl.predict_magnitude(inputs)
    lab = out.labels.reshape(-1)
    rows = np.flatnonzero(decided.reshape(-1))
    np.testing.assert_allclose(m.reshape(-1)[rows], mean[rows, lab[rows]], atol=1e-6)
    np.testing.assert_allclose(hi95.reshape(-1)[rows] - m.reshape(-1)[rows], 1.959964 * sd[rows, lab[rows]], rtol=1e-5)
    written = {p.name for p in write_classification(out, tmp_path / "out")}
    assert "magnitude.tif" in written
    import tifffile

    np.testing.assert_array_equal(tifffile.imread(tmp_path / "out" / "magnitude.tif"), out.magnitude)


def test_default_model_follows_the_maps_channels(tmp_path, capsys):
    """Without --model: the shipped signature model when the maps have its channels (also intensity-only
    maps: it reads only the intensity part), else the LIV/OCDS model with a note."""
    from classifier.infer import DEFAULT_MODEL, SIGNATURE_MODEL, default_model_for, read_maps

    sig, lo = load_spec("signature"), load_spec("single-acquisition")
    rng = np.random.default_rng(1)
    chans = feature_channels(lo, with_mean_db=False) + feature_channels(sig)
    data = rng.uniform(0.1, 1.0, size=(len(chans), 6, 6)).astype(np.float32)
    meta = maps_meta(sig, chans)
    meta["signature"] = {"features": list(sig.metrics), "intensity_only": True}
    full = save_maps(tmp_path / "full.npz", data, meta)
    assert default_model_for([read_maps(full)]) == (SIGNATURE_MODEL, None)
    res = classify_maps(full, threads=1)
    assert res.model.path.stem == SIGNATURE_MODEL and res.magnitude is not None
    plain = save_maps(tmp_path / "plain.npz", data[:7], maps_meta(lo, feature_channels(lo)))
    name, note = default_model_for([read_maps(plain)])
    assert name == DEFAULT_MODEL and "--signature" in note
    res = classify_maps(plain, threads=1)
    assert res.model.path.stem == DEFAULT_MODEL and res.magnitude is None and "--signature" in res.info["model_choice"]
    from classifier.cli import classify_main

    assert classify_main([str(plain), "--out", str(tmp_path / "out")]) == 0
    assert "note: model single-acquisition (LIV/OCDS): the maps have no signature channels" in capsys.readouterr().out


def test_a_model_that_needs_the_phase_refuses_intensity_only_maps(tmp_path):
    spec_path = tmp_path / "phase.toml"
    spec_path.write_text("""name = "phase-test"
metrics = ["rho_lin_1", "g1_1"]
[[configuration]]
name = "original"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
""")
    res = train(
        TrainConfig(
            spec=str(spec_path),
            draws_train=6,
            draws_validation=3,
            draws_test=3,
            replicates=1,
            max_epochs=2,
            singles_per_group=8,
            pooled_per_group=2,
            baselines=False,
            eval_pools=(1, 4),
            max_pool_pixels=8,
        ),
        cache_dir=tmp_path / "cache",
        log=None,
    )
    assert res.spec.needs_field
    path = tmp_path / "phase.onnx"
    export_onnx(res.model, build_metadata(res), path)
    chans = [c for c in feature_channels(res.spec) if c["metric"] != "g1_1"]
    meta = maps_meta(res.spec, chans)
    meta["signature"] = {"features": ["rho_lin_1"], "intensity_only": True}
    maps = save_maps(tmp_path / "inten.npz", np.ones((len(chans), 4, 4), np.float32), meta)
    with pytest.raises(ValueError, match="needs the complex field's phase"):
        classify_maps(maps, path, threads=1)


def test_maps_signature_then_classify_uses_the_signature_model(tmp_path, capsys):
    """torchdoct maps --signature → doct-classify (no --model): the channels match the shipped signature model."""
    from classifier.cli import classify_main
    from torchdoct.cli import main as td_main
    from torchdoct.measured.io import write_sequence

    rng = np.random.default_rng(3)
    t, z, x = 32, 12, 12
    e = np.empty((t, z, x), np.complex64)
    e[0] = rng.standard_normal((z, x)) + 1j * rng.standard_normal((z, x))
    for i in range(1, t):  # partially decorrelating speckle
        e[i] = 0.9 * e[i - 1] + math.sqrt(1 - 0.81) * (rng.standard_normal((z, x)) + 1j * rng.standard_normal((z, x)))
    seq = write_sequence(
        tmp_path / "seq.npz",
        e,
        {
            "axes": "TZX",
            "pitch_um": {"z": 1.5, "x": 2.0},
            "frame_times_s": [0.2048 * i for i in range(t)],
            "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
        },
    )
    maps = tmp_path / "maps.npz"
    assert (
        td_main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(maps),
                "--no-progress",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert classify_main([str(maps), "--out", str(tmp_path / "out"), "--background-db", "none"]) == 0
    out = capsys.readouterr().out
    # B-scan maps (axes TZX, lateral reduction along x only): the B-scan signature model
    assert "model signature-bscan.onnx (signature-bscan)" in out and (tmp_path / "out" / "magnitude.tif").exists()


def test_ablation_subsets_are_candidates_and_name_the_shipped_content():
    from research.ablation import SUBSETS, candidate_spec
    from torchdoct.sim.signature import DEFAULT_FEATURES, available_features

    cand = set(candidate_spec().metrics)
    assert all(set(v) <= cand for v in SUBSETS.values())
    chosen = [v for k, v in SUBSETS.items() if "the signature spec" in k]
    assert len(chosen) == 1 and set(chosen[0]) == set(load_spec("signature").metrics)
    # the maps' default signature holds the spec's features as its intensity part
    assert set(load_spec("signature").metrics) == set(available_features(DEFAULT_FEATURES, False))


@pytest.mark.slow
def test_indeterminate_measurement_partitions_the_test_split(tmp_path):
    """``python -m research.ablation --indeterminate``: the three regimes partition the test pixels that
    are identifiable or decorrelated, and every score is a probability."""
    from classifier.dataset import make_dataset
    from classifier.prior import Prior
    from research.ablation import run_indeterminate

    res = run_indeterminate(draws_train=12, draws_test=6, pixels=3000, cache_dir=tmp_path, log=None)
    te = make_dataset(
        __import__("research.ablation", fromlist=["candidate_spec"]).candidate_spec(),
        Prior(),
        split="test",
        draws=6,
        cache_dir=tmp_path,
    )
    counts = res["test_samples"]
    assert counts["identifiable"] == int((te.status == 0).sum())
    assert counts["decorrelated, transit visible"] + counts["decorrelated, flat"] == int((te.status == 2).sum())
    for row in res["features"].values():
        for v in row.values():
            b = v["balanced_accuracy_identifiable"]
            assert b != b or 0.0 <= b <= 1.0

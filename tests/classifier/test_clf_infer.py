"""doct-classify: maps reading and checks, pooling, classification, outputs, and no torch on this path."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier.cli import classify_main
from classifier.export import build_metadata, export_onnx
from classifier.infer import MASKED, classify_maps, independent_fraction, load_model, pool_features, read_maps
from classifier.pooling import effective_count
from classifier.prior import Draw, Prior
from classifier.rule import apply_rule
from classifier.simulation import simulate_draw
from classifier.train import TrainConfig, train

REPO = Path(__file__).resolve().parents[2]
Z, X = 10, 24  # rows 0-7: three 8-column regions of simulated pixels; rows 8-9: background


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A tiny two-wavelength model and a synthetic maps file of simulated pixels."""
    tmp = tmp_path_factory.mktemp("clf-infer")
    res = train(
        TrainConfig(
            spec="two-wavelength",
            draws_train=9,
            draws_validation=6,
            draws_test=6,
            replicates=2,
            max_epochs=4,
            singles_per_group=16,
            pooled_per_group=4,
        ),
        cache_dir=tmp / "cache",
        log=None,
    )
    model_path = tmp / "tiny.onnx"
    export_onnx(res.model, build_metadata(res), model_path)
    spec = res.spec
    feats = np.zeros((spec.n_features, Z, X), np.float32)
    truth = np.full((Z, X), -1)
    for label, mag, col in ((0, 3e-3, 0), (1, 0.2, 8), (2, 2.0, 16)):
        d = Draw(
            label=label,
            magnitude=mag,
            polar_angle_deg=60.0,
            azimuth_deg=0.0,
            density_per_um3=0.06,
            sim_seed=100 + label,
            nuisance=((0.0, math.nan),),
        )
        x, zero = simulate_draw(spec, d, Prior(), trials=64, truncation_tolerance=1e-2)
        feats[:, :8, col : col + 8] = x[0].T.reshape(spec.n_features, 8, 8)
        truth[:8, col : col + 8] = label
    rng = np.random.default_rng(0)
    feats[:, 8:, :] = rng.uniform(0.1, 1.0, size=(spec.n_features, 2, X))  # finite, but background
    feats[1, 3, 5] = np.nan
    mean_db = rng.normal(20.0, 2.0, size=(Z, X)).astype(np.float32)
    mean_db[8:, :] = -40.0
    data = np.concatenate([feats, mean_db[None]])
    meta = maps_meta(spec, feature_channels(spec))
    npz = save_maps(tmp / "maps.npz", data, meta)
    tif = save_maps(tmp / "maps.tif", data, meta)
    return {
        "tmp": tmp,
        "model": model_path,
        "spec": spec,
        "npz": npz,
        "tif": tif,
        "data": data,
        "meta": meta,
        "truth": truth,
    }


def test_classification_is_the_model_and_rule_on_valid_pixels(setup):
    res = classify_maps(setup["npz"], setup["model"], threads=1, abstain_ambiguous=False)
    assert res.labels.shape == (Z, X) and res.labels.dtype == np.uint8
    assert np.all(res.labels[8:, :] == MASKED) and res.labels[3, 5] == MASKED
    assert res.info["background_pixels"] == 2 * X and res.info["nan_pixels"] == 1
    valid = res.mask
    assert valid.sum() == 8 * X - 1 == res.info["classified"]
    model = load_model(setup["model"], threads=1)
    f = setup["data"][:-1][:, valid].T
    x = np.concatenate([f, np.ones((len(f), 1), np.float32)], axis=1)
    p = model.predict(x)
    labels, _ = apply_rule(p, model.classes, model.rule)
    np.testing.assert_array_equal(res.labels[valid], labels)
    np.testing.assert_allclose(res.probabilities[:, valid].T, p, atol=1e-7)
    assert np.all(np.isnan(res.probabilities[:, ~valid]))
    np.testing.assert_allclose(np.nansum(res.probabilities, axis=0)[valid], 1.0, atol=1e-5)
    # the TIFF flavour of the same maps gives the same result
    res_tif = classify_maps(setup["tif"], setup["model"], threads=1, abstain_ambiguous=False)
    np.testing.assert_array_equal(res_tif.labels, res.labels)


def test_two_files_are_combined_channel_by_channel(setup, tmp_path):
    _spec, data, meta = setup["spec"], setup["data"], setup["meta"]
    ch = meta["channels"]
    first = [i for i, c in enumerate(ch) if c["wavelength_um"] == 0.84]
    second = [i for i, c in enumerate(ch) if c["wavelength_um"] == 1.31]
    a = save_maps(tmp_path / "a.npz", data[first], {**meta, "channels": [ch[i] for i in first]})
    b = save_maps(tmp_path / "b.npz", data[second], {**meta, "channels": [ch[i] for i in second]})
    res2 = classify_maps([a, b], setup["model"], threads=1)
    res1 = classify_maps(setup["npz"], setup["model"], threads=1)
    np.testing.assert_array_equal(res2.labels, res1.labels)
    with pytest.raises(ValueError, match="liv@1310nm"):
        classify_maps([a], setup["model"], threads=1)


@pytest.mark.parametrize(
    "change, text",
    [
        (dict(n_frames=16), "16 frames"),
        (dict(frame_interval_s=0.1), "0.2048 s apart"),
        (dict(ocds_delay_range_s=[0.2048, 0.8192]), "OCDS delay range"),
        (dict(refractive_index=1.37), "refractive_index"),
    ],
)
def test_protocol_and_system_mismatches_are_named(setup, tmp_path, change, text):
    meta = maps_meta(setup["spec"], feature_channels(setup["spec"]), **change)
    path = save_maps(tmp_path / "m.npz", setup["data"], meta)
    with pytest.raises(ValueError, match=text):
        classify_maps(path, setup["model"], threads=1)
    if "refractive_index" in change:
        classify_maps(path, setup["model"], threads=1, ignore_refractive_index=True)


def test_missing_channel_and_wrong_unit_are_named(setup, tmp_path):
    spec, data = setup["spec"], setup["data"]
    ch = feature_channels(spec)
    ch[3] = {**ch[3], "axial_resolution_um": 14.0}  # ocds at 1310 nm now has the wrong resolution
    path = save_maps(tmp_path / "m.npz", data, maps_meta(spec, ch))
    with pytest.raises(ValueError, match=r"ocds at 1310 nm, lateral 4.9 µm, axial 3.8 µm.*Fix"):
        classify_maps(path, setup["model"], threads=1)
    ch = feature_channels(spec)
    ch[0] = {**ch[0], "unit": "dB"}
    path = save_maps(tmp_path / "u.npz", data, maps_meta(spec, ch))
    with pytest.raises(ValueError, match="unit"):
        classify_maps(path, setup["model"], threads=1)


def test_read_maps_rejects_bad_files(setup, tmp_path):
    with pytest.raises(FileNotFoundError):
        read_maps(tmp_path / "none.npz")
    (tmp_path / "x.h5").write_bytes(b"")
    with pytest.raises(ValueError, match=r"\.npz, \.tif"):
        read_maps(tmp_path / "x.h5")
    np.savez(tmp_path / "nomaps.npz", other=np.zeros(3))
    with pytest.raises(ValueError, match="'maps'"):
        read_maps(tmp_path / "nomaps.npz")
    meta = setup["meta"]
    path = save_maps(tmp_path / "short.npz", setup["data"][:-1], meta)  # one channel fewer than listed
    with pytest.raises(ValueError, match="one entry per map"):
        read_maps(path)
    np.savez(tmp_path / "int.npz", maps=np.zeros((2, 3, 3), np.int32), meta_json=np.asarray(json.dumps(meta)))
    with pytest.raises(TypeError, match="floating"):
        read_maps(tmp_path / "int.npz")
    import tifffile

    tifffile.imwrite(tmp_path / "plain.tif", np.zeros((2, 3, 3), np.float32), photometric="minisblack")
    with pytest.raises(ValueError, match="ImageDescription"):
        read_maps(tmp_path / "plain.tif")


def test_pool_features_equals_brute_force():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(2, 3, 9, 11)).astype(np.float32)  # [F, Y, Z, X]
    valid = rng.random((3, 9, 11)) > 0.3
    for n in (1, 2, 3, 5, 9):
        pooled, counts = pool_features(f, valid, n)
        h1, h2 = n // 2, n - 1 - n // 2
        for y in range(3):
            for z in range(9):
                for x in range(11):
                    zs, xs = slice(max(0, z - h1), z + h2 + 1), slice(max(0, x - h1), x + h2 + 1)
                    w = valid[y, zs, xs]
                    assert counts[y, z, x] == (w.sum() if n > 1 else valid[y, z, x])
                    if n > 1 and w.any():
                        np.testing.assert_allclose(
                            pooled[:, y, z, x], f[:, y, zs, xs][:, w].mean(1), rtol=1e-5, atol=1e-6
                        )
    with pytest.raises(ValueError, match="pool"):
        pool_features(f, valid, 0)


def test_independent_fraction_limits(setup):
    spec = setup["spec"]
    # pixels far apart are independent; pixels much finer than the speckle count as few
    assert independent_fraction(5, {"z": 50.0, "x": 50.0}, spec) == pytest.approx(1.0, abs=1e-9)
    assert independent_fraction(5, None, spec) == 1.0 and independent_fraction(1, {"z": 0.1, "x": 0.1}, spec) == 1.0
    fine = independent_fraction(5, {"z": 0.01, "x": 0.01}, spec)
    assert fine == pytest.approx(1 / 25, rel=1e-3)
    # effective count of two pixels with correlation r: 4 / (2 + 2r)
    r = math.exp(-1.0 / 2.0)
    assert effective_count(2, 1.0, 1.0) == pytest.approx(4.0 / (2.0 + 2.0 * r))


def test_pooling_feeds_the_independent_pixel_count(setup):
    res1 = classify_maps(setup["npz"], setup["model"], threads=1)
    res5 = classify_maps(setup["npz"], setup["model"], pool=5, threads=1)
    frac = res5.info["pool_independent_fraction"]
    assert 0 < frac < 1 and res5.info["pool"] == 5
    assert np.array_equal(res5.mask, res1.mask)
    # pooled probabilities differ from single-pixel ones (the features and pool_pixels changed)
    assert not np.allclose(np.nan_to_num(res5.probabilities), np.nan_to_num(res1.probabilities))


def test_cli_writes_outputs_and_refuses_to_overwrite(setup, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [str(setup["npz"]), "--model", str(setup["model"]), "--out", str(out), "--threads", "1"]
    assert classify_main(argv) == 0
    assert "pixels/s" in capsys.readouterr().out
    names = {p.name for p in out.iterdir()}
    assert names == {"classes.tif", "probabilities.tif", "legend.json", "summary.json", "overlay.png"}
    import tifffile

    with tifffile.TiffFile(out / "classes.tif") as tf:
        labels = tf.asarray()
        desc = json.loads(tf.imagej_metadata["Info"])
    assert labels.shape == (Z, X) and [c["name"] for c in desc["legend"]["classes"]] == [
        "diffusion",
        "ballistic",
        "flow",
        "indeterminate",
        "diffusion-or-ballistic",
        "diffusion-or-flow",
        "ballistic-or-flow",
    ]
    assert desc["legend"]["masked_value"] == MASKED
    probs = tifffile.imread(out / "probabilities.tif")
    assert probs.shape == (4, Z, X)
    summary = json.loads((out / "summary.json").read_text())
    assert sum(summary["counts"].values()) == Z * X
    assert classify_main(argv) == 2
    assert "exists" in capsys.readouterr().err
    assert classify_main([*argv, "--force", "--pool", "3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["info"]["pool"] == 3
    assert classify_main([*argv, "--force", "--background-db", "loud"]) == 2
    assert classify_main([str(tmp_path / "missing.npz"), "--out", str(out)]) == 2
    assert classify_main([*argv, "--force", "--pool", "0"]) == 2


def _classify_without_torch(npz, model, out, *extra: str) -> subprocess.CompletedProcess:
    """``doct-classify NPZ --model MODEL --out OUT EXTRA…`` in a fresh interpreter; it asserts exit 0 and
    that no ``torch`` module was loaded, then prints ``ok``."""
    args = ", ".join(repr(a) for a in (str(npz), "--model", str(model), "--out", str(out), "--threads", "1", *extra))
    code = (
        "import sys\nfrom classifier.cli import classify_main\n"
        f"rc = classify_main([{args}])\n"
        "assert rc == 0, rc\n"
        "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))\n"
        "assert not bad, bad\nprint('ok')\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=Path(out).parent, timeout=120
    )


def test_classify_path_does_not_import_torch(setup, tmp_path):
    out = _classify_without_torch(setup["npz"], setup["model"], tmp_path / "o")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")


def test_volume_maps_are_classified_per_bscan(setup, tmp_path):
    """[C, Y, Z, X] maps (TIFF pages restored by the axes): every B-scan as the 2-D map alone."""
    data = np.stack([setup["data"], setup["data"]], axis=1)  # [C, 2, Z, X]
    meta = {**setup["meta"], "axes": "CYZX", "pitch_um": {"z": 2.0, "x": 2.0, "y": 2.0}}
    path = save_maps(tmp_path / "vol.tif", data, meta)
    assert read_maps(path).data.shape == data.shape
    flat = classify_maps(setup["npz"], setup["model"], pool=3, threads=1, abstain_ambiguous=False)
    vol = classify_maps(path, setup["model"], pool=3, threads=1, abstain_ambiguous=False)
    assert vol.labels.shape == (2, Z, X)
    for y in range(2):
        np.testing.assert_array_equal(vol.labels[y], flat.labels)
    out = tmp_path / "o"
    assert classify_main([str(path), "--model", str(setup["model"]), "--out", str(out), "--pool", "3"]) == 0
    assert (out / "overlay.png").stat().st_size > 0


def _broken_maps_files(setup, tmp_path) -> dict[str, tuple[Path, str]]:
    """name -> (file, text the error must contain besides the file name)."""
    meta, data = setup["meta"], setup["data"]
    raw = setup["npz"].read_bytes()
    tif = setup["tif"].read_bytes()
    files = {}

    def put(name, content, text):
        p = tmp_path / name
        p.write_bytes(content)
        files[name] = (p, text)

    put("empty.npz", b"", "empty")
    put("truncated.npz", raw[: len(raw) // 2], "truncated")
    put("header.npz", raw[:30], "truncated")
    put("text.npz", b"maps,meta\n1,2\n", "not a .npz")
    put("empty.tif", b"", "empty")
    put("truncated.tif", tif[: len(tif) // 3], "truncated")
    for name, meta_json, text in (
        ("badjson.npz", np.asarray("{not json"), "not valid JSON"),
        ("listjson.npz", np.asarray(json.dumps([1, 2])), "JSON object"),
        ("pickled.npz", np.array([meta], dtype=object), "pickle"),
        ("numjson.npz", np.arange(3.0), "JSON text"),
    ):
        p = tmp_path / name
        np.savez(p, maps=data, meta_json=meta_json)
        files[name] = (p, text)
    p = tmp_path / "pickledmaps.npz"
    np.savez(p, maps=np.array([data], dtype=object), meta_json=np.asarray(json.dumps(meta)))
    files[p.name] = (p, "pickle")
    p = tmp_path / "channelsjson.npz"
    np.savez(p, maps=data, meta_json=np.asarray(json.dumps({**meta, "channels": "lots"})))
    files[p.name] = (p, "channels")
    return files


def test_unreadable_maps_files_are_named_with_the_fix(setup, tmp_path):
    for name, (path, text) in _broken_maps_files(setup, tmp_path).items():
        with pytest.raises(ValueError) as info:
            read_maps(path)
        msg = str(info.value)
        assert name in msg and text in msg, (name, msg)
        if text in ("empty", "truncated", "not a .npz"):
            assert "torchdoct maps" in msg, msg  # the fix: write it again


def test_cli_unreadable_maps_exit_2_with_one_line(setup, tmp_path, capsys):
    for name, (path, _text) in _broken_maps_files(setup, tmp_path).items():
        code = classify_main(
            [str(path), "--model", str(setup["model"]), "--out", str(tmp_path / "o"), "--threads", "1"]
        )
        captured = capsys.readouterr()
        assert code == 2, (name, captured.err)
        assert captured.err.startswith("error: ") and captured.err.count("\n") == 1, captured.err
        assert name in captured.err and captured.out == ""
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_pool_larger_than_the_image_is_refused(setup, tmp_path, capsys):
    assert Z % 2 == 0  # the largest valid pool is the largest odd one
    assert classify_maps(setup["npz"], str(setup["model"]), pool=Z - 1, threads=1).info["pool"] == Z - 1
    for pool in (Z + 1, X + 1, 1001):
        with pytest.raises(ValueError) as info:
            classify_maps(setup["npz"], str(setup["model"]), pool=pool, threads=1)
        msg = str(info.value)
        assert f"{Z} × {X}" in msg and f"largest valid pool is {Z - 1}" in msg and "maps.npz" in msg, msg
    out = tmp_path / "o"
    assert (
        classify_main(
            [
                str(setup["npz"]),
                "--model",
                str(setup["model"]),
                "--out",
                str(out),
                "--threads",
                "1",
                "--pool",
                str(X + 1),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--pool" in err and f"largest valid pool is {Z - 1}" in err
    assert not out.exists()


@pytest.mark.parametrize("pool", [2, 4, 10])
def test_an_even_pool_is_refused_naming_the_odd_ones_beside_it(setup, tmp_path, capsys, pool):
    with pytest.raises(ValueError, match=rf"pool \(--pool\) must be odd.*half a pixel.*give {pool - 1} or {pool + 1}"):
        classify_maps(setup["npz"], str(setup["model"]), pool=pool, threads=1)
    out = tmp_path / "o"
    assert (
        classify_main(
            [
                str(setup["npz"]),
                "--model",
                str(setup["model"]),
                "--out",
                str(out),
                "--threads",
                "1",
                "--pool",
                str(pool),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: pool (--pool) must be odd") and not out.exists()


def test_cli_exit_codes_follow_the_convention(setup, tmp_path, capsys, monkeypatch):
    """0 done, 2 bad input or usage (nothing written), 1 the system refused a write (one error line)."""
    import classifier.infer as infer

    argv = [str(setup["npz"]), "--model", str(setup["model"]), "--threads", "1"]
    with pytest.raises(SystemExit) as info:
        classify_main(argv)  # no --out: argparse usage error
    assert info.value.code == 2
    capsys.readouterr()
    (tmp_path / "file").write_text("x")
    assert classify_main([*argv, "--out", str(tmp_path / "file")]) == 2
    assert "is a file" in capsys.readouterr().err

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "o" / "classes.tif"))

    monkeypatch.setattr(infer, "write_classification", full)
    assert classify_main([*argv, "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "No space left" in err


def test_predictions_do_not_depend_on_chunks_or_threads(monkeypatch):
    """The shipped signature model on 5003 rows: bit-identical for any chunk size (a multiple of 4, see
    classifier.infer._CHUNK) and thread count, the 3 rows of the last incomplete group of 4 included."""
    import classifier.infer as infer

    rng = np.random.default_rng(11)
    ref_model = load_model("signature", threads=1)
    x = rng.uniform(0.0, 1.0, (5003, len(ref_model.columns))).astype(np.float32)
    x[:, -1] = rng.integers(1, 26, len(x))
    ref = ref_model.predict_all(x)
    for chunk, threads in ((8, 1), (1000, 2), (1 << 17, 2)):
        monkeypatch.setattr(infer, "_CHUNK", chunk)
        got = load_model("signature", threads=threads).predict_all(x)
        for a, b in zip(ref, got):
            assert np.array_equal(a, b), (chunk, threads)


def _calibrated_copy(setup, tmp_path, seed=3):
    """A copy of the tiny model with a calibration beside it, from scores of its own test-like pixels."""
    import shutil

    from classifier.conformal import SCHEMA_VERSION, scores_lac

    model = tmp_path / "cal.onnx"
    shutil.copy(setup["model"], model)
    m = load_model(model, threads=1)
    rng = np.random.default_rng(seed)
    pools = []
    for n in (1, 4):
        p = rng.dirichlet(np.ones(len(m.classes)), size=400)
        truth = rng.integers(0, len(m.classes), 400)
        pools.append(
            {
                "pool_pixels": n,
                "samples": 400,
                "scores": [float(v) for v in scores_lac(p, truth)],
                "truth": [int(v) for v in truth],
            }
        )
    cal = {
        "schema_version": SCHEMA_VERSION,
        "model": m.spec.name,
        "score": "lac",
        "classes": m.classes,
        "mode": "class-conditional",
        "pools": pools,
        "guarantee": "test",
    }
    (tmp_path / "cal.calibration.json").write_text(json.dumps(cal))
    return model


def test_conformal_decision_is_the_default_with_a_calibration_and_writes_set_labels(setup, tmp_path):
    from classifier.outputs import SET_COLORS

    model = _calibrated_copy(setup, tmp_path)
    res = classify_maps(setup["npz"], model, threads=1)
    assert res.info["decision"] == "conformal" and res.info["conformal"]["alpha"] == 0.1
    assert res.label_names[4:] == ["diffusion-or-ballistic", "diffusion-or-flow", "ballistic-or-flow"]
    rule = classify_maps(setup["npz"], model, threads=1, decision="rule", abstain_ambiguous=False)
    assert rule.info["decision"] == "rule" and rule.set_labels == []
    np.testing.assert_array_equal(res.probabilities, rule.probabilities)  # the decision alone differs
    assert classify_maps(setup["npz"], model, threads=1, min_probability=0.6).info["decision"] == "rule"
    decided = [
        int(np.isin(classify_maps(setup["npz"], model, threads=1, alpha=a).labels, [0, 1, 2]).sum())
        for a in (0.05, 0.3, 0.6)
    ]
    assert decided == sorted(decided)  # larger alpha: smaller sets, at least as many pixels decided
    out = tmp_path / "o"
    assert classify_main([str(setup["npz"]), "--model", str(model), "--out", str(out), "--threads", "1"]) == 0
    legend = json.loads((out / "legend.json").read_text())
    assert legend["decision"] == "conformal"
    names = {c["name"]: c["color"] for c in legend["classes"]}
    assert all(names[k] == v for k, v in SET_COLORS.items())
    assert len(set(names.values())) == len(names)  # every label its own colour
    for bad in (
        ["--alpha", "0"],
        ["--alpha", "1.5"],
        ["--decision", "rule", "--alpha", "0.1"],
        ["--decision", "conformal", "--min-probability", "0.6"],
    ):
        assert classify_main([str(setup["npz"]), "--model", str(model), "--out", str(tmp_path / "x"), *bad]) == 2
    # a model without a calibration: the rule, and conformal asked for is refused with the fix
    assert classify_maps(setup["npz"], setup["model"], threads=1).info["decision"] == "rule"
    with pytest.raises(ValueError, match="classifier.calibrate"):
        classify_maps(setup["npz"], setup["model"], threads=1, decision="conformal")


def test_conformal_classify_path_does_not_import_torch(setup, tmp_path):
    model = _calibrated_copy(setup, tmp_path)
    out = _classify_without_torch(setup["npz"], model, tmp_path / "o", "--alpha", "0.2")
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["info"]["decision"] == "conformal"

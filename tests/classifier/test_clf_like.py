"""Your own system: the signature lags of a protocol, the identifiable range and the prior scaled to a system,
the spec from a maps file's metadata (``doct-train --like``), the refusal that names it, and reproducibility."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier.features import Configuration, FeatureSpec, load_spec, spec_from_dict, toml_text
from classifier.matching import spec_from_maps
from classifier.own_system import REFERENCE_RESOLUTIONS_UM, identifiable_range, prior_for_spec
from classifier.prior import CLASSES, Draw, Prior
from classifier.truth import identifiability
from torchdoct.conventions import n_eff
from torchdoct.measured.mapsfile import read_maps
from torchdoct.sim.signature import DEFAULT_FEATURES, DEFAULT_LINEAR_LAGS, default_features, signature_lags

# -- signature lags follow the frame count --------------------------------------------------------------------------


def test_signature_lags_keep_the_reference_protocol_and_scale_with_the_frames():
    assert default_features(32) == DEFAULT_FEATURES  # the shipped models' protocol is unchanged
    assert signature_lags(DEFAULT_LINEAR_LAGS, 32) == DEFAULT_LINEAR_LAGS
    for n in range(4, 200):
        lags = signature_lags(DEFAULT_LINEAR_LAGS, n)
        assert lags[0] == 1 and all(b > a for a, b in zip(lags, lags[1:])) and lags[-1] <= n - 3
    # the longest lag stays T - 4 (its place on the acquisition), the others scale with it
    assert signature_lags(DEFAULT_LINEAR_LAGS, 64)[-1] == 60 and signature_lags(DEFAULT_LINEAR_LAGS, 128)[-1] == 124
    assert signature_lags(DEFAULT_LINEAR_LAGS, 64) == (1, 2, 4, 6, 9, 13, 17, 24, 34, 47, 60)


# -- identifiable ranges and the scaled prior -------------------------------------------------------------------------


def _spec(dt=0.2048, n=1.0, lat=4.9, ax=3.8, wl=0.84, y=None):
    cs = (
        Configuration(name="original", wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax),
        Configuration(name="axial", wavelength_um=wl, lateral_resolution_um=lat, axial_resolution_um=ax * 3.7),
        Configuration(
            name="lateral",
            wavelength_um=wl,
            lateral_resolution_um=lat * 3.7,
            axial_resolution_um=ax,
            lateral_resolution_y_um=y,
        ),
    )
    return FeatureSpec(
        name="t",
        configurations=cs,
        metrics=("rho_lin_1",),
        frame_interval_s=dt,
        ocds_delay_range_s=(dt, 6 * dt),
        refractive_index=n,
    )


def _status(spec, label, mag, prior):
    variants = (
        [dict(polar_angle_deg=a) for a in (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)]
        if label == 2
        else [dict(ballistic_directions=law) for law in ("isotropic", "uniform-angles")]
        if label == 1
        else [{}]
    )
    return {
        identifiability(
            spec,
            Draw(
                label=label,
                magnitude=mag,
                azimuth_deg=0.0,
                density_per_um3=d,
                sim_seed=0,
                **{"polar_angle_deg": 0.0, **v},
            ),
            prior,
        )[0]
        for v in variants
        for d in prior.density_per_um3
    }


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("label", [0, 1, 2])
def test_identifiable_range_is_where_the_closed_forms_say(label):
    spec, prior = _spec(), Prior()
    lo, hi = identifiable_range(spec, label, prior)
    step = 10.0 ** (1.0 / 24.0)  # the grid's resolution
    assert "identifiable" in _status(spec, label, lo, prior) and "identifiable" in _status(spec, label, hi, prior)
    assert _status(spec, label, lo / step**1.01, prior) == {"static"}  # below: every variant static
    above = _status(spec, label, hi * step**1.01, prior)
    assert "identifiable" not in above and above <= {"decorrelated", "static"}


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_identifiability_scales_inversely_with_the_frame_interval():
    """Every criterion depends on D·τ or v·τ only: a protocol 16× faster sees motions 16× faster. The
    status itself scales exactly; the ranges of diffusion and flow (monotone in the magnitude) to the grid's
    resolution. (Random-ballistic |g1|² oscillates in v·τ around ε, so its upper end is an island edge.)"""
    prior = Prior()
    slow, fast = _spec(0.2048), _spec(0.0128)
    for label in range(3):
        for mag in np.geomspace(*prior.magnitude_range(label), 9):
            assert _status(slow, label, float(mag), prior) == _status(fast, label, float(16.0 * mag), prior)
    for label in (0, 2):
        for a, b in zip(identifiable_range(slow, label, prior), identifiable_range(fast, label, prior)):
            assert abs(math.log10(b / a) - math.log10(16.0)) <= 1.0 / 24.0 + 1e-9


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_prior_for_spec_keeps_n_eff_and_widens_each_range_by_the_margin():
    spec = _spec(lat=10.0, ax=8.0, wl=1.31)
    prior, ranges = prior_for_spec(spec, Prior())
    ref = n_eff(0.02, *REFERENCE_RESOLUTIONS_UM)
    assert n_eff(prior.density_per_um3[0], 10.0, 8.0) == pytest.approx(ref, rel=2e-3)
    for label, name in enumerate(CLASSES):
        lo, hi = prior.magnitude_range(label)
        assert lo == pytest.approx(ranges[name][0] / 10**0.5, rel=5e-3)
        top = min(ranges[name][1] * 10**0.5, ranges.get(f"{name}_simulated_max", [math.inf])[0])
        assert hi == pytest.approx(top, rel=5e-3)
    assert prior.flow_speed_um_per_s is not None and prior.flow_speed_um_per_s[0] > prior.speed_um_per_s[0]


def test_speed_cap_bounds_the_scatterers_a_draw_simulates():
    from classifier.own_system import MAX_SCATTERERS_PER_TRIAL, speed_cap
    from classifier.simulation import scene_for
    from torchdoct.sim.plan import make_plan

    spec, prior = _spec(), Prior()
    cap = speed_cap(spec, prior, 2)

    def count(v):
        return max(
            make_plan(
                scene_for(
                    spec,
                    Draw(
                        label=2,
                        magnitude=v,
                        polar_angle_deg=a,
                        azimuth_deg=0.0,
                        density_per_um3=prior.density_per_um3[1],
                        sim_seed=0,
                    ),
                    prior,
                ),
                truncation_tolerance=1e-2,
                truncation="taper",
            ).expected_scatterers_per_trial
            for a in (0.0, 45.0, 90.0)
        )

    assert count(cap) <= MAX_SCATTERERS_PER_TRIAL < count(1.03 * cap)
    assert 3.0 < cap < 30.0  # a volume at the reference system: the shipped prior's 6 µm/s is inside


def test_flow_speed_range_is_optional_and_leaves_old_priors_unchanged():
    assert "flow_speed_um_per_s" not in Prior().to_dict()  # cache keys of the shipped priors unchanged
    p = Prior(flow_speed_um_per_s=(0.1, 100.0))
    assert Prior.from_dict(tomllib.loads(toml_text(p.to_dict()))) == p
    assert p.magnitude_range(2) == (0.1, 100.0) and p.magnitude_range(1) == p.speed_um_per_s
    with pytest.raises(ValueError, match="flow_speed_um_per_s"):
        Prior(flow_speed_um_per_s=(1.0, 0.1))


# -- the spec from the maps -------------------------------------------------------------------------------------------


#: ``doct-train --like`` options of a tiny training (seconds): the recipe's steps, not its accuracy.
TINY_LIKE = ["--quick", "--draws-train", "6", "--draws-validation", "3", "--draws-test", "3", "--max-epochs", "2"]
TINY_LIKE += ["--no-baselines", "--no-cache", "--no-progress"]


def _bscan_maps(tmp_path, *, bulk_phase=False, intensity_only=False, name="own.npz", spec="signature-bscan"):
    s = load_spec(spec)
    feats = s.metrics + (("g1_1", "g1_2") if not intensity_only else ())
    full = dataclasses.replace(s, metrics=feats)
    chans = feature_channels(full)
    meta = maps_meta(s, chans)
    meta["reduction"] = {"lateral_axes": "X"}
    meta["signature"] = {"features": list(feats), "intensity_only": intensity_only}
    if bulk_phase:
        meta["bulk_phase"] = {"method": "weighted-mean"}
    data = np.random.default_rng(0).random((len(chans), 4, 5)).astype(np.float32)
    return save_maps(tmp_path / name, data, meta)


def test_spec_from_bscan_maps_is_the_shipped_bscan_spec(tmp_path):
    path = _bscan_maps(tmp_path)
    spec, notes = spec_from_maps([read_maps(path)])
    shipped = load_spec("signature-bscan")
    assert spec.name == "like-own"
    assert spec.metrics == shipped.metrics  # the field group left out: not bulk-phase corrected
    assert any("bulk-phase" in n for n in notes)
    assert [c.optics for c in spec.configurations] == [c.optics for c in shipped.configurations]
    assert (spec.n_frames, spec.frame_interval_s, spec.ocds_delay_range_s, spec.refractive_index) == (
        shipped.n_frames,
        shipped.frame_interval_s,
        shipped.ocds_delay_range_s,
        shipped.refractive_index,
    )
    assert spec_from_dict(tomllib.loads(toml_text(spec.to_dict()))) == spec  # the SPEC.spec.toml round trip


def test_spec_from_corrected_maps_reads_the_field_group(tmp_path):
    spec, _ = spec_from_maps([read_maps(_bscan_maps(tmp_path, bulk_phase=True))])
    assert spec.needs_field and spec.metrics[-2:] == ("g1_1", "g1_2")


def test_spec_from_maps_refuses_channels_without_optics(tmp_path):
    path = _bscan_maps(tmp_path)
    m = read_maps(path)
    meta = dict(m.meta)
    meta["channels"] = [{**c, "wavelength_um": None} for c in meta["channels"]]
    bad = save_maps(tmp_path / "bad.npz", m.maps, meta)
    with pytest.raises(ValueError, match="--wavelength-um"):
        spec_from_maps([read_maps(bad)])


# -- the commands -------------------------------------------------------------------------------------------------------


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_like_dry_run_prints_spec_prior_time_and_key_and_writes_nothing(tmp_path, capsys):
    from classifier.cli import train_main

    path = _bscan_maps(tmp_path, spec="signature")  # volume maps: isotropic reductions (the faster closed forms)
    m = read_maps(path)
    meta = dict(m.meta)
    meta.pop("reduction")
    path = save_maps(tmp_path / "own.npz", m.maps, meta)
    out = tmp_path / "model"
    assert train_main(["--like", str(path), "--out", str(out), "--dry-run", "--quick", "--no-cache"]) == 0
    text = capsys.readouterr().out
    for needle in (
        "spec like-own",
        "axial_resolution_um = 14.0",
        "identifiable",
        "expected time: about",
        "simulated up to",
        "--spec",
        "--prior",
    ):
        assert needle in text, needle
    assert not out.exists()
    assert train_main(["--like", str(path), "--spec", "signature", "--out", str(out)]) == 2  # exclusive


def test_classify_without_a_fitting_shipped_model_names_the_like_command(tmp_path, capsys):
    from classifier.cli import classify_main

    s = load_spec("signature-bscan")
    other = dataclasses.replace(
        s, configurations=tuple(dataclasses.replace(c, wavelength_um=1.31) for c in s.configurations)
    )
    chans = feature_channels(other)
    meta = maps_meta(other, chans, n_frames=64, frame_interval_s=0.0128)
    meta["signature"] = {"features": list(s.metrics), "intensity_only": False}
    path = save_maps(tmp_path / "sys.npz", np.ones((len(chans), 4, 5), np.float32), meta)
    assert classify_main([str(path), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert f"doct-train --like {path} --out MODEL_DIR" in err and "--model MODEL_DIR" in err
    assert "64 frames 0.0128 s apart" in err
    assert not (tmp_path / "c").exists()


@pytest.mark.slow
def test_like_writes_spec_and_prior_that_retrain_the_same_model(tmp_path, capsys):
    """``doct-train --like`` then ``doct-train --spec SPEC.spec.toml --prior SPEC.prior.toml``: the same
    network weights (the same spec, prior and seed give the same model); tiny sizes."""
    import onnx
    from onnx import numpy_helper

    from classifier.cli import train_main

    path = _bscan_maps(tmp_path, spec="signature", name="vol.npz")  # isotropic reductions: a volume
    m = read_maps(path)
    meta = dict(m.meta)
    meta.pop("reduction")
    path = save_maps(tmp_path / "vol.npz", m.maps, meta)
    tiny = TINY_LIKE
    a, b = tmp_path / "a", tmp_path / "b"
    assert train_main(["--like", str(path), "--out", str(a), *tiny]) == 0
    printed = capsys.readouterr().out
    spec_file, prior_file = a / "like-vol.spec.toml", a / "like-vol.prior.toml"
    assert spec_file.exists() and prior_file.exists() and (a / "like-vol.onnx").exists()
    assert f"--spec {spec_file} --prior {prior_file}" in printed
    assert Prior.from_dict(tomllib.loads(prior_file.read_text())).flow_speed_um_per_s is not None
    assert train_main(["--spec", str(spec_file), "--prior", str(prior_file), "--out", str(b), *tiny]) == 0

    def weights(p):
        return {i.name: numpy_helper.to_array(i) for i in onnx.load(str(p)).graph.initializer}

    wa, wb = weights(a / "like-vol.onnx"), weights(b / "like-vol.onnx")
    assert wa.keys() == wb.keys() and all(np.array_equal(wa[k], wb[k]) for k in wa)
    from classifier.cli import classify_main

    assert classify_main([str(path), "--model", str(a), "--out", str(tmp_path / "cls")]) == 0  # --model DIR
    assert (tmp_path / "cls" / "classes.tif").exists()
    bad = tmp_path / "bad.prior.toml"
    bad.write_text("speed_um_per_s = [1.0, 0.1]\n")
    assert train_main(["--spec", str(spec_file), "--prior", str(bad), "--out", str(tmp_path / "c"), *tiny]) == 2
    assert "bad.prior.toml" in capsys.readouterr().err


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_doct_train_calibrates_a_signature_model_as_classifier_calibrate_does(tmp_path, capsys):
    """``doct-train`` on a signature spec (here ``--like``, tiny sizes) writes the conformal calibration beside
    the model: the very record ``python -m classifier.calibrate`` computes for the written model with the draws
    it names, so ``doct-classify`` decides by the prediction sets. A negative ``--calibration-draws`` is refused
    before any work. (What a retraining without a calibration leaves: the slow
    :func:`test_a_model_retrained_without_a_calibration_loses_the_earlier_models`.)"""
    import json

    from classifier.calibrate import CALIBRATION_SEED, POOLS, calibrate
    from classifier.cli import classify_main, train_main

    path = _bscan_maps(tmp_path)
    tiny = TINY_LIKE
    a = tmp_path / "a"
    assert train_main(["--like", str(path), "--out", str(a), *tiny, "--calibration-draws", "4"]) == 0
    assert "calibrated: " in capsys.readouterr().out
    record = json.loads((a / "like-own.calibration.json").read_text())
    assert (a / "like-own.reliability.png").stat().st_size > 0
    assert record["description"]["draws"] == 4 and record["description"]["seed"] == CALIBRATION_SEED
    assert [p["pool_pixels"] for p in record["pools"]] == list(POOLS)
    again = json.loads(json.dumps(calibrate(str(a / "like-own.onnx"), draws=4, use_cache=False, progress=False)))
    assert [(p["scores"], p["truth"]) for p in again["pools"]] == [(p["scores"], p["truth"]) for p in record["pools"]]
    assert classify_main([str(path), "--model", str(a), "--out", str(tmp_path / "ca")]) == 0
    assert json.loads((tmp_path / "ca" / "legend.json").read_text())["decision"] == "conformal"
    assert train_main(["--like", str(path), "--out", str(tmp_path / "c"), *tiny, "--calibration-draws", "-1"]) == 2
    assert "--calibration-draws -1" in capsys.readouterr().err and not (tmp_path / "c").exists()


@pytest.mark.slow  # three tiny trainings, a calibration and two classifications (about 10 s)
def test_a_model_retrained_without_a_calibration_loses_the_earlier_models(tmp_path):
    """Retrained into the same folder with ``--calibration-draws 0 --force``, the earlier model's calibration
    goes with the earlier model (it would decide the new model by the old one's scores), and the argmax rule
    decides; without ``--force`` nothing is overwritten."""
    import json

    from classifier.cli import classify_main, train_main

    path = _bscan_maps(tmp_path)
    tiny = TINY_LIKE
    a = tmp_path / "a"
    assert train_main(["--like", str(path), "--out", str(a), *tiny, "--calibration-draws", "2"]) == 0
    assert (a / "like-own.calibration.json").exists()
    assert train_main(["--like", str(path), "--out", str(a), *tiny, "--calibration-draws", "0"]) == 2  # no --force
    assert train_main(["--like", str(path), "--out", str(a), *tiny, "--calibration-draws", "0", "--force"]) == 0
    assert not (a / "like-own.calibration.json").exists() and not (a / "like-own.reliability.png").exists()
    assert (a / "like-own.spec.toml").exists() and (a / "like-own.onnx").exists()
    assert classify_main([str(path), "--model", str(a), "--out", str(tmp_path / "cb")]) == 0
    assert json.loads((tmp_path / "cb" / "legend.json").read_text())["decision"] == "rule"

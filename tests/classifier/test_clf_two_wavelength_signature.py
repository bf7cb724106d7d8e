"""The two-wavelength signature spec: its features, its training recipe, the maps of a rendered dual-band
scene (``torchdoct render`` → ``torchdoct maps --signature`` per band) as its input columns, and
doct-classify's choice of the default model for each kind of maps."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier.export import build_metadata, export_onnx
from classifier.features import load_spec
from classifier.train import SCALED_PRIOR_SPECS, SPEC_RECIPES, TrainConfig, default_prior, train

NAME = "two-wavelength-signature"

PHANTOM = """
name = "two-bands"
description = "one diffusing slab seen at 840 nm and 1310 nm (two-wavelength signature test)"
[[system]]
name = "840nm"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[[system]]
name = "1310nm"
wavelength_um = 1.31
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[protocol]
n_frames = 32
frame_interval_s = 0.2048
[grid]
kind = "bscan"
n_x = 16
n_z = 16
pitch_x_um = 2.0
pitch_z_um = 2.0
[[region]]
name = "diffusing"
shape = "slab"
z_min_um = -64.0
z_max_um = 64.0
density_per_um3 = 0.06
[[region.motion]]
kind = "diffusion"
diffusion_um2_per_s = 0.01
[analysis]
metrics = ["liv", "ocds"]
ocds_delay_range_s = [0.2048, 1.2288]
[simulation]
seed = 11
"""


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_spec_is_the_signature_at_the_two_wavelength_configurations():
    spec, sig, two = load_spec(NAME), load_spec("signature"), load_spec("two-wavelength")
    assert spec.n_features == 24 and len(spec.feature_names) == 24
    assert spec.metrics == sig.metrics and spec.is_signature and not spec.needs_field
    assert spec.configurations == two.configurations
    assert spec.feature_names == tuple(f"{m}@{c}" for c in ("840nm", "1310nm") for m in sig.metrics)
    for key in (
        "n_frames",
        "frame_interval_s",
        "ocds_delay_range_s",
        "ocds_scale",
        "ocds_estimator",
        "refractive_index",
    ):
        assert getattr(spec, key) == getattr(sig, key) == getattr(two, key), key
    # the shipped recipe is the signature one (wider network, random-bulk-phase test split, noise in every
    # draw), its prior scaled to the two-band system
    assert SPEC_RECIPES[NAME] == SPEC_RECIPES["signature"]
    assert TrainConfig.for_spec(NAME) == dataclasses.replace(TrainConfig.for_spec("signature"), spec=NAME)
    assert NAME in SCALED_PRIOR_SPECS and default_prior(TrainConfig.for_spec(NAME)).noise_probability == 1.0
    assert TrainConfig.for_spec(NAME).bulk_phase_test and TrainConfig.for_spec(NAME).draws_train == 1920


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """A tiny two-wavelength signature model (its columns and metadata; its accuracy is not used)."""
    tmp = tmp_path_factory.mktemp("clf-2wl-sig")
    res = train(
        TrainConfig.for_spec(
            NAME,
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
            bulk_phase_test=False,
        ),
        cache_dir=tmp / "cache",
        log=None,
    )
    path = tmp / f"{NAME}.onnx"
    export_onnx(res.model, build_metadata(res), path)
    return path


@pytest.fixture(scope="module")
def rendered_maps(tmp_path_factory) -> dict[str, Path]:
    """Signature maps of a rendered dual-band scene: one file per band (original resolution), and the
    840-nm band at the single-acquisition resolutions."""
    from torchdoct.cli import main as td_main

    tmp = tmp_path_factory.mktemp("clf-2wl-maps")
    phantom = tmp / "phantom.toml"
    phantom.write_text(PHANTOM, encoding="utf-8")
    assert td_main(["render", str(phantom), "--out", str(tmp / "seq.npz"), "--no-progress", "--no-preview"]) == 0
    out = {}
    for band in ("840nm", "1310nm"):
        out[band] = tmp / f"maps-{band}.npz"
        assert (
            td_main(["maps", str(tmp / f"seq-{band}.npz"), "--signature", "--out", str(out[band]), "--no-progress"])
            == 0
        )
    out["single"] = tmp / "maps-single.npz"
    assert (
        td_main(
            [
                "maps",
                str(tmp / "seq-840nm.npz"),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(out["single"]),
                "--no-progress",
            ]
        )
        == 0
    )
    return out


def _merge(paths: list[Path], out: Path) -> Path:
    """The channels of several maps files in one file (a dual-band maps file), 1310 nm first."""
    from classifier.infer import read_maps

    maps = [read_maps(p) for p in paths]
    meta = dict(maps[0].meta)
    meta["channels"] = [ch for m in maps for ch in m.channels]
    return save_maps(out, np.concatenate([m.data for m in maps]), meta)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_rendered_dual_band_maps_assemble_into_the_spec_columns(tiny_model, rendered_maps, tmp_path):
    from classifier.infer import assemble_features, classify_maps, load_model, read_maps

    model = load_model(tiny_model, threads=1)
    spec = load_spec(NAME)
    assert [c["name"] for c in model.columns] == [*spec.feature_names, "pool_pixels"]
    two = [read_maps(rendered_maps[b]) for b in ("840nm", "1310nm")]
    one = [read_maps(_merge([rendered_maps["1310nm"], rendered_maps["840nm"]], tmp_path / "both.npz"))]
    expected = []  # column k: the channel of its metric in the maps file of its band
    for metric, conf in spec.features:
        band = two[0] if conf.name == "840nm" else two[1]
        i = [ch["metric"] for ch in band.channels].index(metric)
        ch = band.channels[i]
        assert conf.matches(ch["wavelength_um"], ch["lateral_resolution_um"], ch["axial_resolution_um"])
        expected.append(band.data[i])
    for maps_list in (two, one, two[::-1]):
        feats, mean_db, info = assemble_features(maps_list, model)
        assert feats.shape == (24, 16, 16) and mean_db is not None
        assert [u["feature"] for u in info["features"]] == list(spec.feature_names)
        np.testing.assert_array_equal(feats, np.stack(expected))
    # the two bands differ (diffusion decorrelates faster at the shorter wavelength: physics.md §5.3)
    f = assemble_features(two, model)[0]
    assert np.nanmean(f[0]) < np.nanmean(f[12])  # rho_lin_1: 840 nm below 1310 nm
    res = classify_maps([rendered_maps["840nm"], rendered_maps["1310nm"]], tiny_model, threads=1, background_db="none")
    assert res.info["classified"] == 16 * 16 and res.magnitude is not None
    # one band alone lacks the other band's columns, and the error says how to give them
    with pytest.raises(ValueError, match=r"rho_lin_1@1310nm.*second file"):
        assemble_features(two[:1], model)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_default_model_for_each_kind_of_maps(tiny_model, rendered_maps, tmp_path, monkeypatch):
    import classifier.infer as infer

    real = {k: v for k, v in infer.shipped_models().items() if k != NAME}
    assert infer.SIGNATURE_MODEL in real and infer.DEFAULT_MODEL in real
    lo = load_spec("single-acquisition")
    plain = save_maps(tmp_path / "plain.npz", np.ones((7, 4, 4), np.float32), maps_meta(lo, feature_channels(lo)))
    both = [rendered_maps["840nm"], rendered_maps["1310nm"]]
    merged = _merge(both, tmp_path / "both.npz")

    def choice(paths):
        return infer.default_model_for([infer.read_maps(p) for p in paths])

    # not shipped (yet): the choice of before
    monkeypatch.setattr(infer, "shipped_models", lambda: dict(real))
    name, note = choice(both)
    # (the rendered maps are B-scans, reduced laterally along x only: the B-scan signature model)
    assert name == infer.DEFAULT_MODEL and "instead of signature-bscan: maps lack the model feature" in note
    assert choice([rendered_maps["single"]]) == ("signature-bscan", None)
    # shipped: the dual-band signature maps (two files or one) take it, the rest as before
    monkeypatch.setattr(infer, "shipped_models", lambda: {**real, NAME: tiny_model})
    assert choice(both) == (NAME, None)
    assert choice(both[::-1]) == (NAME, None)
    assert choice([merged]) == (NAME, None)
    assert choice([rendered_maps["single"]]) == ("signature-bscan", None)
    name, note = choice([rendered_maps["840nm"]])  # one band only: the closest signature model says what lacks
    assert name == infer.DEFAULT_MODEL and f"instead of {NAME}" in note and "rho_lin_1@1310nm" in note
    name, note = choice([plain])
    assert name == infer.DEFAULT_MODEL and "no signature channels" in note and "--signature" in note
    res = infer.classify_maps(both, threads=1, background_db="none")
    assert res.model.path == tiny_model and res.info["model_choice"] is None

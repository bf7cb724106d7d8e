"""Feature specifications: the shipped specs, feature order, matching rule and validation errors."""

from __future__ import annotations

import pytest

from classifier.features import Configuration, FeatureSpec, load_spec, same_value, shipped_specs, spec_from_dict


def test_shipped_specs_are_the_documented_ones():
    assert set(shipped_specs()) == {
        "single-acquisition",
        "two-wavelength",
        "signature",
        "two-wavelength-signature",
        "signature-bscan",
        "signature-bscan-field",
        "signature-aline",
        "single-acquisition-bscan",
    }
    aline = load_spec("signature-aline")  # one A-line: no lateral reduction, the signature's metrics
    assert [c.name for c in aline.configurations] == ["original", "axial=14"]
    assert aline.metrics == load_spec("signature-bscan").metrics
    single = load_spec("single-acquisition")
    assert [(c.wavelength_um, c.lateral_resolution_um, c.axial_resolution_um) for c in single.configurations] == [
        (0.84, 4.9, 3.8),
        (0.84, 4.9, 14.0),
        (0.84, 18.0, 3.8),
    ]
    assert single.feature_names == (
        "liv@original",
        "ocds@original",
        "liv@axial=14",
        "ocds@axial=14",
        "liv@lateral=18",
        "ocds@lateral=18",
    )
    assert single.feature_units == ("dB^2", "1/s") * 3
    two = load_spec("two-wavelength")
    assert [(c.wavelength_um, c.lateral_resolution_um, c.axial_resolution_um) for c in two.configurations] == [
        (0.84, 4.9, 3.8),
        (1.31, 4.9, 3.8),
    ]
    for spec in (single, two):  # the paper's protocol (§2.1.2)
        assert spec.n_frames == 32 and spec.frame_interval_s == 0.2048
        assert spec.ocds_delay_range_s == (0.2048, 1.2288)
        assert spec.refractive_index == 1.0
        assert len(spec.frame_times_s) == 32 and spec.frame_times_s[-1] == pytest.approx(31 * 0.2048)


@pytest.mark.parametrize("name", ["single-acquisition", "two-wavelength", "signature", "two-wavelength-signature"])
def test_spec_round_trips_through_its_dict(name):
    spec = load_spec(name)
    assert spec_from_dict(spec.to_dict()) == spec


def test_matching_uses_the_relative_tolerance():
    c = Configuration(name="o", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    assert c.matches(0.84 * (1 + 5e-7), 4.9, 3.8)
    assert not c.matches(0.84 * (1 + 5e-6), 4.9, 3.8)
    assert not c.matches(0.84, 4.9, 14.0)
    assert same_value(1.0, 1.0 + 1e-7) and not same_value(1.0, 1.0 + 1e-5)


def _base() -> dict:
    return load_spec("two-wavelength").to_dict()


@pytest.mark.parametrize(
    "mutate, err, text",
    [
        (lambda d: d.update(colour="red"), ValueError, "unknown key"),
        (lambda d: d["configuration"][0].update(wavelength_um=840.0), ValueError, "0.84"),
        (lambda d: d["configuration"][1].update(name="840nm"), ValueError, "duplicate configuration"),
        (lambda d: d["configuration"][1].update(wavelength_um=0.84), ValueError, "same system"),
        (lambda d: d.update(metrics=["liv", "aliv"]), ValueError, "not supported"),
        (lambda d: d.update(metrics="liv"), TypeError, "list"),
        (lambda d: d["analysis"].update(ocds_delay_range_s=[1.0, 0.5]), ValueError, "max > min"),
        (lambda d: d["protocol"].update(n_frames=2), ValueError, "n_frames"),
        (lambda d: d["configuration"][0].update(lateral_resolution_um=-1.0), ValueError, "lateral_resolution_um"),
        (lambda d: d.update(configuration=[]), ValueError, "at least one"),
    ],
)
def test_bad_specs_are_rejected_with_the_field_named(mutate, err, text):
    d = _base()
    mutate(d)
    with pytest.raises(err, match=text):
        spec_from_dict(d)


def test_load_spec_from_file_and_missing_file(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text(
        'name = "mine"\n[[configuration]]\nname = "a"\nwavelength_um = 1.0\n'
        "lateral_resolution_um = 5.0\naxial_resolution_um = 4.0\n",
        encoding="utf-8",
    )
    spec = load_spec(p)
    assert isinstance(spec, FeatureSpec) and spec.feature_names == ("liv@a", "ocds@a")
    with pytest.raises(FileNotFoundError, match="shipped"):
        load_spec(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = ", encoding="utf-8")
    with pytest.raises(ValueError, match="bad.toml"):
        load_spec(bad)


def test_binary_spec_file_is_named_never_a_codec_error(tmp_path, capsys):
    """A spec that is not UTF-8 text (an image given by mistake): a ValueError naming the file, and
    ``doct-train --spec`` exits 2 with one ``error:`` line and writes nothing (was a bare codec error)."""
    from classifier.cli import train_main

    png = tmp_path / "scan.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(ValueError, match=r"scan\.png: not a TOML text file \(byte 0"):
        load_spec(png)
    out = tmp_path / "model"
    assert train_main(["--out", str(out), "--spec", str(png), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: scan.png:") and "Traceback" not in err and "codec" not in err
    assert not out.exists()

"""Readable outputs: ``doct-classify``'s overlay tells indeterminate from masked pixels in colour-blind-safe
colours and names the model, a magnitude picture with its units sits beside ``magnitude.tif``, and the
TIFFs of ``doct-classify`` and ``torchdoct maps`` carry ImageJ metadata (pixel size in µm, channel names)
that tifffile reads as ``imagej_metadata`` (one ImageDescription, ImageJ's; the project's JSON as its ``Info``),
and the project's readers find their JSON there.

Before: the overlay drew indeterminate grey over a grey image (masked pixels looked the same), named no
model, used red/green; ``magnitude.tif`` had no picture and ``--force`` with a model without magnitudes
left it behind; the TIFFs had no scale; a signature model on maps without signature channels did not say
``--signature``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _refusal import refused

from classifier.cli import classify_main
from torchdoct.cli import main as torchdoct_main

PITCH = {"z": 2.0, "x": 1.5}


def _sequence(path: Path, shape: tuple[int, ...], axes: str, pitch: dict) -> Path:
    rng = np.random.default_rng(1)
    np.save(path, (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64))
    path.with_suffix(".json").write_text(
        json.dumps(
            {
                "axes": axes,
                "pitch_um": pitch,
                "frame_times_s": [0.2048 * i for i in range(shape[0])],
                "system": {
                    "name": "s",
                    "wavelength_um": 0.84,
                    "lateral_resolution_um": 4.9,
                    "axial_resolution_um": 3.8,
                    "refractive_index": 1.0,
                },
            }
        )
    )
    return path


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """B-scan maps of a random complex sequence (32 frames, 20 × 24 pixels) with and without signature."""
    d = tmp_path_factory.mktemp("maps")
    seq = _sequence(d / "seq.npy", (32, 20, 24), "TZX", PITCH)
    res = ["--resolution", "original", "--resolution", "axial=14", "--resolution", "lateral=18"]
    assert (
        torchdoct_main(
            [
                "maps",
                str(seq),
                *res,
                "--signature",
                "--no-progress",
                "--out",
                str(d / "sig.npz"),
                "--out",
                str(d / "sig.tif"),
            ]
        )
        == 0
    )
    assert torchdoct_main(["maps", str(seq), *res, "--no-progress", "--out", str(d / "plain.npz")]) == 0
    return d


@pytest.fixture()
def figures(monkeypatch):
    """The figures ``doct-classify`` saves, by file name (still open for inspection)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    saved = {}
    real = Figure.savefig

    def keep(self, fname, *a, **k):
        saved[Path(str(fname)).name.split(".tmp")[0].lstrip(".")] = self
        return real(self, fname, *a, **k)

    monkeypatch.setattr(Figure, "savefig", keep)
    monkeypatch.setattr("matplotlib.pyplot.close", lambda *a, **k: None)
    return saved


def _by_suffix(saved: dict, suffix: str):
    hits = [fig for name, fig in saved.items() if suffix in name]
    assert hits, list(saved)
    return hits[-1]


def test_overlay_tells_indeterminate_from_masked_and_names_the_model(maps, tmp_path, figures, capsys):
    from classifier.outputs import CLASS_COLORS, MASKED_COLOR

    out = tmp_path / "out"
    # background above the brightest pixels' median: about half the pixels masked, the rest classified
    mean_db = np.load(maps / "sig.npz")
    assert classify_main([str(maps / "sig.npz"), "--out", str(out), "--background-db", "auto", "--threads", "1"]) == 0
    fig = _by_suffix(figures, "overlay")
    ax = fig.axes[0]
    assert "signature-bscan" in ax.get_title()
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(t.startswith("indeterminate") for t in texts) and any(t.startswith("masked") for t in texts)
    colours = [h.get_facecolor()[:3] for h in ax.get_legend().legend_handles]
    assert len({tuple(np.round(c, 3)) for c in colours}) == len(colours), "every entry has its own colour"
    okabe_ito = {"#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442", "#000000"}
    assert {c.upper() for c in CLASS_COLORS.values()} | {MASKED_COLOR} <= okabe_ito
    del mean_db


def test_overlay_pixels_of_masked_and_indeterminate_differ(tmp_path):
    """The drawn image: a masked pixel and an indeterminate one of the same intensity get different colours."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from classifier.outputs import MASKED, Classification, _overlay

    class _Model:
        path = Path("m.onnx")
        metadata = {"spec": {"name": "m"}}
        rule = {}

    labels = np.array([[3, MASKED], [0, 1]], np.uint8)
    res = Classification(
        labels=labels,
        probabilities=np.zeros((4, 2, 2), np.float32),
        classes=["diffusion", "ballistic", "flow", "indeterminate"],
        mask=labels != MASKED,
        background=labels == MASKED,
        intensity_db=np.full((2, 2), 10.0),
        model=_Model(),
        sources=["x"],
        axes="ZX",
        pitch_um={"z": 1.0, "x": 1.0},
        info={"pool": 1},
    )
    seen = {}
    real = Figure.savefig

    def keep(self, *a, **k):
        seen["fig"] = self
        return real(self, *a, **k)

    Figure.savefig = keep
    try:
        _overlay(res, str(tmp_path / "o.png"))
    finally:
        Figure.savefig = real
    rgb = seen["fig"].axes[0].get_images()[0].get_array()
    assert not np.allclose(rgb[0, 0], rgb[0, 1]), "indeterminate and masked look the same"
    assert "m" in seen["fig"].axes[0].get_title()


def test_magnitude_picture_with_units_and_force_removes_it(maps, tmp_path, figures, capsys):
    out = tmp_path / "out"
    assert classify_main([str(maps / "sig.npz"), "--out", str(out), "--threads", "1"]) == 0
    assert (out / "magnitude.png").stat().st_size > 0 and (out / "magnitude.tif").is_file()
    fig = _by_suffix(figures, "magnitude")
    labels = [a.get_ylabel() for a in fig.axes]
    assert "D (µm²/s)" in labels and "speed (µm/s)" in labels
    assert "signature-bscan" in fig._suptitle.get_text()
    # another model without a magnitude head, --force: the earlier run's magnitude files go with the set
    assert (
        classify_main(
            [
                str(maps / "sig.npz"),
                "--model",
                "single-acquisition-bscan",
                "--out",
                str(out),
                "--force",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert not (out / "magnitude.png").exists() and not (out / "magnitude.tif").exists()


def test_classify_tiffs_carry_imagej_scale_and_channel_names(maps, tmp_path, capsys):
    import tifffile

    out = tmp_path / "out"
    assert classify_main([str(maps / "sig.npz"), "--out", str(out), "--threads", "1"]) == 0
    expect = {
        "probabilities.tif": ["diffusion", "ballistic", "flow", "indeterminate"],
        "magnitude.tif": ["log10_magnitude", "lower_68", "upper_68", "lower_95", "upper_95"],
        "classes.tif": "class",
    }
    for name, labels in expect.items():
        with tifffile.TiffFile(out / name) as tf:
            ij = tf.imagej_metadata
            assert ij is not None, name
            assert ij["unit"] == "micron" and ij["Labels"] == labels, (name, ij)
            page = tf.pages[0]
            x_res, y_res = page.tags["XResolution"].value, page.tags["YResolution"].value
            assert x_res[0] / x_res[1] == pytest.approx(1 / PITCH["x"]) and y_res[0] / y_res[1] == pytest.approx(
                1 / PITCH["z"]
            )
            descriptions = [t for t in page.tags.values() if t.code == 270]
            assert len(descriptions) == 1 and page.description.startswith("ImageJ="), "one description, ImageJ's"
            assert json.loads(ij["Info"])["source"], "the project's JSON is ImageJ's Info"
            assert all(270 not in p.tags for p in tf.pages[1:])
            if name != "classes.tif":
                assert tf.series[0].shape == (len(labels), 20, 24)


@pytest.mark.parametrize(
    "shape, axes, pitch", [((32, 20, 24), "TZX", PITCH), ((32, 3, 10, 12), "TYZX", {"z": 2.0, "x": 1.5, "y": 4.0})]
)
def test_maps_tiff_carries_imagej_scale_and_reads_back(tmp_path, capsys, shape, axes, pitch):
    import tifffile

    from torchdoct.measured.io import read_maps

    seq = _sequence(tmp_path / "seq.npy", shape, axes, pitch)
    assert (
        torchdoct_main(
            ["maps", str(seq), "--no-progress", "--out", str(tmp_path / "m.tif"), "--out", str(tmp_path / "m.npz")]
        )
        == 0
    )
    with tifffile.TiffFile(tmp_path / "m.tif") as tf:
        ij = tf.imagej_metadata
        page = tf.pages[0]
        x_res = page.tags["XResolution"].value
        series_axes, series_shape = tf.series[0].axes, tf.series[0].shape
        assert [t.code for t in page.tags.values()].count(270) == 1 and all(270 not in p.tags for p in tf.pages[1:])
    names = ["liv@original", "ocds@original", "mean_db@original"]
    n_y = shape[1] if axes == "TYZX" else 1
    assert ij["unit"] == "micron" and ij["Labels"] == [n for _ in range(n_y) for n in names]  # channel fastest
    assert x_res[0] / x_res[1] == pytest.approx(1 / pitch["x"])
    assert ij["channels"] == 3 and "frames" not in ij  # the metrics on ImageJ's C axis, never on T
    if n_y > 1:
        assert ij["spacing"] == pytest.approx(pitch["y"]) and ij["slices"] == n_y
        assert series_axes == "ZCYX" and series_shape == (n_y, 3, *shape[2:])
    a, b = read_maps(tmp_path / "m.tif"), read_maps(tmp_path / "m.npz")
    assert a.channels == b.channels and np.array_equal(a.maps, b.maps, equal_nan=True)


def test_signature_model_on_maps_without_signature_names_the_option(maps, tmp_path, capsys):
    refused(
        capsys,
        tmp_path,
        [str(maps / "plain.npz"), "--model", "signature-bscan", "--out", str(tmp_path / "o")],
        "plain.npz",
        "--signature",
        run=classify_main,
    )

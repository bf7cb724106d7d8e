"""The napari plugin (torchdoct/napari_plugin, npe2) without Qt: the manifest validates with its imports,
npe2's reader returns maps as Image layers scaled in µm and named by channel, class maps as a Labels
layer in the legend's colours, sequences as their dB intensity; npe2's writer writes maps the maps
reader reads back. The screenshot test with an offscreen Qt viewer is slow and needs napari."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import pytest

npe2 = pytest.importorskip("npe2")

from _formats import maps as _maps  # noqa: E402

from torchdoct.measured.mapsfile import read_maps, write_maps  # noqa: E402

MANIFEST = Path(str(resources.files("torchdoct") / "napari_plugin" / "napari.yaml"))


@pytest.fixture(scope="module")
def plugin():
    from npe2 import PluginManager, PluginManifest

    pm = PluginManager.instance()
    if "torchdoct" not in pm._manifests:  # an install registers it through the napari.manifest entry point
        pm.register(PluginManifest.from_file(MANIFEST))
    return pm


def test_manifest_validates_with_its_imports():
    from npe2 import PluginManifest

    mf = PluginManifest.from_file(MANIFEST)
    mf.validate_imports()
    assert mf.name == "torchdoct"
    kinds = {c.id.split(".")[1] for c in mf.contributions.commands}
    assert {"get_reader", "write_maps", "maps_widget"} <= kinds
    assert mf.contributions.sample_data and mf.contributions.widgets and mf.contributions.writers


def test_the_entry_point_names_the_manifest():
    text = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    assert '[project.entry-points."napari.manifest"]\ntorchdoct = "torchdoct.napari_plugin:napari.yaml"' in text


@pytest.mark.parametrize("suffix", [".npz", ".ome.tif", ".zarr"])
@pytest.mark.parametrize("volume", [False, True], ids=["bscan", "volume"])
def test_npe2_reader_returns_maps_layers_scaled_in_um(tmp_path, plugin, suffix, volume):
    if suffix == ".zarr":
        pytest.importorskip("zarr")
    m = _maps(volume)
    path = write_maps(tmp_path / f"m{suffix}", m)
    layers = npe2.read([str(path)], stack=False, plugin_name="torchdoct")
    assert [lay[1]["name"] for lay in layers] == list(m.channels)
    want = (7.5, 1.9, 2.5) if volume else (1.9, 2.5)  # (y,) z, x pitch in µm
    for (data, attrs, kind), i in zip(layers, range(len(layers))):
        assert kind == "image" and tuple(attrs["scale"]) == pytest.approx(want)
        np.testing.assert_array_equal(data, m.maps[i])
        assert attrs["metadata"]["channel"]["name"] == m.channels[i]


def test_npe2_writer_writes_maps_the_reader_reads_back(tmp_path, plugin):
    m = _maps(False)
    layers = npe2.read([str(write_maps(tmp_path / "m.npz", m))], stack=False, plugin_name="torchdoct")
    out = tmp_path / "again.ome.tif"
    npe2.write(str(out), layers, plugin_name="torchdoct")
    back = read_maps(out)
    assert back.channels == m.channels and back.meta["pitch_um"] == m.meta["pitch_um"]
    np.testing.assert_array_equal(back.maps, m.maps)


@pytest.mark.parametrize("layout", ["imagej-info", "json-description"])
def test_class_map_opens_as_labels_in_the_legend_colours(tmp_path, plugin, layout):
    """doct-classify's classes.tif (the legend in ImageJ's Info) and one of an earlier version (the legend as a
    JSON ImageDescription)."""
    import json

    import tifffile

    from torchdoct.measured.imagej import imagej_write_options

    legend = {
        "classes": [
            {"value": 0, "name": "diffusion", "color": "#0072B2"},
            {"value": 1, "name": "flow", "color": "#E69F00"},
        ],
        "masked_value": 255,
        "axes": "ZX",
        "pitch_um": {"z": 1.9, "x": 2.5},
    }
    labels = np.array([[0, 1, 255], [1, 0, 0]], dtype=np.uint8)
    path = tmp_path / "classes.tif"
    text = json.dumps({"legend": legend})
    if layout == "imagej-info":
        tifffile.imwrite(
            path, labels, **imagej_write_options(labels.shape, "ZX", legend["pitch_um"], ["class"], description=text)
        )
    else:
        tifffile.imwrite(path, labels, description=text)
    [(data, attrs, kind)] = npe2.read([str(path)], stack=False, plugin_name="torchdoct")
    assert kind == "labels" and tuple(attrs["scale"]) == pytest.approx((1.9, 2.5))
    np.testing.assert_array_equal(data, [[1, 2, 0], [2, 1, 1]])  # class v is label v + 1; masked is 0
    assert attrs["colormap"][1] == "#0072B2" and attrs["colormap"][2] == "#E69F00"


def test_sequence_opens_as_db_intensity_over_time(tmp_path, plugin):
    import _formats as F

    a = F.field(t=4)
    [(data, attrs, kind)] = npe2.read(
        [str(F.write_ome_tiff(tmp_path / "s.ome.tif", a))], stack=False, plugin_name="torchdoct"
    )
    np.testing.assert_allclose(data, 10 * np.log10(np.abs(a.astype(np.complex128)) ** 2), rtol=1e-5)
    assert tuple(attrs["scale"]) == pytest.approx((1.0, F.PITCH["z"], F.PITCH["x"]))


def test_files_torchdoct_cannot_read_are_left_to_other_plugins(tmp_path):
    from torchdoct.napari_plugin.reader import get_reader

    (tmp_path / "notes.txt").write_text("x")
    assert get_reader(str(tmp_path / "notes.txt")) is None


@pytest.mark.slow
def test_offscreen_viewer_shows_maps_with_a_um_scale(tmp_path, monkeypatch):
    napari = pytest.importorskip("napari")
    try:  # napari installs without a Qt binding; the viewer needs one (pip install "napari[pyqt5]")
        import qtpy.QtWidgets  # noqa: F401
    except Exception:  # qtpy raises its own error class when no binding is installed
        pytest.skip("no Qt binding for napari's viewer (pip install 'napari[pyqt5]')")
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    path = write_maps(tmp_path / "m.ome.tif", _maps(False))
    viewer = napari.Viewer(show=False)
    try:
        layers = viewer.open(str(path), plugin="torchdoct")
        assert [lay.name for lay in layers] == ["liv@original", "ocds@original", "mean_db@original"]
        assert tuple(layers[0].scale) == pytest.approx((1.9, 2.5))
        shot = viewer.screenshot(canvas_only=True)
        assert shot.ndim == 3 and shot.shape[2] == 4 and shot[..., :3].std() > 0  # something was drawn
    finally:
        viewer.close()

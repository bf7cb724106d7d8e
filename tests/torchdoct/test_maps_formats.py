"""Maps written as OME-TIFF and OME-Zarr (torchdoct.measured.mapsome): channel names, physical sizes in µm
and the metadata inside the file, read back by the one maps reader (that of doct-classify) unchanged, and
read by tifffile's and zarr's own parsers with the same names and sizes."""

from __future__ import annotations

import numpy as np
import pytest
from _formats import maps as _maps

from torchdoct.measured.mapsfile import read_maps, write_maps

tifffile = pytest.importorskip("tifffile")


@pytest.mark.parametrize("volume", [False, True], ids=["bscan", "volume"])
@pytest.mark.parametrize("suffix", [".ome.tif", ".zarr", ".npz", ".tif"])
def test_maps_round_trip_through_every_maps_format(tmp_path, suffix, volume):
    pytest.importorskip("zarr") if suffix == ".zarr" else None
    m = _maps(volume)
    back = read_maps(write_maps(tmp_path / f"m{suffix}", m))
    assert back.channels == m.channels and back.meta == m.meta
    np.testing.assert_array_equal(back.maps, m.maps)


@pytest.mark.parametrize("volume", [False, True], ids=["bscan", "volume"])
def test_ome_tiff_maps_carry_channel_names_and_physical_sizes_in_um(tmp_path, volume):
    import xml.etree.ElementTree as ET

    path = write_maps(tmp_path / "m.ome.tif", _maps(volume))
    with tifffile.TiffFile(path) as tf:
        assert tf.is_ome
        series = tf.series[0]
        # planes in XYCZT order (channel fastest): tifffile names the series ZCYX; OME Z is depth
        assert series.axes == ("ZCYX" if volume else "CYX")
        assert series.shape == ((12, 3, 5, 16) if volume else (3, 12, 16))
        root = ET.fromstring(tf.ome_metadata)
    ns = {"o": "http://www.openmicroscopy.org/Schemas/OME/2016-06"}
    px = root.find("o:Image/o:Pixels", ns)
    assert [c.get("Name") for c in px.findall("o:Channel", ns)] == ["liv@original", "ocds@original", "mean_db@original"]
    want = {"Z": 1.9, "Y": 7.5, "X": 2.5} if volume else {"Y": 1.9, "X": 2.5}  # OME Y of a B-scan is depth
    for k, v in want.items():
        assert float(px.get(f"PhysicalSize{k}")) == pytest.approx(v) and px.get(f"PhysicalSize{k}Unit") == "µm"
    note = root.find("o:StructuredAnnotations/o:CommentAnnotation", ns)
    assert note.get("Namespace") == "torchdoct" and '"system"' in note.find("o:Value", ns).text


def test_ome_zarr_maps_have_ngff_axes_scale_and_labels(tmp_path):
    zarr = pytest.importorskip("zarr")
    path = write_maps(tmp_path / "m.zarr", _maps(True))
    g = zarr.open_group(str(path), mode="r")
    ms = g.attrs["multiscales"][0]
    assert ms["version"] == "0.4" and [a["name"] for a in ms["axes"]] == ["c", "z", "y", "x"]
    assert all(a["unit"] == "micrometer" for a in ms["axes"][1:])
    assert ms["datasets"][0]["coordinateTransformations"][0]["scale"] == pytest.approx([1.0, 1.9, 7.5, 2.5])
    assert next(c["label"] for c in g.attrs["omero"]["channels"]) == "liv@original"
    assert g["0"].shape == (3, 12, 5, 16)


@pytest.mark.parametrize("volume", [False, True], ids=["bscan", "volume"])
def test_ome_zarr_maps_hold_what_ngff_0_4_requires(tmp_path, volume):
    """NGFF 0.4 (image metadata): multiscales with version, axes (name and type; 2 to 3 space axes last, in
    z, y, x order, after the channel) and datasets whose one scale transform has a number per axis; omero
    channels each with a colour and a window of start, min, end, max."""
    zarr = pytest.importorskip("zarr")
    m = _maps(volume)
    g = zarr.open_group(str(write_maps(tmp_path / "m.zarr", m)), mode="r")
    [ms] = g.attrs["multiscales"]
    assert ms["version"] == "0.4" and isinstance(ms["name"], str)
    axes = ms["axes"]
    assert all(isinstance(a["name"], str) and a["type"] in ("channel", "space") for a in axes)
    space = [a["name"] for a in axes if a["type"] == "space"]
    assert space == (["z", "y", "x"] if volume else ["y", "x"]) and axes[0]["type"] == "channel"
    for d in ms["datasets"]:
        scales = [t for t in d["coordinateTransformations"] if t["type"] == "scale"]
        assert len(scales) == 1 and len(scales[0]["scale"]) == len(axes) == g[d["path"]].ndim
        assert all(isinstance(v, float) for v in scales[0]["scale"])
    chans = g.attrs["omero"]["channels"]
    assert [c["label"] for c in chans] == list(m.channels)
    for i, c in enumerate(chans):
        w = c["window"]
        assert isinstance(c["color"], str) and len(c["color"]) == 6
        assert w["min"] == w["start"] == pytest.approx(float(np.nanmin(m.maps[i])))
        assert w["max"] == w["end"] == pytest.approx(float(np.nanmax(m.maps[i])))


def test_truncated_ome_tiff_maps_are_refused(tmp_path):
    path = write_maps(tmp_path / "m.ome.tif", _maps(True))
    path.write_bytes(path.read_bytes()[:-2000])
    with pytest.raises(ValueError, match="m.ome.tif"):
        read_maps(path)


def test_the_maps_reader_stays_torch_free(tmp_path):
    import subprocess
    import sys

    path = write_maps(tmp_path / "m.ome.tif", _maps(False))
    code = (
        "import sys; from torchdoct.measured.mapsfile import read_maps; read_maps(sys.argv[1]); "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)


@pytest.mark.parametrize("volume", [False, True], ids=["bscan", "volume"])
def test_imagej_maps_tiff_has_one_description_and_the_metrics_on_c(tmp_path, volume):
    """Fiji sees a hyperstack of channels (and, for volumes, slices), never the metrics as frames; every page
    has at most one ImageDescription; the maps JSON is ImageJ's Info."""
    import json

    m = _maps(volume)
    path = write_maps(tmp_path / "m.tif", m)
    with tifffile.TiffFile(path) as tf:
        ij = tf.imagej_metadata
        assert [sum(t.code == 270 for t in p.tags.values()) for p in tf.pages] == [1] + [0] * (len(tf.pages) - 1)
        assert tf.pages[0].description.startswith("ImageJ=") and json.loads(ij["Info"]) == m.meta
        assert ij["channels"] == 3 and "frames" not in ij
        series = tf.series[0]
        assert series.axes == ("ZCYX" if volume else "CYX")  # tifffile's names: ImageJ slices Z, channels C
        stack = series.asarray()
    # page k of the volume is B-scan k // 3, channel k % 3
    want = m.maps.transpose(1, 0, 2, 3) if volume else m.maps
    np.testing.assert_array_equal(stack, want)


def test_maps_tiff_of_an_earlier_version_is_still_read(tmp_path):
    """Before: the JSON as the first ImageDescription, ImageJ's second, the volume's channels slowest."""
    import json

    m = _maps(True)
    path = tmp_path / "old.tif"
    ij = "ImageJ=1.11a\nimages=15\nslices=5\nframes=3\nhyperstack=true\nmode=grayscale\nloop=false\n"
    tifffile.imwrite(
        path,
        m.maps.reshape(-1, *m.maps.shape[-2:]),
        description=None,
        metadata=None,
        photometric="minisblack",
        extratags=[(270, "s", 0, json.dumps(m.meta), True), (270, "s", 0, ij, True)],
    )
    back = read_maps(path)
    assert back.channels == m.channels and back.meta == m.meta
    np.testing.assert_array_equal(back.maps, m.maps)

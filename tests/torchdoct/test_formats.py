"""The lab formats (torchdoct.measured.formats): one sequence stored as .npy, MATLAB v5, raw + sidecar,
OME-TIFF, OME-Zarr (NGFF 0.4 and 0.5) and a folder of per-frame TIFFs gives the same maps (read_sequence and
compute_maps, and ``torchdoct maps`` itself), with the pitch and the frame times taken from each format's own
metadata; the scale and orientation options; and every new reader's hardening (truncated, declared too large,
wrong dtype, special file: exit 2, one error line, nothing written)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import _formats as F
import numpy as np
import pytest
from _refusal import refused

from torchdoct.measured import guards
from torchdoct.measured.io import read_sequence

pytest.importorskip("scipy")
pytest.importorskip("tifffile")
zarr = pytest.importorskip("zarr")

SYSTEM = {"wavelength_um": 0.84, "lateral_resolution_um": 4.0, "axial_resolution_um": 3.0}
#: float32 rounding of maps computed from one field in another memory layout (summation and FFT order):
#: 256 ulp of the channel's largest value
ULP256 = 256 * float(np.finfo(np.float32).eps)

WRITERS = {
    "npy": lambda d, a: F.write_npy(d / "s.npy", a),
    "mat-v5": lambda d, a: F.write_mat(d / "s.mat", a),
    "raw-big-endian-header": lambda d, a: F.write_raw(d / "s.raw", a),
    "bin-little-endian": lambda d, a: F.write_raw(d / "s.bin", a, header=b"", big=False),
    "ome-tiff-time-increment": lambda d, a: F.write_ome_tiff(d / "s.ome.tif", a),
    "ome-tiff-plane-deltat": lambda d, a: F.write_ome_tiff(d / "s.ome.tif", a, per_plane=True),
    "ome-zarr-0.4": lambda d, a: F.write_ome_zarr(d / "s.zarr", a, "0.4"),
    "ome-zarr-0.5": lambda d, a: F.write_ome_zarr(d / "s.zarr", a, "0.5"),
    "tiff-folder": lambda d, a: F.write_tiff_folder(d / "frames", a),
}


pytestmark = pytest.mark.usefixtures("default_input_limit")  # tests/torchdoct/conftest.py


@pytest.fixture(scope="module")
def reference_maps(tmp_path_factory):
    """Maps of the field and of its intensity read from .npy, at the original and a reduced resolution."""
    from torchdoct.measured.maps import compute_maps

    d = tmp_path_factory.mktemp("ref")
    a = F.field()
    out = {
        "complex": compute_maps(
            read_sequence(F.write_npy(d / "c.npy", a), system=SYSTEM), ["original", "lateral=8,axial=6"]
        )
    }
    out["intensity"] = compute_maps(read_sequence(F.write_npy(d / "i.npy", np.abs(a) ** 2)), ["original"])
    return out


def _same_maps(got, want):
    assert got.channels == want.channels
    for i, name in enumerate(want.channels):
        w = want.maps[i]
        np.testing.assert_array_equal(np.isnan(got.maps[i]), np.isnan(w), err_msg=name)
        scale = float(np.nanmax(np.abs(w)))
        np.testing.assert_allclose(got.maps[i], w, rtol=ULP256, atol=ULP256 * scale, err_msg=name)


#: Formats read slab by slab when streamed (torchdoct maps --max-memory-gb): memory-mapped (.npy, raw, an
#: uncompressed OME-TIFF), chunked (OME-Zarr) or one file per frame (a folder of TIFFs); MATLAB v5 is read whole.
STREAMED = {
    "npy",
    "raw-big-endian-header",
    "bin-little-endian",
    "ome-tiff-time-increment",
    "ome-tiff-plane-deltat",
    "ome-zarr-0.4",
    "ome-zarr-0.5",
    "tiff-folder",
}


@pytest.mark.parametrize("read", ["whole", "streamed"])
@pytest.mark.parametrize("kind", ["complex", "intensity"])
@pytest.mark.parametrize("fmt", list(WRITERS))
def test_one_sequence_in_every_format_gives_the_same_maps(tmp_path, reference_maps, fmt, kind, read):
    from torchdoct.measured.formats.lazy import LazyArray
    from torchdoct.measured.maps import compute_maps

    a = F.field() if kind == "complex" else (np.abs(F.field()) ** 2).astype(np.float32)
    path = WRITERS[fmt](tmp_path, a)
    seq = read_sequence(path, system=SYSTEM if kind == "complex" else None, stream=read == "streamed")
    lazy = isinstance(seq.data, LazyArray)
    assert lazy == ((read == "streamed" and fmt in STREAMED) or fmt.startswith("ome-zarr")), type(seq.data)
    assert seq.axes == "TZX" and seq.data.shape == a.shape and seq.data.dtype == a.dtype
    np.testing.assert_allclose(seq.frame_times_s, [k * F.DT_S for k in range(a.shape[0])], rtol=1e-12, atol=1e-15)
    assert seq.pitch_um == pytest.approx(F.PITCH, rel=1e-12)
    resolutions = ["original", "lateral=8,axial=6"] if kind == "complex" else ["original"]
    _same_maps(compute_maps(seq, resolutions, slab_elements=3000), reference_maps[kind])


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_torchdoct_maps_gives_the_same_maps_file_from_every_format(tmp_path, fmt):
    """As a user runs it: ``torchdoct maps FILE --out m.npz`` on each format's copy of one complex sequence
    writes the maps of the .npy copy, with the pitch and frame times of the format's own metadata."""
    from torchdoct.cli import main
    from torchdoct.measured.mapsfile import read_maps

    a = F.field(t=16)
    opts = [
        "--no-progress",
        "--ocds-delay-range-s",
        "0.05",
        "0.3",
        "--resolution",
        "original",
        "--resolution",
        "lateral=8,axial=6",
        "--wavelength-um",
        "0.84",
        "--lateral-resolution-um",
        "4",
        "--axial-resolution-um",
        "3",
    ]
    (tmp_path / "ref").mkdir()
    (tmp_path / "fmt").mkdir()
    assert (
        main(["maps", str(F.write_npy(tmp_path / "ref" / "s.npy", a)), "--out", str(tmp_path / "ref.npz"), *opts]) == 0
    )
    assert main(["maps", str(WRITERS[fmt](tmp_path / "fmt", a)), "--out", str(tmp_path / "m.npz"), *opts]) == 0
    got, want = read_maps(tmp_path / "m.npz"), read_maps(tmp_path / "ref.npz")
    assert got.meta["pitch_um"] == pytest.approx(F.PITCH, rel=1e-12)
    np.testing.assert_allclose(got.meta["frame_times_s"], [k * F.DT_S for k in range(16)], rtol=1e-12, atol=1e-15)
    _same_maps(got, want)


def test_the_pitch_comes_from_the_format_not_from_a_stray_sidecar(tmp_path):
    """OME metadata win over a sidecar, which only fills in what the file lacks (here: the system)."""
    a = F.field(t=4)
    path = F.write_ome_tiff(tmp_path / "s.ome.tif", a)
    (tmp_path / "s.ome.json").write_text(json.dumps({"pitch_um": {"z": 9.0, "x": 9.0}, "system": SYSTEM}))
    seq = read_sequence(path)
    assert seq.pitch_um == pytest.approx(F.PITCH) and seq.system["lateral_resolution_um"] == 4.0


def test_ome_zarr_is_read_chunk_by_chunk(tmp_path):
    from torchdoct.measured.formats.lazy import LazyArray

    a = F.field(t=8)
    seq = read_sequence(F.write_ome_zarr(tmp_path / "s.zarr", a, chunks=(1, 12, 16)))
    assert isinstance(seq.data, LazyArray)
    np.testing.assert_array_equal(seq.data[2:5, 3], a[2:5, 3])


def test_ome_volume_has_z_as_depth(tmp_path):
    """OME-TIFF with SizeZ > 1: OME Z is depth (the optical axis), OME Y the slow lateral axis."""
    import tifffile

    v = F.field(t=4 * 3 * 5).reshape(4, 3, 5, 12, 16)[:, :, 0]  # [T, Zome=3, Yome=12, Xome=16]
    p = tmp_path / "v.ome.tif"
    tifffile.imwrite(
        p,
        v,
        ome=True,
        metadata={
            "axes": "TZYX",
            "PhysicalSizeZ": 2.5,
            "PhysicalSizeY": 7.0,
            "PhysicalSizeX": 1.5,
            "TimeIncrement": 0.1,
        },
    )
    seq = read_sequence(p)
    assert seq.axes == "TYZX" and seq.data.shape == (4, 12, 3, 16)
    assert seq.pitch_um == pytest.approx({"z": 2.5, "y": 7.0, "x": 1.5})
    np.testing.assert_array_equal(seq.data[1, 5, 2], v[1, 2, 5])


def test_folder_of_tiffs_is_read_in_name_order(tmp_path):
    import tifffile

    a = (np.abs(F.field(t=12)) ** 2).astype(np.float32)
    d = tmp_path / "frames"
    d.mkdir()
    for k in range(12):  # f2 before f10: digits compared as numbers
        tifffile.imwrite(d / f"f{k}.tif", a[k])
    F.sidecar(d, t=12)
    np.testing.assert_array_equal(read_sequence(d).data, a)


def test_ome_zarr_volume_has_z_as_depth(tmp_path):
    """NGFF axes t, z, y, x: z is depth (the optical axis), y the slow lateral axis; the pitch per axis from the
    scale transform in its unit."""
    v = F.field(t=4 * 3 * 5).reshape(4, 3, 5, 12, 16)[:, :, 0]  # [T, Zngff=3, Yngff=12, Xngff=16]
    group = zarr.open_group(str(tmp_path / "v.zarr"), mode="w", zarr_format=2)
    group.create_array("0", shape=v.shape, dtype=v.dtype)[:] = v
    axes = [{"name": "t", "type": "time", "unit": "second"}] + [
        {"name": n, "type": "space", "unit": "micrometer"} for n in "zyx"
    ]
    group.attrs["multiscales"] = [
        {
            "version": "0.4",
            "axes": axes,
            "datasets": [
                {"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [0.1, 2.5, 7.0, 1.5]}]}
            ],
        }
    ]
    seq = read_sequence(tmp_path / "v.zarr")
    assert seq.axes == "TYZX" and seq.data.shape == (4, 12, 3, 16)
    assert seq.pitch_um == pytest.approx({"z": 2.5, "y": 7.0, "x": 1.5})
    np.testing.assert_allclose(seq.frame_times_s, [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(seq.data[1, 5, 2], v[1, 2, 5])


def test_thorlabs_oct_is_refused_naming_the_exports_to_use(outdir, capsys):
    path = outdir / "scan.oct"
    path.write_bytes(b"PK\x05\x06" + b"\x00" * 18)  # an empty zip archive
    refused(capsys, outdir, _argv(outdir, path), "scan.oct", "not read", "OME-TIFF")


def test_dataset_names_the_variable_of_a_mat_v5_file(outdir, capsys):
    import scipy.io as sio

    a = F.field(t=8)
    p = outdir / "s.mat"
    sio.savemat(p, {"E": np.ascontiguousarray(a.transpose(1, 2, 0)), "background": np.ones((3, 3))})
    F.sidecar(p, t=8, axes="ZXT")
    np.testing.assert_array_equal(read_sequence(p, dataset="E").data, a)
    refused(capsys, outdir, _argv(outdir, p), "s.mat", "E", "background", "--dataset")
    refused(capsys, outdir, _argv(outdir, p, "--dataset", "nope"), "s.mat", "'nope'", "E, background")


def test_axes_override_reorients_a_mat_file(tmp_path):
    a = F.field(t=4)
    p = F.write_mat(tmp_path / "s.mat", a)
    seq = read_sequence(p, axes="ZXT")
    np.testing.assert_array_equal(seq.data, a)
    assert read_sequence(p, axes="XZT").data.shape == (4, 16, 12)


def test_db_scale_is_converted_to_linear_and_checked(tmp_path):
    i = (np.abs(F.field(t=4)) ** 2).astype(np.float64) + 1e-3
    p = F.write_npy(tmp_path / "db.npy", 10 * np.log10(i))
    np.testing.assert_allclose(read_sequence(p, scale="db").data, i, rtol=1e-12)
    with pytest.raises(ValueError, match="not dB values"):
        read_sequence(F.write_npy(tmp_path / "lin.npy", i * 1e40), scale="db")
    with pytest.raises(ValueError, match="negative"):  # dB read as linear: the fix names the dB conversion
        read_sequence(p, scale="linear")
    with pytest.raises(ValueError, match="--scale complex"):
        read_sequence(F.write_npy(tmp_path / "c.npy", F.field(t=4)), scale="db")
    with pytest.raises(ValueError, match="are real"):
        read_sequence(p, scale="complex")


# ----------------------------------------------------------------------------------------------------------
# hardening of every new reader: exit 2, one error line naming the file and the fix, nothing written
# ----------------------------------------------------------------------------------------------------------
def _argv(d: Path, src: Path, *extra: str) -> list[str]:
    return ["maps", str(src), "--out", str(d / "out" / "m.npz"), "--no-progress", *extra]


def _truncate(path: Path, keep: float = 0.6) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _zarr_chunk(store: Path) -> Path:
    chunks = sorted(
        p
        for p in store.rglob("*")
        if p.is_file() and not p.name.startswith((".", "zarr.json")) and p.parent.name != store.name
    )
    return chunks[0]


TRUNCATED = {
    "mat": (lambda d, a: F.write_mat(d / "s.mat", a), lambda p: _truncate(p), ["s.mat", "truncated"]),
    "raw": (lambda d, a: F.write_raw(d / "s.raw", a), lambda p: _truncate(p), ["s.raw", "truncated", "header_bytes"]),
    "ome-tiff": (lambda d, a: F.write_ome_tiff(d / "s.ome.tif", a), lambda p: _truncate(p), ["s.ome.tif"]),
    "ome-zarr": (
        lambda d, a: F.write_ome_zarr(d / "s.zarr", a),
        lambda p: _truncate(_zarr_chunk(p), 0.5),
        ["s.zarr", "chunk", "again completely"],
    ),
    "tiff-folder": (
        lambda d, a: F.write_tiff_folder(d / "fold", np.abs(a) ** 2),
        lambda p: _truncate(p / "frame3.tif", 0.5),
        ["frame3.tif", "truncated"],
    ),
}


@pytest.mark.parametrize("fmt", list(TRUNCATED))
def test_truncated_input_is_refused(outdir, capsys, fmt):
    write, cut, names = TRUNCATED[fmt]
    path = write(outdir, F.field(t=8))
    cut(path)
    refused(capsys, outdir, _argv(outdir, path), *names)


@pytest.mark.parametrize("fmt", ["mat", "raw", "ome-tiff", "ome-zarr", "tiff-folder"])
def test_declared_size_over_the_limit_is_refused_before_reading(outdir, capsys, fmt):
    path = TRUNCATED[fmt][0](outdir, F.field(t=8))
    refused(capsys, outdir, _argv(outdir, path, "--max-input-gb", "1e-6"), path.name, "--max-input-gb")


def test_raw_sidecar_declaring_a_huge_shape_is_refused_before_the_file_is_mapped(outdir, capsys):
    path = F.write_raw(outdir / "s.raw", F.field(t=4))
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["shape"] = [4, 10**6, 10**6]
    path.with_suffix(".json").write_text(json.dumps(meta))
    refused(capsys, outdir, _argv(outdir, path), "s.raw", "--max-input-gb")


def test_zarr_declaring_a_huge_array_is_refused_before_reading(outdir, capsys):
    path = F.write_ome_zarr(outdir / "s.zarr", F.field(t=4))
    group = zarr.open_group(str(path), mode="a")
    group.create_array("0", shape=(4, 10**6, 10**6), dtype=np.complex64, chunks=(1, 16, 16), overwrite=True)
    refused(capsys, outdir, _argv(outdir, path), "s.zarr", "--max-input-gb")


def _wrong_dtype(fmt: str, d: Path) -> tuple[Path, list[str], list[str]]:
    if fmt == "mat":
        import scipy.io as sio

        p = d / "s.mat"
        sio.savemat(p, {"E": np.arange(8 * 6 * 5, dtype=np.int32).reshape(6, 5, 8)})
        F.sidecar(p, t=8, axes="ZXT")
        return p, [], ["s.mat", "neither complex"]
    if fmt == "raw":
        p = F.write_raw(d / "s.raw", F.field(t=8))
        meta = json.loads(p.with_suffix(".json").read_text())
        meta["dtype"] = "int64"
        p.with_suffix(".json").write_text(json.dumps(meta))
        return p, [], ["s.json", "int64", "complex64"]
    if fmt == "ome-tiff":
        return F.write_ome_tiff(d / "s.ome.tif", F.field(t=8)), ["--scale", "db"], ["s.ome.tif", "--scale complex"]
    if fmt == "ome-zarr":
        p = F.write_ome_zarr(d / "s.zarr", F.field(t=8))
        zarr.open_group(str(p), mode="a").create_array("0", shape=(8, 12, 16), dtype=bool, overwrite=True)
        return p, [], ["s.zarr", "bool", "not numeric"]
    import tifffile

    p = F.write_tiff_folder(d / "fold", (np.abs(F.field(t=8)) ** 2).astype(np.float32))
    tifffile.imwrite(p / "frame5.tif", np.zeros((12, 16), np.uint16))
    return p, [], ["frame5.tif", "same shape and dtype"]


@pytest.mark.parametrize("fmt", ["mat", "raw", "ome-tiff", "ome-zarr", "tiff-folder"])
def test_wrong_dtype_is_refused(outdir, capsys, fmt):
    path, extra, names = _wrong_dtype(fmt, outdir)
    refused(capsys, outdir, _argv(outdir, path, *extra), *names)


@pytest.mark.parametrize("kind", ["fifo", "device", "directory"])
@pytest.mark.parametrize("name", ["s.mat", "s.raw", "s.bin", "s.ome.tif", "s.zarr"])
def test_special_file_is_refused_at_once(outdir, capsys, name, kind):
    """A FIFO (a reader that opened it would block until a writer came), a link to an endless device or a
    folder named like a file format; an OME-Zarr is a folder, so a folder named .zarr is its format's (an empty
    one is no OME-Zarr) and a device or FIFO named .zarr is refused."""
    from _special import special

    path = special(outdir / name, kind)
    F.sidecar(path, t=8)
    if name == "s.zarr" and kind == "directory":
        refused(capsys, outdir, _argv(outdir, path), name, "not a readable zarr group", "zarr.json")
    else:
        refused(capsys, outdir, _argv(outdir, path), name, "not a regular file" if kind != "directory" else "")


def test_a_plain_file_named_zarr_is_refused_naming_the_folder_it_must_be(outdir, capsys):
    path = outdir / "s.zarr"
    path.write_bytes(b"\x00" * 64)
    F.sidecar(path, t=8)
    refused(capsys, outdir, _argv(outdir, path), "s.zarr", "folder")


def test_fifo_in_a_tiff_folder_is_refused_at_once(outdir, capsys):
    path = F.write_tiff_folder(outdir / "fold", (np.abs(F.field(t=4)) ** 2).astype(np.float32))
    os.mkfifo(path / "frame9.tif")
    refused(capsys, outdir, _argv(outdir, path), "fold/frame9.tif", "is not a regular file (it is a FIFO")


def test_ome_tiff_declaring_more_planes_than_pages_is_refused(outdir, capsys):
    path = F.write_ome_tiff(outdir / "s.ome.tif", F.field(t=8))
    import tifffile

    with tifffile.TiffFile(path) as tf:
        xml = tf.pages[0].description
    data = path.read_bytes().replace(b'SizeT="8"', b'SizeT="9"')
    assert b'SizeT="9"' in data and 'SizeT="8"' in xml
    path.write_bytes(data)
    refused(capsys, outdir, _argv(outdir, path), "s.ome.tif", "SizeT=9", "pages")


def test_ome_xml_with_entities_is_refused(tmp_path):
    from torchdoct.measured.formats.ometiff import parse_ome

    with pytest.raises(ValueError, match="entities"):
        parse_ome('<?xml version="1.0"?><!DOCTYPE a [<!ENTITY x "y">]><OME/>', "s.ome.tif")


# ----------------------------------------------------------------------------------------------------------
# sequence files carry their metadata inside
# ----------------------------------------------------------------------------------------------------------
def _meta(t: int) -> dict:
    return {
        "axes": "TZX",
        "pitch_um": F.PITCH,
        "frame_times_s": [k * F.DT_S for k in range(t)],
        "system": {"name": "lab", **SYSTEM, "refractive_index": 1.33},
    }


def test_npz_sequence_travels_without_its_sidecar(tmp_path):
    from torchdoct.measured.io import write_sequence

    a = F.field(t=4)
    p = write_sequence(tmp_path / "s.npz", a, _meta(4))
    p.with_suffix(".json").unlink()
    seq = read_sequence(p)
    assert seq.pitch_um == F.PITCH and seq.system["refractive_index"] == 1.33
    np.testing.assert_array_equal(seq.data, a)


def test_hdf5_sequence_has_one_attribute_per_field(tmp_path):
    h5py = pytest.importorskip("h5py")
    from torchdoct.measured.io import write_sequence

    p = write_sequence(tmp_path / "s.h5", F.field(t=4), _meta(4))
    with h5py.File(p, "r") as fh:
        attrs = dict(fh.attrs)
    assert attrs["axes"] == "TZX" and attrs["pitch_um.z"] == F.PITCH["z"] and attrs["system.name"] == "lab"
    np.testing.assert_allclose(attrs["frame_times_s"], [k * F.DT_S for k in range(4)])
    assert attrs["system.refractive_index"] == 1.33 and json.loads(attrs["torchdoct"])["axes"] == "TZX"


def test_an_hdf5_field_attribute_edited_apart_from_the_json_is_refused(outdir, capsys):
    """An HDF5 viewer shows one attribute per field; one edited there and not in the JSON attribute that is
    read would be ignored without a word: it is refused, naming both values."""
    h5py = pytest.importorskip("h5py")
    from torchdoct.measured.io import write_sequence

    p = write_sequence(outdir / "s.h5", F.field(t=8), _meta(8))
    assert read_sequence(p).pitch_um == F.PITCH
    with h5py.File(p, "a") as fh:
        fh.attrs["pitch_um.z"] = 2.5
    refused(capsys, outdir, _argv(outdir, p), "s.h5", "'pitch_um.z'", "2.5", "1.0", "edit both")


# ----------------------------------------------------------------------------------------------------------
# streaming: a memory-mapped input is read slab by slab within --max-memory-gb
# ----------------------------------------------------------------------------------------------------------
def test_streamed_npy_is_read_in_slabs_within_the_budget_and_gives_the_same_maps(tmp_path, monkeypatch):
    from torchdoct.measured.formats import lazy
    from torchdoct.measured.maps import compute_maps
    from torchdoct.runtime.resources import MAPS_WORK_COPIES, slab_elements_within

    a = F.field(t=32, z=64, x=48)
    p = F.write_npy(tmp_path / "s.npy", a)
    reads = []
    real_getitem = lazy.MappedFile.__getitem__

    def counted(self, key):
        out = real_getitem(self, key)
        reads.append(out.nbytes)
        return out

    monkeypatch.setattr(lazy.MappedFile, "__getitem__", counted)
    seq = read_sequence(p, stream=True)
    assert isinstance(seq.data, lazy.LazyArray)
    budget_gb = 0.0004  # 429 kB: the output maps (37 kB) and slabs of a few rows
    n = slab_elements_within(
        budget_gb, a.shape, 8, complex_samples=True, n_resolutions=1, metrics=["liv", "ocds", "mean_db"]
    )
    reads.clear()
    got = compute_maps(seq, ["original"], slab_elements=n)
    assert reads and max(reads) <= max(n * 8, a[0].nbytes)  # a slab, or one frame for the peak scan
    assert MAPS_WORK_COPIES * n * 8 < budget_gb * (1 << 30)
    want = compute_maps(read_sequence(p), ["original"])
    np.testing.assert_array_equal(got.maps, want.maps)  # per-pixel metrics: the slab size changes nothing


@pytest.mark.parametrize("fmt", ["npy", "raw", "ome-zarr"])
def test_a_streamed_input_is_bound_by_the_budget_not_by_the_default_input_limit(tmp_path, monkeypatch, fmt):
    """Read slab by slab (--max-memory-gb), a .npy, raw binary or OME-Zarr over the default input limit is read;
    read whole it is refused naming --max-input-gb, and an explicit limit binds a streamed input too."""
    write = {
        "npy": lambda: F.write_npy(tmp_path / "s.npy", a),
        "raw": lambda: F.write_raw(tmp_path / "s.raw", a),
        "ome-zarr": lambda: F.write_ome_zarr(tmp_path / "s.zarr", a),
    }[fmt]
    a = F.field(t=8)
    path = write()
    monkeypatch.setattr(guards, "DEFAULT_MAX_INPUT_GB", 1e-6)  # 1 kB: the field is 12 kB
    seq = read_sequence(path, stream=True)
    np.testing.assert_array_equal(seq.data[2:5], a[2:5])
    with pytest.raises(ValueError, match="--max-memory-gb GB .*, or raise the limit with --max-input-gb"):
        read_sequence(path)
    guards.set_max_input_gb(1e-6)
    with pytest.raises(ValueError, match="--max-input-gb"):
        read_sequence(path, stream=True)


def test_streamed_big_endian_raw_and_integer_zarr_are_converted_as_they_are_read(tmp_path):
    from torchdoct.measured.formats.lazy import LazyArray

    a = F.field(t=8)
    seq = read_sequence(F.write_raw(tmp_path / "s.raw", a), stream=True)  # big-endian samples
    assert isinstance(seq.data, LazyArray) and seq.data.dtype == np.complex64 and seq.data.dtype.isnative
    np.testing.assert_array_equal(seq.data[1:3, 4], a[1:3, 4])
    counts = (np.abs(a) ** 2 * 1000).astype(np.uint16)
    seq = read_sequence(F.write_ome_zarr(tmp_path / "c.zarr", counts))
    assert isinstance(seq.data, LazyArray) and seq.data.dtype == np.float32  # OME-Zarr counts: an intensity
    np.testing.assert_array_equal(seq.data[3], counts[3].astype(np.float32))


def test_a_compressed_ome_tiff_is_read_whole_even_when_streamed(tmp_path):
    import tifffile

    from torchdoct.measured.formats.lazy import LazyArray

    a = F.field(t=6)
    p = tmp_path / "z.ome.tif"
    tifffile.imwrite(
        p,
        a,
        ome=True,
        compression="zlib",
        metadata={"axes": "TYX", "TimeIncrement": 0.05, "PhysicalSizeX": 1.5, "PhysicalSizeY": 1.0},
    )
    seq = read_sequence(p, stream=True)
    assert not isinstance(seq.data, LazyArray)  # no run of raw bytes to map
    np.testing.assert_array_equal(seq.data, a)


def test_a_frame_file_damaged_after_the_check_is_named_when_streamed(tmp_path):
    path = F.write_tiff_folder(tmp_path / "fold", (np.abs(F.field(t=6)) ** 2).astype(np.float32))
    seq = read_sequence(path, stream=True)
    _truncate(path / "frame4.tif", 0.5)
    with pytest.raises(ValueError, match="frame4.tif"):
        seq.data[:, 2:4]


def test_streamed_db_input_is_converted_slab_by_slab_to_the_same_intensity(tmp_path):
    from torchdoct.measured.formats.lazy import LazyArray

    i = (np.abs(F.field(t=8)) ** 2).astype(np.float32) + np.float32(1e-3)
    p = F.write_npy(tmp_path / "db.npy", (10 * np.log10(i)).astype(np.float32))
    streamed, whole = read_sequence(p, scale="db", stream=True), read_sequence(p, scale="db")
    assert isinstance(streamed.data, LazyArray) and streamed.data.dtype == np.float32
    np.testing.assert_array_equal(streamed.data[2:6, 3], whole.data[2:6, 3])
    np.testing.assert_allclose(whole.data, i, rtol=1e-5)


def test_a_budget_the_output_alone_fills_is_refused(outdir, capsys):
    path = F.write_npy(outdir / "s.npy", F.field(t=8))  # 8 frames: OCDS delays on 2+ pairs up to 6 frame intervals
    refused(
        capsys,
        outdir,
        _argv(outdir, path, "--max-memory-gb", "1e-7", "--ocds-delay-range-s", "0.05", "0.3"),
        "--max-memory-gb",
        "output maps",
    )


def _peak_rss_growth(tmp_path: Path, argv: list[str]) -> int:
    import subprocess
    import sys

    probe = (
        "import json, sys\nimport torch, torchdoct.measured.maps\nfrom torchdoct.cli import main\n"
        "def st(k):\n    return next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith(k))\n"
        "b = st('VmRSS:')\nc = main(sys.argv[1:])\nprint(json.dumps([c, st('VmHWM:') - b]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, *argv],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    code, growth = json.loads(out.stdout.strip().splitlines()[-1])
    assert code == 0, out.stderr
    return growth


@pytest.mark.slow
def test_peak_rss_of_a_streamed_input_stays_far_below_its_size(tmp_path):
    """64 MiB memory-mapped input, 16 MiB budget: the peak resident growth stays below the input's size
    (the default run keeps every page it touched)."""
    rng = np.random.default_rng(0)
    a = np.lib.format.open_memmap(tmp_path / "s.npy", mode="w+", dtype=np.complex64, shape=(32, 512, 512))
    for t in range(32):
        a[t] = (rng.standard_normal((512, 512)) + 1j * rng.standard_normal((512, 512))).astype(np.complex64)
    a.flush()
    del a
    F.sidecar(tmp_path / "s.npy", t=32)
    base = ["maps", str(tmp_path / "s.npy"), "--no-progress", "--force"]
    default = _peak_rss_growth(tmp_path, base + ["--out", str(tmp_path / "a.npz")])
    streamed = _peak_rss_growth(tmp_path, base + ["--out", str(tmp_path / "b.npz"), "--max-memory-gb", "0.016"])
    assert streamed < 64 << 20 < default


def _long_input(folder: Path, frames: int) -> Path:
    """A memory-mapped complex64 [frames, 16, 64] sequence, sparse after its first frame."""
    rng = np.random.default_rng(0)
    a = np.lib.format.open_memmap(folder / "s.npy", mode="w+", dtype=np.complex64, shape=(frames, 16, 64))
    a[0] = (rng.standard_normal((16, 64)) + 1j * rng.standard_normal((16, 64))).astype(np.complex64)
    a.flush()
    del a
    (folder / "s.json").write_text(
        json.dumps({"axes": "TZX", "pitch_um": F.PITCH, "frame_times_s": [k * 0.2048 for k in range(frames)]})
    )
    return folder / "s.npy"


@pytest.mark.slow
def test_peak_memory_of_streamed_maps_does_not_grow_with_the_frames(tmp_path):
    """The same B-scan over 256 and 8192 frames (0.5 and 64 MiB), streamed within 16 MiB: the peak resident
    growth of the longer one stays within 32 MiB of the shorter one's (before, the OCDS pair check listed
    every frame pair on every slab: gigabytes at 8192 frames)."""
    growth = []
    for frames in (256, 8192):
        d = tmp_path / str(frames)
        d.mkdir()
        path = _long_input(d, frames)
        growth.append(
            _peak_rss_growth(
                d,
                [
                    "maps",
                    str(path),
                    "--no-progress",
                    "--out",
                    str(d / "m.npz"),
                    "--max-memory-gb",
                    "0.016",
                    "--threads",
                    "1",
                ],
            )
        )
    assert growth[1] < growth[0] + (32 << 20), growth

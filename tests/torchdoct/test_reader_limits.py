"""The readers' limits: bounded resources, safe HDF5, nonsense refused.

Each refusal is exit 2 with one ``error:`` line naming the file, what is wrong and the fix (the option
or environment variable that allows it), no traceback and nothing written; a read the system refuses is
exit 1.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from _refusal import refused
from _refusal import tree as _tree

from torchdoct.cli import main
from torchdoct.measured import guards
from torchdoct.measured.io import read_sequence

h5py = pytest.importorskip("h5py")
tifffile = pytest.importorskip("tifffile")

META = {
    "axes": "TZX",
    "pitch_um": {"z": 2.0, "x": 2.0},
    "frame_times_s": [0.2048 * i for i in range(8)],
    "system": {
        "name": "s",
        "wavelength_um": 0.84,
        "lateral_resolution_um": 4.9,
        "axial_resolution_um": 3.8,
        "refractive_index": 1.0,
    },
}


pytestmark = pytest.mark.usefixtures("default_input_limit")  # tests/torchdoct/conftest.py


def _field(shape=(8, 6, 5), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)


def _sidecar(path: Path) -> Path:
    path.with_suffix(".json").write_text(json.dumps(META))
    return path


def _maps_argv(tmp_path: Path, src: Path, *extra: str) -> list[str]:
    return ["maps", str(src), "--out", str(tmp_path / "out" / "m.npz"), "--no-progress", *extra]


# ----------------------------------------------------------------------------------------------------------
# 1. safe HDF5: nothing outside the input file is read unless --allow-external-hdf5
# ----------------------------------------------------------------------------------------------------------
def _h5_external_storage(tmp_path: Path) -> tuple[Path, Path]:
    secret = tmp_path / "secret.bin"
    secret.write_bytes(_field().tobytes())
    path = tmp_path / "ext.h5"
    with h5py.File(path, "w") as fh:
        fh.create_dataset("data", shape=(8, 6, 5), dtype=np.complex64, external=[(str(secret), 0, 8 * 6 * 5 * 8)])
        fh.attrs["torchdoct"] = json.dumps(META)
    return path, secret


def _h5_external_link(tmp_path: Path) -> tuple[Path, Path]:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as fh:
        fh["data"] = _field()
    path = tmp_path / "link.h5"
    with h5py.File(path, "w") as fh:
        fh["data"] = h5py.ExternalLink(str(other), "/data")
        fh.attrs["torchdoct"] = json.dumps(META)
    return path, other


def _h5_virtual(tmp_path: Path) -> tuple[Path, Path]:
    other = tmp_path / "source.h5"
    with h5py.File(other, "w") as fh:
        fh["field"] = _field()
    layout = h5py.VirtualLayout(shape=(8, 6, 5), dtype=np.complex64)
    layout[:] = h5py.VirtualSource(str(other), "field", shape=(8, 6, 5))
    path = tmp_path / "virtual.h5"
    with h5py.File(path, "w") as fh:
        fh.create_virtual_dataset("data", layout)
        fh.attrs["torchdoct"] = json.dumps(META)
    return path, other


@pytest.mark.parametrize(
    "make, what",
    [(_h5_external_storage, "external file"), (_h5_external_link, "external link"), (_h5_virtual, "virtual dataset")],
)
def test_hdf5_pointing_outside_the_file_is_refused_unless_allowed(outdir, capsys, make, what):
    path, target = make(outdir)
    line = refused(
        capsys, outdir, _maps_argv(outdir, path), path.name, "/data", target.name, what, "--allow-external-hdf5"
    )
    assert "\n" not in line
    with pytest.raises(ValueError, match="allow_external_hdf5=True"):
        read_sequence(path)
    seq = read_sequence(path, allow_external_hdf5=True)  # explicitly allowed: the other file is read
    np.testing.assert_array_equal(seq.data, _field())
    assert main(_maps_argv(outdir, path, "--allow-external-hdf5")) == 0


def test_virtual_dataset_inside_the_file_is_read(tmp_path):
    path = tmp_path / "self.h5"
    with h5py.File(path, "w") as fh:
        fh["field"] = _field()
        layout = h5py.VirtualLayout(shape=(8, 6, 5), dtype=np.complex64)
        layout[:] = h5py.VirtualSource(".", "field", shape=(8, 6, 5))
        fh.create_virtual_dataset("data", layout)
        fh.attrs["torchdoct"] = json.dumps(META)
    np.testing.assert_array_equal(read_sequence(path).data, _field())


# ----------------------------------------------------------------------------------------------------------
# 2. declared sizes checked before anything is allocated
# ----------------------------------------------------------------------------------------------------------
def _npy_bytes_declaring(shape: tuple[int, ...], dtype=np.complex64, payload: bytes = b"") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue() + payload


def test_tiny_npz_declaring_a_tebibyte_is_refused(outdir, capsys):
    path = outdir / "liar.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("data.npy", _npy_bytes_declaring((1200, 1 << 14, 8000)) + bytes(1000))
    _sidecar(path)
    assert path.stat().st_size < 1300
    line = refused(capsys, outdir, _maps_argv(outdir, path), "liar.npz", "TiB", "--max-input-gb", guards.MAX_INPUT_ENV)
    assert "1.14 TiB" in line  # 1200 * 16384 * 8000 * 8 bytes = 1.258e15


def test_zip_bomb_npz_is_refused_before_decompressing(outdir, capsys, monkeypatch):
    path = outdir / "bomb.npz"
    np.savez_compressed(path, data=np.zeros((64, 256, 256), np.complex64))  # 32 MiB in ~33 KB
    _sidecar(path)
    assert path.stat().st_size < 100_000
    monkeypatch.setenv(guards.MAX_INPUT_ENV, "0.01")  # a 10 MiB limit stands for the 8 GiB default
    import tracemalloc

    tracemalloc.start()
    refused(capsys, outdir, _maps_argv(outdir, path), "bomb.npz", "32 MiB", "--max-input-gb", guards.MAX_INPUT_ENV)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 4 << 20, peak  # nothing near the declared 32 MiB was allocated


def test_limit_is_raised_by_the_option(outdir, capsys, monkeypatch):
    path = _sidecar(outdir / "seq.npy")
    np.save(path, _field())
    monkeypatch.setenv(guards.MAX_INPUT_ENV, "1e-6")  # ~1 KiB: the 1.9 KiB sequence is over it
    refused(capsys, outdir, _maps_argv(outdir, path), "seq.npy", "--max-input-gb")
    assert main(_maps_argv(outdir, path, "--max-input-gb", "1")) == 0


def test_npy_and_hdf5_declaring_huge_arrays_are_refused(outdir, capsys):
    npy = _sidecar(outdir / "huge.npy")
    npy.write_bytes(_npy_bytes_declaring((4096, 4096, 4096)) + bytes(64))
    refused(capsys, outdir, _maps_argv(outdir, npy), "huge.npy", "512 GiB", "--max-input-gb")
    h5 = outdir / "huge.h5"
    with h5py.File(h5, "w") as fh:  # chunked and compressed, never written: a few KB on disk
        fh.create_dataset("data", shape=(4096, 4096, 4096), dtype=np.complex64, chunks=(1, 64, 64), compression="gzip")
        fh.attrs["torchdoct"] = json.dumps(META)
    assert h5.stat().st_size < 100_000
    refused(capsys, outdir, _maps_argv(outdir, h5), "huge.h5", "data", "512 GiB", "--max-input-gb")


@pytest.mark.parametrize(
    "extra, names",
    [
        ((), ("frame_times_s", "T = 3 frames")),
        (("--axes", "TYZX"), ("axes", "--axes")),
        (("--block-raster", "2:2:4"), ("block raster 2:2:4", "[16, Z, X]", "--block-raster")),
    ],
)
def test_metadata_that_does_not_fit_the_declared_shape_is_refused_before_a_sample_is_read(
    outdir, capsys, monkeypatch, extra, names
):
    from torchdoct.measured import io as mio

    def touched(*args, **kwargs):
        raise AssertionError("a sample was read before the metadata were checked against the declared shape")

    monkeypatch.setattr(mio, "_check_values", touched)
    monkeypatch.setattr(mio, "_apply_scale", touched)
    path = _sidecar(outdir / "sparse.npy")  # the sidecar's 8 frame times against 3 declared frames
    shape = (3, 64, 64) if not extra else (8, 64, 64)
    if extra and extra[0] == "--block-raster":
        shape = (6, 64, 64)
        meta = dict(META, frame_times_s=[0.0, 0.2])
        path.with_suffix(".json").write_text(json.dumps(meta))
    with path.open("wb") as fh:  # a sparse file: the header, then holes
        fh.write(_npy_bytes_declaring(shape))
        fh.truncate(fh.tell() + int(np.prod(shape)) * 8)
    refused(capsys, outdir, _maps_argv(outdir, path, *extra), "sparse.npy", *names)


def test_tiff_over_the_limit_is_refused(outdir, capsys, monkeypatch):
    path = outdir / "stack.tif"
    tifffile.imwrite(path, np.zeros((64, 128, 128), np.float32), compression="zlib")  # 4 MiB, small on disk
    monkeypatch.setenv(guards.MAX_INPUT_ENV, "0.001")
    refused(
        capsys,
        outdir,
        _maps_argv(outdir, path, "--pitch-um", "z=2,x=2", "--frame-interval-s", "0.2"),
        "stack.tif",
        "64 pages",
        "4 MiB",
        "--max-input-gb",
        absent=("not a readable",),
    )  # a size, not damage


def test_maps_file_over_the_limit_is_refused_in_compare(tmp_path, capsys):
    path = tmp_path / "a.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("maps.npy", _npy_bytes_declaring((3, 1 << 16, 1 << 16), np.float32))
        zf.writestr("meta_json.npy", _npy_bytes_declaring((), "<U2") + "{}".encode("utf-32-le"))
    refused(capsys, tmp_path, ["compare", f"A={path}", f"B={path}"], "a.npz", "48 GiB", "--max-input-gb")


# ----------------------------------------------------------------------------------------------------------
# 3. nonsense samples and broken files named with the fix
# ----------------------------------------------------------------------------------------------------------
def _speckle_seq(tmp_path: Path, name: str, a: np.ndarray):
    meta = dict(META, frame_times_s=[0.2048 * i for i in range(a.shape[0])], pitch_um={"z": 1.5, "x": 2.0})
    from torchdoct.measured.io import write_sequence

    return read_sequence(write_sequence(tmp_path / name, a, meta))


def test_one_nan_sample_costs_its_neighbourhood_a_share_of_its_window_not_its_pixels(tmp_path):
    """One NaN sample (of 30,720): at the original resolution its pixel alone is NaN; after a reduction no pixel
    is (normalised convolution), the valid-weight channel is below 1 only within the window's reach of it
    (5 sigma') and every pixel beyond equals the clean data's maps."""
    from torchdoct.measured.maps import MIN_VALID_WEIGHT, compute_maps
    from torchdoct.measured.slabs import nonfinite_mask

    a = _field((16, 40, 48), seed=3)
    clean = _speckle_seq(tmp_path, "clean.npy", a)
    b = a.copy()
    b[3, 20, 24] = np.nan
    dirty = _speckle_seq(tmp_path, "dirty.npy", b)
    assert dirty.nonfinite_samples == 1
    res = ["original", "lateral=18", "axial=14,lateral=18"]
    mc = compute_maps(clean, res)
    md = compute_maps(dirty, res)
    assert md.meta["nonfinite"]["samples"] == 1
    assert md.meta["nonfinite"]["masked_pixels"] == {"original": 1, "lateral=18": 0, "axial=14,lateral=18": 0}
    for r in res:
        w = md.maps[md.channels.index(f"valid_weight@{r}")]
        reach = nonfinite_mask(dirty, r)  # within 5 sigma' of the sample (its pixel at the original)
        assert np.all(w[~reach] == 1.0) and w[20, 24] == w.min() < 1.0, r  # the deficit is largest at the sample
        assert w.min() >= (0.0 if r == "original" else MIN_VALID_WEIGHT), r
    for i, ch in enumerate(mc.channels):
        r = ch.split("@")[1]
        got = md.maps[md.channels.index(ch)]
        reach = nonfinite_mask(dirty, r)
        if r == "original":
            assert np.isnan(got[20, 24]) and np.isfinite(got[reach == 0][np.isfinite(mc.maps[i][reach == 0])]).all()
        else:
            assert np.array_equal(np.isfinite(got), np.isfinite(mc.maps[i])), ch  # no pixel lost
        keep = ~reach & np.isfinite(mc.maps[i])
        np.testing.assert_allclose(got[keep], mc.maps[i][keep], rtol=1e-4, atol=1e-3, err_msg=ch)


def test_a_region_of_missing_samples_voids_only_the_pixels_whose_window_rests_mostly_on_it(tmp_path):
    from torchdoct.measured.maps import MIN_VALID_WEIGHT, compute_maps

    a = _field((16, 40, 48), seed=4)
    a[:, :, 20:30] = np.nan  # ten dead A-lines
    m = compute_maps(_speckle_seq(tmp_path, "dead.npy", a), ["lateral=18"])
    w = m.maps[m.channels.index("valid_weight@lateral=18")]
    liv = m.maps[m.channels.index("liv@lateral=18")]
    assert np.array_equal(np.isnan(liv), w < MIN_VALID_WEIGHT)
    assert np.isnan(liv[:, 24]).all() and np.isfinite(liv[:, :15]).all() and np.isfinite(liv[:, 35:]).all()


def test_nan_samples_give_a_note_and_masked_signature(outdir, capsys):
    path = _sidecar(outdir / "nan.npy")
    a = _field((8, 6, 10))  # 10 × 2 µm wide: the field of view holds the lateral=18 target
    a[3, 2, 1] = np.nan
    a[5, 2, 1] = np.inf
    np.save(path, a)
    assert main(_maps_argv(outdir, path, "--resolution", "original", "--resolution", "lateral=18", "--signature")) == 0
    out = capsys.readouterr().out
    assert "note: nan.npy: 2 samples are NaN or infinite, masked" in out and "(pixels: 1 at original" in out
    from torchdoct.measured.io import read_maps

    m = read_maps(outdir / "out" / "m.npz")
    for i, ch in enumerate(m.channels):
        v = m.maps[i]
        if ch.endswith("@original") and not ch.startswith(("aliv", "valid_weight")):
            assert np.isnan(v[2, 1]) and np.isfinite(np.delete(v.ravel(), 2 * v.shape[1] + 1)).any(), ch
        if ch.endswith("@lateral=18") and not ch.startswith("valid_weight"):  # normalised: no pixel lost
            assert np.isfinite(v[2]).any(), ch
    w = m.maps[m.channels.index("valid_weight@lateral=18")]
    assert np.all(w[[0, 1, 3, 4, 5]] == 1.0) and np.all(w[2] < 1.0)


def test_negative_intensities_are_refused(outdir, capsys):
    path = _sidecar(outdir / "neg.npy")
    a = np.abs(_field()) ** 2
    a[:, 0, :2] = -1.0
    np.save(path, a.astype(np.float32))
    refused(capsys, outdir, _maps_argv(outdir, path), "neg.npy", "16 of 240 intensity samples are negative")


def test_tiff_pages_of_two_shapes_are_refused(outdir, capsys):
    path = outdir / "mixed.tif"
    with tifffile.TiffWriter(path) as tw:
        for k in range(4):
            tw.write(np.ones((6, 5) if k < 2 else (6, 4), np.float32))
    refused(
        capsys,
        outdir,
        _maps_argv(outdir, path, "--pitch-um", "z=2,x=2", "--frame-interval-s", "0.2"),
        "mixed.tif",
        "page 0 is [6, 5]",
        "page 2 is [6, 4]",
    )


def test_extended_precision_is_refused_naming_the_fix(outdir, capsys):
    if np.dtype(np.clongdouble).itemsize <= 16:
        pytest.skip("no extended precision on this platform")
    path = _sidecar(outdir / "long.npy")
    np.save(path, _field().astype(np.clongdouble))
    refused(capsys, outdir, _maps_argv(outdir, path), "long.npy", "complex128")


def test_truncated_arrays_are_named_with_the_fix(outdir, capsys):
    full = _field()
    npy = _sidecar(outdir / "cut.npy")
    np.save(npy, full)
    npy.write_bytes(npy.read_bytes()[:-100])
    refused(capsys, outdir, _maps_argv(outdir, npy), "cut.npy", "truncated", "again completely")
    npz = _sidecar(outdir / "cut.npz")
    with zipfile.ZipFile(npz, "w") as zf:  # a member whose data stop short of its header's shape
        zf.writestr("data.npy", _npy_bytes_declaring(full.shape) + full.tobytes()[:-80])
    refused(capsys, outdir, _maps_argv(outdir, npz), "cut.npz", "truncated", "again completely")


def test_unreadable_input_is_a_system_refusal(outdir, capsys, monkeypatch):
    path = _sidecar(outdir / "locked.npy")
    np.save(path, _field())
    from torchdoct.measured.formats import npy as npy_format

    def denied(p):
        raise PermissionError(13, "Permission denied", str(p))

    monkeypatch.setattr(npy_format, "load_array", denied)  # running as root, chmod cannot deny a read
    refused(capsys, outdir, _maps_argv(outdir, path), "locked.npy", "Permission denied", code=1)


# ----------------------------------------------------------------------------------------------------------
# 4. a target resolution the pixel grid cannot hold
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "pitch, res, names",
    [
        ("z=2,x=20", "lateral=18", ["lateral resolution of 18 µm", "x pitch of 20 µm", "lateral=40"]),
        ("z=10,x=2", "axial=14", ["axial resolution of 14 µm", "z pitch of 10 µm", "axial=20"]),
        ("z=2,x=20", "lateral=0.05", ["lateral resolution of 0.05 µm", "lateral=40"]),
    ],
)
def test_resolution_finer_than_the_pitch_allows_is_refused(outdir, capsys, pitch, res, names):
    path = _sidecar(outdir / "coarse.npy")
    np.save(path, _field())
    argv = _maps_argv(outdir, path, "--pitch-um", pitch, "--resolution", res)
    if res == "lateral=0.05":
        argv += ["--lateral-resolution-um", "0.04"]
    refused(capsys, outdir, argv, "--resolution", "smallest", *names)
    from torchdoct.measured.maps import compute_maps

    with pytest.raises(ValueError, match="smallest"):
        compute_maps(
            read_sequence(
                path, pitch_um=pitch, system={"lateral_resolution_um": 0.04} if res == "lateral=0.05" else None
            ),
            [res],
        )


def test_resolution_of_two_pixels_is_accepted(outdir):
    path = _sidecar(outdir / "coarse.npy")
    np.save(path, _field())
    assert main(_maps_argv(outdir, path, "--pitch-um", "z=2,x=9", "--resolution", "lateral=18")) == 0


def test_maps_file_over_the_limit_is_refused_in_doct_classify(tmp_path, capsys):
    from classifier.cli import classify_main

    path = tmp_path / "a.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("maps.npy", _npy_bytes_declaring((3, 1 << 16, 1 << 16), np.float32))
        zf.writestr("meta_json.npy", _npy_bytes_declaring((), "<U2") + "{}".encode("utf-32-le"))
    before = _tree(tmp_path)
    assert classify_main([str(path), "--out", str(tmp_path / "cls")]) == 2
    err = capsys.readouterr().err
    assert "a.npz" in err and "48 GiB" in err and "--max-input-gb" in err and "Traceback" not in err
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".tif"])
def test_mask_over_the_limit_is_refused(tmp_path, capsys, monkeypatch, suffix):
    from torchdoct.measured.io import Maps, write_maps

    maps = Maps(
        maps=np.ones((1, 6, 5), np.float32),
        channels=("liv@original",),
        meta={
            "channels": [{"name": "liv@original", "metric": "liv", "unit": "dB^2", "resolution": "original"}],
            "axes": "CZX",
        },
    )
    write_maps(tmp_path / "a.npz", maps)
    mask = np.ones((64, 64), bool)
    path = tmp_path / f"mask{suffix}"
    if suffix == ".npy":
        np.save(path, mask)
    elif suffix == ".npz":
        np.savez_compressed(path, mask=mask)
    else:
        tifffile.imwrite(path, mask.astype(np.uint8))
    monkeypatch.setenv(guards.MAX_INPUT_ENV, str(1000 / 2**30))  # 1000 bytes
    line = refused(
        capsys,
        tmp_path,
        ["compare", f"A={tmp_path / 'a.npz'}", "--mask", str(path)],
        f"mask mask{suffix}",
        "4 KiB",
        "--max-input-gb",
    )
    assert "mask mask mask" not in line


@pytest.mark.parametrize("suffix", [".h5", ".tif"])
def test_unreadable_hdf5_or_tiff_is_a_system_refusal(outdir, capsys, monkeypatch, suffix):
    """Readers that wrap OS errors as 'not readable' (exit 2) are never reached: the open is tried first."""
    import builtins

    path = outdir / f"locked{suffix}"
    path.write_bytes(b"x")
    real_open = builtins.open

    def guarded(file, *a, **k):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr(builtins, "open", guarded)
    refused(
        capsys,
        outdir,
        _maps_argv(outdir, path, "--pitch-um", "z=2,x=2", "--frame-interval-s", "0.2"),
        f"locked{suffix}",
        "Permission denied",
        code=1,
    )


def test_unreadable_maps_tiff_is_a_system_refusal(tmp_path, capsys, monkeypatch):
    import builtins

    path = tmp_path / "locked.tif"
    tifffile.imwrite(path, np.ones((2, 6, 5), np.float32))
    real_open = builtins.open

    def guarded(file, *a, **k):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr(builtins, "open", guarded)
    refused(capsys, tmp_path, ["compare", f"A={path}"], "locked.tif", "Permission denied", code=1)


LABEL_PHANTOM = """name = "lab"
[grid]
kind = "bscan"
n_x = 32
n_z = 32
pitch_x_um = 2.0
pitch_z_um = 2.0
[[system]]
name = "s"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[protocol]
n_frames = 8
frame_interval_s = 0.2048
[[region]]
name = "r"
shape = "label-image"
file = "labels.npy"
value = 1
density_per_um3 = 0.05
"""


@pytest.mark.parametrize(
    "shape,dtype,names",
    [
        ((1 << 18, 1 << 18), np.int64, ("(262144, 262144)", "does not match")),
        ((32, 32), np.float64, ("float64", "not integer")),
    ],
)
def test_a_label_image_is_judged_by_its_header_before_a_byte_of_it_is_read(tmp_path, monkeypatch, shape, dtype, names):
    import torchdoct as td
    from torchdoct.image import phantom as phantom_module
    from torchdoct.sim.config import SceneError

    def read(*args, **kwargs):
        raise AssertionError("the label image was read before its header was checked")

    monkeypatch.setattr(phantom_module.np, "load", read)
    (tmp_path / "labels.npy").write_bytes(_npy_bytes_declaring(shape, dtype))  # a header only: 128 bytes
    (tmp_path / "ph.toml").write_text(LABEL_PHANTOM)
    with pytest.raises(SceneError, match="region\\[0\\]\\.file") as info:
        td.load_phantom(tmp_path / "ph.toml")
    assert all(n in str(info.value) for n in names), str(info.value)

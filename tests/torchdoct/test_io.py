"""Sequence and maps files (torchdoct.measured.io): formats, metadata validation, overrides, safety."""

from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest
import tifffile
import torch

from torchdoct.measured.io import (
    BlockRaster,
    Maps,
    read_maps,
    read_sequence,
    sidecar_path,
    validate_meta,
    write_maps,
    write_sequence,
)


def _meta(t=4, volume=False, **extra):
    m = {
        "axes": "TYZX" if volume else "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0, **({"y": 7.8} if volume else {})},
        "frame_times_s": [0.2048 * i for i in range(t)],
        "system": {
            "name": "840nm",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
            "refractive_index": 1.0,
        },
    }
    m.update(extra)
    return m


def _field(shape, dtype=np.complex64, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(dtype)


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".h5"])
@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
@pytest.mark.parametrize("volume", [False, True])
def test_round_trip(tmp_path, suffix, dtype, volume):
    shape = (4, 3, 5, 6) if volume else (4, 5, 6)
    data = _field(shape, dtype)
    labels = None if suffix == ".npy" else np.arange(6).reshape(2, 3)
    params = None if suffix == ".npy" else np.array(["diffusion", "flow"])
    meta = _meta(volume=volume, note="extra keys are kept")
    path = write_sequence(tmp_path / f"seq{suffix}", data, meta, labels=labels, label_params=params)
    seq = read_sequence(path)
    assert seq.data.dtype == dtype and seq.data.shape == shape
    np.testing.assert_array_equal(seq.data, data)
    assert seq.meta["note"] == "extra keys are kept"
    assert seq.axes == meta["axes"] and seq.pitch_um == meta["pitch_um"]
    assert seq.frame_times_s == meta["frame_times_s"]
    assert seq.system["wavelength_um"] == 0.84 and seq.is_complex and seq.source == f"seq{suffix}"
    if labels is not None:
        np.testing.assert_array_equal(seq.labels, labels)
        assert list(seq.label_params) == ["diffusion", "flow"]
    assert sorted(os.listdir(tmp_path)) == sorted({f"seq{suffix}"} | ({"seq.json"} if suffix != ".h5" else set()))


def test_torch_input_and_h5_attribute(tmp_path):
    data = torch.randn(3, 4, 5, dtype=torch.complex64, generator=torch.Generator().manual_seed(1))
    path = write_sequence(tmp_path / "t.h5", data, _meta(3))
    with h5py.File(path) as fh:
        assert json.loads(fh.attrs["torchdoct"])["axes"] == "TZX"
    np.testing.assert_array_equal(read_sequence(path).data, data.numpy())


def test_refuses_to_overwrite_either_file(tmp_path):
    data = _field((4, 5, 6))
    p = write_sequence(tmp_path / "a.npz", data, _meta())
    with pytest.raises(ValueError, match="exists; pass --force"):
        write_sequence(p, data, _meta())
    p.unlink()  # the sidecar alone still blocks
    with pytest.raises(ValueError, match="sidecar.*exists"):
        write_sequence(p, data, _meta())
    assert not p.exists()
    write_sequence(p, data * 2, _meta(), force=True)
    np.testing.assert_array_equal(read_sequence(p).data, data * 2)


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda m: m.update(axes="TYZX"), "4 letters but the data have 3"),
        (lambda m: m.update(axes="XZT"), "not canonical"),
        (lambda m: m.update(axes="TZQ"), "permutation of TZX"),
        (lambda m: m["pitch_um"].pop("x"), "missing \\['x'\\]"),
        (lambda m: m["pitch_um"].update(y=3.0), "keys \\['y'\\]"),
        (lambda m: m["pitch_um"].update(z=-1.0), "pitch_um\\['z'\\]"),
        (lambda m: m.update(frame_times_s=[0.0, 0.1]), "2 entries but the data have T = 4"),
        (lambda m: m.update(frame_times_s=[0.0, 0.2, 0.1, 0.3]), "strictly increasing"),
        (lambda m: m["system"].update(wavelength_um=840.0), "wavelengths are in micrometres"),
        (lambda m: m["system"].update(axial_resolution_um=float("nan")), "axial_resolution_um"),
        (lambda m: m.pop("frame_times_s"), "missing 'frame_times_s'"),
    ],
)
def test_meta_validation(tmp_path, change, match):
    meta = _meta()
    change(meta)
    with pytest.raises(ValueError, match=match):
        write_sequence(tmp_path / "bad.npy", _field((4, 5, 6)), meta)
    assert not list(tmp_path.iterdir())


def test_write_errors(tmp_path):
    with pytest.raises(ValueError, match="labels need a .npz or .h5"):
        write_sequence(tmp_path / "a.npy", _field((4, 5, 6)), _meta(), labels=np.zeros(3))
    with pytest.raises(ValueError, match="must end in"):
        write_sequence(tmp_path / "a.mat", _field((4, 5, 6)), _meta())
    with pytest.raises(TypeError, match="complex"):
        write_sequence(tmp_path / "a.npy", np.zeros((4, 5, 6), np.int32), _meta())
    with pytest.raises(ValueError, match="\\[T, Z, X\\]"):
        write_sequence(tmp_path / "a.npy", _field((5, 6)), _meta())


def test_missing_metadata_names_the_option(tmp_path):
    data = _field((4, 5, 6))
    np.save(tmp_path / "raw.npy", data)
    with pytest.raises(ValueError, match="missing 'axes'.*--axes"):
        read_sequence(tmp_path / "raw.npy")
    with pytest.raises(ValueError, match="missing 'frame_times_s'.*--frame-interval-s"):
        read_sequence(tmp_path / "raw.npy", axes="TZX", pitch_um="z=1,x=2")
    no_pitch = read_sequence(tmp_path / "raw.npy", axes="TZX", frame_interval_s=0.5)  # only a reduction needs it
    with pytest.raises(ValueError, match="raw.npy: missing 'pitch_um'.*--pitch-um"):
        no_pitch.pitch_um
    with pytest.raises(ValueError, match="missing 'pitch_um'.*--pitch-um"):
        validate_meta(_meta(pitch_um=None), (4, 5, 6), require_pitch=True)
    seq = read_sequence(tmp_path / "raw.npy", axes="TZX", pitch_um="z=1,x=2", frame_interval_s=0.5)
    assert seq.frame_times_s == [0.0, 0.5, 1.0, 1.5]
    with pytest.raises(ValueError, match="--wavelength-um"):
        seq.system
    seq = read_sequence(
        tmp_path / "raw.npy",
        axes="TZX",
        pitch_um={"z": 1, "x": 2},
        frame_times_s=[0, 1, 2, 4],
        system={"wavelength_um": 1.31, "lateral_resolution_um": 18, "axial_resolution_um": 14},
    )
    assert seq.system["lateral_resolution_um"] == 18.0 and seq.system["refractive_index"] == 1.0
    with pytest.raises(FileNotFoundError):
        read_sequence(tmp_path / "nothing.npy")


def test_keyword_overrides_merge_with_the_sidecar(tmp_path):
    p = write_sequence(tmp_path / "a.npy", _field((4, 5, 6)), _meta())
    seq = read_sequence(p, pitch_um="x=3.0", frame_interval_s=0.1, system={"axial_resolution_um": 5.0})
    assert seq.pitch_um == {"z": 1.5, "x": 3.0}
    assert seq.frame_times_s == pytest.approx([0.0, 0.1, 0.2, 0.3])
    assert seq.system["axial_resolution_um"] == 5.0 and seq.system["lateral_resolution_um"] == 4.9


def test_axes_permutation_is_transposed_to_canonical(tmp_path):
    data = _field((4, 3, 5, 6))  # T, Y, Z, X
    stored = np.ascontiguousarray(data.transpose(3, 2, 1, 0))  # X, Z, Y, T
    np.save(tmp_path / "perm.npy", stored)
    seq = read_sequence(tmp_path / "perm.npy", axes="xzyt", pitch_um="z=1,x=2,y=3", frame_interval_s=0.2)
    assert seq.axes == "TYZX"
    np.testing.assert_array_equal(seq.data, data)


def test_object_arrays_are_refused(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([1, "a"], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="unpickling"):
        read_sequence(tmp_path / "obj.npy", axes="TZX")
    np.savez(tmp_path / "obj.npz", data=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="unpickling"):
        read_sequence(tmp_path / "obj.npz")
    np.savez(tmp_path / "nodata.npz", other=np.zeros(3))
    with pytest.raises(ValueError, match="no array 'data'"):
        read_sequence(tmp_path / "nodata.npz")


def test_binary_metadata_is_named_never_a_codec_error(tmp_path, capsys):
    """A sidecar or HDF5 ``torchdoct`` attribute that is not UTF-8 text: a ValueError naming the file
    (was a bare ``'utf-8' codec can't decode`` message), and ``maps`` exits 2 writing nothing."""
    from torchdoct.cli import main

    write_sequence(tmp_path / "s.npy", _field((4, 5, 6)), _meta())
    (tmp_path / "s.json").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(ValueError, match=r"s\.json: the metadata sidecar of s\.npy is not UTF-8 text \(byte 0\)"):
        read_sequence(tmp_path / "s.npy")
    with h5py.File(tmp_path / "h.h5", "w") as fh:
        fh.create_dataset("data", data=_field((4, 5, 6)))
        fh.attrs["torchdoct"] = np.bytes_(b'{"axes": "\xff\xfe"}')
    with pytest.raises(ValueError, match=r"h\.h5: attribute 'torchdoct' is not UTF-8 text \(byte 10\)"):
        read_sequence(tmp_path / "h.h5")
    for name in ("s.npy", "h.h5"):
        assert main(["maps", str(tmp_path / name), "--out", str(tmp_path / "m.npz"), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and "codec" not in err and not (tmp_path / "m.npz").exists()


def test_matlab_v73_compound_complex(tmp_path):
    """MATLAB v7.3 stores a [Z, X, T] complex array as an HDF5 compound {real, imag} of shape (T, X, Z)."""
    data = _field((4, 5, 6))  # T, Z, X
    stored = data.transpose(0, 2, 1)  # (T, X, Z) as HDF5 sees MATLAB's [Z, X, T]
    comp = np.empty(stored.shape, dtype=[("real", "<f4"), ("imag", "<f4")])
    comp["real"], comp["imag"] = stored.real, stored.imag
    path = tmp_path / "scan.h5"
    with h5py.File(path, "w", userblock_size=512) as fh:
        fh.create_dataset("oct", data=comp)
    seq = read_sequence(path, axes="TXZ", pitch_um="z=1.5,x=2", frame_interval_s=0.2048)
    assert seq.data.dtype == np.complex64
    np.testing.assert_array_equal(seq.data, data)
    with h5py.File(path, "a") as fh:
        fh.create_dataset("other", data=np.zeros(3))
    with pytest.raises(ValueError, match="name one with --dataset"):
        read_sequence(path, axes="TXZ", pitch_um="z=1.5,x=2", frame_interval_s=0.2048)
    seq = read_sequence(path, axes="TXZ", pitch_um="z=1.5,x=2", frame_interval_s=0.2048, dataset="oct")
    np.testing.assert_array_equal(seq.data, data)
    with pytest.raises(ValueError, match="no dataset 'nope'"):
        read_sequence(path, dataset="nope")


def test_intensity_tiff_stack(tmp_path):
    inten = np.random.default_rng(2).random((5, 6, 7)).astype(np.float32)
    tifffile.imwrite(tmp_path / "cog.tif", inten)
    seq = read_sequence(tmp_path / "cog.tif", pitch_um="z=2,x=3", frame_interval_s=0.2048)
    assert seq.axes == "TZX" and not seq.is_complex
    np.testing.assert_array_equal(seq.data, inten)


def test_tiff_written_page_by_page_and_truncated_tiffs(tmp_path, capsys):
    """A stack written one page at a time (each page its own series) reads as all its pages (was only
    the first: 'data have shape [6, 7]'); a truncated one (tifffile only logs its broken page table and
    reads the first page) and a truncated maps TIFF are refused as truncated, naming the file, with no
    stray log line."""
    inten = np.random.default_rng(4).random((5, 6, 7)).astype(np.float32)
    with tifffile.TiffWriter(tmp_path / "pages.tif") as tw:
        for frame in inten:
            tw.write(frame, contiguous=False)
    np.testing.assert_array_equal(read_sequence(tmp_path / "pages.tif", frame_interval_s=0.2).data, inten)
    raw = (tmp_path / "pages.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"cut\.tif: not a readable TIFF stack"):
        read_sequence(tmp_path / "cut.tif", frame_interval_s=0.2)
    chans = [
        {
            "name": f"liv@r{i}",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": f"r{i}",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
        }
        for i in range(3)
    ]
    m = Maps(
        maps=np.ones((3, 64, 64), np.float32),
        channels=[c["name"] for c in chans],
        meta={"channels": chans, "axes": "CZX"},
    )
    raw = write_maps(tmp_path / "m.tif", m).read_bytes()
    (tmp_path / "mcut.tif").write_bytes(raw[: int(len(raw) * 0.8)])
    with pytest.raises(ValueError, match=r"mcut\.tif: not a readable maps TIFF \(truncated or corrupt"):
        read_maps(tmp_path / "mcut.tif")
    assert capsys.readouterr().err == ""


def test_block_raster_unpack_and_boundaries(tmp_path):
    raster = BlockRaster.parse("3:4:5")
    assert (raster.n_bscans, raster.n_y) == (60, 15)
    code = np.zeros((60, 2, 3), np.complex64)
    for b in range(3):
        for r in range(4):
            for k in range(5):
                code[(b * 4 + r) * 5 + k] = 100 * b + 10 * r + k  # acquisition order: block, repeat, B-scan
    out = raster.unpack(code)
    assert out.shape == (4, 15, 2, 3)
    for r in range(4):
        for y in range(15):
            assert out[r, y, 0, 0] == 100 * (y // 5) + 10 * r + y % 5
    assert list(np.flatnonzero(~raster.keep_y())) == [4, 5, 9, 10]
    assert BlockRaster(n_blocks=3, n_repeats=4, bscans_per_block=5, drop_boundary=0).keep_y().all()
    np.save(tmp_path / "flat.npy", code)
    seq = read_sequence(
        tmp_path / "flat.npy", axes="TZX", pitch_um="z=1,x=2,y=8", frame_interval_s=0.2048, block_raster=raster
    )
    assert seq.axes == "TYZX" and seq.data.shape == (4, 15, 2, 3)
    assert seq.block_raster == raster and seq.meta["block_raster"]["n_blocks"] == 3
    with pytest.raises(ValueError, match="acquisition order"):
        BlockRaster.parse("2:4:5").unpack(code)
    with pytest.raises(ValueError, match="drop_boundary"):
        BlockRaster(n_blocks=2, n_repeats=4, bscans_per_block=2, drop_boundary=1)
    with pytest.raises(ValueError, match="BLOCKS:REPEATS"):
        BlockRaster.parse("8:32")


def _maps():
    arr = np.random.default_rng(3).random((2, 4, 5)).astype(np.float32)
    chans = [
        {
            "name": "liv@original",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": "original",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
        },
        {
            "name": "liv@axial=14",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": "axial=14",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 14.0,
        },
    ]
    meta = {
        "channels": chans,
        "axes": "CZX",
        "pitch_um": {"z": 1.5, "x": 2.0},
        "frame_times_s": [0.0, 0.2],
        "system": _meta()["system"],
        "ocds_delay_range_s": [0.2048, 1.2288],
        "source": "seq.npy",
    }
    return Maps(maps=arr, channels=[c["name"] for c in chans], meta=meta)


@pytest.mark.parametrize("suffix", [".npz", ".tif"])
def test_maps_round_trip(tmp_path, suffix):
    m = _maps()
    p = write_maps(tmp_path / f"m{suffix}", m)
    r = read_maps(p)
    np.testing.assert_array_equal(r.maps, m.maps)
    assert r.channels == m.channels and r.meta == m.meta
    assert r.find("liv", axial_resolution_um=14.0 * (1 + 5e-7)) == ["liv@axial=14"]
    assert r.find("liv", wavelength_um=0.84) == ["liv@original", "liv@axial=14"]
    assert r.find("ocds") == []
    np.testing.assert_array_equal(r["liv@axial=14"], m.maps[1])
    with pytest.raises(ValueError, match="exists"):
        write_maps(p, m)
    if suffix == ".tif":
        with tifffile.TiffFile(p) as tf:
            assert json.loads(tf.imagej_metadata["Info"])["channels"][1]["axial_resolution_um"] == 14.0


def test_validate_meta_is_exposed_and_returns_a_clean_copy():
    meta = _meta()
    clean = validate_meta(meta, (4, 5, 6))
    assert clean == {**meta, "frame_times_s": [float(v) for v in meta["frame_times_s"]]}
    assert clean is not meta and sidecar_path("a/b.npz").name == "b.json"


@pytest.mark.parametrize("shape,axes", [((1, 4, 5), "CZX"), ((1, 3, 4, 5), "CYZX"), ((2, 3, 4, 5), "CYZX")])
def test_maps_tiff_keeps_single_channels_and_volumes(tmp_path, shape, axes):
    chans = [
        {
            "name": f"liv@r{i}",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": f"r{i}",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
        }
        for i in range(shape[0])
    ]
    m = Maps(
        maps=np.random.default_rng(5).random(shape).astype(np.float32),
        channels=[c["name"] for c in chans],
        meta={"channels": chans, "axes": axes},
    )
    r = read_maps(write_maps(tmp_path / "m.tif", m))
    assert r.maps.shape == shape
    np.testing.assert_array_equal(r.maps, m.maps)


def _bad_meta_variants():
    good = _maps().meta
    chans = good["channels"]
    return {
        "number": "5",
        "list": "[1, 2]",
        "channel-names-only": json.dumps({**good, "channels": [c["name"] for c in chans]}),
        "channel-without-metric": json.dumps(
            {**good, "channels": [{k: v for k, v in c.items() if k != "metric"} for c in chans]}
        ),
        "wavelength-text": json.dumps({**good, "channels": [{**c, "wavelength_um": "abc"} for c in chans]}),
        "name-mismatch": json.dumps({**good, "channels": [{**c, "name": "x@y"} for c in chans]}),
        "axes-rank": json.dumps({**good, "axes": "CYZX"}),
        "pitch-text": json.dumps({**good, "pitch_um": "z=1"}),
    }


@pytest.mark.parametrize("kind", sorted(_bad_meta_variants()))
def test_maps_npz_with_invalid_meta_json_names_file_and_key(tmp_path, kind, capsys):
    from torchdoct.cli import main

    m = _maps()
    good = write_maps(tmp_path / "good.npz", m)
    arrays = {"maps": m.maps, "channels": np.asarray(m.channels), "meta_json": np.asarray(_bad_meta_variants()[kind])}
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=r"bad\.npz.*meta_json") as info:
        read_maps(tmp_path / "bad.npz")
    assert "object arrays" not in str(info.value)  # valid JSON of the wrong shape is not a pickle
    assert main(["compare", str(tmp_path / "bad.npz"), str(good)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "bad.npz" in err and "Traceback" not in err


def test_maps_npz_with_a_non_text_meta_json(tmp_path):
    m = _maps()
    np.savez(tmp_path / "num.npz", maps=m.maps, channels=np.asarray(m.channels), meta_json=np.arange(3.0))
    with pytest.raises(ValueError, match=r"num\.npz.*meta_json.*(text|string)"):
        read_maps(tmp_path / "num.npz")


def test_object_array_masks_are_refused_naming_the_file(tmp_path, capsys):
    from torchdoct.cli import main

    m = _maps()
    maps_path = write_maps(tmp_path / "m.npz", m)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.savez(tmp_path / "obj.npz", mask=np.array([{"a": 1}], dtype=object))
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04broken")
    for name in ("obj.npy", "obj.npz", "cut.npz"):
        assert (
            main(
                [
                    "compare",
                    f"a={maps_path}",
                    f"b={maps_path}",
                    "--mask",
                    str(tmp_path / name),
                    "--mask",
                    str(tmp_path / name),
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert err.startswith("error: ") and name in err and "allow_pickle" not in err, err


def test_a_file_that_is_not_npy_is_named_as_such(tmp_path):
    """Random bytes or a pickle under the .npy suffix: 'not a NumPy .npy file', never 'object array'."""
    import pickle

    from torchdoct.measured.io import read_sequence

    for name, payload in (("garbage.npy", b"hello, this is not numpy" * 10), ("pickled.npy", pickle.dumps([1, 2]))):
        p = tmp_path / name
        p.write_bytes(payload)
        with pytest.raises(ValueError, match=rf"{name}: not a NumPy \.npy file"):
            read_sequence(p)

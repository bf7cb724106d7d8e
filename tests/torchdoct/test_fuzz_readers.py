"""Property-based tests of every reader: malformed sequence and maps files fail clearly, never unpickle.

A broken file (truncated, wrong dtype or rank, mismatched or missing metadata, zero-size axes) must
give ``ValueError``/``TypeError``/``FileNotFoundError`` whose message names the file or the
metadata key, and the CLI must exit with code 2 and one ``error:`` line. NaN pixels are data, not
errors: their maps are NaN and every other pixel is finite (the documented policy).
"""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from _fuzz import examples

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from torchdoct.cli import main  # noqa: E402
from torchdoct.measured.io import read_maps, read_sequence  # noqa: E402

T, Z, X = 8, 6, 5
META = {
    "axes": "TZX",
    "pitch_um": {"z": 2.0, "x": 2.0},
    "frame_times_s": [0.2048 * i for i in range(T)],
    "system": {
        "name": "s",
        "wavelength_um": 0.84,
        "lateral_resolution_um": 4.9,
        "axial_resolution_um": 3.8,
        "refractive_index": 1.0,
    },
}
ERRORS = (ValueError, TypeError, FileNotFoundError)
SETTINGS = settings(
    max_examples=examples(220),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _field(rng, shape=(T, Z, X), dtype=np.complex64):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(dtype)


def _write(path, data, meta, fmt, sidecar=True):
    if fmt == "npy":
        np.save(path.with_suffix(".npy"), data, allow_pickle=data.dtype.hasobject)
    elif fmt == "npz":
        np.savez(path.with_suffix(".npz"), data=data)
    elif fmt == "h5":
        import h5py

        with h5py.File(path.with_suffix(".h5"), "w") as fh:
            fh.create_dataset("data", data=data.astype("S3") if data.dtype.kind == "U" else data)
            if meta is not None and sidecar:
                fh.attrs["torchdoct"] = meta if isinstance(meta, (str, bytes)) else json.dumps(meta)
        return path.with_suffix(".h5")
    if sidecar and meta is not None:
        path.with_suffix(".json").write_text(meta if isinstance(meta, str) else json.dumps(meta))
    return path.with_suffix("." + fmt)


@st.composite
def broken_sequences(draw):
    fmt = draw(st.sampled_from(["npy", "npz", "h5"]))
    kind = draw(
        st.sampled_from(
            [
                "truncate",
                "dtype",
                "rank",
                "axes",
                "frames",
                "pitch",
                "zero",
                "sidecar",
                "not-json",
                "system",
                "binary-meta",
            ]
        )
    )
    meta = json.loads(json.dumps(META))
    shape = (T, Z, X)
    dtype = np.complex64
    if kind == "dtype":
        dtype = draw(st.sampled_from([np.int32, np.bool_, "U3"]))  # float data are intensity (valid)
    if kind == "rank":
        shape = draw(st.sampled_from([(T,), (T, Z), (2, T, 3, Z, X)]))
    if kind == "zero":
        shape = draw(st.sampled_from([(0, Z, X), (T, 0, X), (T, Z, 0)]))
        if shape[0] == 0:
            meta["frame_times_s"] = []
    if kind == "axes":
        meta["axes"] = draw(st.sampled_from(["TZ", "TZXY", "TTX", "ABC", "", 5, None]))
    if kind == "frames":
        meta["frame_times_s"] = draw(
            st.sampled_from([[0.0, 0.1], [0.1 * i for i in range(T)][::-1], [float("nan")] * T, "0.2", [0.0] * T])
        )
    if kind == "pitch":
        meta["pitch_um"] = draw(
            st.sampled_from(
                [
                    {"z": 2.0},
                    {"z": -1.0, "x": 2.0},
                    {"z": float("nan"), "x": 1.0},
                    {"z": "2", "x": 2.0},
                    [2.0, 2.0],
                    {"z": 0.0, "x": 2.0},
                ]
            )
        )
    if kind == "system":
        meta["system"] = draw(
            st.sampled_from(
                [
                    {"wavelength_um": -0.84},
                    {"wavelength_um": 840.0, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
                    "840nm",
                    {"wavelength_um": 0.84, "lateral_resolution_um": 0.0, "axial_resolution_um": 3.8},
                ]
            )
        )
    cut = draw(st.floats(0.0, 0.95))
    return fmt, kind, shape, dtype, meta, cut


@SETTINGS
@given(broken_sequences())
def test_broken_sequence_files_fail_clearly(tmp_path, case):
    fmt, kind, shape, dtype, meta, cut = case
    rng = np.random.default_rng(0)
    data = _field(rng, shape) if dtype == np.complex64 else np.zeros(shape, dtype=dtype)
    meta_out = meta
    if kind == "not-json":
        meta_out = "{'axes': TZX"
    if kind == "binary-meta":  # an image or data file saved as the metadata: not UTF-8 text
        meta_out = b"\x89PNG\r\n\x1a\n\xff\xfe" + bytes(range(1, 256))
        if fmt != "h5":
            (tmp_path / f"seq-{kind}.json").write_bytes(meta_out)
            meta_out = None
    path = _write(tmp_path / f"seq-{kind}", data, meta_out, fmt, sidecar=kind != "sidecar")
    if kind == "truncate":
        raw = path.read_bytes()
        path.write_bytes(raw[: int(len(raw) * cut)])
    try:
        seq = read_sequence(path)
    except ERRORS as err:
        msg = str(err)
        assert kind != "binary-meta" or (path.name in msg and ("not UTF-8 text" in msg or "invalid JSON" in msg)), msg
        assert (
            path.name in msg
            or path.stem in msg
            or any(k in msg for k in ("axes", "frame", "pitch", "system", "wavelength", "resolution", "json", "JSON"))
        ), msg
        code = main(["maps", str(path), "--out", str(tmp_path / "m.npz"), "--no-progress"])
        assert code == 2
        return
    # accepted: only a valid, consistent sequence may pass
    assert kind in ("system",) or False, f"{kind} was accepted: {seq.data.shape} {seq.meta}"


@settings(
    max_examples=examples(30),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(st.sampled_from(["npy", "npz", "h5"]), st.integers(1, 6))
def test_nan_pixels_give_nan_maps_only_there(tmp_path, fmt, n_bad):
    from torchdoct.measured.io import write_sequence
    from torchdoct.measured.maps import compute_maps

    rng = np.random.default_rng(n_bad)
    data = _field(rng)
    bad = rng.choice(Z * X, size=n_bad, replace=False)
    zz, xx = np.unravel_index(bad, (Z, X))
    data[rng.integers(0, T), zz, xx] = np.nan
    path = write_sequence(tmp_path / f"nan.{fmt}", data, META, force=True)
    maps = compute_maps(read_sequence(path), ["original"], metrics=("liv", "ocds"), ocds_delay_range_s=(0.2048, 0.6144))
    for c, name in enumerate(maps.channels):
        m = maps.maps[c]
        if name.startswith("valid_weight@"):  # the share of each pixel's window on finite samples
            assert (m[zz, xx] == 0).all() and (m.sum() == Z * X - n_bad)
            continue
        assert np.isnan(m[zz, xx]).all()
        mask = np.ones((Z, X), bool)
        mask[zz, xx] = False
        assert np.isfinite(m[mask]).all()


def test_pickle_bearing_files_are_refused_everywhere(tmp_path, capsys):
    """Object arrays, pickled payloads and pickle-bearing metadata never reach ``pickle.loads``."""
    import h5py

    payload = np.array([{"evil": 1}], dtype=object)
    np.save(tmp_path / "obj.npy", payload, allow_pickle=True)
    (tmp_path / "obj.json").write_text(json.dumps(META))
    np.savez(tmp_path / "obj.npz", data=payload)
    np.savez(tmp_path / "objmaps.npz", maps=payload, channels=np.array(["liv@original"]), meta_json=np.array("{}"))
    with h5py.File(tmp_path / "pickled-attr.h5", "w") as fh:
        fh.create_dataset("data", data=_field(np.random.default_rng(1)))
        fh.attrs["torchdoct"] = np.void(pickle.dumps({"axes": "TZX"}))
    (tmp_path / "model.pkl").write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    for name in ("obj.npy", "obj.npz", "pickled-attr.h5"):
        with pytest.raises(ERRORS):
            read_sequence(tmp_path / name)
        assert main(["maps", str(tmp_path / name), "--out", str(tmp_path / "m.npz"), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ")
    with pytest.raises(ERRORS, match="objmaps.npz"):
        read_maps(tmp_path / "objmaps.npz")
    from torchdoct.measured.io import Maps, write_maps

    chans = [
        {
            "name": "liv@original",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": "original",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
        }
    ]
    good = write_maps(
        tmp_path / "good.npz",
        Maps(maps=np.zeros((1, Z, X), np.float32), channels=["liv@original"], meta={"channels": chans, "axes": "CZX"}),
    )
    for mask in ("obj.npy", "obj.npz"):  # object-array masks: refused naming the file, never unpickled
        assert (
            main(["compare", f"a={good}", f"b={good}", "--mask", str(tmp_path / mask), "--mask", str(tmp_path / mask)])
            == 2
        )
        err = capsys.readouterr().err
        assert err.startswith("error: mask ") and mask in err and "allow_pickle" not in err
    assert main(["compare", str(tmp_path / "objmaps.npz"), str(tmp_path / "objmaps.npz")]) == 2
    from classifier.cli import classify_main

    for model in ("model.pkl", "model-as.onnx"):
        (tmp_path / "model-as.onnx").write_bytes((tmp_path / "model.pkl").read_bytes())
        assert (
            classify_main(
                [str(tmp_path / "objmaps.npz"), "--model", str(tmp_path / model), "--out", str(tmp_path / "clf")]
            )
            == 2
        )
        assert capsys.readouterr().err.startswith("error: ")
        assert not (tmp_path / "clf").exists()


@settings(
    max_examples=examples(40),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    st.sampled_from(["npy", "npz", "h5"]),
    st.sampled_from(["one-frame", "all-nan", "all-zero", "big-endian"]),
    st.sampled_from([np.complex64, np.complex128]),
)
def test_readable_but_unusable_sequences(tmp_path, capsys, fmt, kind, dtype):
    """Files the reader accepts: a one-frame or all-NaN/all-zero stack is refused by ``maps`` naming the
    file; a big-endian stack gives the same maps as the native one."""
    import tempfile
    from pathlib import Path

    from torchdoct.cli import main as cli

    tmp_path = Path(tempfile.mkdtemp(dir=tmp_path))  # one directory per example
    rng = np.random.default_rng(3)
    meta = json.loads(json.dumps(META))
    data = _field(rng, (T, 8, X), dtype=dtype)  # 8 × 2 µm deep: the field of view holds the axial=14 target
    if kind == "one-frame":
        data, meta["frame_times_s"] = data[:1], [0.0]
    elif kind == "all-nan":
        data[:] = np.nan
    elif kind == "all-zero":
        data[:] = 0
    native = _write(tmp_path / "native", data, meta, fmt)
    if kind == "big-endian":
        data = data.astype(data.dtype.newbyteorder(">"))
    path = _write(tmp_path / f"seq-{kind}", data, meta, fmt)
    if kind == "all-nan":  # refused by the reader already, naming the file
        with pytest.raises(ValueError, match=rf"{path.name}: holds no finite sample"):
            read_sequence(path)
    else:
        assert read_sequence(path).data.dtype.isnative
    args = [
        "--ocds-delay-range-s",
        "0.2048",
        "0.6144",
        "--aliv",
        "--no-progress",
        "--resolution",
        "original",
        "--resolution",
        "axial=14",
    ]
    code = cli(["maps", str(path), "--out", str(tmp_path / "m.npz"), *args])
    if kind == "big-endian":
        assert code == 0 and cli(["maps", str(native), "--out", str(tmp_path / "n.npz"), *args]) == 0
        np.testing.assert_array_equal(read_maps(tmp_path / "m.npz").maps, read_maps(tmp_path / "n.npz").maps)
    else:
        assert code == 2 and not (tmp_path / "m.npz").exists()
        assert path.name in capsys.readouterr().err


@st.composite
def broken_maps(draw):
    kind = draw(
        st.sampled_from(
            [
                "truncate",
                "shape",
                "channels",
                "meta",
                "dtype",
                "missing-key",
                "meta-number",
                "meta-list",
                "meta-channel-names",
                "meta-channel-no-metric",
                "meta-optics-text",
                "meta-axes",
                "meta-not-text",
                "meta-pitch",
            ]
        )
    )
    return kind, draw(st.floats(0.0, 0.95))


@settings(
    max_examples=examples(120),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(broken_maps())
def test_broken_maps_files_fail_clearly(tmp_path, case):
    kind, cut = case
    chans = [
        {
            "name": "liv@original",
            "metric": "liv",
            "unit": "dB^2",
            "resolution": "original",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
        }
    ]
    meta = {
        "channels": chans,
        "axes": "CZX",
        "pitch_um": {"z": 2.0, "x": 2.0},
        "frame_times_s": META["frame_times_s"],
        "system": META["system"],
        "ocds_delay_range_s": [0.2048, 1.2288],
        "source": "x",
    }
    maps = np.zeros((1, Z, X), np.float32)
    arrays = {"maps": maps, "channels": np.array(["liv@original"]), "meta_json": np.array(json.dumps(meta))}
    if kind == "shape":
        arrays["maps"] = np.zeros(draw_shape(cut), np.float32)
    elif kind == "channels":
        arrays["channels"] = np.array(["liv@original", "ocds@original"])
    elif kind == "meta":
        arrays["meta_json"] = np.array("{not json")
    elif kind == "dtype":
        arrays["maps"] = np.zeros((1, Z, X), np.complex64)
    elif kind == "missing-key":
        del arrays["meta_json"]
    elif kind.startswith("meta-"):
        bad = {
            "meta-number": "5",
            "meta-list": "[1]",
            "meta-channel-names": json.dumps({**meta, "channels": ["liv@original"]}),
            "meta-channel-no-metric": json.dumps({**meta, "channels": [{"name": "liv@original"}]}),
            "meta-optics-text": json.dumps({**meta, "channels": [{**chans[0], "wavelength_um": "840nm"}]}),
            "meta-axes": json.dumps({**meta, "axes": "CYZX"}),
            "meta-pitch": json.dumps({**meta, "pitch_um": [2, 2]}),
            "meta-not-text": np.arange(3.0),
        }[kind]
        arrays["meta_json"] = np.asarray(bad)
    path = tmp_path / f"maps-{kind}.npz"
    np.savez(path, **arrays)
    if kind == "truncate":
        raw = path.read_bytes()
        path.write_bytes(raw[: int(len(raw) * cut)])
    with pytest.raises(ERRORS) as info:
        read_maps(path)
    assert path.name in str(info.value) or "channel" in str(info.value) or "meta" in str(info.value)
    if kind.startswith("meta-"):
        assert path.name in str(info.value) and "object arrays" not in str(info.value)
        assert main(["compare", str(path), str(path)]) == 2


def draw_shape(u: float) -> tuple[int, ...]:
    return [(Z, X), (1, 1, 1, 1, Z, X), (0, Z, X), (1, 0, X)][int(u * 4) % 4]

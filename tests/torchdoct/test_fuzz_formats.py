"""One fuzz harness over every sequence reader (:data:`torchdoct.measured.formats.FORMATS` and the folder of
TIFFs): a generated file, valid or damaged (truncated, garbage, sizes declared beyond the data, HDF5 link
graphs, OME-XML sizes, sidecar values, a FIFO in place of the data), is read by ``read_sequence`` in a child process with a time limit
and an address-space limit, and answered as every command answers it (``error:`` line, exit 2). The
property: a correct result (the data as written) or exit 2 with one ``error:`` line naming the file; never
a traceback, a hang or unbounded memory. The short profile runs in the default suite; the full one
(``TORCHDOCT_FUZZ=full``, tests/_fuzz.py) by the command of CONTRIBUTING.md (each case runs in a process under a
wall-time limit, which a heavily loaded machine can exceed: not a gate for CI)."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys

import numpy as np
import pytest
from _formats import write_mat, write_npy, write_ome_tiff, write_ome_zarr, write_raw, write_tiff_folder
from _fuzz import examples

hypothesis = pytest.importorskip("hypothesis")
h5py = pytest.importorskip("h5py")
tifffile = pytest.importorskip("tifffile")
pytest.importorskip("zarr")
pytest.importorskip("scipy")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from torchdoct.measured.formats import FORMATS  # noqa: E402

T, Z, X = 8, 6, 5
#: The child's limits: seconds of wall time, and address space (bytes): far below what a declared size
#: of gigabytes or a hang would need, far above what reading these small files takes.
TIME_LIMIT_S = 60
ADDRESS_SPACE = 4 << 30
FORMAT_NAMES = ("npy", "npz", "h5", "tif", "mat", "raw", "ome.tif", "zarr", "folder")
MUTATIONS = ("none", "truncate", "garbage", "huge", "sidecar", "links", "special")
READER = """
import sys
import numpy as np
from torchdoct.measured.io import read_sequence
try:
    seq = read_sequence(sys.argv[1])
except (ValueError, TypeError, FileNotFoundError) as err:
    print(f"error: {err}", file=sys.stderr)
    sys.exit(2)
np.save(sys.argv[2], np.asarray(seq.data))
"""


def test_the_harness_covers_every_reader():
    suffixes = {s for m in FORMATS for s in m.SUFFIXES}
    covered = {"." + f for f in FORMAT_NAMES if f != "folder"} | {".npy", ".tiff", ".ome.tiff", ".bin"}
    assert suffixes <= covered, suffixes - covered


def _limits():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def _read_in_child(path, out):
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, "-c", READER, str(path), str(out)],
        capture_output=True,
        text=True,
        timeout=TIME_LIMIT_S,
        preexec_fn=_limits,
        env=env,
    )


def _field(seed):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((T, Z, X)) + 1j * rng.standard_normal((T, Z, X))).astype(np.complex64)


def _write(fmt, d, a):
    """The file of ``a`` in format ``fmt`` under folder ``d`` (metadata in the format's own fields)."""
    if fmt == "npy":
        return write_npy(d / "seq.npy", a)
    if fmt == "npz":
        np.savez(d / "seq.npz", data=a)
        write_npy(d / "side.npy", a).unlink()  # the sidecar alone, renamed to the npz's
        (d / "side.json").rename(d / "seq.json")
        return d / "seq.npz"
    if fmt == "h5":
        meta = json.loads(write_npy(d / "side.npy", a).with_suffix(".json").read_text())
        with h5py.File(d / "seq.h5", "w") as fh:
            fh["data"] = a
            fh.attrs["torchdoct"] = json.dumps(meta)
        return d / "seq.h5"
    if fmt == "tif":
        tifffile.imwrite(d / "seq.tif", np.abs(a) ** 2)
        write_npy(d / "side.npy", a).unlink()
        (d / "side.json").rename(d / "seq.json")
        return d / "seq.tif"
    if fmt == "mat":
        return write_mat(d / "seq.mat", a)
    if fmt == "raw":
        return write_raw(d / "seq.raw", a)
    if fmt == "ome.tif":
        return write_ome_tiff(d / "seq.ome.tif", np.abs(a) ** 2)
    if fmt == "zarr":
        return write_ome_zarr(d / "seq.zarr", a)
    return write_tiff_folder(d / "frames", np.abs(a) ** 2)


def _data_file(path):
    """The file whose bytes hold the samples (a chunk of a Zarr store, a frame of a folder)."""
    if path.is_dir():
        files = sorted(
            p
            for p in path.rglob("*")
            if p.is_file() and not p.name.startswith(".") and p.suffix not in (".json", ".zattrs", ".zgroup", ".zarray")
        )
        return files[0]
    return path


def _sidecar(path):
    return path.with_suffix(".json")


def _declare_huge(fmt, path, n):
    """Make ``path`` declare ``n`` frames (or ``n`` times its size) without holding them."""
    if fmt in ("npy", "raw"):
        side = _sidecar(path)
        meta = json.loads(side.read_text())
        if fmt == "raw":
            meta["shape"] = [n, Z, X]
        meta["frame_times_s"] = [0.05 * k for k in range(min(n, 4))]
        side.write_text(json.dumps(meta))
        if fmt == "npy":
            raw = bytearray(path.read_bytes())
            head = (
                raw[:128]
                .decode("latin1")
                .replace(f"({T}, {Z}, {X})", f"({n}, {Z}, {X})".ljust(len(f"({T}, {Z}, {X})")))
            )
            if len(head.encode("latin1")) == 128:
                raw[:128] = head.encode("latin1")
            path.write_bytes(bytes(raw))
    elif fmt == "ome.tif":
        with tifffile.TiffFile(path) as tf:
            xml = tf.ome_metadata
            pages = np.stack([p.asarray() for p in tf.pages])
        tifffile.imwrite(path, pages, description=xml.replace(f'SizeT="{T}"', f'SizeT="{n}"'), metadata=None)
    elif fmt == "h5":
        with h5py.File(path, "a") as fh:
            del fh["data"]
            fh.create_dataset(
                "data", shape=(n, Z * 1000, X * 1000), dtype=np.complex64, chunks=(1, 64, 64), compression="gzip"
            )
    elif fmt == "zarr":
        zarray = path / "0" / ".zarray"
        meta = json.loads(zarray.read_text())
        meta["shape"] = [n, Z * 1000, X * 1000]
        zarray.write_text(json.dumps(meta))
    elif fmt == "npz":
        import io
        import zipfile

        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, {"descr": "<c8", "fortran_order": False, "shape": (n, 4096, 4096)})
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("data.npy", buf.getvalue() + bytes(64))
    else:
        return False
    return True


def _bad_sidecar(path, which):
    side = _sidecar(path)
    if not side.exists():
        return False
    text = side.read_text()
    meta = json.loads(text)
    if which == "strings":
        meta["frame_times_s"] = [str(t) for t in meta["frame_times_s"]]
        side.write_text(json.dumps(meta))
    elif which == "digits":
        side.write_text(
            text.replace('"pitch_um": {', '"pitch_um": {"z": 1' + "0" * 100_000 + ", ", 1).replace(', "z": 1.0', "")
        )
    elif which == "beyond-float":
        side.write_text(text.replace('"frame_times_s": [0.0', '"frame_times_s": [1e400', 1))
    elif which == "index":
        meta["system"] = {
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.9,
            "axial_resolution_um": 3.8,
            "refractive_index": 1e6,
        }
        side.write_text(json.dumps(meta))
    else:  # the frame count of another file
        meta["frame_times_s"] = meta["frame_times_s"][:-1]
        side.write_text(json.dumps(meta))
    return True


def _links(path, which):
    with h5py.File(path, "a") as fh:
        if which == "self":
            del fh["data"]
            fh["data"] = h5py.SoftLink("/data")
        elif which == "loop":
            fh["a"] = h5py.SoftLink("/b")
            fh["b"] = h5py.SoftLink("/a")
        else:  # dangling, beside the good data: legal
            fh["zzz"] = h5py.SoftLink("/nowhere")
    return which != "self"


@settings(
    max_examples=examples(120),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    fmt=st.sampled_from(FORMAT_NAMES),
    mutation=st.sampled_from(MUTATIONS),
    cut=st.floats(0.0, 0.95),
    n=st.sampled_from([T + 1, 90_000_000, 1 << 40]),
    which=st.sampled_from(["strings", "digits", "beyond-float", "index", "frames", "self", "loop", "dangling"]),
    seed=st.integers(0, 3),
)
def test_every_reader_answers_any_file_with_its_data_or_one_error_line(
    tmp_path_factory, fmt, mutation, cut, n, which, seed
):
    d = tmp_path_factory.mktemp("case")
    a = _field(seed)
    path = _write(fmt, d, a)
    data_name = _data_file(path).name  # before a mutation replaces it
    legal = True
    if mutation == "truncate":
        target = _data_file(path)
        raw = target.read_bytes()
        target.write_bytes(raw[: int(len(raw) * cut)])
        legal = False
    elif mutation == "garbage":
        target = _data_file(path)
        target.write_bytes(np.random.default_rng(seed).bytes(max(16, int(target.stat().st_size * cut))))
        legal = False
    elif mutation == "huge":
        legal = not _declare_huge(fmt, path, n)
    elif mutation == "sidecar":
        legal = not _bad_sidecar(path, which if which in ("strings", "digits", "beyond-float", "index") else "frames")
    elif mutation == "special":  # the data file (a chunk, a frame) a FIFO: refused, never read (it would block)
        target = _data_file(path)
        target.unlink()
        os.mkfifo(target)
        legal = False
    elif mutation == "links" and fmt == "h5":
        legal = _links(path, which if which in ("self", "loop") else "dangling")
    out = d / "read.npy"
    proc = _read_in_child(path, out)
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    if proc.returncode == 0:
        assert legal, f"{fmt} {mutation} {which} was accepted"
        got = np.load(out)
        want = a if fmt in ("npy", "npz", "h5", "mat", "raw", "zarr") else np.abs(a) ** 2
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
        return
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(err) == 1 and err[0].startswith("error: "), proc.stderr[-2000:]
    assert any(s in err[0] for s in (path.name, path.stem, data_name)), err[0]
    assert not (legal and mutation == "none"), err[0]


@pytest.mark.parametrize("fmt,cut", [("zarr", 0.5), ("tif", 0.002), ("ome.tif", 0.002), ("folder", 0.002)])
def test_cases_the_harness_found_are_refused_naming_the_file(tmp_path, fmt, cut):
    """A Blosc chunk cut in half (decoded into numbers beyond it before), a TIFF cut inside its header (a
    struct.error traceback before)."""
    path = _write(fmt, tmp_path, _field(0))
    target = _data_file(path)
    raw = target.read_bytes()
    target.write_bytes(raw[: max(3, int(len(raw) * cut))])
    proc = _read_in_child(path, tmp_path / "read.npy")
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(err) == 1 and err[0].startswith("error: "), proc.stderr[-2000:]
    assert "truncated or corrupt" in err[0] or "not a readable" in err[0], err[0]

"""Reading and writing complex OCT time sequences (numpy only, no torch), and the maps files' names.

**Sequence files** (complex OCT time sequences), one reader module per format in
:mod:`torchdoct.measured.formats`, chosen by suffix (docs/formats.md lists them):

* ``NAME.npy`` (complex64/complex128 array) with a JSON sidecar ``NAME.json``;
* ``NAME.npz`` (key ``data``, optional keys ``labels`` and ``label_params``) with the sidecar;
* ``NAME.h5`` with dataset ``data`` (complex, or a MATLAB v7.3 compound ``{real, imag}``), optional
  datasets ``labels`` / ``label_params``, and the JSON as the string attribute ``torchdoct`` of the
  root (a MATLAB file has no attribute: give the metadata in a sidecar or as keywords / options, and
  name its variable with ``dataset=`` unless it holds only one);
* ``NAME.tif`` / ``NAME.tiff``: a linear-intensity stack (float, ``[T, Z, X]`` as the COG contrast
  library writes it), intensity only, so no resolution change is possible; the metadata come from a
  JSON ImageDescription, a sidecar or keywords.

Every reader's array goes through the same rules here (:func:`read_sequence`): the sidecar, the keyword
overrides, the dtype and value checks, the axes and :func:`validate_meta`; one :class:`SequenceData`
comes out whatever the format. The metadata, the orientation and the block raster protocol are
described in :mod:`torchdoct.measured.sequence`. Keyword arguments of :func:`read_sequence` (and the CLI
options built on them) override the file's values key by key or supply missing ones. ``axes`` given
when reading may be any permutation of the letters (e.g. ``"XZT"`` for a MATLAB ``[Z, X, T]`` array,
which HDF5 stores reversed); the data are transposed to the canonical ``TZX`` / ``TYZX`` order.

**Maps files** (written by ``torchdoct maps``): ``.npz`` with ``maps`` float32 ``[C, Z, X]`` or
``[C, Y, Z, X]``, ``channels`` (str array) and ``meta_json``; or ``.tif`` with the same stack and the
meta JSON as ImageDescription. Their owner is :mod:`torchdoct.measured.mapsfile` (:class:`Maps`,
:func:`read_maps`, :func:`write_maps`, re-exported here).

Safety (:mod:`torchdoct.measured.guards`, shared by every reader): files are never unpickled
(``allow_pickle=False``; object arrays are refused), outputs are written atomically and never
overwritten without ``force``. numpy only: importing this module does not import torch.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Mapping
from collections.abc import Sequence as _Seq
from pathlib import Path
from typing import Any

import numpy as np

from ..files import atomic_write, check_out, check_regular_file, open_regular, read_capped
from .formats import SEQUENCE_SUFFIXES, reader_for
from .formats.hdf5 import flat_attributes as _flat_attributes
from .guards import parse_json_object
from .mapsfile import MAPS_SUFFIXES, Maps, read_maps, write_maps
from .sequence import HOW as _HOW
from .sequence import (
    BlockRaster,
    SequenceData,
    check_axes,
    finite_positive,
    sidecar_exists,
    sidecar_path,
    validate_meta,
)

__all__ = [
    "SEQUENCE_SUFFIXES",
    "MAPS_SUFFIXES",
    "SequenceData",
    "BlockRaster",
    "Maps",
    "validate_meta",
    "write_sequence",
    "read_sequence",
    "write_maps",
    "read_maps",
    "sidecar_path",
]

_WRITE_SUFFIXES = (".npy", ".npz", ".h5")


def _sidecar_exists(side: Path) -> bool:
    return sidecar_exists(side)


# ----------------------------------------------------------------------------------------------
# sequence writer


def _as_numpy(data: Any) -> np.ndarray:
    if hasattr(data, "detach") and hasattr(data, "cpu"):  # a torch tensor, without importing torch
        data = data.detach().cpu().numpy()
    arr = np.asarray(data)
    if arr.dtype == object:
        raise TypeError("object arrays cannot be stored; give a numeric array")
    return arr


def _check_label_array(name: str, arr: Any) -> np.ndarray | None:
    if arr is None:
        return None
    a = _as_numpy(arr)
    if a.dtype.kind not in "biufcUS":
        raise TypeError(f"{name} must be a numeric or string array; got dtype {a.dtype}")
    return a


def write_sequence(
    path: str | os.PathLike,
    data: Any,
    meta: Mapping[str, Any],
    *,
    labels: Any = None,
    label_params: Any = None,
    force: bool = False,
) -> Path:
    """Write a complex sequence ``data`` (``[T, Z, X]`` / ``[T, Y, Z, X]``) with its metadata.

    Format by suffix: ``.npy`` + ``.json`` sidecar; ``.npz`` (``data``, optional ``labels`` /
    ``label_params``, and the metadata JSON as ``meta_json``) + sidecar; ``.h5`` (datasets ``data``,
    ``labels``, ``label_params``; the JSON as root attribute ``torchdoct`` and every field as its own
    attribute, :func:`_flat_attributes`). ``data`` may be numpy or torch, complex64 or complex128
    (float intensity is accepted too). Metadata are validated (:func:`validate_meta`). Every file is
    written atomically; an existing data file or sidecar is an error unless ``force``.
    Returns the data file path.
    """
    out = Path(path)
    if out.suffix not in _WRITE_SUFFIXES:
        raise ValueError(f"sequence file must end in {' or '.join(_WRITE_SUFFIXES)}; got {str(path)!r}")
    arr = _as_numpy(data)
    if arr.ndim not in (3, 4):
        raise ValueError(f"sequence data must be [T, Z, X] or [T, Y, Z, X]; got shape {list(arr.shape)}")
    if arr.dtype.kind not in "cf":
        raise TypeError(f"sequence data must be complex (complex64/complex128) or float intensity; got {arr.dtype}")
    clean = validate_meta(meta, arr.shape, where=f"{out.name} metadata")
    lab = _check_label_array("labels", labels)
    par = _check_label_array("label_params", label_params)
    if out.suffix == ".npy" and (lab is not None or par is not None):
        raise ValueError(f"{out.name}: labels need a .npz or .h5 file (a .npy holds only the data)")
    text = json.dumps(clean, indent=2)
    check_out(out, force, out.suffix, what=str(out.name))
    side = None
    if out.suffix in (".npy", ".npz"):
        side = check_out(sidecar_path(out), force, ".json", what=f"sidecar of {out.name}")

    if out.suffix == ".npy":

        def write(tmp: str) -> None:
            with open(tmp, "wb") as fh:
                np.save(fh, arr, allow_pickle=False)
    elif out.suffix == ".npz":
        # the metadata inside too (the archive may travel alone); Any: the names are array names, never savez's options
        arrays: dict[str, Any] = {"data": arr, "meta_json": np.asarray(text)}
        if lab is not None:
            arrays["labels"] = lab
        if par is not None:
            arrays["label_params"] = par

        def write(tmp: str) -> None:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    else:

        def write(tmp: str) -> None:
            import h5py

            with h5py.File(tmp, "w") as fh:
                fh.create_dataset("data", data=arr)
                for key, a in (("labels", lab), ("label_params", par)):
                    if a is None:
                        continue
                    if a.dtype.kind == "U":
                        fh.create_dataset(key, data=a.astype(object), dtype=h5py.string_dtype("utf-8"))
                    else:
                        fh.create_dataset(key, data=a)
                fh.attrs["torchdoct"] = text  # what the reader reads
                for key, value in _flat_attributes(clean).items():  # one attribute per field, for HDF5 viewers
                    fh.attrs[key] = value

    atomic_write(out, write)
    if side is not None:
        atomic_write(side, lambda tmp: Path(tmp).write_text(text + "\n", encoding="utf-8"))
    return out


# ----------------------------------------------------------------------------------------------
# sequence reader


def _check_values(data: np.ndarray, name: str) -> int:
    """The number of non-finite samples (NaN, inf; data holding no finite sample are refused); negative
    intensities are refused, counted, naming the fix. Read frame by frame (a memory-mapped ``.npy`` is never
    loaded whole for this)."""
    n_bad = n_neg = 0
    for frame in data:
        fin = np.isfinite(frame)
        n_bad += int(fin.size - np.count_nonzero(fin))
        if data.dtype.kind == "f":
            n_neg += int(np.count_nonzero(frame < 0))
    if n_bad == data.size:
        raise ValueError(
            f"{name}: holds no finite sample (all {n_bad} are NaN or inf); check the file (and --dataset / --axes)"
        )
    if n_neg:
        raise ValueError(
            f"{name}: {n_neg} of {data.size} intensity samples are negative; a linear intensity is >= 0 "
            "(a dB or background-subtracted image is not one). Fix: store the linear intensity |E|^2, "
            "e.g. 10**(dB/10), or clip the subtracted background at 0"
        )
    return n_bad


#: The scales of ``read_sequence(scale=...)`` / ``--scale``: what the stored samples are.
SCALES = ("linear", "db", "complex")
#: The largest dB value read (``10^(38.0)`` is near float32's largest number: a larger one is not a dB value).
MAX_DB = 380.0


def _apply_scale(data: Any, scale: str, name: str) -> Any:
    """The samples as the maps read them, after checking they fit ``scale``: ``complex`` (the field; the data
    must be complex), ``linear`` (an intensity; must be real, and non-negative as :func:`_check_values`
    checks) or ``db`` (``10·log10`` of an intensity, converted to the linear ``10^(dB/10)``; real and at
    most :data:`MAX_DB`)."""
    if scale not in SCALES:
        raise ValueError(f"--scale must be one of {', '.join(SCALES)}; got {scale!r}")
    if scale == "complex":
        if data.dtype.kind != "c":
            raise ValueError(
                f"{name}: --scale complex, but the data are real ({data.dtype}): an intensity; give "
                "--scale linear or --scale db"
            )
        return data
    if data.dtype.kind == "c":
        raise ValueError(
            f"{name}: --scale {scale}, but the data are complex ({data.dtype}): the field; give "
            "--scale complex (or drop --scale)"
        )
    if scale == "linear":
        return data
    dtype = np.dtype(np.float64 if data.dtype == np.float64 else np.float32)
    from .formats.lazy import LazyArray

    lazy = isinstance(data, LazyArray)
    out = None if lazy else np.empty(data.shape, dtype=dtype)
    for k in range(data.shape[0]):  # frame by frame
        frame = np.asarray(data[k], dtype=dtype)
        top = float(np.max(frame, where=np.isfinite(frame), initial=-np.inf))
        if top > MAX_DB:
            raise ValueError(
                f"{name}: --scale db, but frame {k} holds {top:.4g}, over {MAX_DB:g} dB (10^(dB/10) "
                "would overflow): these are not dB values; give --scale linear for a linear intensity"
            )
        if out is not None:
            np.power(10.0, frame / 10.0, out=out[k])
    if lazy:  # a streamed input stays streamed: converted slab by slab as the maps read it
        return data.converted(
            lambda b: np.power(10.0, b.astype(dtype, copy=False) / 10.0).astype(dtype, copy=False), dtype
        )
    return out


def _parse_pitch(pitch: Any) -> dict[str, float]:
    if isinstance(pitch, str):
        out = {}
        for part in pitch.split(","):
            if "=" not in part:
                raise ValueError(f"pitch must be like z=1.5,x=2.0[,y=7.8] (µm); got {pitch!r}")
            k, v = part.split("=", 1)
            out[k.strip().lower()] = float(v)
        return out
    if not isinstance(pitch, Mapping):
        raise TypeError(f"pitch_um must be a dict or 'z=..,x=..' string; got {pitch!r}")
    return {str(k).lower(): v for k, v in pitch.items()}


def _check_meta_before_reading(
    meta: Mapping[str, Any],
    stored_shape: _Seq[int],
    stored: str,
    block_raster: BlockRaster | None,
    frame_times_s: _Seq[float] | None,
    frame_interval_s: float | None,
    name: str,
) -> None:
    """:func:`validate_meta` on the shape the file declares, before a sample is read: a frame count, pitch or
    block raster that does not fit the array is refused at once, not after reading gigabytes."""
    shape = [stored_shape[stored.index(c)] for c in ("TZX" if len(stored) == 3 else "TYZX")]
    trial = dict(meta, axes="TZX" if len(stored) == 3 else "TYZX")
    if block_raster is not None and len(stored) == 3:
        if shape[0] != block_raster.n_bscans:
            raise ValueError(
                f"{name}: block raster {block_raster.n_blocks}:{block_raster.n_repeats}:"
                f"{block_raster.bscans_per_block} needs [{block_raster.n_bscans}, Z, X] B-scans in "
                f"acquisition order; the data hold {shape[0]}; check --block-raster and --axes"
            )
        shape = [block_raster.n_repeats, block_raster.n_y, shape[1], shape[2]]
        trial["axes"] = "TYZX"
    if block_raster is not None:
        trial["block_raster"] = block_raster.to_dict()
    if frame_times_s is not None:
        trial["frame_times_s"] = list(frame_times_s)
    elif frame_interval_s is not None:
        dt = finite_positive("frame_interval_s (s)", frame_interval_s)
        trial["frame_times_s"] = [i * dt for i in range(shape[0])]
    validate_meta(trial, shape, where=name)


def read_sequence(
    path: str | os.PathLike,
    *,
    axes: str | None = None,
    pitch_um: Mapping[str, float] | str | None = None,
    frame_times_s: _Seq[float] | None = None,
    frame_interval_s: float | None = None,
    system: Mapping[str, Any] | None = None,
    dataset: str | None = None,
    block_raster: BlockRaster | None = None,
    allow_external_hdf5: bool = False,
    scale: str | None = None,
    stream: bool = False,
) -> SequenceData:
    """Read a sequence file (see the module docstring) into a :class:`SequenceData` in canonical order.

    Metadata come from the file (h5 attribute, TIFF JSON description) or its JSON sidecar; the
    keywords override them key by key or supply missing ones: ``axes`` (the stored order, any
    permutation of TZX / TYZX), ``pitch_um`` (dict or ``"z=..,x=..,y=.."``, µm), ``frame_times_s`` or
    ``frame_interval_s`` (s, uniform from 0), ``system`` (dict of ``name``, ``wavelength_um``,
    ``lateral_resolution_um``, ``axial_resolution_um``, ``refractive_index``), ``dataset`` (HDF5
    variable name), ``block_raster`` (unpack an acquisition-order ``[blocks·repeats·bscans, Z, X]``
    stack, whose stored axes must then be a permutation of TZX with T the scan index, to
    ``[T, Y, Z, X]``; data already ``[T, Y, Z, X]`` just record it for boundary exclusion),
    ``allow_external_hdf5`` (read HDF5 external storage, external links and virtual datasets whose data
    lie in other files; refused by default, :func:`torchdoct.measured.guards.check_hdf5_local`),
    ``scale`` (``linear``, ``db`` or ``complex``: what the samples are, checked; dB intensities are
    converted to linear, :func:`_apply_scale`; default: complex data are the field, real data a linear
    intensity), ``stream`` (a memory-mapped ``.npy`` or raw binary is read slice by slice through
    :class:`~torchdoct.measured.formats.lazy.MappedFile`, converted to native byte order or float32 as it
    is read, so only the slabs the maps read are ever resident; an OME-Zarr always is; such inputs are
    then bound by an explicit ``--max-input-gb`` only, :func:`torchdoct.measured.guards.streaming_reads`). Declared sizes over :func:`torchdoct.measured.guards.max_input_bytes` are refused before reading;
    negative intensities and extended-precision dtypes are refused naming the file, the count and the
    fix; samples that are not finite (NaN, inf) are counted (``nonfinite_samples``) and their pixels are
    masked in the maps (:func:`torchdoct.measured.maps.compute_maps`). A file the system does not let us read raises ``PermissionError``.
    A TIFF stack without axes is taken as ``TZX`` (the COG layout). Missing metadata raise a
    ``ValueError`` naming the key and the option that gives it.
    """
    p = Path(path)
    if not os.path.lexists(p):  # a link that loops or leads nowhere: named by check_regular_file
        raise FileNotFoundError(f"sequence file {p} does not exist")
    fmt = reader_for(p)
    if not (fmt is not None and getattr(fmt, "DIRECTORY", False) and p.is_dir()):
        check_regular_file(p, "sequence file")  # a FIFO, device or folder: at once, whatever its name
    if fmt is None and p.suffix.lower() == ".oct":
        raise ValueError(
            f"{p.name}: Thorlabs .oct files are not read (their layout has no public specification, "
            "docs/formats.md); export the data from ThorImageOCT to OME-TIFF, MATLAB or a raw binary "
            "with a JSON sidecar and read that"
        )
    if fmt is None:
        raise ValueError(f"{p.name}: unknown sequence format; use {', '.join(SEQUENCE_SUFFIXES)}")
    suffix = p.suffix.lower()
    if getattr(fmt, "DIRECTORY", False):
        if not p.is_dir():
            raise ValueError(f"{p.name}: a {fmt.NAME} is a folder; give the folder")
    else:
        with open_regular(p, "sequence file"):  # a FIFO swapped in meanwhile: refused; a file the system does not
            pass  # let us read: PermissionError (exit 1), whatever the format
    from .guards import streaming_reads

    try:
        with streaming_reads(stream):  # arrays read slab by slab: bound by the budget, not the input limit
            loaded = fmt.load(p, dataset=dataset, allow_external_hdf5=allow_external_hdf5)
    except PermissionError:  # the system refuses: exit 1 at the command line, as for an unreadable sidecar
        raise
    except (EOFError, OSError, zipfile.BadZipFile, KeyError) as err:
        raise ValueError(
            f"{p.name}: not a readable {suffix} file (truncated or corrupt: {type(err).__name__}: {err})"
        ) from None
    if dataset is not None and not fmt.DATASET:
        raise ValueError(f"{p.name}: dataset= applies to .h5 and .mat files only")
    data, labels, params, file_meta = loaded.data, loaded.labels, loaded.label_params, loaded.meta
    if stream and isinstance(data, np.memmap) and data.flags.c_contiguous:  # any byte order: converted as read
        from .formats.lazy import LazyArray, MappedFile

        data = LazyArray(MappedFile(data.filename, data.dtype, data.shape, data.offset), p.name)
    side = sidecar_path(p)
    meta: dict[str, Any] = {}
    if file_meta is not None and not (loaded.sidecar_fills and _sidecar_exists(side)):
        meta.update(file_meta)
    elif _sidecar_exists(side):
        try:
            side_text = read_capped(side, f"the metadata sidecar of {p.name}").decode("utf-8")
        except UnicodeDecodeError as err:
            raise ValueError(
                f"{side.name}: the metadata sidecar of {p.name} is not UTF-8 text (byte {err.start}); "
                "it must be the JSON metadata file (fix it, or remove it and give the metadata as "
                "options)"
            ) from None
        meta.update(parse_json_object(side_text, side.name))
        meta.update(file_meta or {})  # a format whose sidecar only fills in: the file's own values win
    if loaded.default_axes is not None and axes is None and "axes" not in meta:
        axes = loaded.default_axes
    # keyword overrides
    if axes is not None:
        meta["axes"] = axes
    if pitch_um is not None:
        merged = dict(meta.get("pitch_um") or {})
        merged.update(_parse_pitch(pitch_um))
        meta["pitch_um"] = merged
    if frame_times_s is not None and frame_interval_s is not None:
        raise ValueError("give frame_times_s or frame_interval_s, not both")
    if system is not None:
        merged = dict(meta.get("system") or {})
        merged.update({k: v for k, v in dict(system).items() if v is not None})
        meta["system"] = merged

    if (data.dtype.kind == "c" and data.dtype.itemsize > 16) or (data.dtype.kind == "f" and data.dtype.itemsize > 8):
        raise TypeError(
            f"{p.name}: data dtype {data.dtype} (extended precision) is not supported; convert it to "
            f"{'complex128' if data.dtype.kind == 'c' else 'float64'} (e.g. a.astype(np."
            f"{'complex128' if data.dtype.kind == 'c' else 'float64'})) and save again"
        )
    if data.dtype.kind not in "cf":
        if data.dtype.kind in "iu" and loaded.integer_intensity:
            data = data.astype(np.float32)
        else:
            raise TypeError(
                f"{p.name}: data dtype {data.dtype} is neither complex (complex OCT) nor float (linear intensity)"
            )
    if data.ndim not in (3, 4):
        raise ValueError(
            f"{p.name}: data have shape {list(data.shape)}; expected 3 ([T, Z, X]) or 4 ([T, Y, Z, X]) dimensions"
        )
    if 0 in data.shape:
        raise ValueError(f"{p.name}: data have an empty axis (shape {list(data.shape)}); nothing to read")
    if scale is not None and scale not in SCALES:
        raise ValueError(f"--scale must be one of {', '.join(SCALES)}; got {scale!r}")
    if meta.get("axes") is None:
        raise ValueError(f"{p.name}: missing 'axes'; {_HOW['axes']}")
    stored = check_axes(meta["axes"], data.ndim, p.name)
    canonical = "TZX" if len(stored) == 3 else "TYZX"
    _check_meta_before_reading(meta, data.shape, stored, block_raster, frame_times_s, frame_interval_s, p.name)
    if not data.dtype.isnative:  # e.g. a big-endian '>c8' .npy: read into native byte order (torch needs it)
        data = data.astype(data.dtype.newbyteorder("="))
    if scale is not None:
        data = _apply_scale(data, scale, p.name)
        meta["input_scale"] = scale
    n_nonfinite = _check_values(data, p.name)
    data = data.transpose([stored.index(c) for c in canonical]) if stored != canonical else data
    meta["axes"] = canonical
    if block_raster is not None:
        if canonical == "TZX":
            data = block_raster.unpack(data)
            meta["axes"] = "TYZX"
        elif data.shape[1] != block_raster.n_y or data.shape[0] != block_raster.n_repeats:
            raise ValueError(
                f"{p.name}: block raster {block_raster.n_blocks}:{block_raster.n_repeats}:"
                f"{block_raster.bscans_per_block} does not match [T, Y, Z, X] = {list(data.shape)}"
            )
        meta["block_raster"] = block_raster.to_dict()
    if frame_times_s is not None:
        meta["frame_times_s"] = list(frame_times_s)
    elif frame_interval_s is not None:
        dt = finite_positive("frame_interval_s (s)", frame_interval_s)
        meta["frame_times_s"] = [i * dt for i in range(data.shape[0])]
    clean = validate_meta(meta, data.shape, where=p.name)
    return SequenceData(
        data=data, meta=clean, labels=labels, label_params=params, source=p.name, nonfinite_samples=n_nonfinite
    )

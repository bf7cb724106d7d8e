"""Readers and writers of complex OCT time sequences and of DOCT map files (numpy only, no torch).

**Sequence files** (complex OCT time sequences):

* ``NAME.npy`` (complex64/complex128 array) with a JSON sidecar ``NAME.json``;
* ``NAME.npz`` (key ``data``, optional keys ``labels`` and ``label_params``) with the sidecar;
* ``NAME.h5`` with dataset ``data`` (complex, or a MATLAB v7.3 compound ``{real, imag}``), optional
  datasets ``labels`` / ``label_params``, and the JSON as the string attribute ``torchdoct`` of the
  root (a MATLAB file has no attribute: give the metadata in a sidecar or as keywords / options, and
  name its variable with ``dataset=`` unless it holds only one);
* ``NAME.tif`` / ``NAME.tiff``: a linear-intensity stack (float, ``[T, Z, X]`` as the COG contrast
  library writes it), intensity only, so no resolution change is possible; the metadata come from a
  JSON ImageDescription, a sidecar or keywords.

Metadata (the sidecar / attribute JSON)::

    {"axes": "TZX" | "TYZX", "pitch_um": {"z": .., "x": .., ["y": ..]}, "frame_times_s": [...],
     "system": {"name": .., "wavelength_um": .., "lateral_resolution_um": .., "axial_resolution_um": ..,
                "refractive_index": ..}, ...optional extra keys}

``pitch_um["z"]`` is the in-medium depth step. Keyword arguments of :func:`read_sequence` (and the CLI
options built on them) override the file's values key by key or supply missing ones. ``axes`` given
when reading may be any permutation of the letters (e.g. ``"XZT"`` for a MATLAB ``[Z, X, T]`` array,
which HDF5 stores reversed); the data are transposed to the canonical ``TZX`` / ``TYZX`` order.

**Block raster protocol** (paper Section 2.1.2; El-Sadek 2021): the en-face field is split into
``n_blocks`` blocks of ``bscans_per_block`` B-scan positions; each block is raster-scanned
``n_repeats`` times before the next. A stack stored in acquisition order ``[n_blocks·n_repeats·
bscans_per_block, Z, X]`` is unpacked to ``[T = n_repeats, Y = n_blocks·bscans_per_block, Z, X]``
(:meth:`BlockRaster.unpack`). The B-scans next to block boundaries have a ~6.6 s acquisition gap to
their neighbours; :meth:`BlockRaster.keep_y` marks the ``drop_boundary`` B-scans on each side of every
inner boundary for exclusion (the paper drops one).

**Maps files** (written by ``torchdoct maps``): ``.npz`` with ``maps`` float32 ``[C, Z, X]`` or
``[C, Y, Z, X]``, ``channels`` (str array) and ``meta_json``; or ``.tif`` with the same stack and the
meta JSON as ImageDescription. Their owner is :mod:`torchdoct.measured.mapsfile` (:class:`Maps`,
:func:`read_maps`, :func:`write_maps`, re-exported here).

Safety (:mod:`torchdoct.measured.guards`, shared by every reader): files are never unpickled
(``allow_pickle=False``; object arrays are refused), outputs are written atomically and never
overwritten without ``force``. numpy only: importing this module does not import torch.
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence as _Seq

import numpy as np

from ..files import atomic_write, check_out
from .guards import (TiffDamage, check_declared_size, check_hdf5_local, check_npy_header, check_npy_size,
                     check_npz_sizes, check_tiff_pages, parse_json_object, refuse_object)
from .mapsfile import MAPS_SUFFIXES, Maps, read_maps, write_maps

__all__ = [
    "SEQUENCE_SUFFIXES",
    "MAPS_SUFFIXES",
    "SequenceData",
    "Sequence",
    "BlockRaster",
    "Maps",
    "validate_meta",
    "write_sequence",
    "read_sequence",
    "write_maps",
    "read_maps",
    "sidecar_path",
]

SEQUENCE_SUFFIXES = (".npy", ".npz", ".h5", ".tif", ".tiff")
_WRITE_SUFFIXES = (".npy", ".npz", ".h5")
_CANONICAL_AXES = ("TZX", "TYZX")
_SYSTEM_NUMBERS = ("wavelength_um", "lateral_resolution_um", "axial_resolution_um", "refractive_index")
_HOW = {
    "axes": "give --axes (e.g. TZX, TYZX, or the stored order such as XZT) or 'axes' in the sidecar JSON",
    "pitch_um": "give --pitch-um z=..,x=..[,y=..] (µm) or 'pitch_um' in the sidecar JSON",
    "frame_times_s": "give --frame-interval-s DT, --frame-times-s t0,t1,.. or 'frame_times_s' in the sidecar JSON",
    "system": ("give --wavelength-um, --lateral-resolution-um and --axial-resolution-um or 'system' in the "
               "sidecar JSON"),
}


def sidecar_path(path: str | os.PathLike) -> Path:
    """The JSON sidecar of a sequence file: same directory and stem, suffix ``.json``."""
    return Path(path).with_suffix(".json")


# ----------------------------------------------------------------------------------------------
# data classes


@dataclass(frozen=True, kw_only=True)
class BlockRaster:
    """The paper's 3D block raster protocol (Section 2.1.2): blocks × repeats × B-scans per block.

    ``drop_boundary``: how many B-scans on each side of every inner block boundary to exclude from
    the analysis (the paper: 1). Use more when the lateral Gaussian of a resolution reduction reaches
    further than one B-scan pitch across the boundary.
    """

    n_blocks: int
    n_repeats: int
    bscans_per_block: int
    drop_boundary: int = 1

    def __post_init__(self) -> None:
        for key in ("n_blocks", "n_repeats", "bscans_per_block", "drop_boundary"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"block raster {key} must be an integer; got {v!r}")
            object.__setattr__(self, key, int(v))
        for key in ("n_blocks", "bscans_per_block"):
            if getattr(self, key) < 1:
                raise ValueError(f"block raster {key} must be >= 1; got {getattr(self, key)}")
        if self.n_repeats < 2:
            raise ValueError(f"block raster n_repeats must be >= 2 (frames per location); got {self.n_repeats}")
        if self.drop_boundary < 0 or 2 * self.drop_boundary >= self.bscans_per_block:
            raise ValueError(f"block raster drop_boundary must be >= 0 and leave B-scans in each block "
                             f"(< bscans_per_block/2 = {self.bscans_per_block / 2:g}); got {self.drop_boundary}")

    @classmethod
    def parse(cls, text: str, drop_boundary: int = 1) -> "BlockRaster":
        """From ``"BLOCKS:REPEATS:BSCANS"`` (e.g. ``"8:32:16"``, the paper's protocol)."""
        parts = str(text).replace("x", ":").split(":")
        if len(parts) != 3:
            raise ValueError(f"--block-raster must be BLOCKS:REPEATS:BSCANS_PER_BLOCK (e.g. 8:32:16); got {text!r}")
        try:
            b, r, k = (int(p) for p in parts)
        except ValueError:
            raise ValueError(f"--block-raster must be three integers BLOCKS:REPEATS:BSCANS; got {text!r}") from None
        return cls(n_blocks=b, n_repeats=r, bscans_per_block=k, drop_boundary=drop_boundary)

    @property
    def n_bscans(self) -> int:
        """Total B-scans acquired: ``n_blocks·n_repeats·bscans_per_block``."""
        return self.n_blocks * self.n_repeats * self.bscans_per_block

    @property
    def n_y(self) -> int:
        """B-scan positions of the volume: ``n_blocks·bscans_per_block``."""
        return self.n_blocks * self.bscans_per_block

    def unpack(self, data: np.ndarray) -> np.ndarray:
        """``[n_bscans, Z, X]`` in acquisition order → ``[n_repeats, n_y, Z, X]`` (a view when possible).

        Acquisition index of (block b, repeat r, position k) is ``(b·n_repeats + r)·bscans_per_block + k``.
        """
        if data.ndim != 3 or data.shape[0] != self.n_bscans:
            raise ValueError(f"block raster {self.n_blocks}:{self.n_repeats}:{self.bscans_per_block} needs data "
                             f"[{self.n_bscans}, Z, X] in acquisition order; got shape {list(data.shape)}")
        z, x = data.shape[1:]
        a = data.reshape(self.n_blocks, self.n_repeats, self.bscans_per_block, z, x)
        return a.transpose(1, 0, 2, 3, 4).reshape(self.n_repeats, self.n_y, z, x)

    def keep_y(self) -> np.ndarray:
        """Boolean ``[n_y]``: False for the ``drop_boundary`` B-scans on each side of inner boundaries."""
        keep = np.ones(self.n_y, dtype=bool)
        d = self.drop_boundary
        for b in range(1, self.n_blocks):
            edge = b * self.bscans_per_block
            keep[edge - d:edge + d] = False
        return keep

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, kw_only=True, eq=False)
class SequenceData:
    """A time sequence of OCT frames with validated metadata.

    ``data``: numpy array in canonical order ``[T, Z, X]`` or ``[T, Y, Z, X]``: complex64/complex128
    (complex OCT) or float (linear intensity, e.g. a TIFF stack). May be a read-only memory map.
    ``meta``: the metadata dict (canonical ``axes``, ``pitch_um``, ``frame_times_s``, optional
    ``system`` and extra keys). ``labels`` / ``label_params``: optional arrays stored with the data.
    ``source``: the file name it was read from (no directory). ``nonfinite_samples``: how many samples
    of ``data`` are NaN or infinite (counted by :func:`read_sequence`; the maps mask their pixels).
    """

    data: np.ndarray
    meta: dict[str, Any]
    labels: np.ndarray | None = None
    label_params: np.ndarray | None = None
    source: str | None = None
    nonfinite_samples: int = 0

    @property
    def axes(self) -> str:
        return self.meta["axes"]

    @property
    def pitch_um(self) -> dict[str, float]:
        """The pixel pitch (µm); a ``ValueError`` says how to give it when the metadata have none (only a
        resolution change needs it)."""
        pitch = self.meta.get("pitch_um")
        if pitch is None:
            raise ValueError(f"{self.source or 'sequence'}: missing 'pitch_um' (µm per pixel); {_HOW['pitch_um']}")
        return dict(pitch)

    @property
    def frame_times_s(self) -> list[float]:
        return list(self.meta["frame_times_s"])

    @property
    def n_frames(self) -> int:
        return int(self.data.shape[0])

    @property
    def is_complex(self) -> bool:
        return bool(np.iscomplexobj(self.data))

    @property
    def system(self) -> dict[str, Any]:
        """The system dict; a ``ValueError`` says how to give it when it is missing or incomplete."""
        sysd = self.meta.get("system")
        missing = [k for k in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um")
                   if not isinstance(sysd, Mapping) or sysd.get(k) is None]
        if missing:
            raise ValueError(f"{self.source or 'sequence'}: system metadata missing {', '.join(missing)}; "
                             f"{_HOW['system']}")
        return dict(sysd)

    @property
    def block_raster(self) -> BlockRaster | None:
        br = self.meta.get("block_raster")
        return None if br is None else BlockRaster(**br)


#: The former name of :class:`SequenceData` (it shadowed ``typing.Sequence``), kept for the public API.
Sequence = SequenceData


# ----------------------------------------------------------------------------------------------
# metadata


def _finite_positive(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{where} must be a number; got {type(value).__name__} {value!r}")
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{where} must be a finite number > 0; got {value!r}")
    return v


def _check_axes(axes: Any, ndim: int | None, where: str) -> str:
    if not isinstance(axes, str):
        raise TypeError(f"{where}: axes must be a string such as 'TZX' or 'TYZX'; got {axes!r}")
    a = axes.upper()
    if sorted(a) not in (sorted("TZX"), sorted("TYZX")):
        raise ValueError(f"{where}: axes {axes!r} must be a permutation of TZX or TYZX (T frames, Y slow lateral, "
                         "Z depth, X fast lateral)")
    if ndim is not None and len(a) != ndim:
        raise ValueError(f"{where}: axes {axes!r} has {len(a)} letters but the data have {ndim} dimensions; "
                         "give --axes matching the stored array")
    return a


def validate_meta(meta: Mapping[str, Any], shape: _Seq[int], *, where: str = "metadata",
                  require_system: bool = False, require_pitch: bool = False) -> dict[str, Any]:
    """Check metadata against canonical-order data of ``shape``; return a cleaned copy.

    Checks: ``axes`` is ``TZX`` or ``TYZX`` and matches the rank; ``pitch_um`` (when present, or when
    ``require_pitch``; only a resolution change needs it) has a positive entry for every spatial axis
    (and no other key); ``frame_times_s`` has ``T`` finite, strictly increasing
    entries; ``system`` (when present, or when ``require_system``) has positive ``wavelength_um``,
    ``lateral_resolution_um``, ``axial_resolution_um`` (µm) and ``refractive_index`` ≥ 1.
    """
    if not isinstance(meta, Mapping):
        raise TypeError(f"{where} must be a dict; got {type(meta).__name__}")
    out = dict(meta)
    for key in ("axes", "frame_times_s") + (("pitch_um",) if require_pitch else ()):
        if out.get(key) is None:
            raise ValueError(f"{where}: missing {key!r}; {_HOW[key]}")
    axes = _check_axes(out["axes"], len(shape), where)
    if axes not in _CANONICAL_AXES:
        raise ValueError(f"{where}: axes {axes!r} is not canonical (TZX or TYZX); transpose the data first")
    out["axes"] = axes
    pitch = out.get("pitch_um")
    if pitch is None:  # only a resolution change needs it (Sequence.pitch_um says how to give it)
        out.pop("pitch_um", None)
    else:
        if not isinstance(pitch, Mapping):
            raise TypeError(f"{where}: pitch_um must be a dict like {{'z': 1.5, 'x': 2.0}}; got {pitch!r}")
        spatial = [c.lower() for c in axes if c != "T"]
        extra = sorted(set(pitch) - set(spatial))
        if extra:
            raise ValueError(f"{where}: pitch_um has keys {extra} for axes not in {axes!r}; allowed: {spatial}")
        missing = [c for c in spatial if pitch.get(c) is None]
        if missing:
            raise ValueError(f"{where}: pitch_um is missing {missing} (µm per pixel); {_HOW['pitch_um']}")
        out["pitch_um"] = {c: _finite_positive(f"{where}: pitch_um[{c!r}] (µm)", pitch[c]) for c in spatial}
    times = out["frame_times_s"]
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        raise TypeError(f"{where}: frame_times_s must be a list of times in s; got {times!r}")
    try:
        t = [float(v) for v in times]
    except (TypeError, ValueError):
        raise TypeError(f"{where}: frame_times_s must be numbers (s); got {times!r}") from None
    if len(t) != shape[0]:
        raise ValueError(f"{where}: frame_times_s has {len(t)} entries but the data have T = {shape[0]} frames; "
                         f"{_HOW['frame_times_s']}")
    if not all(math.isfinite(v) for v in t):
        raise ValueError(f"{where}: frame_times_s must be finite; got {times!r}")
    if any(b <= a for a, b in zip(t, t[1:])):
        raise ValueError(f"{where}: frame_times_s must be strictly increasing (s)")
    out["frame_times_s"] = t
    sysd = out.get("system")
    if sysd is not None or require_system:
        if not isinstance(sysd, Mapping):
            raise ValueError(f"{where}: missing 'system'; {_HOW['system']}")
        s = dict(sysd)
        for key in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um"):
            if s.get(key) is None:
                if require_system:
                    raise ValueError(f"{where}: system is missing {key!r}; {_HOW['system']}")
                continue
            s[key] = _finite_positive(f"{where}: system.{key}", s[key])
        if s.get("wavelength_um") is not None and not (0.1 <= s["wavelength_um"] <= 20.0):
            raise ValueError(f"{where}: system.wavelength_um = {s['wavelength_um']} is outside 0.1-20 µm; "
                             "wavelengths are in micrometres (840 nm is 0.84)")
        n = s.get("refractive_index", 1.0)
        s["refractive_index"] = _finite_positive(f"{where}: system.refractive_index", 1.0 if n is None else n)
        if s["refractive_index"] < 1.0:
            raise ValueError(f"{where}: system.refractive_index must be >= 1; got {s['refractive_index']}")
        s.setdefault("name", "system")
        out["system"] = s
    br = out.get("block_raster")
    if br is not None:
        raster = BlockRaster(**br) if isinstance(br, Mapping) else br
        if not isinstance(raster, BlockRaster):
            raise TypeError(f"{where}: block_raster must be a dict; got {br!r}")
        if axes != "TYZX" or shape[1] != raster.n_y or shape[0] != raster.n_repeats:
            raise ValueError(f"{where}: block_raster {raster.to_dict()} does not match data {list(shape)} "
                             f"({axes}): need T = n_repeats and Y = n_blocks·bscans_per_block")
        out["block_raster"] = raster.to_dict()
    try:
        json.dumps(out)
    except TypeError as err:
        raise TypeError(f"{where}: metadata must be JSON-serializable ({err})") from None
    return out


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


def write_sequence(path: str | os.PathLike, data: Any, meta: Mapping[str, Any], *, labels: Any = None,
                   label_params: Any = None, force: bool = False) -> Path:
    """Write a complex sequence ``data`` (``[T, Z, X]`` / ``[T, Y, Z, X]``) with its metadata.

    Format by suffix: ``.npy`` + ``.json`` sidecar; ``.npz`` (``data``, optional ``labels`` /
    ``label_params``) + sidecar; ``.h5`` (datasets ``data``, ``labels``, ``label_params``; the JSON
    as root attribute ``torchdoct``). ``data`` may be numpy or torch, complex64 or complex128
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
        arrays = {"data": arr}
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
                fh.attrs["torchdoct"] = text

    atomic_write(out, write)
    if side is not None:
        atomic_write(side, lambda tmp: Path(tmp).write_text(text + "\n", encoding="utf-8"))
    return out


# ----------------------------------------------------------------------------------------------
# sequence reader


def _load_npy(path: Path) -> np.ndarray:
    check_npy_header(path)
    check_npy_size(path)
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as err:
        if "pickle" in str(err).lower() or "object" in str(err).lower():
            raise ValueError(f"{path.name}: holds an object array, which would need unpickling; refused "
                             "(store a complex64/complex128 array)") from None
        raise ValueError(f"{path.name}: not a readable .npy file ({err})") from None


def _load_npz(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    check_npz_sizes(path)  # declared sizes, before anything is decompressed
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # our handle: closed on errors too
            if "data" not in z.files:
                raise ValueError(f"{path.name}: no array 'data' (arrays: {', '.join(z.files) or 'none'}); "
                                 "store the sequence under the key 'data'")
            out = []
            for key in ("data", "labels", "label_params"):
                out.append(refuse_object(z[key], f"{path.name}[{key}]") if key in z.files else None)
    except ValueError as err:
        if "pickle" in str(err).lower() or "object" in str(err).lower():
            raise ValueError(f"{path.name}: holds an object array, which would need unpickling; refused") from None
        if "EOF" in str(err) or "reading array data" in str(err):
            raise ValueError(f"{path.name}: an array is truncated ({err}); copy or write the file again "
                             "completely") from None
        raise
    return out[0], out[1], out[2]


def _h5_array(ds: Any, where: str) -> np.ndarray:
    dt = ds.dtype
    check_declared_size(where, ds.shape or (), dt.itemsize, what="dataset")  # before reading (and decompressing)
    if dt.names is not None:
        names = {n.lower(): n for n in dt.names}
        if set(names) != {"real", "imag"}:
            raise ValueError(f"{where}: compound dataset with fields {dt.names}; expected MATLAB v7.3 complex "
                             "{real, imag}")
        raw = ds[()]
        re = np.asarray(raw[names["real"]])
        im = np.asarray(raw[names["imag"]])
        ctype = np.complex128 if re.dtype == np.float64 else np.complex64
        arr = np.empty(re.shape, dtype=ctype)
        arr.real = re
        arr.imag = im
        return arr
    if dt.kind == "O":
        import h5py

        if h5py.check_string_dtype(dt) is not None:
            return np.asarray(ds.asstr()[()], dtype=str)
        raise ValueError(f"{where}: object/reference datasets are not supported; store a numeric array")
    return np.asarray(ds[()])


def _load_h5(path: Path, dataset: str | None, allow_external: bool = False
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, dict | None]:
    import h5py

    try:
        fh = h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path.name}: not a readable HDF5 / MATLAB v7.3 file ({err})") from None
    with fh:
        check_hdf5_local(fh, path, allow_external)  # before any link is followed or any data read
        names = [k for k in fh.keys() if not k.startswith("#") and isinstance(fh[k], h5py.Dataset)]
        if dataset is None:
            if "data" in names:
                dataset = "data"
            else:
                cands = [n for n in names if n not in ("labels", "label_params")]
                if len(cands) != 1:
                    raise ValueError(f"{path.name}: no dataset 'data' and {len(cands)} candidate datasets "
                                     f"({', '.join(cands) or 'none'}); name one with --dataset")
                dataset = cands[0]
        if dataset not in fh or not isinstance(fh[dataset], h5py.Dataset):
            raise ValueError(f"{path.name}: no dataset {dataset!r} (datasets: {', '.join(names) or 'none'})")
        data = _h5_array(fh[dataset], f"{path.name}:{dataset}")
        labels = _h5_array(fh["labels"], f"{path.name}:labels") if "labels" in names else None
        params = _h5_array(fh["label_params"], f"{path.name}:label_params") if "label_params" in names else None
        meta = None
        if "torchdoct" in fh.attrs:
            raw = fh.attrs["torchdoct"]
            if isinstance(raw, bytes):
                try:
                    raw = raw.decode("utf-8")
                except UnicodeDecodeError as err:
                    raise ValueError(f"{path.name}: attribute 'torchdoct' is not UTF-8 text (byte {err.start}); it "
                                     "must hold the JSON metadata (write the file again)") from None
            meta = parse_json_object(str(raw), f"{path.name} attribute 'torchdoct'")
    return data, labels, params, meta


def _load_tif(path: Path) -> tuple[np.ndarray, dict | None]:
    import tifffile

    try:
        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            check_tiff_pages(path, tf)  # one shape on every page, total within the input limit
            data = tf.asarray()
            if data.ndim == 2 and len(tf.pages) > 1:  # one image per page, each its own series: all pages
                data = tf.asarray(key=range(len(tf.pages)))
            desc = tf.pages[0].description if len(tf.pages) else ""
            damage.check()
    except (tifffile.TiffFileError, OSError, ValueError) as err:
        raise ValueError(f"{path.name}: not a readable TIFF stack ({err})") from None
    meta = None
    if desc and desc.lstrip().startswith("{"):
        from ..files import check_nesting

        check_nesting(desc, f"{path.name}: TIFF ImageDescription")  # before the parser's recursion
        try:
            d = json.loads(desc)
        except json.JSONDecodeError:
            d = None
        if isinstance(d, dict) and "axes" in d and "frame_times_s" in d:
            meta = d
    return data, meta


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
        raise ValueError(f"{name}: holds no finite sample (all {n_bad} are NaN or inf); check the file (and "
                         "--dataset / --axes)")
    if n_neg:
        raise ValueError(f"{name}: {n_neg} of {data.size} intensity samples are negative; a linear intensity is >= 0 "
                         "(a dB or background-subtracted image is not one). Fix: store the linear intensity |E|^2, "
                         "e.g. 10**(dB/10), or clip the subtracted background at 0")
    return n_bad


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


def read_sequence(path: str | os.PathLike, *, axes: str | None = None, pitch_um: Mapping[str, float] | str | None = None,
                  frame_times_s: _Seq[float] | None = None, frame_interval_s: float | None = None,
                  system: Mapping[str, Any] | None = None, dataset: str | None = None,
                  block_raster: BlockRaster | None = None, allow_external_hdf5: bool = False) -> SequenceData:
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
    lie in other files; refused by default, :func:`torchdoct.measured.guards.check_hdf5_local`).
    Declared sizes over :func:`torchdoct.measured.guards.max_input_bytes` are refused before reading;
    negative intensities and extended-precision dtypes are refused naming the file, the count and the
    fix; samples that are not finite (NaN, inf) are counted (``nonfinite_samples``) and their pixels are
    masked in the maps (:func:`torchdoct.measured.maps.compute_maps`). A file the system does not let us read raises ``PermissionError``.
    A TIFF stack without axes is taken as ``TZX`` (the COG layout). Missing metadata raise a
    ``ValueError`` naming the key and the option that gives it.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"sequence file {p} does not exist")
    if p.suffix.lower() not in SEQUENCE_SUFFIXES:
        raise ValueError(f"{p.name}: unknown sequence format; use {', '.join(SEQUENCE_SUFFIXES)}")
    suffix = p.suffix.lower()
    with open(p, "rb"):  # a file the system does not let us read: PermissionError (exit 1), whatever the format
        pass
    labels = params = None
    file_meta: dict | None = None
    try:
        if suffix == ".npy":
            data = refuse_object(_load_npy(p), p.name)
        elif suffix == ".npz":
            data, labels, params = _load_npz(p)
        elif suffix == ".h5":
            data, labels, params, file_meta = _load_h5(p, dataset, allow_external_hdf5)
        else:
            data, file_meta = _load_tif(p)
    except PermissionError:  # the system refuses: exit 1 at the command line, as for an unreadable sidecar
        raise
    except (EOFError, OSError, zipfile.BadZipFile, KeyError) as err:
        raise ValueError(f"{p.name}: not a readable {suffix} file (truncated or corrupt: "
                         f"{type(err).__name__}: {err})") from None
    if dataset is not None and suffix != ".h5":
        raise ValueError(f"{p.name}: dataset= applies to .h5 files only")
    side = sidecar_path(p)
    meta: dict[str, Any] = {}
    if file_meta is not None:
        meta.update(file_meta)
    elif side.exists():
        try:
            side_text = side.read_text(encoding="utf-8")
        except UnicodeDecodeError as err:
            raise ValueError(f"{side.name}: the metadata sidecar of {p.name} is not UTF-8 text (byte {err.start}); "
                             "it must be the JSON metadata file (fix it, or remove it and give the metadata as "
                             "options)") from None
        meta.update(parse_json_object(side_text, side.name))
    if suffix in (".tif", ".tiff") and axes is None and "axes" not in meta:
        axes = "TZX"
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
        raise TypeError(f"{p.name}: data dtype {data.dtype} (extended precision) is not supported; convert it to "
                        f"{'complex128' if data.dtype.kind == 'c' else 'float64'} (e.g. a.astype(np."
                        f"{'complex128' if data.dtype.kind == 'c' else 'float64'})) and save again")
    if data.dtype.kind not in "cf":
        if data.dtype.kind in "iu" and suffix in (".tif", ".tiff"):
            data = data.astype(np.float32)
        else:
            raise TypeError(f"{p.name}: data dtype {data.dtype} is neither complex (complex OCT) nor float "
                            "(linear intensity)")
    if data.ndim not in (3, 4):
        raise ValueError(f"{p.name}: data have shape {list(data.shape)}; expected 3 ([T, Z, X]) or 4 ([T, Y, Z, X]) "
                         "dimensions")
    if 0 in data.shape:
        raise ValueError(f"{p.name}: data have an empty axis (shape {list(data.shape)}); nothing to read")
    if not data.dtype.isnative:  # e.g. a big-endian '>c8' .npy: read into native byte order (torch needs it)
        data = data.astype(data.dtype.newbyteorder("="))
    n_nonfinite = _check_values(data, p.name)
    if meta.get("axes") is None:
        raise ValueError(f"{p.name}: missing 'axes'; {_HOW['axes']}")
    stored = _check_axes(meta["axes"], data.ndim, p.name)
    canonical = "TZX" if len(stored) == 3 else "TYZX"
    data = data.transpose([stored.index(c) for c in canonical]) if stored != canonical else data
    meta["axes"] = canonical
    if block_raster is not None:
        if canonical == "TZX":
            data = block_raster.unpack(data)
            meta["axes"] = "TYZX"
        elif data.shape[1] != block_raster.n_y or data.shape[0] != block_raster.n_repeats:
            raise ValueError(f"{p.name}: block raster {block_raster.n_blocks}:{block_raster.n_repeats}:"
                             f"{block_raster.bscans_per_block} does not match [T, Y, Z, X] = {list(data.shape)}")
        meta["block_raster"] = block_raster.to_dict()
    if frame_times_s is not None:
        meta["frame_times_s"] = list(frame_times_s)
    elif frame_interval_s is not None:
        dt = _finite_positive("frame_interval_s (s)", frame_interval_s)
        meta["frame_times_s"] = [i * dt for i in range(data.shape[0])]
    clean = validate_meta(meta, data.shape, where=p.name)
    return SequenceData(data=data, meta=clean, labels=labels, label_params=params, source=p.name,
                        nonfinite_samples=n_nonfinite)

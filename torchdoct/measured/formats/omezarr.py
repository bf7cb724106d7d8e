"""OME-Zarr (NGFF 0.4 on zarr v2, 0.5 on zarr v3) sequences: a ``.zarr`` folder whose multiscales metadata
name the axes and their units; the pitch and the frame interval come from the scale transform of the
full-resolution dataset (``datasets[0]``, times the multiscale's own scale when it has one), the frame
times from it and the ``t`` translation. Only that dataset is read, and chunk by chunk: the sequence is a
:class:`~torchdoct.measured.formats.lazy.LazyArray` that the maps read in slabs.

Orientation (as for OME-TIFF, docs/formats.md): without a ``z`` axis (or with ``z`` of length 1) the
planes are B-scans: ``y`` (rows) is depth z and ``x`` lateral x, ``[t, y, x]`` is read as ``TZX``; with a
``z`` axis, ``z`` is depth and ``[t, z, y, x]`` is read as ``TZYX``. A ``c`` axis must have length 1.
A length or time axis without a unit gives no pitch / times (the options supply them). Integer arrays are
intensities (read as float32, as OME-TIFF pages are). Object arrays
(which a zarr v2 pickle codec would need) are refused before anything is read. The group's attribute
``torchdoct`` (as the maps writer stores it) supplies ``system`` and the other keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...files import check_folder_files
from ..guards import check_declared_size
from .base import LENGTH_UM, TIME_S, Loaded, to_unit
from .lazy import LazyArray, Squeezed

SUFFIXES = (".zarr",)
NAME = "OME-Zarr (NGFF 0.4, 0.5; a .zarr folder)"
DATASET = False
DIRECTORY = True


def multiscale(attrs: dict[str, Any], where: str) -> tuple[str, dict[str, Any]]:
    """The NGFF version and the first multiscale of a group's attributes (0.5: under ``ome``)."""
    if isinstance(attrs.get("ome"), dict) and "multiscales" in attrs["ome"]:
        ome = attrs["ome"]
        version, ms = str(ome.get("version", "0.5")), ome["multiscales"]
    elif "multiscales" in attrs:
        ms = attrs["multiscales"]
        version = str(ms[0].get("version", "")) if isinstance(ms, list) and ms and isinstance(ms[0], dict) else ""
    else:
        raise ValueError(f"{where}: no OME-NGFF 'multiscales' in the group's attributes; not an OME-Zarr image")
    if version not in ("0.4", "0.5"):
        raise ValueError(f"{where}: OME-NGFF version {version!r}; 0.4 and 0.5 are read")
    if not isinstance(ms, list) or not ms or not isinstance(ms[0], dict):
        raise ValueError(f"{where}: 'multiscales' must be a list of objects")
    return version, ms[0]


def _scale(transforms: Any, n: int, kind: str, where: str) -> list[float] | None:
    for t in transforms or []:
        if isinstance(t, dict) and t.get("type") == kind:
            v = t.get(kind)
            if not isinstance(v, list) or len(v) != n:
                raise ValueError(f"{where}: the {kind} transform must list {n} numbers (one per axis); got {v!r}")
            return [float(x) for x in v]
    return None


#: Metadata files of a zarr array folder (the others hold chunks).
_ZARR_METADATA = (".zarray", ".zattrs", ".zgroup", ".zmetadata", "zarr.json")


def check_chunk_files(folder: Path, arr: Any, where: str) -> None:
    """Refuse a store whose chunk files cannot hold their chunk, before any is decompressed: a Blosc chunk
    whose header's compressed size is not the file's (a truncated one: Blosc would decode bytes beyond it
    into numbers), an uncompressed one of another size than the chunk. Other codecs check their own
    streams when they decode."""
    compressors = [type(c).__name__.lower() for c in (getattr(arr, "compressors", None) or ())]
    if getattr(arr, "filters", None) or not folder.is_dir():
        return
    nbytes = int(np.prod(arr.chunks, dtype=np.int64)) * np.dtype(arr.dtype).itemsize
    for f in folder.rglob("*"):
        if f.name in _ZARR_METADATA or not f.is_file():
            continue
        size = f.stat().st_size
        if len(compressors) == 1 and compressors[0].startswith("blosc"):
            with f.open("rb") as fh:
                head = fh.read(16)
            ok = len(head) == 16 and int.from_bytes(head[12:16], "little") == size
            ok = ok and int.from_bytes(head[4:8], "little") == nbytes
        elif not compressors:
            ok = size == nbytes
        else:
            continue
        if not ok:
            raise ValueError(
                f"{where}: chunk {f.relative_to(folder)} holds {size} bytes, not the chunk its header "
                "declares: truncated or corrupt; copy the store again completely"
            )


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    import zarr

    where = path.name
    check_folder_files(path, "OME-Zarr store")  # a FIFO among its files would block zarr's read
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as err:
        raise ValueError(
            f"{where}: not a readable zarr group ({type(err).__name__}); an OME-Zarr image is a folder "
            "holding .zgroup and .zattrs (NGFF 0.4) or zarr.json (0.5): give that folder"
        ) from None
    version, ms = multiscale(dict(group.attrs), where)
    axes = ms.get("axes")
    if not isinstance(axes, list) or not axes:
        raise ValueError(f"{where}: multiscales[0].axes is missing; NGFF {version} needs it")
    names = [str(a.get("name") if isinstance(a, dict) else a).lower() for a in axes]
    units = [a.get("unit") if isinstance(a, dict) else None for a in axes]
    if sorted(set(names)) != sorted(names) or not set(names) <= set("tczyx") or "t" not in names:
        raise ValueError(f"{where}: axes {names}: a sequence needs a 't' axis and names from t, c, z, y, x")
    datasets = ms.get("datasets")
    if not isinstance(datasets, list) or not datasets or not isinstance(datasets[0], dict):
        raise ValueError(f"{where}: multiscales[0].datasets is missing")
    key = str(datasets[0].get("path"))
    try:
        arr = group[key]
    except KeyError:
        raise ValueError(f"{where}: dataset {key!r} named by multiscales is missing from the store") from None
    if not isinstance(arr, zarr.Array) or len(arr.shape) != len(names):  # a group, or other axes
        raise ValueError(f"{where}/{key}: not an array of the {len(names)} axes {names}")
    dt = np.dtype(arr.dtype)
    if dt.hasobject or dt.kind not in "cfiu":
        raise TypeError(
            f"{where}/{key}: dtype {dt} is not numeric (object arrays would need unpickling); store "
            "complex64/complex128 or float data"
        )
    check_declared_size(f"{where}/{key}", arr.shape, dt.itemsize, streamed=True)
    check_chunk_files(path / key, arr, f"{where}/{key}")
    scale = _scale(datasets[0].get("coordinateTransformations"), len(names), "scale", f"{where}/{key}")
    top = _scale(ms.get("coordinateTransformations"), len(names), "scale", where)
    shift = _scale(datasets[0].get("coordinateTransformations"), len(names), "translation", f"{where}/{key}")
    if scale is not None and top is not None:
        scale = [a * b for a, b in zip(scale, top)]
    size = dict(zip(names, arr.shape))
    drop = [i for i, n in enumerate(names) if n == "c" or (n == "z" and size[n] == 1)]
    if size.get("c", 1) != 1:
        raise ValueError(f"{where}: the c axis has {size['c']} channels; a sequence has one")
    volume = "z" in names and size["z"] > 1
    ours = {"t": "T", "z": "Z", "y": "Y", "x": "X"} if volume else {"t": "T", "y": "Z", "x": "X"}
    kept = [i for i in range(len(names)) if i not in drop]
    stored = "".join(ours[names[i]] for i in kept)
    meta: dict[str, Any] = {"axes": stored}
    note = group.attrs.get("torchdoct")
    if isinstance(note, dict):
        meta.update({k: v for k, v in note.items() if k not in ("axes", "pitch_um", "frame_times_s")})
    if scale is not None:
        pitch = {}
        for i in kept:
            n = names[i]
            if n != "t" and units[i]:
                pitch[ours[n].lower()] = to_unit(
                    scale[i], units[i], LENGTH_UM, "micrometer", f"{where}: axis {n} scale"
                )
        if pitch:
            meta["pitch_um"] = pitch
        it = names.index("t")
        if units[it]:
            dt_s = to_unit(scale[it], units[it], TIME_S, "second", f"{where}: axis t scale")
            t0 = (shift[it] if shift is not None else 0.0) * dt_s / scale[it]
            meta["frame_times_s"] = [t0 + k * dt_s for k in range(size["t"])]
    source = Squeezed(arr, tuple(drop)) if drop else arr
    return Loaded(
        data=LazyArray(source, f"{where}/{key}"), meta=meta, sidecar_fills=True, integer_intensity=dt.kind in "iu"
    )

"""HDF5 ``.h5`` sequences, MATLAB v7.3 included: dataset ``data`` (complex, or a MATLAB compound
``{real, imag}``), optional ``labels`` / ``label_params``, the JSON metadata as the root's string attribute
``torchdoct`` (a MATLAB file has none: a sidecar or options give them; ``dataset=`` names its variable
unless it holds only one), beside one attribute per field for HDF5 viewers (:func:`flat_attributes`), which
must agree with it. External storage, external links and virtual datasets whose data lie in
other files are refused unless allowed (:func:`torchdoct.measured.guards.check_hdf5_local`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..guards import check_declared_size, check_hdf5_local, parse_json_object
from .base import Loaded

SUFFIXES = (".h5",)
NAME = "HDF5 .h5 (MATLAB v7.3)"
DATASET = True


def flat_attributes(meta: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """One HDF5 attribute per metadata field (nested tables as ``table.key``): strings, numbers and lists of
    numbers; what is neither (None, lists of tables) is left to the JSON attribute ``torchdoct``."""
    out: dict[str, Any] = {}
    for key, value in meta.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flat_attributes(value, f"{name}."))
        elif isinstance(value, (str, int, float)) and not isinstance(value, bool):
            out[name] = value
        elif isinstance(value, bool):
            out[name] = np.bool_(value)
        elif (
            isinstance(value, (list, tuple))
            and value
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        ):
            out[name] = np.asarray(value, dtype=np.float64)
    return out


def check_flat_attributes(attrs: Any, meta: Mapping[str, Any], where: str) -> None:
    """Every per-field attribute (:func:`flat_attributes`) the file holds must agree with the JSON attribute
    ``torchdoct`` that is read: one edited in an HDF5 viewer and not the other is a ``ValueError`` naming the
    attribute, both values and the fix (instead of the edit being ignored without a word)."""
    for key, want in flat_attributes(meta).items():
        if key not in attrs:
            continue
        got = attrs[key]
        got = got.decode("utf-8", "replace") if isinstance(got, bytes) else got
        same = (
            (got == want)
            if isinstance(want, str)
            else (np.shape(got) == np.shape(want) and bool(np.all(np.asarray(got, dtype=np.float64) == want)))
        )
        if not same:
            raise ValueError(
                f"{where}: attribute {key!r} = {got!r} disagrees with the JSON attribute 'torchdoct' "
                f"({want!r}), which is what is read; edit both to the same value, or delete {key!r}"
            )


def read_dataset(ds: Any, where: str) -> np.ndarray:
    """One HDF5 dataset as numpy, its declared size checked before it is read (and decompressed); a
    MATLAB v7.3 complex compound becomes a complex array, a string dataset a ``str`` array."""
    dt = ds.dtype
    check_declared_size(where, ds.shape or (), dt.itemsize, what="dataset")  # before reading (and decompressing)
    if dt.names is not None:
        names = {n.lower(): n for n in dt.names}
        if set(names) != {"real", "imag"}:
            raise ValueError(
                f"{where}: compound dataset with fields {dt.names}; expected MATLAB v7.3 complex {{real, imag}}"
            )
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


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    import h5py

    try:
        fh = h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path.name}: not a readable HDF5 / MATLAB v7.3 file ({err})") from None
    with fh:
        check_hdf5_local(fh, path, allow_external_hdf5)  # before any link is followed or any data read

        def resolved(k: str):  # None for a dangling soft link or one into a loop: only the one asked for is named
            try:
                return fh.get(k)
            except (KeyError, RuntimeError, OSError, ValueError):
                return None

        names = [k for k in fh.keys() if not k.startswith("#") and isinstance(resolved(k), h5py.Dataset)]
        if dataset is None:
            if "data" in names or "data" in fh.keys():  # a 'data' link to nothing is named below
                dataset = "data"
            else:
                cands = [n for n in names if n not in ("labels", "label_params")]
                if len(cands) != 1:
                    raise ValueError(
                        f"{path.name}: no dataset 'data' and {len(cands)} candidate datasets "
                        f"({', '.join(cands) or 'none'}); name one with --dataset"
                    )
                dataset = cands[0]
        if dataset in fh.keys() and resolved(dataset) is None:
            link = fh.get(dataset, getlink=True)
            raise ValueError(
                f"{path.name}: dataset {dataset!r} is a link that leads to no dataset ("
                f"{type(link).__name__} to {getattr(link, 'path', '?')!r}: dangling or a loop); "
                "write the data into the file, or name another dataset with --dataset"
            )
        if dataset not in fh or not isinstance(fh[dataset], h5py.Dataset):
            raise ValueError(f"{path.name}: no dataset {dataset!r} (datasets: {', '.join(names) or 'none'})")
        data = read_dataset(fh[dataset], f"{path.name}:{dataset}")
        labels = read_dataset(fh["labels"], f"{path.name}:labels") if "labels" in names else None
        params = read_dataset(fh["label_params"], f"{path.name}:label_params") if "label_params" in names else None
        meta = None
        if "torchdoct" in fh.attrs:
            raw = fh.attrs["torchdoct"]
            if isinstance(raw, bytes):
                try:
                    raw = raw.decode("utf-8")
                except UnicodeDecodeError as err:
                    raise ValueError(
                        f"{path.name}: attribute 'torchdoct' is not UTF-8 text (byte {err.start}); it "
                        "must hold the JSON metadata (write the file again)"
                    ) from None
            meta = parse_json_object(str(raw), f"{path.name} attribute 'torchdoct'")
            check_flat_attributes(fh.attrs, meta, path.name)
    return Loaded(data=data, labels=labels, label_params=params, meta=meta)

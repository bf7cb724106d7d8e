"""MATLAB ``.mat`` sequences. Version 5 files are read with :func:`scipy.io.loadmat` (``dataset=`` names the
variable unless the file holds only one numeric array); a v7.3 file is HDF5 and goes to
:mod:`torchdoct.measured.formats.hdf5`. The metadata come from the sidecar or the options.

Axis order: ``loadmat`` keeps MATLAB's index order, so a MATLAB ``E(z, x, t)`` array is ``--axes ZXT``
(a v7.3 file, read through HDF5, stores it reversed: ``TXZ``). Nothing is unpickled: cell arrays,
structs and objects are refused. The declared size (the variable's dimensions from the file's header,
counted as complex, the largest it can be) is checked before the variable is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..guards import check_declared_size
from . import hdf5
from .base import Loaded

SUFFIXES = (".mat",)
NAME = "MATLAB .mat (v5 via scipy.io; v7.3 via HDF5)"
DATASET = True

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: bytes per element of a MATLAB class (a complex variable takes twice this)
_CLASS_BYTES = {
    "double": 8,
    "single": 4,
    "int8": 1,
    "uint8": 1,
    "int16": 2,
    "uint16": 2,
    "int32": 4,
    "uint32": 4,
    "int64": 8,
    "uint64": 8,
    "logical": 1,
    "char": 4,
}


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    with open(path, "rb") as fh:
        head = fh.read(520)
    if head[512:520] == _HDF5_MAGIC:  # v7.3: an HDF5 file with a 512-byte MATLAB header
        return hdf5.load(path, dataset=dataset, allow_external_hdf5=allow_external_hdf5)
    if len(head) < 128:
        raise ValueError(
            f"{path.name}: truncated: {len(head)} bytes, shorter than a MATLAB file header (128); "
            "copy or save the file again completely"
        )
    import scipy.io as sio

    try:
        found = sio.whosmat(path)
    except Exception as err:  # scipy raises many types on damaged files
        raise ValueError(
            f"{path.name}: not a readable MATLAB v5 file ({type(err).__name__}: {err}); save it "
            "again in MATLAB with save(..., '-v7') or '-v7.3'"
        ) from None
    numeric = [(n, s, c) for n, s, c in found if c in _CLASS_BYTES and c not in ("char", "logical")]
    if dataset is None:
        if len(numeric) != 1:
            names = ", ".join(f"{n} ({c} {list(s)})" for n, s, c in found) or "none"
            raise ValueError(
                f"{path.name}: {len(numeric)} numeric variables (variables: {names}); name one with --dataset"
            )
        dataset = numeric[0][0]
    entry = next((e for e in found if e[0] == dataset), None)
    if entry is None:
        raise ValueError(
            f"{path.name}: no variable {dataset!r} (variables: {', '.join(n for n, _, _ in found) or 'none'})"
        )
    name, shape, mclass = entry
    if mclass not in _CLASS_BYTES:
        raise ValueError(
            f"{path.name}:{name}: a MATLAB {mclass} (cell, struct or object) is not a numeric array; "
            "store the sequence as a numeric (complex single/double) array"
        )
    check_declared_size(f"{path.name}:{name}", shape, 2 * _CLASS_BYTES[mclass], what="variable")
    try:
        arr = sio.loadmat(
            path,
            variable_names=[name],
            squeeze_me=False,
            mat_dtype=False,
            chars_as_strings=False,
            struct_as_record=True,
        )[name]
    except Exception as err:
        raise ValueError(
            f"{path.name}:{name}: the variable is truncated or corrupt ({type(err).__name__}: {err}); "
            "copy or save the file again completely"
        ) from None
    arr = np.asarray(arr)
    if arr.dtype.hasobject:
        raise ValueError(f"{path.name}:{name}: holds MATLAB cells or objects; store a numeric array")
    return Loaded(data=arr)

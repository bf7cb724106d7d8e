"""The sequence readers, one module per format, behind one dispatch by suffix (numpy only, no torch).

Each format module holds ``SUFFIXES`` (the lower-case suffixes it reads), ``NAME`` (shown in errors and
docs), ``DATASET`` (whether ``dataset=`` names a variable in it) and ``load(path, dataset=None,
allow_external_hdf5=False) -> Loaded``: the stored array (not yet transposed, checked for its declared
size before anything is read, nothing unpickled), optional labels, and the metadata the file itself
carries. :func:`torchdoct.measured.io.read_sequence` then applies the rules every format shares (the
sidecar, the keyword overrides, the dtype and value checks, the axes, :func:`validate_meta`) and returns
one :class:`~torchdoct.measured.sequence.SequenceData` whatever the format.

A module reading a folder has ``DIRECTORY = True``. To add a format: a module here with those names,
listed in :data:`FORMATS`. See docs/formats.md.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

from . import hdf5, matlab, npy, npz, ometiff, omezarr, raw, tiff, tifffolder
from .base import Loaded

__all__ = ["Loaded", "FORMATS", "SEQUENCE_SUFFIXES", "reader_for"]


#: The format modules, in the order their suffixes are tried (longest suffix first within a module).
FORMATS: tuple[ModuleType, ...] = (npy, npz, hdf5, tiff, matlab, raw, ometiff, omezarr)

SEQUENCE_SUFFIXES: tuple[str, ...] = tuple(s for m in FORMATS for s in m.SUFFIXES)


def reader_for(path: str | os.PathLike) -> ModuleType | None:
    """The format module that reads ``path`` (by its longest matching suffix, case-insensitive; a folder
    named by no file format's suffix is a folder of per-frame TIFFs; a folder named like a file, such as
    ``x.npy/``, gets that file's reader, whose regular-file check refuses it), or None."""
    p = Path(path)
    name = p.name.lower()
    best: tuple[int, ModuleType] | None = None
    for module in FORMATS:
        for suffix in module.SUFFIXES:
            if name.endswith(suffix) and (best is None or len(suffix) > best[0]):
                best = (len(suffix), module)
    if best is None and p.is_dir():
        return tifffolder
    return None if best is None else best[1]

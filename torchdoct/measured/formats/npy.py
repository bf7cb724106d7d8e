"""NumPy ``.npy`` sequences (metadata in the JSON sidecar), memory-mapped, never unpickled."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..guards import check_npy_header, check_npy_size, refuse_object
from .base import Loaded

SUFFIXES = (".npy",)
NAME = "NumPy .npy (+ .json sidecar)"
DATASET = False


def load_array(path: Path) -> np.ndarray:
    """The array of a ``.npy`` file, memory-mapped read-only, after its header's checks (NPY magic,
    declared size within the input limit, file long enough to hold it; a memory map can be read slab by
    slab: :func:`~torchdoct.measured.guards.streaming_reads`)."""
    check_npy_header(path)
    check_npy_size(path, streamed=True)
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as err:
        if "pickle" in str(err).lower() or "object" in str(err).lower():
            raise ValueError(
                f"{path.name}: holds an object array, which would need unpickling; refused "
                "(store a complex64/complex128 array)"
            ) from None
        raise ValueError(f"{path.name}: not a readable .npy file ({err})") from None


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    return Loaded(data=refuse_object(load_array(path), path.name))

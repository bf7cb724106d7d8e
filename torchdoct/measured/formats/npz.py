"""NumPy ``.npz`` sequences: key ``data``, optional ``labels`` / ``label_params``; metadata in the sidecar."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import Loaded
from ..guards import check_npz_sizes, refuse_object

SUFFIXES = (".npz",)
NAME = "NumPy .npz (+ .json sidecar)"
DATASET = False


def load_arrays(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``data``, ``labels``, ``label_params`` of a ``.npz`` (the last two None when absent), each member's
    declared size checked before anything is decompressed; object arrays refused."""
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


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    data, labels, params = load_arrays(path)
    return Loaded(data=data, labels=labels, label_params=params)

"""NumPy ``.npz`` sequences: key ``data``, optional ``labels`` / ``label_params``; the metadata in the JSON
sidecar, else in the archive's own ``meta_json`` (a 0-d string array, as :func:`torchdoct.measured.io.write_sequence`
writes beside the sidecar, so the archive carries its metadata when it travels alone)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..guards import check_npz_sizes, parse_json_object, refuse_object
from ..sequence import sidecar_exists, sidecar_path
from .base import Loaded

SUFFIXES = (".npz",)
NAME = "NumPy .npz (+ .json sidecar)"
DATASET = False


def load_arrays(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """``data``, ``labels``, ``label_params``, ``meta_json`` of a ``.npz`` (None when absent), each member's
    declared size checked before anything is decompressed; object arrays refused."""
    check_npz_sizes(path)  # declared sizes, before anything is decompressed
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # our handle: closed on errors too
            if "data" not in z.files:
                raise ValueError(
                    f"{path.name}: no array 'data' (arrays: {', '.join(z.files) or 'none'}); "
                    "store the sequence under the key 'data'"
                )
            out = []
            for key in ("data", "labels", "label_params", "meta_json"):
                out.append(refuse_object(z[key], f"{path.name}[{key}]") if key in z.files else None)
    except ValueError as err:
        if "pickle" in str(err).lower() or "object" in str(err).lower():
            raise ValueError(f"{path.name}: holds an object array, which would need unpickling; refused") from None
        if "EOF" in str(err) or "reading array data" in str(err):
            raise ValueError(
                f"{path.name}: an array is truncated ({err}); copy or write the file again completely"
            ) from None
        raise
    data = out[0]
    assert data is not None  # 'data' is in the archive (refused above otherwise)
    return data, out[1], out[2], out[3]


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    data, labels, params, raw = load_arrays(path)
    meta = None
    if raw is not None and not sidecar_exists(sidecar_path(path)):  # the sidecar, when there is one, is read instead
        if raw.dtype.kind not in "US" or raw.size != 1:
            raise ValueError(
                f"{path.name}: 'meta_json' must be a JSON text (a 0-d string array); got a {raw.dtype} "
                f"array of shape {list(raw.shape)}"
            )
        meta = parse_json_object(str(raw.reshape(())), f"{path.name}: 'meta_json'")
    return Loaded(data=data, labels=labels, label_params=params, meta=meta)

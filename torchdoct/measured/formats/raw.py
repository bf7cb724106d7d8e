"""Raw binary sequences (``.raw``, ``.bin``): the samples with no structure of their own, described by the
JSON sidecar ``NAME.json``. Besides the metadata keys (``axes``, ``pitch_um``, ``frame_times_s``,
``system``) the sidecar declares the layout::

    {"dtype": "complex64", "shape": [T, Z, X], "byte_order": "little", "header_bytes": 0, ...}

``dtype``: ``complex64``, ``complex128``, ``float32``, ``float64`` (a linear intensity, or dB with
``--scale db``), or ``uint8`` / ``uint16`` (integer intensity, read as float32); ``shape`` in the stored
order that ``axes`` names (C order: the last axis varies fastest); ``byte_order`` ``little`` or ``big``
(default ``little``); ``header_bytes``: bytes before the first sample (default 0). The file must hold
exactly ``header_bytes + prod(shape)·itemsize`` bytes: a shorter one is truncated, a longer one declares
the wrong shape; both are refused. The samples are memory-mapped, never read whole.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..guards import check_declared_size, parse_json_object
from ..sequence import sidecar_exists, sidecar_path
from .base import Loaded

SUFFIXES = (".raw", ".bin")
NAME = "raw binary (.raw, .bin) + JSON sidecar with dtype, shape, byte_order, header_bytes"
DATASET = False

LAYOUT_KEYS = ("dtype", "shape", "byte_order", "header_bytes")
DTYPES = ("complex64", "complex128", "float32", "float64", "uint8", "uint16")


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    from ...files import read_capped

    side = sidecar_path(path)
    if not sidecar_exists(side):
        raise ValueError(
            f"{path.name}: a raw binary needs its JSON sidecar {side.name} declaring dtype, shape "
            "(and byte_order, header_bytes); write one beside it (a name short enough that the "
            "sidecar's is legal too)"
        )
    try:
        text = read_capped(side, f"the sidecar of {path.name}").decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{side.name}: the sidecar of {path.name} is not UTF-8 text (byte {err.start})") from None
    meta = parse_json_object(text, side.name)
    where = f"{side.name}"
    missing = [k for k in ("dtype", "shape") if k not in meta]
    if missing:
        raise ValueError(
            f"{where}: missing {', '.join(repr(k) for k in missing)} for the raw binary {path.name}; "
            f'e.g. "dtype": "complex64", "shape": [T, Z, X]'
        )
    dtype = meta.pop("dtype")
    if dtype not in DTYPES:
        raise TypeError(f"{where}: dtype {dtype!r} is not supported; use one of {', '.join(DTYPES)}")
    order = meta.pop("byte_order", "little")
    if order not in ("little", "big"):
        raise ValueError(f"{where}: byte_order must be 'little' or 'big'; got {order!r}")
    shape = meta.pop("shape")
    if (
        not isinstance(shape, list)
        or not shape
        or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)
    ):
        raise ValueError(f"{where}: shape must be a list of positive integers such as [T, Z, X]; got {shape!r}")
    header = meta.pop("header_bytes", 0)
    if isinstance(header, bool) or not isinstance(header, int) or header < 0:
        raise ValueError(f"{where}: header_bytes must be an integer >= 0; got {header!r}")
    dt = np.dtype(dtype).newbyteorder("<" if order == "little" else ">")
    n = check_declared_size(f"{path.name} (shape from {side.name})", shape, dt.itemsize, streamed=True)
    have = os.stat(path).st_size
    if have < header + n:
        raise ValueError(
            f"{path.name}: truncated: {side.name} declares {shape} {dtype} after {header} header bytes "
            f"({header + n} bytes) but the file holds {have}; copy the file again completely, or fix "
            "shape / header_bytes"
        )
    if have > header + n:
        raise ValueError(
            f"{path.name}: holds {have - header - n} bytes more than {side.name} declares ({shape} "
            f"{dtype} after {header} header bytes); fix shape, dtype or header_bytes"
        )
    data = np.memmap(path, dtype=dt, mode="r", offset=header, shape=tuple(shape))
    return Loaded(data=data, meta=meta, integer_intensity=dtype.startswith("uint"))

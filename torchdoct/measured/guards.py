"""The safe-opening guards of every reader of the project's files (numpy only, no torch).

One set of rules for sequences (:mod:`torchdoct.measured.io`), maps (:mod:`torchdoct.measured.mapsfile`),
masks (``torchdoct compare --mask``) and the classifier's maps: nothing is unpickled (object arrays and
pickle streams are refused, naming the file), a ``.npy`` must carry the NPY header, a JSON text must be
an object, and a damaged TIFF, which tifffile only logs before reading what it can reach, is an error.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

__all__ = ["TiffDamage", "check_npy_header", "refuse_object", "parse_json_object"]


class TiffDamage:
    """Turns what tifffile only logs about a damaged file (a broken page table: it then reads the pages it
    can reach, e.g. one page of a truncated stack) into a ``ValueError`` after the read.

    Use around the read and call :meth:`check` before leaving::

        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            data = tf.asarray()
            damage.check()
    """

    def __enter__(self) -> "TiffDamage":
        class _Collect(logging.Handler):
            def __init__(self):
                super().__init__(logging.ERROR)
                self.messages: list[str] = []

            def emit(self, record):
                self.messages.append(record.getMessage())

        self.log, self.handler = logging.getLogger("tifffile"), _Collect()
        self.propagate, self.log.propagate = self.log.propagate, False
        self.log.addHandler(self.handler)
        return self

    def check(self) -> None:
        """Raise ``ValueError`` (the logged messages) when tifffile logged an error since ``__enter__``."""
        if self.handler.messages:
            raise ValueError("; ".join(self.handler.messages))

    def __exit__(self, *exc) -> bool:
        self.log.removeHandler(self.handler)
        self.log.propagate = self.propagate
        return False


def refuse_object(arr: np.ndarray, where: str) -> np.ndarray:
    """``arr`` unless it holds Python objects (which would need unpickling): then a ``ValueError``."""
    if arr.dtype.hasobject:
        raise ValueError(f"{where}: object arrays are refused (they would need unpickling); store a numeric array")
    return arr


def check_npy_header(path: Path, what: str = "") -> None:
    """A ``.npy`` file must start with the NPY magic; anything else (a pickle, another format, random
    bytes) is refused naming the file, before numpy would take it for a pickle."""
    with open(path, "rb") as fh:
        head = fh.read(6)
    if head != b"\x93NUMPY":
        raise ValueError(f"{what}{path.name}: not a NumPy .npy file (no NPY header: "
                         f"{'empty' if not head else 'a pickle or another format'}); write it with numpy.save")


def parse_json_object(text: str, where: str) -> dict:
    """The JSON object in ``text``; invalid JSON or another JSON type is a ``ValueError`` naming ``where``."""
    from .._files import check_nesting

    check_nesting(text, where)  # before the parser's recursion
    try:
        d = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: invalid JSON ({err})") from None
    if not isinstance(d, dict):
        raise ValueError(f"{where}: metadata JSON must be an object {{...}}; got {type(d).__name__} {text[:40]!r}")
    return d

"""The safe-opening guards of every reader of the project's files (numpy only, no torch).

One set of rules for sequences (:mod:`torchdoct.measured.io`), maps (:mod:`torchdoct.measured.mapsfile`),
masks (``torchdoct compare --mask``) and the classifier's maps: nothing is unpickled (object arrays and
pickle streams are refused, naming the file), a ``.npy`` must carry the NPY header, a JSON text must be
an object, and a damaged TIFF, which tifffile only logs before reading what it can reach, is an error.

Bounded sizes: every reader checks the size an array declares (a ``.npy`` header's shape × itemsize, each
``.npz`` member's header, an HDF5 dataset's shape × dtype, a TIFF's pages × page shape × dtype) against
:func:`max_input_bytes` *before* allocating it, so a small file that declares or decompresses to a huge
array (a zip bomb) is one clear error. The limit is 8 GiB unless the environment variable
``TORCHDOCT_MAX_INPUT_GB`` or the option ``--max-input-gb`` (which calls :func:`set_max_input_gb`) says
otherwise. Within :func:`streaming_reads` (``torchdoct maps --max-memory-gb``) an array read slab by slab
is bound only by an explicit limit.

Safe HDF5 (:func:`check_hdf5_local`): a dataset with external storage, an external link or a virtual
dataset whose sources lie in another file would make any file the user can read into "data"; they are
refused unless the caller allows them explicitly (``allow_external=True``, ``--allow-external-hdf5``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

import numpy as np

__all__ = [
    "TiffDamage",
    "check_npy_header",
    "refuse_object",
    "parse_json_object",
    "json_loads",
    "MAX_INPUT_ENV",
    "DEFAULT_MAX_INPUT_GB",
    "max_input_bytes",
    "set_max_input_gb",
    "check_declared_size",
    "check_npy_size",
    "check_npz_sizes",
    "check_tiff_pages",
    "check_hdf5_local",
    "check_memory_budget",
    "streaming_reads",
    "streaming",
    "npy_header",
]

MAX_INPUT_ENV = "TORCHDOCT_MAX_INPUT_GB"
DEFAULT_MAX_INPUT_GB = 8.0
_GIB = 1 << 30
_max_input_gb: float | None = None  # set by --max-input-gb


def set_max_input_gb(gb: float | None) -> None:
    """Set (or with ``None`` clear) the limit on one input array's declared size in GiB, over the
    environment variable ``TORCHDOCT_MAX_INPUT_GB`` and the 8 GiB default."""
    global _max_input_gb
    if gb is not None and not (isinstance(gb, (int, float)) and math.isfinite(gb) and gb > 0):
        raise ValueError(f"--max-input-gb must be a positive number of GiB; got {gb!r}")
    _max_input_gb = None if gb is None else float(gb)


def max_input_bytes() -> int:
    """The largest array (bytes) a reader allocates: ``--max-input-gb``, else ``TORCHDOCT_MAX_INPUT_GB``,
    else 8 GiB."""
    gb = _max_input_gb
    if gb is None:
        raw = os.environ.get(MAX_INPUT_ENV, "").strip()
        if raw:
            try:
                gb = float(raw)
            except ValueError:
                gb = math.nan
            if not (math.isfinite(gb) and gb > 0):
                raise ValueError(f"environment variable {MAX_INPUT_ENV}={raw!r} must be a positive number of GiB")
        else:
            gb = DEFAULT_MAX_INPUT_GB
    return int(gb * _GIB)


def _human(n: int) -> str:
    for unit, size in (("TiB", 1 << 40), ("GiB", _GIB), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n} bytes"


_streaming = False  # set by streaming_reads(): arrays read slab by slab are not held whole


def _explicit_limit() -> bool:
    return _max_input_gb is not None or os.environ.get(MAX_INPUT_ENV, "").strip() != ""


@contextlib.contextmanager
def streaming_reads(on: bool = True):
    """Within it (``torchdoct maps --max-memory-gb``), an array a reader hands over to be read slab by slab
    (``check_declared_size(..., streamed=True)``: a memory-mapped ``.npy`` or raw binary, an OME-Zarr) is
    never held whole, so neither the default input limit nor the memory budget applies to it; an explicit
    limit (``--max-input-gb``, ``TORCHDOCT_MAX_INPUT_GB``) still does."""
    global _streaming
    before, _streaming = _streaming, bool(on)
    try:
        yield
    finally:
        _streaming = before


def streaming() -> bool:
    """Whether the reader runs within :func:`streaming_reads` (so it may hand over an array read slab by slab)."""
    return _streaming


class InputRefusal(ValueError):
    """A refusal whose message is whole (a declared size over the limit, TIFF pages of two shapes): a reader
    that wraps the errors of a damaged file in "not a readable …" passes it on as it is."""


def check_declared_size(
    where: str, shape: Iterable[int], itemsize: int, what: str = "array", streamed: bool = False
) -> int:
    """The byte count ``prod(shape) * itemsize`` (exact integers: no overflow), or a ``ValueError`` naming
    ``where``, the size and the option / environment variable that raises the limit when over it.
    ``streamed``: the caller reads the array slab by slab; within :func:`streaming_reads` only an explicit
    limit applies to it."""
    n = int(itemsize)
    dims = [int(d) for d in shape]
    for d in dims:
        n *= d
    if streamed and _streaming and not _explicit_limit():
        return n
    limit = max_input_bytes()
    if n > limit:
        raise InputRefusal(
            f"{where}: the {what} declares shape {dims} and would take {_human(n)} in memory, over "
            f"the input limit of {_human(limit)}; if the data really are this large, "
            + (
                "stream them through the maps with --max-memory-gb GB (torchdoct maps), or "
                if streamed and not _explicit_limit()
                else ""
            )
            + f"raise the limit with --max-input-gb GB or the environment variable {MAX_INPUT_ENV}=GB"
        )
    check_memory_budget(where, n, f"the {what} declares shape {dims}")
    return n


def check_memory_budget(where: str, n: int, what: str) -> None:
    """Refuse reading ``n`` bytes that do not fit the memory budget
    (:func:`torchdoct.runtime.resources.memory_budget`: ``MemAvailable``, ``RLIMIT_AS``, the cgroup limit) with a
    :class:`torchdoct.runtime.resources.MemoryLimitError` (a ``ValueError``) naming ``where``, ``what`` it holds,
    the budget, what sets it and the fix, before the read would fail half-way (and be taken for a
    truncated file). An explicit input limit (``--max-input-gb``, ``TORCHDOCT_MAX_INPUT_GB``) overrides
    the machine's estimate ``MemAvailable``, never a hard limit."""
    from ..runtime.resources import MemoryLimitError, memory_budget

    budget = memory_budget()
    if budget is None or n <= budget.bytes:
        return
    if _explicit_limit() and not budget.hard:
        return
    fix = (
        "read a smaller crop of it (fewer frames, B-scans or pixels), or give it as chunked input (HDF5 or "
        "Zarr chunks, read slab by slab)"
    )
    fix += (
        ", or raise that limit (ulimit -v, the container's memory limit)"
        if budget.hard
        else ", or free memory; if you know the memory is there, --max-input-gb GB reads it anyway"
    )
    raise MemoryLimitError(
        f"{where}: not enough memory for the file: {what} ({_human(n)}) but the memory budget "
        f"is {_human(budget.bytes)} ({budget.source}); {fix}"
    )


def npy_header(path: Path, where: str) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype a ``.npy`` file declares, read from its header alone (the NPY magic checked first:
    :func:`check_npy_header`), so that a caller can refuse them before a byte of data is read."""
    check_npy_header(path)
    with open(path, "rb") as fh:
        return _npy_header(fh, where)


def _npy_header(fh, where: str) -> tuple[tuple[int, ...], np.dtype]:
    from numpy.lib import format as npf

    try:
        version = npf.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npf.read_array_header_1_0(fh, max_header_size=1 << 20)
        else:
            shape, _, dtype = npf.read_array_header_2_0(fh, max_header_size=1 << 20)
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(f"{where}: not a readable .npy header ({err}); write it again with numpy.save") from None
    return shape, dtype


def check_npy_size(path: Path, what: str = "", streamed: bool = False) -> None:
    """A ``.npy`` file's declared array within :func:`max_input_bytes` (``streamed``: see
    :func:`check_declared_size`), and the file long enough to hold it (a truncated array is named as such,
    with the fix)."""
    with open(path, "rb") as fh:
        shape, dtype = _npy_header(fh, f"{what}{path.name}")
        n = check_declared_size(f"{what}{path.name}", shape, dtype.itemsize, streamed=streamed)
        have = os.fstat(fh.fileno()).st_size - fh.tell()
    if not dtype.hasobject and have < n:
        raise ValueError(
            f"{what}{path.name}: truncated: the header declares {list(shape)} {dtype} ({n} bytes of "
            f"data) but the file holds {have}; copy or write the file again completely"
        )


def check_npz_sizes(path: Path, what: str = "") -> None:
    """Every ``.npy`` member of a ``.npz`` archive within :func:`max_input_bytes`, read from its header
    before anything is decompressed beyond it (a zip bomb declares its size there: numpy reads exactly that)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as fh:
                    head = fh.read(6)
                    if head != b"\x93NUMPY":
                        continue  # numpy's own reader names what it is
                    fh.seek(0)
                    shape, dtype = _npy_header(fh, f"{what}{path.name}[{info.filename[:-4]}]")
                check_declared_size(f"{what}{path.name}[{info.filename[:-4]}]", shape, dtype.itemsize)
    except zipfile.BadZipFile:
        return  # the caller's reader reports the damaged archive


def check_tiff_pages(path: Path, tf: Any, what: str = "", streamed: bool = False) -> None:
    """A TIFF's pages all of one shape and dtype (mixed pages are refused naming the first page that
    differs, instead of reading some and dropping the rest) and their total within :func:`max_input_bytes`
    (``streamed``: :func:`check_declared_size`)."""
    pages = tf.pages
    n = len(pages)
    if n == 0:
        return
    first = pages[0]
    shape0, dtype0 = tuple(first.shape), first.dtype
    for i in range(1, n):
        page = pages[i]
        if tuple(page.shape) != shape0 or page.dtype != dtype0:
            raise InputRefusal(
                f"{what}{path.name}: TIFF pages of two shapes: page 0 is {list(shape0)} {dtype0}, page "
                f"{i} is {list(page.shape)} {page.dtype}; a stack needs one shape on every page (write "
                "the frames as one stack of equal images)"
            )
    itemsize = dtype0.itemsize if dtype0 is not None else 1
    check_declared_size(f"{what}{path.name}", (n, *shape0), itemsize, what=f"TIFF stack ({n} pages)", streamed=streamed)


def check_hdf5_local(fh: Any, path: Path, allow_external: bool = False) -> None:
    """Refuse external links, datasets with external storage and virtual datasets with sources in another
    file anywhere in the open HDF5 file ``fh`` (walked without following any external link), unless
    ``allow_external``."""
    import h5py

    fix = (
        "if you trust the file and want those files read, give --allow-external-hdf5 (read_sequence: "
        "allow_external_hdf5=True); otherwise copy the data into the file (e.g. h5repack)"
    )
    seen: set = set()

    def walk(group: Any, prefix: str, depth: int) -> None:
        if depth > 64:
            raise ValueError(
                f"{path.name}: HDF5 groups nested over 64 levels at {prefix[:80] or '/'}…; copy the dataset "
                "into a file of its own (h5py: dst['data'] = src['data'][()])"
            )
        for name in group.keys():
            full = f"{prefix}/{name}"
            link = group.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                if not allow_external:
                    raise ValueError(
                        f"{path.name}: {full} is an external link to {link.filename}:{link.path} "
                        f"outside the input file; refused ({fix})"
                    )
                continue
            try:
                obj = group.get(name)
            except (KeyError, RuntimeError, OSError, ValueError):  # a soft link to itself or into a loop
                obj = None
            if obj is None:  # a dangling soft link: it is named only if it is the dataset asked for
                continue
            if isinstance(obj, h5py.Group):
                if obj.id in seen:  # a hard-link cycle
                    continue
                seen.add(obj.id)
                walk(obj, full, depth + 1)
            elif isinstance(obj, h5py.Dataset):
                if obj.external and not allow_external:
                    files = ", ".join(sorted({str(e[0]) for e in obj.external}))
                    raise ValueError(
                        f"{path.name}: dataset {full} stores its data in external file(s) {files} "
                        f"outside the input file; refused ({fix})"
                    )
                if obj.is_virtual and not allow_external:
                    others = sorted(
                        {
                            vs.file_name
                            for vs in obj.virtual_sources()
                            if vs.file_name not in (".", str(path), os.path.basename(str(path)))
                        }
                    )
                    if others:
                        raise ValueError(
                            f"{path.name}: virtual dataset {full} takes its data from "
                            f"{', '.join(others)} outside the input file; refused ({fix})"
                        )

    walk(fh, "", 0)


class TiffDamage:
    """Turns what tifffile only logs about a damaged file (a broken page table: it then reads the pages it
    can reach, e.g. one page of a truncated stack) into a ``ValueError`` after the read.

    Use around the read and call :meth:`check` before leaving::

        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            data = tf.asarray()
            damage.check()
    """

    def __enter__(self) -> TiffDamage:
        class _Collect(logging.Handler):
            def __init__(self) -> None:
                super().__init__(logging.ERROR)
                self.messages: list[str] = []

            def emit(self, record: logging.LogRecord) -> None:
                self.messages.append(record.getMessage())

        self.log, self.handler = logging.getLogger("tifffile"), _Collect()
        self.propagate, self.log.propagate = self.log.propagate, False
        self.log.addHandler(self.handler)
        return self

    def check(self) -> None:
        """Raise ``ValueError`` (the logged messages) when tifffile logged an error since ``__enter__``."""
        if self.handler.messages:
            raise ValueError("; ".join(self.handler.messages))

    def __exit__(self, *exc) -> Literal[False]:
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
        raise ValueError(
            f"{what}{path.name}: not a NumPy .npy file (no NPY header: "
            f"{'empty' if not head else 'a pickle or another format'}); write it with numpy.save"
        )


#: Digits of the longest JSON integer read as an integer: a longer one (a 100,000-digit number, which
#: Python refuses to convert at all) is read as a float, i.e. inf, and refused by the field's own check.
MAX_INT_DIGITS = 300


def _parse_int(text: str):
    return int(text) if len(text) <= MAX_INT_DIGITS else float(text)


def json_loads(text: str | bytes) -> Any:
    """``json.loads`` with integers of more than :data:`MAX_INT_DIGITS` digits read as floats (inf), so that
    the field that holds one names it instead of Python's digit limit failing the whole parse."""
    return json.loads(text, parse_int=_parse_int)


def parse_json_object(text: str, where: str) -> dict:
    """The JSON object in ``text``; invalid JSON or another JSON type is a ``ValueError`` naming ``where``."""
    from ..files import check_nesting

    check_nesting(text, where)  # before the parser's recursion
    try:
        d = json_loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: invalid JSON ({err})") from None
    if not isinstance(d, dict):
        raise ValueError(f"{where}: metadata JSON must be an object {{...}}; got {type(d).__name__} {text[:40]!r}")
    return d

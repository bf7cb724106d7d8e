"""A read-only array read on demand, slab by slab (:class:`LazyArray`): what a chunked store (OME-Zarr)
hands to the maps, which read it in slabs (:func:`torchdoct.measured.maps.compute_maps`) so the whole
sequence is never in memory. It supports what the readers and the slab loop use: ``shape``, ``dtype``,
``ndim``, ``size``, ``transpose``, ``astype`` (converted as it is read), basic indexing (integers and slices)
and iteration over the first axis."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["LazyArray", "Squeezed"]


class LazyArray:
    """``source[...]`` (any object with ``shape``, ``dtype`` and numpy-style basic indexing, e.g. a zarr
    array) seen through the axis permutation ``perm``; every read returns a numpy array. Errors of the
    store while reading (a truncated or corrupt chunk) become a ``ValueError`` naming ``where``."""

    def __init__(
        self,
        source: Any,
        where: str,
        perm: tuple[int, ...] | None = None,
        cast: Any = None,
        convert: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        self._src = source
        self._where = where
        self._perm = tuple(range(len(source.shape))) if perm is None else tuple(perm)
        self._cast = None if cast is None else np.dtype(cast)
        self._convert = convert
        self.dtype = np.dtype(source.dtype) if self._cast is None else self._cast

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(int(self._src.shape[i]) for i in self._perm)

    @property
    def ndim(self) -> int:
        return len(self._perm)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def transpose(self, *axes: Any) -> LazyArray:
        order = tuple(axes[0]) if len(axes) == 1 and not isinstance(axes[0], int) else tuple(axes)
        return LazyArray(self._src, self._where, tuple(self._perm[i] for i in order), self._cast, self._convert)

    def __getitem__(self, key: Any) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            i = key.index(Ellipsis)
            key = key[:i] + (slice(None),) * (self.ndim - len(key) + 1) + key[i + 1 :]
        key = key + (slice(None),) * (self.ndim - len(key))
        if len(key) != self.ndim or not all(isinstance(k, (slice, int, np.integer)) for k in key):
            raise IndexError("a LazyArray takes integers and slices only")
        src_key = [slice(None)] * self.ndim
        for mine, k in enumerate(key):
            src_key[self._perm[mine]] = k
        try:
            block = np.asarray(self._src[tuple(src_key)])
        except (ValueError, OSError, RuntimeError, TypeError, KeyError) as err:
            raise ValueError(
                f"{self._where}: a chunk is unreadable, truncated or corrupt ({type(err).__name__}: "
                f"{err}); copy the store again completely"
            ) from None
        if self._cast is not None:
            block = block.astype(self._cast, copy=False)
        if self._convert is not None:
            block = self._convert(block)
        kept = [self._perm[i] for i, k in enumerate(key) if isinstance(k, slice)]  # source axes left, in my order
        order = sorted(kept)  # the block's axes are in source order
        return block.transpose([order.index(a) for a in kept]) if kept != order else block

    def astype(self, dtype: Any) -> LazyArray:
        """The array seen as ``dtype``, still read on demand: each read is converted (an integer store read
        as float32 intensity, a byte-swapped one in native order)."""
        if self._convert is not None:
            raise TypeError("astype after an elementwise conversion: convert first")
        return LazyArray(self._src, self._where, self._perm, dtype)

    def converted(self, fn: Callable[[np.ndarray], np.ndarray], dtype: Any) -> LazyArray:
        """The array after the elementwise ``fn`` (which returns ``dtype``), applied to each block as it is read
        (a dB intensity converted to linear, :func:`torchdoct.measured.io.read_sequence`)."""
        return LazyArray(self._src, self._where, self._perm, dtype, fn)

    def __iter__(self):
        for i in range(self.shape[0]):
            yield self[i]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = self[...]
        return out if dtype is None else out.astype(dtype)


class Squeezed:
    """``source`` without its axes ``drop`` (each of length 1): what :class:`LazyArray` reads when a store
    keeps a singleton channel or depth axis."""

    def __init__(self, source: Any, drop: tuple[int, ...]):
        self._src, self._drop = source, tuple(sorted(drop))
        self.dtype = source.dtype
        self.shape = tuple(n for i, n in enumerate(source.shape) if i not in self._drop)

    def __getitem__(self, key: tuple) -> Any:
        full, it = [], iter(key)
        for i in range(len(self._src.shape)):
            full.append(0 if i in self._drop else next(it))
        return self._src[tuple(full)]


class MappedFile:
    """A C-order array stored in a file at ``offset`` (a ``.npy`` body, a raw binary, uncompressed OME-TIFF
    planes), read slice by slice with plain file reads: for each frame (first index) the one run of bytes
    that holds the rows asked for, then the columns kept. Nothing is memory-mapped, so the pages read never
    count in the process's resident memory (a memory map's pages do while it is mapped, and a slab across
    thousands of frames touches at least a page of every frame)."""

    def __init__(self, path: Any, dtype: Any, shape: tuple[int, ...], offset: int):
        self._path, self.dtype, self.shape, self._offset = path, np.dtype(dtype), tuple(shape), int(offset)

    def __getitem__(self, key: Any) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        key = key + (slice(None),) * (len(self.shape) - len(key))
        frames = range(self.shape[0])[key[0]]
        inner = self.shape[1:]
        if not inner:  # a 1-D array: one read of the frames' span
            picked = [frames] if isinstance(frames, int) else list(frames)
            whole = np.asarray([self._read(t, 0, 1, ())[0] for t in picked], dtype=self.dtype)
            return whole[0] if isinstance(frames, int) else whole
        rows = range(inner[0])[key[1]]
        lo, hi = (rows, rows + 1) if isinstance(rows, int) else ((min(rows), max(rows) + 1) if len(rows) else (0, 0))
        take = (rows - lo) if isinstance(rows, int) else np.asarray(rows, dtype=np.intp) - lo
        rest = tuple(key[2:])
        out = None
        picked = [frames] if isinstance(frames, int) else frames
        with open(self._path, "rb") as fh:
            for k, t in enumerate(picked):
                block = self._read_from(fh, t, lo, hi, inner[1:])
                part = block[take][rest] if isinstance(take, int) else block[take][(slice(None), *rest)]
                if isinstance(frames, int):
                    return np.ascontiguousarray(part)
                if out is None:
                    out = np.empty((len(frames), *part.shape), dtype=self.dtype)
                out[k] = part
        if out is None:  # no frame asked for
            shape = np.empty((0, *inner), dtype=self.dtype)[(slice(None), key[1], *rest)].shape
            out = np.empty(shape, dtype=self.dtype)
        return out

    def _read(self, t: int, lo: int, hi: int, tail: tuple[int, ...]) -> np.ndarray:
        with open(self._path, "rb") as fh:
            return self._read_from(fh, t, lo, hi, tail)

    def _read_from(self, fh: Any, t: int, lo: int, hi: int, tail: tuple[int, ...]) -> np.ndarray:
        """Rows ``lo:hi`` of frame ``t`` (each row ``tail`` samples) from the open file ``fh``."""
        per_row = int(np.prod(tail, dtype=np.int64)) if tail else 1
        per_frame = int(np.prod(self.shape[1:], dtype=np.int64)) if len(self.shape) > 1 else 1
        count = (hi - lo) * per_row
        fh.seek(self._offset + (t * per_frame + lo * per_row) * self.dtype.itemsize)
        block = np.fromfile(fh, dtype=self.dtype, count=count)
        if block.size != count:
            raise OSError(f"the file ends inside frame {t} (truncated)")
        return block.reshape(hi - lo, *tail)

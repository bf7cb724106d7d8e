"""A folder of per-frame TIFFs (``FOLDER/`` holding ``*.tif`` / ``*.tiff``): one file per frame, in name
order with runs of digits compared as numbers (``f2.tif`` before ``f10.tif``). Each file is one B-scan
page ``[Z, X]`` (the sequence is ``TZX``) or a volume of ``[Z, X]`` pages (``TYZX``); every file must have
the same shape and dtype. Intensity only (linear, or dB with ``--scale db``); the metadata come from the
sidecar ``FOLDER.json`` beside the folder, or the options. Every file's pages are checked (one shape, the
total within the input limit) before any is read; a damaged file is an error naming it. Read whole, or, within
:func:`~torchdoct.measured.guards.streaming_reads` (``torchdoct maps --max-memory-gb``), frame files opened as
the slabs need them (:class:`FrameFiles`)."""

from __future__ import annotations

import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ...files import check_regular_file
from ...runtime.resources import MemoryLimitError
from ..guards import InputRefusal, TiffDamage, check_declared_size, streaming
from .base import Loaded
from .lazy import LazyArray

SUFFIXES: tuple[str, ...] = ()  # a folder: chosen by :func:`torchdoct.measured.formats.reader_for`
NAME = "folder of per-frame TIFFs (+ FOLDER.json sidecar)"
DATASET = False
DIRECTORY = True


def _natural(name: str) -> list:
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def frame_files(folder: Path) -> list[Path]:
    """The TIFFs of ``folder`` in name order (digits as numbers); hidden files are skipped."""
    files = [p for p in folder.iterdir() if p.suffix.lower() in (".tif", ".tiff") and not p.name.startswith(".")]
    return sorted(files, key=lambda p: _natural(p.name))


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    import tifffile

    files = frame_files(path)
    if len(files) < 2:
        raise ValueError(
            f"{path.name}/: {len(files)} TIFF file(s); a folder sequence needs one TIFF per frame (at least 2)"
        )
    shape: tuple[int, ...] | None = None
    dtype = None
    for f in files:  # every file's shape before any pixel is read
        check_regular_file(f, "frame file")  # the one reader-side check: a FIFO would block the read
        try:
            with TiffDamage() as damage, tifffile.TiffFile(f) as tf:
                pages = [tuple(pg.shape) for pg in tf.pages]
                dts = {pg.dtype for pg in tf.pages}
                damage.check()
        except (InputRefusal, MemoryLimitError):  # whole messages: a size, two page shapes
            raise
        except (
            tifffile.TiffFileError,
            OSError,
            ValueError,
            IndexError,
            KeyError,
            struct.error,
        ) as err:  # a damaged file
            raise ValueError(f"{path.name}/{f.name}: not a readable TIFF ({err})") from None
        if not pages or len(set(pages)) != 1 or len(dts) != 1 or len(pages[0]) != 2:
            raise ValueError(
                f"{path.name}/{f.name}: pages of shapes {sorted(set(pages))}; each frame file must "
                "hold one or more [Z, X] pages of one shape"
            )
        this = (len(pages), *pages[0]) if len(pages) > 1 else pages[0]
        if shape is None:
            shape, dtype = this, dts.pop()
            check_declared_size(
                f"{path.name}/",
                (len(files), *shape),
                np.dtype(dtype).itemsize,
                what=f"folder of {len(files)} frames",
                streamed=True,
            )
        elif this != shape or dts.pop() != dtype:
            raise ValueError(
                f"{path.name}/{f.name}: shape {list(this)} differs from {files[0].name}'s "
                f"{list(shape)}; every frame file must have the same shape and dtype"
            )
    assert shape is not None  # set by the first file (at least 2)
    frames = FrameFiles(path, files, tuple(shape), np.dtype(dtype))
    if streaming():  # torchdoct maps --max-memory-gb: the frames the slabs need, read as they are needed
        data: Any = LazyArray(frames, f"{path.name}/")
    else:
        data = frames[(slice(None),) + (slice(None),) * len(shape)]
    return Loaded(data=data, default_axes="TZX" if len(shape) == 2 else "TYZX", integer_intensity=True)


class FrameFiles:
    """The frames of a folder as one array ``[T, ...]`` read on demand (what :class:`LazyArray` reads): a
    read opens only the frame files its first index names, and keeps of each what the other indices name."""

    def __init__(self, folder: Path, files: list[Path], frame_shape: tuple[int, ...], dtype: np.dtype):
        self._folder, self._files, self.dtype = folder, files, dtype
        self.shape = (len(files), *frame_shape)

    def __getitem__(self, key: tuple) -> np.ndarray:
        import tifffile

        first, rest = key[0], tuple(key[1:])
        picked = range(len(self._files))[first]
        single = isinstance(picked, int)
        block = None
        for k, i in enumerate([picked] if single else picked):
            f = self._files[i]
            try:
                with TiffDamage() as damage, tifffile.TiffFile(f) as tf:
                    frame = tf.asarray(key=range(len(tf.pages))) if len(tf.pages) > 1 else tf.pages[0].asarray()
                    damage.check()
            except (InputRefusal, MemoryLimitError):  # whole messages: a size, two page shapes
                raise
            except (
                tifffile.TiffFileError,
                OSError,
                ValueError,
                IndexError,
                KeyError,
                struct.error,
            ) as err:  # a damaged file
                raise ValueError(
                    f"{self._folder.name}/{f.name}: not a readable TIFF, truncated or corrupt ({err})"
                ) from None
            if tuple(frame.shape) != self.shape[1:] or frame.dtype != self.dtype:  # changed since it was checked
                raise ValueError(
                    f"{self._folder.name}/{f.name}: shape {list(frame.shape)} {frame.dtype}, not the "
                    f"{list(self.shape[1:])} {self.dtype} of the other frames; every frame file must "
                    "have the same shape and dtype"
                )
            part = frame[rest]
            if single:
                return np.asarray(part)
            if block is None:
                block = np.empty((len(picked), *np.shape(part)), dtype=self.dtype)
            block[k] = part
        if block is None:  # no frame picked
            block = np.empty((0, *np.empty(self.shape[1:], dtype=self.dtype)[rest].shape), dtype=self.dtype)
        return block

"""TIFF stacks (``.tif`` / ``.tiff``): a linear-intensity stack (float or integer pages, ``[T, Z, X]`` as
the COG contrast library writes it), intensity only, so no resolution change is possible; the metadata
come from a JSON ImageDescription, a sidecar or keywords. Damaged files are errors
(:class:`torchdoct.measured.guards.TiffDamage`); all pages are checked for one shape and the total for the
input limit before anything is read."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import cast

from ...runtime.resources import MemoryLimitError
from ..guards import InputRefusal, TiffDamage, check_tiff_pages, json_loads
from .base import Loaded

SUFFIXES = (".tif", ".tiff")
NAME = "TIFF stack"
DATASET = False


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    import tifffile

    try:
        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            check_tiff_pages(path, tf)  # one shape on every page, total within the input limit
            data = tf.asarray()
            if data.ndim == 2 and len(tf.pages) > 1:  # one image per page, each its own series: all pages
                data = tf.asarray(key=range(len(tf.pages)))
            # the first page is always a TiffPage (later ones may be TiffFrames): tifffile's TiffPages.first
            desc = cast("tifffile.TiffPage", tf.pages[0]).description if len(tf.pages) else ""
            damage.check()
    except (InputRefusal, MemoryLimitError):  # whole messages: a size, two page shapes
        raise
    except (tifffile.TiffFileError, OSError, ValueError, IndexError, KeyError, struct.error) as err:  # a damaged file
        raise ValueError(f"{path.name}: not a readable TIFF stack ({err})") from None
    meta = None
    if desc and desc.lstrip().startswith("{"):
        from ...files import check_nesting

        check_nesting(desc, f"{path.name}: TIFF ImageDescription")  # before the parser's recursion
        try:
            d = json_loads(desc)
        except json.JSONDecodeError:
            d = None
        if isinstance(d, dict) and "axes" in d and "frame_times_s" in d:
            meta = d
    return Loaded(data=data, meta=meta, default_axes="TZX", integer_intensity=True)

"""OME-TIFF sequences (``.ome.tif``, ``.ome.tiff``): the pixel sizes, the time increment (or each plane's
``DeltaT``) and their units come from the file's OME-XML, parsed once and cross-checked against the
pages: a ``SizeT·SizeZ·SizeC`` beyond the pages the file holds is refused, as is more than one channel.

Orientation (docs/formats.md): without a Z axis the planes are B-scans, so an OME plane's rows (OME Y)
are depth z and its columns (OME X) lateral x: ``[T, Y, X]`` is read as ``TZX`` with ``pitch_um`` z =
PhysicalSizeY, x = PhysicalSizeX. With ``SizeZ > 1`` the stack is a volume with OME Z as depth, the
optical axis as in microscopy: ``[T, Z, Y, X]`` is read as ``TZYX`` (z = PhysicalSizeZ, y = PhysicalSizeY,
x = PhysicalSizeX). ``--axes`` overrides the stored order. Frame times: the planes' ``DeltaT`` (of the
first Z plane of each time point) when every time point has one, else ``TimeIncrement``·t. A JSON
``CommentAnnotation`` of namespace ``torchdoct`` (as :func:`torchdoct.measured.mapsfile.write_maps`
writes) supplies ``system`` and the other keys; the OME values win for the pitch and the times.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, cast

import numpy as np

from ...runtime.resources import MemoryLimitError
from ..guards import InputRefusal, TiffDamage, check_tiff_pages, parse_json_object, streaming
from .base import LENGTH_UM, TIME_S, Loaded, to_unit

SUFFIXES = (".ome.tif", ".ome.tiff")
NAME = "OME-TIFF (.ome.tif)"
DATASET = False

ANNOTATION_NAMESPACE = "torchdoct"
_MAX_XML = 16 << 20


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def parse_ome(xml: str, where: str) -> dict[str, Any]:
    """The first image's Pixels attributes, its planes (``TheT``, ``TheZ``, ``TheC``, ``DeltaT``,
    ``DeltaTUnit``) and the ``torchdoct`` annotation of an OME-XML text. Entity and DOCTYPE declarations
    (an entity bomb) and texts over 16 MiB are refused."""
    import xml.etree.ElementTree as ET

    if len(xml) > _MAX_XML:
        raise ValueError(f"{where}: the OME-XML is {len(xml)} characters, over 16 MiB; refused")
    if "<!DOCTYPE" in xml or "<!ENTITY" in xml:
        raise ValueError(f"{where}: the OME-XML declares a DOCTYPE or entities; refused (OME-XML needs neither)")
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as err:
        raise ValueError(f"{where}: the OME-XML is not well-formed ({err})") from None
    pixels = next((el for el in root.iter() if _local(el.tag) == "Pixels"), None)
    if pixels is None:
        raise ValueError(f"{where}: the OME-XML has no Image/Pixels element")
    planes = [dict(el.attrib) for el in pixels if _local(el.tag) == "Plane"]
    note = None
    for el in root.iter():
        if _local(el.tag) == "CommentAnnotation" and el.attrib.get("Namespace") == ANNOTATION_NAMESPACE:
            value = next((c.text for c in el if _local(c.tag) == "Value"), None)
            if value:
                note = parse_json_object(value, f"{where}: OME annotation {ANNOTATION_NAMESPACE!r}")
    return {"pixels": dict(pixels.attrib), "planes": planes, "annotation": note}


def _size(px: dict[str, str], key: str, where: str) -> int:
    try:
        n = int(px.get(key, "1"))
    except ValueError:
        raise ValueError(f"{where}: OME Pixels {key}={px.get(key)!r} is not an integer") from None
    if n < 1:
        raise ValueError(f"{where}: OME Pixels {key}={n} must be >= 1")
    return n


def ome_meta(ome: dict[str, Any], where: str) -> tuple[str, dict[str, Any]]:
    """The stored axes (``TZX`` or ``TZYX`` after the orientation rule, module docstring) and the metadata
    (``pitch_um`` when the sizes are given, ``frame_times_s`` when the times are) of a parsed OME-XML."""
    px = ome["pixels"]
    size_t, size_z = _size(px, "SizeT", where), _size(px, "SizeZ", where)
    volume = size_z > 1
    meta: dict[str, Any] = {}
    if ome["annotation"]:
        meta.update({k: v for k, v in ome["annotation"].items() if k not in ("axes", "pitch_um", "frame_times_s")})
    pitch = {}
    for ours, theirs in (("z", "Z"), ("y", "Y"), ("x", "X")) if volume else (("z", "Y"), ("x", "X")):
        key = f"PhysicalSize{theirs}"
        if px.get(key) is not None:
            pitch[ours] = to_unit(px[key], px.get(f"{key}Unit"), LENGTH_UM, "µm", f"{where}: OME {key}")
    if pitch:
        meta["pitch_um"] = pitch
    first = {}
    for pl in ome["planes"]:
        if pl.get("TheZ", "0") == "0" and pl.get("TheC", "0") == "0" and pl.get("DeltaT") is not None:
            first[int(pl.get("TheT", "0"))] = pl
    if len(first) == size_t and set(first) == set(range(size_t)):
        meta["frame_times_s"] = [
            float(first[t]["DeltaT"])
            * to_unit(1.0, first[t].get("DeltaTUnit"), TIME_S, "s", f"{where}: OME Plane DeltaTUnit")
            for t in range(size_t)
        ]
    elif px.get("TimeIncrement") is not None:
        dt = to_unit(px["TimeIncrement"], px.get("TimeIncrementUnit"), TIME_S, "s", f"{where}: OME TimeIncrement")
        meta["frame_times_s"] = [t * dt for t in range(size_t)]
    return ("TZYX" if volume else "TZX"), meta


def _contiguous_offset(tf: Any, planes: int) -> int | None:
    """The file offset of the first ``planes`` pages when they lie uncompressed, one after another, in one
    run of bytes (then they can be memory-mapped and read slab by slab), else None."""
    pages = tf.pages
    if planes > len(pages):
        return None
    first = pages[0]
    if first.compression != 1 or not first.is_contiguous:
        return None
    offset, nbytes = first.dataoffsets[0], first.nbytes
    for i in range(1, planes):  # every page's strip is uncompressed and right after the one before
        pg = pages[i]
        if pg.compression != 1 or not pg.is_contiguous or pg.dataoffsets[0] != offset + i * nbytes:
            return None
    return int(offset)


def load(path: Path, dataset: str | None = None, allow_external_hdf5: bool = False) -> Loaded:
    import tifffile

    where = path.name
    try:
        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            # the first page is always a TiffPage (later ones may be TiffFrames): tifffile's TiffPages.first
            xml = cast("tifffile.TiffPage", tf.pages[0]).description if len(tf.pages) else ""
            if not tf.is_ome or not xml.lstrip().startswith("<"):
                raise ValueError(
                    "no OME-XML in the first page's ImageDescription; name it .tif if it is a plain TIFF stack"
                )
            ome = parse_ome(xml, where)
            px = ome["pixels"]
            sizes = {k: _size(px, f"Size{k}", where) for k in "TZCYX"}
            if sizes["C"] != 1:
                raise ValueError(f"OME SizeC={sizes['C']}: a sequence has one channel; export one channel")
            planes = sizes["T"] * sizes["Z"]
            if planes > len(tf.pages):
                raise ValueError(
                    f"OME-XML declares SizeT={sizes['T']} × SizeZ={sizes['Z']} = {planes} planes but the "
                    f"file holds {len(tf.pages)} pages; the file is truncated or its OME-XML is wrong"
                )
            offset = _contiguous_offset(tf, planes) if streaming() else None
            check_tiff_pages(path, tf, streamed=offset is not None)  # one shape on every page, the size limit
            page = tf.pages[0]
            if tuple(page.shape) != (sizes["Y"], sizes["X"]):
                raise ValueError(
                    f"OME-XML declares planes of SizeY×SizeX = {sizes['Y']}×{sizes['X']} but the pages "
                    f"are {list(page.shape)}"
                )
            data: np.ndarray  # a memory map, or the pages read
            if offset is not None:  # read slab by slab (torchdoct maps --max-memory-gb)
                dt = np.dtype(page.dtype).newbyteorder(tf.byteorder)
                data = np.memmap(path, dtype=dt, mode="r", offset=offset, shape=(planes, sizes["Y"], sizes["X"]))
            else:
                data = tf.asarray(key=range(planes)) if planes > 1 else page.asarray()[None]
            damage.check()
    except (InputRefusal, MemoryLimitError):  # whole messages: a size, two page shapes
        raise
    except (tifffile.TiffFileError, OSError, ValueError, IndexError, KeyError, struct.error) as err:  # a damaged file
        msg = str(err)
        raise ValueError(msg if msg.startswith(where) else f"{where}: not a readable OME-TIFF ({msg})") from None
    order = px.get("DimensionOrder", "XYZCT")  # fastest first: the planes run in order[2:]
    axes, meta = ome_meta(ome, where)
    if sizes["Z"] > 1:
        slow = [c for c in reversed(order[2:]) if c in "ZT"]  # e.g. XYZCT: T slowest, then Z
        data = data.reshape(sizes[slow[0]], sizes[slow[1]], sizes["Y"], sizes["X"])
        if slow[0] != "T":
            data = data.transpose(1, 0, 2, 3)
    return Loaded(data=data, meta={"axes": axes, **meta}, integer_intensity=True, sidecar_fills=True)

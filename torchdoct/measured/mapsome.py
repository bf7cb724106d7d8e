"""Maps as OME-TIFF (``.ome.tif``) and OME-Zarr (``.zarr``), written and read back (numpy, tifffile and,
for OME-Zarr, zarr; no torch): the formats of :mod:`torchdoct.measured.mapsfile` that Fiji (through
Bio-Formats) and napari open with a µm scale and the channel names.

Orientation (docs/formats.md): B-scan maps ``[C, Z, X]`` are OME ``CYX`` planes whose rows (OME Y) are
depth: ``PhysicalSizeY`` = the z pitch, ``PhysicalSizeX`` = the x pitch. Volume maps ``[C, Y, Z, X]`` are
OME ``CZYX`` with OME Z as depth (the optical axis, as in microscopy): ``PhysicalSizeZ`` = the z pitch,
``PhysicalSizeY`` = the y pitch. Channel names are ``f"{metric}@{resolution}"`` (``liv@original``, ...).
The maps metadata JSON (system, optics per channel, ...) is kept in the file: an OME
``CommentAnnotation`` of namespace ``torchdoct`` (OME-TIFF), the group attribute ``torchdoct`` (OME-Zarr,
NGFF 0.4 on zarr v2, ``omero`` channel labels, colours and display windows).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape, quoteattr

import numpy as np

__all__ = [
    "OME_TIFF_SUFFIXES",
    "ZARR_SUFFIXES",
    "is_ome_tiff",
    "is_zarr",
    "write_ome_tiff",
    "read_ome_tiff",
    "write_zarr",
    "read_zarr",
]

OME_TIFF_SUFFIXES = (".ome.tif", ".ome.tiff")
ZARR_SUFFIXES = (".zarr",)
NAMESPACE = "torchdoct"


def is_ome_tiff(path: str | os.PathLike) -> bool:
    return Path(path).name.lower().endswith(OME_TIFF_SUFFIXES)


def is_zarr(path: str | os.PathLike) -> bool:
    return Path(path).name.lower().endswith(ZARR_SUFFIXES)


def _ome_layout(arr: np.ndarray, pitch: dict[str, float] | None) -> tuple[np.ndarray, str, dict[str, float]]:
    """The stack in OME order (``CYX`` or ``CZYX``, module docstring) and its physical sizes (µm)."""
    pitch = pitch or {}
    if arr.ndim == 3:  # [C, Z, X]: rows are depth
        sizes = {"Y": pitch.get("z"), "X": pitch.get("x")}
        return arr, "CYX", {k: float(v) for k, v in sizes.items() if v is not None}
    sizes = {"Z": pitch.get("z"), "Y": pitch.get("y"), "X": pitch.get("x")}
    return arr.transpose(0, 2, 1, 3), "CZYX", {k: float(v) for k, v in sizes.items() if v is not None}


def ome_xml(
    shape: tuple[int, ...], axes: str, dtype: np.dtype, sizes: dict[str, float], channels: list[str], meta_json: str
) -> str:
    """The OME-XML of one image of ``shape`` (``axes`` ``CYX`` / ``CZYX``, planes in ``XYZCT`` order: the
    channel index fastest after the plane), µm physical sizes, channel names and the ``torchdoct``
    annotation."""
    dims = dict(zip(axes, shape))
    ome_type = {"float32": "float", "float64": "double"}[np.dtype(dtype).name]
    size_attrs = "".join(f' PhysicalSize{k}="{v:.12g}" PhysicalSize{k}Unit="µm"' for k, v in sizes.items())
    chans = "".join(
        f'<Channel ID="Channel:0:{i}" Name={quoteattr(n)} SamplesPerPixel="1"/>' for i, n in enumerate(channels)
    )
    n_planes = dims["C"] * dims.get("Z", 1)
    order = "XYCZT"  # pages: for each z, every channel (the page order of a [Z, C, Y, X] array)
    return (
        '<?xml version="1.0" encoding="UTF-8"?>'
        '<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06">'
        f'<Image ID="Image:0" Name="maps"><Pixels ID="Pixels:0" DimensionOrder="{order}" Type="{ome_type}" '
        f'SizeX="{dims["X"]}" SizeY="{dims["Y"]}" SizeZ="{dims.get("Z", 1)}" SizeC="{dims["C"]}" SizeT="1"'
        f"{size_attrs}>"
        f'{chans}<TiffData IFD="0" PlaneCount="{n_planes}"/></Pixels>'
        '<AnnotationRef ID="Annotation:0"/></Image>'
        f'<StructuredAnnotations><CommentAnnotation ID="Annotation:0" Namespace="{NAMESPACE}">'
        f"<Value>{escape(meta_json)}</Value></CommentAnnotation></StructuredAnnotations></OME>"
    )


def write_ome_tiff(tmp: str, arr: np.ndarray, channels: list[str], meta: dict[str, Any]) -> None:
    """Write maps ``arr`` (``[C, (Y,) Z, X]`` float) to ``tmp`` as OME-TIFF (module docstring)."""
    import tifffile

    ome, axes, sizes = _ome_layout(arr, meta.get("pitch_um"))
    xml = ome_xml(ome.shape, axes, ome.dtype, sizes, channels, json.dumps(meta))
    pages = ome.transpose(1, 0, 2, 3) if ome.ndim == 4 else ome  # [Z, C, Y, X]: channel fastest
    pages = np.ascontiguousarray(pages).reshape(-1, *ome.shape[-2:])
    xml = xml.encode("ascii", "xmlcharrefreplace").decode("ascii")  # TIFF text is 7-bit ASCII: µ as &#181;
    tifffile.imwrite(tmp, pages, description=xml, metadata=None, photometric="minisblack")


def read_ome_tiff(path: Path, tf: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """The maps ``[C, (Y,) Z, X]`` and their metadata JSON of an open OME-TIFF written by
    :func:`write_ome_tiff` (pages checked by the caller)."""
    from .formats.ometiff import parse_ome

    ome = parse_ome(tf.pages[0].description or "", path.name)
    meta = ome["annotation"]
    if not meta or "channels" not in meta:
        raise ValueError(
            f"{path.name}: no torchdoct maps annotation (namespace {NAMESPACE!r}) in the OME-XML; "
            "write it with `torchdoct maps ... --out FILE.ome.tif`"
        )
    px = ome["pixels"]
    n_c, n_z = int(px.get("SizeC", 1)), int(px.get("SizeZ", 1))
    if n_c * n_z != len(tf.pages):
        raise ValueError(
            f"{path.name}: the OME-XML declares SizeC={n_c} × SizeZ={n_z} planes but the file holds "
            f"{len(tf.pages)} pages; the file is truncated or was edited"
        )
    pages = tf.asarray(key=range(len(tf.pages))) if len(tf.pages) > 1 else tf.pages[0].asarray()[None]
    if n_z > 1:  # [Z, C, Y, X] pages -> [C, Y(ome), Z(ome)=depth, X]: ours [C, Y, Z, X]
        data = pages.reshape(n_z, n_c, *pages.shape[-2:]).transpose(1, 2, 0, 3)
    else:
        data = pages
    return np.ascontiguousarray(data), meta


def write_zarr(tmp: str, arr: np.ndarray, channels: list[str], meta: dict[str, Any]) -> None:
    """Write maps to the folder ``tmp`` as OME-Zarr (NGFF 0.4, zarr v2): axes ``c, (z,) y, x`` in µm,
    the scale transform from the pitch, channel labels under ``omero``, the metadata as ``torchdoct``."""
    import zarr

    ome, axes, sizes = _ome_layout(arr, meta.get("pitch_um"))
    names = [a.lower() for a in axes]
    group = zarr.open_group(tmp, mode="w", zarr_format=2)
    chunks = (1, *ome.shape[1:]) if ome[0].nbytes <= 64 << 20 else (1, *(min(n, 256) for n in ome.shape[1:]))
    z = group.create_array("0", shape=ome.shape, dtype=ome.dtype, chunks=chunks, fill_value=np.nan)
    z[...] = ome
    ax = [{"name": "c", "type": "channel"}] + [{"name": n, "type": "space", "unit": "micrometer"} for n in names[1:]]
    scale = [1.0] + [sizes.get(a, 1.0) for a in axes[1:]]
    group.attrs["multiscales"] = [
        {
            "version": "0.4",
            "name": "maps",
            "axes": ax,
            "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": scale}]}],
        }
    ]
    group.attrs["omero"] = {"channels": [_omero_channel(n, ome[i]) for i, n in enumerate(channels)]}
    group.attrs[NAMESPACE] = meta


def _omero_channel(name: str, plane: np.ndarray) -> dict[str, Any]:
    """The ``omero`` entry of one channel as NGFF 0.4 requires it: its label, a grey colour and a display
    window over the channel's finite values (0..1 when it has none)."""
    finite = plane[np.isfinite(plane)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    return {
        "label": name,
        "active": True,
        "color": "FFFFFF",
        "window": {"min": lo, "max": hi, "start": lo, "end": hi if hi > lo else lo + 1.0},
    }


def read_zarr(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The maps ``[C, (Y,) Z, X]`` and their metadata of an OME-Zarr written by :func:`write_zarr`; the
    declared size is checked before the array is read, object dtypes are refused."""
    import zarr

    from ..files import check_folder_files
    from .formats.omezarr import check_chunk_files
    from .guards import check_declared_size

    check_folder_files(path, "OME-Zarr maps")  # a FIFO among its files would block zarr's read
    try:
        group = zarr.open_group(str(path), mode="r")
        meta = group.attrs.get(NAMESPACE)
        arr = group["0"]
    except Exception as err:
        raise ValueError(
            f"{path.name}: not a readable OME-Zarr maps folder ({type(err).__name__}: {err}); write it "
            "with `torchdoct maps ... --out FILE.zarr`"
        ) from None
    if hasattr(arr, "chunks"):
        check_chunk_files(path / "0", arr, f"{path.name}/0")  # a truncated chunk is not decoded into numbers
    if not isinstance(meta, dict) or "channels" not in meta:
        raise ValueError(
            f"{path.name}: no 'torchdoct' maps metadata in the group's attributes; write it with "
            "`torchdoct maps ... --out FILE.zarr`"
        )
    dt = np.dtype(arr.dtype)
    if dt.hasobject:
        raise ValueError(f"{path.name}: object arrays are refused (they would need unpickling)")
    check_declared_size(path.name, arr.shape, dt.itemsize)
    try:
        data = np.asarray(arr[...])
    except Exception as err:
        raise ValueError(
            f"{path.name}: a chunk is unreadable, truncated or corrupt ({type(err).__name__}); copy it again completely"
        ) from None
    if data.ndim == 4:
        data = data.transpose(0, 2, 1, 3)
    return np.ascontiguousarray(data), meta

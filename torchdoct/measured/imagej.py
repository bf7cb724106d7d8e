"""ImageJ-compatible TIFF stacks for what torchdoct and ``doct-classify`` write (numpy and tifffile only, no
torch): Fiji, ImageJ and napari show the physical pixel size in µm and the channel names.

A stack ``[C, Z, X]`` (B-scan maps) is an ImageJ hyperstack of ``C`` channels, each a ``Z × X`` image
(image rows are depth). A stack ``[C, Y, Z, X]`` (volume maps) is a hyperstack of ``C`` channels and ``Y``
slices: the metrics are on ImageJ's channel axis, and the pages are written in ImageJ's order, channel
fastest (``[Y, C, Z, X]``, :func:`imagej_pages`). Each page carries its channel name as the ImageJ slice
label (``Labels``); the pixel size is the TIFF X/Y resolution (pixels per µm, x and z), the slice spacing
the y pitch, and ``unit=micron``.

Every page holds at most one ImageDescription, ImageJ's (on the first page). The project's own JSON (the
maps metadata, a class map's legend) is ImageJ's ``Info`` text in the IJMetadata tag, which Fiji shows
under *Image › Show Info* and tifffile reads as ``imagej_metadata["Info"]``; :func:`project_description`
finds it there, or, in files written before, as the first page's JSON ImageDescription.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["imagej_write_options", "imagej_pages", "project_description", "restore_channels"]


def imagej_pages(arr: np.ndarray, axes: str) -> np.ndarray:
    """``arr`` in the page order ImageJ reads (channel fastest): a ``C`` + ``YZX`` stack as ``[Y, C, Z, X]``,
    anything else as it is. Pass it to ``tifffile.imwrite`` with :func:`imagej_write_options`."""
    if axes.startswith("C") and len(axes) == 4 and arr.shape[0] > 1 and arr.shape[1] > 1:
        return np.ascontiguousarray(np.swapaxes(arr, 0, 1))
    return arr


def imagej_write_options(
    shape: Sequence[int],
    axes: str,
    pitch_um: Mapping[str, float] | None,
    channel_names: Sequence[str],
    *,
    description: str,
    value_unit: str | None = None,
) -> dict[str, Any]:
    """Keyword arguments for ``tifffile.imwrite`` that write one ImageDescription (ImageJ's hyperstack
    description) and the IJMetadata tag holding the slice labels and ``description`` (the project's JSON) as
    ImageJ's ``Info``, for a stack of ``shape`` (``[C, (Y,) Z, X]``, before :func:`imagej_pages`) with
    ``axes`` ``"C" + "ZX"`` or ``"C" + "YZX"`` (``C`` may be absent for one image). The data written must be
    ``imagej_pages(arr, axes)``. ``pitch_um``: ``{"z", "x"[, "y"]}`` in µm (None: no scale).
    ``value_unit``: the unit of the pixel values (ImageJ's value unit)."""
    import tifffile

    shape = tuple(int(s) for s in shape)
    if len(axes) != len(shape):
        raise ValueError(f"axes {axes!r} do not match the shape {shape}")
    dims = dict(zip(axes, shape))
    n_c = dims.get("C", 1)
    n_y = dims.get("Y", 1)
    labels = [str(name) for _ in range(n_y) for name in channel_names] if channel_names else []
    lines = ["ImageJ=1.11a", f"images={n_c * n_y}"]
    if n_c > 1:
        lines.append(f"channels={n_c}")
    if "Y" in dims:
        lines.append(f"slices={n_y}")
    if n_c * n_y > 1:
        lines.append("hyperstack=true")
    lines.append("mode=grayscale")
    opts: dict[str, Any] = {"description": None, "metadata": None, "photometric": "minisblack"}
    if pitch_um:
        lines.append("unit=micron")
        if "Y" in dims and pitch_um.get("y"):
            lines.append(f"spacing={float(pitch_um['y']):.9g}")
        opts["resolution"] = (1.0 / float(pitch_um["x"]), 1.0 / float(pitch_um["z"]))
        opts["resolutionunit"] = 1  # NONE: ImageJ takes the unit from its description
    if value_unit:
        lines.append(f"vunit={value_unit.encode('ascii', 'replace').decode('ascii')}")
    lines.append("loop=false")
    extratags: list[Any] = [(270, "s", 0, "\n".join(lines) + "\n", True)]
    ij: dict[str, Any] = {"Info": description}
    if labels:
        ij["Labels"] = labels
    extratags += list(tifffile.imagej_metadata_tag(ij, "<"))
    opts["extratags"] = extratags
    return opts


def project_description(tf: Any) -> str | None:
    """The project's JSON text of an open ``tifffile.TiffFile``: ImageJ's ``Info`` when it holds a JSON
    object, else (files written before it moved there, and other tools' stacks) the first page's first
    ImageDescription that does; None when neither does."""
    if not len(tf.pages):
        return None
    ij = tf.imagej_metadata if tf.is_imagej else None
    info = ij.get("Info") if isinstance(ij, dict) else None
    if isinstance(info, str) and info.lstrip().startswith("{"):
        return info
    page = tf.pages[0]
    for tag in page.tags.values():
        if tag.code == 270 and isinstance(tag.value, str) and tag.value.lstrip().startswith("{"):
            return tag.value
    return None


def restore_channels(data: np.ndarray, n_c: int, tf: Any) -> np.ndarray:
    """A volume stack read from an open ImageJ TIFF, its pages ``[Y·C, Z, X]`` in any leading shape, back
    to ``[C, Y, Z, X]``: channel fastest when ImageJ's description names both ``channels`` and ``slices``
    (:func:`imagej_pages`), channel slowest otherwise (files written before, and stacks without ImageJ
    metadata)."""
    ij = tf.imagej_metadata if tf.is_imagej else None
    pages = data.reshape(-1, *data.shape[-2:])
    if isinstance(ij, dict) and int(ij.get("channels", 1)) == n_c > 1 and int(ij.get("slices", 1)) > 1:
        return np.ascontiguousarray(np.swapaxes(pages.reshape(-1, n_c, *pages.shape[-2:]), 0, 1))
    return pages.reshape(n_c, -1, *pages.shape[-2:])

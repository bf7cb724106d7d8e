"""ImageJ-compatible metadata for the TIFF stacks torchdoct and ``doct-classify`` write (numpy and tifffile
only, no torch): Fiji, ImageJ and napari then show the physical pixel size in µm and the channel names.

A stack ``[C, Z, X]`` (B-scan maps) is an ImageJ hyperstack of ``C`` channels, each a ``Z × X`` image
(image rows are depth). A stack ``[C, Y, Z, X]`` (volume maps) is stored in that order, channel slowest,
which is ImageJ's frame order: ``C`` frames of ``Y`` slices. Each page carries its channel name as the
ImageJ slice label (``Labels``); the pixel size is the TIFF X/Y resolution (pixels per µm, x and z), the
slice spacing the y pitch, and ``unit=micron``.

The project's own JSON description stays the first ImageDescription (the maps readers use it); the
ImageJ description is the second, which tifffile reads as ``imagej_metadata`` and ImageJ's decoder
keeps (it takes the last ImageDescription that starts with ``ImageJ=``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["imagej_write_options"]


def imagej_write_options(shape: Sequence[int], axes: str, pitch_um: Mapping[str, float] | None,
                         channel_names: Sequence[str], *, description: str,
                         value_unit: str | None = None) -> dict[str, Any]:
    """Keyword arguments for ``tifffile.imwrite`` that write ``description`` (the project's JSON, ASCII)
    as the first ImageDescription and ImageJ metadata after it, for a stack of ``shape`` with ``axes``
    ``"C" + "ZX"`` or ``"C" + "YZX"`` (``C`` may be absent for one image). ``pitch_um``:
    ``{"z", "x"[, "y"]}`` in µm (None: no scale). ``value_unit``: the unit of the pixel values
    (ImageJ's value unit)."""
    import tifffile

    shape = tuple(int(s) for s in shape)
    if len(axes) != len(shape):
        raise ValueError(f"axes {axes!r} do not match the shape {shape}")
    dims = dict(zip(axes, shape))
    n_c = dims.get("C", 1)
    n_y = dims.get("Y", 1)
    labels = [str(name) for name in channel_names for _ in range(n_y)] if channel_names else []
    lines = ["ImageJ=1.11a", f"images={n_c * n_y}"]
    if "Y" in dims:  # channel slowest: C frames of Y slices (ImageJ's page order t, z, c)
        lines += [f"slices={n_y}"] + ([f"frames={n_c}"] if n_c > 1 else [])
    elif n_c > 1:
        lines += [f"channels={n_c}"]
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
    extratags = [(270, "s", 0, description, True), (270, "s", 0, "\n".join(lines) + "\n", True)]
    if labels:
        byte_counts, data = tifffile.imagej_metadata_tag({"Labels": labels}, "<")
        extratags += [byte_counts, data]
    opts["extratags"] = extratags
    return opts

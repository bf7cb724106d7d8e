"""npe2 writer: Image layers (maps channels, as :mod:`.reader` opens them) to a maps file
(:func:`torchdoct.measured.mapsfile.write_maps`: ``.ome.tif``, ``.zarr``, ``.npz``, ``.tif``). The layers'
``metadata["channel"]`` entries (the maps' channel metadata) and the first layer's ``metadata["maps"]``
are written back; a layer without them becomes a channel of metric = its name, unit ``""``, its scale the
pitch (µm)."""

from __future__ import annotations

from typing import Any

import numpy as np


def write_maps(path: str, layers: list[tuple[Any, dict[str, Any], str]]) -> list[str]:
    from ..measured.mapsfile import Maps
    from ..measured.mapsfile import write_maps as _write

    if not layers:
        raise ValueError("no layers to write")
    arrays, chans = [], []
    first_meta = dict(layers[0][1].get("metadata") or {})
    for data, attrs, kind in layers:
        if kind != "image":
            raise ValueError(f"layer {attrs.get('name')!r} is a {kind} layer; DOCT maps are Image layers")
        a = np.asarray(data, dtype=np.float32)
        if arrays and a.shape != arrays[0].shape:
            raise ValueError(
                f"layer {attrs.get('name')!r} has shape {a.shape}, not {arrays[0].shape}; maps channels share one grid"
            )
        arrays.append(a)
        info = (attrs.get("metadata") or {}).get("channel")
        name = str(attrs.get("name"))
        chans.append(
            dict(info)
            if isinstance(info, dict)
            else {
                "name": name,
                "metric": name.split("@")[0],
                "unit": "",
                "resolution": name.split("@")[1] if "@" in name else "original",
                "wavelength_um": None,
                "lateral_resolution_um": None,
                "axial_resolution_um": None,
            }
        )
    stack = np.stack(arrays)
    meta = dict(first_meta.get("maps") or {})
    axes = "CZX" if stack.ndim == 3 else "CYZX"
    if "pitch_um" not in meta:
        scale = layers[0][1].get("scale")
        if scale is not None and len(scale) == stack.ndim - 1:
            meta["pitch_um"] = {c.lower(): float(s) for c, s in zip(axes[1:], scale)}
    meta.update(axes=axes, channels=chans)
    _write(path, Maps(maps=stack, channels=tuple(c["name"] for c in chans), meta=meta), force=False)
    return [path]

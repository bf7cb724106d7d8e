"""npe2 reader: sequences, maps and class maps as napari layer-data tuples ``(data, kwargs, kind)``, each
scaled in µm (no napari or Qt import: testable through npe2 alone).

* a **maps** file (any maps format, :func:`torchdoct.measured.mapsfile.read_maps`): one Image layer per
  channel, named by the channel (``liv@original``), metadata = the channel's entry and the file's;
* a **class map** (``classes.tif`` of ``doct-classify``, its JSON holding the legend): a Labels
  layer whose label ``v + 1`` is class ``v`` in the legend's colour (napari keeps 0 for "no label": the
  masked pixels);
* a **sequence** (:func:`torchdoct.measured.io.read_sequence`): the intensity ``10·log10 |E|²`` (dB) as
  one Image layer over ``T`` (a time axis of scale 1 frame; the frame times are in the metadata).

Orientation: B-scans are shown with rows = depth z, columns = x (scale ``(pitch_z, pitch_x)``); volumes
as ``(Y, Z, X)``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

LayerData = tuple[Any, dict[str, Any], str]


def _scale(pitch: dict[str, float] | None, axes: str) -> tuple[float, ...]:
    pitch = pitch or {}
    return tuple(float(pitch.get(c.lower(), 1.0)) for c in axes)


def _classes_legend(path: Path) -> dict[str, Any] | None:
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    import tifffile

    from ..measured.imagej import project_description

    with tifffile.TiffFile(path) as tf:
        desc = project_description(tf)  # ImageJ's Info (or the first JSON ImageDescription of earlier files)
    if desc is None:
        return None
    from ..measured.guards import parse_json_object

    try:
        d = parse_json_object(desc, path.name)
    except ValueError:
        return None
    legend = d.get("legend")
    return legend if isinstance(legend, dict) and isinstance(legend.get("classes"), list) else None


def read_classes(path: Path, legend: dict[str, Any]) -> list[LayerData]:
    """The Labels layer of a ``classes.tif`` (module docstring)."""
    import tifffile

    from ..measured.guards import TiffDamage, check_tiff_pages

    with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
        check_tiff_pages(path, tf)
        raw = tf.asarray()
        damage.check()
    values = {int(c["value"]) for c in legend["classes"]}
    labels = np.where(np.isin(raw, list(values)), raw.astype(np.int32) + 1, 0).astype(np.int32)
    colors: dict[Any, str] = {None: "transparent", 0: "transparent"}
    colors.update({int(c["value"]) + 1: str(c["color"]) for c in legend["classes"]})
    axes = str(legend.get("axes") or ("YZX" if labels.ndim == 3 else "ZX"))
    return [
        (
            labels,
            {
                "name": f"{path.stem} classes",
                "scale": _scale(legend.get("pitch_um"), axes),
                "colormap": colors,
                "metadata": {"legend": legend, "source": path.name},
            },
            "labels",
        )
    ]


def read_maps_layers(path: Path) -> list[LayerData]:
    """One Image layer per maps channel (module docstring)."""
    from ..measured.mapsfile import read_maps

    m = read_maps(path)
    axes = str(m.meta.get("axes") or ("CYZX" if m.maps.ndim == 4 else "CZX"))[1:]
    scale = _scale(m.meta.get("pitch_um"), axes)
    meta = {k: v for k, v in m.meta.items() if k != "channels"}
    out = []
    for i, name in enumerate(m.channels):
        info = m.meta["channels"][i]
        colormap = "gray" if info.get("metric") == "mean_db" else "viridis"
        out.append(
            (
                m.maps[i],
                {
                    "name": name,
                    "scale": scale,
                    "colormap": colormap,
                    "metadata": {"channel": info, "maps": meta, "source": path.name},
                },
                "image",
            )
        )
    return out


def read_sequence_layers(path: Path) -> list[LayerData]:
    """The dB intensity of a sequence over time (module docstring)."""
    from ..measured.io import read_sequence

    seq = read_sequence(path)
    frames = []
    for k in range(seq.n_frames):  # frame by frame: never the whole complex field at once beside it
        f = np.asarray(seq.data[k])
        inten = f.real**2 + f.imag**2 if np.iscomplexobj(f) else f.astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            frames.append((10 * np.log10(inten)).astype(np.float32))
    scale = (1.0, *_scale(seq.meta.get("pitch_um"), seq.axes[1:]))
    return [
        (
            np.stack(frames),
            {
                "name": f"{path.name} (dB)",
                "scale": scale,
                "colormap": "gray",
                "metadata": {"sequence": seq.meta, "source": path.name},
            },
            "image",
        )
    ]


def read(path: str | os.PathLike | list) -> list[LayerData]:
    """The layers of ``path`` (a maps file, a class map or a sequence, in that order of trial)."""
    paths = path if isinstance(path, list) else [path]
    out: list[LayerData] = []
    for one in paths:
        p = Path(one)
        legend = _classes_legend(p) if p.is_file() else None
        if legend is not None:
            out += read_classes(p, legend)
            continue
        try:
            out += read_maps_layers(p)
        except ValueError as maps_err:
            try:
                out += read_sequence_layers(p)
            except (ValueError, TypeError) as seq_err:
                raise ValueError(f"{p.name}: neither a maps file ({maps_err}) nor a sequence ({seq_err})") from None
    return out


def get_reader(path: str | os.PathLike | list) -> Callable[..., list[LayerData]] | None:
    """The npe2 reader hook: :func:`read` for paths torchdoct can read, else None (napari tries others)."""
    from ..measured.formats import reader_for
    from ..measured.mapsfile import MAPS_SUFFIXES

    paths = path if isinstance(path, list) else [path]
    for one in paths:
        p = Path(one)
        if not p.exists() or (reader_for(p) is None and p.suffix.lower() not in MAPS_SUFFIXES):
            return None
    return read


__all__ = ["get_reader", "read", "read_maps_layers", "read_classes", "read_sequence_layers"]

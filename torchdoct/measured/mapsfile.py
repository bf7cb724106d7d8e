"""The maps format: :class:`Maps`, its one reader and its one writer (numpy only, no torch).

Written by ``torchdoct maps``; read by ``torchdoct compare``, ``doct-classify`` and ``doct-train``'s
checks, all through :func:`read_maps`:

* ``.npz`` with ``maps`` float32 ``[C, Z, X]`` or ``[C, Y, Z, X]``, ``channels`` (str array; optional
  when reading, the names then come from the metadata) and ``meta_json`` (one JSON text);
* ``.tif`` / ``.tiff``: an ImageJ hyperstack of ``[Z, X]`` pages, the metrics on ImageJ's channel axis
  (a volume's pages channel fastest), one ImageDescription (ImageJ's) and the metadata JSON as ImageJ's
  ``Info`` (:mod:`torchdoct.measured.imagej`; files of earlier versions, the JSON as the first
  ImageDescription and the channels slowest, are read too); the axes restore ``[C, (Y,) Z, X]``;
* ``.ome.tif`` and ``.zarr``: OME-TIFF and OME-Zarr (:mod:`torchdoct.measured.mapsome`).

The metadata hold one dict per channel (``meta["channels"]``): ``name`` (``f"{metric}@{resolution}"``),
``metric``, ``unit``, ``resolution`` and the optics ``wavelength_um``, ``lateral_resolution_um``,
``axial_resolution_um`` (µm, or null when unknown), plus ``axes`` (``CZX`` / ``CYZX``), ``pitch_um``,
``frame_times_s``, ``system``, ``ocds_delay_range_s``, ``reduction`` and optional extra keys. A
channel's optics as one value: :meth:`Maps.optics` (:class:`torchdoct.optics.ChannelOptics`).

Safety (:mod:`torchdoct.measured.guards`): nothing is unpickled; an empty, truncated or corrupted file,
an object array, a pickle under the maps suffix, or metadata of the wrong shape is a ``ValueError``
naming the file, the field and the fix. Outputs are written atomically, never over a file without
``force``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..files import atomic_write, check_out
from ..optics import ChannelOptics
from .guards import MAX_INPUT_ENV, TiffDamage, check_npz_sizes, check_tiff_pages, json_loads

__all__ = ["MAPS_SUFFIXES", "Maps", "read_maps", "write_maps"]

MAPS_SUFFIXES = (".npz", ".tif", ".tiff", ".zarr")  # .tif includes .ome.tif (mapsome)
_CHANNEL_TEXT = ("name", "metric", "unit", "resolution")
_CHANNEL_OPTICS = ("wavelength_um", "lateral_resolution_um", "axial_resolution_um")


@dataclass(frozen=True, kw_only=True, eq=False)
class Maps:
    """DOCT maps: ``maps`` float32 ``[C, Z, X]`` or ``[C, Y, Z, X]``, channel names, metadata.

    ``meta["channels"]`` holds one dict per channel (module docstring). Match channels by metric and
    optics (:meth:`optics`, :meth:`find`), not by name. ``path``: the file it was read from (None for
    maps computed in memory).
    """

    maps: np.ndarray
    channels: tuple[str, ...]
    meta: dict[str, Any]
    path: Path | None = None

    def __post_init__(self) -> None:
        m = np.asarray(self.maps)
        if m.ndim not in (3, 4):
            raise ValueError(f"maps must be [C, Z, X] or [C, Y, Z, X]; got shape {list(m.shape)}")
        if m.shape[0] != len(self.channels):
            raise ValueError(f"maps has {m.shape[0]} channels but {len(self.channels)} channel names")
        object.__setattr__(self, "channels", tuple(str(c) for c in self.channels))

    @property
    def data(self) -> np.ndarray:
        """The stack ``[C, (Y,) Z, X]`` (the same array as :attr:`maps`)."""
        return self.maps

    @property
    def spatial_shape(self) -> tuple[int, ...]:
        """``(Z, X)`` or ``(Y, Z, X)``."""
        return tuple(self.maps.shape[1:])

    @property
    def name(self) -> str:
        """The file name (no directory), else the metadata's ``source``, else ``"maps"``."""
        return self.path.name if self.path is not None else str(self.meta.get("source") or "maps")

    @property
    def channel_meta(self) -> list[dict[str, Any]]:
        """The metadata dict of every channel, in channel order."""
        return list(self.meta["channels"])

    def index(self, name: str) -> int:
        try:
            return self.channels.index(name)
        except ValueError:
            raise ValueError(f"no channel {name!r}; channels: {', '.join(self.channels)}") from None

    def __getitem__(self, name: str) -> np.ndarray:
        return self.maps[self.index(name)]

    def channel_info(self, name: str) -> dict[str, Any]:
        return dict(self.meta["channels"][self.index(name)])

    def optics(self, channel: str | int) -> ChannelOptics | None:
        """The optics of a channel (name or index) from the metadata, or None when it records none
        (:meth:`torchdoct.optics.ChannelOptics.of_channel`: B-scan data reduced along x keep the original
        lateral width along y)."""
        i = self.index(channel) if isinstance(channel, str) else int(channel)
        return ChannelOptics.of_channel(self.meta["channels"][i], self.meta)

    def find(
        self,
        metric: str,
        *,
        wavelength_um: float | None = None,
        lateral_resolution_um: float | None = None,
        axial_resolution_um: float | None = None,
        rtol: float = 1e-6,
    ) -> list[str]:
        """Names of channels of ``metric`` whose optics match the given values within ``rtol`` (a value
        not given matches any; the lateral resolution is the one along x)."""
        out = []
        for i, info in enumerate(self.meta["channels"]):
            optics = self.optics(i)
            if info["metric"] != metric or optics is None:
                continue
            want = ChannelOptics(
                optics.wavelength_um if wavelength_um is None else float(wavelength_um),
                optics.lateral_resolution_um if lateral_resolution_um is None else float(lateral_resolution_um),
                optics.axial_resolution_um if axial_resolution_um is None else float(axial_resolution_um),
            )
            if want.matches(optics, rel_tol=rtol, lateral_y=False):
                out.append(info["name"])
        return out


# ----------------------------------------------------------------------------------------------
# writer


def write_maps(path: str | os.PathLike, maps: Maps, *, force: bool = False) -> Path:
    """Write :class:`Maps` to ``.npz`` (``maps``, ``channels``, ``meta_json``), ``.tif`` (an ImageJ
    hyperstack: metrics on the channel axis, pixel size in µm, channel names, the JSON as ImageJ's ``Info``,
    :mod:`torchdoct.measured.imagej`), ``.ome.tif`` or ``.zarr`` (:mod:`torchdoct.measured.mapsome`),
    atomically; refuses to overwrite without ``force``."""
    out = check_out(path, force, MAPS_SUFFIXES, what="maps output")
    arr = np.ascontiguousarray(maps.maps, dtype=np.float32)
    meta = dict(maps.meta)
    text = json.dumps(meta)
    from . import mapsome

    if mapsome.is_zarr(out):
        import shutil
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp.zarr", dir=out.parent))
        try:
            mapsome.write_zarr(str(tmp), arr, list(maps.channels), meta)
            if out.exists() and force:
                shutil.rmtree(out)
            os.replace(tmp, out)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
        return out
    if mapsome.is_ome_tiff(out):

        def write(tmp: str) -> None:
            mapsome.write_ome_tiff(tmp, arr, list(maps.channels), meta)
    elif out.suffix == ".npz":

        def write(tmp: str) -> None:
            with open(tmp, "wb") as fh:
                np.savez(fh, maps=arr, channels=np.asarray(maps.channels, dtype=np.str_), meta_json=np.asarray(text))
    else:

        def write(tmp: str) -> None:
            import tifffile

            from .imagej import imagej_pages, imagej_write_options

            units = {ch.get("unit") for ch in meta.get("channels", []) if isinstance(ch, dict)}
            axes = meta.get("axes") or ("CYZX" if arr.ndim == 4 else "CZX")
            tifffile.imwrite(
                tmp,
                imagej_pages(arr, axes),
                **imagej_write_options(  # Fiji/napari: µm, channel names
                    arr.shape,
                    axes,
                    meta.get("pitch_um"),
                    list(maps.channels),
                    description=text,
                    value_unit=units.pop() if len(units) == 1 else None,
                ),
            )

    atomic_write(out, write)
    return out


# ----------------------------------------------------------------------------------------------
# reader


def _rewrite_fix(path: Path) -> str:
    return f"Fix: write it again with `torchdoct maps DATA --out {path.name}` (or copy it again completely)"


def read_maps(path: str | os.PathLike) -> Maps:
    """Read a maps file (``.npz`` or ``.tif``/``.tiff``, module docstring) into :class:`Maps`.

    Nothing is unpickled. An empty, truncated or corrupted file, an object (pickled) array, a
    ``meta_json`` that is not a JSON object, or metadata of the wrong shape is a ``ValueError`` naming
    the file, the field and the fix; maps that are not floating point are a ``TypeError``.
    """
    from ..files import check_regular_file, open_regular

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"maps file {p} does not exist")
    if not (p.suffix.lower() == ".zarr" and p.is_dir()):  # an OME-Zarr is a folder
        check_regular_file(p, "maps file")  # a FIFO, device or folder: at once, whatever its name
    if p.suffix.lower() not in MAPS_SUFFIXES:
        raise ValueError(
            f"maps file {p.name}: must be .npz, .tif/.tiff/.ome.tif or .zarr (the formats of `torchdoct maps`)"
        )
    from . import mapsome

    if mapsome.is_zarr(p):
        if not p.is_dir():
            raise ValueError(f"maps file {p.name}: an OME-Zarr is a folder; give the .zarr folder")
        arr, meta = mapsome.read_zarr(p)
        return _finish(p, arr, None, meta, f"{p.name} attribute 'torchdoct'")
    with open_regular(p, "maps file") as fh:  # a FIFO, device or folder: refused at once; a read the system
        if os.fstat(fh.fileno()).st_size == 0:  # refuses stays a PermissionError (exit 1), not 'unreadable' (2)
            raise ValueError(f"{p.name}: the file is empty (0 bytes). {_rewrite_fix(p)}")
    if p.suffix.lower() == ".npz":
        arr, names, meta = _read_npz(p)
        where = f"{p.name} meta_json"
    else:
        arr, meta = _read_tiff(p)
        names, where = None, f"{p.name} {'OME annotation' if mapsome.is_ome_tiff(p) else 'ImageDescription'}"
    return _finish(p, arr, names, meta, where)


def _finish(p: Path, arr: np.ndarray, names: np.ndarray | None, meta: dict[str, Any], where: str) -> Maps:
    """The checks every maps format shares, then :class:`Maps`."""
    if arr.dtype.kind != "f":
        raise TypeError(f"{p.name}: maps must be floating point (float32); got {arr.dtype}. {_rewrite_fix(p)}")
    if arr.ndim not in (3, 4) or 0 in arr.shape:
        raise ValueError(
            f"{p.name}: maps must be [C, Z, X] or [C, Y, Z, X] with no empty axis; got shape {list(arr.shape)}"
        )
    channels = meta.get("channels")
    if not isinstance(channels, list) or len(channels) != arr.shape[0]:
        raise ValueError(
            f"{where}: 'channels' must list one entry per map; got "
            f"{len(channels) if isinstance(channels, list) else repr(channels)} for {arr.shape[0]} maps"
        )
    _check_maps_meta(meta, arr.ndim, where)
    meta_names = tuple(ch["name"] for ch in channels)
    keys = [
        (
            ch.get("name"),
            ch.get("wavelength_um"),
            ch.get("lateral_resolution_um"),
            ch.get("axial_resolution_um"),
            ch.get("lateral_resolution_y_um"),
        )
        for ch in channels
    ]
    dup = sorted({str(k[0]) for k in keys if keys.count(k) > 1})
    if dup:  # a reader takes a channel by name and optics: a repeated one would silently pick one of them
        raise ValueError(
            f"{where}: channel(s) {dup} appear more than once with the same wavelength and "
            f"resolutions; every map needs its own name or optics. {_rewrite_fix(p)}"
        )
    if names is not None:
        if names.dtype.kind not in "US":
            raise ValueError(f"{p.name}: 'channels' must be an array of channel names; got dtype {names.dtype}")
        stored = tuple(str(c) for c in np.atleast_1d(names))
        if len(stored) != len(meta_names):
            raise ValueError(f"{p.name}: 'channels' holds {len(stored)} names for {len(meta_names)} maps")
        for i, (a, b) in enumerate(zip(meta_names, stored)):
            if a != b:
                raise ValueError(
                    f"{where}: channels[{i}].name {a!r} differs from the channel name {b!r} (the file "
                    "was not written by torchdoct maps or was edited; recompute the maps)"
                )
    return Maps(maps=arr.astype(np.float32, copy=False), channels=meta_names, meta=meta, path=p)


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """``maps``, the ``channels`` names (None when absent) and the parsed ``meta_json`` of a maps
    ``.npz``; never unpickles."""
    import zipfile
    import zlib

    unreadable = (zipfile.BadZipFile, EOFError, OSError, zlib.error)
    check_npz_sizes(path)  # declared sizes within the input limit, before anything is decompressed
    with open(path, "rb") as fh:  # our handle: numpy leaves its own open when the archive is damaged
        try:
            z = np.load(fh, allow_pickle=False)
        except (*unreadable, ValueError) as err:
            fh.seek(0)
            if "Object arrays" in str(err) or fh.read(1) == b"\x80":  # a .npy of objects, or a pickle stream
                raise ValueError(
                    f"{path.name}: holds Python objects (a pickle), not a maps archive; pickles are never "
                    f"loaded (loading one can run code). {_rewrite_fix(path)}"
                ) from None
            raise ValueError(
                f"{path.name}: not a readable .npz archive: the file is truncated, corrupted or not "
                f"a .npz file ({err}). {_rewrite_fix(path)}"
            ) from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(
                f"{path.name}: holds one bare array, not a maps archive ('maps', 'channels', "
                f"'meta_json'). {_rewrite_fix(path)}"
            )
        arrays = _npz_arrays(path, z, unreadable)
    raw = arrays["meta_json"]
    if raw.dtype.kind not in "US" or raw.size != 1:
        raise ValueError(
            f"{path.name}: 'meta_json' must be a JSON text (a 0-d string array); got a "
            f"{raw.dtype} array of shape {list(raw.shape)}. {_rewrite_fix(path)}"
        )
    from ..files import check_nesting

    check_nesting(str(raw.reshape(())), f"{path.name}: 'meta_json'")  # before the parser's recursion
    try:
        meta = json_loads(str(raw.reshape(())))
    except ValueError as err:
        raise ValueError(f"{path.name}: 'meta_json' is not valid JSON ({err}). {_rewrite_fix(path)}") from None
    if not isinstance(meta, dict):
        raise ValueError(
            f"{path.name}: 'meta_json' must be a JSON object ({{\"channels\": [...], ...}}); got a "
            f"{type(meta).__name__}. {_rewrite_fix(path)}"
        )
    return arrays["maps"], arrays.get("channels"), meta


def _npz_arrays(path: Path, z, unreadable: tuple[type[BaseException], ...]) -> dict[str, np.ndarray]:
    with z:
        for key in ("maps", "meta_json"):
            if key not in z:
                raise ValueError(
                    f"{path.name}: missing array {key!r} (maps files have 'maps', 'channels', "
                    "'meta_json'; write them with `torchdoct maps`)"
                )
        arrays = {}
        for key in ("maps", "meta_json", "channels"):
            if key not in z:
                continue
            try:
                arrays[key] = z[key]
            except ValueError as err:  # object arrays: numpy refuses them without allow_pickle
                if "pickle" not in str(err) and "Object arrays" not in str(err):
                    raise ValueError(
                        f"{path.name}: array {key!r} is unreadable ({err}). {_rewrite_fix(path)}"
                    ) from None
                raise ValueError(
                    f"{path.name}: array {key!r} holds Python objects (a pickle); pickles are never "
                    "loaded (loading one can run code). Fix: store 'maps' as a float array and "
                    "'meta_json' as a JSON string, as `torchdoct maps` writes them"
                ) from None
            except unreadable as err:
                raise ValueError(
                    f"{path.name}: array {key!r} is truncated or corrupted ({err}). {_rewrite_fix(path)}"
                ) from None
    return arrays


def _tiff_meta(path: Path, tf) -> dict[str, Any]:
    """The JSON maps description (with ``channels``): ImageJ's ``Info``, or the first page's JSON
    ImageDescription in files written before (:func:`torchdoct.measured.imagej.project_description`)."""
    from ..files import check_nesting
    from .imagej import project_description

    text = project_description(tf)
    if text is not None:
        check_nesting(text, f"{path.name}: TIFF ImageDescription")  # before the parser's recursion
        try:
            meta = json_loads(text)
        except (TypeError, ValueError):
            meta = None
        if isinstance(meta, dict) and "channels" in meta:
            return meta
    raise ValueError(
        f"{path.name}: no JSON maps description (with 'channels') in the TIFF ImageDescription; "
        "write it with `torchdoct maps ... --out FILE.tif`"
    )


def _read_tiff(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The image stack and the JSON description of a maps TIFF, restored to ``[C, (Y,) Z, X]``."""
    import tifffile

    try:
        with TiffDamage() as damage, tifffile.TiffFile(path) as tf:
            check_tiff_pages(path, tf)  # one shape on every page, total within the input limit
            if path.name.lower().endswith((".ome.tif", ".ome.tiff")):
                from .mapsome import read_ome_tiff

                data, meta = read_ome_tiff(path, tf)
                damage.check()
                return data, meta
            data = tf.asarray()
            meta = _tiff_meta(path, tf)
            n_ch = len(meta["channels"]) if isinstance(meta.get("channels"), list) else 0
            if len(str(meta.get("axes", "CZX"))) == 4 and n_ch and data.size % n_ch == 0:  # volume pages
                from .imagej import restore_channels

                data = restore_channels(data, n_ch, tf)
            damage.check()
    except ValueError as err:
        if (
            "ImageDescription" in str(err)
            or "OME" in str(err)
            or MAX_INPUT_ENV in str(err)
            or "TIFF pages of two shapes" in str(err)
        ):
            raise
        raise ValueError(
            f"{path.name}: not a readable maps TIFF (truncated or corrupt: {err}). {_rewrite_fix(path)}"
        ) from None
    except Exception as err:  # tifffile raises many types on damaged files (struct, index, OS errors)
        raise ValueError(
            f"{path.name}: not a readable maps TIFF (truncated or corrupt: {type(err).__name__}: "
            f"{err}). {_rewrite_fix(path)}"
        ) from None
    n_ch = len(meta["channels"]) if isinstance(meta.get("channels"), list) else 0
    n_sp = len(str(meta.get("axes", "CZX"))) - 1  # pages are [Z, X] images: restore [C, (Y), Z, X]
    shape = (n_ch, -1, *data.shape[-2:]) if n_sp == 3 else (n_ch, *data.shape[-2:])
    try:
        data = data.reshape(shape)
    except ValueError:
        raise ValueError(
            f"{path.name}: a stack of shape {list(data.shape)} does not hold {n_ch} channels "
            f"of axes {meta.get('axes')!r}"
        ) from None
    return data, meta


def _check_maps_meta(meta: dict, ndim: int, where: str) -> None:
    """The fields of a maps file's metadata that readers use, with their types and ranges: one dict per
    channel with the text fields ``name``, ``metric``, ``unit``, ``resolution`` and the optics (µm, > 0,
    or null when unknown); ``axes`` ``C`` + ``ZX``/``YZX`` of the stack's rank; ``pitch_um`` a dict of
    positive µm; ``system``, ``reduction``, ``signature`` tables; ``frame_times_s`` a list of times (s);
    ``ocds_delay_range_s`` ``[low, high]`` (s); the system's lengths and refractive index positive."""
    fix = "the file was not written by torchdoct maps or was edited; recompute the maps"

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def fail(key: str, want: str, got: Any) -> None:
        raise ValueError(f"{where}: {key} must be {want}; got {got!r} ({fix})")

    for i, ch in enumerate(meta["channels"]):
        if not isinstance(ch, Mapping):
            fail(f"channels[{i}]", f"an object with {', '.join(_CHANNEL_TEXT)} and the optics", ch)
        for key in _CHANNEL_TEXT:
            if not isinstance(ch.get(key), str):
                fail(f"channels[{i}].{key}", "a string", ch.get(key))
        for key in _CHANNEL_OPTICS:
            v = ch.get(key)
            if v is not None and not (number(v) and v > 0):
                fail(f"channels[{i}].{key}", "a number > 0 (µm) or null", v)
    axes = meta.get("axes")
    if axes is not None and axes != ("CZX" if ndim == 3 else "CYZX"):
        fail("axes", f"{'CZX' if ndim == 3 else 'CYZX'} for maps of rank {ndim}", axes)
    for key in ("system", "reduction", "pitch_um", "signature"):
        if meta.get(key) is not None and not isinstance(meta[key], Mapping):
            fail(key, "a table (JSON object)" + (" of positive µm per axis" if key == "pitch_um" else ""), meta[key])
    for key, value in (meta.get("pitch_um") or {}).items():
        if not (number(value) and value > 0):
            fail(f"pitch_um.{key}", "a positive number (µm)", value)
    times = meta.get("frame_times_s")
    if times is not None and not (isinstance(times, list) and all(number(t) for t in times)):
        fail("frame_times_s", "a list of times (s)", times)
    delays = meta.get("ocds_delay_range_s")
    if delays is not None and not (isinstance(delays, list) and len(delays) == 2 and all(number(t) for t in delays)):
        fail("ocds_delay_range_s", "[low, high] (s)", delays)
    for key, value in (meta.get("system") or {}).items():
        if (key.endswith("_um") or key == "refractive_index") and value is not None:
            if not (number(value) and value > 0):
                fail(f"system.{key}", "a positive number or null", value)

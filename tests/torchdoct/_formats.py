"""Writers of one sequence in every format the readers take, each with its metadata in the format's own
fields (sidecar JSON for .npy, .mat and raw; OME-XML for OME-TIFF; the multiscales scale for OME-Zarr),
for the format tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PITCH = {"z": 1.0, "x": 1.5}
DT_S = 0.05


def field(t: int = 32, z: int = 12, x: int = 16, seed: int = 0) -> np.ndarray:
    """A complex64 speckle-like field [T, Z, X]: circular Gaussian samples, a slow drift of the phase."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((t, z, x)) + 1j * rng.standard_normal((t, z, x))
    return e.astype(np.complex64)


def sidecar(path: Path, **extra) -> None:
    meta = {"axes": "TZX", "pitch_um": PITCH, "frame_times_s": [k * DT_S for k in range(extra.pop("t"))]}
    meta.update(extra)
    path.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")


def write_npy(path: Path, a: np.ndarray) -> Path:
    np.save(path, a)
    sidecar(path, t=a.shape[0])
    return path


def write_mat(path: Path, a: np.ndarray) -> Path:
    import scipy.io as sio

    sio.savemat(path, {"E": np.ascontiguousarray(a.transpose(1, 2, 0))})  # MATLAB E(z, x, t)
    sidecar(path, t=a.shape[0], axes="ZXT")
    return path


def write_raw(path: Path, a: np.ndarray, header: bytes = b"HEAD" * 4, big: bool = True) -> Path:
    dt = a.dtype.newbyteorder(">" if big else "<")
    path.write_bytes(header + a.astype(dt).tobytes())
    sidecar(
        path,
        t=a.shape[0],
        dtype=a.dtype.name,
        shape=list(a.shape),
        byte_order="big" if big else "little",
        header_bytes=len(header),
    )
    return path


def write_ome_tiff(path: Path, a: np.ndarray, per_plane: bool = False) -> Path:
    import tifffile

    md = {
        "axes": "TYX",
        "PhysicalSizeX": PITCH["x"] * 1000,
        "PhysicalSizeXUnit": "nm",
        "PhysicalSizeY": PITCH["z"],
        "PhysicalSizeYUnit": "µm",
    }
    if per_plane:
        md["Plane"] = {"DeltaT": [k * DT_S * 1000 for k in range(a.shape[0])], "DeltaTUnit": ["ms"] * a.shape[0]}
    else:
        md.update(TimeIncrement=DT_S * 1000, TimeIncrementUnit="ms")
    tifffile.imwrite(path, a, ome=True, metadata=md)
    return path


def write_ome_zarr(path: Path, a: np.ndarray, version: str = "0.4", chunks: tuple[int, ...] | None = None) -> Path:
    import zarr

    axes = [
        {"name": "t", "type": "time", "unit": "millisecond"},
        {"name": "y", "type": "space", "unit": "micrometer"},
        {"name": "x", "type": "space", "unit": "micrometer"},
    ]
    ms = {
        "axes": axes,
        "datasets": [
            {
                "path": "0",
                "coordinateTransformations": [{"type": "scale", "scale": [DT_S * 1000, PITCH["z"], PITCH["x"]]}],
            }
        ],
        "name": "sequence",
    }
    group = zarr.open_group(str(path), mode="w", zarr_format=2 if version == "0.4" else 3)
    arr = group.create_array("0", shape=a.shape, dtype=a.dtype, chunks=chunks or (4, *a.shape[1:]))
    arr[:] = a
    if version == "0.4":
        group.attrs["multiscales"] = [{"version": "0.4", **ms}]
    else:
        group.attrs["ome"] = {"version": "0.5", "multiscales": [ms]}
    return path


def write_tiff_folder(path: Path, a: np.ndarray) -> Path:
    import tifffile

    path.mkdir()
    for k, frame in enumerate(a):
        tifffile.imwrite(path / f"frame{k}.tif", frame)
    sidecar(path, t=a.shape[0])
    return path


def maps(volume: bool):
    """Small maps (LIV, OCDS, mean dB at the original resolution; one NaN) as a B-scan or a volume."""
    from torchdoct.measured.mapsfile import Maps

    rng = np.random.default_rng(1)
    shape = (3, 5, 12, 16) if volume else (3, 12, 16)
    names = ["liv@original", "ocds@original", "mean_db@original"]
    units = ["dB²", "1/s", "dB"]
    chans = [
        {
            "name": n,
            "metric": n.split("@")[0],
            "unit": u,
            "resolution": "original",
            "wavelength_um": 0.84,
            "lateral_resolution_um": 4.0,
            "axial_resolution_um": 3.0,
        }
        for n, u in zip(names, units)
    ]
    pitch = {"z": 1.9, "y": 7.5, "x": 2.5} if volume else {"z": 1.9, "x": 2.5}
    data = rng.standard_normal(shape).astype(np.float32)
    data[0, ..., 0, 0] = np.nan
    meta = {
        "axes": "CYZX" if volume else "CZX",
        "pitch_um": pitch,
        "channels": chans,
        "system": {"name": "lab", "wavelength_um": 0.84},
        "frame_times_s": [0.0, 0.2],
    }
    return Maps(maps=data, channels=tuple(names), meta=meta)

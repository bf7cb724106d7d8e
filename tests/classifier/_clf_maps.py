"""Synthetic maps files in the project's maps format (see torchdoct.measured.io), for the classify tests."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from classifier.features import FeatureSpec, metric_unit


def maps_meta(
    spec: FeatureSpec,
    channels: list[dict[str, Any]],
    *,
    pitch_um=None,
    n_frames=None,
    frame_interval_s=None,
    ocds_delay_range_s=None,
    refractive_index=None,
    axes="CZX",
) -> dict[str, Any]:
    c0 = spec.configurations[0]
    n = spec.n_frames if n_frames is None else n_frames
    dt = spec.frame_interval_s if frame_interval_s is None else frame_interval_s
    return {
        "channels": channels,
        "axes": axes,
        "pitch_um": pitch_um if pitch_um is not None else {"z": 2.0, "x": 2.0},
        "frame_times_s": [i * dt for i in range(n)],
        "system": {
            "name": "synthetic",
            "wavelength_um": c0.wavelength_um,
            "lateral_resolution_um": c0.lateral_resolution_um,
            "axial_resolution_um": c0.axial_resolution_um,
            "refractive_index": spec.refractive_index if refractive_index is None else refractive_index,
        },
        "ocds_delay_range_s": list(spec.ocds_delay_range_s if ocds_delay_range_s is None else ocds_delay_range_s),
        "source": "synthetic.npy",
    }


def feature_channels(spec: FeatureSpec, with_mean_db: bool = True) -> list[dict[str, Any]]:
    out = []
    for metric, c in spec.features:
        out.append(
            {
                "name": f"{metric}@{c.name}",
                "metric": metric,
                "unit": metric_unit(metric),
                "resolution": c.name,
                "wavelength_um": c.wavelength_um,
                "lateral_resolution_um": c.lateral_resolution_um,
                "axial_resolution_um": c.axial_resolution_um,
            }
        )
    if with_mean_db:
        c = spec.configurations[0]
        out.append(
            {
                "name": f"mean_db@{c.name}",
                "metric": "mean_db",
                "unit": "dB",
                "resolution": c.name,
                "wavelength_um": c.wavelength_um,
                "lateral_resolution_um": c.lateral_resolution_um,
                "axial_resolution_um": c.axial_resolution_um,
            }
        )
    return out


def save_maps(path: Path, data: np.ndarray, meta: dict[str, Any]) -> Path:
    path = Path(path)
    data = np.asarray(data, np.float32)
    if path.suffix == ".npz":
        np.savez(
            path,
            maps=data,
            channels=np.array([c["name"] for c in meta["channels"]]),
            meta_json=np.asarray(json.dumps(meta)),
        )
    else:
        import tifffile

        tifffile.imwrite(path, data, description=json.dumps(meta), metadata=None, photometric="minisblack")
    return path

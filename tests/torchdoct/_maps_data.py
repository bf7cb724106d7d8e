"""Synthetic LIV/OCDS maps for the comparison tests (imported by module name, never through ``conftest``)."""

from __future__ import annotations

import numpy as np

from torchdoct.measured.io import Maps

RES = {
    "original": (4.9, 3.8),
    "axial=7.6": (4.9, 7.6),
    "axial=11.4": (4.9, 11.4),
    "axial=14": (4.9, 14.0),
    "axial=14,lateral=18": (18.0, 14.0),
}


def make_maps(rng, resolutions, *, wavelength=0.84, shift=None, shape=(6, 7), nan_at=None, source="s.npy"):
    """Maps with liv, ocds, mean_db per resolution; liv/ocds offset by ``shift[resolution]``."""
    shift = shift or {}
    arrays, chans = [], []
    for r in resolutions:
        lat, ax = RES[r]
        for metric, base, unit in (("liv", 10.0, "dB^2"), ("ocds", 0.5, "1/s"), ("mean_db", 20.0, "dB")):
            a = base + rng.normal(0, 1.0 if metric != "ocds" else 0.05, shape)
            if metric != "mean_db":
                a = a + shift.get(r, 0.0) * (1.0 if metric == "liv" else 0.01)
            else:
                a[0] = 0.0  # a dark row for the threshold tests
            if nan_at is not None and metric == "liv":
                a[nan_at] = np.nan
            arrays.append(a)
            chans.append(
                {
                    "name": f"{metric}@{r}",
                    "metric": metric,
                    "unit": unit,
                    "resolution": r,
                    "wavelength_um": wavelength,
                    "lateral_resolution_um": lat,
                    "axial_resolution_um": ax,
                }
            )
    meta = {
        "channels": chans,
        "axes": "CZX",
        "pitch_um": {"z": 1.5, "x": 2.0},
        "frame_times_s": [0.0, 0.2],
        "system": {},
        "ocds_delay_range_s": [0.2048, 1.2288],
        "source": source,
    }
    return Maps(maps=np.array(arrays, dtype=np.float32), channels=[c["name"] for c in chans], meta=meta)

"""The four-slab phantom of the end-to-end test and its chain, shared by the test
(``tests/classifier/test_clf_end_to_end.py``) and the command that records its floors
(``python -m tests.reference.floors slabs``).

The phantom stacks four 64-µm slabs (diffusion D = 0.002 µm²/s, random-ballistic v = 0.1 µm/s,
flow v = 1 µm/s at 60° from depth, static), all at 0.06 µm⁻³ and 30 dB SNR: the first three are
identifiable by the ground-truth definition (classifier.truth), the static one is indeterminate.
Pixels within 16 µm of a slab boundary are not scored (the axial reduction to 14 µm mixes slabs).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

CODES = {2: 0, 3: 1, 4: 2}  # render's motion codes (torchdoct.image.phantom.MOTION_CODES) -> classifier labels
STATIC = 1

PHANTOM = """
name = "four-slabs"
description = "diffusion / random-ballistic / flow / static slabs (classifier end-to-end test)"
[[system]]
name = "840nm-high"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[protocol]
n_frames = 32
frame_interval_s = 0.2048
[grid]
{grid}
[[region]]
name = "diffusing"
shape = "slab"
z_min_um = -128.0
z_max_um = -64.0
density_per_um3 = 0.06
[[region.motion]]
kind = "diffusion"
diffusion_um2_per_s = 0.002
[[region]]
name = "ballistic"
shape = "slab"
z_min_um = -64.0
z_max_um = 0.0
density_per_um3 = 0.06
[[region.motion]]
kind = "ballistic"
speed_um_per_s = 0.1
[[region]]
name = "flowing"
shape = "slab"
z_min_um = 0.0
z_max_um = 64.0
density_per_um3 = 0.06
[[region.motion]]
kind = "flow"
speed_um_per_s = 1.0
polar_angle_deg = 60.0
azimuth_deg = 0.0
[[region]]
name = "static"
shape = "slab"
z_min_um = 64.0
z_max_um = 128.0
density_per_um3 = 0.06
[noise]
snr_db = 30.0
[analysis]
metrics = ["liv", "ocds"]
ocds_delay_range_s = [0.2048, 1.2288]
[simulation]
seed = 7
"""
BSCAN = 'kind = "bscan"\nn_x = 96\nn_z = 128\npitch_x_um = 2.0\npitch_z_um = 2.0'
VOLUME = 'kind = "volume"\nn_y = 24\nn_x = 48\nn_z = 128\npitch_x_um = 2.0\npitch_y_um = 2.0\npitch_z_um = 2.0'
#: The geometries: (grid table, depth axis of the labels).
GEOMETRIES = {"bscan": (BSCAN, 0), "volume": (VOLUME, 1)}
#: The phantom's own rendering seed (``[simulation] seed``), the one the test renders.
SEED = 7
#: The scores of :func:`score` a floor is recorded for.
FLOORED = ("balanced", "mean_coverage", "static_indeterminate")


def run_chain(work: Path, grid: str, seed: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """render (the phantom's own seed, or ``seed``) → maps → ``doct-classify --pool 5 --decision rule
    --decide-ballistic`` in ``work``: the ground-truth labels, the decided classes and the summary."""
    import tifffile

    from classifier.cli import classify_main
    from torchdoct.cli import main as torchdoct_main

    phantom = work / "phantom.toml"
    phantom.write_text(PHANTOM.format(grid=grid), encoding="utf-8")
    seq, maps, out = work / "seq.npz", work / "maps.npz", work / "classified"
    seeded = [] if seed is None else ["--seed", str(seed)]
    assert torchdoct_main(["render", str(phantom), *seeded, "--out", str(seq), "--no-progress", "--no-preview"]) == 0
    resolutions = ["--resolution", "original", "--resolution", "axial=14", "--resolution", "lateral=18"]
    assert torchdoct_main(["maps", str(seq), *resolutions, "--out", str(maps), "--no-progress"]) == 0
    # the model's own argmax decisions, which the reference scores (its default conformal sets answer most
    # pixels of LIV/OCDS maps with a set; the default's ballistic-or-flow: test_clf_ambiguity)
    argv = [str(maps), "--out", str(out), "--pool", "5", "--threads", "1", "--decision", "rule", "--decide-ballistic"]
    assert classify_main(argv) == 0
    with np.load(seq) as z:
        truth = z["labels"]
    decided = tifffile.imread(out / "classes.tif")
    summary = json.loads((out / "summary.json").read_text())
    assert decided.shape == truth.shape
    return truth, decided, summary


def score(truth: np.ndarray, decided: np.ndarray, z_axis: int) -> dict:
    """Per motion slab (away from the boundaries) the decided share and the recall of the decided pixels;
    the balanced accuracy; the share of the static slab left indeterminate."""
    zc = (np.arange(truth.shape[z_axis]) - (truth.shape[z_axis] - 1) / 2) * 2.0
    keep_z = np.all([np.abs(zc - b) >= 16.0 for b in (-64.0, 0.0, 64.0)], axis=0)
    shape = [1] * truth.ndim
    shape[z_axis] = -1
    inner = np.broadcast_to(keep_z.reshape(shape), truth.shape)
    out = {"recall": [], "coverage": []}
    for code, label in CODES.items():
        v = decided[(truth == code) & inner]
        dec = v < 3
        out["coverage"].append(float(dec.mean()))
        out["recall"].append(float((v[dec] == label).mean()))
    v = decided[(truth == STATIC) & inner]
    out["static_indeterminate"] = float((v == 3).mean())
    out["balanced"] = float(np.mean(out["recall"]))
    out["mean_coverage"] = float(np.mean(out["coverage"]))
    return out

"""Scene texts shared by the test suite (imported by module name, never through ``conftest``)."""

from __future__ import annotations

import textwrap

SMALL_SCENE_TOML = textwrap.dedent("""\
    name = "small-file"
    description = "one system, 8 frames, diffusing scatterers (test scene)"

    [[system]]
    name = "840nm"
    wavelength_um = 0.84
    lateral_resolution_um = 4.9
    axial_resolution_um = 3.8

    [protocol]
    n_frames = 8
    frame_interval_s = 0.2048

    [[population]]
    density_per_um3 = 0.055

    [[population.motion]]
    kind = "diffusion"
    diffusion_um2_per_s = 0.1

    [analysis]
    metrics = ["liv", "ocds"]
    ocds_delay_range_s = [0.2048, 0.6144]

    [simulation]
    trials = 64
    seed = 7
    """)

#: A 16-cell diffusion sweep (D from 0.001 to 3 µm²/s, 16 frames) with ``{trials}`` trials per cell: the sweeps
#: that are interrupted, killed and resumed (``.format(trials=N)``).
DIFFUSION_SWEEP_TOML = """
name = "diffusion-sweep"
[[system]]
name = "840nm"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8
[protocol]
n_frames = 16
frame_interval_s = 0.2048
[[population]]
density_per_um3 = 0.055
[[population.motion]]
kind = "diffusion"
diffusion_um2_per_s = 0.1
[analysis]
metrics = ["liv", "ocds"]
ocds_delay_range_s = [0.2048, 1.2288]
[simulation]
trials = {trials}
seed = 5
[sweep]
[[sweep.field]]
path = "population.0.motion.0.diffusion_um2_per_s"
log = {{ start = 0.001, stop = 3.0, num = 16 }}
"""

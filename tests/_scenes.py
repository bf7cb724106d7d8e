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

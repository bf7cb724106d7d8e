"""Patch simulation (torchdoct.sim.patch) against physics.md §5.2-5.4 and docs/concepts/speckle-motion.md §3.

Tolerances: z = 3.5 standard errors of the mean over independent trials (the centre pixel's window per
trial)."""

from __future__ import annotations

import math

import pytest
import torch

from torchdoct.conventions import mean_intensity, n_eff
from torchdoct.sim.patch import simulate_patch
from torchdoct.sim.speckle import speckle_motion

Z_SE = 3.5
DT = 0.2048
PITCH = {"z": 2.0, "x": 2.0}


def _mean_se(v: torch.Tensor) -> tuple[float, float]:
    return float(v.mean()), float(v.std() / math.sqrt(v.numel()))


def test_static_patch_has_the_mean_intensity_and_contrast_of_the_poisson_medium():
    e = simulate_patch("static", trials=400, seed=3, shape=(3, 3), n_frames=2, dtype=torch.complex128)
    i = (e[:, 0].abs() ** 2)[:, 1, 1]  # one pixel per independent trial
    mean, se = _mean_se(i)
    expect = mean_intensity(0.055, 4.9, 3.8)
    assert abs(mean - expect) < Z_SE * se
    c2 = i / expect
    m2, se2 = _mean_se(c2**2)  # ⟨I²⟩/⟨I⟩² = 2 + 1/N_eff (physics.md §5.4)
    assert abs(m2 - (2.0 + 1.0 / n_eff(0.055, 4.9, 3.8))) < Z_SE * se2


@pytest.fixture(scope="module")
def flow_features():
    v, polar, azimuth = 0.3, 45.0, 60.0
    e = simulate_patch("flow", trials=40, seed=1, speed_um_s=v, polar_deg=polar, azimuth_deg=azimuth)
    names = ("xc_velocity_z", "xc_velocity_x", "xc_shift_z_16", "xc_shift_x_16")
    _, f = speckle_motion(e, PITCH, DT, names)
    t, p = math.radians(polar), math.radians(azimuth)
    return (v * math.cos(t), v * math.sin(t) * math.cos(p)), f[:, :, 6, 6]


def test_flow_patch_moves_its_speckle_at_the_in_plane_velocity(flow_features):
    (vz, vx), f = flow_features
    for i, expect in enumerate((vz, vx, vz * 16 * DT, vx * 16 * DT)):
        mean, se = _mean_se(f[:, i])
        assert abs(mean - expect) < Z_SE * se, (i, mean, expect, se)
        assert se < 0.25 * abs(expect)


@pytest.mark.parametrize(
    "motion, kwargs", [("ballistic", {"speed_um_s": 0.12}), ("diffusion", {"diffusion_um2_s": 0.03})]
)
def test_direction_symmetric_patches_stay_centred(motion, kwargs):
    e = simulate_patch(motion, trials=24, seed=2, **kwargs)
    _, f = speckle_motion(e, PITCH, DT, ("xc_velocity_z", "xc_velocity_x"))
    for i in range(2):
        mean, se = _mean_se(f[:, i, 6, 6])
        assert abs(mean) < Z_SE * se, (motion, i, mean, se)


def test_a_trial_is_the_same_whatever_the_number_of_trials():
    a = simulate_patch("ballistic", trials=2, seed=9, speed_um_s=0.1, shape=(5, 5), n_frames=4)
    b = simulate_patch("ballistic", trials=3, seed=9, speed_um_s=0.1, shape=(5, 5), n_frames=4)
    assert torch.equal(a, b[:2])
    assert not torch.equal(b[1], b[2])


def test_volume_patch_has_its_axes_and_static_share():
    e = simulate_patch(
        "diffusion",
        trials=1,
        seed=0,
        shape=(3, 4, 5),
        pitch_um=(2.0, 2.0, 2.0),
        n_frames=3,
        diffusion_um2_s=0.01,
        static_fraction=0.5,
        snr_db=20.0,
    )
    assert e.shape == (1, 3, 3, 4, 5) and bool(torch.isfinite(e).all())


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"motion": "swim"}, "motion"),
        ({"static_fraction": 1.0}, "static"),
        ({"speed_um_s": 1e4, "motion": "ballistic"}, "expected scatterers"),
    ],
)
def test_bad_patch_requests_are_refused(kwargs, match):
    args = {"motion": "flow", "trials": 1, "seed": 0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        simulate_patch(**args)

"""Shared fixtures: a guard on global torch state, a small scene and a scene file."""

from __future__ import annotations

import os

# One thread per pool (torch, OpenMP, OpenBLAS) for every library loaded from here on: parallel
# regions stall when another process is busy (torchdoct.runtime.threads); set before numpy and torch load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest
import threadpoolctl
import torch
from _scenes import SMALL_SCENE_TOML

import torchdoct

# The threading policy of torchdoct (torchdoct.runtime.threads): tensor operations run on one torch thread;
# parallel work runs over independent pieces. Tests that call torch directly follow it too.
torch.set_num_threads(1)
_BLAS_ONE_THREAD = threadpoolctl.threadpool_limits(1)  # numpy's BLAS (reference renderers) likewise


@pytest.fixture(autouse=True)
def guard_global_torch_state():
    """Every test must leave the default dtype and the global RNG untouched.

    The simulator draws only from its own ``torch.Generator``s; tests that need randomness must use
    a local generator too (``torch.Generator().manual_seed(...)`` or numpy's ``default_rng``).
    """
    dtype = torch.get_default_dtype()
    rng_state = torch.get_rng_state().clone()
    yield
    assert torch.get_default_dtype() == dtype, f"default dtype changed from {dtype} to {torch.get_default_dtype()}"
    assert torch.equal(torch.get_rng_state(), rng_state), "the global torch RNG state was changed"


@pytest.fixture
def small_scene() -> torchdoct.Scene:
    """One 840-nm system (4.9/3.8 µm), 8 frames at 0.2048 s, one diffusing population."""
    return torchdoct.Scene(
        name="small",
        systems=(
            torchdoct.OCTSystem(name="840nm", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8),
        ),
        protocol=torchdoct.Protocol(n_frames=8, frame_interval_s=0.2048),
        populations=(
            torchdoct.Population(density_per_um3=0.055, motion=(torchdoct.Diffusion(diffusion_um2_per_s=0.1),)),
        ),
        analysis=torchdoct.Analysis(metrics=("liv", "ocds"), ocds_delay_range_s=(0.2048, 0.6144)),
    )


@pytest.fixture
def tmp_scene_file(tmp_path):
    """Path of a valid TOML scene file (the same scene as ``small_scene``, 64 trials, seed 7)."""
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENE_TOML, encoding="utf-8")
    return path

"""Every shipped scene plans and simulates, with finite metrics for every system."""

from __future__ import annotations

import pytest
import torch

import torchdoct as td

_HEAVY = {"paper-diffusion", "flowing-diffusers"}  # tens of ms per trial: slow suite


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in _HEAVY else n for n in sorted(td.shipped_scenes())]
)
def test_shipped_scene_simulates(name):
    scene = td.load_scene(name)
    plan = td.make_plan(scene)
    assert plan.expected_scatterers_per_trial > 0
    res = td.simulate(scene, trials=64, seed=1)
    assert res.signals.shape == (64, len(scene.systems), scene.protocol.n_frames)
    m = res.metrics()
    for key in scene.analysis.metrics:
        assert bool(torch.isfinite(m[key]).all()), key
    summary = res.summary()
    assert set(summary) == {s.name for s in scene.systems}

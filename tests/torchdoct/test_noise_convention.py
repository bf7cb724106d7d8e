"""The noise level from an SNR in dB (torchdoct.conventions.noise_power, noise_sigma; physics.md §5.2, §8):
closed forms, the types it keeps, the one place that converts, and the callers that use it."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from torchdoct.conventions import mean_intensity, noise_power, noise_sigma

REPO = Path(__file__).resolve().parents[2]


def test_closed_forms():
    assert noise_power(3.0, 0.0) == 3.0  # 0 dB: noise as strong as the signal
    assert noise_power(2.0, 10.0) == pytest.approx(0.2, rel=1e-15)
    assert noise_power(1.0, -20.0) == pytest.approx(100.0, rel=1e-15)
    # the power splits evenly between the two quadratures
    for i_mean, snr in ((1.0, 0.0), (0.37, 17.3), (5e-3, 42.0)):
        assert 2.0 * noise_sigma(i_mean, snr) ** 2 == pytest.approx(noise_power(i_mean, snr), rel=1e-15)
    # each 10 dB divides the power by 10 and the standard deviation by √10
    assert noise_sigma(1.0, 10.0) / noise_sigma(1.0, 20.0) == pytest.approx(math.sqrt(10.0), rel=1e-15)


def test_numbers_tensors_and_arrays_keep_their_type():
    assert type(noise_sigma(1.0, 20.0)) is float
    t = torch.tensor([1.0, 2.5], dtype=torch.float32)
    s = noise_sigma(t, 13.0)
    assert s.dtype == torch.float32 and torch.equal(s, torch.sqrt(t / 10.0 ** (13.0 / 10.0) / 2.0))
    a = np.array([1.0, 2.5])
    assert isinstance(noise_sigma(a, 13.0), np.ndarray)
    np.testing.assert_array_equal(noise_sigma(a, 13.0), np.sqrt(a / 10.0**1.3 / 2.0))


def test_no_other_module_converts_an_snr():
    """The dB-to-power step ``10^(SNR/10)`` is written in conventions.py only."""
    pattern = re.compile(r"10(\.0)?\s*\*\*\s*\(\s*-?\s*(float\()?\s*snr", re.IGNORECASE)
    found = []
    for pkg in ("torchdoct", "classifier"):
        for path in (REPO / pkg).rglob("*.py"):
            if path.name == "conventions.py" and path.parent.name == "torchdoct":
                continue
            if pattern.search(path.read_text(encoding="utf-8")):
                found.append(str(path.relative_to(REPO)))
    assert found == []


def test_the_plan_and_the_training_data_use_it():
    import torchdoct as td
    from classifier.nuisance import combine_fields
    from torchdoct.sim.plan import make_plan

    system = td.OCTSystem(name="s", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    sc = td.Scene(
        systems=(system,),
        protocol=td.Protocol(n_frames=4, frame_interval_s=0.2),
        populations=(td.Population(density_per_um3=0.05),),
        noise=td.Noise(snr_db=12.5),
        analysis=td.Analysis(metrics=("liv",)),
    )
    sp = make_plan(sc).systems[0]
    assert sp.mean_intensity == mean_intensity(0.05, 4.9, 3.8)
    assert sp.noise_power == noise_power(sp.mean_intensity, 12.5)
    # the training data's noise on a zero field: per-quadrature variance σ² within 4 standard errors
    zero = torch.zeros(4096, 2, 16, dtype=torch.complex64)
    mean_i = [1.0, 0.25]
    n = combine_fields(zero, None, 0.0, 20.0, mean_i, torch.Generator().manual_seed(0))
    for k, m in enumerate(mean_i):
        x = torch.cat([n[:, k].real.flatten(), n[:, k].imag.flatten()]).double()
        var = float(x.var())
        se = var * math.sqrt(2.0 / (x.numel() - 1))  # Gaussian: SE of the sample variance
        assert abs(var - noise_sigma(m, 20.0) ** 2) <= 4 * se

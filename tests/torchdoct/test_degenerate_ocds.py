"""Degenerate OCDS estimators (issue class 7): a delay of the OCDS fit that rests on fewer than
MIN_PAIRS_PER_DELAY frame pairs is refused (Python API, scene files, maps), naming the delay, its pairs
and the fix; the number comes from the lag correlation's variance (docs/reliability.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _refusal import refused

import torchdoct as td
from torchdoct.sim.config import MIN_PAIRS_PER_DELAY, SceneError, delay_pair_counts, scene_from_dict

DT = 0.2048


def _times(n):
    return [DT * i for i in range(n)]


def test_three_frame_ocds_is_refused_not_minus_two_over_dt():
    x = torch.rand(16, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) + 0.5
    with pytest.raises(ValueError, match=r"delay 0\.4096 s, which rests on 1 frame pair\(s\).*no estimate"):
        td.ocds(x, _times(3), delay_range_s=(DT, 2 * DT))


@pytest.mark.parametrize("n_frames,accepted", [(6, False), (7, True)])
def test_the_pair_floor_is_exact_at_its_boundary(n_frames, accepted):
    """Lags 1-5: the longest rests on n_frames - 5 pairs (1 refused, 2 accepted)."""
    x = torch.rand(8, n_frames, generator=torch.Generator().manual_seed(2), dtype=torch.float64) + 0.5
    if accepted:
        assert torch.isfinite(td.ocds(x, _times(n_frames), delay_range_s=(DT, 5 * DT))).all()
    else:
        with pytest.raises(ValueError, match=r"delay 1\.024 s, which rests on 1 frame pair.*up to 0\.8192 s"):
            td.ocds(x, _times(n_frames), delay_range_s=(DT, 5 * DT))


def test_non_uniform_frame_times_count_the_pairs_of_each_delay():
    counts = dict(delay_pair_counts([0.0, 1.0, 2.0, 4.0]))
    assert counts == {1.0: 2, 2.0: 2, 3.0: 1, 4.0: 1}
    x = torch.ones(2, 4, dtype=torch.float64) + torch.arange(4.0, dtype=torch.float64)
    assert torch.isfinite(td.ocds(x, [0.0, 1.0, 2.0, 4.0], delay_range_s=(1.0, 2.0))).all()
    with pytest.raises(ValueError, match="delay 3 s, which rests on 1 frame pair"):
        td.ocds(x, [0.0, 1.0, 2.0, 4.0], delay_range_s=(1.0, 3.0))


def test_a_scene_with_too_few_frames_for_its_delay_range_is_refused():
    d = {
        "system": [{"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}],
        "protocol": {"n_frames": 8, "frame_interval_s": DT},
        "population": [{"density_per_um3": 0.05}],
        "analysis": {"metrics": ["liv", "ocds"], "ocds_delay_range_s": [DT, 7 * DT]},
    }
    with pytest.raises(SceneError, match=r"analysis\.ocds_delay_range_s.*1\.4336 s.*1 frame pair.*n_frames"):
        scene_from_dict(d)
    d["analysis"]["ocds_delay_range_s"] = [DT, 6 * DT]
    scene_from_dict(d)  # lag 6 rests on 2 pairs


def test_maps_refuse_a_degenerate_delay_range_naming_the_file_and_the_option(tmp_path, capsys, seq):
    line = refused(
        capsys,
        tmp_path,
        [
            "maps",
            str(seq),
            "--ocds-delay-range-s",
            "0.2048",
            "1.4336",
            "--out",
            str(tmp_path / "m.npz"),
            "--no-progress",
        ],
        "seq.npy",
        "--ocds-delay-range-s",
        "1 frame pair",
    )
    assert "--metrics" in line


@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_the_null_variance_of_a_pearson_coefficient_is_one_over_n_minus_one(n):
    """The premise of MIN_PAIRS_PER_DELAY: without correlation, Var r = 1/(N − 1), finite from N = 2 on
    (and |r| = 1 for N = 2); Monte Carlo over 200 000 draws, within 5 standard errors."""
    rng = np.random.default_rng(n)
    m = 200_000
    x, y = rng.standard_normal((2, m, n))
    xc, yc = x - x.mean(1, keepdims=True), y - y.mean(1, keepdims=True)
    r = (xc * yc).sum(1) / np.sqrt((xc * xc).sum(1) * (yc * yc).sum(1))
    r2 = r * r
    se = r2.std() / math.sqrt(m)
    assert abs(r2.mean() - 1 / (n - 1)) < 5 * se + 1e-12
    if n == 2:
        assert np.allclose(np.abs(r), 1.0)
    assert n >= MIN_PAIRS_PER_DELAY == 2


def test_one_pair_has_nothing_to_correlate():
    """N = 1: both sides of the pair are one number each; their centred values are 0 and the coefficient
    0/0; the metrics' convention ρ = 1 then holds for any data, so OCDS through it is no estimate."""
    a = torch.tensor([[1.0, 5.0]], dtype=torch.float64)
    b = torch.tensor([[7.0, 2.0]], dtype=torch.float64)
    from torchdoct.sim.metrics import lag_correlations

    _, rho_a = lag_correlations(a, [0.0, DT])
    _, rho_b = lag_correlations(b, [0.0, DT])
    assert rho_a.item() == rho_b.item() == 1.0


@pytest.mark.parametrize(
    "n_frames,max_window,accepted", [(3, None, False), (4, None, True), (32, 0.3, False), (32, 0.62, True)]
)
def test_aliv_needs_more_time_windows_than_the_two_parameters_of_its_fit(
    tmp_path, capsys, seq, n_frames, max_window, accepted
):
    import json

    from torchdoct.cli import main

    data = np.load(seq)
    meta = json.loads(seq.with_suffix(".json").read_text())
    idx = np.arange(n_frames) % data.shape[0]
    path = tmp_path / "s.npy"
    np.save(path, data[idx])
    meta["frame_times_s"] = _times(n_frames)
    path.with_suffix(".json").write_text(json.dumps(meta))
    argv = ["maps", str(path), "--metrics", "liv,aliv", "--no-progress", "--out", str(tmp_path / "out" / "m.npz")]
    argv += [] if max_window is None else ["--aliv-max-window-s", str(max_window)]
    (tmp_path / "out").mkdir()
    if accepted:
        assert main(argv) == 0
    else:
        refused(capsys, tmp_path / "out", argv, "s.npy", "at least 3 time windows", "--metrics")

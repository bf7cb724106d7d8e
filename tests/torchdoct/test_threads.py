"""Threading policy (torchdoct.runtime.threads): one torch thread per worker, bit-identical for any thread count."""

from __future__ import annotations

import threading
import time

import pytest
import torch

import torchdoct as td
from torchdoct.cli import main
from torchdoct.runtime import threads as th


def test_simulate_bit_identical_for_any_threads_and_chunking(small_scene):
    ref = td.simulate(small_scene, trials=300, seed=5, threads=1).signals
    for t, chunk in ((2, None), (3, None), (2, 64), (4, 128)):
        out = td.simulate(small_scene, trials=300, seed=5, threads=t, chunk_trials=chunk).signals
        assert torch.equal(out, ref), (t, chunk)


def test_simulate_restores_torch_threads(small_scene):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        td.simulate(small_scene, trials=64, seed=1, threads=2)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_single_torch_thread_nests_and_restores():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with th.single_torch_thread():
            assert torch.get_num_threads() == 1
            with th.single_torch_thread():
                assert torch.get_num_threads() == 1
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_map_ordered_keeps_order_and_bounds_work_in_flight():
    running, peak, lock = [0], [0], threading.Lock()

    def work(i):
        with lock:
            running[0] += 1
            peak[0] = max(peak[0], running[0])
        time.sleep(0.01 * ((7 * i) % 3))  # finish out of order
        with lock:
            running[0] -= 1
        return i * i

    assert list(th.map_ordered(work, range(10), 3)) == [i * i for i in range(10)]
    assert 1 <= peak[0] <= 3
    assert list(th.map_ordered(work, range(4), 1)) == [0, 1, 4, 9]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_thread_counts_are_refused(bad, small_scene):
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        th.resolve_threads(bad)
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        td.simulate(small_scene, trials=64, threads=bad)


def test_default_threads_follow_setting_and_environment(monkeypatch):
    monkeypatch.setenv("TORCHDOCT_THREADS", "3")
    assert th.default_threads() == 3
    with th.using_threads(1):
        assert th.default_threads() == 1
    assert th.default_threads() == 3
    monkeypatch.setenv("TORCHDOCT_THREADS", "many")
    with pytest.raises(ValueError, match="TORCHDOCT_THREADS"):
        th.default_threads()
    monkeypatch.delenv("TORCHDOCT_THREADS")
    assert th.default_threads() >= 1


def test_cli_threads_option(capsys, tmp_path):
    assert main(["simulate", "example", "--trials", "64", "--threads", "0", "--no-progress"]) == 2
    assert "--threads" in capsys.readouterr().err
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert main(["simulate", "example", "--trials", "128", "--threads", "1", "--no-progress", "--out", str(a)]) == 0
    assert main(["simulate", "example", "--trials", "128", "--threads", "2", "--no-progress", "--out", str(b)]) == 0
    import numpy as np

    with np.load(a) as fa, np.load(b) as fb:
        assert np.array_equal(fa["signals"], fb["signals"])
    th.set_default_threads(None)


def test_render_bit_identical_for_any_threads():
    ph = td.phantom_from_dict(
        {
            "name": "threads",
            "system": [
                {"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}
            ],
            "protocol": {"n_frames": 6, "frame_interval_s": 0.2048},
            "analysis": {"metrics": ["liv", "ocds"], "ocds_delay_range_s": [0.2048, 0.8192]},  # 2+ pairs per delay
            "grid": {"kind": "bscan", "n_x": 12, "n_z": 12, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
            "region": [
                {
                    "name": "flow",
                    "shape": "slab",
                    "z_min_um": -12.0,
                    "z_max_um": 0.0,
                    "density_per_um3": 0.05,
                    "motion": [{"kind": "flow", "speed_um_per_s": 2.0, "polar_angle_deg": 60.0}],
                }
            ],
            "background": [{"density_per_um3": 0.05, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.5}]}],
        }
    )  # a walk and straight paths
    ref = td.render(ph, seed=3, threads=1).data
    assert ref.abs().max() > 0
    assert torch.equal(td.render(ph, seed=3, threads=2).data, ref)
    assert torch.equal(td.render(ph, seed=3, threads=3).data, ref)


@pytest.mark.slow
@pytest.mark.parametrize("process_work", [1, 10**12])  # worker processes; threads
def test_sweep_cells_side_by_side_equal_one_at_a_time(monkeypatch, process_work):
    from torchdoct.sim.config import read_toml
    from torchdoct.sim.scenes import resolve_scene_path
    from torchdoct.study import sweep as sw

    s = sw.make_sweep(
        read_toml(resolve_scene_path("example")),
        [{"path": "population.0.motion.0.diffusion_um2_per_s", "values": [0.01, 0.1, 1.0]}],
        name="t",
    )
    ref = sw.run_sweeps([s], trials=128, workers=1).table()
    monkeypatch.setattr(sw, "_PROCESS_WORK", process_work)
    got = sw.run_sweeps([s], trials=128, workers=2).table()
    cols = [c for c in ref.columns if c != "elapsed_s"]
    assert got[cols].equals(ref[cols])

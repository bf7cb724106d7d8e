"""One resource check before work for every command (torchdoct.runtime.resources): an input whose estimate exceeds the
available memory (or its output the free disk) is refused before the work starts, in one line naming the
input, the estimate, the available amount and the fix. The machine's memory is monkeypatched small, so the
inputs stay tiny."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from _refusal import refused
from _scenes import SMALL_SCENE_TOML

import torchdoct.runtime.resources as resources

KB = 1 << 10


@pytest.fixture()
def tiny_memory(monkeypatch):
    """The machine has 1 KiB of memory available (every estimate is larger)."""
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: KB)


def _no_work(*args, **kwargs):
    raise AssertionError("the work started")


def _gb_numbers(line: str) -> list[float]:
    return [float(x) for x in re.findall(r"([0-9.]+) GB", line)]


# ----------------------------------------------------------------------------------------------------------
# the check itself


def test_check_resources_names_the_input_estimate_available_and_fix(monkeypatch, tmp_path):
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 3 << 30)
    resources.check_resources("input x", 2 << 30, "lower --n")  # fits: nothing raised
    with pytest.raises(resources.MemoryLimitError) as err:
        resources.check_resources("input x", 5 << 30, "lower --n", detail="5 pieces")
    assert str(err.value) == ("input x needs about 5.00 GB (5 pieces) but only 3.00 GB are available; lower --n")
    assert isinstance(err.value, ValueError)  # exit code 2 on the command line
    monkeypatch.setattr(resources, "free_disk_bytes", lambda path: 1 << 30)
    with pytest.raises(
        resources.DiskLimitError,
        match=r"output .*out\.npz takes about 2\.00 GB on disk but only "
        r"1\.00 GB are free there; write elsewhere",
    ):
        resources.check_resources(
            "input x", 0, "lower --n", out_path=tmp_path / "out.npz", out_bytes=2 << 30, out_fix="write elsewhere"
        )


def test_unknown_memory_refuses_nothing(monkeypatch):
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: None)
    monkeypatch.setattr(resources, "free_disk_bytes", lambda path: None)
    resources.check_resources("input x", 1 << 60, "never", out_path="x", out_bytes=1 << 60)


def test_free_disk_of_a_path_not_yet_made_is_its_parents(tmp_path):
    assert resources.free_disk_bytes(tmp_path / "a" / "b" / "c.npz") == resources.free_disk_bytes(tmp_path)


def test_maps_estimate_closed_form():
    """[T=8, Z=6, X=5] complex64, 2 resolutions × (liv, aliv + fit flag): slab = the whole sequence."""
    need, disk = resources.maps_bytes(
        (8, 6, 5), 8, complex_samples=True, n_resolutions=2, metrics=["liv", "aliv"], slab_elements=1 << 23
    )
    channels, pixels = 2 * 3, 30
    assert disk == channels * pixels * 4
    assert need == resources.MAPS_WORK_COPIES * 8 * 6 * 5 * 8 + channels * pixels * 4 + disk
    # a slab smaller than the sequence bounds the working memory
    need_small, _ = resources.maps_bytes(
        (8, 6, 5), 8, complex_samples=True, n_resolutions=2, metrics=["liv", "aliv"], slab_elements=10
    )
    assert need_small == resources.MAPS_WORK_COPIES * 10 * 8 + channels * pixels * 4 + disk


def test_classify_estimate_reads_declared_sizes_without_loading(tmp_path):
    import zipfile

    p = tmp_path / "m.npz"
    np.savez_compressed(p, maps=np.zeros((3, 64, 64), np.float32))  # compresses to almost nothing
    declared = sum(i.file_size for i in zipfile.ZipFile(p).infolist())
    assert resources.declared_array_bytes(p) == declared > 3 * 64 * 64 * 4
    assert resources.classify_bytes([p, p]) == resources.CLASSIFY_COPIES * 2 * declared
    assert resources.classify_bytes([p], limit_bytes=10) == 0  # over the input limit: the reader refuses it


# ----------------------------------------------------------------------------------------------------------
# every command


def test_simulate_refused_before_any_chunk(tiny_memory, monkeypatch):
    import torchdoct
    import torchdoct.sim.simulate as sim

    monkeypatch.setattr(sim, "_simulate_chunk", _no_work)
    with pytest.raises(resources.MemoryLimitError) as err:
        torchdoct.simulate(torchdoct.load_scene("example"), trials=64)
    msg = str(err.value)
    assert msg.startswith("this simulation needs about ") and "trials per chunk" in msg
    assert "simulation.truncation_tolerance" in msg and "lower chunk_trials" in msg


def test_simulate_estimate_is_the_one_it_checks(monkeypatch):
    """The refusal's estimate is :func:`torchdoct.sim.memory.simulation_bytes`; 1 byte more memory passes."""
    import torchdoct
    from torchdoct.sim.memory import simulation_bytes
    from torchdoct.sim.plan import make_plan

    scene = torchdoct.load_scene("example")
    plan = make_plan(scene, truncation_tolerance=scene.simulation.truncation_tolerance)
    need = simulation_bytes(
        plan, trials=128, n_systems=len(scene.systems), n_frames=scene.protocol.n_frames, threads=1
    )[0]
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: need - 1)
    with pytest.raises(resources.MemoryLimitError):
        torchdoct.simulate(scene, trials=128, threads=1)
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: need)
    assert torchdoct.simulate(scene, trials=128, threads=1).signals.shape[0] == 128


def test_render_refused(tiny_memory, capsys, tmp_path):
    refused(
        capsys,
        tmp_path,
        ["render", "example", "--grid", "8x8", "--pitch-um", "2", "--out", str(tmp_path / "r.h5")],
        "the rendered sequence needs about",
        "GB are available",
        "--system",
        "float32",
    )


def test_maps_refused_before_the_slab_loop(tiny_memory, capsys, seq):
    line = refused(
        capsys,
        seq.parent,
        ["maps", str(seq), "--no-progress", "--out", str(seq.parent / "m.npz")],
        "maps of seq.npy",
        "sequence [8, 6, 5]",
        "GB are available",
        "--resolution",
        "--metrics",
    )
    assert _gb_numbers(line)[1] == 0.0  # 1 KiB available


def test_maps_library_call_refused(tiny_memory, seq):
    from torchdoct.measured.io import read_sequence
    from torchdoct.measured.maps import compute_maps

    with pytest.raises(resources.MemoryLimitError, match="maps of .*seq.npy needs about"):
        compute_maps(read_sequence(seq), ["original"])


def test_maps_output_larger_than_the_free_disk_refused(monkeypatch, capsys, seq):
    monkeypatch.setattr(resources, "free_disk_bytes", lambda path: 100)  # the maps take 3 × 30 × 4 bytes
    refused(
        capsys,
        seq.parent,
        ["maps", str(seq), "--no-progress", "--out", str(seq.parent / "m.npz")],
        "maps of seq.npy",
        "m.npz takes about",
        "on disk",
        "write --out elsewhere",
    )


SWEEP_TOML = (
    SMALL_SCENE_TOML
    + """
[sweep]
name = "tiny"
[[sweep.field]]
path = "population.0.motion.0.diffusion_um2_per_s"
values = [0.01, 0.1, 1.0]
"""
)


def test_sweep_refused_before_any_cell(tiny_memory, monkeypatch, capsys, tmp_path):
    import torchdoct.study.sweep as sweep_module

    monkeypatch.setattr(sweep_module, "_execute", _no_work)
    scene = tmp_path / "sw.toml"
    scene.write_text(SWEEP_TOML, encoding="utf-8")
    out = tmp_path / "o"
    out.mkdir()
    before = set(tmp_path.rglob("*"))
    from torchdoct.cli import main

    assert main(["sweep", str(scene), "--out", str(out), "--trials", "64", "--workers", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {scene}: sweep 'tiny' needs about") and "\n" not in err  # names the file
    for name in (
        "largest cell",
        "population.0.motion.0.diffusion_um2_per_s",
        "× 2 cell(s) side by side",
        "GB are available",
        "--trials, now 64",
        "--workers, now 2",
        "--tolerance",
    ):
        assert name in err, (name, err)
    assert set(tmp_path.rglob("*")) == before  # no cache folder, no table


def test_sweep_from_the_cache_needs_no_simulation_memory(monkeypatch, tmp_path):
    """A rerun whose cells all come from the cache computes nothing, so it is not refused."""
    from torchdoct.sim.config import read_toml
    from torchdoct.study import sweep as sw

    path = tmp_path / "sw.toml"
    path.write_text(SWEEP_TOML, encoding="utf-8")
    s = sw.parse_sweep(read_toml(path))
    first = sw.run_sweeps([s], trials=64, cache_dir=tmp_path / "cache")
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: KB)
    monkeypatch.setattr(sw, "_execute", _no_work)
    again = sw.run_sweeps([s], trials=64, cache_dir=tmp_path / "cache")
    assert again.cached == 3 and again.table()["mean"].equals(first.table()["mean"])


def test_study_refused_before_any_cell(tiny_memory, monkeypatch, capsys, tmp_path):
    from _studies import write_tiny_study

    import torchdoct.study.sweep as sweep_module

    monkeypatch.setattr(sweep_module, "_execute", _no_work)
    study = write_tiny_study(tmp_path)
    refused(
        capsys,
        tmp_path,
        ["study", str(study), "--out", str(tmp_path / "o"), "--no-cache"],
        "needs about",
        "largest cell",
        "GB are available",
        "--trials",
        "--workers",
    )


def test_training_data_refused_before_any_draw(tiny_memory, monkeypatch, tmp_path):
    import classifier.dataset as dataset

    monkeypatch.setattr(dataset, "simulate_draw", _no_work)
    with pytest.raises(resources.MemoryLimitError) as err:
        dataset.make_dataset("single-acquisition", draws=3, trials_per_draw=64, replicates=2, cache_dir=tmp_path)
    msg = str(err.value)
    assert msg.startswith("the train split of 'single-acquisition' needs about")
    assert "384 samples = 3 draws × 2 replicates × 64 trials" in msg
    assert "--draws-train" in msg and "--trials-per-draw" in msg and "--replicates" in msg
    assert not any(tmp_path.iterdir())


def test_training_data_cache_larger_than_the_free_disk_refused(monkeypatch, tmp_path):
    import classifier.dataset as dataset

    monkeypatch.setattr(dataset, "simulate_draw", _no_work)
    monkeypatch.setattr(resources, "free_disk_bytes", lambda path: 100)
    with pytest.raises(resources.DiskLimitError, match="--no-cache"):
        dataset.make_dataset("single-acquisition", draws=3, trials_per_draw=64, replicates=2, cache_dir=tmp_path)


def test_doct_train_refused(tiny_memory, monkeypatch, capsys, tmp_path):
    import classifier.dataset as dataset
    from classifier.cli import train_main

    monkeypatch.setattr(dataset, "simulate_draw", _no_work)
    out = tmp_path / "model"
    refused(
        capsys,
        tmp_path,
        ["--quick", "--out", str(out), "--cache", str(tmp_path / "cache"), "--no-progress"],
        "split of 'single-acquisition' needs about",
        "--draws-train",
        run=train_main,
    )


def _maps_file(seq, capsys) -> object:
    from torchdoct.cli import main

    out = seq.parent / "m.npz"
    assert main(["maps", str(seq), "--no-progress", "--out", str(out)]) == 0
    capsys.readouterr()
    return out


def test_doct_classify_refused_before_reading(monkeypatch, capsys, seq):
    from classifier.cli import classify_main

    maps = _maps_file(seq, capsys)
    import torchdoct.measured.mapsfile as mapsfile

    monkeypatch.setattr(mapsfile, "read_maps", _no_work)
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: KB)
    line = refused(
        capsys,
        seq.parent,
        [str(maps), "--out", str(seq.parent / "c")],
        "doct-classify of m.npz",
        "needs about",
        "GB are available",
        "crop",
        run=classify_main,
    )
    assert "4 × the maps arrays" in line


def test_translate_refused_before_reading(monkeypatch, capsys, seq):
    maps = _maps_file(seq, capsys)
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: KB)
    from torchdoct.cli import main

    try:
        main(["translate", "--help"])
    except SystemExit:
        pass
    if "--to" not in capsys.readouterr().out:
        pytest.skip("torchdoct translate is not registered in this installation")
    refused(
        capsys,
        seq.parent,
        ["translate", str(maps), "--to", "example", "--out", str(seq.parent / "t.npz")],
        "torchdoct translate of m.npz",
        "needs about",
        "crop",
    )


def test_compare_refused_before_reading(monkeypatch, capsys, seq):
    maps = _maps_file(seq, capsys)
    import torchdoct.measured.mapsfile as mapsfile

    monkeypatch.setattr(mapsfile, "read_maps", _no_work)
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: KB)
    line = refused(
        capsys,
        seq.parent,
        ["compare", f"a={maps}", f"b={maps}", "--out", str(seq.parent / "c.csv")],
        "torchdoct compare of m.npz, m.npz",
        "needs about",
        "GB are available",
        "fewer maps files",
    )
    declared = resources.declared_array_bytes(maps)
    assert f"{resources.COMPARE_COPIES} × the maps arrays" in line
    # the estimate: every file's declared arrays, COMPARE_COPIES times; exactly that much memory passes the check
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: resources.COMPARE_COPIES * 2 * declared)
    resources.check_compare([maps, maps])
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: resources.COMPARE_COPIES * 2 * declared - 1)
    with pytest.raises(resources.MemoryLimitError):
        resources.check_compare([maps, maps])


@pytest.mark.parametrize(
    "argv,names",
    [
        (["bench", "maps", "--size", "64", "64", "--frames", "8"], ("torchdoct bench maps", "[8, 64, 64]", "--size")),
        (
            ["bench", "bulk-phase", "--lines", "100", "--depth", "16", "--frames", "8"],
            ("torchdoct bench bulk-phase", "100 A-lines", "--lines"),
        ),
        (["bench", "classify", "--size", "64"], ("torchdoct bench classify", "64×64 pixels", "--size")),
    ],
)
def test_benchmarks_with_a_size_refused_before_making_their_input(
    tiny_memory, monkeypatch, capsys, tmp_path, argv, names
):
    import torch

    monkeypatch.setattr(torch, "randn", _no_work)  # the synthetic inputs are never drawn
    monkeypatch.setattr(np.random, "default_rng", _no_work)
    refused(capsys, tmp_path, argv + ["--out", str(tmp_path / "b.json")], *names, "GB are available")


def test_every_refusal_is_one_exception_class():
    from torchdoct.sim.memory import MemoryLimitError as from_memory
    from torchdoct.sim.simulate import MemoryLimitError as from_simulate

    assert from_memory is from_simulate is resources.MemoryLimitError
    assert issubclass(resources.DiskLimitError, resources.ResourceLimitError)
    assert json.dumps(resources.__all__)  # a public, documented module

"""The cell runner (torchdoct.study.cells) of sweeps and training data: every executor gives the same results,
the cache returns exactly what was stored (and nothing for another key or a damaged file), an interruption
keeps the finished cells and the rerun computes only the others."""

from __future__ import annotations

import signal
from types import SimpleNamespace

import numpy as np
import pytest

import torchdoct.runtime.interrupt as interrupt
from torchdoct.study.cells import CellCache, CellJob, cell_seed, run_cached, run_cells


def square_stream(payload: dict) -> dict:
    """A module-level task (picklable for worker processes): a seeded draw of the payload's size."""
    rng = np.random.default_rng(payload["seed"])
    return {"x": rng.standard_normal(payload["n"]) ** 2}


PAYLOADS = [{"seed": cell_seed(7, f"cell-{i}"), "n": 5 + i} for i in range(7)]


def _collect(**kw) -> tuple[list, list[int]]:
    got: list = [None] * len(PAYLOADS)
    order: list[int] = []

    def done(i, r):
        assert got[i] is None, "each cell is done once"
        got[i] = r["x"]
        order.append(i)

    run_cells(square_stream, PAYLOADS, done=done, **kw)
    return got, order


def test_every_executor_gives_the_same_cells():
    ref, order = _collect(workers=1)
    assert order == list(range(len(PAYLOADS)))
    for kw in (
        dict(workers=2),
        dict(workers=3, batch=2),
        dict(workers=2, batch=7),
        dict(workers=2, one_torch_thread=True),
    ):
        got, order = _collect(**kw)
        assert order == list(range(len(PAYLOADS))), kw  # threads: done in the order of the cells
        assert all(np.array_equal(a, b) for a, b in zip(got, ref)), kw


@pytest.mark.slow
def test_worker_processes_give_the_same_cells():
    ref, _ = _collect(workers=1)
    got, order = _collect(workers=2, batch=2, processes=True)
    assert sorted(order) == list(range(len(PAYLOADS)))
    assert all(np.array_equal(a, b) for a, b in zip(got, ref))


def test_cell_seed_depends_on_the_base_seed_and_key_only():
    assert cell_seed(7, "a") == cell_seed(7, "a")
    assert len({cell_seed(7, "a"), cell_seed(8, "a"), cell_seed(7, "b")}) == 3
    assert 0 <= cell_seed(0, "") < 2**63
    # the sweeps' seeds (a cell key's seed is part of the caches already written): fixed forever
    from torchdoct.study.sweep import cell_seed as sweep_seed

    assert sweep_seed is cell_seed
    assert cell_seed(2025, '{"population.0.motion.0.diffusion_um2_per_s":0.1}') == 5248728518214911224
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        cell_seed(-1, "a")


def test_cache_returns_what_was_stored(tmp_path):
    cache = CellCache(tmp_path / "c")
    arrays = {"a": np.arange(5, dtype=np.float32), "flag": np.array([True, False])}
    cache.put("k1", arrays, {"note": "x"})
    got, meta = cache.get("k1")
    assert meta == {"cache_key": "k1", "note": "x"}
    assert set(got) == {"a", "flag"} and all(
        np.array_equal(got[k], arrays[k]) and got[k].dtype == arrays[k].dtype for k in arrays
    )
    assert [p.name for p in (tmp_path / "c").iterdir()] == ["k1.npz"]  # written atomically: no temporary file
    assert cache.get("k2") is None
    (tmp_path / "c" / "k2.npz").write_bytes((tmp_path / "c" / "k1.npz").read_bytes())  # another key's content
    assert cache.get("k2") is None
    (tmp_path / "c" / "k3.npz").write_bytes(b"PK\x03\x04 damaged")
    assert cache.get("k3") is None
    assert CellCache(None).get("k1") is None


@pytest.fixture()
def fresh_notes(monkeypatch):
    monkeypatch.setattr(
        interrupt, "_STATE", SimpleNamespace(signum=None, defer=0, pending=None, kept={}, resume=None, active=False)
    )


def _jobs() -> list[CellJob]:
    return [CellJob(key=f"key{i}", payload=p, weight=p["n"]) for i, p in enumerate(PAYLOADS)]


def _encode(job, res):
    return {"x": res["x"]}, {"n": job.payload["n"]}


def _decode(job, arrays, meta):
    return {"x": arrays["x"]}


def test_an_interruption_keeps_the_finished_cells_and_the_rerun_computes_the_rest(tmp_path, fresh_notes):
    cache = CellCache(tmp_path / "cache")

    def interrupted(payloads, done):
        for i in range(3):
            done(i, square_stream(payloads[i]))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_cached(_jobs(), cache=cache, execute=interrupted, encode=_encode, decode=_decode, what="cells")
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["key0.npz", "key1.npz", "key2.npz"]
    line = interrupt.message(signal.SIGINT)
    assert f"kept 3 of the 7 cells to compute in the cache {tmp_path / 'cache'}" in line and "resume" in line

    ran: list[int] = []

    def execute(payloads, done):
        ran.append(len(payloads))
        run_cells(square_stream, payloads, done=done)

    results, computed = run_cached(_jobs(), cache=cache, execute=execute, encode=_encode, decode=_decode)
    assert ran == [4] and computed == [3, 4, 5, 6]
    ref, _ = _collect(workers=1)
    assert all(np.array_equal(r["x"], x) for r, x in zip(results, ref))
    # all cached: nothing executes
    results2, computed2 = run_cached(_jobs(), cache=cache, execute=execute, encode=_encode, decode=_decode)
    assert ran == [4] and computed2 == []
    assert all(np.array_equal(r["x"], x) for r, x in zip(results2, ref))


def test_the_resource_check_runs_before_any_cell(tmp_path):
    seen = []

    def before(todo):
        seen.append(list(todo))
        raise ValueError("too large")

    def execute(payloads, done):
        raise AssertionError("the work started")

    cache = CellCache(tmp_path / "cache")
    cache.put("key1", {"x": np.zeros(1)}, {})
    with pytest.raises(ValueError, match="too large"):
        run_cached(_jobs(), cache=cache, execute=execute, encode=_encode, decode=_decode, before=before)
    assert seen == [[0, 2, 3, 4, 5, 6]]  # the cached cell is not counted


def test_training_data_resumes_from_the_draws_an_interruption_kept(tmp_path, monkeypatch, fresh_notes):
    """make_dataset runs its draws through the same runner: Ctrl-C after 2 of 4 draws keeps them; the rerun
    simulates only the other 2 and gives the split of an uninterrupted run bit for bit; once the split is
    written, the kept draws are removed."""
    import classifier.dataset as dataset
    from classifier.prior import Prior, draw_parameters
    from torchdoct.runtime.threads import using_threads

    kw = dict(draws=4, trials_per_draw=64, replicates=1)
    with using_threads(1):
        ref = dataset.make_dataset("single-acquisition", use_cache=False, **kw)
    real = dataset.simulate_draw
    calls = []

    def stops_at_the_third(*args, **kwargs):
        calls.append(args[1].sim_seed)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset, "simulate_draw", stops_at_the_third)
    with using_threads(1), pytest.raises(KeyboardInterrupt):
        dataset.make_dataset("single-acquisition", cache_dir=tmp_path, **kw)
    kept = list(tmp_path.iterdir())
    assert len(kept) == 1 and kept[0].name.startswith(".single-acquisition-train-") and kept[0].is_dir()
    assert len(list(kept[0].glob("draw-*.npz"))) == 2
    assert "kept 2 of the 4 draws of this split to compute in the cache" in interrupt.message(signal.SIGINT)

    calls.clear()
    monkeypatch.setattr(dataset, "simulate_draw", lambda *a, **k: (calls.append(a[1].sim_seed), real(*a, **k))[1])
    with using_threads(2):
        ds = dataset.make_dataset("single-acquisition", cache_dir=tmp_path, **kw)
    seeds = [draw_parameters(Prior(), 0, "train", k, 1).sim_seed for k in range(4)]
    assert sorted(calls) == sorted(seeds[2:])
    for name in ("x", "y", "draw", "group", "status", "magnitude", "density", "static_fraction", "snr_db"):
        assert np.array_equal(getattr(ds, name), getattr(ref, name), equal_nan=True), name
    assert [p.name for p in tmp_path.iterdir()] == [f"single-acquisition-train-{ds.meta['key'][:16]}.npz"]

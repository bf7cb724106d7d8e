"""Sweeps (torchdoct.study.sweep): grids, validation, per-cell seeds, cache and resume, tables, Dask.

Tiny scenes only (two systems, 8 frames, 64 trials per cell).
"""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pandas as pd
import pytest
import torch

import torchdoct
from torchdoct import scene_from_dict, simulate
from torchdoct.cli import main
from torchdoct.sim.config import SceneError
from torchdoct.sim.metrics import summarize
from torchdoct.study.sweep import (
    SCALAR_METRICS,
    cache_key,
    cell_seed,
    field_values,
    load_sweep,
    make_sweep,
    parse_sweep,
    run_sweep,
    run_sweeps,
    write_sweep_outputs,
)

BASE = {
    "name": "tiny",
    "system": [
        {"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
        {"name": "1310nm", "wavelength_um": 1.31, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
    ],
    "protocol": {"n_frames": 8, "frame_interval_s": 0.2048},
    "population": [{"density_per_um3": 0.055, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.1}]}],
    "analysis": {"metrics": ["liv", "ocds"], "ocds_delay_range_s": [0.2048, 0.6144]},
    "simulation": {"trials": 64, "seed": 7},
}
D_PATH = "population.0.motion.0.diffusion_um2_per_s"

SWEEP_TOML = textwrap.dedent("""\
    name = "tiny-file"

    [[system]]
    name = "840nm"
    wavelength_um = 0.84
    lateral_resolution_um = 4.9
    axial_resolution_um = 3.8

    [[system]]
    name = "1310nm"
    wavelength_um = 1.31
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

    [sweep]
    name = "diffusion"

    [[sweep.field]]
    path = "population.0.motion.0.diffusion_um2_per_s"
    name = "D_um2_per_s"
    values = [0.0]
    log = { start = 0.01, stop = 1.0, num = 2 }
    """)


def _sweep(values, **kw):
    return make_sweep(BASE, [{"path": D_PATH, "name": "D_um2_per_s", "values": list(values)}], **kw)


# ----------------------------------------------------------------------------------------------------------
# values and cells
# ----------------------------------------------------------------------------------------------------------
def test_field_values_linear_log_explicit_and_union():
    assert field_values({"linear": {"start": 0.0, "stop": 15.0, "num": 31}})[:3] == (0.0, 0.5, 1.0)
    lin = field_values({"linear": {"start": 0.0, "stop": 15.0, "num": 31}})
    assert len(lin) == 31 and lin[-1] == 15.0
    lg = field_values({"log": {"start": 0.001, "stop": 10.0, "num": 5}})
    np.testing.assert_allclose(lg, [0.001, 0.01, 0.1, 1.0, 10.0], rtol=1e-12)
    assert all(float(f"{v:.12g}") == v for v in lg)  # rounded to 12 significant digits
    # explicit values keep their order; several sources give the sorted union without duplicates
    assert field_values({"values": [3.0, 1.0, 2.0]}) == (3.0, 1.0, 2.0)
    u = field_values(
        {
            "values": [0.0, 1.0],
            "log": {"start": 0.1, "stop": 1.0, "num": 2},
            "linear": {"start": 1.0, "stop": 3.0, "num": 3},
        }
    )
    assert u == (0.0, 0.1, 1.0, 2.0, 3.0)
    assert field_values({"values": ["isotropic", "uniform-angles"]}) == ("isotropic", "uniform-angles")
    assert field_values({"linear": {"start": 2.0, "stop": 0.0, "num": 3}}) == (2.0, 1.0, 0.0)


@pytest.mark.parametrize(
    "spec, match",
    [
        ({}, "gives no values"),
        ({"log": {"start": 0.0, "stop": 1.0, "num": 3}}, "start and stop must be > 0"),
        ({"linear": {"start": 0.0, "stop": 1.0, "num": 0}}, "num: must be >= 1"),
        ({"linear": {"start": 0.0, "stop": 1.0}}, "missing"),
        ({"linear": {"start": 0.0, "stop": 1.0, "num": 3, "step": 1}}, "unknown"),
        ({"values": ["a"], "linear": {"start": 0.0, "stop": 1.0, "num": 2}}, "non-numeric"),
        ({"linear": {"start": float("nan"), "stop": 1.0, "num": 2}}, "finite"),
    ],
)
def test_field_values_errors_name_the_field(spec, match):
    with pytest.raises(SceneError, match=match) as err:
        field_values(spec, "sweep.field[2]")
    assert "sweep.field[2]" in str(err.value)


def test_field_values_type_errors():
    with pytest.raises(TypeError, match="sweep.field.values must be a non-empty array"):
        field_values({"values": []})
    with pytest.raises(TypeError, match="num must be an integer"):
        field_values({"linear": {"start": 0.0, "stop": 1.0, "num": 2.5}})


def test_product_and_zip_cells():
    fields = [
        {"path": D_PATH, "name": "D", "values": [0.0, 0.1, 1.0]},
        {"path": "system.1.axial_resolution_um", "name": "dz_1310", "values": [3.8, 14.0]},
    ]
    prod = make_sweep(BASE, fields)
    assert len(prod.cells) == 6
    assert [c.values for c in prod.cells[:3]] == [
        {"D": 0.0, "dz_1310": 3.8},
        {"D": 0.0, "dz_1310": 14.0},
        {"D": 0.1, "dz_1310": 3.8},
    ]
    c = prod.cells[1]
    assert c.scene.systems[1].axial_resolution_um == 14.0 and c.scene.systems[0].axial_resolution_um == 3.8
    assert c.scene.populations[0].motion[0].diffusion_um2_per_s == 0.0
    zipped = make_sweep(BASE, [fields[0], {**fields[1], "values": [3.8, 7.6, 14.0]}], mode="zip")
    assert [tuple(c.values.values()) for c in zipped.cells] == [(0.0, 3.8), (0.1, 7.6), (1.0, 14.0)]
    with pytest.raises(SceneError, match="zip needs fields of equal length"):
        make_sweep(BASE, fields, mode="zip")


def test_missing_tables_are_created_and_single_tables_accepted():
    base = {k: v for k, v in BASE.items() if k != "population"}
    base["population"] = {"density_per_um3": 0.055, "motion": {"kind": "flow", "speed_um_per_s": 1.0}}
    sw = make_sweep(
        base,
        [
            {"path": "noise.snr_db", "values": [20.0, 40.0]},
            {"path": "population.0.motion.0.speed_um_per_s", "values": [0.5]},
        ],
    )
    assert [c.scene.noise.snr_db for c in sw.cells] == [20.0, 40.0]
    assert sw.cells[0].scene.populations[0].motion[0].speed_um_per_s == 0.5
    assert [f.name for f in sw.fields] == ["snr_db", "speed_um_per_s"]


@pytest.mark.parametrize(
    "field, match",
    [
        ({"path": "system.2.axial_resolution_um", "values": [3.0]}, r"system has 2 entries \(indices 0..1\)"),
        ({"path": "system.first.axial_resolution_um", "values": [3.0]}, "is an array; 'first' is not an index"),
        ({"path": "protocol.n_frames.x", "values": [3.0]}, "is a value"),
        ({"path": "system.0.axial_resolution_mm", "values": [3.0]}, "unknown key"),
        ({"path": "system.0.axial_resolution_um", "values": [-3.0]}, "must be > 0"),
        ({"path": "simulation.seed", "values": [1, 2]}, "cannot be swept|trials and seed"),
        ({"path": "population..density_per_um3", "values": [0.1]}, "empty segment"),
        ({"path": D_PATH, "name": "mean", "values": [0.1]}, "column of the table"),
        ({"path": D_PATH, "values": [0.1], "step": 2}, "unknown key"),
    ],
)
def test_bad_fields_name_the_path_and_fix(field, match):
    with pytest.raises(SceneError, match=match) as err:
        make_sweep(BASE, [field])
    msg = str(err.value)
    assert "sweep" in msg
    if match not in ("column of the table", "unknown key") and ".." not in field["path"]:
        assert field["path"] in msg or field["path"].split(".")[0] in msg


def test_bad_cell_error_names_the_cell_and_path():
    with pytest.raises(SceneError) as err:
        make_sweep(BASE, [{"path": "system.0.wavelength_um", "values": [0.84, 840.0]}])
    msg = str(err.value)
    assert "cell 1" in msg and "system.0.wavelength_um = 840.0" in msg and "micrometres" in msg


def test_duplicate_fields_and_cells_are_rejected():
    with pytest.raises(SceneError, match="swept twice"):
        make_sweep(
            BASE, [{"path": D_PATH, "name": "a", "values": [0.1]}, {"path": D_PATH, "name": "b", "values": [1.0]}]
        )
    with pytest.raises(SceneError, match="cells 0 and 2 are the same"):
        make_sweep(BASE, [{"path": D_PATH, "values": [0.1, 1.0, 0.1]}])
    with pytest.raises(SceneError, match="cells 0 and 1 are the same"):
        make_sweep(BASE, [{"path": D_PATH, "values": [0.1, 0.1]}, {"path": "name", "values": ["x", "x"]}], mode="zip")
    # a repeated value in one zipped field is fine when the cells differ
    assert (
        len(
            make_sweep(
                BASE, [{"path": D_PATH, "values": [0.1, 0.1]}, {"path": "name", "values": ["x", "y"]}], mode="zip"
            ).cells
        )
        == 2
    )


def test_parse_sweep_validates_the_scene_without_the_sweep_table(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(SWEEP_TOML)
    sw = load_sweep(path)
    assert sw.name == "diffusion" and [c.values["D_um2_per_s"] for c in sw.cells] == [0.0, 0.01, 1.0]
    bad = SWEEP_TOML.replace('name = "diffusion"', 'name = "diffusion"\nbatch = 3')
    path.write_text(bad)
    with pytest.raises(SceneError, match=r"s.toml: sweep: unknown key\(s\) \['batch'\]"):
        load_sweep(path)
    path.write_text(SWEEP_TOML.replace("[protocol]", "[protocol]\nspeed = 2"))
    with pytest.raises(SceneError, match="unknown key"):
        load_sweep(path)
    with pytest.raises(SceneError, match=r"no \[sweep\] table"):
        parse_sweep(BASE)
    with pytest.raises(FileNotFoundError, match="not found"):
        load_sweep(tmp_path / "missing.toml")


# ----------------------------------------------------------------------------------------------------------
# seeds, cache keys
# ----------------------------------------------------------------------------------------------------------
def test_cell_seed_depends_on_base_seed_and_key_only():
    a = _sweep([0.0, 0.1, 1.0])
    b = _sweep([1.0, 0.5, 0.1])  # other cells, other order
    sa = {c.values["D_um2_per_s"]: cell_seed(7, c.key) for c in a.cells}
    sb = {c.values["D_um2_per_s"]: cell_seed(7, c.key) for c in b.cells}
    assert sa[0.1] == sb[0.1] and sa[1.0] == sb[1.0]
    assert len(set(sa.values())) == 3
    assert cell_seed(8, a.cells[1].key) != sa[0.1]
    assert 0 <= sa[0.1] < 2**63
    # 1 and 1.0 are the same cell
    assert make_sweep(BASE, [{"path": D_PATH, "values": [1]}]).cells[0].key == a.cells[2].key


def test_cache_key_covers_what_changes_the_numbers(monkeypatch):
    scene = _sweep([0.1]).cells[0].scene
    k = cache_key(scene, seed=1, trials=64, dtype="float32", tolerance=1e-3)
    assert k == cache_key(
        scene.replace(name="other", description="renamed"), seed=1, trials=64, dtype="float32", tolerance=1e-3
    )
    changed = [
        cache_key(scene, seed=2, trials=64, dtype="float32", tolerance=1e-3),
        cache_key(scene, seed=1, trials=128, dtype="float32", tolerance=1e-3),
        cache_key(scene, seed=1, trials=64, dtype="float64", tolerance=1e-3),
        cache_key(scene, seed=1, trials=64, dtype="float32", tolerance=1e-4),
        cache_key(
            scene_from_dict({**BASE, "protocol": {"n_frames": 9, "frame_interval_s": 0.2048}}),
            seed=1,
            trials=64,
            dtype="float32",
            tolerance=1e-3,
        ),
        cache_key(
            scene.replace(simulation=torchdoct.SimulationSettings(truncation="hard")),
            seed=1,
            trials=64,
            dtype="float32",
            tolerance=1e-3,
        ),
    ]
    # the default truncation is the taper: a scene that names it has the same key
    assert k == cache_key(
        scene.replace(simulation=torchdoct.SimulationSettings(truncation="taper")),
        seed=1,
        trials=64,
        dtype="float32",
        tolerance=1e-3,
    )
    monkeypatch.setattr(torchdoct, "__version__", "0.0.0-test")
    changed.append(cache_key(scene, seed=1, trials=64, dtype="float32", tolerance=1e-3))
    assert len({k, *changed}) == len(changed) + 1


# ----------------------------------------------------------------------------------------------------------
# running
# ----------------------------------------------------------------------------------------------------------
def test_cell_equals_a_direct_simulation_with_its_seed():
    sw = _sweep([0.0, 0.1])
    res = run_sweep(sw)
    cr = res.cell("tiny", 1)
    assert cr.seed == cell_seed(7, sw.cells[1].key) and cr.trials == 64
    direct = simulate(sw.cells[1].scene, trials=64, seed=cr.seed)
    m = direct.metrics()
    np.testing.assert_array_equal(cr.metrics["liv"], m["liv"].numpy())
    np.testing.assert_array_equal(cr.metrics["ocds"], m["ocds"].numpy())
    summ = summarize(m, direct.system_names)
    t = res.table()
    assert len(t) == 2 * 2 * 2  # cells × systems × metrics
    for sname in ("840nm", "1310nm"):
        for metric in ("liv", "ocds"):
            row = t[(t["cell"] == 1) & (t["system"] == sname) & (t["metric"] == metric)].iloc[0]
            assert row["mean"] == pytest.approx(summ[sname][metric]["mean"], rel=1e-12)
            assert row["sd"] == pytest.approx(summ[sname][metric]["sd"], rel=1e-12)
            assert row["se"] == pytest.approx(summ[sname][metric]["se"], rel=1e-12)
            assert row["n"] == 64 and row["trials"] == 64 and row["seed"] == cr.seed
            assert row["unit"] == SCALAR_METRICS[metric] and row["D_um2_per_s"] == 0.1


def test_zero_motion_cell_gives_zero_liv_and_ocds():
    t = run_sweep(_sweep([0.0])).table()
    assert (t["mean"] == 0).all() and (t["sd"] == 0).all() and (t["n"] == 64).all() and (t["empty"] == 0).all()


def test_results_do_not_depend_on_batching_splitting_or_order(tmp_path):
    full = run_sweep(_sweep([0.0, 0.01, 0.1, 1.0]), batch_cells=3).table()
    parts = [run_sweep(_sweep([1.0, 0.01])).table(), run_sweep(_sweep([0.1, 0.0])).table()]
    cols = ["D_um2_per_s", "system", "metric", "mean", "sd", "se", "n", "seed", "cache_key"]
    merged = pd.concat(parts)[cols].sort_values(cols[:3]).reset_index(drop=True)
    pd.testing.assert_frame_equal(full[cols].sort_values(cols[:3]).reset_index(drop=True), merged)
    # two sweeps in one call give the same cells as separate calls
    other = make_sweep({**BASE, "name": "other"}, [{"path": D_PATH, "values": [0.01]}], name="other")
    both = run_sweeps([_sweep([0.01]), other]).table()
    assert set(both["sweep"]) == {"tiny", "other"}
    a = both[both["sweep"] == "tiny"]["mean"].to_numpy()
    b = both[both["sweep"] == "other"]["mean"].to_numpy()
    np.testing.assert_array_equal(a, b)  # same key and base seed: the same cell


def test_cache_resumes_and_reruns_only_changed_cells(tmp_path):
    cache = tmp_path / "cache"
    first = run_sweep(_sweep([0.0, 0.1]), cache_dir=cache)
    assert (first.computed, first.cached) == (2, 0)
    assert len(list(cache.glob("*.npz"))) == 2
    again = run_sweep(_sweep([0.0, 0.1, 1.0]), cache_dir=cache)
    assert (again.computed, again.cached) == (1, 2)
    pd.testing.assert_frame_equal(again.table(), run_sweep(_sweep([0.0, 0.1, 1.0])).table())
    # renaming the scene changes nothing; more trials or another density recompute everything
    renamed = make_sweep(
        {**BASE, "description": "same cells"}, [{"path": D_PATH, "name": "D_um2_per_s", "values": [0.0, 0.1]}]
    )
    assert run_sweep(renamed, cache_dir=cache).computed == 0
    assert run_sweep(_sweep([0.0, 0.1]), cache_dir=cache, trials=128).computed == 2
    denser = {
        **BASE,
        "population": [{"density_per_um3": 0.06, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.1}]}],
    }
    r = run_sweep(make_sweep(denser, [{"path": D_PATH, "name": "D_um2_per_s", "values": [0.0, 0.1]}]), cache_dir=cache)
    assert r.computed == 2
    assert [c.seed for c in r.cells] == [c.seed for c in first.cells]  # same keys: same seeds


def test_unreadable_cache_entry_is_recomputed(tmp_path):
    cache = tmp_path / "cache"
    ref = run_sweep(_sweep([0.1]), cache_dir=cache)
    (path,) = cache.glob("*.npz")
    path.write_bytes(b"not an npz file")
    again = run_sweep(_sweep([0.1]), cache_dir=cache)
    assert again.computed == 1
    pd.testing.assert_frame_equal(again.table(), ref.table())


def test_run_argument_errors():
    sw = _sweep([0.1])
    for kw, match in (
        ({"batch_cells": 0}, "batch_cells"),
        ({"trials": 0}, "trials"),
        ({"dtype": "float16"}, "dtype"),
        ({"tolerance": 2.0}, "tolerance"),
    ):
        with pytest.raises(ValueError, match=match):
            run_sweep(sw, **kw)
    with pytest.raises(ValueError, match="unique"):
        run_sweeps([sw, sw])


def test_outputs_csv_parquet_json_and_no_overwrite(tmp_path):
    res = run_sweep(_sweep([0.0, 0.1]))
    out = tmp_path / "out"
    files = write_sweep_outputs(res, out)
    assert sorted(p.name for p in files) == ["results.csv", "results.parquet", "sweep.json"]
    csv = pd.read_csv(out / "results.csv")
    pq = pd.read_parquet(out / "results.parquet")
    pd.testing.assert_frame_equal(pq, res.table())
    np.testing.assert_allclose(csv["mean"], pq["mean"], rtol=1e-15)
    assert list(csv["seed"]) == list(pq["seed"])
    rec = json.loads((out / "sweep.json").read_text())
    assert rec["sweeps"][0]["fields"][0]["values"] == [0.0, 0.1]
    assert scene_from_dict(rec["sweeps"][0]["scene"]).name == "tiny"
    assert [c["seed"] for c in rec["cells"]] == [c.seed for c in res.cells]
    with pytest.raises(ValueError, match="pass --force"):
        write_sweep_outputs(res, out)
    write_sweep_outputs(res, out, force=True)
    with pytest.raises(ValueError, match="does not exist"):
        write_sweep_outputs(res, tmp_path / "no" / "such")


def test_cli_sweep_resumes_and_refuses_to_overwrite(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text(SWEEP_TOML)
    out = tmp_path / "out"
    assert main(["sweep", str(path), "--out", str(out), "--no-progress", "--workers", "1"]) == 0
    text = capsys.readouterr().out
    assert "3 cells (3 computed, 0 from the cache)" in text and "liv mean (SE)" in text and "D_um2_per_s=0.01" in text
    assert main(["sweep", str(path), "--out", str(out), "--no-progress"]) == 2
    assert "pass --force" in capsys.readouterr().err
    assert main(["sweep", str(path), "--out", str(out), "--no-progress", "--force"]) == 0
    assert "(0 computed, 3 from the cache)" in capsys.readouterr().out
    assert (
        main(["sweep", str(path), "--out", str(out), "--force", "--no-progress", "--trials", "128", "--workers", "2"])
        == 0
    )  # two cells side by side
    assert "(3 computed, 0 from the cache)" in capsys.readouterr().out
    t = pd.read_parquet(out / "results.parquet")
    assert t["trials"].eq(128).all()
    ref = run_sweep(load_sweep(path), trials=128).table()  # in this process
    pd.testing.assert_frame_equal(t, ref)
    assert main(["sweep", str(tmp_path / "nope.toml"), "--out", str(out)]) == 2
    assert "not found" in capsys.readouterr().err


def test_dask_local_cluster_gives_identical_numbers(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    sw = _sweep([0.0, 0.01, 0.1])
    local = run_sweep(sw).table()
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        remote = run_sweep(sw, scheduler=cluster.scheduler_address, batch_cells=2, cache_dir=tmp_path / "c").table()
    pd.testing.assert_frame_equal(local, remote)
    assert len(list((tmp_path / "c").glob("*.npz"))) == 3  # the client writes the cache
    assert torch.get_default_dtype() == torch.float32

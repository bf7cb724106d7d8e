"""``torchdoct maps`` on many inputs (torchdoct.cli.mapsbatch): each input's maps are those of the single-input
command, bit for bit, whether run one after another, in worker processes or as tasks on a Dask cluster;
``{stem}`` names each input's outputs; usage that would make two inputs share an output, a missing input or an
existing output is refused before any work; one input refused does not stop the others."""

from __future__ import annotations

import _formats as F
import numpy as np
import pytest
from _refusal import refused

from torchdoct.cli import main
from torchdoct.measured.mapsfile import read_maps

OPTS = ["--no-progress", "--ocds-delay-range-s", "0.05", "0.3"]


@pytest.fixture()
def inputs(tmp_path):
    """Three sequences in three formats: a.npy, b.ome.tif, c.zarr (each its own field)."""
    d = tmp_path / "in"
    d.mkdir()
    return [
        F.write_npy(d / "a.npy", F.field(t=8, seed=1)),
        F.write_ome_tiff(d / "b.ome.tif", F.field(t=8, seed=2)),
        F.write_ome_zarr(d / "c.zarr", F.field(t=8, seed=3)),
    ]


def _single(tmp_path, path):
    out = tmp_path / "single" / f"{path.name}.npz"
    out.parent.mkdir(exist_ok=True)
    assert main(["maps", str(path), "--out", str(out), *OPTS]) == 0
    return read_maps(out)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("how", [[], ["--workers", "2"]], ids=["one-after-another", "worker-processes"])
def test_many_inputs_give_each_input_its_single_input_maps(tmp_path, inputs, capsys, how):
    out = tmp_path / "out"
    out.mkdir()
    assert main(["maps", *map(str, inputs), "--out", str(out / "{stem}.npz"), *OPTS, *how]) == 0
    printed = capsys.readouterr().out
    for path, stem in zip(inputs, ["a", "b", "c"]):
        got, want = read_maps(out / f"{stem}.npz"), _single(tmp_path, path)
        assert got.channels == want.channels and got.meta == want.meta
        np.testing.assert_array_equal(got.maps, want.maps)
        assert f"wrote {out / f'{stem}.npz'}" in printed


def test_many_inputs_run_as_tasks_on_a_dask_cluster(tmp_path, inputs):
    distributed = pytest.importorskip("dask.distributed")
    out = tmp_path / "out"
    out.mkdir()
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        assert (
            main(
                [
                    "maps",
                    *map(str, inputs),
                    "--out",
                    str(out / "{stem}.ome.tif"),
                    *OPTS,
                    "--scheduler",
                    cluster.scheduler_address,
                ]
            )
            == 0
        )
    for path, stem in zip(inputs, ["a", "b", "c"]):
        want = _single(tmp_path, path)
        np.testing.assert_array_equal(read_maps(out / f"{stem}.ome.tif").maps, want.maps)


def test_an_out_without_stem_is_refused_for_many_inputs(tmp_path, inputs, capsys):
    refused(
        capsys, tmp_path / "in", ["maps", *map(str, inputs), "--out", str(tmp_path / "m.npz"), *OPTS], "--out", "{stem}"
    )


def test_two_inputs_of_one_stem_are_refused_before_any_work(tmp_path, inputs, capsys):
    twin = F.write_raw(tmp_path / "a.raw", F.field(t=8))  # stem "a", as in/a.npy
    refused(
        capsys,
        tmp_path / "in",
        ["maps", str(inputs[0]), str(twin), "--out", str(tmp_path / "{stem}.npz"), *OPTS],
        "a.npz",
        "a.npy",
        "a.raw",
    )
    assert not (tmp_path / "a.npz").exists()


def test_a_missing_input_or_an_existing_output_is_refused_before_any_work(tmp_path, inputs, capsys):
    out = tmp_path / "out"
    out.mkdir()
    refused(
        capsys,
        out,
        ["maps", str(inputs[0]), str(tmp_path / "nope.npy"), "--out", str(out / "{stem}.npz"), *OPTS],
        "nope.npy",
    )
    (out / "c.npz").write_bytes(b"x")
    refused(capsys, out, ["maps", *map(str, inputs), "--out", str(out / "{stem}.npz"), *OPTS], "c.npz", "--force")
    assert sorted(p.name for p in out.iterdir()) == ["c.npz"]


def test_one_input_refused_does_not_stop_the_others(tmp_path, inputs, capsys):
    bad = tmp_path / "in" / "d.npy"
    np.save(bad, np.zeros((8, 12, 16), np.int32))  # integers: neither complex nor an intensity
    F.sidecar(bad, t=8)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["maps", str(inputs[0]), str(bad), str(inputs[2]), "--out", str(out / "{stem}.npz"), *OPTS]) == 2
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if line.startswith("error:")] == [
        next(line for line in err.splitlines() if line.startswith("error: d.npy"))
    ]
    assert "1 of 3 inputs refused (" in err and sorted(p.name for p in out.iterdir()) == ["a.npz", "c.npz"]

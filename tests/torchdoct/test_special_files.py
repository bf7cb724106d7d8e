"""Special files given as inputs (issue class 1): a FIFO, a character device or a directory in any input
role is refused at once (exit 2, one ``error:`` line with "is not a regular file"), never "not found",
never blocking on the open and never reading a device without end; every JSON or TOML file is read with
a size cap (:func:`torchdoct.files.read_capped`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from _refusal import refused
from _special import (
    no_hang,  # noqa: F401 (autouse fixture)
    special,
)

from torchdoct import files

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")

KINDS = ("fifo", "device", "directory")


@pytest.mark.parametrize("kind", KINDS)
def test_check_regular_file_names_the_kind_and_never_says_not_found(tmp_path, kind):
    p = special(tmp_path / "x.npy", kind)
    with pytest.raises(files.NotRegularFileError, match="is not a regular file") as err:
        files.check_regular_file(p, "sequence file")
    assert "sequence file" in str(err.value) and {
        "fifo": "FIFO",
        "device": "character device",
        "directory": "directory",
    }[kind] in str(err.value)
    assert "not found" not in str(err.value) and isinstance(err.value, ValueError)
    with pytest.raises(FileNotFoundError, match="no such file"):
        files.check_regular_file(tmp_path / "missing.npy", "sequence file")


def test_a_link_that_loops_or_leads_nowhere_is_named_as_such(tmp_path, capsys):
    from _refusal import refused

    links, out = tmp_path / "links", tmp_path / "out"
    links.mkdir()
    out.mkdir()
    loop = links / "loop.npz"
    loop.symlink_to("loop.npz")
    dangling = links / "dangling.npz"
    dangling.symlink_to("nowhere.npz")
    refused(
        capsys,
        out,
        ["maps", str(loop), "--out", str(out / "m.npz"), "--no-progress"],
        "loop.npz",
        "a loop of symbolic links",
    )
    refused(
        capsys,
        out,
        ["maps", str(dangling), "--out", str(out / "m.npz"), "--no-progress"],
        "dangling.npz",
        "a symbolic link to nowhere.npz",
        "does not exist",
    )


def test_read_capped_refuses_a_text_file_over_the_cap(tmp_path):
    p = tmp_path / "big.json"
    p.write_bytes(b" " * 101)
    assert files.read_capped(p, "sidecar", limit=101) == b" " * 101
    with pytest.raises(ValueError, match="sidecar .*big.json: 101 bytes, over"):
        files.read_capped(p, "sidecar", limit=100)


def _maps_file(tmp_path, seq, capsys) -> Path:
    from torchdoct.cli import main

    out = tmp_path / "good.npz"
    assert main(["maps", str(seq), "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    return out


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "role", ["sequence", "sidecar", "maps", "mask", "scene", "sweep", "study", "phantom", "to-scene", "label-image"]
)
def test_a_special_file_in_any_input_role_is_refused_at_once(tmp_path, capsys, seq, role, kind):
    d = tmp_path / "in"
    d.mkdir()
    ext = {"sequence": ".npy", "sidecar": ".json", "maps": ".npz", "mask": ".npy", "label-image": ".npy"}.get(
        role, ".toml"
    )
    bad = d / f"bad{ext}"
    if role == "sidecar":
        data = d / "bad.npy"
        data.write_bytes(seq.read_bytes())
    if role == "label-image":
        (d / "ph.toml").write_text(
            'name = "p"\n[[system]]\nname = "s"\nwavelength_um = 0.84\nlateral_resolution_um = 4.9\n'
            'axial_resolution_um = 3.8\n[protocol]\nn_frames = 2\nframe_interval_s = 0.2\n[analysis]\nmetrics = ["liv"]\n'
            "[grid]\nn_z = 8\nn_x = 8\npitch_z_um = 2.0\npitch_x_um = 2.0\n"
            '[[region]]\nname = "cells"\nshape = "label-image"\nfile = "bad.npy"\nvalue = 7\n'
            "density_per_um3 = 0.05\n"
        )
    special(bad, kind)
    out = d / "o"
    out.mkdir()
    argv = {
        "sequence": ["maps", str(bad), "--out", str(out / "m.npz")],
        "sidecar": ["maps", str(d / "bad.npy"), "--out", str(out / "m.npz")],
        "maps": ["compare", str(bad)],
        "scene": ["plan", str(bad)],
        "sweep": ["sweep", str(bad), "--out", str(out / "sw")],
        "study": ["study", str(bad), "--out", str(out / "st")],
        "phantom": ["render", str(bad), "--out", str(out / "r.npz")],
        "label-image": ["render", str(d / "ph.toml"), "--out", str(out / "r.npz")],
    }.get(role)
    if role in ("mask", "to-scene"):
        good = _maps_file(d, seq, capsys)
        argv = (
            ["compare", str(good), "--mask", str(bad)]
            if role == "mask"
            else ["translate", str(good), "--to", str(bad), "--out", str(out / "t.npz")]
        )
    line = refused(capsys, d, argv, "bad", "is not a regular file")
    assert "not found" not in line and "does not exist" not in line and "Errno" not in line


def test_a_directory_named_like_a_shipped_scene_still_names_the_shipped_scene(tmp_path, monkeypatch):
    from torchdoct.sim.scenes import resolve_scene_path, shipped_scenes

    monkeypatch.chdir(tmp_path)
    (tmp_path / "example").mkdir()
    assert resolve_scene_path("example") == shipped_scenes()["example"]


def test_a_sidecar_linked_to_an_endless_device_is_not_read(tmp_path, capsys, seq):
    side = seq.with_suffix(".json")
    side.unlink()
    side.symlink_to("/dev/zero")
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--out", str(tmp_path / "m.npz")],
        "sidecar",
        "seq.json",
        "character device",
    )


def test_a_sidecar_over_the_text_cap_is_refused_naming_it(tmp_path, capsys, seq, monkeypatch):
    meta = json.loads(seq.with_suffix(".json").read_text())
    text = json.dumps(meta)
    monkeypatch.setattr(files, "MAX_TEXT_BYTES", len(text) - 1)
    monkeypatch.setattr(files.read_capped, "__defaults__", ("input file", len(text) - 1))
    refused(capsys, tmp_path, ["maps", str(seq), "--out", str(tmp_path / "m.npz")], "seq.json", "bytes, over")


@pytest.mark.parametrize("role", ["sequence", "maps"])
@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_a_special_file_inside_a_zarr_store_is_refused_before_zarr_opens_it(tmp_path, role, kind):
    """A chunk of an OME-Zarr sequence or maps folder that is a FIFO blocked the read in zarr's own threads
    (a signal could not end it); read in a child process, so that a regression fails instead of hanging."""
    import subprocess
    import sys

    pytest.importorskip("zarr")
    from _formats import field, maps, write_ome_zarr

    if role == "sequence":
        store = write_ome_zarr(tmp_path / "seq.zarr", field(t=8, z=6, x=5))
        code = "from torchdoct.measured.io import read_sequence as r"
    else:
        from torchdoct.measured.mapsfile import write_maps

        store = tmp_path / "maps.zarr"
        write_maps(store, maps(volume=False))
        code = "from torchdoct.measured.io import read_maps as r"
    chunk = next(
        p for p in sorted(store.rglob("*")) if p.is_file() and not p.name.startswith(".") and p.name != "zarr.json"
    )
    chunk.unlink()
    special(chunk, kind)
    script = f"{code}\ntry:\n    r({str(store)!r})\nexcept ValueError as e:\n    print(e)\n    raise SystemExit(2)\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "is not a regular file" in proc.stdout and chunk.name in proc.stdout, proc.stdout

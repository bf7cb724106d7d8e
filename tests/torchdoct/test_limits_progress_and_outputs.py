"""Adversarial rows: bounds checked before the work (render grids from pitch and extent,
table counts of scene and phantom files), progress bars only on runs that last, benchmarks that write
only when asked, and commands that say which files a pattern output becomes.

Each test would have failed before its fix: ``render --pitch-um 0.001`` allocated gigabytes (a PSF
window of ``2·h/pitch`` pixels per axis), ``--pitch-um 1e6`` seeded ~1e15 scatterers, a scene of
100,000 systems ran for minutes in ``plan``, a ``maps`` run far shorter than a second drew a bar, ``bench maps`` wrote
``bench-maps.json`` into the current folder, and ``render --out medium.h5`` with four systems wrote
four other files without saying so first.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _refusal import refused
from _refusal import tree as _tree

from torchdoct.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _run(argv: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """A command as a user runs it (a fresh interpreter: tqdm and the environment as at start-up)."""
    return subprocess.run(
        [sys.executable, "-m", "torchdoct.cli", *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=300,
    )


#: The process's peak resident memory (kB) as the kernel counts it for this program: VmHWM belongs to the
#: address space made by exec, whereas ru_maxrss keeps the high-water mark of the forking parent (pytest).
_VMHWM = "int(next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM:')))"


def _peak_rss_mb(argv: list[str], cwd: Path) -> tuple[int, float, str]:
    """Exit code, peak resident memory (MB) and stderr of ``torchdoct argv`` run in a fresh interpreter."""
    code = (
        f"import sys\nfrom torchdoct.cli import main\nrc = main({argv!r})\nprint('PEAK_KB', {_VMHWM})\nsys.exit(rc)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)
    kb = [ln.split()[1] for ln in p.stdout.splitlines() if ln.startswith("PEAK_KB")]
    return p.returncode, (int(kb[0]) / 1024 if kb else float("nan")), p.stderr


# ----------------------------------------------------------------------------------------------------------
# render: grid bounds from pitch and extent


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("pitch", ["1e-3", "1e-300"])
def test_render_with_a_pitch_far_below_the_psf_stays_small(tmp_path, pitch):
    """A PSF window is never wider than the grid: 1e-3 µm pixels cost the grid's 16 × 16 pixels, not
    a 20,000 × 20,000 window per scatterer (3.2 GB per chunk before)."""
    rc, peak, err = _peak_rss_mb(
        [
            "render",
            "example",
            "--grid",
            "16x16",
            "--pitch-um",
            pitch,
            "--system",
            "840nm-high",
            "--no-preview",
            "--no-progress",
            "--out",
            "r.h5",
        ],
        tmp_path,
    )
    assert rc == 0, err
    assert peak < 1024, f"peak RSS {peak:.0f} MB"
    assert (tmp_path / "r.h5").is_file()


def test_window_clamped_to_the_grid_changes_no_number(monkeypatch):
    """The clamped window covers every pixel within the truncation half-width: the image is bit-identical
    to the one of the full ``2·h/pitch + 2`` window (a grid narrower than the PSF window on both axes)."""
    import math

    import torch

    from torchdoct.image import render as r
    from torchdoct.image.phantom import load_phantom

    ph = load_phantom("example", grid={"n_z": 6, "n_x": 5, "pitch_x_um": 0.7, "pitch_z_um": 0.5})
    clamped = r.render(ph, systems="840nm-high", seed=3, threads=1)
    monkeypatch.setattr(r, "_window_pixels", lambda half, pitch, n: int(math.floor(2.0 * half / pitch)) + 2)
    full = r.render(ph, systems="840nm-high", seed=3, threads=1)
    assert torch.equal(clamped.data, full.data)
    assert clamped.data.abs().max() > 0


def test_render_of_a_huge_field_of_view_is_refused_before_the_work(tmp_path, capsys):
    """64 × 64 pixels of 1 m: ~3e15 scatterers, refused naming the count, the memory and the options."""
    line = refused(
        capsys,
        tmp_path,
        ["render", "example", "--grid", "64x64", "--pitch-um", "1e6", "--out", str(tmp_path / "r.h5")],
        "example",
        "scatterers",
        "GB",
        "--pitch-um",
        "--max-scatterers",
    )
    assert "e+15" in line


def test_max_scatterers_sets_the_limit(tmp_path, capsys):
    argv = [
        "render",
        "example",
        "--grid",
        "8x8",
        "--pitch-um",
        "2",
        "--system",
        "840nm-high",
        "--no-preview",
        "--no-progress",
        "--out",
        str(tmp_path / "r.h5"),
    ]
    refused(capsys, tmp_path, argv + ["--max-scatterers", "100"], "--max-scatterers", "the limit is 100")
    assert main(argv) == 0
    assert (tmp_path / "r.h5").is_file()


def test_render_says_which_files_several_systems_become(tmp_path, capsys, monkeypatch):
    """``--out medium.h5`` with four systems: one line before the work names the four files."""
    import torchdoct.image.render as r

    def stop(*a, **k):
        raise KeyboardInterrupt  # the note must already be out when the work starts

    monkeypatch.setattr(r, "render", stop)
    with pytest.raises(KeyboardInterrupt):
        from torchdoct.cli import _main

        _main(["render", "example", "--grid", "8x8", "--pitch-um", "2", "--out", str(tmp_path / "medium.h5")])
    out = capsys.readouterr().out
    assert "4 systems: one file per system" in out
    for name in ("840nm-high", "1310nm-high", "840nm-axial14", "840nm-lateral18"):
        assert f"medium-{name}.h5" in out
    assert "--system" in out
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------------------
# table counts: checked before the tables are read


def _scene_text(systems: int = 1, populations: int = 1, motions: int = 1) -> str:
    s = "".join(
        f'[[system]]\nname = "s{i}"\nwavelength_um = 0.84\nlateral_resolution_um = 4.9\naxial_resolution_um = 3.8\n\n'
        for i in range(systems)
    )
    m = '[[population.motion]]\nkind = "diffusion"\ndiffusion_um2_per_s = 0.003\n' * motions
    p = "".join(f"[[population]]\ndensity_per_um3 = 0.01\n{m}" for _ in range(populations))
    return f'name = "many"\n{s}[protocol]\nn_frames = 8\nframe_interval_s = 0.2048\n{p}'


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_scene_of_100000_systems_is_refused_in_seconds(tmp_path, capsys):
    """A 10 MB scene of 100,000 systems: refused naming the file, the count and the limit (it ran for
    minutes in ``plan`` before)."""
    f = tmp_path / "big.toml"
    f.write_text(_scene_text(systems=100_000))
    t0 = time.perf_counter()
    line = refused(capsys, tmp_path, ["plan", str(f)], "big.toml", "100000", "at most 64", "split")
    assert time.perf_counter() - t0 < 30, line


@pytest.mark.parametrize(
    "kw, names",
    [
        ({"systems": 65}, ("system", "65")),
        ({"populations": 1025}, ("population", "1025")),
        ({"motions": 17}, ("motion", "17")),
    ],
)
def test_table_counts_over_the_limit_are_refused(tmp_path, capsys, kw, names):
    f = tmp_path / "many.toml"
    f.write_text(_scene_text(**kw))
    refused(capsys, tmp_path, ["plan", str(f)], "many.toml", *names)


def test_table_counts_at_the_limit_are_planned(tmp_path, capsys):
    f = tmp_path / "many.toml"
    f.write_text(_scene_text(systems=64, motions=16))
    assert main(["plan", str(f)]) == 0


def test_phantom_with_too_many_regions_is_refused(tmp_path, capsys):
    region = '[[region]]\nshape = "slab"\nz_min_um = -1.0\nz_max_um = 1.0\ndensity_per_um3 = 0.01\n'
    f = tmp_path / "ph.toml"
    f.write_text(
        'name = "ph"\n[[system]]\nname = "s"\nwavelength_um = 0.84\nlateral_resolution_um = 4.9\n'
        "axial_resolution_um = 3.8\n[protocol]\nn_frames = 8\nframe_interval_s = 0.2048\n"
        "[grid]\nn_x = 8\nn_z = 8\npitch_x_um = 2.0\npitch_z_um = 2.0\n" + region * 1025
    )
    refused(capsys, tmp_path, ["render", str(f), "--out", str(tmp_path / "r.h5")], "ph.toml", "region", "1025")


def test_a_scene_built_in_python_is_limited_in_make_plan():
    import dataclasses

    import torchdoct as td
    from torchdoct.sim.config import SceneError

    sc = td.load_scene("example")
    many = sc.replace(systems=tuple(dataclasses.replace(sc.systems[0], name=f"s{i}") for i in range(65)))
    with pytest.raises(SceneError, match="65"):
        td.make_plan(many)


# ----------------------------------------------------------------------------------------------------------
# progress bars and benchmark outputs


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_a_short_run_shows_no_progress_bar(seq):
    """A short ``maps`` run prints no bar (it ends within tqdm's delay); with the delay set to 0 the same run
    draws one, so the bar is there for runs that last."""
    argv = ["maps", str(seq), "--out", "m.npz"]
    p = _run(argv, seq.parent)
    assert p.returncode == 0, p.stderr
    assert "%|" not in p.stderr and "slab/s" not in p.stderr, p.stderr
    p = _run(["maps", str(seq), "--out", "m2.npz"], seq.parent, env={"TQDM_DELAY": "0"})
    assert p.returncode == 0 and "slab/s" in p.stderr, p.stderr


@pytest.mark.parametrize(
    "argv",
    [
        ["bench", "maps", "--frames", "8", "--size", "8", "8", "--resolution", "original"],
        ["bench", "classify", "--size", "16", "--repeats", "1"],
    ],
)
def test_bench_writes_json_only_when_asked(tmp_path, capsys, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    assert _tree(tmp_path) == {}, "nothing may be written into the current folder unasked"
    assert "wrote" not in capsys.readouterr().out
    assert main(argv + ["--out", "b.json"]) == 0
    assert json.loads((tmp_path / "b.json").read_text())


def test_png_colour_ranges_are_shared_across_resolutions(seq, tmp_path, monkeypatch):
    """``maps --png``: without ``--range`` every resolution of one metric gets the same colour range, so
    the images of one metric compare by eye (pooled 1st-99th percentile)."""
    import torchdoct.measured.maps as mm

    seen = {}
    real = mm.map_figure

    def record(maps, name, **kw):
        seen[name] = kw["value_range"]
        return real(maps, name, **kw)

    monkeypatch.setattr(mm, "map_figure", record)
    assert (
        main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "lateral=8",
                "--png",
                "--no-progress",
                "--out",
                str(tmp_path / "m.npz"),
            ]
        )
        == 0
    )
    for metric in ("liv", "ocds", "mean_db"):
        assert seen[f"{metric}@original"] == seen[f"{metric}@lateral=8"], (metric, seen)
    assert seen["liv@original"] != seen["ocds@original"]


@pytest.mark.slow  # an end-to-end command run; the default suite covers its parts
def test_study_figures_phase_has_a_progress_bar(tmp_path, capsys):
    """The figures and the claims report advance a bar per step."""
    import re

    from _studies import write_tiny_study

    from torchdoct.study import run_study

    run_study(write_tiny_study(tmp_path), tmp_path / "out", cache_dir=None, workers=1, progress=True)
    err = capsys.readouterr().err.replace("\r", "\n")
    steps = re.findall(r"figures and claims report: +\d+%\S* *\| *(\d+)/(\d+)", err)
    assert steps and max(int(a) for a, _ in steps) >= 1, err[-2000:]  # it advanced, step by step


# ----------------------------------------------------------------------------------------------------------
# peak memory on the bombs: within the README's budget (Command line, "Memory")


def _bomb_inputs(d: Path) -> dict[str, Path]:
    """The adversarial pass's bombs: a 1.2 KB .npz declaring 1.14 TiB, a few-KB .h5 declaring 512 GiB
    (chunked and compressed, never written), a maps .npz declaring 48 GiB, a scene of 100,000 systems."""
    import io
    import zipfile

    import h5py

    def npy_header(shape, dtype) -> bytes:
        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape}
        )
        return buf.getvalue()

    meta = {
        "axes": "TZX",
        "pitch_um": {"z": 2.0, "x": 2.0},
        "frame_times_s": [0.2048 * i for i in range(32)],
        "system": {"name": "s", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8},
    }
    out = {"npz": d / "liar.npz", "h5": d / "huge.h5", "maps": d / "maps.npz", "scene": d / "big.toml"}
    with zipfile.ZipFile(out["npz"], "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("data.npy", npy_header((1200, 1 << 14, 8000), np.complex64) + bytes(1000))
    out["npz"].with_suffix(".json").write_text(json.dumps(meta))
    with h5py.File(out["h5"], "w") as fh:
        fh.create_dataset("data", shape=(4096, 4096, 4096), dtype=np.complex64, chunks=(1, 64, 64), compression="gzip")
        fh.attrs["torchdoct"] = json.dumps(meta)
    with zipfile.ZipFile(out["maps"], "w") as zf:
        zf.writestr("maps.npy", npy_header((3, 1 << 16, 1 << 16), np.float32) + bytes(64))
        zf.writestr("channels.npy", npy_header((3,), "<U16") + bytes(192))
    out["scene"].write_text(_scene_text(systems=100_000))
    return out


@pytest.mark.slow
def test_peak_memory_on_the_bombs_stays_within_the_budget(tmp_path):
    """Each bomb is refused (exit 2) with the command's peak resident memory within its documented
    budget for no accepted input (README: maps, compare and plan 400 MB, doct-classify 300 MB, render
    600 MB), far from the gigabytes to terabytes the files declare."""
    b = _bomb_inputs(tmp_path)
    runs = {
        "maps npz": (["maps", str(b["npz"]), "--out", "m.npz"], 400),
        "maps h5": (["maps", str(b["h5"]), "--out", "m.npz"], 400),
        "compare": (["compare", f"A={b['maps']}", f"B={b['maps']}"], 400),
        "plan": (["plan", str(b["scene"])], 400),
        "render": (["render", "example", "--grid", "64x64", "--pitch-um", "1e6", "--out", "r.h5"], 600),
    }
    for what, (argv, budget_mb) in runs.items():
        rc, peak, err = _peak_rss_mb(argv, tmp_path)
        assert rc == 2 and "Traceback" not in err, (what, err)
        assert peak < budget_mb, f"{what}: peak {peak:.0f} MB over the {budget_mb} MB budget"
    code = (
        "import sys\nfrom classifier.cli import classify_main\n"
        f"rc = classify_main([{str(b['maps'])!r}, '--out', 'c'])\n"
        f"print('PEAK_KB', {_VMHWM})\nsys.exit(rc)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    peak = int(next(ln.split()[1] for ln in p.stdout.splitlines() if ln.startswith("PEAK_KB"))) / 1024
    assert p.returncode == 2 and peak < 300, (p.stderr, peak)
    assert not any(x.name in ("m.npz", "r.h5", "c") for x in tmp_path.iterdir())


@pytest.mark.slow
def test_peak_memory_of_maps_within_its_budget(tmp_path):
    """``maps`` at three resolutions on a [32, 256, 256] complex64 stack (16.8 MB): the README's budget
    of 300 MB + 10 × the input array (measured 417 MB)."""
    rng = np.random.default_rng(0)
    shape = (32, 256, 256)
    a = rng.standard_normal(shape, dtype=np.float32) + 1j * rng.standard_normal(shape, dtype=np.float32)
    np.save(tmp_path / "s.npy", a.astype(np.complex64))
    (tmp_path / "s.json").write_text(
        json.dumps(
            {
                "axes": "TZX",
                "pitch_um": {"z": 2.0, "x": 2.0},
                "frame_times_s": [0.2048 * i for i in range(32)],
                "system": {
                    "name": "s",
                    "wavelength_um": 0.84,
                    "lateral_resolution_um": 4.9,
                    "axial_resolution_um": 3.8,
                },
            }
        )
    )
    rc, peak, err = _peak_rss_mb(
        [
            "maps",
            "s.npy",
            "--resolution",
            "original",
            "--resolution",
            "axial=14",
            "--resolution",
            "lateral=18",
            "--no-progress",
            "--out",
            "m.npz",
        ],
        tmp_path,
    )
    assert rc == 0, err
    assert peak < 300 + 10 * a.astype(np.complex64).nbytes / 2**20, peak


def test_float32_overflow_of_the_intensity_is_named(seq, capsys):
    """|E| ≈ 1e25 in complex64: |E|² overflows float32; named with the fix (it was reported as 'holds no
    finite nonzero sample')."""
    big = seq.with_name("big.npy")
    np.save(big, (np.load(seq) * np.float32(1e25)).astype(np.complex64))
    big.with_suffix(".json").write_text(seq.with_suffix(".json").read_text())
    line = refused(
        capsys,
        seq.parent,
        ["maps", str(big), "--no-progress", "--out", str(seq.parent / "m.npz")],
        "big.npy",
        "overflows float32",
        "complex128",
    )
    assert "no finite nonzero" not in line


def test_bench_all_needs_its_output_folder(tmp_path, capsys, monkeypatch):
    """``bench all`` writes a folder of results: only where ``--out DIR`` says (it made ./bench unasked)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["bench", "all"])
    assert exc.value.code == 2 and "--out" in capsys.readouterr().err
    assert _tree(tmp_path) == {}


def test_maps_force_replaces_the_earlier_png_set(seq, tmp_path, capsys):
    """``maps --png --force`` with fewer resolutions: the earlier run's PNGs of this output go (they would
    sit beside maps that no longer hold their channels); the user's other files stay."""
    out = seq.parent / "m.npz"
    assert (
        main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "lateral=8",
                "--png",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    old = seq.parent / "m_liv_lateral8.png"
    assert old.is_file()
    mine = seq.parent / "m_notes.png"
    mine.write_bytes(b"the user's own")
    assert main(["maps", str(seq), "--png", "--force", "--no-progress", "--out", str(out)]) == 0
    assert not old.exists() and (seq.parent / "m_liv_original.png").is_file() and mine.is_file()
    assert f"removed {old}" in capsys.readouterr().out

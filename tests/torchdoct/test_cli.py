"""Command line (torchdoct.cli.main): scenes, plan, simulate; tiny scenes only (1 system, 8 frames, 64 trials)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchdoct import load_scene, scene_from_dict, shipped_scenes
from torchdoct.cli import main
from torchdoct.sim.metrics import compute_metrics

STATIC_SCENE = """\
name = "static-only"

[[system]]
name = "840nm"
wavelength_um = 0.84
lateral_resolution_um = 4.9
axial_resolution_um = 3.8

[protocol]
n_frames = 8
frame_interval_s = 0.2048

[[population]]
density_per_um3 = 0.055

[analysis]
metrics = ["liv", "ocds"]
ocds_delay_range_s = [0.2048, 0.6144]
"""


def _run(argv) -> tuple[int, str]:
    """(exit code, SystemExit message): main's return value, or the SystemExit code (a message counts as 1)."""
    try:
        return main(argv), ""
    except SystemExit as exc:
        return (exc.code if isinstance(exc.code, int) else 1), str(exc.code)


def _stages_line(text: str) -> str:
    return next(line for line in text.splitlines() if line.startswith("stages:"))


# ----------------------------------------------------------------------------------------------------------
# scenes, plan
# ----------------------------------------------------------------------------------------------------------
def test_scenes_lists_every_shipped_scene(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name, path in shipped_scenes().items():
        assert f"{name}: " in out
        assert load_scene(path).description in out


def test_plan_example(capsys):
    assert main(["plan", "example"]) == 0
    out = capsys.readouterr().out
    stages = _stages_line(out)
    assert "seed scatterers" in stages and "random walk" in stages and "metrics" in stages
    assert "noise" not in stages
    for ens in ("5.018", "18.488", "67.716"):
        assert ens in out
    line = next(line for line in out.splitlines() if "840nm-high:" in line)
    assert "5.018" in line
    assert "for 500 trials" in out  # the scene's trials


def test_plan_example_json(capsys):
    assert main(["plan", "example", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert {"stages", "systems", "populations"} <= set(plan)
    assert [s["name"] for s in plan["systems"]] == ["840nm-high", "1310nm-high", "840nm-axial14", "840nm-lateral18"]
    np.testing.assert_allclose([s["ens_paper"] for s in plan["systems"]], [5.018, 5.018, 18.488, 67.716], atol=5e-4)
    assert plan["populations"][0]["sampler"] == "diffusive"


def test_plan_of_static_scene_has_no_motion_or_noise_stage(tmp_path, capsys):
    path = tmp_path / "static.toml"
    path.write_text(STATIC_SCENE)
    assert main(["plan", str(path)]) == 0
    out = capsys.readouterr().out
    stages = _stages_line(out)
    for absent in ("random walk", "straight paths", "noise"):
        assert absent not in stages
        assert absent not in out
    assert "constant over frames" in stages
    assert main(["plan", str(path), "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert not any(w in s for s in plan["stages"] for w in ("random walk", "straight paths", "noise"))
    assert plan["has_noise"] is False


# ----------------------------------------------------------------------------------------------------------
# simulate
# ----------------------------------------------------------------------------------------------------------
def test_simulate_writes_npz_and_refuses_to_overwrite(tmp_scene_file, tmp_path, capsys):
    out = tmp_path / "x.npz"
    argv = ["simulate", str(tmp_scene_file), "--trials", "64", "--seed", "3", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "LIV" in captured.out and "840nm" in captured.out and f"wrote {out}" in captured.out
    assert captured.err == ""  # no progress bar

    scene = load_scene(tmp_scene_file)
    with np.load(out, allow_pickle=False) as z:
        signals = z["signals"]
        assert signals.shape == (64, 1, 8) and signals.dtype == np.complex64
        assert z["liv"].shape == z["ocds"].shape == z["zero_intensity"].shape == (64, 1)
        assert z["system_names"].tolist() == ["840nm"]
        np.testing.assert_allclose(z["frame_times_s"], [0.2048 * i for i in range(8)], rtol=1e-12)
        assert int(z["trials"]) == 64 and int(z["seed"]) == 3
        assert scene_from_dict(json.loads(str(z["scene_json"]))) == scene
        assert set(json.loads(str(z["plan_json"]))) >= {"stages", "systems", "populations"}
        # the stored metrics are those of the stored signals
        metrics = compute_metrics(torch.from_numpy(signals), scene.protocol.times_s, scene.analysis)
        np.testing.assert_array_equal(z["liv"], metrics["liv"].numpy())
        np.testing.assert_array_equal(z["ocds"], metrics["ocds"].numpy())
        assert np.isfinite(z["liv"][~z["zero_intensity"]]).all()
    first = out.read_bytes()

    # an existing file is kept unless --force is given
    code, message = _run(argv)
    assert code != 0
    assert out.read_bytes() == first
    assert "--force" in capsys.readouterr().err + message

    assert main(argv + ["--force"]) == 0
    with np.load(out, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["signals"], signals)  # same seed, same signals


def test_simulate_float64(tmp_scene_file, tmp_path, capsys):
    out = tmp_path / "y.npz"
    assert (
        main(
            [
                "simulate",
                str(tmp_scene_file),
                "--trials",
                "64",
                "--dtype",
                "float64",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    capsys.readouterr()
    with np.load(out, allow_pickle=False) as z:
        assert z["signals"].dtype == np.complex128 and z["signals"].shape == (64, 1, 8)
        assert z["liv"].dtype == np.float64


def test_simulate_json_summary(tmp_scene_file, capsys):
    assert main(["simulate", str(tmp_scene_file), "--trials", "64", "--json", "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out)
    row = summary["840nm"]
    assert row["liv"]["n"] + row["zero_intensity_trials"] == 64
    assert np.isfinite(row["liv"]["mean"]) and np.isfinite(row["ocds"]["mean"])


def test_simulate_out_needs_npz_suffix(tmp_scene_file, tmp_path, capsys):
    out = tmp_path / "x.txt"
    code, message = _run(["simulate", str(tmp_scene_file), "--trials", "64", "--out", str(out), "--no-progress"])
    assert code == 2 and ".npz" in capsys.readouterr().err + message
    assert not out.exists()


# ----------------------------------------------------------------------------------------------------------
# errors: exit code 2 and a message on stderr
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["plan", "simulate"])
def test_unknown_key_exits_2_naming_the_key(tmp_scene_file, tmp_path, capsys, command):
    tmp_scene_file.write_text(tmp_scene_file.read_text().replace("n_frames = 8", "n_frames = 8\nn_franes = 8"))
    argv = [command, str(tmp_scene_file)] + (["--trials", "64", "--no-progress"] if command == "simulate" else [])
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("error: ")
    assert "protocol" in captured.err and "'n_franes'" in captured.err


@pytest.mark.parametrize("command", ["plan", "simulate"])
def test_missing_scene_file_exits_2(tmp_path, capsys, command):
    missing = tmp_path / "missing.toml"
    assert main([command, str(missing)] + (["--no-progress"] if command == "simulate" else [])) == 2
    err = capsys.readouterr().err
    assert "missing.toml" in err and "not found" in err and "example" in err


@pytest.mark.parametrize("content", [bytes(range(256)) * 4, b"\xff\xfe[system]\n", b'name = "\xe9"\n'])
def test_binary_scene_file_exits_2_naming_the_file(tmp_path, capsys, content):
    path = tmp_path / "scan.toml"
    path.write_bytes(content)
    assert main(["plan", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert "scan.toml" in err and "UTF-8" in err and "codec" not in err


# ----------------------------------------------------------------------------------------------------------
# --device: one check for every command that has it
# ----------------------------------------------------------------------------------------------------------
_NO_CUDA = not torch.cuda.is_available()


@pytest.mark.parametrize(
    "device, text",
    [
        ("bogus", "not a torch device"),
        ("gpu", "not a torch device"),
        ("cuda:x", "not a torch device"),
        pytest.param("cuda", "CUDA", marks=pytest.mark.skipif(not _NO_CUDA, reason="a CUDA device exists")),
        pytest.param("cuda:0", "CUDA", marks=pytest.mark.skipif(not _NO_CUDA, reason="a CUDA device exists")),
        ("cuda:99", "CUDA"),
        ("meta", "meta"),
    ],
)
@pytest.mark.parametrize("command", ["simulate", "render", "maps"])
def test_unusable_device_exits_2_listing_the_devices(tmp_scene_file, tmp_path, capsys, command, device, text):
    out = tmp_path / ("x.npz" if command != "maps" else "m.npz")
    argv = {
        "simulate": ["simulate", str(tmp_scene_file), "--trials", "2", "--no-progress"],
        "render": ["render", "spheroid", "--out", str(out), "--no-progress"],
        "maps": ["maps", str(tmp_path / "seq.npy"), "--out", str(out)],
    }[command]
    assert main(argv + ["--device", device]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith("error: ") and captured.err.count("\n") == 1, captured.err
    err = captured.err
    assert f"--device {device!r}" in err and text in err and "devices here: cpu" in err and "--device cpu" in err, err
    assert not out.exists()


def test_cpu_device_is_accepted(tmp_scene_file, capsys):
    assert main(["simulate", str(tmp_scene_file), "--trials", "2", "--no-progress", "--device", "cpu"]) == 0
    assert main(["simulate", str(tmp_scene_file), "--trials", "2", "--no-progress", "--device", "cpu:0"]) == 0
    capsys.readouterr()


# ----------------------------------------------------------------------------------------------------------
# exit codes: 0 done, 2 bad input or usage (nothing written), 1 any other failure (README, Command line)
# ----------------------------------------------------------------------------------------------------------
def test_bad_output_paths_exit_2_not_1(tmp_scene_file, tmp_path, capsys):
    existing = tmp_path / "old.npz"
    existing.write_bytes(b"keep")
    for argv, text in (
        (["simulate", str(tmp_scene_file), "--out", str(tmp_path / "x.txt")], ".npz"),
        (["simulate", str(tmp_scene_file), "--out", str(existing)], "--force"),
        (["simulate", str(tmp_scene_file), "--out", str(tmp_path / "no" / "x.npz")], "create it"),
        (["bench", "simulate", "--out", str(tmp_path / "b.txt")], ".json"),
        (["bench", "classify", "--out", str(existing)], ".json"),
    ):
        assert main(argv + (["--no-progress"] if argv[0] == "simulate" else [])) == 2, argv  # not SystemExit
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and text in err, err
    assert existing.read_bytes() == b"keep"
    with pytest.raises(SystemExit) as info:  # argparse usage errors: 2 as well
        main(["simulate"])
    assert info.value.code == 2
    capsys.readouterr()


def test_failed_write_exits_1_with_one_line(tmp_scene_file, tmp_path, capsys, monkeypatch):
    import torchdoct.cli.simulate as simulate_command

    def full(path, write):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(simulate_command, "atomic_write", full)
    out = tmp_path / "x.npz"
    assert main(["simulate", str(tmp_scene_file), "--trials", "2", "--no-progress", "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("error: ") and captured.err.count("\n") == 1
    assert "No space left" in captured.err and "x.npz" in captured.err
    assert not out.exists()

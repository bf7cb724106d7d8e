"""Adversarial rows: nonsense input is refused (exit 2, one ``error:`` line naming the file or option,
no traceback, nothing written) or flagged, and outputs are checked before the work.

Each row is a class of input an adversarial pass found accepted or answered with a traceback: input
nested thousands of levels deep (TOML scenes and specs, JSON sidecars, maps metadata), numbers that
overflow (``--resolution axial=1e200``), names that would become file names (newline, BEL, path
separators), PNG options that cannot be drawn, a cache or output that is a regular file, identical
samples given to ``compare``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _refusal import refused

from torchdoct.cli import main

DEEP = "[" * 5000 + "]" * 5000
SPHEROID = Path(__file__).resolve().parents[2] / "torchdoct" / "data" / "phantoms" / "spheroid.toml"


# ----------------------------------------------------------------------------------------------------------
# nesting depth: one check before each parser (RecursionError tracebacks before)
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text",
    ["a = " + DEEP, ".".join(["x"] * 5000) + " = 1", "a = " + "{x = " * 3000 + "1" + "}" * 3000],
    ids=["arrays", "dotted-keys", "inline-tables"],
)
def test_deeply_nested_scene_is_refused(tmp_path, capsys, text):
    path = tmp_path / "deep.toml"
    path.write_text(text + "\n")
    refused(capsys, tmp_path, ["plan", str(path)], "deep.toml", "nested more than")
    refused(capsys, tmp_path, ["simulate", str(path)], "deep.toml", "nested more than")


def test_shallow_brackets_in_strings_and_comments_are_not_nesting(tmp_path, capsys):
    from torchdoct.files import check_nesting

    text = 'a = "' + "[" * 500 + '"\n# ' + "{" * 500 + "\nb = '''" + "[" * 500 + "'''\nc = [[1], [2]]\n"
    check_nesting(text, "x.toml", toml=True)  # no error: the brackets are in strings and comments
    check_nesting(json.dumps({"a": "[" * 500, "b": [[1]]}), "x.json")
    with pytest.raises(ValueError, match="x.json: nested more than 64"):
        check_nesting(json.dumps({"a": "]" * 500, "b": [[[[[[[[1]]]]]]]] * 1}) + DEEP, "x.json")


def test_deeply_nested_sidecar_and_maps_metadata_are_refused(tmp_path, capsys, seq):
    seq.with_suffix(".json").write_text('{"axes": ' + DEEP + "}")
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--out", str(tmp_path / "m.npz"), "--no-progress"],
        "seq.json",
        "nested more than",
    )
    maps = tmp_path / "maps.npz"
    np.savez(
        maps,
        maps=np.zeros((3, 4, 4), np.float32),
        channels=np.array(["a", "b", "c"]),
        meta_json=np.asarray('{"channels": ' + DEEP + "}"),
    )
    refused(capsys, tmp_path, ["compare", f"A={maps}", f"B={maps}"], "maps.npz", "meta_json", "nested more than")


# ----------------------------------------------------------------------------------------------------------
# overflowing numbers
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("res", ["axial=1e200", "lateral=1e300", "axial=14,lateral=1e20", "axial=0", "lateral=-3"])
def test_overflowing_or_absurd_resolution_is_refused(tmp_path, capsys, seq, res):
    refused(
        capsys,
        tmp_path,
        ["maps", str(seq), "--resolution", res, "--out", str(tmp_path / "m.npz"), "--no-progress"],
        "--resolution",
        "µm",
    )


# ----------------------------------------------------------------------------------------------------------
# PNG options: checked before anything is written (the .npz was written, then exit 2, before)
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "extra,names",
    [
        (["--png", "--range", "foo=0,1"], ["--range", "'foo'", "liv, ocds, mean_db"]),
        (["--png", "--range", "liv=10,0"], ["--range liv", "LO < HI"]),
        (["--png", "--range", "liv=nan,1"], ["--range liv", "finite"]),
        (["--png", "--db-range", "nan", "nan"], ["--db-range", "finite"]),
        (["--png", "--db-range", "30", "10"], ["--db-range", "LO < HI"]),
        (["--png", "--png-y", "99"], ["--png-y", "not a volume"]),
        (["--png", "--png-y", "-1"], ["--png-y", ">= 0"]),
        (["--range", "liv=0,10"], ["--range", "--png"]),
        (["--png-y", "0"], ["--png-y", "--png"]),
    ],
)
def test_png_options_are_checked_before_the_work(tmp_path, capsys, seq, extra, names):
    refused(capsys, tmp_path, ["maps", str(seq), "--out", str(tmp_path / "m.npz"), "--no-progress", *extra], *names)


def test_png_y_outside_a_volume_is_refused(tmp_path, capsys):
    rng = np.random.default_rng(1)
    path = tmp_path / "vol.npy"
    np.save(path, (rng.standard_normal((8, 3, 4, 5)) + 1j).astype(np.complex64))  # 8 frames: OCDS delays have 2+ pairs
    path.with_suffix(".json").write_text(
        json.dumps(
            {"axes": "TYZX", "pitch_um": {"z": 2.0, "x": 2.0, "y": 2.0}, "frame_times_s": [0.2 * i for i in range(8)]}
        )
    )
    refused(
        capsys,
        tmp_path,
        ["maps", str(path), "--out", str(tmp_path / "m.npz"), "--png", "--png-y", "3", "--no-progress"],
        "--png-y 3",
        "0..2",
    )


def test_maps_and_pngs_appear_together(tmp_path, capsys, seq, monkeypatch):
    import torchdoct.measured.maps as maps_module

    def broken(*args, **kwargs):
        if kwargs.get("check_only"):
            return real(*args, **kwargs)
        raise OSError(28, "No space left on device")

    real = maps_module.write_pngs
    monkeypatch.setattr(maps_module, "write_pngs", broken)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["maps", str(seq), "--out", str(out / "m.npz"), "--png", "--no-progress"]) == 1
    assert "No space left" in capsys.readouterr().err
    assert list(out.iterdir()) == []  # the .npz was left without its PNGs before
    monkeypatch.undo()
    assert main(["maps", str(seq), "--out", str(out / "m.npz"), "--png", "--no-progress"]) == 0  # no --force
    assert {p.name for p in out.iterdir()} == {
        "m.npz",
        "m_liv_original.png",
        "m_ocds_original.png",
        "m_mean_db_original.png",
    }


# ----------------------------------------------------------------------------------------------------------
# compare: identical samples
# ----------------------------------------------------------------------------------------------------------
def test_identical_samples_report_no_difference_testable(tmp_path, capsys):
    from _maps_data import make_maps

    from torchdoct.measured.io import write_maps

    m = tmp_path / "x.npz"
    write_maps(m, make_maps(np.random.default_rng(0), ["original", "axial=14"]))
    assert main(["compare", f"A={m}", f"B={m}"]) == 0
    out = capsys.readouterr().out
    assert "no difference testable" in out and "inf" not in out and "***" not in out  # `statistic -inf, p = 0 ***`
    # samples that differ keep their test
    m2 = tmp_path / "y.npz"
    write_maps(m2, make_maps(np.random.default_rng(1), ["original", "axial=14"]))
    assert main(["compare", f"A={m}", f"B={m2}"]) == 0
    out = capsys.readouterr().out
    assert "no difference testable" not in out and "paired t-test: original vs axial=14: statistic" in out


# ----------------------------------------------------------------------------------------------------------
# names that become file names
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["a\\nb\\u0007", "../up", "a/b", "..", "a\\\\b"])
def test_a_system_name_that_cannot_be_a_file_name_is_refused(tmp_path, capsys, name):
    text = SPHEROID.read_text(encoding="utf-8")
    system = text[text.index("[[system]]") : text.index("[protocol]")]
    two = system.replace('name = "840nm-high"', f'name = "{name}"') + system.replace("840nm-high", "second")
    path = tmp_path / "ph.toml"
    path.write_text(text.replace(system, two), encoding="utf-8")
    refused(
        capsys,
        tmp_path,
        ["render", str(path), "--grid", "8x8", "--pitch-um", "2", "--out", str(tmp_path / "r.npz"), "--no-progress"],
        "system name",
        "--system",
    )


def test_a_study_figure_name_that_cannot_be_a_file_name_is_refused(tmp_path, capsys):
    from _studies import write_tiny_study

    path = write_tiny_study(tmp_path)
    text = path.read_text(encoding="utf-8")
    assert 'figure = "fig6-wavelength"' in text
    path.write_text(text.replace('figure = "fig6-wavelength"', 'figure = "../fig\\u0007"'), encoding="utf-8")
    refused(capsys, tmp_path, ["study", str(path), "--out", str(tmp_path / "out")], "figure", "'../fig\\x07'")


# ----------------------------------------------------------------------------------------------------------
# outputs and caches that are regular files: refused before the work
# ----------------------------------------------------------------------------------------------------------
def test_cache_or_out_that_is_a_file_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    from _studies import write_tiny_study

    import torchdoct.study.sweep as sweep_module

    def no_work(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(sweep_module, "_execute", no_work)
    study = write_tiny_study(tmp_path)
    a_file = tmp_path / "plain.txt"
    a_file.write_text("x")
    refused(
        capsys,
        tmp_path,
        ["study", str(study), "--out", str(tmp_path / "o"), "--cache", str(a_file)],
        "--cache",
        "plain.txt",
        "is a file",
    )
    refused(capsys, tmp_path, ["study", str(study), "--out", str(a_file)], "--out", "plain.txt", "not a directory")
    scene = tmp_path / "sw.toml"
    from _scenes import DIFFUSION_SWEEP_TOML

    scene.write_text(DIFFUSION_SWEEP_TOML.format(trials=16), encoding="utf-8")
    refused(
        capsys,
        tmp_path,
        ["sweep", str(scene), "--out", str(tmp_path / "o"), "--cache", str(a_file)],
        "--cache",
        "plain.txt",
        "is a file",
    )
    refused(capsys, tmp_path, ["simulate", "example", "--out", str(tmp_path)], "--out")


def test_compare_names_the_mask_that_does_not_fit(tmp_path, capsys):
    from _maps_data import make_maps

    from torchdoct.measured.io import write_maps

    m = tmp_path / "x.npz"
    write_maps(m, make_maps(np.random.default_rng(0), ["original", "axial=14"]))
    mask = tmp_path / "small-mask.npy"
    np.save(mask, np.ones((3, 3), bool))
    refused(
        capsys,
        tmp_path,
        ["compare", f"A={m}", f"B={m}", "--mask", str(mask), "--mask", str(mask), "--out", str(tmp_path / "t.csv")],
        "--mask",
        "small-mask.npy",
    )

"""Adversarial rows of ``doct-train`` and ``doct-classify``: options named as typed, outputs and caches
checked before the work, input nested too deep refused, an output set written whole (and an earlier
run's files of it removed with ``--force``), an interruption leaving the folder as it was."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from _clf_maps import feature_channels, maps_meta, save_maps
from _refusal import refused as _refused

from classifier.cli import classify_main, train_main
from classifier.features import load_spec

SPECS = Path(__file__).resolve().parents[2] / "classifier" / "specs"


def refused(capsys, tmp_path: Path, run, argv: list[str], *names: str, absent: tuple[str, ...] = ()) -> str:
    """Exit 2, one ``error:`` line naming ``names`` (and not ``absent``), no traceback, nothing written."""
    return _refused(capsys, tmp_path, argv, *names, run=run, absent=absent)


@pytest.fixture()
def no_work(monkeypatch):
    """Fail if training or classification starts."""
    import classifier.infer as infer
    import classifier.train as train

    def started(*args, **kwargs):
        raise AssertionError("the work started before the options were checked")

    monkeypatch.setattr(train, "train", started)
    monkeypatch.setattr(infer, "classify_maps", started)


@pytest.fixture()
def maps_file(tmp_path):
    spec = load_spec("single-acquisition")
    rng = np.random.default_rng(0)
    n = spec.n_features
    feats = np.concatenate([rng.uniform(0.0, 12.0, (n // 2, 6, 7)), rng.uniform(0.0, 0.5, (n - n // 2, 6, 7))])
    data = np.concatenate([feats, np.full((1, 6, 7), 20.0)]).astype(np.float32)
    return save_maps(tmp_path / "maps.npz", data, maps_meta(spec, feature_channels(spec)))


# ----------------------------------------------------------------------------------------------------------
# doct-train
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "option,value",
    [
        ("--draws-train", "0"),
        ("--draws-test", "1"),
        ("--max-epochs", "-1"),
        ("--min-probability", "2"),
        ("--seed", "-1"),
        ("--replicates", "0"),
    ],
)
def test_doct_train_names_options_as_typed(tmp_path, capsys, no_work, option, value):
    refused(
        capsys,
        tmp_path,
        train_main,
        ["--out", str(tmp_path / "o"), option, value, "--no-progress"],
        option,
        absent=("TrainConfig",),
    )


def test_doct_train_names_a_recipe_field_that_no_option_sets(tmp_path, capsys, no_work):
    line = refused(
        capsys,
        tmp_path,
        train_main,
        ["--out", str(tmp_path / "o"), "--trials-per-draw", "1"],
        "--trials-per-draw",
        absent=("TrainConfig",),
    )
    assert "the training recipe's max_pool_pixels" in line


def test_doct_train_refuses_a_cache_that_is_a_file_and_a_spec_name_that_is_a_path(tmp_path, capsys, no_work):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    refused(
        capsys,
        tmp_path,
        train_main,
        ["--out", str(tmp_path / "o"), "--cache", str(plain)],
        "--cache",
        "plain.txt",
        "is a file",
    )
    text = (SPECS / "single-acquisition.toml").read_text(encoding="utf-8")
    spec = tmp_path / "spec.toml"
    spec.write_text(text.replace('name = "single-acquisition"', 'name = "../model\\u0007"'), encoding="utf-8")
    refused(
        capsys,
        tmp_path,
        train_main,
        ["--out", str(tmp_path / "o"), "--spec", str(spec)],
        "feature spec name",
        "'../model\\x07'",
    )


@pytest.mark.parametrize(
    "text", ["a = " + "[" * 5000 + "]" * 5000, ".".join(["k"] * 5000) + " = 1"], ids=["arrays", "dotted-keys"]
)
def test_doct_train_refuses_a_deeply_nested_spec(tmp_path, capsys, no_work, text):
    spec = tmp_path / "deep.toml"
    spec.write_text(text + "\n")
    refused(
        capsys,
        tmp_path,
        train_main,
        ["--out", str(tmp_path / "o"), "--spec", str(spec)],
        "deep.toml",
        "nested more than",
    )


# ----------------------------------------------------------------------------------------------------------
# doct-classify
# ----------------------------------------------------------------------------------------------------------
def test_doct_classify_checks_its_outputs_before_the_work(tmp_path, capsys, no_work, maps_file):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    refused(capsys, tmp_path, classify_main, [str(maps_file), "--out", str(plain)], "--out", "is a file")
    out = tmp_path / "out"
    out.mkdir()
    (out / "magnitude.tif").write_bytes(b"an earlier run's")
    refused(capsys, tmp_path, classify_main, [str(maps_file), "--out", str(out)], "magnitude.tif", "--force")


def test_doct_classify_refuses_deeply_nested_maps_metadata(tmp_path, capsys):
    maps = tmp_path / "deep.npz"
    np.savez(
        maps,
        maps=np.zeros((3, 4, 4), np.float32),
        channels=np.array(["a", "b", "c"]),
        meta_json=np.asarray('{"channels": ' + "[" * 5000 + "]" * 5000 + "}"),
    )
    refused(capsys, tmp_path, classify_main, [str(maps), "--out", str(tmp_path / "o")], "deep.npz", "nested more than")


def test_doct_classify_force_leaves_only_this_runs_set(tmp_path, capsys, maps_file):
    out = tmp_path / "out"
    out.mkdir()
    (out / "magnitude.tif").write_bytes(b"of an earlier run with the signature model")
    (out / "notes.txt").write_text("the user's own file")
    assert (
        classify_main([str(maps_file), "--model", "single-acquisition", "--out", str(out), "--force", "--threads", "1"])
        == 0
    )
    assert {p.name for p in out.iterdir()} == {
        "classes.tif",
        "probabilities.tif",
        "legend.json",
        "summary.json",
        "overlay.png",
        "notes.txt",
    }  # no stale magnitude.tif beside them


def test_doct_classify_interrupted_while_writing_leaves_the_folder_as_it_was(tmp_path, capsys, maps_file, monkeypatch):
    import tifffile

    real = tifffile.imwrite
    calls = []

    def imwrite(*args, **kwargs):  # classes.tif is written; SIGTERM arrives during probabilities.tif
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.5)
        return real(*args, **kwargs)

    monkeypatch.setattr(tifffile, "imwrite", imwrite)
    out = tmp_path / "out"
    argv = [str(maps_file), "--model", "single-acquisition", "--out", str(out), "--threads", "1"]
    assert classify_main(argv) == 143
    err = capsys.readouterr().err
    assert err.startswith("interrupted (SIGTERM)") and len(err.strip().splitlines()) == 1
    assert not out.exists()  # not even the folder it created
    monkeypatch.undo()
    assert classify_main(argv) == 0  # the rerun needs no --force
    assert json.loads((out / "summary.json").read_text())["model"] == "single-acquisition.onnx"


def test_doct_train_interrupted_says_what_the_cache_keeps(tmp_path, capsys, monkeypatch):
    import classifier.train as train

    def simulating(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(2)

    monkeypatch.setattr(train, "train", simulating)
    out = tmp_path / "o"
    assert train_main(["--out", str(out), "--quick", "--cache", str(tmp_path / "cache"), "--no-progress"]) == 143
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("interrupted (SIGTERM): kept the data splits simulated so far")
    assert str(tmp_path / "cache") in lines[0] and "rerun the same command" in lines[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "field,value,names",
    [
        ("opset", 99, ("opset 99", "opsets onnxruntime", "(7 to ", "doct-train writes opset 17")),
        ("opset", 1, ("opset 1", "(7 to ")),
        ("ir_version", 99, ("IR version 99", "IR versions up to", "upgrade onnxruntime")),
    ],
)
def test_a_model_of_an_unsupported_opset_or_ir_version_names_the_supported_range(
    tmp_path, capsys, maps_file, field, value, names
):
    onnx = pytest.importorskip("onnx")
    from classifier.runtime import shipped_models

    proto = onnx.load(str(shipped_models()["single-acquisition"]))
    if field == "opset":
        proto.opset_import[0].version = value
    else:
        proto.ir_version = value
    model = tmp_path / "model.onnx"
    onnx.save(proto, str(model))
    line = refused(
        capsys,
        tmp_path,
        classify_main,
        [str(maps_file), "--model", str(model), "--out", str(tmp_path / "o")],
        "model.onnx",
        *names,
        absent=("onnxruntime_src", "ONNXRuntimeError"),
    )
    assert "\n" not in line

"""The quick start reproduces: ``doct-train --quick`` from an empty cache is seed-fixed and deterministic on a
machine (two runs write the same ONNX file byte for byte), and gives the coverage, accuracy and ECE of the
recorded run (``docs/results/quick-single-acquisition.json``, the report ``doct-train --quick --no-cache
--out DIR`` wrote; the documentation renders it) within 2 bootstrap standard errors: another CPU rounds the
training's floating-point sums otherwise, which moves the last digits."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

RECORDED = Path(__file__).resolve().parents[2] / "docs" / "results" / "quick-single-acquisition.json"
KEYS = ("coverage_identifiable", "accuracy_identifiable", "balanced_accuracy_identifiable", "ece")


def _recorded() -> dict:
    return json.loads(RECORDED.read_text(encoding="utf-8"))


def test_the_recorded_quick_run_is_a_quick_run_with_its_standard_errors():
    rec = _recorded()
    assert rec["data"]["draws"] == {"train": 90, "validation": 24, "test": 36}
    assert rec["spec"]["name"] == "single-acquisition" and rec["seed"] == 0
    for key in KEYS:
        assert 0 <= rec["test"]["network"]["1"][key] <= 1 and rec["standard_errors"]["1"][key] > 0, key


@pytest.mark.slow
def test_doct_train_quick_reproduces_the_recorded_run(tmp_path):
    from classifier.cli import train_main

    rec = _recorded()
    assert train_main(["--quick", "--no-cache", "--no-progress", "--out", str(tmp_path / "first")]) == 0
    report = json.loads((tmp_path / "first" / "single-acquisition.json").read_text())
    test, se = report["test"]["network"]["1"], report["standard_errors"]["1"]
    for key in KEYS:
        # the recorded figure within 2 bootstrap SEs (over the 36 test draws) of this machine's run
        assert abs(test[key] - rec["test"]["network"]["1"][key]) <= 2 * se[key], (key, test[key], se[key])
    # deterministic on this machine: a second run from an empty cache writes the same model, byte for byte
    assert train_main(["--quick", "--no-cache", "--no-progress", "--out", str(tmp_path / "second")]) == 0
    assert (tmp_path / "first" / "single-acquisition.onnx").read_bytes() == (
        tmp_path / "second" / "single-acquisition.onnx"
    ).read_bytes()

"""The quick start of ``classifier/README.md`` reproduces: ``doct-train --quick`` from an empty cache is
seed-fixed and deterministic on a machine (two runs write the same ONNX file byte for byte), gives the
coverage, accuracy and ECE the README states within their bootstrap standard errors (another CPU rounds the
training's floating-point sums otherwise, which moves the last digits), and its CPU time stays near the
documented figure."""

from __future__ import annotations

import json
import re
import resource
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "classifier" / "README.md"


def _documented() -> dict[str, float]:
    text = " ".join(README.read_text(encoding="utf-8").split())
    m = re.search(r"identifiable: coverage (\d\.\d+), accuracy (\d\.\d+), balanced (\d\.\d+); ECE (\d\.\d+)", text)
    assert m, "classifier/README.md no longer states the --quick summary line"
    cpu = re.search(r"doct-train --quick --no-cache --out first/`, twice, on 2 cores beside other processes\): "
                    r"(\d+) s of CPU time", text)
    assert cpu, "classifier/README.md no longer states the --quick CPU time"
    return {"coverage_identifiable": float(m.group(1)), "accuracy_identifiable": float(m.group(2)),
            "balanced_accuracy_identifiable": float(m.group(3)), "ece": float(m.group(4)),
            "cpu_s": float(cpu.group(1))}


def test_the_readme_states_the_quick_figures():
    doc = _documented()
    assert 0 < doc["coverage_identifiable"] < 1 and 0 < doc["balanced_accuracy_identifiable"] < 1


@pytest.mark.slow
def test_doct_train_quick_reproduces_the_readme(tmp_path, capsys):
    from classifier.cli import train_main

    doc = _documented()

    def cpu_s() -> float:  # this process and its (finished) worker processes
        return sum(u.ru_utime + u.ru_stime for u in (resource.getrusage(resource.RUSAGE_SELF),
                                                     resource.getrusage(resource.RUSAGE_CHILDREN)))

    before = cpu_s()
    assert train_main(["--quick", "--no-cache", "--no-progress", "--out", str(tmp_path / "first")]) == 0
    cpu = cpu_s() - before
    report = json.loads((tmp_path / "first" / "single-acquisition.json").read_text())
    test, se = report["test"]["network"]["1"], report["standard_errors"]["1"]
    for key in ("coverage_identifiable", "accuracy_identifiable", "balanced_accuracy_identifiable", "ece"):
        # the README's figure within 2 bootstrap SEs (over the 36 test draws) of this machine's run
        assert abs(test[key] - doc[key]) <= 2 * se[key], (key, test[key], doc[key], se[key])
    # deterministic on this machine: a second run from an empty cache writes the same model, byte for byte
    assert train_main(["--quick", "--no-cache", "--no-progress", "--out", str(tmp_path / "second")]) == 0
    assert ((tmp_path / "first" / "single-acquisition.onnx").read_bytes()
            == (tmp_path / "second" / "single-acquisition.onnx").read_bytes())
    # CPU time varies with the machine (not the numbers): within a factor of 2.5 of the documented figure
    assert cpu < 2.5 * doc["cpu_s"], (cpu, doc["cpu_s"])
